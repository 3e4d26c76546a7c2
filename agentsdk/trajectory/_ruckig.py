"""The ruckig wrapper: joint limits for ruckig, one reusable solver, profiles turned into trajectory points."""

from __future__ import annotations

import contextlib
import contextvars
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from ruckig import ControlInterface, InputParameter, Result, Ruckig, RuckigError, Synchronization
from ruckig import Trajectory as _RuckigTrajectory

from ..errors import CommandRejected, ConfigurationError, InvalidValueError, LimitViolation
from ..types import FloatArray, JointInfo
from ._sampler import quintic
from ._types import Trajectory, TrajectoryPoint

#: the ruckig problems solved while :func:`recording_solves` is active (benchmarks replay them raw)
_solve_log: contextvars.ContextVar[list[tuple[list[float], ...]] | None] = contextvars.ContextVar(
    "agentsdk_ruckig_solve_log", default=None
)


@contextlib.contextmanager
def recording_solves() -> Iterator[list[tuple[list[float], ...]]]:
    """Collect the point-to-point ruckig problems solved inside the block.

    Yields a list that fills with ``(q0, v0, a0, q1, v1)`` per solve; ``bench/planning.py``
    replays them on raw ruckig to measure the planner's own overhead against the same problems.
    """
    log: list[tuple[list[float], ...]] = []
    token = _solve_log.set(log)
    try:
        yield log
    finally:
        _solve_log.reset(token)


#: the longest profile ruckig computes (its ``ErrorTrajectoryDuration``, result -101, beyond 7.6e3 s)
MAX_PROFILE_DURATION = 7.6e3

PLAN_POS_TOL = 1e-7  # rad or m, ruckig reaches its targets within ~1e-8

MIN_GAP = 1e-6  # s, breakpoints closer than this are merged

#: relative margin inside max_velocity and max_acceleration that the planners give ruckig, so the float
#: rounding of the breakpoints and of the ~1e-8 end correction never makes a plan fail its own check
#: (``move_to`` once planned 8.00002 rad/s^2 against a limit of 8). See :func:`joint_limits`.
PLAN_LIMIT_MARGIN = 1e-5
#: the merge margin of :func:`joint_limits` is at most this fraction of a limit
_MAX_MERGE_MARGIN = 0.01
_INF_JERK_RAMP = 0.002  # s, acceleration ramp time used for joints with max_jerk = inf


@dataclass(frozen=True, slots=True)
class JointLimits:
    """Per-joint position limits and the (scaled) velocity, acceleration and jerk limits ruckig plans with."""

    names: tuple[str, ...]
    lower: FloatArray
    upper: FloatArray
    vmax: FloatArray
    amax: FloatArray
    jmax: FloatArray


def joint_limits(
    infos: Sequence[JointInfo],
    velocity_scale: float,
    acceleration_scale: float,
    jerk_scale: float,
    *,
    margin: bool = True,
) -> JointLimits:
    """The limits of ``infos`` scaled for planning; bad scales or missing limits raise a specific error.

    The velocity and acceleration limits given to ruckig sit inside the joints' limits, so that a plan
    never fails the check of its executed motion (:func:`check_motion_limits`): by
    :data:`PLAN_LIMIT_MARGIN` (relative, float rounding), and by what merging two profile breakpoints
    closer than :data:`MIN_GAP` can add between the kept ones (the acceleration changes by up to
    ``max_jerk * MIN_GAP`` there, the velocity by ``max_acceleration * MIN_GAP``), twice that, at most
    1 % of the limit. The jerk limit is not shrunk (a smaller jerk would make a moving start overshoot
    its velocity more). A minimum-time move is slower by about the margin (1e-5, 1e-3 with no jerk limit).
    ``margin=False`` plans at the limits themselves (a stop: as fast as the limits allow, never checked).
    """
    for what, s in (
        ("velocity_scale", velocity_scale),
        ("acceleration_scale", acceleration_scale),
        ("jerk_scale", jerk_scale),
    ):
        if not (0.0 < s <= 1.0):
            raise InvalidValueError(f"{what} must be in (0, 1], got {s}")
    for j in infos:
        for what, lim, allow_inf in (
            ("max_velocity", j.max_velocity, False),
            ("max_acceleration", j.max_acceleration, False),
            ("max_jerk", j.max_jerk, True),
        ):
            if not (lim > 0.0 and (allow_inf or math.isfinite(lim))):
                raise ConfigurationError(
                    f"joint {j.name!r}: {what} is {lim}; time parameterization needs a positive"
                    f"{'' if allow_inf else ', finite'} limit (set joint_limits in robot.yaml)"
                )
    inside = 1.0 - PLAN_LIMIT_MARGIN if margin else 1.0
    amax = np.array([j.max_acceleration for j in infos]) * (acceleration_scale * inside)
    vmax = np.array([j.max_velocity for j in infos]) * (velocity_scale * inside)
    jmax = np.array([j.max_jerk for j in infos]) * jerk_scale
    # no jerk limit: ramp the acceleration over _INF_JERK_RAMP instead of stepping it, so that the
    # planned trajectories stay C2 (what the quintic interpolation reproduces exactly)
    jmax = np.where(np.isfinite(jmax), jmax, amax / _INF_JERK_RAMP)
    if margin:
        vmax = vmax - np.minimum(2.0 * amax * MIN_GAP, _MAX_MERGE_MARGIN * vmax)
        amax = amax - np.minimum(2.0 * jmax * MIN_GAP, _MAX_MERGE_MARGIN * amax)
    return JointLimits(
        names=tuple(j.name for j in infos),
        lower=np.array([j.lower for j in infos]),
        upper=np.array([j.upper for j in infos]),
        vmax=vmax,
        amax=amax,
        jmax=jmax,
    )


