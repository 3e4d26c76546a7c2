"""Trajectory execution: the :class:`Motion` handle and the executor that runs inside the control tick.

Modelled on ros2_controllers' JointTrajectoryController (JTC) and the
FollowJointTrajectory action:

* ``robot.follow(traj)`` returns a :class:`Motion` at once; ``await motion``
  gives a :class:`MotionResult` whose code is named after FollowJointTrajectory
  (plus CANCELED, PREEMPTED, ABORTED).
* Validation like JTC, and on the whole motion: joint names, positions, velocities,
  accelerations of every point against the joints' limits; a last point at rest
  (unless ``allow_nonzero_velocity_at_end``); and the *interpolated* motion, including the
  segment from the current state, within the position, velocity and acceleration limits
  (or, with ``stretch_to_limits=True``, slowed down uniformly until it is).
* The executor samples the trajectory every control tick (no asyncio timers in
  the loop), so tracking is identical in lockstep and in real time.
* ``start_time`` schedules the start on the robot clock (JTC's ``header.stamp``); a
  start in the past skips the points that have elapsed.
* Speed scaling (:meth:`MotionManager.set_speed_scaling`, JTC's speed scaling, a UR
  teach pendant's speed slider): every running trajectory advances its own time at the
  factor, which each motion follows with a bounded rate, so velocities never jump.
* ``motion.cancel()`` -- or cancelling the task awaiting the motion, e.g. via
  ``asyncio.timeout`` -- decelerates every joint to rest within its deceleration
  limit (a jerk-limited ruckig profile from the current desired state), then
  holds position. Not an instant freeze, not a runaway.
* An *abort* (path or goal tolerance violated, a safety stop) drops the reference at once:
  every joint decelerates from its *measured* position and velocity (ruckig stop profile)
  and holds where it stopped. A joint whose servo tracks its setpoint within
  :data:`TRACKING_BAND` starts the stop from its setpoint instead: the same state up to
  servo accuracy, and a setpoint that neither jumps nor stalls.
* A new ``follow`` on overlapping joints preempts the running motion (PREEMPTED)
  and starts from its *desired* position, velocity and acceleration, so the
  desired velocity is continuous at the switch.
* ``continuous`` joints take the shortest angle from the current state (the trajectory is
  moved by whole turns) and their errors wrap around (tolerances, feedback, results).
"""

from __future__ import annotations

import asyncio
import dataclasses
import enum
import math
from collections.abc import AsyncIterator, Callable, Generator, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np

from . import scope
from .backend import ModeCode
from .config import format_value
from .errors import CommandRejected, ConfigurationError, InvalidValueError, LimitViolation, UnknownJointError
from .limits import STEP_RTOL as _STEP_RTOL
from .limits import PositionBounds, StepGuard, StepLimiter
from .loop import ControlLoop, HookHandle, Phase, Setpoint, StateView
from .offload import OffloadedGoal, OffloadRequest, TrajectoryOffload
from .trajectory import (
    MAX_TIME_FROM_START,
    Trajectory,
    TrajectorySampler,
    check_motion_limits,
    plan_point_to_point,
    plan_stop,
    time_scale_for_limits,
)

if TYPE_CHECKING:
    from .kinematics import Kinematics
    from .pose import Pose

__all__ = ["TRACKING_BAND", "Feedback", "Motion", "MotionResult", "ResultCode", "Tolerances"]

_POS = int(ModeCode.POSITION)  # a plain int: numpy compares arrays with an IntEnum member slowly
_TWO_PI = 2.0 * math.pi

#: (position rad or m, velocity rad/s or m/s): a joint whose measured state is this close to its
#: setpoint (plus the servo's lag ``kd/kp * |v|`` at speed) is tracking it; an abort then starts its
#: stop from the setpoint (the same state up to servo accuracy, no jump), else from the measured state
TRACKING_BAND = (0.02, 0.2)
#: fraction of max_acceleration the speed-scaling ramp may add to a trajectory's own acceleration
_SCALE_ACC_MARGIN = 0.95
_MAX_STRETCH_ITERATIONS = 12
#: the ``poses`` of a feedback message nobody asked link poses for (shared, immutable)
_NO_POSES: Mapping[str, Pose] = MappingProxyType({})
#: an ended offloaded goal's joints are at rest when their mean speed stays below this (rad/s or m/s) ...
_REMOTE_STILL_SPEED = 1e-2
#: ... for this long (s): then the setpoint holds there and the backend streams again
_REMOTE_STILL = 0.1
#: a planned position beyond the bounds by more than this is not float noise (rad or m)
_BOUND_TOL = 2e-6


class ResultCode(enum.IntEnum):
    """FollowJointTrajectory result codes, plus the outcomes of an action goal."""

    SUCCESSFUL = 0
    INVALID_GOAL = -1
    INVALID_JOINTS = -2
    #: a controller refused a goal stamped too far in the past (offloaded goals, :mod:`agentsdk.offload`)
    OLD_HEADER_TIMESTAMP = -3
    PATH_TOLERANCE_VIOLATED = -4
    GOAL_TOLERANCE_VIOLATED = -5
    #: motion.cancel() or the awaiting task was cancelled: decelerated and holding
    CANCELED = -10
    #: replaced by a newer follow() on overlapping joints
    PREEMPTED = -11
    #: stopped by the safety layer (e-stop, fault), the robot closing, or a setpoint step the
    #: position-step limiter would have had to clip
    ABORTED = -12


class MotionPhase(enum.Enum):
    """Where a running motion is in its life (internal bookkeeping, shown in debug logs)."""

    #: scheduled with a future ``start_time``: validated, waiting for its start
    PENDING = "pending"
    #: sampling its trajectory
    FOLLOW = "follow"
    #: the trajectory has ended; waiting for the goal tolerance within ``goal_time``
    SETTLE = "settle"
    #: decelerating to rest (cancel, preemption, abort, e-stop)
    STOPPING = "stopping"
    #: finished: its result is set and it writes nothing
    DEAD = "dead"


@dataclass(frozen=True, slots=True)
class MotionResult:
    """How a motion ended.

    A FollowJointTrajectory-style result code, the final error per joint, a message and the robot time.
    """

    code: ResultCode
    #: final position error per joint (desired goal - actual, wrapped for continuous joints), rad or m
    error: Mapping[str, float]
    message: str = ""
    #: robot time when the motion ended
    time: float = 0.0

    @property
    def ok(self) -> bool:
        """True when the motion ended SUCCESSFUL."""
        return self.code is ResultCode.SUCCESSFUL


def _check_tolerance_value(value: object, what: str) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InvalidValueError(f"{what} tolerance must be a number, got {value!r}") from None
    if not v > 0.0:  # NaN, zero and negatives
        raise InvalidValueError(f"{what} tolerance must be > 0 (math.inf: not checked), got {value!r}")
    return v


