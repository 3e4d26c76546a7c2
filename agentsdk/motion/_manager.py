"""The :class:`MotionManager`: the motion layer's public face to the robot and its safety stop port.

A thin facade: it builds the motion layer's objects (ownership, stop planner, admission, executor),
wires each with exactly the collaborators it needs and the one :class:`~._records._MotionTable` they
share, and keeps the public methods the robot, the safety layer and the applications call.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import scope
from ..config import format_value
from ..errors import ConfigurationError, InvalidValueError, LimitViolation, UnknownJointError
from ..limits import PositionBounds, StepGuard, StepLimiter
from ..loop import ControlLoop, HookHandle, Phase, Setpoint, StateView
from ..offload import TrajectoryOffload
from ..trajectory import (
    Trajectory,
    plan_point_to_point,
)
from ._admission import _Admission
from ._block import BlockPlanner
from ._executor import _Executor
from ._handle import Motion
from ._ownership import _Ownership
from ._records import _Exec, _MotionTable
from ._stops import _StopPlanner
from ._types import MotionPhase, ResultCode, Tolerances, _per_joint, _turns_to

if TYPE_CHECKING:
    from ..kinematics import Kinematics


class MotionManager:
    """Owns the running motions of one robot; one executor record per motion, run in the control tick.

    Implements the safety layer's :class:`~agentsdk.safety.StopPort` and the handle's ``_MotionOwner``.
    """

    def __init__(
        self, loop: ControlLoop, bounds: PositionBounds, decel_scale: float = 1.0, guard: StepGuard | None = None
    ) -> None:
        self.loop = loop
        table = self._table = _MotionTable(loop)
        #: joints currently driven by a motion or a stop ramp (read-only for other modules)
        self.owned_mask = table.owned_mask
        n = len(loop.joints)
        #: the safety layer's limiter (None: none): told where stops restart, reported what it would clip
        self._guard = guard
        # the limiter the executor applies: the safety layer's, else (no guard) the position bounds alone
        limiter = guard.limiter if guard is not None else StepLimiter(
            bounds.lo, bounds.hi, None, np.full(n, np.inf), np.full(n, np.inf))
        backend = getattr(loop, "backend", None)
        # the backend's controller runs whole trajectories (goals) instead of streamed setpoints
        offload = backend if isinstance(backend, TrajectoryOffload) else None
        own = self._ownership = _Ownership(loop, table)
        stops = self._stops = _StopPlanner(loop, table, own, bounds, decel_scale, guard)
        admission = self._admission = _Admission(loop, table, own, bounds, limiter)
        self._executor = _Executor(loop, table, own, stops, admission, limiter, guard, offload)
        #: block lockstep's motion side (see :mod:`agentsdk.block`)
        self.block_planner = BlockPlanner(loop, table, None if guard is None else guard.origin, self._executor)
        #: the robot's kinematics (set by the Robot), for link poses in motion feedback
        self.kinematics_source: Callable[[], Kinematics] | None = None
        #: the robot's sensors (set by the Robot), for ``motion.feedback(sensors=...)``
        self.sensors_source: Callable[[], Any] | None = None

    def kinematics(self) -> Kinematics:
        """The robot's :class:`~agentsdk.kinematics.Kinematics` (raises if it has none)."""
        if self.kinematics_source is None:
            raise ConfigurationError("link poses need the robot's kinematics; this motion manager has no robot")
        return self.kinematics_source()

    @property
    def bounds(self) -> PositionBounds:
        """Position bounds every trajectory point must respect (URDF limits minus the safety margin)."""
        return self._admission.bounds

    @property
    def decel_scale(self) -> float:
        """Scale of max_acceleration used by stop ramps."""
        return self._stops.decel_scale

    # ------------------------------------------------------------ speed scaling, queries
    @property
    def speed_scaling(self) -> float:
        """The speed scaling factor every trajectory follows (1.0: as timed, 0.0: paused)."""
        return self._ownership.speed_scaling

    def set_speed_scaling(self, factor: float) -> None:
        """Set the speed scaling factor in [0, 1]; running trajectories follow it smoothly."""
        self._ownership.set_speed_scaling(factor)

    def owner_of(self, idx: np.ndarray) -> tuple[int, Motion | None] | None:
        """The first of joints ``idx`` driven (or reserved by a scheduled motion), with its motion."""
        return self._ownership.owner_of(idx)

    def desired(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Current desired (q, v, a) for joints: from their executor, else the setpoint/state."""
        return self._ownership.desired(idx)

    def _request_stop(self, motion: Motion, code: ResultCode, msg: str) -> None:
        """Stop ``motion`` along a stop ramp, then resolve it with ``code`` (the handle's cancel, stop_early)."""
        self._stops.request_stop(motion, code, msg)

    # ------------------------------------------------------------- start
    def follow(
        self,
        traj: Trajectory,
        tolerances: Tolerances | None,
        *,
        start_time: float | None = None,
        allow_nonzero_velocity_at_end: bool = False,
        stretch_to_limits: bool = False,
    ) -> Motion:
        """Start executing ``traj`` (validated against the joints and limits); returns its :class:`Motion`.

        ``start_time`` (robot clock) schedules the start; in the past, the points that have
        elapsed are skipped. See :meth:`agentsdk.Robot.follow`.
        """
        ctl = self.loop
        if not isinstance(traj, Trajectory):
            raise InvalidValueError(f"expected a Trajectory, got {type(traj).__name__}")
        traj.validate(ctl.joints, allow_nonzero_velocity_at_end=bool(allow_nonzero_velocity_at_end))
        names = tuple(traj.joint_names)
        idx = np.array([ctl.index[n] for n in names], dtype=np.intp)
        for k, p in enumerate(traj.points):
            try:
                self.bounds.check(np.asarray(p.positions, dtype=float), idx)
            except LimitViolation as exc:
                raise LimitViolation(f"point {k}: {exc}") from None
        tol = tolerances if tolerances is not None else Tolerances()
        if not isinstance(tol, Tolerances):
            raise InvalidValueError(f"tolerances must be a Tolerances, got {type(tol).__name__}")
        path_tol = _per_joint(tol.path, names, "path")
        goal_tol = _per_joint(tol.goal, names, "goal")
        goal_time = float(tol.goal_time)
        now = ctl.stamp
        if start_time is None:
            t_start = now
        else:
            try:
                t_start = float(start_time)
            except (TypeError, ValueError):
                raise InvalidValueError(f"start_time must be a robot time in seconds, got {start_time!r}") from None
            if not math.isfinite(t_start):
                raise InvalidValueError(f"start_time must be a finite robot time in seconds, got {start_time!r}")
        if t_start < now:  # JTC: a start in the past skips what has elapsed
            traj = traj.after(now - t_start)
            t_start = now
        ex = _Exec(None, idx, None, t_start, path_tol, goal_tol, goal_time,
                   goal=np.asarray(traj.positions[-1], dtype=float).copy())
        ex.stretch = bool(stretch_to_limits)
        ex.end_moving = traj.velocities is not None and bool(np.any(traj.velocities[-1] != 0.0))
        wrap = self._table.continuous[idx]
        ex.wrap = wrap if wrap.any() else None
        if t_start > now:
            # scheduled: validated now against the state predicted for its start, again when it starts
            q0, v0, a0 = self._admission.predicted(idx, t_start)
            traj, _ = self._admission.prepare(ex, traj, q0, v0, a0, t_start)
            ex.pending_traj = traj
            ex.phase = MotionPhase.PENDING
            motion = Motion(self, idx, names, traj, t_start)
            ex.motion = motion
            self._drop_pending(idx, ResultCode.PREEMPTED, "preempted by a newer trajectory")
            self._executor.schedule(ex)
            scope.register(motion)
            return motion
        q0, v0, a0 = self.desired(idx)
        traj, sampler = self._admission.prepare(ex, traj, q0, v0, a0, t_start)
        motion = Motion(self, idx, names, traj, t_start)
        ex.motion = motion
        executor = self._executor
        executor.preempt_offloaded()
        executor.preempt(idx)
        self._drop_pending(idx, ResultCode.PREEMPTED, "preempted by a newer trajectory")
        self._admission.begin(ex, sampler, q0, v0, a0, t_start)
        executor.install(ex)
        executor.try_offload(ex, traj)
        scope.register(motion)
        return motion

    def move_to(self, positions: Mapping[str, float], duration: float | None, tol: Tolerances | None) -> Motion:
        """Plan a jerk-limited move from the current desired state to ``positions`` and follow it.

        Continuous joints take the shortest angle to the target.
        """
        ctl = self.loop
        if not isinstance(positions, Mapping) or not positions:
            raise InvalidValueError("move_to expects a non-empty {joint name: position} mapping")
        unknown = [n for n in positions if n not in ctl.index]
        if unknown:
            raise UnknownJointError(f"unknown joint {unknown[0]!r}; this robot's joints are: {', '.join(ctl.names)}")
        names = tuple(positions)
        idx = np.array([ctl.index[n] for n in names], dtype=np.intp)
        try:
            goal = np.array([float(positions[n]) for n in names])
        except (TypeError, ValueError):
            raise InvalidValueError(f"move_to: targets must be numbers, got {dict(positions)!r}") from None
        if not np.isfinite(goal).all():
            j = int(np.flatnonzero(~np.isfinite(goal))[0])
            raise InvalidValueError(
                f"move_to: non-finite target {format_value(goal[j])} for joint {names[j]!r}"
            )
        if duration is not None:
            try:
                duration = float(duration)
            except (TypeError, ValueError):
                raise InvalidValueError(f"move_to: duration must be a number of seconds, got {duration!r}") from None
        self.bounds.check(goal, idx)
        q0, v0, a0 = self.desired(idx)
        wrap = self._table.continuous[idx]
        if wrap.any():
            goal = goal + np.where(wrap, _turns_to(q0, goal), 0.0)
        joints = [ctl.joints[i] for i in idx.tolist()]
        traj = plan_point_to_point((q0, v0, a0), goal, joints, duration=duration)
        return self.follow(traj, tol)

    def _drop_pending(self, idx: np.ndarray, code: ResultCode, msg: str) -> None:
        for ex in list(self._table.pending):
            if np.intersect1d(ex.idx, idx).size:
                self._ownership.finish(ex, code, msg)

    async def stop_all_ramp(self, damp_only: bool = False, damping: float = 5.0, *,
                            from_reference: bool = False) -> None:
        """Decelerate every joint to rest (e-stop categories 1 and 2); returns when at rest.

        Running motions end ABORTED at once (their reference is dropped) and every joint
        stops from its measured state (or, where it tracks its setpoint within
        :data:`TRACKING_BAND`, from that setpoint), within its deceleration limit.
        ``from_reference`` (a sensor fault: the measurement is not to be trusted): every
        position-mode joint stops from its desired state, whatever the measurement says.
        ``damp_only`` (backends without position control): velocity mode at zero
        velocity with gain ``damping`` until every joint is still. The joints of a goal
        offloaded to the backend's controller (:mod:`agentsdk.offload`) are stopped by that
        controller: the goal is cancelled, its motion ends ABORTED with the controller's outcome,
        and their setpoint follows the measured position until they are still.
        """
        loop = self.loop
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        idx = np.arange(len(loop.joints))
        handle: HookHandle | None = None
        if damp_only:
            self.abort_all("stopped by the safety layer")
            loop.damp(idx, damping)

            def _until_still(t: float, st: StateView, sp: Setpoint) -> bool:
                if np.all(np.abs(st.velocity) < 1e-2) and not done.done():
                    done.set_result(None)
                return not done.done()

            handle = loop.add_hook(Phase.COMMAND, _until_still)
        else:
            # an offloaded goal's joints are stopped by the controller that runs it, from its own (current) state:
            # a ramp planned here would start from a state one feedback latency old and, once streamed, pull the
            # robot back to where this side thought it was. They stop as a cancel does (_update_remote): the goal
            # is cancelled, the setpoint follows the measured position until still, then holds there.
            remote = [ex for ex in self._records() if ex is not None and ex.remote is not None
                      and ex.phase != MotionPhase.PENDING]
            local = np.ones(len(idx), dtype=bool)
            for ex in remote:
                local[ex.idx] = False
            idx = idx[local]
            waiting: set[object] = set()

            def _ended(key: object) -> Callable[[], None]:
                def _cb() -> None:
                    waiting.discard(key)
                    if not waiting and not done.done():
                        done.set_result(None)
                return _cb

            q, v, a = self.desired(idx)
            if from_reference:
                q0, v0, a0, meas = q, v, a, np.zeros(len(idx), dtype=bool)
            else:
                q0, v0, a0, meas = self._stops.stop_start(idx, q, v, a, None)
            for rec in self._records():
                if rec is not None and not any(rec is r for r in remote):
                    self._ownership.finish(rec, ResultCode.ABORTED, "stopped by the safety layer")
            for ex in remote:
                waiting.add(ex)
                ex.on_done = _chain(ex.on_done, _ended(ex))
                if ex.remote_rest >= 0.0:
                    continue  # the goal has ended (its motion has its result): the joints come to rest
                if ex.phase == MotionPhase.STOPPING:  # already cancelled: the stop decides the result
                    ex.stop_code, ex.stop_msg = ResultCode.ABORTED, "stopped by the safety layer"
                else:  # the goal still runs: cancelled, its motion ends ABORTED with the controller's outcome
                    rq, rv, ra = self._ownership.desired_next(ex)
                    self._stops.begin_stop(ex, ResultCode.ABORTED, "stopped by the safety layer", loop.stamp,
                                           rq, rv, ra, measured=None)
            if meas.any() and self._guard is not None:
                self._guard.rebase(idx[meas], q0[meas])
            if len(idx) or not remote:
                ramp = object()
                waiting.add(ramp)
                self._executor.start_ramp(idx, q0, v0, a0, None, "", on_done=_ended(ramp))
        try:
            await done
        finally:
            if handle is not None:
                handle.remove()

    def abort_all(self, reason: str = "robot closed") -> None:
        """Resolve every motion ABORTED (no ramp: the caller takes over the joints)."""
        for ex in self._records():
            if ex is not None and ex.motion is not None:
                self._ownership.finish(ex, ResultCode.ABORTED, f"aborted: {reason}")

    def end_all(self, reason: str) -> None:
        """End every motion (ABORTED) and every stop ramp now, leaving the setpoint where it is.

        Used by ``reset()``: nothing may keep driving the joints over time afterwards.
        """
        for ex in self._records():
            if ex is not None:
                self._ownership.finish(ex, ResultCode.ABORTED if ex.motion is not None else None, f"aborted: {reason}")

    def fail_all(self, exc: BaseException) -> None:
        """Fail every motion with ``exc`` (the control loop died)."""
        for ex in self._records():
            if ex is None:
                continue
            self._ownership.release(ex)
            if ex.motion is not None:
                ex.motion._fail(exc)
            ex.phase = MotionPhase.DEAD

    def limiter_clipped(self, idx: np.ndarray, detail: str) -> None:
        """The safety layer's limiter had to clip the setpoint of joints ``idx`` that a motion drives.

        A planned motion is never clipped silently: the motion aborts (ABORTED) and stops from
        the measured state; a stop ramp that reaches a joint's bounds is reported once.
        """
        owner = self._table.owner
        for j in idx.tolist():
            ex = owner[j]
            if ex is None or ex.reported_clip:
                continue
            ex.reported_clip = True
            if self._guard is not None:
                self._guard.report("clip", detail, self.loop.names[j])
            if ex.phase in (MotionPhase.FOLLOW, MotionPhase.SETTLE):
                q, v, a = ex.des_q, ex.des_v, ex.des_a
                self._stops.abort(ex, ResultCode.ABORTED, f"aborted: {detail}", self.loop.stamp, q, v, a, None)

    def _records(self) -> list[_Exec | None]:
        """Every record that drives joints (once each, None among them) and every scheduled one."""
        return [*set(self._table.owner), *self._table.pending]


def _chain(first: Callable[[], None] | None, then: Callable[[], None]) -> Callable[[], None]:
    """``first`` (if any), then ``then``."""
    if first is None:
        return then

    def _both() -> None:
        first()
        then()
    return _both
