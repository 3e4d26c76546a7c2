"""Trajectory execution: the :class:`Motion` handle and the executor that runs inside the control tick.

Modelled on ros2_controllers' JointTrajectoryController and the
FollowJointTrajectory action:

* ``robot.follow(traj)`` returns a :class:`Motion` at once; ``await motion``
  gives a :class:`MotionResult` whose code is named after FollowJointTrajectory
  (plus CANCELED, PREEMPTED, ABORTED).
* The executor samples the trajectory every control tick (no asyncio timers in
  the loop), so tracking is identical in lockstep and in real time.
* ``motion.cancel()`` — or cancelling the task awaiting the motion, e.g. via
  ``asyncio.timeout`` — decelerates every joint to rest within its deceleration
  limit (a jerk-limited ruckig profile from the current desired state), then
  holds position. Not an instant freeze, not a runaway.
* A new ``follow`` on overlapping joints preempts the running motion (PREEMPTED)
  and starts from its *desired* position, velocity and acceleration, so the
  desired velocity is continuous at the switch.
* Path, goal and goal-time tolerances per joint; a violation aborts with the
  matching code, decelerates and holds.
"""

from __future__ import annotations

import asyncio
import enum
import functools
from collections.abc import AsyncIterator, Generator, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from . import scope
from .backend import ModeCode
from .errors import InvalidValueError, UnknownJointError
from .loop import ControlLoop, HookHandle, Phase, Setpoint, StateView
from .trajectory import Trajectory, TrajectorySampler, plan_point_to_point, plan_stop

if TYPE_CHECKING:
    from .safety import PositionBounds

__all__ = ["Feedback", "Motion", "MotionResult", "ResultCode", "Tolerances"]

_POS = int(ModeCode.POSITION)  # a plain int: numpy handles an IntEnum member slowly


class ResultCode(enum.IntEnum):
    """FollowJointTrajectory result codes, plus the outcomes of an action goal."""

    SUCCESSFUL = 0
    INVALID_GOAL = -1
    INVALID_JOINTS = -2
    PATH_TOLERANCE_VIOLATED = -4
    GOAL_TOLERANCE_VIOLATED = -5
    #: motion.cancel() or the awaiting task was cancelled: decelerated and holding
    CANCELED = -10
    #: replaced by a newer follow() on overlapping joints
    PREEMPTED = -11
    #: stopped by the safety layer (e-stop, fault) or the robot closing
    ABORTED = -12


@dataclass(frozen=True, slots=True)
class MotionResult:
    """How a motion ended.

    A FollowJointTrajectory-style result code, the final error per joint, a message and the robot time.
    """

    code: ResultCode
    #: final position error per joint (desired goal - actual), rad or m
    error: Mapping[str, float]
    message: str = ""
    #: robot time when the motion ended
    time: float = 0.0

    @property
    def ok(self) -> bool:
        """True when the motion ended SUCCESSFUL."""
        return self.code is ResultCode.SUCCESSFUL


@dataclass(frozen=True, slots=True)
class Tolerances:
    """Per-joint tolerances (a float for all joints, or ``{joint: value}``).

    ``path``: max ``|desired - actual|`` position error while moving (None: not checked).
    ``goal``: max ``|goal - actual|`` position error at the end.
    ``goal_time``: how long after the trajectory's end the goal tolerance may take to be met.
    """

    path: float | Mapping[str, float] | None = None
    goal: float | Mapping[str, float] = 0.02
    goal_time: float = 1.0


@dataclass(frozen=True, slots=True)
class Feedback:
    """Like FollowJointTrajectory feedback: desired, actual and error at ``time``."""

    time: float
    joint_names: tuple[str, ...]
    desired_positions: np.ndarray
    desired_velocities: np.ndarray
    actual_positions: np.ndarray
    actual_velocities: np.ndarray
    error: np.ndarray
    #: 0.0 at the start, 1.0 at the end of the trajectory
    progress: float