@dataclass(frozen=True, slots=True)
class Tolerances:
    """Per-joint tolerances (a float for all joints, or ``{joint: value}``), rad or m.

    ``path``: max ``|desired - actual|`` position error while moving (None: not checked).
    ``goal``: max ``|goal - actual|`` position error at the end (None: not checked).
    ``goal_time``: how long after the trajectory's end (in trajectory time, which speed
    scaling slows down) the goal tolerance may take to be met; 0 means no slack
    (``math.inf``: wait indefinitely). Values must be > 0 (``math.inf`` = not checked);
    NaN, zero or negative values raise :class:`InvalidValueError` here.
    Errors of ``continuous`` joints wrap around (shortest angle).
    """

    path: float | Mapping[str, float] | None = None
    goal: float | Mapping[str, float] | None = 0.02
    goal_time: float = 1.0

    def __post_init__(self) -> None:
        for what in ("path", "goal"):
            value = getattr(self, what)
            if value is None:
                continue
            if isinstance(value, Mapping):
                for name, v in value.items():
                    if not isinstance(name, str):
                        raise InvalidValueError(f"{what} tolerance: joint names must be strings, got {name!r}")
                    _check_tolerance_value(v, f"{what} ({name!r})")
            else:
                _check_tolerance_value(value, what)
        try:
            gt = float(self.goal_time)
        except (TypeError, ValueError):
            raise InvalidValueError(f"goal_time must be a number of seconds, got {self.goal_time!r}") from None
        if not gt >= 0.0:
            raise InvalidValueError(f"goal_time must be >= 0 s (math.inf: wait indefinitely), got {self.goal_time!r}")


@dataclass(frozen=True, slots=True)
class Feedback:
    """Like FollowJointTrajectory feedback: desired, actual and error at ``time``.

    ``poses`` and ``desired_poses`` hold the poses (root frame) of the links chosen with
    ``motion.feedback(links=...)``; empty when no links were chosen.
    """

    time: float
    joint_names: tuple[str, ...]
    desired_positions: np.ndarray
    desired_velocities: np.ndarray
    actual_positions: np.ndarray
    actual_velocities: np.ndarray
    #: desired - actual position (wrapped for continuous joints)
    error: np.ndarray
    #: 0.0 at the start, 1.0 at the end of the trajectory (in trajectory time)
    progress: float
    #: ``{link: Pose}`` of the chosen links at the measured state of ``time`` (all joints' measured
    #: positions), computed host-side by ``robot.kinematics``
    poses: Mapping[str, Pose] = field(default_factory=lambda: _NO_POSES)
    #: ``{link: Pose}`` of the chosen links with the motion's joints at their desired positions
    #: (the robot's other joints at their measured positions)
    desired_poses: Mapping[str, Pose] = field(default_factory=lambda: _NO_POSES)
    #: ``{sensor: reading}`` of the sensors chosen with ``motion.feedback(sensors=...)``, latest at ``time``
    sensors: Mapping[str, Any] = field(default_factory=lambda: _NO_POSES)


def _link_names(links: Sequence[str] | str) -> tuple[str, ...]:
    """``links`` as a tuple of names: one name, or a sequence of names."""
    if isinstance(links, str):
        return (links,)
    try:
        names = tuple(links)
    except TypeError:
        raise InvalidValueError(f"links must be a link name or a sequence of link names, got {links!r}") from None
    for link in names:
        if not isinstance(link, str):
            raise InvalidValueError(f"links must be link names (str), got {link!r}")
    return names


def _per_joint(value: float | Mapping[str, float] | None, names: tuple[str, ...], what: str) -> np.ndarray:
    if value is None:
        return np.full(len(names), np.inf)
    if isinstance(value, Mapping):
        unknown = set(value) - set(names)
        if unknown:
            raise UnknownJointError(f"{what} tolerance for joints not in the trajectory: {sorted(unknown)}")
        return np.array([_check_tolerance_value(value[n], f"{what} ({n!r})") if n in value else np.inf
                         for n in names])
    return np.full(len(names), _check_tolerance_value(value, what))


def _wrap_angle(x: np.ndarray) -> np.ndarray:
    """``x`` wrapped into [-pi, pi) (shortest angular distance)."""
    return np.remainder(x + math.pi, _TWO_PI) - math.pi


