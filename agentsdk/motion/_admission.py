"""Admission of a trajectory: validation against the joints' limits, timing, and its start state."""

from __future__ import annotations

import math

import numpy as np

from ..errors import LimitViolation
from ..limits import STEP_RTOL as _STEP_RTOL
from ..limits import PositionBounds, StepLimiter
from ..loop import ControlLoop
from ..trajectory import (
    MAX_TIME_FROM_START,
    Trajectory,
    TrajectorySampler,
    check_motion_limits,
    time_scale_for_limits,
)
from ._envelope import envelope
from ._ownership import _Ownership
from ._records import _Exec, _MotionTable
from ._types import _MAX_STRETCH_ITERATIONS, MotionPhase, _turns_to


class _Admission:
    """Checks and prepares a trajectory before it may run (the JTC's validation, on the whole motion)."""

    def __init__(self, loop: ControlLoop, table: _MotionTable, ownership: _Ownership, bounds: PositionBounds,
                 limiter: StepLimiter) -> None:
        self.loop = loop
        self.table = table
        self.ownership = ownership
        #: position bounds every trajectory point must respect (URDF limits minus the safety margin)
        self.bounds = bounds
        #: the limiter the executor applies (a started motion gets its joints' part and envelope)
        self.limiter = limiter

    def prepare(
        self, ex: _Exec, traj: Trajectory, q0: np.ndarray, v0: np.ndarray, a0: np.ndarray, t0: float
    ) -> tuple[Trajectory, TrajectorySampler]:
        """Wrap continuous joints to the shortest angle from ``q0``, build the sampler from the start
        state and check the whole motion against the limits (stretching it if asked). Raises
        :class:`LimitViolation` naming the segment and joint.
        """
        idx = ex.idx
        if ex.wrap is not None:
            offsets = np.where(ex.wrap, _turns_to(q0, traj.positions[0]), 0.0)
            if offsets.any():
                traj = traj.shifted(offsets)
                ex.goal = np.asarray(traj.positions[-1], dtype=float).copy()
        lo, hi = self.bounds.lo[idx], self.bounds.hi[idx]
        vmax, amax = self.table.vmax[idx], self.table.amax[idx]
        if traj.velocities is not None and traj.points[0].time_from_start == 0.0:
            # a first point at time 0 is output at once (JTC): its velocity must continue the current one
            step = np.abs(traj.velocities[0] - v0)
            bad = ~(step <= amax * self.loop.period * (1.0 + _STEP_RTOL) + 1e-9)
            if bad.any():
                k = int(np.argmax(bad))
                raise LimitViolation(
                    f"point 0: joint {traj.joint_names[k]!r} velocity {traj.velocities[0, k]:.6g} at time_from_start "
                    f"0 is a step from its current velocity {v0[k]:.6g}, beyond max_acceleration {amax[k]:.6g}; "
                    "give point 0 a time_from_start > 0 (the motion then starts from the current state)"
                )
        sampler = TrajectorySampler(traj, start_time=t0, start_positions=q0, start_velocities=v0,
                                    start_accelerations=a0)
        hint = ("; slow the trajectory down (later time_from_start), or pass stretch_to_limits=True to "
                "let follow() stretch its timing")
        if not ex.stretch:
            check_motion_limits(sampler, lo, hi, vmax, amax, hint=hint)
            return traj, sampler
        scaled = traj
        factor = 1.0
        for _ in range(_MAX_STRETCH_ITERATIONS):
            try:
                check_motion_limits(sampler, lo, hi, vmax, amax)
                return scaled, sampler
            except LimitViolation:
                scale = time_scale_for_limits(sampler, vmax, amax)
                # scale == 1: velocities and accelerations fit, the position limits do not: no stretching helps
                too_long = traj.duration * factor * scale > MAX_TIME_FROM_START
                if not math.isfinite(scale) or scale <= 1.0 + 1e-9 or too_long:
                    break
                factor *= max(scale, 1.01)
                scaled = traj.time_scaled(factor)
                sampler = TrajectorySampler(scaled, start_time=t0, start_positions=q0, start_velocities=v0,
                                            start_accelerations=a0)
        check_motion_limits(sampler, lo, hi, vmax, amax,
                            hint=f" even stretched {factor:.3g} times slower (stretch_to_limits)")
        return scaled, sampler

    def predicted(self, idx: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Desired (q, v, a) of joints ``idx`` at robot time ``t``, if nothing changes meanwhile."""
        q, v, a = self.ownership.desired(idx)
        owner = self.table.owner
        for k, j in enumerate(idx.tolist()):
            ex = owner[j]
            if ex is not None and ex.sampler is not None and ex.remote_rest < 0.0:
                m = int(np.flatnonzero(ex.idx == j)[0])
                tau = t if ex.phase == MotionPhase.STOPPING else ex.tau + ex.s * (t - ex.t_last)
                eq, ev, ea = ex.sampler.sample(tau)
                s = 1.0 if ex.phase == MotionPhase.STOPPING else ex.s
                q[k], v[k], a[k] = eq[m], ev[m] * s, ea[m] * s * s
        return q, v, a

    def begin(self, ex: _Exec, sampler: TrajectorySampler, q0: np.ndarray, v0: np.ndarray, a0: np.ndarray,
               t0: float) -> None:
        """Make ``ex`` follow ``sampler`` from time ``t0`` (the desired state there is (q0, v0, a0))."""
        ex.sampler = sampler
        ex.t0 = ex.tau = ex.t_last = t0
        ex.phase = MotionPhase.FOLLOW
        # the trajectory's velocities are in its own time: start at full speed when the start state
        # moves (no velocity jump), else directly at the current scaling (a paused robot stays put)
        ex.s = 1.0 if np.any(np.abs(v0) > 1e-9) else self.table.speed
        ex.sdot = 0.0
        ex.des_q, ex.des_v, ex.des_a = q0.copy(), v0.copy(), a0.copy()
        ex.vt, ex.at = v0.copy(), a0.copy()
        ex.path_unbounded = bool(np.all(ex.path_tol == np.inf))
        # what the tick may skip of the limiter for this motion (the sampler's peaks are known from the check)
        if ex.limits is None:
            ex.limits = self.limiter.select(ex.idx)
        ex.env = envelope(sampler, ex.limits, self.loop.period)