def check_positions(q: FloatArray, lim: JointLimits, what: str, tol: float = 0.0) -> None:
    """Raise :class:`LimitViolation` naming the first joint of ``q`` outside its position limits (+ ``tol``)."""
    bad = (q < lim.lower - tol) | (q > lim.upper + tol)
    if bad.any():
        j = int(np.argmax(bad))
        raise LimitViolation(
            f"{what}: joint {lim.names[j]!r} position {q[j]:.6g} is outside its limits "
            f"[{lim.lower[j]:.6g}, {lim.upper[j]:.6g}]"
        )


class RuckigSolver:
    """One reusable ruckig problem (position or velocity interface) over a set of joints."""

    def __init__(self, lim: JointLimits, *, velocity_interface: bool = False, synchronize: bool = True) -> None:
        n = len(lim.names)
        self.lim = lim
        self.n = n
        self.otg = Ruckig(n)
        self.traj = _RuckigTrajectory(n)
        inp = self.inp = InputParameter(n)
        inp.max_velocity = lim.vmax.tolist()
        inp.max_acceleration = lim.amax.tolist()
        inp.max_jerk = lim.jmax.tolist()
        if velocity_interface:
            inp.control_interface = ControlInterface.Velocity
        if not synchronize:
            inp.synchronization = Synchronization.No

    def solve(
        self,
        q0: FloatArray,
        v0: FloatArray,
        a0: FloatArray,
        q1: FloatArray | None,
        v1: FloatArray,
        min_duration: float | None = None,
    ) -> _RuckigTrajectory:
        log = _solve_log.get()
        if log is not None and q1 is not None and min_duration is None:
            log.append((q0.tolist(), v0.tolist(), a0.tolist(), q1.tolist(), v1.tolist()))
        inp = self.inp
        inp.current_position = q0.tolist()
        inp.current_velocity = v0.tolist()
        inp.current_acceleration = a0.tolist()
        if q1 is not None:
            inp.target_position = q1.tolist()
        inp.target_velocity = v1.tolist()
        inp.target_acceleration = [0.0] * self.n
        inp.minimum_duration = min_duration
        try:
            res = self.otg.calculate(inp, self.traj)
        except (RuntimeError, RuckigError) as exc:  # ruckig raises for invalid input
            raise CommandRejected(f"trajectory generation failed: {exc}") from exc
        except ValueError as exc:  # a result code the Python enum lacks (-101: longer than ruckig can time)
            if "-101" in str(exc):
                raise CommandRejected(
                    f"trajectory generation failed: the move would last longer than {MAX_PROFILE_DURATION:g} s, "
                    "the longest profile ruckig times"
                ) from None
            raise CommandRejected(f"trajectory generation failed: ruckig returned {exc}") from None
        if res != Result.Working:
            raise CommandRejected(f"trajectory generation failed: ruckig returned {res.name}")
        return self.traj

    def within_position_limits(self, traj: _RuckigTrajectory) -> int:
        """-1 if the profile stays within the position limits, else the first offending joint."""
        lo, hi = position_extrema(traj)
        bad = (lo < self.lim.lower - PLAN_POS_TOL) | (hi > self.lim.upper + PLAN_POS_TOL)
        return int(np.argmax(bad)) if bad.any() else -1