def _per_joint(value: float | Mapping[str, float] | None, names: tuple[str, ...], what: str) -> np.ndarray:
    if value is None:
        return np.full(len(names), np.inf)
    if isinstance(value, Mapping):
        unknown = set(value) - set(names)
        if unknown:
            raise UnknownJointError(f"{what} tolerance for joints not in the trajectory: {sorted(unknown)}")
        return np.array([float(value.get(n, np.inf)) for n in names])
    v = float(value)
    if not v > 0:
        raise InvalidValueError(f"{what} tolerance must be > 0, got {value!r}")
    return np.full(len(names), v)


class Motion:
    """Handle of a running trajectory. Awaitable; ``cancel()``; ``feedback()``."""

    def __init__(self, manager: MotionManager, idx: np.ndarray, names: tuple[str, ...]) -> None:
        self._mgr = manager
        self.idx = idx
        self.joint_names = names
        self._future: asyncio.Future[MotionResult] = asyncio.get_running_loop().create_future()
        #: the executor driving this motion (its per-tick buffers hold the latest feedback)
        self._exec: _Exec | None = None
        self._fb_cache: Feedback | None = None
        self._fb_cache_tick = 0
        self._cancel_requested = False

    # awaitable ------------------------------------------------------------
    def __await__(self) -> Generator[Any, None, MotionResult]:
        return self._wait().__await__()

    async def _wait(self) -> MotionResult:
        try:
            return await asyncio.shield(self._future)
        except asyncio.CancelledError:
            # the awaiting task was cancelled (e.g. asyncio.timeout): stop safely
            self.cancel()
            raise

    def done(self) -> bool:
        """True once the motion has ended (its result is available)."""
        return self._future.done()

    def result(self) -> MotionResult:
        """The result; raises ``asyncio.InvalidStateError`` while running."""
        return self._future.result()

    def cancel(self) -> None:
        """Decelerate to rest within the joints' limits, then hold. Result: CANCELED."""
        if not self._future.done() and not self._cancel_requested:
            self._cancel_requested = True
            self._mgr._request_stop(self, ResultCode.CANCELED, "canceled")

    async def feedback(self, rate: float = 50.0) -> AsyncIterator[Feedback]:
        """Yield feedback at ``rate`` Hz of robot time until the motion ends (the last one included)."""
        if not rate > 0:
            raise InvalidValueError(f"feedback rate must be > 0, got {rate!r}")
        clock = self._mgr.loop.clock
        period = 1.0 / rate
        next_t = clock.now()
        last: Feedback | None = None
        while True:
            fb = self._latest_feedback()
            if fb is not None and fb is not last:
                last = fb
                yield fb
            if self._future.done():
                return
            next_t += period
            await clock.sleep_until(next_t)

    def _latest_feedback(self) -> Feedback | None:
        """The feedback of the latest tick the executor ran, built when asked (not every tick)."""
        ex = self._exec
        if ex is None or ex.fb_tick == 0:
            return None
        if self._fb_cache is None or self._fb_cache_tick != ex.fb_tick:
            q, v = ex.out[0].copy(), ex.out[1].copy()
            actual, actual_v = ex.fb_state.copy()
            self._fb_cache = Feedback(ex.fb_time, self.joint_names, q, v, actual, actual_v, q - actual,
                                      ex.fb_progress)
            self._fb_cache_tick = ex.fb_tick
        return self._fb_cache

    def __repr__(self) -> str:
        state = self._future.result().code.name if self._future.done() else "running"
        return f"<Motion {list(self.joint_names)} {state}>"


