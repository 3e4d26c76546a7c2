"""The joint limiting rule, in one place: position bounds, a position step per control period,
velocity and effort limits.

Two writers put position references in the setpoint and both must limit them the same way: the
safety layer's per-tick filter (every position-mode joint) and the trajectory executor (a planned
motion checks its own step first, so that the filter never clips a motion silently). Both call
the methods of one :class:`StepLimiter`; neither re-implements its arithmetic. The limiter is a
value: its limits are fixed when it is made; it keeps only preallocated scratch for the tick path
(no arrays allocated per tick).

This module sits below the safety layer and the motion executor and imports neither.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from .errors import ConfigurationError, LimitViolation
from .types import CommandMode, JointInfo

__all__ = ["STEP_RTOL", "PositionBounds", "StepGuard", "StepLimiter"]

#: relative slack of the per-tick step check (float noise of trajectories planned at the limits)
STEP_RTOL = 1e-5


class PositionBounds:
    """Joint position bounds the safety layer enforces: the URDF limits minus ``position_margin``."""

    __slots__ = ("hi", "lo", "names")

    def __init__(self, joints: Sequence[JointInfo], margin: float) -> None:
        lower = np.array([j.lower for j in joints])
        upper = np.array([j.upper for j in joints])
        self.names = tuple(j.name for j in joints)
        self.lo = np.where(np.isfinite(lower), lower + margin, -np.inf)
        self.hi = np.where(np.isfinite(upper), upper - margin, np.inf)
        bad = self.lo > self.hi
        if bad.any():
            name = self.names[int(np.argmax(bad))]
            raise ConfigurationError(
                f"safety position_margin {margin:g} is larger than half of joint {name!r}'s range"
            )
        self.lo.flags.writeable = False
        self.hi.flags.writeable = False

    def check(self, positions: np.ndarray, idx: np.ndarray) -> None:
        """Raise :class:`LimitViolation` if a position of joints ``idx`` is outside the bounds."""
        bad = (positions < self.lo[idx]) | (positions > self.hi[idx])
        if bad.any():
            k = int(np.argmax(bad))
            j = int(idx[k])
            raise LimitViolation(
                f"trajectory position {positions[k]:.4g} for joint {self.names[j]!r} is outside "
                f"[{self.lo[j]:.4g}, {self.hi[j]:.4g}]"
            )


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.flags.writeable = False
    return a


class StepLimiter:
    """Position bounds ``[lo, hi]``, a step window ``origin ± step`` per control period, and the
    velocity and effort limits ``±vmax``, ``±emax`` of a set of joints.

    Every method writes into an ``out`` array the caller owns (or the array it limits in
    place) and allocates nothing. :meth:`select` gives the limiter of a subset of the joints
    (the trajectory executor limits only the joints of its motion).
    """

    __slots__ = (
        "_whi",
        "_wlo",
        "emax",
        "ff_max",
        "ff_min",
        "hi",
        "lo",
        "rows_max",
        "rows_min",
        "step",
        "step_tol",
        "vmax",
    )

    def __init__(
        self, lo: np.ndarray, hi: np.ndarray, step: np.ndarray | None, vmax: np.ndarray, emax: np.ndarray
    ) -> None:
        self.lo, self.hi = _readonly(lo), _readonly(hi)
        #: the largest position change per control period (None: no step limit)
        self.step: np.ndarray | None = None
        #: a step beyond this is more than float noise (a plan exactly at the limit)
        self.step_tol: np.ndarray | None = None
        if step is not None:
            self.step = _readonly(step)
            self.step_tol = _readonly(np.asarray(self.step * (1.0 + STEP_RTOL) + 1e-12))
        self.vmax = _readonly(np.where(np.isnan(vmax), np.inf, vmax))
        self.emax = _readonly(np.where(np.isnan(emax), np.inf, emax))
        #: the limits of the setpoint's velocity and effort rows (``Setpoint.block[1:3]``)
        self.ff_min = _readonly(np.vstack([-self.vmax, -self.emax]))
        self.ff_max = _readonly(np.vstack([self.vmax, self.emax]))
        #: ... and with the position row (``Setpoint.block[0:3]``)
        self.rows_min = _readonly(np.vstack([self.lo, -self.vmax, -self.emax]))
        self.rows_max = _readonly(np.vstack([self.hi, self.vmax, self.emax]))
        n = len(self.lo)
        self._wlo = np.zeros(n)
        self._whi = np.zeros(n)

    @classmethod
    def for_joints(
        cls, joints: Sequence[JointInfo], bounds: PositionBounds, step: float | Literal["auto"] | None, period: float
    ) -> StepLimiter:
        """The limiter of a robot's joints: ``step`` ``"auto"`` is ``max_velocity * period``."""
        n = len(joints)
        steps: np.ndarray | None
        if step == "auto":
            steps = np.array([j.max_velocity for j in joints]) * period
        elif step is None:
            steps = None
        else:
            steps = np.full(n, float(step))
        return cls(
            bounds.lo, bounds.hi, steps,
            np.array([j.max_velocity for j in joints], dtype=np.float64),
            np.array([j.max_effort for j in joints], dtype=np.float64),
        )

    def select(self, idx: np.ndarray) -> StepLimiter:
        """The limiter of joints ``idx`` (the same limits, its own scratch)."""
        return StepLimiter(
            self.lo[idx], self.hi[idx], None if self.step is None else self.step[idx], self.vmax[idx], self.emax[idx]
        )

    # ------------------------------------------------------------ positions
    def clamp_bounds(self, q: np.ndarray, out: np.ndarray) -> np.ndarray:
        """``out = clip(q, lo, hi)``; returns ``out``."""
        np.maximum(q, self.lo, out=out)
        np.minimum(out, self.hi, out=out)
        return out

    def clamp_step(self, q: np.ndarray, origin: np.ndarray, out: np.ndarray) -> np.ndarray:
        """``out = clip(q, origin - step, origin + step)`` (no step limit: ``out = q``); returns ``out``."""
        step = self.step
        if step is None:
            if out is not q:
                out[...] = q
            return out
        lo, hi = self._wlo, self._whi
        np.subtract(origin, step, out=lo)
        np.add(origin, step, out=hi)
        np.maximum(q, lo, out=out)
        np.minimum(out, hi, out=out)
        return out

    def clamp_position(self, q: np.ndarray, origin: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Bounds, then the step window around ``origin``: the position a joint may be given this period."""
        self.clamp_bounds(q, out)
        return self.clamp_step(out, origin, out)

    # ------------------------------------------------------------ setpoint rows
    def clamp_rows(self, rows: np.ndarray) -> None:
        """Clip a setpoint's position, velocity and effort rows (``block[0:3]``) in place."""
        np.maximum(rows, self.rows_min, out=rows)
        np.minimum(rows, self.rows_max, out=rows)

    def clamp_feedforward(self, rows: np.ndarray) -> None:
        """Clip a setpoint's velocity and effort rows (``block[1:3]``) in place."""
        np.maximum(rows, self.ff_min, out=rows)
        np.minimum(rows, self.ff_max, out=rows)

    # ------------------------------------------------------------ commands
    def command_range(self, mode: CommandMode, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, str, str]:
        """``(lo, hi, quantity, unit)`` of a direct ``mode`` command to joints ``idx``."""
        if mode == "position":
            return self.lo[idx], self.hi[idx], "position", "rad"
        if mode == "velocity":
            hi = self.vmax[idx]
            return -hi, hi, "velocity", "rad/s"
        hi = self.emax[idx]
        return -hi, hi, "effort", "N·m"

    def clamp_command(self, mode: CommandMode, idx: np.ndarray, values: np.ndarray) -> np.ndarray:
        """A new array: ``values`` of joints ``idx`` clipped into the range of ``mode``."""
        lo, hi, _, _ = self.command_range(mode, idx)
        out: np.ndarray = np.minimum(np.maximum(values, lo), hi)
        return out

    def step_exceeded(self, values: np.ndarray, origin: np.ndarray, idx: np.ndarray) -> np.ndarray | None:
        """Which of ``values`` (joints ``idx``) step further than ``step`` from ``origin``; None if none do."""
        if self.step is None:
            return None
        jump: np.ndarray = np.abs(values - origin[idx]) > self.step[idx] + 1e-12
        return jump if jump.any() else None


@dataclass(frozen=True, eq=False)
class StepGuard:
    """What a writer of planned references needs to stay inside the safety layer's limiter.

    ``limiter``: the rule; ``origin``: where each joint's step is measured from (the reference
    the filter let through last tick; a live read-only array); ``rebase(idx, q)``: tell the
    limiter that the reference of joints ``idx`` was reset to their measured ``q`` (an abort);
    ``report(kind, detail, joint)``: record a safety event. Made by the safety layer, given to
    the motion manager, so neither imports the other.
    """

    limiter: StepLimiter
    origin: np.ndarray
    rebase: Callable[[np.ndarray, np.ndarray], None]
    report: Callable[[str, str, str | None], Any]
