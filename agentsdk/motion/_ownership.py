"""Who drives which joint: joint ownership, speed scaling, the desired state and how a motion ends
(resolve, release), over the motion layer's shared :class:`~._records._MotionTable`.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InvalidValueError
from ..loop import ControlLoop
from ._handle import Motion
from ._records import _Exec, _MotionTable
from ._types import _POS, _SCALE_ACC_MARGIN, MotionPhase, MotionResult, ResultCode, _wrap_angle


class _Ownership:
    """Which record owns which joint, the speed scaling factor, the desired state, how a motion ends."""

    def __init__(self, loop: ControlLoop, table: _MotionTable) -> None:
        self.loop = loop
        self.table = table

    # ------------------------------------------------------------ speed scaling
    @property
    def speed_scaling(self) -> float:
        """The speed scaling factor every trajectory follows (1.0: as timed, 0.0: paused)."""
        return self.table.speed

    def set_speed_scaling(self, factor: float) -> None:
        """Set the speed scaling factor in [0, 1]; running trajectories follow it smoothly."""
        try:
            f = float(factor)
        except (TypeError, ValueError):
            raise InvalidValueError(f"speed scaling must be a number in [0, 1], got {factor!r}") from None
        if not 0.0 <= f <= 1.0:
            raise InvalidValueError(f"speed scaling must be in [0, 1] (0 pauses, 1 is full speed), got {factor!r}")
        self.table.speed = f

    # ------------------------------------------------------------ queries
    def owner_of(self, idx: np.ndarray) -> tuple[int, Motion | None] | None:
        """The first of joints ``idx`` driven (or reserved by a scheduled motion), with its motion."""
        table = self.table
        owner = table.owner
        if owner.count(None) != len(owner):  # (a C-level scan: nothing to look up while no joint is driven)
            for j in idx.tolist():
                ex = owner[j]
                if ex is not None:
                    return j, ex.motion
        for ex in table.pending:
            hit = np.intersect1d(ex.idx, idx)
            if len(hit):
                return int(hit[0]), ex.motion
        return None

    def desired(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Current desired (q, v, a) for joints: from their executor, else the setpoint/state."""
        loop = self.loop
        sp, st = loop.setpoint, loop.state
        pos = sp.mode[idx] == _POS
        q = np.where(pos, sp.position[idx], st.position[idx])
        v = np.where(pos, sp.velocity[idx], st.velocity[idx])
        a = np.zeros(len(idx))
        for k, j in enumerate(idx.tolist()):
            ex = self.table.owner[j]
            if ex is not None and len(ex.des_q):
                m = int(np.flatnonzero(ex.idx == j)[0])
                eq, ev, ea = self.desired_next(ex)
                q[k], v[k], a[k] = eq[m], ev[m], ea[m]
        return q, v, a

    def desired_next(self, ex: _Exec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Desired (q, v, a) of ``ex`` at the next tick (``ctl.stamp``), not at the last one (``ex.des_*``).

        A trajectory or stop ramp started now starts at ``ctl.stamp`` from this state, so the
        desired motion continues seamlessly; starting it from the last tick's state would
        repeat that position for one tick (a stall of v*dt while the desired velocity says v).
        """
        if ex.remote_rest >= 0.0:  # an ended offloaded goal: the setpoint follows the measured position, at rest
            zero = np.zeros(len(ex.idx))
            return ex.des_q.copy(), zero, zero.copy()
        tau, s, sdot = self.advance(ex, self.loop.stamp)
        q, vt, at = ex.sampler.sample(tau)
        if ex.phase == MotionPhase.STOPPING or (s == 1.0 and sdot == 0.0):
            return q, vt, at
        return q, vt * s, at * (s * s) + vt * sdot

    # --------------------------------------------------------- every tick
    def advance(self, ex: _Exec, t: float) -> tuple[float, float, float]:
        """(tau, s, sdot) of ``ex`` at tick time ``t``, without committing them.

        Trajectory time advances by at most one control period per tick (a late realtime tick
        slows the trajectory instead of making it jump), times the speed scaling ``s``. ``s``
        follows the factor at a rate bounded so that the acceleration it adds (``v(tau) * ds/dt``)
        keeps every joint within its acceleration limit: velocities stay continuous.
        """
        dt = t - ex.t_last
        if dt <= 0.0:
            return ex.tau, ex.s, ex.sdot
        if dt > self.loop.period:
            dt = self.loop.period
        if ex.phase == MotionPhase.STOPPING:
            return ex.tau + dt, 1.0, 0.0
        s = ex.s
        f = self.table.speed if ex.remote is None else 1.0  # an offloaded goal runs at the controller's timing
        if s == f:
            return ex.tau + s * dt, s, 0.0
        d = f - s
        idx = ex.idx
        amax = self.table.amax[idx] * _SCALE_ACC_MARGIN
        vmax = self.table.vmax[idx]
        vt, at = ex.vt, ex.at
        speed = np.abs(vt)
        # the ramp alone reaches the acceleration limit at full speed in 1/rate seconds ...
        rate = float(np.min(amax / vmax))
        # ... and never pushes a joint's total acceleration a = a(tau) s^2 + v(tau) ds/dt past its limit
        moving = speed > 1e-12
        if moving.any():
            room = amax[moving] - np.sign(vt[moving] * d) * at[moving] * (s * s)
            rate = min(rate, max(0.0, float(np.min(room / speed[moving]))))
        step = rate * dt
        s_new = s + (d if abs(d) <= step else math.copysign(step, d))
        return ex.tau + 0.5 * (s + s_new) * dt, s_new, (s_new - s) / dt

    def own(self, ex: _Exec) -> None:
        """Make ``ex`` the driver of its joints."""
        owner = self.table.owner
        for j in ex.idx.tolist():
            owner[j] = ex
        self.table.owned_mask[ex.idx] = True

    def release(self, ex: _Exec) -> None:
        """``ex`` drives nothing any more (an offloaded goal is released; a scheduled one unscheduled)."""
        remote, ex.remote = ex.remote, None
        if remote is not None:
            remote.release()  # cancels the goal if it still runs; the backend streams again
            self.loop.controller_desired[ex.idx] = np.nan  # its controller no longer stands for their command
        owner, mask, pending = self.table.owner, self.table.owned_mask, self.table.pending
        for j in ex.idx.tolist():
            if owner[j] is ex:
                owner[j] = None
                mask[j] = False
        if ex in pending:
            pending.remove(ex)

    def finish(self, ex: _Exec, code: ResultCode | None, msg: str) -> None:
        """End ``ex``: release its joints, resolve its motion with ``code`` (None: no result), call its ``on_done``."""
        self.release(ex)
        ex.phase = MotionPhase.DEAD
        self.resolve(ex, code, msg)
        if ex.on_done is not None:
            ex.on_done()

    def resolve(self, ex: _Exec, code: ResultCode | None, msg: str) -> None:
        """Set the motion's result (once): ``code``, the goal error per joint, the robot time."""
        m = ex.motion
        if m is None:
            return
        if code is None or m.done():
            m._settle(None)  # no result to set: only the feedback stops moving
            return
        st = self.loop.state
        err = ex.goal - st.position[ex.idx]
        if ex.wrap is not None:
            err = np.where(ex.wrap, _wrap_angle(err), err)
        m._settle(MotionResult(code, dict(zip(m.joint_names, err.tolist(), strict=True)), msg, self.loop.stamp))