@dataclass(eq=False, slots=True)
class _Exec:
    """Executor state of one motion (lives in the control tick)."""

    motion: Motion | None
    idx: np.ndarray
    sampler: Any
    t0: float
    path_tol: np.ndarray
    goal_tol: np.ndarray
    goal_time: float
    goal: np.ndarray
    phase: str = "follow"  # follow | settle | stopping
    stop_code: ResultCode | None = None
    stop_msg: str = ""
    des_q: np.ndarray = field(default_factory=lambda: np.zeros(0))
    des_v: np.ndarray = field(default_factory=lambda: np.zeros(0))
    des_a: np.ndarray = field(default_factory=lambda: np.zeros(0))
    on_done: Any = None
    # per-tick buffers (allocated once in __post_init__; the tick writes them in place)
    #: the joints as a slice when they are consecutive (cheaper indexing), else ``idx``
    sel: Any = None
    #: the sampler's output ``[q, v, a]`` of the latest tick (shape (3, joints))
    out: np.ndarray = field(default_factory=lambda: np.zeros((3, 0)))
    #: setpoint rows effort, kp, kd written every tick (0, the default gains)
    fixed: np.ndarray = field(default_factory=lambda: np.zeros((3, 0)))
    #: True when a path tolerance is finite (else the path check is skipped)
    check_path: bool = False
    #: the latest tick's time, measured position/velocity and progress (read by Motion feedback)
    fb_tick: int = 0
    fb_time: float = 0.0
    fb_progress: float = 0.0
    #: measured ``[position, velocity]`` of the joints at the latest tick (shape (2, joints))
    fb_state: np.ndarray = field(default_factory=lambda: np.zeros((2, 0)))
    #: views made once: the rows of ``out`` and ``fb_state``; scratch of the tolerance checks
    out_rows: tuple[np.ndarray, np.ndarray, np.ndarray] = ()  # type: ignore[assignment]
    out_qv: np.ndarray = field(default_factory=lambda: np.zeros((2, 0)))
    fb_rows: tuple[np.ndarray, np.ndarray] = ()  # type: ignore[assignment]
    err: np.ndarray = field(default_factory=lambda: np.zeros(0))
    abs_err: np.ndarray = field(default_factory=lambda: np.zeros(0))
    over: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    #: the setpoint and state this executor's views below were made of (the loop's, fixed)
    views_of: Any = None
    #: views of the setpoint's mode, enabled, [position, velocity] rows, [effort, kp, kd] rows,
    #: target and of the state's [position, velocity] rows at the joints (consecutive joints only)
    sp_views: tuple[Any, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.idx)
        start = int(self.idx[0]) if n else 0
        consecutive = n > 0 and bool(np.array_equal(self.idx, np.arange(start, start + n)))
        self.sel = slice(start, start + n) if consecutive else self.idx
        self.out = np.zeros((3, n))
        self.out_rows = (self.out[0], self.out[1], self.out[2])
        self.out_qv = self.out[0:2]
        self.fb_state = np.zeros((2, n))
        self.fb_rows = (self.fb_state[0], self.fb_state[1])
        self.err = np.zeros(n)
        self.abs_err = np.zeros(n)
        self.over = np.zeros(n, dtype=bool)
        self.check_path = bool(np.isfinite(self.path_tol).any())

    def setpoint_views(self, st: StateView, sp: Setpoint) -> tuple[Any, ...]:
        """The views of :attr:`sp_views` for ``st`` and ``sp``, made at the first tick (consecutive joints only)."""
        if self.views_of is not sp:
            sel = self.sel
            if isinstance(sel, slice) and st.block is not None:
                self.sp_views = (sp.mode[sel], sp.enabled[sel], sp.block[0:2, sel], sp.block[2:5, sel],
                                 sp.target[sel], st.block[0:2, sel])
            else:
                self.sp_views = ()
            self.views_of = sp
        return self.sp_views


