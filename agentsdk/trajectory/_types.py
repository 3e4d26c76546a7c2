"""Trajectory value types (points, trajectories), their validation, and value conversion."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal, TypeAlias

import numpy as np
import numpy.typing as npt

from ..errors import InvalidValueError, LimitViolation, UnknownJointError
from ..types import FloatArray, JointInfo

Interpolation = Literal["linear", "spline"]
Values: TypeAlias = Mapping[str, float] | Sequence[float] | npt.NDArray[np.floating]
StartState: TypeAlias = tuple[Values, Values | None, Values | None]
"""``(positions, velocities, accelerations)``; velocities/accelerations may be None (zero)."""

POS_TOL = 1e-6  # rad or m, position limit tolerance of Trajectory.validate
VEL_RTOL = 1e-6  # relative tolerance of the velocity limit check
ACC_RTOL = 1e-6  # relative tolerance of the acceleration limit check
#: |velocity| below which the last point counts as at rest (JTC: float epsilon)
_END_VEL_EPS = float(np.finfo(np.float32).eps)
# longest ``time_from_start`` accepted (s, ~11.6 days): beyond it the polynomial coefficients lose
# their precision (and at ~1e60 s overflow to NaN setpoints)
MAX_TIME_FROM_START = 1e6
# shortest time between two points (and from the start to a first point at a time > 0), s
MIN_SEGMENT_DURATION = 1e-9


# --------------------------------------------------------------------------- value types


def _float_tuple(values: object, what: str) -> tuple[float, ...]:
    if isinstance(values, str | bytes | Mapping):
        raise InvalidValueError(f"{what}: expected a sequence of floats, got {values!r}")
    try:
        seq = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidValueError(f"{what}: expected a sequence of floats, got {values!r}") from exc
    if seq.ndim != 1:
        raise InvalidValueError(f"{what}: expected a flat sequence of floats, got shape {seq.shape}")
    return tuple(seq.tolist())


@dataclass(frozen=True, slots=True, init=False)
class TrajectoryPoint:
    """One point of a trajectory, like ``trajectory_msgs/JointTrajectoryPoint``.

    ``time_from_start`` is in seconds; values are in the trajectory's
    ``joint_names`` order and stored as tuples of floats.
    """

    time_from_start: float
    positions: tuple[float, ...]
    velocities: tuple[float, ...] | None
    accelerations: tuple[float, ...] | None

    def __init__(
        self,
        time_from_start: float,
        positions: Sequence[float] | npt.ArrayLike,
        velocities: Sequence[float] | npt.ArrayLike | None = None,
        accelerations: Sequence[float] | npt.ArrayLike | None = None,
    ) -> None:
        try:
            t = float(time_from_start)
        except (TypeError, ValueError) as exc:
            raise InvalidValueError(f"time_from_start: {time_from_start!r} is not a number") from exc
        object.__setattr__(self, "time_from_start", t)
        object.__setattr__(self, "positions", _float_tuple(positions, "positions"))
        object.__setattr__(self, "velocities", None if velocities is None else _float_tuple(velocities, "velocities"))
        object.__setattr__(
            self, "accelerations", None if accelerations is None else _float_tuple(accelerations, "accelerations")
        )


def _frozen_array(rows: Sequence[Sequence[float]]) -> FloatArray:
    arr = np.array(rows, dtype=np.float64)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, slots=True, init=False)
class Trajectory:
    """A joint trajectory, like ``trajectory_msgs/JointTrajectory``.

    Construction checks the structure (non-empty, unique joint names, lengths,
    finite values, strictly increasing non-negative times, either all or no points
    with velocities/accelerations); :meth:`validate` checks it against a robot's
    joints and limits. ``times``/``positions``/``velocities``/``accelerations``
    are read-only arrays of shape (points,) and (points, joints).
    """

    joint_names: tuple[str, ...]
    points: tuple[TrajectoryPoint, ...]
    times: FloatArray = field(init=False, repr=False, compare=False)
    positions: FloatArray = field(init=False, repr=False, compare=False)
    velocities: FloatArray | None = field(init=False, repr=False, compare=False)
    accelerations: FloatArray | None = field(init=False, repr=False, compare=False)

    def __init__(self, joint_names: Sequence[str], points: Sequence[TrajectoryPoint]) -> None:
        if isinstance(joint_names, str):
            raise InvalidValueError(f"joint_names must be a sequence of names, got the string {joint_names!r}")
        names = tuple(joint_names)
        object.__setattr__(self, "joint_names", names)
        object.__setattr__(self, "points", tuple(points))
        self._check_structure()

    def _check_structure(self) -> None:
        names, points = self.joint_names, self.points
        if not names:
            raise InvalidValueError("trajectory has no joint_names")
        seen: set[str] = set()
        for name in names:
            if not isinstance(name, str) or not name:
                raise InvalidValueError(f"joint names must be non-empty strings, got {name!r}")
            if name in seen:
                raise InvalidValueError(f"duplicate joint name {name!r} in joint_names")
            seen.add(name)
        if not points:
            raise InvalidValueError("trajectory has no points")
        n = len(names)
        has_vel = points[0].velocities is not None
        has_acc = points[0].accelerations is not None
        prev_t = -math.inf
        for k, p in enumerate(points):
            if not isinstance(p, TrajectoryPoint):
                raise InvalidValueError(f"point {k}: expected a TrajectoryPoint, got {type(p).__name__}")
            t = p.time_from_start
            if not math.isfinite(t):
                raise InvalidValueError(f"point {k}: time_from_start {t} is not finite")
            if t < 0.0:
                raise InvalidValueError(f"point {k}: time_from_start {t} s is negative")
            if t > MAX_TIME_FROM_START:
                raise InvalidValueError(
                    f"point {k}: time_from_start {t:g} s is beyond the supported {MAX_TIME_FROM_START:g} s"
                )
            if t <= prev_t:
                raise InvalidValueError(
                    f"point {k}: time_from_start {t} s is not after point {k - 1}'s {prev_t} s "
                    "(times must strictly increase)"
                )
            if t - max(prev_t, 0.0) < MIN_SEGMENT_DURATION and (k > 0 or t > 0.0):
                raise InvalidValueError(
                    f"point {k}: time_from_start {t:g} s is less than {MIN_SEGMENT_DURATION:g} s after "
                    f"{'the start' if k == 0 else f'point {k - 1}'}: a segment too short to interpolate"
                )
            prev_t = t
            if (p.velocities is not None) != has_vel:
                raise InvalidValueError(
                    f"point {k}: {'has' if p.velocities is not None else 'lacks'} velocities but point 0 "
                    f"{'has' if has_vel else 'does not'}; all points or none must have velocities"
                )
            if (p.accelerations is not None) != has_acc:
                raise InvalidValueError(
                    f"point {k}: {'has' if p.accelerations is not None else 'lacks'} accelerations but point 0 "
                    f"{'has' if has_acc else 'does not'}; all points or none must have accelerations"
                )
            if p.accelerations is not None and p.velocities is None:
                raise InvalidValueError(f"point {k}: accelerations given without velocities")
            for what, vals in (
                ("positions", p.positions),
                ("velocities", p.velocities),
                ("accelerations", p.accelerations),
            ):
                if vals is None:
                    continue
                if len(vals) != n:
                    raise InvalidValueError(f"point {k}: {len(vals)} {what} for {n} joints {list(names)}")
                for j, v in enumerate(vals):
                    if not math.isfinite(v):
                        raise InvalidValueError(f"point {k}: {what[:-1]} of joint {names[j]!r} is {v}")
        times = np.array([p.time_from_start for p in points], dtype=np.float64)
        times.setflags(write=False)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "positions", _frozen_array([p.positions for p in points]))
        object.__setattr__(
            self,
            "velocities",
            _frozen_array([p.velocities for p in points]) if has_vel else None,  # type: ignore[misc]
        )
        object.__setattr__(
            self,
            "accelerations",
            _frozen_array([p.accelerations for p in points]) if has_acc else None,  # type: ignore[misc]
        )

    @property
    def duration(self) -> float:
        """``time_from_start`` of the last point (s)."""
        return self.points[-1].time_from_start

    def validate(self, joints: Sequence[JointInfo], *, allow_nonzero_velocity_at_end: bool = False) -> None:
        """Check joint names against ``joints`` and every point against their limits, like JTC.

        Raises :class:`UnknownJointError` for a joint not in ``joints``; :class:`LimitViolation`
        for a position outside ``[lower, upper]``, a velocity above ``max_velocity`` or an
        acceleration above ``max_acceleration``; :class:`InvalidValueError` for a last point with a
        non-zero velocity unless ``allow_nonzero_velocity_at_end`` (JTC's
        ``allow_nonzero_velocity_at_trajectory_end``). The motion *between* the points is checked
        by :func:`check_motion_limits` on a :class:`TrajectorySampler`.
        """
        by_name = {j.name: j for j in joints}
        infos: list[JointInfo] = []
        for name in self.joint_names:
            info = by_name.get(name)
            if info is None:
                raise UnknownJointError(f"unknown joint {name!r}; known joints: {sorted(by_name)}")
            infos.append(info)
        lower = np.array([j.lower for j in infos])
        upper = np.array([j.upper for j in infos])
        vmax = np.array([j.max_velocity for j in infos])
        amax = np.array([j.max_acceleration for j in infos])
        bad = ~((self.positions >= lower - POS_TOL) & (self.positions <= upper + POS_TOL))
        if bad.any():
            k, j = (int(i) for i in np.argwhere(bad)[0])
            val = self.positions[k, j]
            raise LimitViolation(
                f"point {k}: joint {self.joint_names[j]!r} position {val:.6g} is outside its limits "
                f"[{lower[j]:.6g}, {upper[j]:.6g}]"
            )
        if self.velocities is not None:
            bad = ~(np.abs(self.velocities) <= vmax * (1.0 + VEL_RTOL))
            if bad.any():
                k, j = (int(i) for i in np.argwhere(bad)[0])
                val = self.velocities[k, j]
                raise LimitViolation(
                    f"point {k}: joint {self.joint_names[j]!r} velocity {val:.6g} exceeds max_velocity {vmax[j]:.6g}"
                )
            if not allow_nonzero_velocity_at_end:
                moving = np.abs(self.velocities[-1]) > _END_VEL_EPS
                if moving.any():
                    j = int(np.argmax(moving))
                    raise InvalidValueError(
                        f"point {len(self.points) - 1} (the last): joint {self.joint_names[j]!r} velocity "
                        f"{self.velocities[-1, j]:.6g} is not zero; a trajectory ends at rest unless "
                        "allow_nonzero_velocity_at_end=True (JTC's allow_nonzero_velocity_at_trajectory_end)"
                    )
        if self.accelerations is not None:
            bad = ~(np.abs(self.accelerations) <= amax * (1.0 + ACC_RTOL))
            if bad.any():
                k, j = (int(i) for i in np.argwhere(bad)[0])
                val = self.accelerations[k, j]
                raise LimitViolation(
                    f"point {k}: joint {self.joint_names[j]!r} acceleration {val:.6g} exceeds max_acceleration "
                    f"{amax[j]:.6g}"
                )

    def time_scaled(self, factor: float) -> Trajectory:
        """This trajectory ``factor`` times slower: times x factor, velocities / factor, accelerations / factor^2.

        The path (every point's positions) is unchanged; ``factor`` must be finite and > 0.
        """
        if not (math.isfinite(factor) and factor > 0.0):
            raise InvalidValueError(f"time scale factor must be a positive number, got {factor!r}")
        k2 = factor * factor
        return Trajectory(
            self.joint_names,
            [
                TrajectoryPoint(
                    p.time_from_start * factor,
                    p.positions,
                    None if p.velocities is None else [v / factor for v in p.velocities],
                    None if p.accelerations is None else [a / k2 for a in p.accelerations],
                )
                for p in self.points
            ],
        )

    def shifted(self, offsets: Sequence[float] | npt.ArrayLike) -> Trajectory:
        """The same motion with every position of joint ``j`` moved by ``offsets[j]`` (e.g. 2*pi turns)."""
        off = np.asarray(offsets, dtype=np.float64)
        if off.shape != (len(self.joint_names),) or not np.isfinite(off).all():
            raise InvalidValueError(f"offsets: expected {len(self.joint_names)} finite values, got {offsets!r}")
        if not off.any():
            return self
        return Trajectory(
            self.joint_names,
            [
                TrajectoryPoint(p.time_from_start, np.asarray(p.positions) + off, p.velocities, p.accelerations)
                for p in self.points
            ],
        )

    def after(self, elapsed: float) -> Trajectory:
        """What is left ``elapsed`` seconds after the start: the points after it, times relative to then.

        Points at or before ``elapsed`` are dropped (a scheduled start in the past skips what
        has elapsed, as JTC does); raises :class:`InvalidValueError` if none is left.
        """
        if elapsed <= 0.0:
            return self
        keep = [p for p in self.points if p.time_from_start > elapsed]
        if not keep:
            raise InvalidValueError(
                f"the trajectory ended {elapsed - self.duration:.6g} s ago (its start time is {elapsed:.6g} s in "
                f"the past and it lasts {self.duration:.6g} s)"
            )
        return Trajectory(
            self.joint_names,
            [TrajectoryPoint(p.time_from_start - elapsed, p.positions, p.velocities, p.accelerations) for p in keep],
        )


# --------------------------------------------------------------------------- interpolation



def vector(values: Values | None, names: Sequence[str], what: str, default: float | None = None) -> FloatArray:
    """``values`` (mapping by name, or sequence in ``names`` order) as a float array."""
    n = len(names)
    if values is None:
        if default is None:
            raise InvalidValueError(f"{what} is required")
        return np.full(n, default)
    if isinstance(values, Mapping):
        missing = [nm for nm in names if nm not in values]
        extra = [k for k in values if k not in names]
        if extra:
            raise UnknownJointError(f"{what}: unknown joint(s) {extra}; expected {list(names)}")
        if missing:
            raise InvalidValueError(f"{what}: missing joint(s) {missing}")
        arr = np.array([float(values[nm]) for nm in names])
    else:
        arr = np.array(_float_tuple(values, what))
        if arr.shape != (n,):
            raise InvalidValueError(f"{what}: {arr.size} values for {n} joints {list(names)}")
    bad = ~np.isfinite(arr)
    if bad.any():
        j = int(np.argmax(bad))
        raise InvalidValueError(f"{what}: value of joint {names[j]!r} is {arr[j]}")
    return arr
