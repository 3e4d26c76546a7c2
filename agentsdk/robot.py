"""The user-facing :class:`Robot` and :func:`connect`.

``connect`` resolves the robot description, loads the backend by name, wraps
it in the safety layer and starts the control loop::

    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        await robot.command(JointCommand("position", {"joint1": 0.4}))
        await robot.clock.sleep(1.0)
        state = await robot.read()
"""

from __future__ import annotations

import asyncio
import logging
import warnings
from collections.abc import Callable, Generator, Mapping
from pathlib import Path
from types import MappingProxyType, TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np

from .backend import Backend, Capabilities, SetpointView
from .clock import Clock
from .config import Gains
from .description import apply_overrides, resolve_robot
from .errors import AgentSDKError, BackendStartError, ConfigurationError
from .limits import PositionBounds
from .loop import ControlLoop, HookHandle, Phase
from .registry import load_backend
from .safety import SafetyConfig, SafetyLayer
from .threads import run_blocking
from .types import AppliedCommand, FloatArray, JointCommand, JointInfo, JointState

if TYPE_CHECKING:
    import numpy.typing as npt

    from .block import BlockLockstep
    from .description import RobotDescription
    from .kinematics import Kinematics
    from .motion import Motion, MotionManager, MotionResult, Tolerances
    from .pose import BaseState, Pose
    from .sensors import Condition, Sensors
    from .trajectory import Trajectory

__all__ = ["Robot", "connect"]

log = logging.getLogger("agentsdk")