def position_extrema(traj: _RuckigTrajectory) -> tuple[FloatArray, FloatArray]:
    """Per-joint (min, max) position of a single-section ruckig trajectory.

    Computed from the constant-jerk phases (ruckig 0.19's ``position_extrema`` misses extrema
    inside constant-acceleration phases, e.g. a joint reversing while braking at full deceleration).
    """
    duration = traj.duration
    los: list[float] = []
    his: list[float] = []
    for prof in traj.profiles[0]:
        t, p, v, a = prof.t, prof.p, prof.v, prof.a
        lo, hi = min(p), max(p)  # phase boundaries, including the end
        # an extremum inside a phase needs a velocity root in it: a sign change of v, or of a (v's vertex)
        phases = [
            (t[k], p[k], v[k], a[k], k)
            for k in range(len(t))
            if t[k] > 0.0 and (v[k] * v[k + 1] < 0.0 or a[k] * a[k + 1] < 0.0)
        ]
        if phases:
            jerk = prof.j
            phases = [(dt, p0, v0, a0, jerk[k]) for dt, p0, v0, a0, k in phases]
        if sum(t) < duration - 1e-12:  # rare: a brake pre-phase or a final acceleration phase
            for part in (prof.brake, prof.accel):
                if part.duration > 0.0:
                    for ph in zip(part.t, part.p, part.v, part.a, part.j, strict=True):
                        if ph[0] > 0.0:
                            phases.append(ph)
                            lo, hi = min(lo, ph[1]), max(hi, ph[1])
        for dt, p0, v0, a0, j in phases:
            taus = [dt]
            if j != 0.0:
                disc = a0 * a0 - 2.0 * j * v0
                if disc >= 0.0:
                    taus += [(-a0 + math.sqrt(disc)) / j, (-a0 - math.sqrt(disc)) / j]
            elif a0 != 0.0:
                taus.append(-v0 / a0)
            for tau in taus:
                if 0.0 < tau <= dt:
                    x = p0 + (v0 + (0.5 * a0 + j / 6.0 * tau) * tau) * tau
                    lo, hi = min(lo, x), max(hi, x)
        los.append(lo)
        his.append(hi)
    return np.array(los), np.array(his)


def _breakpoints(traj: _RuckigTrajectory) -> list[float]:
    """Sorted phase boundaries (union over joints) of a single-section ruckig trajectory, without 0."""
    duration = traj.duration
    ts: list[float] = []
    for prof in traj.profiles[0]:
        off = 0.0
        for part in (prof.brake.t, prof.t, prof.accel.t):
            for dt in part:
                off += dt
                ts.append(off)
    ts.append(duration)
    ts.sort()
    out: list[float] = []
    last = 0.0
    for t in ts:
        if t - last >= MIN_GAP and t <= duration - MIN_GAP:
            out.append(t)
            last = t
    out.append(duration)
    return out


def append_profile(
    rows: list[tuple[float, FloatArray, FloatArray, FloatArray]],
    traj: _RuckigTrajectory,
    t_offset: float,
    end_q: FloatArray | None,
    end_v: FloatArray,
) -> None:
    """Append the breakpoints of ``traj`` (after its start) as (t, q, v, a) rows, ending exactly at
    ``(end_q, end_v, 0)`` (``end_q=None``: wherever the profile ends).

    ruckig reaches its target within ~1e-8 (its numerical precision). Forcing the exact target into
    only the last point would turn that error into an acceleration spike over the last, possibly very
    short, interval; instead the error is spread over the whole profile by adding the quintic that goes
    from 0 to the end error. Between breakpoints each joint then moves on cubic + quintic, which the
    quintic interpolation of :class:`TrajectorySampler` reproduces exactly.
    """
    bps = np.array(_breakpoints(traj))
    duration = float(bps[-1])
    states = np.array([traj.at_time(float(t)) for t in bps])  # (k, 3, joints)
    q_end, v_end, a_end = states[-1]
    target_q = q_end if end_q is None else end_q
    z = np.zeros((1, len(q_end)))
    c = quintic(z, z, z, (target_q - q_end)[None, :], (end_v - v_end)[None, :], -a_end[None, :], np.array([duration]))[
        0
    ]
    t = bps[:, None]
    states[:, 0] += ((c[5] * t + c[4]) * t + c[3]) * t**3
    states[:, 1] += ((5.0 * c[5] * t + 4.0 * c[4]) * t + 3.0 * c[3]) * t**2
    states[:, 2] += ((20.0 * c[5] * t + 12.0 * c[4]) * t + 6.0 * c[3]) * t
    states[-1] = (target_q, end_v, np.zeros_like(end_v))  # exactly, without rounding
    for k, tk in enumerate(bps.tolist()):
        rows.append((t_offset + tk, states[k, 0], states[k, 1], states[k, 2]))


def to_trajectory(names: Sequence[str], rows: list[tuple[float, FloatArray, FloatArray, FloatArray]]) -> Trajectory:
    """A :class:`Trajectory` from ``(time, positions, velocities, accelerations)`` rows."""
    return Trajectory(names, [TrajectoryPoint(t, q, v, a) for t, q, v, a in rows])