def _turns_to(current: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Whole turns (multiples of 2*pi) to add to ``target`` so it is the nearest equivalent of ``current``.

    Like JTC's ``wraparound_joint`` (angles::shortest_angular_distance): at exactly half a turn
    the joint turns in the direction of the target's raw value.
    """
    dist = _wrap_angle(target - current)
    half = np.abs(np.abs(dist) - math.pi) < 1e-9
    dist = np.where(half, np.where(target > current, np.abs(dist), -np.abs(dist)), dist)
    turns: np.ndarray = np.round(((current + dist) - target) / _TWO_PI) * _TWO_PI
    return turns


class Motion:
    """Handle of a running (or scheduled) trajectory. Awaitable; ``cancel()``; ``feedback()``."""

    def __init__(self, manager: MotionManager, idx: np.ndarray, names: tuple[str, ...],
                 trajectory: Trajectory, start_time: float) -> None:
        self._mgr = manager
        self.idx = idx
        self.joint_names = names
        #: the trajectory as executed: points already elapsed at a past ``start_time`` dropped,
        #: continuous joints moved by whole turns, stretched if ``stretch_to_limits`` slowed it
        self.trajectory = trajectory
        #: robot time at which the trajectory starts (``time_from_start`` is relative to it)
        self.start_time = start_time
        self._future: asyncio.Future[MotionResult] = asyncio.get_running_loop().create_future()
        #: the executor's latest tick (references to its buffers; frozen when the motion ends)
        self._snap: _FeedbackSnapshot | None = None
        self._fb: Feedback | None = None
        self._fb_seq = -1
        #: measured positions of every joint at the latest tick, kept only while a feedback
        #: stream with link poses runs (``_pose_streams > 0``)
        self._feedback_q: np.ndarray | None = None
        self._pose_streams = 0
        self._cancel_requested = False

    @property
    def _feedback(self) -> Feedback | None:
        """The latest tick's :class:`Feedback`, built when read (the tick itself allocates nothing)."""
        snap = self._snap
        if snap is None:
            return None
        if self._fb is None or self._fb_seq != snap.seq:
            self._fb = snap.feedback(self.joint_names)
            self._fb_seq = snap.seq
        return self._fb

    # the executor's side: it resolves and publishes only through these ----------
    def _settle(self, result: MotionResult | None) -> None:
        """End with ``result`` (the first result wins; later ones are ignored); freeze the feedback."""
        if self._snap is not None:
            self._snap.freeze()
        if result is not None and not self._future.done():
            self._future.set_result(result)

    def _fail(self, exc: BaseException) -> None:
        """End with the backend's failure ``exc`` (re-raised where the motion is awaited)."""
        if not self._future.done():
            self._future.set_exception(exc)
            self._future.exception()  # mark retrieved: the awaiting side re-raises it

    def _publish(self) -> _FeedbackSnapshot:
        """The snapshot the executor fills each tick (made on the first tick, reused after)."""
        snap = self._snap
        if snap is None:
            snap = self._snap = _FeedbackSnapshot()
        return snap

    def _keep_measured(self, position: np.ndarray) -> None:
        """Keep the measured positions of this tick while a feedback stream wants link poses."""
        self._feedback_q = position.copy() if self._pose_streams else None

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
        """Decelerate to rest within the joints' limits, then hold. Result: CANCELED.

        A motion whose scheduled start has not come yet ends at once (nothing moved).
        Idempotent; never raises.
        """
        if self._future.done() or self._cancel_requested:
            return
        self._cancel_requested = True
        self._mgr._request_stop(self, ResultCode.CANCELED, "canceled")

    def stop_early(self, reason: str) -> None:
        """End SUCCESSFUL before the goal (a guarded move's condition held): decelerate within the limits, hold.

        Idempotent; never raises. See :mod:`agentsdk.sensors`.
        """
        if self._future.done() or self._cancel_requested:
            return
        self._cancel_requested = True
        self._mgr._request_stop(self, ResultCode.SUCCESSFUL, reason)

    def feedback(
        self, rate: float = 50.0, *, links: Sequence[str] | str = (), sensors: Sequence[str] | str = ()
    ) -> AsyncIterator[Feedback]:
        """Yield feedback at ``rate`` Hz of robot time until the motion ends (the last one included).

        ``links`` (a link name or a sequence of them, e.g. ``("tool0",)``) adds their poses to
        every message: :attr:`Feedback.poses` at the measured state of the message's ``time``
        and :attr:`Feedback.desired_poses` at the desired positions, computed host-side by
        ``robot.kinematics`` (the same on every backend). Checked here, at the call: a bad
        rate raises :class:`~agentsdk.errors.InvalidValueError`, an unknown link
        :class:`~agentsdk.errors.UnknownLinkError` naming it and listing the robot's links.
        ``sensors`` adds the latest readings of those sensors (:attr:`Feedback.sensors`).
        """
        if not (rate > 0 and math.isfinite(rate)):
            raise InvalidValueError(f"feedback rate must be a positive number of Hz, got {format_value(rate)}")
        names = _link_names(links)
        kin: Kinematics | None = None
        if names:
            kin = self._mgr.kinematics()
            for link in names:
                kin.body_id(link)  # UnknownLinkError naming the link and the valid ones
        stream = self._feedback_stream(1.0 / rate, names, kin)
        chosen = (sensors,) if isinstance(sensors, str) else tuple(sensors)
        if not chosen:
            return stream
        source = self._mgr.sensors_source
        if source is None:
            raise InvalidValueError("this robot has no sensors to add to motion feedback")
        robot_sensors = source()
        for name in chosen:
            robot_sensors[name]  # UnknownSensorError naming it and the robot's sensors
        return _with_sensors(stream, robot_sensors, chosen)

    async def _feedback_stream(
        self, period: float, links: tuple[str, ...], kin: Kinematics | None
    ) -> AsyncIterator[Feedback]:
        clock = self._mgr.loop.clock
        next_t = clock.now()
        last: Feedback | None = None
        if kin is not None:
            self._pose_streams += 1  # from now on every tick keeps the full measured state
        try:
            while True:
                fb = self._feedback
                if fb is not None and fb is not last:
                    if kin is None:
                        last = fb
                        yield fb
                    else:
                        q = self._feedback_q
                        if q is not None or self._future.done():
                            last = fb
                            yield self._with_poses(fb, q, links, kin)
                        # else: published before this stream asked for the full state; the next tick's will do
                if self._future.done():
                    return
                next_t += period
                await clock.sleep_until(next_t)
        finally:
            if kin is not None:
                self._pose_streams -= 1

    def _with_poses(self, fb: Feedback, q: np.ndarray | None, links: tuple[str, ...], kin: Kinematics) -> Feedback:
        """``fb`` plus the poses of ``links`` at its measured state and at its desired positions."""
        if q is None:
            # the motion ended before a tick kept the full state: its own joints as measured at
            # fb.time, the others (not driven by it) as measured now
            q = self._mgr.loop.snapshot().position.copy()
            q[self.idx] = fb.actual_positions
        qd = q.copy()
        qd[self.idx] = fb.desired_positions
        poses = MappingProxyType({link: kin.fk(link, q) for link in links})
        desired = MappingProxyType({link: kin.fk(link, qd) for link in links})
        return dataclasses.replace(fb, poses=poses, desired_poses=desired)

    def __repr__(self) -> str:
        state = self._future.result().code.name if self._future.done() else "running"
        return f"<Motion {list(self.joint_names)} {state}>"


async def _with_sensors(
    stream: AsyncIterator[Feedback], sensors: Any, names: tuple[str, ...]
) -> AsyncIterator[Feedback]:
    async for fb in stream:
        yield dataclasses.replace(fb, sensors=sensors.snapshot(names))


class _FeedbackSnapshot:
    """What the executor wrote in its last tick for one motion: references to its tick buffers.

    :class:`Feedback` is built from it only when someone reads it; :meth:`freeze` copies the
    arrays when the motion ends (the executor may reuse its buffers for a stop afterwards).
    """

    __slots__ = ("actual_q", "actual_v", "err", "progress", "q", "seq", "time", "v")

    def __init__(self) -> None:
        self.seq = 0
        self.time = 0.0
        self.progress = 0.0
        self.q = self.v = self.actual_q = self.actual_v = self.err = np.zeros(0)

    def freeze(self) -> None:
        self.q, self.v, self.err = self.q.copy(), self.v.copy(), self.err.copy()
        self.actual_q, self.actual_v = self.actual_q.copy(), self.actual_v.copy()

    def feedback(self, names: tuple[str, ...]) -> Feedback:
        return Feedback(self.time, names, self.q.copy(), self.v.copy(), self.actual_q.copy(), self.actual_v.copy(),
                        self.err.copy(), self.progress)


class _TickBuffers:
    """Preallocated arrays of one executor's tick path (a tick allocates no arrays)."""

    __slots__ = (
        "a",
        "act",
        "actual",
        "actual_v",
        "at",
        "bound",
        "dev",
        "err",
        "gain",
        "mask",
        "o",
        "out",
        "q",
        "sample",
        "sel",
        "sp_views",
        "st_views",
        "tmp",
        "v",
        "vt",
    )

    def __init__(self, n: int) -> None:
        self.sample = np.zeros((3, n))
        # row views made once (a view is a Python object: making them per tick would allocate)
        self.q, self.vt, self.at = self.sample[0], self.sample[1], self.sample[2]
        self.v, self.a, self.err, self.actual, self.out = (np.zeros(n) for _ in range(5))
        self.tmp, self.o, self.dev, self.gain, self.act, self.actual_v = (np.zeros(n) for _ in range(6))
        self.mask = np.zeros(n, dtype=bool)
        #: the joints as a slice when they are consecutive, else their index array
        self.sel: Any = None
        #: views of the setpoint, state and limiter arrays made once (basic indexing makes a view each
        #: time), for the (setpoint, state, origin) objects they were made from
        self.bound: tuple[Any, Any, Any] | None = None
        self.sp_views: tuple[np.ndarray, ...] = ()
        self.st_views: tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None] = (None, None, None)

    def selection(self, idx: np.ndarray) -> Any:
        """The joints ``idx`` as a slice when they are consecutive (basic indexing is ~4x cheaper), else ``idx``."""
        if self.sel is None:
            n = len(idx)
            start = int(idx[0]) if n else 0
            consecutive = n > 0 and bool(np.array_equal(idx, np.arange(start, start + n)))
            self.sel = slice(start, start + n) if consecutive else idx
        return self.sel

    def bind(self, idx: np.ndarray, sp: Setpoint, st: StateView, origin: np.ndarray | None, loop: ControlLoop) -> None:
        """Make the views of consecutive joints ``idx`` into ``sp``, ``st``, ``origin`` and the loop's gains."""
        sel = self.selection(idx)
        self.bound = (sp, st, origin)
        if isinstance(sel, slice):
            self.sp_views = (sp.mode[sel], sp.enabled[sel], sp.position[sel], sp.velocity[sel], sp.effort[sel],
                             sp.kp[sel], sp.kd[sel], sp.target[sel], loop.gain_p[sel], loop.gain_d[sel],
                             sp.acceleration[sel])
            self.st_views = (st.position[sel], st.velocity[sel], None if origin is None else origin[sel])
        else:
            self.sp_views = ()
            self.st_views = (None, None, None)


