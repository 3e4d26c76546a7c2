"""Stop planning: where a stop starts (measured or reference state) and the stop ramp it follows."""

from __future__ import annotations

import numpy as np

from ..errors import CommandRejected
from ..limits import PositionBounds, StepGuard
from ..loop import ControlLoop
from ..trajectory import (
    TrajectorySampler,
    plan_stop,
)
from ._handle import Motion
from ._ownership import _Ownership
from ._records import _Exec, _MotionTable
from ._types import TRACKING_BAND, MotionPhase, ResultCode, _wrap_angle


class _StopPlanner:
    """Plans the stop ramps of motions that are cancelled, stopped early or aborted."""

    def __init__(self, loop: ControlLoop, table: _MotionTable, ownership: _Ownership, bounds: PositionBounds,
                 decel_scale: float, guard: StepGuard | None) -> None:
        self.loop = loop
        self.table = table
        self.ownership = ownership
        #: position bounds a stop's start is kept inside
        self.bounds = bounds
        #: scale of max_acceleration used by stop ramps
        self.decel_scale = decel_scale
        #: the safety layer's limiter, told where a stop restarts a joint's reference (None: none)
        self.guard = guard
        kp, kd = loop.gain_p, loop.gain_d
        # a stiffness below 1e-12 (e.g. a denormal gain from a config) counts as none, like kp == 0:
        # kd/kp would overflow
        stiff = kp > 1e-12
        self._lag_per_speed = np.divide(kd, kp, out=np.zeros(len(kp)), where=stiff)

    def request_stop(self, motion: Motion, code: ResultCode, msg: str) -> None:
        """Stop ``motion`` along a ramp from its desired state (a scheduled one ends at once), result ``code``."""
        for ex in list(self.table.pending):
            if ex.motion is motion:
                self.ownership.finish(ex, code, f"{msg} before its scheduled start")
                return
        for owner in set(self.table.owner):
            if owner is not None and owner.motion is motion:
                # cancel: from the current desired state (the robot tracks it; a smooth stop)
                q, v, a = self.ownership.desired_next(owner)
                self.begin_stop(owner, code, msg, self.loop.stamp, q, v, a, measured=None)
                return

    def stop_start(
        self, idx: np.ndarray, q: np.ndarray, v: np.ndarray, a: np.ndarray, force: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Where an abort's stop starts: (q0, v0, a0, from_measured) for joints ``idx``.

        From the measured position and velocity (the reference is dropped), except for joints
        that track their desired state ``(q, v, a)`` within :data:`TRACKING_BAND` and are not in
        ``force``: those start from it (the same state up to servo accuracy, and smooth). The
        start is made consistent with the limits: positions inside the bounds, |v| <= max_velocity.
        """
        st = self.loop.state
        qm = st.position[idx]
        vm = st.velocity[idx]
        dq = q - qm
        wrap = self.table.continuous[idx]
        if wrap.any():
            dq = np.where(wrap, _wrap_angle(dq), dq)
        band_q, band_v = TRACKING_BAND
        # a PD servo following a reference that moves at v lags it by kd/kp * v (no feed-forward)
        band = band_q + self._lag_per_speed[idx] * np.abs(v)
        tracking = (np.abs(dq) <= band) & (np.abs(v - vm) <= band_v)
        if force is not None:
            tracking &= ~force
        # a measurement that is not finite (a failing sensor) cannot be a stop's start
        meas = ~tracking & np.isfinite(qm) & np.isfinite(vm)
        if not meas.any():
            return q, v, a, meas
        vmax = self.table.vmax[idx]
        q0 = np.where(meas, np.clip(q - dq, self.bounds.lo[idx], self.bounds.hi[idx]), q)
        v0 = np.where(meas, np.clip(vm, -vmax, vmax), v)
        a0 = np.where(meas, 0.0, a)
        return q0, v0, a0, meas

    def plan_stop_sampler(self, idx: np.ndarray, q: np.ndarray, v: np.ndarray, a: np.ndarray,
                          t0: float) -> TrajectorySampler:
        """The stop ramp of joints ``idx`` from (q, v, a) at robot time ``t0``, within their deceleration limits."""
        joints = [self.loop.joints[i] for i in idx.tolist()]
        try:
            stop = plan_stop(q, v, a, joints, decel_scale=self.decel_scale)
        except CommandRejected:
            # (cannot happen from a finite state) hold where the setpoint is rather than fail the stop
            q = np.where(np.isfinite(q), q, self.loop.setpoint.position[idx])
            z = np.zeros(len(idx))
            stop = plan_stop(q, z, z, joints, decel_scale=self.decel_scale)
            v, a = z, z
        return TrajectorySampler(stop, start_time=t0, start_positions=q, start_velocities=v, start_accelerations=a)

    def begin_stop(self, ex: _Exec, code: ResultCode | None, msg: str, t0: float, q: np.ndarray, v: np.ndarray,
                   a: np.ndarray, measured: np.ndarray | None) -> None:
        """Replace ``ex``'s reference by a stop ramp from (q, v, a) at ``t0``; ``measured`` marks the joints
        whose reference was reset to their measured state (the limiter is told).
        """
        if ex.phase in (MotionPhase.STOPPING, MotionPhase.DEAD):
            return
        if ex.remote is not None:
            ex.remote.cancel()  # the controller stops its goal; its outcome ends the motion (_update_remote)
        if measured is not None and measured.any() and self.guard is not None:
            self.guard.rebase(ex.idx[measured], q[measured])
        ex.sampler = self.plan_stop_sampler(ex.idx, q, v, a, t0)
        ex.t0 = ex.tau = ex.t_last = t0
        ex.s, ex.sdot = 1.0, 0.0
        ex.phase = MotionPhase.STOPPING
        ex.stop_code = code
        ex.stop_msg = msg

    def abort(self, ex: _Exec, code: ResultCode, msg: str, t: float, q: np.ndarray, v: np.ndarray,
              a: np.ndarray, force: np.ndarray | None) -> None:
        """Abort ``ex`` in the tick at ``t``: drop its reference, stop from the measured state, hold."""
        q0, v0, a0, meas = self.stop_start(ex.idx, q, v, a, force)
        self.begin_stop(ex, code, msg, t, q0, v0, a0, meas)