class MotionManager:
    """Owns the running motions of one robot; one executor per motion, run in the control tick."""

    def __init__(self, loop: ControlLoop, bounds: PositionBounds, decel_scale: float = 1.0) -> None:
        self.loop = loop
        #: position bounds every trajectory point must respect (URDF limits minus the safety margin)
        self.bounds = bounds
        #: scale of max_acceleration used by stop ramps
        self.decel_scale = decel_scale
        n = len(loop.joints)
        self._owner: list[_Exec | None] = [None] * n
        #: joints currently driven by a motion or a stop ramp (read-only for other modules)
        self.owned_mask = np.zeros(n, dtype=bool)

    # ------------------------------------------------------------ queries
    def owner_of(self, idx: np.ndarray) -> tuple[int, Motion | None] | None:
        for j in idx.tolist():
            ex = self._owner[j]
            if ex is not None:
                return j, ex.motion
        return None

    def desired(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Current desired (q, v, a) for joints: from their executor, else the setpoint/state."""
        loop = self.loop
        sp, st = loop.setpoint, loop.state
        q = np.where(sp.mode[idx] == _POS, sp.position[idx], st.position[idx])
        v = np.where(sp.mode[idx] == _POS, sp.velocity[idx], st.velocity[idx])
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
        return ex.sampler.sample(self.loop.stamp)

    # ------------------------------------------------------------- start
    def follow(self, traj: Trajectory, tolerances: Tolerances | None) -> Motion:
        """Start executing ``traj`` (validated against the joints); returns its :class:`Motion` handle."""
        ctl = self.loop
        if not isinstance(traj, Trajectory):
            raise InvalidValueError(f"expected a Trajectory, got {type(traj).__name__}")
        traj.validate(ctl.joints)
        names = tuple(traj.joint_names)
        idx = np.array([ctl.index[n] for n in names], dtype=np.intp)
        for p in traj.points:
            self.bounds.check(np.asarray(p.positions, dtype=float), idx)
        tol = tolerances or Tolerances()
        path_tol = _per_joint(tol.path, names, "path")
        goal_tol = _per_joint(tol.goal, names, "goal")
        if not tol.goal_time >= 0:
            raise InvalidValueError(f"goal_time must be >= 0, got {tol.goal_time!r}")
        q0, v0, a0 = self.desired(idx)
        self._preempt(idx)
        t0 = ctl.stamp
        sampler = TrajectorySampler(traj, start_time=t0, start_positions=q0, start_velocities=v0,
                                    start_accelerations=a0)
        motion = Motion(self, idx, names)
        ex = _Exec(motion, idx, sampler, t0, path_tol, goal_tol, tol.goal_time,
                   goal=np.asarray(traj.points[-1].positions, dtype=float))
        ex.des_q, ex.des_v, ex.des_a = q0.copy(), v0.copy(), a0.copy()
        self._install(ex)
        scope.register(motion)
        return motion

    def move_to(self, positions: Mapping[str, float], duration: float | None, tol: Tolerances | None) -> Motion:
        """Plan a jerk-limited move from the current desired state to ``positions`` and follow it."""
        ctl = self.loop
        if not isinstance(positions, Mapping) or not positions:
            raise InvalidValueError("move_to expects a non-empty {joint name: position} mapping")
        unknown = [n for n in positions if n not in ctl.index]
        if unknown:
            raise UnknownJointError(f"unknown joint {unknown[0]!r}; this robot's joints are: {', '.join(ctl.names)}")
        names = tuple(positions)
        idx = np.array([ctl.index[n] for n in names], dtype=np.intp)
        goal = np.array([float(positions[n]) for n in names])
        if not np.isfinite(goal).all():
            raise InvalidValueError(f"move_to: non-finite target in {dict(positions)!r}")
        self.bounds.check(goal, idx)
        q0, v0, a0 = self.desired(idx)
        joints = [ctl.joints[i] for i in idx.tolist()]
        traj = plan_point_to_point((q0, v0, a0), goal, joints, duration=duration)
        return self.follow(traj, tol)

    def _install(self, ex: _Exec) -> None:
        for j in ex.idx.tolist():
            self._owner[j] = ex
        self.owned_mask[ex.idx] = True
        loop = self.loop
        ex.fixed = np.vstack([np.zeros(len(ex.idx)), loop.gain_p[ex.idx], loop.gain_d[ex.idx]])
        if ex.motion is not None:
            ex.motion._exec = ex
        self.loop.add_hook(Phase.COMMAND, functools.partial(self._update, ex))

    def _release(self, ex: _Exec) -> None:
        for j in ex.idx.tolist():
            if self._owner[j] is ex:
                self._owner[j] = None
                self.owned_mask[j] = False

    def _preempt(self, idx: np.ndarray) -> None:
        seen: list[_Exec] = []
        for j in idx.tolist():
            ex = self._owner[j]
            if ex is not None and ex not in seen:
                seen.append(ex)
        for ex in seen:
            rest = np.array([j for j in ex.idx.tolist() if j not in set(idx.tolist())], dtype=np.intp)
            q, v, a = self.desired(rest) if len(rest) else (None, None, None)
            self._finish(ex, ResultCode.PREEMPTED, "preempted by a newer trajectory")
            if len(rest):
                # joints the new trajectory does not cover come to rest smoothly
                self._start_ramp(rest, q, v, a, None, "")

    # ----------------------------------------------------------- stopping
    def _request_stop(self, motion: Motion, code: ResultCode, msg: str) -> None:
        for ex in set(self._owner):
            if ex is not None and ex.motion is motion:
                self._begin_stop(ex, code, msg)
                return

    def _begin_stop(self, ex: _Exec, code: ResultCode, msg: str) -> None:
        if ex.phase == "stopping":
            return
        q, v, a = self._desired_next(ex)
        joints = [self.loop.joints[i] for i in ex.idx.tolist()]
        stop = plan_stop(q, v, a, joints, decel_scale=self.decel_scale)
        ex.sampler = TrajectorySampler(stop, start_time=self.loop.stamp, start_positions=q, start_velocities=v,
                                       start_accelerations=a)
        ex.t0 = self.loop.stamp
        ex.phase = "stopping"
        ex.stop_code = code
        ex.stop_msg = msg

    def _start_ramp(self, idx: np.ndarray, q: Any, v: Any, a: Any, code: ResultCode | None, msg: str,
                    on_done: Any = None) -> _Exec:
        joints = [self.loop.joints[i] for i in idx.tolist()]
        stop = plan_stop(q, v, a, joints, decel_scale=self.decel_scale)
        t0 = self.loop.stamp
        sampler = TrajectorySampler(stop, start_time=t0, start_positions=q, start_velocities=v,
                                    start_accelerations=a)
        n = len(idx)
        ex = _Exec(None, idx, sampler, t0, np.full(n, np.inf), np.full(n, np.inf), 0.0, goal=q.copy(),
                   phase="stopping", stop_code=code, stop_msg=msg, on_done=on_done)
        ex.des_q, ex.des_v, ex.des_a = q.copy(), v.copy(), a.copy()
        self._install(ex)
        return ex

    async def stop_all_ramp(self, damp_only: bool = False, damping: float = 5.0) -> None:
        """Decelerate every joint to rest (e-stop categories 1 and 2); returns when at rest.

        ``damp_only`` (backends without position control): velocity mode at zero
        velocity with gain ``damping`` until every joint is still.
        """
        loop = self.loop
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        idx = np.arange(len(loop.joints))
        handle: HookHandle | None = None
        if damp_only:
            loop.damp(idx, damping)

            def _until_still(t: float, st: StateView, sp: Setpoint) -> bool:
                if np.all(np.abs(st.velocity) < 1e-2) and not done.done():
                    done.set_result(None)
                return not done.done()

            handle = loop.add_hook(Phase.COMMAND, _until_still)
        else:
            q, v, a = self.desired(idx)
            for ex in set(self._owner):
                if ex is not None:
                    self._finish(ex, ResultCode.ABORTED, "stopped by the safety layer")
            self._start_ramp(idx, q, v, a, None, "", on_done=lambda: done.done() or done.set_result(None))
        try:
            await done
        finally:
            if handle is not None:
                handle.remove()

    def abort_all(self, reason: str = "robot closed") -> None:
        """Resolve every motion ABORTED (no ramp: the caller takes over the joints)."""
        for ex in set(self._owner):
            if ex is not None and ex.motion is not None:
                self._finish(ex, ResultCode.ABORTED, f"aborted: {reason}")

    def end_all(self, reason: str) -> None:
        """End every motion (ABORTED) and every stop ramp now, leaving the setpoint where it is.

        Used by ``reset()``: nothing may keep driving the joints over time afterwards.
        """
        for ex in set(self._owner):
            if ex is not None:
                self._finish(ex, ResultCode.ABORTED if ex.motion is not None else None, f"aborted: {reason}")

    def fail_all(self, exc: BaseException) -> None:
        """Fail every motion with ``exc`` (the control loop died)."""
        for ex in set(self._owner):
            if ex is None:
                continue
            self._release(ex)
            if ex.motion is not None and not ex.motion._future.done():
                ex.motion._future.set_exception(exc)
                ex.motion._future.exception()  # mark retrieved: the awaiting side re-raises it
            ex.phase = "dead"

    def _finish(self, ex: _Exec, code: ResultCode | None, msg: str) -> None:
        self._release(ex)
        ex.phase = "dead"
        if ex.motion is not None and code is not None and not ex.motion._future.done():
            st = self.loop.state
            err = ex.goal - st.position[ex.idx]
            res = MotionResult(code, dict(zip(ex.motion.joint_names, err.tolist(), strict=True)), msg, self.loop.stamp)
            ex.motion._future.set_result(res)
        if ex.on_done is not None:
            ex.on_done()

    # --------------------------------------------------------- every tick
    def _update(self, ex: _Exec, t: float, st: StateView, sp: Setpoint) -> bool:
        # allocation-free: the sample goes into ex.out, the setpoint rows are written in a few
        # block operations (a slice when the joints are consecutive), feedback is built on demand
        if ex.phase == "dead":
            return False
        out = ex.sampler.sample_into(t, ex.out)
        rows = ex.out_rows
        ex.des_q, ex.des_v, ex.des_a = rows
        q = rows[0]
        fb_state = ex.fb_state
        views = ex.setpoint_views(st, sp)
        if views:  # consecutive joints: copies into views made once
            mode, enabled, pos_vel, fixed, target, measured = views
            mode.fill(_POS)
            enabled.fill(True)
            pos_vel[...] = ex.out_qv  # position, velocity
            fixed[...] = ex.fixed  # effort feed-forward 0, default kp, kd
            target[...] = q
            fb_state[...] = measured
        else:
            sel = ex.sel
            sp.mode[sel] = _POS
            sp.enabled[sel] = True
            block = sp.block
            block[0:2, sel] = out[0:2]
            block[2:5, sel] = ex.fixed
            sp.target[sel] = q
            if st.block is not None:
                fb_state[:] = st.block[0:2, sel]
            else:
                fb_state[0] = st.position[sel]
                fb_state[1] = st.velocity[sel]
        actual = ex.fb_rows[0]
        ex.fb_time = t
        ex.fb_tick += 1
        m = ex.motion
        elapsed = t - ex.t0
        dur = ex.sampler.duration
        phase = ex.phase
        if phase != "stopping":  # the stop ramp is not progress along the trajectory: keep the last value
            ex.fb_progress = min(1.0, elapsed / dur) if dur > 0 else 1.0
        if phase == "follow":
            if ex.check_path:
                err, over = ex.err, ex.over
                np.subtract(q, actual, out=err)
                abs_err = ex.abs_err
                np.absolute(err, out=abs_err)
                np.greater(abs_err, ex.path_tol, out=over)
                if np.count_nonzero(over):
                    k = int(np.argmax(over))
                    self._begin_stop(ex, ResultCode.PATH_TOLERANCE_VIOLATED,
                                     f"path tolerance violated on joint {m.joint_names[k] if m else k!r}: "
                                     f"error {err[k]:.4f} > {ex.path_tol[k]:.4f}")
                    return True
            if elapsed >= dur:
                ex.phase = "settle"
        if ex.phase == "settle":
            gerr, inside = ex.abs_err, ex.over
            np.subtract(ex.goal, actual, out=gerr)
            np.absolute(gerr, out=gerr)
            np.less_equal(gerr, ex.goal_tol, out=inside)
            if np.count_nonzero(inside) == len(inside):
                self._finish(ex, ResultCode.SUCCESSFUL, "")
                self._hold_at(ex.idx, ex.goal)
                return False
            if elapsed >= ex.sampler.duration + ex.goal_time:
                k = int(np.argmax(gerr - ex.goal_tol))
                name = m.joint_names[k] if m else str(k)
                self._finish(ex, ResultCode.GOAL_TOLERANCE_VIOLATED,
                             f"goal tolerance violated on joint {name!r}: error {gerr[k]:.4f} > {ex.goal_tol[k]:.4f}")
                self._hold_at(ex.idx, ex.goal)
                return False
        elif ex.phase == "stopping" and elapsed >= ex.sampler.duration:
            final = ex.des_q.copy()
            self._finish(ex, ex.stop_code, ex.stop_msg)
            self._hold_at(ex.idx, final)
            return False
        return True

    def _hold_at(self, idx: np.ndarray, q: np.ndarray) -> None:
        self.loop.hold_at(idx, q)


