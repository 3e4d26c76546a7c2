"""Who drives which joint: the motion manager's state, joint ownership, speed scaling, the
desired state and how a motion ends (resolve, release).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigurationError, InvalidValueError
from ..limits import PositionBounds, StepGuard, StepLimiter
from ..loop import ControlLoop
from ..offload import TrajectoryOffload
from ._handle import Motion
from ._records import _Exec
from ._types import _POS, _SCALE_ACC_MARGIN, MotionPhase, MotionResult, ResultCode, _wrap_angle

if TYPE_CHECKING:
    from ..kinematics import Kinematics


class _Ownership:
    """The motion manager's state: which executor owns which joint, speed scaling, the desired state."""

    def __init__(
        self, loop: ControlLoop, bounds: PositionBounds, decel_scale: float = 1.0, guard: StepGuard | None = None
    ) -> None:
        self.loop = loop
        #: position bounds every trajectory point must respect (URDF limits minus the safety margin)
        self.bounds = bounds
        #: scale of max_acceleration used by stop ramps
        self.decel_scale = decel_scale
        n = len(loop.joints)
        self._owner: list[_Exec | None] = [None] * n
        #: motions scheduled to start later (``start_time`` in the future)
        self._pending: list[_Exec] = []
        #: joints currently driven by a motion or a stop ramp (read-only for other modules)
        self.owned_mask = np.zeros(n, dtype=bool)
        joints = loop.joints
        self._vmax = np.array([j.max_velocity for j in joints], dtype=np.float64)
        self._amax = np.array([j.max_acceleration for j in joints], dtype=np.float64)
        #: continuous joints: shortest-angle start, wrapped errors
        self._continuous = np.array([j.type == "continuous" for j in joints], dtype=bool)
        kp, kd = loop.gain_p, loop.gain_d
        # a stiffness below 1e-12 (e.g. a denormal gain from a config) counts as none, like kp == 0:
        # kd/kp would overflow
        stiff = kp > 1e-12
        self._lag_per_speed = np.divide(kd, kp, out=np.zeros(len(kp)), where=stiff)
        self._speed = 1.0
        #: the safety layer's limiter the setpoints pass through (None: none), so that a planned step
        #: it would clip is caught here and reported, never clipped silently
        self._guard = guard
        #: the limiter the executor applies: the safety layer's, else (no guard) the position bounds alone
        self._limiter = guard.limiter if guard is not None else StepLimiter(
            bounds.lo, bounds.hi, None, np.full(n, np.inf), np.full(n, np.inf))
        self._origin = None if guard is None else guard.origin
        #: the robot's kinematics (set by the Robot), for link poses in motion feedback
        self.kinematics_source: Callable[[], Kinematics] | None = None
        #: the robot's sensors (set by the Robot), for ``motion.feedback(sensors=...)``
        self.sensors_source: Callable[[], Any] | None = None
        backend = getattr(loop, "backend", None)
        #: the backend's controller runs whole trajectories (goals) instead of streamed setpoints
        self._offload = backend if isinstance(backend, TrajectoryOffload) else None

    def kinematics(self) -> Kinematics:
        """The robot's :class:`~agentsdk.kinematics.Kinematics` (raises if it has none)."""
        if self.kinematics_source is None:
            raise ConfigurationError("link poses need the robot's kinematics; this motion manager has no robot")
        return self.kinematics_source()

    # ------------------------------------------------------------ speed scaling
    @property
    def speed_scaling(self) -> float:
        """The speed scaling factor every trajectory follows (1.0: as timed, 0.0: paused)."""
        return self._speed

    def set_speed_scaling(self, factor: float) -> None:
        """Set the speed scaling factor in [0, 1]; running trajectories follow it smoothly."""
        try:
            f = float(factor)
        except (TypeError, ValueError):
            raise InvalidValueError(f"speed scaling must be a number in [0, 1], got {factor!r}") from None
        if not 0.0 <= f <= 1.0:
            raise InvalidValueError(f"speed scaling must be in [0, 1] (0 pauses, 1 is full speed), got {factor!r}")
        self._speed = f

    # ------------------------------------------------------------ queries
    def owner_of(self, idx: np.ndarray) -> tuple[int, Motion | None] | None:
        """The first of joints ``idx`` driven (or reserved by a scheduled motion), with its motion."""
        for j in idx.tolist():
            ex = self._owner[j]
            if ex is not None:
                return j, ex.motion
        for ex in self._pending:
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
            ex = self._owner[j]
            if ex is not None and len(ex.des_q):
                m = int(np.flatnonzero(ex.idx == j)[0])
                eq, ev, ea = self._desired_next(ex)
                q[k], v[k], a[k] = eq[m], ev[m], ea[m]
        return q, v, a

    def _desired_next(self, ex: _Exec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Desired (q, v, a) of ``ex`` at the next tick (``ctl.stamp``), not at the last one (``ex.des_*``).

        A trajectory or stop ramp started now starts at ``ctl.stamp`` from this state, so the
        desired motion continues seamlessly; starting it from the last tick's state would
        repeat that position for one tick (a stall of v*dt while the desired velocity says v).
        """
        if ex.remote_rest >= 0.0:  # an ended offloaded goal: the setpoint follows the measured position, at rest
            zero = np.zeros(len(ex.idx))
            return ex.des_q.copy(), zero, zero.copy()
        tau, s, sdot = self._advance(ex, self.loop.stamp)
        q, vt, at = ex.sampler.sample(tau)
        if ex.phase == MotionPhase.STOPPING or (s == 1.0 and sdot == 0.0):
            return q, vt, at
        return q, vt * s, at * (s * s) + vt * sdot

    # --------------------------------------------------------- every tick
    def _advance(self, ex: _Exec, t: float) -> tuple[float, float, float]:
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
        f = self._speed if ex.remote is None else 1.0  # an offloaded goal runs at the controller's timing
        if s == f:
            return ex.tau + s * dt, s, 0.0
        d = f - s
        idx = ex.idx
        amax = self._amax[idx] * _SCALE_ACC_MARGIN
        vmax = self._vmax[idx]
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

    def _own(self, ex: _Exec) -> None:
        for j in ex.idx.tolist():
            self._owner[j] = ex
        self.owned_mask[ex.idx] = True

    def _release(self, ex: _Exec) -> None:
        remote, ex.remote = ex.remote, None
        if remote is not None:
            remote.release()  # cancels the goal if it still runs; the backend streams again
        for j in ex.idx.tolist():
            if self._owner[j] is ex:
                self._owner[j] = None
                self.owned_mask[j] = False
        if ex in self._pending:
            self._pending.remove(ex)

    def _finish(self, ex: _Exec, code: ResultCode | None, msg: str) -> None:
        self._release(ex)
        ex.phase = MotionPhase.DEAD
        self._resolve(ex, code, msg)
        if ex.on_done is not None:
            ex.on_done()

    def _resolve(self, ex: _Exec, code: ResultCode | None, msg: str) -> None:
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