class Robot:
    """A connected robot: the one object behaviors talk to.

    Every method is safe to call from several tasks; commands are serialized.
    After :meth:`close` every call raises :class:`RobotClosedError`.
    """

    def __init__(
        self, loop: ControlLoop, safety: SafetyLayer, motions: MotionManager, sensors: Sensors | None = None
    ) -> None:
        self._loop = loop
        #: the safety layer (state, events, e-stop)
        self.safety = safety
        if sensors is None:
            from .sensors import SensorHub, Sensors

            sensors = Sensors(SensorHub(loop, loop.backend), safety)
        #: the robot's sensors: names, types, frames and latest readings (:mod:`agentsdk.sensors`)
        self.sensors: Sensors = sensors
        self._motions = motions
        #: block lockstep's runner (:meth:`block_lockstep`): connect turns it on where it can run
        self._block: BlockLockstep | None = None
        self._kinematics: Kinematics | None = None
        self._kinematics_error: Exception | None = None
        motions.kinematics_source = lambda: self.kinematics  # link poses in motion feedback
        motions.sensors_source = lambda: self.sensors  # sensor readings in motion feedback

    # ------------------------------------------------------------ metadata
    @property
    def joints(self) -> tuple[JointInfo, ...]:
        """Actuated joints in URDF order, with limits."""
        return self._loop.joints

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Names of the actuated joints, in :attr:`joints` order."""
        return self._loop.names

    @property
    def joint_index(self) -> Mapping[str, int]:
        """Joint name -> index in :attr:`joints` (read-only)."""
        return MappingProxyType(self._loop.index)

    @property
    def clock(self) -> Clock:
        """Robot time: simulated in lockstep, wall clock in realtime."""
        return self._loop.clock

    @property
    def backend(self) -> Backend:
        """The backend this robot runs on: its name is ``robot.backend.name`` (``"mujoco"``, ``"can"``...).

        Backend-specific extras live on it (CAN ``set_zero`` and ``stats``, MuJoCo ``model``/``data``,
        ``gain_sources``); behaviors should not need it, since everything common to all backends is on
        the Robot. ``str(robot.backend)`` is the name, so ``f"{robot.backend}"`` prints it as before.
        """
        return self._loop.backend

    @property
    def capabilities(self) -> Capabilities:
        """What this connection's backend supports (modes, time models)."""
        return self._loop.backend.capabilities

    @property
    def name(self) -> str:
        """The robot's name (from the description)."""
        return self._loop.backend.description.name

    @property
    def realtime(self) -> bool:
        """True when paced to the wall clock, False in lockstep simulated time."""
        return self._loop.realtime

    @property
    def control_period(self) -> float:
        """Seconds per control tick (1 / update_rate)."""
        return self._loop.period

    @property
    def controller(self) -> Backend:
        """Deprecated former name of :attr:`backend` (the backend instance): use ``robot.backend``."""
        warnings.warn("Robot.controller is deprecated: use Robot.backend (the same Backend instance)",
                      DeprecationWarning, stacklevel=2)
        return self._loop.backend

    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._loop.closed

    @property
    def gains(self) -> Mapping[str, Gains]:
        """The servo gains in effect per joint (``p``, ``d`` and velocity-mode ``v``), read-only.

        robot.yaml ``gains`` where given, else the position servo the description declares (an MJCF
        position actuator's ``kp``/``kv``), else computed from the model (see
        :func:`agentsdk.dynamics.model_gains`; ``robot.backend.gain_sources`` says which per joint,
        ``robot.backend.model_gain_report`` what bounded the model's).
        """
        loop = self._loop
        return MappingProxyType({
            name: Gains(p=float(p), d=float(d), v=float(v))
            for name, p, d, v in zip(loop.names, loop.gain_p, loop.gain_d, loop.gain_v, strict=True)
        })

    @property
    def gravity_compensation(self) -> Mapping[str, bool]:
        """Per joint: whether the servo law adds the model's gravity torque (robot.yaml ``gravity_compensation``)."""
        flags = self._loop.backend.gravity_compensation.tolist()
        return MappingProxyType(dict(zip(self._loop.names, flags, strict=True)))

    def base_state(self) -> BaseState:
        """The base's pose in the world and its linear/angular velocity (world frame), now.

        A floating base (robot.yaml ``floating_base: true``) as the simulator measures it; a
        fixed base is the world's identity pose at rest.
        """
        self._loop.check_open()
        state = self._loop.backend.base_state()
        from .pose import BaseState

        return BaseState(state.pose, state.linear_velocity, state.angular_velocity, self._loop.stamp)

    # ------------------------------------------------------------ loop state
    @property
    def setpoint(self) -> SetpointView:
        """Read-only view of the servo setpoint the backend was (or will next be) given, after safety."""
        return self._loop.setpoint

    def command_targets(self) -> FloatArray:
        """Copy of the last commanded value per joint (position, velocity or effort per its mode)."""
        return self._loop.targets.copy()

    @property
    def torque_enabled(self) -> bool:
        """False after an emergency stop removed torque, until :meth:`enable`."""
        return not self._loop.torque_off

    @property
    def busy(self) -> bool:
        """True while a trajectory or a stop ramp drives some joints."""
        return self._loop.busy

    @property
    def motion_joints(self) -> tuple[str, ...]:
        """Names of the joints currently driven by a trajectory or a stop ramp."""
        mask = self._motions.owned_mask
        return tuple(n for n, owned in zip(self._loop.names, mask.tolist(), strict=True) if owned)

    @property
    def ticks(self) -> int:
        """Control ticks run since connect."""
        return self._loop.ticks

    @property
    def missed_deadlines(self) -> int:
        """Control periods skipped because the realtime loop ran late (always 0 in lockstep)."""
        return self._loop.missed_deadlines

    def add_tick_hook(self, phase: Phase, fn: Callable[..., Any], *, order: int = 0) -> HookHandle:
        """Register ``fn`` in a phase of every control tick (tools: recorders, viewers, replay).

        See :class:`agentsdk.loop.Phase` for the signatures. Returns a handle; ``handle.remove()``.
        """
        self._loop.check_open()
        return self._loop.add_hook(phase, fn, order=order)

    def add_fault_listener(self, fn: Callable[[BaseException], None]) -> HookHandle:
        """Call ``fn(exc)`` once if the control loop dies (backend fault, simulation divergence)."""
        return self._loop.add_fault_listener(fn)

    @property
    def description(self) -> RobotDescription:
        """The loaded robot description (links, joints, repaired inertials, source file)."""
        return self._loop.backend.description

    def latest_state(self) -> JointState:
        """The latest measured joint state, without awaiting (what :meth:`read` returns)."""
        self._loop.check_open()
        return self._loop.snapshot()

    def desired_state(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The current desired ``(positions, velocities, accelerations)`` of every joint, in joint order.

        Where a motion or stop ramp drives a joint, its reference at the next tick; else the
        setpoint of position-mode joints and the measured state of the others. A new motion
        planned from here starts without a jump.
        """
        return self._motions.desired(np.arange(len(self._loop.joints), dtype=np.intp))

    # ---------------------------------------------------------- kinematics
    @property
    def kinematics(self) -> Kinematics:
        """FK, Jacobians, TF snapshots and IK of this robot (host-side, the same on every backend).

        ``positions=None`` means the latest measured state; see :mod:`agentsdk.kinematics`.
        """
        if self._kinematics is None:
            if self._kinematics_error is not None:
                raise self._kinematics_error
            self._kinematics = self._build_kinematics()
        return self._kinematics

    def _build_kinematics(self) -> Kinematics:
        kin = _build_kinematics(self._loop.backend)
        kin.bind_state(self.latest_state)
        return kin

    def _adopt_kinematics(self, kin: Kinematics | Exception) -> None:
        """Take the kinematics built at connect (or the error that building them raised)."""
        if isinstance(kin, Exception):
            self._kinematics_error = kin
        else:
            kin.bind_state(self.latest_state)
            self._kinematics = kin

    @property
    def link_names(self) -> tuple[str, ...]:
        """Every link (frame) of the robot, the root link first, fixed-joint links included."""
        return self.kinematics.link_names

    # -------------------------------------------------------------- direct
    def block_lockstep(self, capacity: int = 256) -> BlockLockstep:
        """This lockstep robot's block runner of ``capacity`` ticks: the one on, or a new one in its place.

        Block lockstep (:mod:`agentsdk.block`: uneventful ticks as blocks, bit for bit tick by tick) is
        on from :func:`connect` (256 ticks) unless ``block_lockstep=False``; ``close()`` on the runner
        turns it off. A realtime robot, or a backend without blocks, raises :class:`ConfigurationError`.
        """
        from .block import lockstep_runner

        self._loop.check_open()
        seam, planner = self.safety.block_seam, self._motions.block_planner
        self._block = lockstep_runner(self._loop, seam, planner, self._block, capacity)
        return self._block

    @property
    def block_runner(self) -> BlockLockstep | None:
        """The block lockstep runner that is on (:meth:`block_lockstep`), or None: every tick on its own."""
        return self._block if self._block is not None and self._block.active else None

    async def read(self) -> JointState:
        """The latest measured joint state (position, velocity, effort, stamp)."""
        self._loop.check_open()
        self.safety.check_fault()
        return self._loop.snapshot()

    async def command(self, cmd: JointCommand | AppliedCommand) -> AppliedCommand:
        """Apply a direct command now; returns the command actually applied.

        Raises a :class:`CommandRejected` subclass (state unchanged) for unknown
        joints, NaN/inf, wrong length, unsupported modes, limit violations under
        the reject policy, or joints owned by a running trajectory; raises
        :class:`EStopActive` while the e-stop is latched.
        """
        loop = self._loop
        loop.check_open()
        if isinstance(cmd, AppliedCommand):
            cmd = cmd.as_command()
        lock = loop.lock
        if not lock.locked():
            # admit() never awaits: with the lock free, taking and releasing it around the call
            # (two coroutines and a wake-up scan per command) changes nothing another task could see
            return self.safety.admit(cmd)
        async with lock:
            loop.check_open()
            return self.safety.admit(cmd)

    # ---------------------------------------------------------- trajectory
    def follow(
        self,
        trajectory: Trajectory,
        tolerances: Tolerances | None = None,
        *,
        start_time: float | None = None,
        allow_nonzero_velocity_at_end: bool = False,
        stretch_to_limits: bool = False,
    ) -> Motion:
        """Start following ``trajectory``; returns an awaitable :class:`Motion` handle at once.

        The trajectory is validated like ros2_controllers' JointTrajectoryController and on
        its whole interpolated motion (from the current desired state): a
        :class:`CommandRejected` subclass naming the point or segment and the joint is raised,
        nothing starts. ``stretch_to_limits=True`` slows a trajectory whose motion is too fast
        or accelerates too hard down uniformly (times stretched) instead of rejecting it.
        A last point with a non-zero velocity needs ``allow_nonzero_velocity_at_end=True``
        (the motion then decelerates to rest after it).

        ``start_time`` (robot clock, :attr:`clock`) schedules the start, like JTC's
        ``header.stamp``: until then whatever drives the joints continues; a start in the past
        skips the points that have elapsed. A running trajectory on overlapping joints is
        preempted (its result is PREEMPTED) when the new one starts, which then starts from
        its current desired state. Trajectories run at :attr:`speed_scaling`.
        """
        self._loop.check_open()
        self.safety.check_motion_allowed()
        return self._motions.follow(trajectory, tolerances, start_time=start_time,
                                    allow_nonzero_velocity_at_end=allow_nonzero_velocity_at_end,
                                    stretch_to_limits=stretch_to_limits)

    @property
    def speed_scaling(self) -> float:
        """The speed scaling factor trajectories run at: 1.0 as timed, 0.5 half speed, 0.0 paused."""
        return self._motions.speed_scaling

    def set_speed_scaling(self, factor: float) -> None:
        """Slow every running and future trajectory down to ``factor`` in [0, 1] (0 pauses, 1 resumes).

        Like JTC's speed scaling and an industrial pendant's speed slider: trajectory time advances
        at ``factor`` times robot time. The change is smooth (each motion ramps to the new factor
        within its joints' acceleration limits, velocities never jump). Path tolerances keep
        being checked against the slowed reference and ``goal_time`` counts trajectory time, so
        a paused motion neither times out nor fails. Stops (cancel, aborts, e-stops) are never
        slowed. Callable from any task or state; raises :class:`InvalidValueError` outside [0, 1].
        """
        self._loop.check_open()
        self._motions.set_speed_scaling(factor)

    async def move_to(
        self,
        positions: Mapping[str, float],
        duration: float | None = None,
        tolerances: Tolerances | None = None,
        *,
        until: Condition | None = None,
    ) -> MotionResult:
        """Plan from the current desired state to ``positions`` and follow it to the end.

        ``until`` (a guarded move): a sensor condition (``agentsdk.sensors.force_above("wrist", 5.0)``,
        or any ``cond(robot.sensors) -> bool``) checked every tick; once it holds the motion decelerates
        to rest within the limits and ends SUCCESSFUL, its message naming the condition.
        """
        self._loop.check_open()
        self.safety.check_motion_allowed()
        if until is not None:
            from .sensors._guarded import check_condition

            check_condition(self.sensors, until)  # a wrong sensor name or type raises here
        motion = self._motions.move_to(positions, duration, tolerances)
        if until is not None:
            from .sensors._guarded import guard

            guard(self._loop, self.sensors, motion, until)
        return await motion

    async def move_to_pose(
        self,
        link: str,
        pose: Pose | npt.ArrayLike,
        linear: bool = False,
        duration: float | None = None,
        tolerances: Tolerances | None = None,
        *,
        position_only: bool = False,
        path_tolerance: float = 1e-3,
        velocity_scale: float = 1.0,
        acceleration_scale: float = 1.0,
    ) -> MotionResult:
        """Move ``link`` to ``pose`` (root frame) and return the motion's result.

        ``linear=False``: IK from the current desired positions, then :meth:`move_to`.
        ``linear=True``: the link's origin follows the straight line (orientation: slerp),
        densely sampled and IK'd into a joint trajectory timed from the joint limits and run
        by :meth:`follow` (cancel, preemption, ``tolerances`` and safety as for any trajectory);
        samples may deviate from the line by at most ``path_tolerance`` (m); ``velocity_scale`` and
        ``acceleration_scale`` (in (0, 1], like MoveIt's scaling factors) slow the line down.
        ``pose`` may be a position (3,) (implies ``position_only``). An unreachable target
        returns ``MotionResult(INVALID_GOAL)`` whose message names the IK residual; nothing
        moves. See :mod:`agentsdk.cartesian`.
        """
        from .cartesian import move_to_pose

        return await move_to_pose(self, link, pose, linear, duration, tolerances, position_only=position_only,
                                  path_tolerance=path_tolerance, velocity_scale=velocity_scale,
                                  acceleration_scale=acceleration_scale)

    # -------------------------------------------------------------- safety
    async def estop(self, category: int = 1) -> None:
        """Latched emergency stop, IEC 60204-1 category 0, 1 or 2 (see SafetyLayer)."""
        self._loop.check_open()
        await self.safety.estop(category)

    def estop_threadsafe(self, category: int = 0) -> None:
        """Latch an e-stop from any thread (no event loop needed for category 0)."""
        self.safety.estop_threadsafe(category)

    async def reset(self) -> None:
        """Clear a latched e-stop or fault. Never moves the robot: call :meth:`enable` next."""
        self._loop.check_open()
        await self.safety.reset()

    async def enable(self) -> None:
        """Re-enable motion after :meth:`reset`: holds the current position with torque on."""
        self._loop.check_open()
        await self.safety.enable()

    # ----------------------------------------------------------- lifecycle
    async def close(self) -> None:
        """Leave the robot safe and release the backend. Idempotent; completes even if cancelled, then re-raises.

        A controlled stop (e-stop category 1 or 2) in progress is completed first, so
        a category 1 stop reaches rest before torque is removed; then motions end,
        the watchdogs stop and the backend closes (actuators safe).
        """
        if self._loop.closed:
            return
        # Cancelled while waiting for the stop to finish: the cleanup below still runs to the end
        # (the backend's close leaves the actuators safe), then the cancellation propagates
        # (trio's ``aclose`` contract: never swallow it).
        try:
            if self.safety.stop_in_progress and self._loop.fault is None:
                await asyncio.shield(self.safety.wait_stopped())
        finally:
            try:
                self._motions.abort_all()
            finally:
                self.safety.shutdown_now()
                try:
                    await asyncio.shield(self.safety.shutdown())
                finally:
                    await self._loop.stop()

    async def __aenter__(self) -> Robot:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def __repr__(self) -> str:
        mode = "realtime" if self.realtime else "lockstep"
        state = "closed" if self.closed else self.safety.state.name
        return f"<Robot {self.name!r} on {self.backend} ({mode}, {state}), {len(self.joints)} joints>"


async def _open_robot(
    backend: str,
    robot: str | Path | None,
    realtime: bool | None,
    safety: SafetyConfig | Mapping[str, Any] | None,
    options: dict[str, Any],
    strict: bool | None = None,
    trusted: bool | None = None,
    update_rate: float | None = None,
    block_lockstep: bool = True,
) -> Robot:
    from .motion import MotionManager

    if not isinstance(block_lockstep, bool):
        raise ConfigurationError(f"block_lockstep must be True or False, got {block_lockstep!r}")

    def prepare() -> tuple[Backend, SafetyConfig, PositionBounds, Kinematics | Exception]:
        # blocking work (importing the simulator, xacro, parsing, meshes): in a worker thread,
        # so that other robots on this event loop keep their deadlines while this one loads
        cls = load_backend(backend)
        config, description = resolve_robot(_robot_spec(cls, robot, options), strict=strict, trusted=trusted)
        if update_rate is not None:
            config = config.with_update_rate(update_rate)
        joints = apply_overrides(description, config)
        safety_cfg = SafetyConfig.from_sources(config.safety, safety, source=config.label)
        bounds = PositionBounds(joints, safety_cfg.position_margin)
        # the backend's ready values (options, start pose, gains from the host model: its one compile)
        backend_obj = cls.create(config, description, joints, realtime=realtime, **options)
        backend_obj.sensors  # noqa: B018 - the declared sensors (parsing, an MJCF compile) here too
        # the kinematics on the same host model and the IK solver (the first ``import mink`` loads
        # scipy's shared libraries, holding the GIL for up to a second on a slow machine): built here,
        # before the control loop runs, so that neither the loop nor the stall watchdog waits for them.
        # A description the kinematics cannot model fails at ``robot.kinematics``, not here.
        kin: Kinematics | Exception
        try:
            kin = _build_kinematics(backend_obj)
        except Exception as exc:
            kin = exc
        return backend_obj, safety_cfg, bounds, kin

    backend_obj, safety_cfg, bounds, kin = await run_blocking(prepare, name=f"agentsdk-connect-{backend}")
    loop = ControlLoop(backend_obj)
    layer = SafetyLayer(loop, safety_cfg, bounds)
    motions = MotionManager(loop, bounds, safety_cfg.stop_deceleration_scale, layer.step_guard)
    layer.attach_motions(motions)
    try:
        await loop.start()
    except AgentSDKError:
        layer.shutdown_now()
        raise
    except Exception as exc:
        layer.shutdown_now()
        raise BackendStartError(f"backend {backend!r} failed to start: {exc}") from exc
    layer.start()
    log.debug("connected %s on %s (%d joints)", backend_obj.description.name, backend, len(backend_obj.joints))
    from .sensors import connect_sensors

    robot_obj = Robot(loop, layer, motions, connect_sensors(loop, layer))
    robot_obj._adopt_kinematics(kin)
    from .block import available

    if block_lockstep and available(loop):
        robot_obj.block_lockstep()  # (cannot fail: a lockstep loop, a block stepper, no runner yet)
    return robot_obj


def _robot_spec(cls: type[Backend], robot: str | Path | None, options: Mapping[str, Any]) -> str | Path:
    """``robot``, else the description the backend finds itself (``remote_description``: ros2), else arm3."""
    if robot is not None:
        return robot
    remote = getattr(cls, "remote_description", None)
    return remote(options) if callable(remote) else "arm3"


def _build_kinematics(backend: Backend) -> Kinematics:
    """The robot's kinematics on its one host model (``backend.spec.host``: compiled once per connect)."""
    from .kinematics import Kinematics

    kin = Kinematics(backend.description, backend.joints, host=backend.spec.host.get())
    kin.prepare_ik()
    return kin


class _Connection:
    """What :func:`connect` returns: ``async with`` it, or ``await`` it."""

    def __init__(self, args: tuple[Any, ...]) -> None:
        self._args = args
        self._robot: Robot | None = None

    async def __aenter__(self) -> Robot:
        self._robot = await _open_robot(*self._args)
        return self._robot

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._robot is not None:
            await self._robot.close()

    def __await__(self) -> Generator[Any, None, Robot]:
        return _open_robot(*self._args).__await__()


def connect(
    backend: str = "mujoco",
    robot: str | Path | None = None,
    *,
    realtime: bool | None = None,
    safety: SafetyConfig | Mapping[str, Any] | None = None,
    strict: bool | None = None,
    trusted: bool | None = None,
    update_rate: float | None = None,
    block_lockstep: bool = True,
    **options: Any,
) -> _Connection:
    """Connect to ``robot`` on ``backend``.

    ``robot`` is a name from ``robots/`` or a path to a ``.urdf``, ``.xacro``,
    MJCF ``.xml`` or ``robot.yaml``; omitted: ``arm3``, except on a backend that reads the
    description from the robot itself (``ros2``: the ``robot_description`` topic).
    ``realtime=None`` picks the backend's default (lockstep for simulators).
    ``strict=True`` (or robot.yaml ``strict: true``) refuses a description that
    needs repairs (``DescriptionError`` listing them) instead of repairing it with
    a warning. ``trusted=True`` (or robot.yaml ``trusted: true``) loads a robot file
    you trust as code: xacro expressions unchecked, files outside its package
    allowed (by default a robot file is data, see README "Bring your own robot").
    ``safety`` overrides fields of the robot.yaml ``safety`` section;
    ``update_rate`` (Hz) overrides robot.yaml's control rate (like ros2_control's
    ``controller_manager.update_rate`` set at launch); ``block_lockstep=False`` runs every lockstep
    tick on its own, never as blocks (:meth:`Robot.block_lockstep`; the same results); other keyword
    options go to the backend (they override robot.yaml ``backends.<name>``). Use as
    ``async with connect(...) as robot`` or ``robot = await connect(...)`` (then ``await robot.close()``).
    """
    return _Connection((backend, robot, realtime, safety, dict(options), strict, trusted, update_rate, block_lockstep))