def _wrap_into(x: np.ndarray, wrap: np.ndarray, tmp: np.ndarray) -> None:
    """``x[wrap] = _wrap_angle(x[wrap])`` in place (the same arithmetic, no allocation)."""
    np.add(x, math.pi, out=tmp)
    np.remainder(tmp, _TWO_PI, out=tmp)
    np.subtract(tmp, math.pi, out=tmp)
    np.copyto(x, tmp, where=wrap)


@dataclass(eq=False)
class _Exec:
    """Executor state of one motion or stop ramp (lives in the control tick)."""

    motion: Motion | None
    idx: np.ndarray
    sampler: Any
    #: robot time the trajectory (or stop ramp) starts
    t0: float
    path_tol: np.ndarray
    goal_tol: np.ndarray
    goal_time: float
    goal: np.ndarray
    phase: MotionPhase = MotionPhase.FOLLOW
    stop_code: ResultCode | None = None
    stop_msg: str = ""
    des_q: np.ndarray = field(default_factory=lambda: np.zeros(0))
    des_v: np.ndarray = field(default_factory=lambda: np.zeros(0))
    des_a: np.ndarray = field(default_factory=lambda: np.zeros(0))
    on_done: Any = None
    #: sample time of the trajectory (advances at the speed scaling factor), and the last tick's time
    tau: float = 0.0
    t_last: float = 0.0
    #: speed scaling actually applied, and its rate (1/s)
    s: float = 1.0
    sdot: float = 0.0
    #: trajectory-time velocity and acceleration at ``tau`` (for the scaling ramp's bound)
    vt: np.ndarray = field(default_factory=lambda: np.zeros(0))
    at: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: continuous joints of this motion (errors wrap around), or None
    wrap: np.ndarray | None = None
    #: the trajectory to start at ``t0`` (pending motions), its tolerance options
    pending_traj: Trajectory | None = None
    stretch: bool = False
    #: the trajectory ends moving (allow_nonzero_velocity_at_end): decelerate after the end
    end_moving: bool = False
    reported_clip: bool = False
    #: the safety limiter of its joints (:meth:`StepLimiter.select`), made on the first tick
    limits: StepLimiter | None = None
    #: its joints as a slice when they are consecutive (basic indexing: ~4x cheaper than ``idx`` per write)
    sel: Any = None
    #: the tick path's preallocated arrays (made on the first tick)
    work: _TickBuffers | None = None
    #: the goal the backend's own controller runs instead (:mod:`agentsdk.offload`), and its desired state
    remote: OffloadedGoal | None = None
    remote_q: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: robot time since which the joints of an ended offloaded goal are still (-1: the goal runs)
    remote_rest: float = -1.0
    remote_v: np.ndarray = field(default_factory=lambda: np.zeros(0))


class MotionManager:
    """Owns the running motions of one robot; one executor per motion, run in the control tick."""

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
        wrap = self._continuous[idx]
        ex.wrap = wrap if wrap.any() else None
        if t_start > now:
            # scheduled: validated now against the state predicted for its start, again when it starts
            q0, v0, a0 = self._predicted(idx, t_start)
            traj, _ = self._prepare(ex, traj, q0, v0, a0, t_start)
            ex.pending_traj = traj
            ex.phase = MotionPhase.PENDING
            motion = Motion(self, idx, names, traj, t_start)
            ex.motion = motion
            self._drop_pending(idx, ResultCode.PREEMPTED, "preempted by a newer trajectory")
            self._pending.append(ex)
            self.loop.add_hook(Phase.COMMAND, lambda t, st, sp, ex=ex: self._update(ex, t, st, sp))
            scope.register(motion)
            return motion
        q0, v0, a0 = self.desired(idx)
        traj, sampler = self._prepare(ex, traj, q0, v0, a0, t_start)
        motion = Motion(self, idx, names, traj, t_start)
        ex.motion = motion
        self._preempt_offloaded()
        self._preempt(idx)
        self._drop_pending(idx, ResultCode.PREEMPTED, "preempted by a newer trajectory")
        self._begin(ex, sampler, q0, v0, a0, t_start)
        self._install(ex)
        self._try_offload(ex, traj)
        scope.register(motion)
        return motion

    def _prepare(
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
        vmax, amax = self._vmax[idx], self._amax[idx]
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

    def _predicted(self, idx: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Desired (q, v, a) of joints ``idx`` at robot time ``t``, if nothing changes meanwhile."""
        q, v, a = self.desired(idx)
        for k, j in enumerate(idx.tolist()):
            ex = self._owner[j]
            if ex is not None and ex.sampler is not None and ex.remote_rest < 0.0:
                m = int(np.flatnonzero(ex.idx == j)[0])
                tau = t if ex.phase == MotionPhase.STOPPING else ex.tau + ex.s * (t - ex.t_last)
                eq, ev, ea = ex.sampler.sample(tau)
                s = 1.0 if ex.phase == MotionPhase.STOPPING else ex.s
                q[k], v[k], a[k] = eq[m], ev[m] * s, ea[m] * s * s
        return q, v, a

    def _begin(self, ex: _Exec, sampler: TrajectorySampler, q0: np.ndarray, v0: np.ndarray, a0: np.ndarray,
               t0: float) -> None:
        """Make ``ex`` follow ``sampler`` from time ``t0`` (the desired state there is (q0, v0, a0))."""
        ex.sampler = sampler
        ex.t0 = ex.tau = ex.t_last = t0
        ex.phase = MotionPhase.FOLLOW
        # the trajectory's velocities are in its own time: start at full speed when the start state
        # moves (no velocity jump), else directly at the current scaling (a paused robot stays put)
        ex.s = 1.0 if np.any(np.abs(v0) > 1e-9) else self._speed
        ex.sdot = 0.0
        ex.des_q, ex.des_v, ex.des_a = q0.copy(), v0.copy(), a0.copy()
        ex.vt, ex.at = v0.copy(), a0.copy()

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
        wrap = self._continuous[idx]
        if wrap.any():
            goal = goal + np.where(wrap, _turns_to(q0, goal), 0.0)
        joints = [ctl.joints[i] for i in idx.tolist()]
        traj = plan_point_to_point((q0, v0, a0), goal, joints, duration=duration)
        return self.follow(traj, tol)

    # ------------------------------------------------------------ offload (agentsdk.offload)
    def _try_offload(self, ex: _Exec, traj: Trajectory) -> None:
        """Hand ``ex``'s validated trajectory to the backend's controller as one goal, where it can take it.

        Only a motion that alone drives the robot (the other joints hold) and ends at rest is
        offloaded; the executor then keeps sampling it locally (limits, setpoint) while the
        backend streams nothing, and the controller's outcome ends it (:meth:`_update_remote`).
        """
        if self._offload is None or ex.motion is None or ex.end_moving:
            return
        if any(o is not None and o is not ex for o in self._owner):
            return  # another motion or stop ramp drives joints: streamed
        names, sp = self.loop.names, self.loop.setpoint
        others = np.ones(len(names), dtype=bool)
        others[ex.idx] = False
        hold = MappingProxyType({names[j]: float(sp.position[j]) for j in np.flatnonzero(others).tolist()})
        remote = self._offload.offload_trajectory(
            OffloadRequest(traj, ex.path_tol.copy(), ex.goal_tol.copy(), ex.goal_time, hold))
        if remote is None:
            return
        ex.remote, ex.s, ex.sdot = remote, 1.0, 0.0
        ex.remote_q, ex.remote_v = np.zeros(len(ex.idx)), np.zeros(len(ex.idx))

    def _preempt_offloaded(self) -> None:
        """A new motion on any joint preempts an offloaded goal (the controller runs one trajectory at a time)."""
        for ex in [o for o in dict.fromkeys(self._owner) if o is not None and o.remote is not None]:
            if ex.remote_rest >= 0.0:  # its goal has ended: the joints hold where the setpoint is
                self._finish(ex, None, "")
                continue
            q, v, a = self._desired_next(ex)
            self._finish(ex, ResultCode.PREEMPTED, "preempted by a newer trajectory")
            self._start_ramp(ex.idx, q, v, a, None, "")

    def _update_remote(self, ex: _Exec, remote: OffloadedGoal, t: float, st: StateView, sp: Setpoint,
                       q: np.ndarray, v: np.ndarray, a: np.ndarray, err: np.ndarray, elapsed: float) -> bool:
        """One tick of an offloaded motion: follow the local sample (not streamed) until the controller's outcome.

        Success: the local sample runs to its end (the goal), then the joints hold there. Any other
        outcome (or a cancel asked here): the motion's result is known at once; the controller stops
        the robot itself, and the setpoint follows the measured position (nothing streamed) until
        the joints have been still for :data:`_REMOTE_STILL` s, then holds there and streaming resumes.
        """
        outcome = remote.outcome(t)
        if ex.remote_rest >= 0.0:  # the goal ended: wait for the controller's own stop to come to rest
            return self._follow_remote_stop(ex, t, st, sp)
        if outcome is not None:
            try:
                code = ResultCode(outcome[0])
            except ValueError:
                code = ResultCode.ABORTED
            msg = outcome[1]
            if ex.phase == MotionPhase.STOPPING and ex.stop_code is not None:
                code, msg = ex.stop_code, ex.stop_msg  # asked here (cancel, abort, stop_early): that is the result
            elif code is ResultCode.SUCCESSFUL:
                if elapsed >= ex.sampler.duration:
                    qc = self._limited(ex, q, v, a)
                    if qc is None:
                        return self._write_stop(ex, t, st, sp)
                    self._write(ex, t, st, sp, qc, v, a, err)
                    self._finish(ex, ResultCode.SUCCESSFUL, msg)
                    self.loop.hold_at(ex.idx, qc)
                    return False
                outcome = None  # reached early: the local sample catches up before the motion ends
            if outcome is not None:
                self._resolve(ex, code, msg)
                ex.motion = None
                ex.phase = MotionPhase.STOPPING
                ex.remote_rest = t
                return self._follow_remote_stop(ex, t, st, sp)
        if ex.phase == MotionPhase.FOLLOW and elapsed >= ex.sampler.duration:
            ex.phase = MotionPhase.SETTLE  # the controller's goal tolerance and goal time decide
        qc = self._limited(ex, q, v, a)
        if qc is None:
            return self._write_stop(ex, t, st, sp)
        self._write(ex, t, st, sp, qc, v, a, err)
        return True

    def _follow_remote_stop(self, ex: _Exec, t: float, st: StateView, sp: Setpoint) -> bool:
        """The setpoint of an ended offloaded goal's joints is their measured position until they are still."""
        idx = ex.idx
        n = len(idx)
        w = ex.work
        if w is None:
            w = ex.work = _TickBuffers(n)
        qm = np.take(st.position, idx, out=w.actual, mode="clip")
        if np.count_nonzero(np.isfinite(qm, out=w.mask)) != n:
            np.copyto(qm, ex.des_q)  # a failing sensor: hold the last setpoint
        # still: the measured position stays within _REMOTE_STILL_SPEED * _REMOTE_STILL of where the window
        # began (a velocity is not needed: some controllers report none, and encoder noise stays well below)
        ref = ex.remote_q  # no feedback is published any more (the motion has its result): free buffers
        if ex.remote_rest == t:
            ref[...] = qm
        moved = float(np.abs(np.subtract(qm, ref, out=w.dev), out=w.dev).max(initial=0.0))
        zero = ex.remote_v
        zero.fill(0.0)
        qc = self._limited(ex, qm, zero, zero)
        assert qc is not None  # a stopping executor is limited, never aborted
        err = np.subtract(qm, qc, out=w.err)
        # ... and the setpoint has reached it (the step limiter moves it at most max_position_step a tick)
        if (moved > _REMOTE_STILL_SPEED * _REMOTE_STILL
                or float(np.abs(err, out=w.tmp).max(initial=0.0)) > 1e-9):
            ex.remote_rest = t
            ref[...] = qm
        self._write(ex, t, st, sp, qc, zero, zero, err)
        if t - ex.remote_rest >= _REMOTE_STILL:
            self._finish(ex, None, "")
            self.loop.hold_at(idx, qc)
            return False
        return True

    def _install(self, ex: _Exec) -> None:
        for j in ex.idx.tolist():
            self._owner[j] = ex
        self.owned_mask[ex.idx] = True
        self.loop.add_hook(Phase.COMMAND, lambda t, st, sp, ex=ex: self._update(ex, t, st, sp))

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

    def _preempt(self, idx: np.ndarray) -> None:
        seen: list[_Exec] = []
        for j in idx.tolist():
            ex = self._owner[j]
            if ex is not None and ex not in seen:
                seen.append(ex)
        taken = set(idx.tolist())
        for ex in seen:
            rest = np.array([j for j in ex.idx.tolist() if j not in taken], dtype=np.intp)
            q, v, a = self.desired(rest) if len(rest) else (None, None, None)
            self._finish(ex, ResultCode.PREEMPTED, "preempted by a newer trajectory")
            if len(rest):
                # joints the new trajectory does not cover come to rest smoothly
                self._start_ramp(rest, q, v, a, None, "")

    def _drop_pending(self, idx: np.ndarray, code: ResultCode, msg: str) -> None:
        for ex in list(self._pending):
            if np.intersect1d(ex.idx, idx).size:
                self._finish(ex, code, msg)

    # ----------------------------------------------------------- stopping
    def _request_stop(self, motion: Motion, code: ResultCode, msg: str) -> None:
        for ex in list(self._pending):
            if ex.motion is motion:
                self._finish(ex, code, f"{msg} before its scheduled start")
                return
        for owner in set(self._owner):
            if owner is not None and owner.motion is motion:
                # cancel: from the current desired state (the robot tracks it; a smooth stop)
                q, v, a = self._desired_next(owner)
                self._begin_stop(owner, code, msg, self.loop.stamp, q, v, a, measured=None)
                return

    def _stop_start(
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
        wrap = self._continuous[idx]
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
        vmax = self._vmax[idx]
        q0 = np.where(meas, np.clip(q - dq, self.bounds.lo[idx], self.bounds.hi[idx]), q)
        v0 = np.where(meas, np.clip(vm, -vmax, vmax), v)
        a0 = np.where(meas, 0.0, a)
        return q0, v0, a0, meas

    def _plan_stop_sampler(self, idx: np.ndarray, q: np.ndarray, v: np.ndarray, a: np.ndarray,
                           t0: float) -> TrajectorySampler:
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

    def _begin_stop(self, ex: _Exec, code: ResultCode | None, msg: str, t0: float, q: np.ndarray, v: np.ndarray,
                    a: np.ndarray, measured: np.ndarray | None) -> None:
        """Replace ``ex``'s reference by a stop ramp from (q, v, a) at ``t0``; ``measured`` marks the joints
        whose reference was reset to their measured state (the limiter is told).
        """
        if ex.phase in (MotionPhase.STOPPING, MotionPhase.DEAD):
            return
        if ex.remote is not None:
            ex.remote.cancel()  # the controller stops its goal; its outcome ends the motion (_update_remote)
        if measured is not None and measured.any() and self._guard is not None:
            self._guard.rebase(ex.idx[measured], q[measured])
        ex.sampler = self._plan_stop_sampler(ex.idx, q, v, a, t0)
        ex.t0 = ex.tau = ex.t_last = t0
        ex.s, ex.sdot = 1.0, 0.0
        ex.phase = MotionPhase.STOPPING
        ex.stop_code = code
        ex.stop_msg = msg

    def _abort(self, ex: _Exec, code: ResultCode, msg: str, t: float, q: np.ndarray, v: np.ndarray,
               a: np.ndarray, force: np.ndarray | None) -> None:
        """Abort ``ex`` in the tick at ``t``: drop its reference, stop from the measured state, hold."""
        q0, v0, a0, meas = self._stop_start(ex.idx, q, v, a, force)
        self._begin_stop(ex, code, msg, t, q0, v0, a0, meas)

    def _start_ramp(self, idx: np.ndarray, q: Any, v: Any, a: Any, code: ResultCode | None, msg: str,
                    on_done: Any = None) -> _Exec:
        t0 = self.loop.stamp
        sampler = self._plan_stop_sampler(idx, q, v, a, t0)
        n = len(idx)
        ex = _Exec(None, idx, sampler, t0, np.full(n, np.inf), np.full(n, np.inf), 0.0, goal=q.copy(),
                   phase=MotionPhase.STOPPING, stop_code=code, stop_msg=msg, on_done=on_done)
        ex.tau = ex.t_last = t0
        ex.des_q, ex.des_v, ex.des_a = q.copy(), v.copy(), a.copy()
        self._install(ex)
        return ex

    async def stop_all_ramp(self, damp_only: bool = False, damping: float = 5.0, *,
                            from_reference: bool = False) -> None:
        """Decelerate every joint to rest (e-stop categories 1 and 2); returns when at rest.

        Running motions end ABORTED at once (their reference is dropped) and every joint
        stops from its measured state (or, where it tracks its setpoint within
        :data:`TRACKING_BAND`, from that setpoint), within its deceleration limit.
        ``from_reference`` (a sensor fault: the measurement is not to be trusted): every
        position-mode joint stops from its desired state, whatever the measurement says.
        ``damp_only`` (backends without position control): velocity mode at zero
        velocity with gain ``damping`` until every joint is still.
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
            q, v, a = self.desired(idx)
            if from_reference:
                q0, v0, a0, meas = q, v, a, np.zeros(len(idx), dtype=bool)
            else:
                q0, v0, a0, meas = self._stop_start(idx, q, v, a, None)
            for ex in [*set(self._owner), *self._pending]:
                if ex is not None:
                    self._finish(ex, ResultCode.ABORTED, "stopped by the safety layer")
            if meas.any() and self._guard is not None:
                self._guard.rebase(idx[meas], q0[meas])
            self._start_ramp(idx, q0, v0, a0, None, "", on_done=lambda: None if done.done() else done.set_result(None))
        try:
            await done
        finally:
            if handle is not None:
                handle.remove()

    def abort_all(self, reason: str = "robot closed") -> None:
        """Resolve every motion ABORTED (no ramp: the caller takes over the joints)."""
        for ex in [*set(self._owner), *self._pending]:
            if ex is not None and ex.motion is not None:
                self._finish(ex, ResultCode.ABORTED, f"aborted: {reason}")

    def end_all(self, reason: str) -> None:
        """End every motion (ABORTED) and every stop ramp now, leaving the setpoint where it is.

        Used by ``reset()``: nothing may keep driving the joints over time afterwards.
        """
        for ex in [*set(self._owner), *self._pending]:
            if ex is not None:
                self._finish(ex, ResultCode.ABORTED if ex.motion is not None else None, f"aborted: {reason}")

    def fail_all(self, exc: BaseException) -> None:
        """Fail every motion with ``exc`` (the control loop died)."""
        for ex in [*set(self._owner), *self._pending]:
            if ex is None:
                continue
            self._release(ex)
            if ex.motion is not None:
                ex.motion._fail(exc)
            ex.phase = MotionPhase.DEAD

    def limiter_clipped(self, idx: np.ndarray, detail: str) -> None:
        """The safety layer's limiter had to clip the setpoint of joints ``idx`` that a motion drives.

        A planned motion is never clipped silently: the motion aborts (ABORTED) and stops from
        the measured state; a stop ramp that reaches a joint's bounds is reported once.
        """
        for j in idx.tolist():
            ex = self._owner[j]
            if ex is None or ex.reported_clip:
                continue
            ex.reported_clip = True
            if self._guard is not None:
                self._guard.report("clip", detail, self.loop.names[j])
            if ex.phase in (MotionPhase.FOLLOW, MotionPhase.SETTLE):
                q, v, a = ex.des_q, ex.des_v, ex.des_a
                self._abort(ex, ResultCode.ABORTED, f"aborted: {detail}", self.loop.stamp, q, v, a, None)

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

    def _update(self, ex: _Exec, t: float, st: StateView, sp: Setpoint) -> bool:
        if ex.phase == MotionPhase.DEAD:
            return False
        if ex.phase == MotionPhase.PENDING:
            if t < ex.t0 - 1e-9:
                return True
            if not self._activate(ex, t):
                return False
        idx = ex.idx
        w = ex.work
        if w is None:
            w = ex.work = _TickBuffers(len(idx))
        remote = ex.remote
        if remote is not None and ex.remote_rest < 0.0 and not remote.started():
            ex.t_last = t  # the controller has not taken the goal yet: its trajectory time has not begun
        dt = t - ex.t_last
        s = ex.s
        if dt > 0.0 and s == self._speed and ex.phase != MotionPhase.STOPPING:  # _advance's common case, inline
            if dt > self.loop.period:
                dt = self.loop.period
            tau = ex.tau = ex.tau + s * dt
            sdot = ex.sdot = 0.0
        else:
            tau, s, sdot = self._advance(ex, t)
            ex.tau, ex.s, ex.sdot = tau, s, sdot
        ex.t_last = t
        ex.sampler.sample_into(tau, w.sample)
        q, vt, at = w.q, w.vt, w.at
        stopping = ex.phase == MotionPhase.STOPPING
        if stopping or (s == 1.0 and sdot == 0.0):
            v, a = vt, at
        else:  # v = vt * s, a = at * s^2 + vt * sdot
            v, a = w.v, w.a
            np.multiply(vt, s, out=v)
            np.multiply(at, s * s, out=a)
            np.multiply(vt, sdot, out=w.tmp)
            np.add(a, w.tmp, out=a)
        ex.vt, ex.at = vt, at
        bound = w.bound
        if bound is None or bound[0] is not sp or bound[1] is not st or bound[2] is not self._origin:
            w.bind(idx, sp, st, self._origin, self.loop)
        pos_view = w.st_views[0]
        actual = pos_view if pos_view is not None else np.take(st.position, idx, out=w.actual, mode="clip")
        err = np.subtract(q, actual, out=w.err)
        if ex.wrap is not None:
            _wrap_into(err, ex.wrap, w.tmp)
        m = ex.motion
        elapsed = tau - ex.t0
        if ex.remote is not None:
            return self._update_remote(ex, ex.remote, t, st, sp, q, v, a, err, elapsed)
        if ex.phase == MotionPhase.FOLLOW:
            np.less_equal(np.abs(err, out=w.tmp), ex.path_tol, out=w.mask)
            if np.count_nonzero(w.mask) != len(idx):
                over = ~w.mask
                k = int(np.argmax(over))
                name = m.joint_names[k] if m else str(k)
                self._abort(ex, ResultCode.PATH_TOLERANCE_VIOLATED,
                            f"path tolerance violated on joint {name!r}: error {err[k]:.4f} > {ex.path_tol[k]:.4f}",
                            t, q, v, a, over)
                return self._write_stop(ex, t, st, sp)
            if elapsed >= ex.sampler.duration:
                if ex.end_moving:  # ends moving (allow_nonzero_velocity_at_end): decelerate, then hold
                    self._begin_stop(ex, ResultCode.SUCCESSFUL, "ended moving; decelerated to rest", t, q, v, a,
                                     None)
                    return self._write_stop(ex, t, st, sp)
                ex.phase = MotionPhase.SETTLE
        qc = self._limited(ex, q, v, a)
        if qc is None:  # a step the limiter would have clipped: aborted
            return self._write_stop(ex, t, st, sp)
        if ex.phase == MotionPhase.SETTLE:
            gerr = np.subtract(ex.goal, actual, out=w.tmp)
            if ex.wrap is not None:
                _wrap_into(gerr, ex.wrap, w.dev)
            np.abs(gerr, out=gerr)
            if np.count_nonzero(np.less_equal(gerr, ex.goal_tol, out=w.mask)) == len(idx):
                self._write(ex, t, st, sp, qc, v, a, err)
                self._finish(ex, ResultCode.SUCCESSFUL, "")
                self.loop.hold_at(idx, qc)
                return False
            if elapsed >= ex.sampler.duration + ex.goal_time:
                bad = ~(gerr <= ex.goal_tol)
                k = int(np.argmax(gerr - ex.goal_tol))
                name = m.joint_names[k] if m else str(k)
                msg = f"goal tolerance violated on joint {name!r}: error {gerr[k]:.4f} > {ex.goal_tol[k]:.4f}"
                self._abort(ex, ResultCode.GOAL_TOLERANCE_VIOLATED, msg, t, q, v, a, bad)
                # like JTC the result is known now; the stop from the measured state carries on
                self._resolve(ex, ResultCode.GOAL_TOLERANCE_VIOLATED, msg)
                ex.motion = None
                return self._write_stop(ex, t, st, sp)
        elif stopping and elapsed >= ex.sampler.duration:
            self._write(ex, t, st, sp, qc, v, a, err)
            self._finish(ex, ex.stop_code, ex.stop_msg)
            self.loop.hold_at(idx, qc)
            return False
        self._write(ex, t, st, sp, qc, v, a, err)
        return True

    def _write_stop(self, ex: _Exec, t: float, st: StateView, sp: Setpoint) -> bool:
        """The reference was just replaced by a stop starting at ``t``: write its first sample."""
        q, v, a = ex.sampler.sample(t)
        ex.vt, ex.at = v, a
        err = q - st.position[ex.idx]
        if ex.wrap is not None:
            err = np.where(ex.wrap, _wrap_angle(err), err)
        qc = self._limited(ex, q, v, a)
        assert qc is not None  # only a FOLLOW sample aborts instead of being limited; this is a stop
        self._write(ex, t, st, sp, qc, v, a, err)
        if ex.sampler.duration <= 0.0:
            self._finish(ex, ex.stop_code, ex.stop_msg)
            self.loop.hold_at(ex.idx, qc)
            return False
        return True

    def _limited(self, ex: _Exec, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray | None:
        """``q`` through the safety layer's :class:`~agentsdk.limits.StepLimiter` (the same calls its filter makes).

        For a validated motion this only removes float noise (a plan exactly at the limits), so the
        filter never clips what a motion writes. A planned step beyond it (e.g. a first point at
        time 0 away from the robot) aborts the motion before anything is written (None is returned:
        the caller writes the stop instead); a stop ramp limited by more than noise (stopping a
        joint that moves towards its limit) is reported once. Never silent.
        """
        guard = self._guard
        lim = ex.limits
        if lim is None:
            lim = ex.limits = self._limiter.select(ex.idx)
        w = ex.work
        if w is None:
            w = ex.work = _TickBuffers(len(ex.idx))
        out = lim.clamp_bounds(q, w.out)
        what = ""
        if np.count_nonzero(np.not_equal(out, q, out=w.mask)) and float(np.max(np.abs(out - q))) > _BOUND_TOL:
            what = "bounds"
        step, step_tol = lim.step, lim.step_tol
        origin = self._origin
        if step is not None and step_tol is not None and origin is not None:
            o = w.st_views[2]
            if o is None or w.bound is None or w.bound[2] is not origin:
                o = np.take(origin, ex.idx, out=w.o, mode="clip")
            dev = np.abs(np.subtract(out, o, out=w.dev), out=w.dev)
            # beyond the limiter's window: float noise is clamped, more aborts
            if np.count_nonzero(np.greater(dev, step, out=w.mask)):
                if not what and (dev > step_tol).any():
                    what = "step"
                lim.clamp_step(out, o, out)
        if not what:
            return out
        lo, hi = lim.lo, lim.hi
        idx = ex.idx
        k = int(np.argmax(np.abs(out - q)))
        name = self.loop.names[int(idx[k])]
        if ex.phase == MotionPhase.FOLLOW:
            if what == "step":
                assert step is not None and origin is not None
                detail = (f"the planned setpoint of joint {name!r} steps {abs(q[k] - origin[idx[k]]):.4g} in one "
                          f"control period, more than max_position_step {step[k]:.4g}: the motion does not continue "
                          "from the current reference (e.g. a first point at time_from_start 0 away from the "
                          "robot); aborted, not clipped")
            else:
                detail = (f"the planned setpoint of joint {name!r} ({q[k]:.6g}) leaves its bounds "
                          f"[{lo[k]:.6g}, {hi[k]:.6g}]; aborted, not clipped")
            if guard is not None:
                guard.report(what, detail, name)
            bad = np.abs(out - q) > 0.0
            # the joints that would step stop from their measured state, the others from this sample
            self._abort(ex, ResultCode.ABORTED, f"aborted: {detail}", ex.t_last, q, v, a, bad)
            return None
        if not ex.reported_clip:
            ex.reported_clip = True
            if guard is not None:
                kind = "stop ramp" if ex.phase is MotionPhase.STOPPING else "motion"
                guard.report("clip", f"the {kind} of joint {name!r} "
                             f"was limited by {abs(out[k] - q[k]):.4g} ({what}: position bounds or "
                             "max_position_step)", name)
        return out

    def _write(self, ex: _Exec, t: float, st: StateView, sp: Setpoint, qc: np.ndarray, v: np.ndarray,
               a: np.ndarray, err: np.ndarray) -> None:
        """Write the (already limited) reference ``qc``/``v`` of ``ex``'s joints; publish its feedback."""
        idx = ex.idx
        loop = self.loop
        ex.des_q, ex.des_v, ex.des_a = qc, v, a
        w = ex.work
        if w is None:
            w = ex.work = _TickBuffers(len(idx))
        bound = w.bound
        if bound is None or bound[0] is not sp or bound[1] is not st:
            w.bind(idx, sp, st, self._origin, loop)
        sel = ex.sel = w.sel
        if w.sp_views:  # consecutive joints, through views made once (basic indexing makes a view per write)
            mode, enabled, position, velocity, effort, kp, kd, target, gain_p, gain_d, acceleration = w.sp_views
            mode.fill(_POS)
            enabled.fill(True)
            position[...] = qc
            velocity[...] = v
            acceleration[...] = a  # the servo law's inverse-dynamics feed-forward
            effort.fill(0.0)
            kp[...] = gain_p
            kd[...] = gain_d
            target[...] = qc
        else:
            sp.mode[sel] = _POS
            sp.enabled[sel] = True
            sp.position[sel] = qc
            sp.velocity[sel] = v
            sp.acceleration[sel] = a
            sp.effort[sel] = 0.0
            sp.kp[sel] = np.take(loop.gain_p, sel, out=w.gain, mode="clip")
            sp.kd[sel] = np.take(loop.gain_d, sel, out=w.gain, mode="clip")
            sp.target[sel] = qc
        m = ex.motion
        if m is not None:
            # the feedback of this tick, by reference (a Feedback is built only when someone reads it)
            snap = m._publish()
            if ex.phase != MotionPhase.STOPPING:  # a stop ramp is no progress along the trajectory: keep the last
                dur = ex.sampler.duration
                snap.progress = min(1.0, (ex.tau - ex.t0) / dur) if dur > 0 else 1.0
            snap.time = t
            snap.q, snap.v, snap.err = qc, v, err
            pos_view, vel_view, _ = w.st_views
            if pos_view is not None and vel_view is not None:
                w.act[...] = pos_view
                w.actual_v[...] = vel_view
            else:
                np.take(st.position, idx, out=w.act, mode="clip")
                np.take(st.velocity, idx, out=w.actual_v, mode="clip")
            snap.actual_q, snap.actual_v = w.act, w.actual_v
            remote = ex.remote
            if remote is not None and remote.desired_into(ex.remote_q, ex.remote_v):
                # an offloaded goal: the desired state is the controller's, from its feedback
                snap.q, snap.v = ex.remote_q, ex.remote_v
                np.subtract(ex.remote_q, w.act, out=err)
                if ex.wrap is not None:
                    _wrap_into(err, ex.wrap, w.tmp)
            snap.seq += 1
            m._keep_measured(st.position)

    def _activate(self, ex: _Exec, t: float) -> bool:
        """A scheduled motion's start time has come: take over its joints from whatever drives them."""
        if ex in self._pending:
            self._pending.remove(ex)
        idx = ex.idx
        q0, v0, a0 = self.desired(idx)
        traj = ex.pending_traj
        assert traj is not None
        try:
            late = t - ex.t0
            if late > 1e-9:  # the start fell between two ticks: what elapsed since is skipped
                traj = traj.after(late)
            traj, sampler = self._prepare(ex, traj, q0, v0, a0, t)
        except CommandRejected as exc:
            ex.phase = MotionPhase.DEAD
            if ex.motion is not None:
                ex.motion._settle(
                    MotionResult(ResultCode.INVALID_GOAL, {n: 0.0 for n in ex.motion.joint_names},
                                 f"invalid at its scheduled start: {exc}", t))
            return False
        if ex.motion is not None:
            ex.motion.trajectory = traj
        self._preempt_offloaded()
        self._preempt(idx)
        self._own(ex)
        self._begin(ex, sampler, q0, v0, a0, t)
        self._try_offload(ex, traj)
        return True
