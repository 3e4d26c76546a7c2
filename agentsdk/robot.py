"""The user-facing :class:`Robot` and :func:`connect`.

``connect`` resolves the robot description, loads the backend by name, wraps
it in the safety layer and starts the control loop::

    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        await robot.command(JointCommand("position", {"joint1": 0.4}))
        await robot.clock.sleep(1.0)
        state = await robot.read()
"""

from __future__ import annotations

import logging
from collections.abc import Generator, Mapping
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

from .clock import Clock
from .controller import Controller
from .description import apply_overrides, resolve_robot
from .errors import AgentSDKError, BackendStartError, CommandRejected
from .registry import load_backend
from .safety import SafetyConfig, SafetyLayer
from .types import JointCommand, JointInfo, JointState

if TYPE_CHECKING:
    import numpy.typing as npt

    from .kinematics import Kinematics
    from .motion import Motion, MotionResult, Tolerances
    from .pose import Pose
    from .trajectory import Trajectory

__all__ = ["Robot", "connect"]

log = logging.getLogger("agentsdk")


class Robot:
    """A connected robot: the one object behaviors talk to.

    Every method is safe to call from several tasks; commands are serialized.
    After :meth:`close` every call raises :class:`RobotClosedError`.
    """

    def __init__(self, controller: Controller, safety: SafetyLayer) -> None:
        self._ctl = controller
        self.safety = safety
        from .motion import MotionManager

        self._motions = MotionManager(controller, safety)
        self._kinematics: Kinematics | None = None

    # ------------------------------------------------------------ metadata
    @property
    def joints(self) -> tuple[JointInfo, ...]:
        """Actuated joints in URDF order, with limits."""
        return self._ctl.joints

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self._ctl.names

    @property
    def clock(self) -> Clock:
        """Robot time: simulated in lockstep, wall clock in realtime."""
        return self._ctl.clock

    @property
    def backend(self) -> str:
        return self._ctl.name

    @property
    def name(self) -> str:
        return self._ctl.description.name

    @property
    def realtime(self) -> bool:
        return self._ctl.realtime

    @property
    def control_period(self) -> float:
        return self._ctl.period

    @property
    def controller(self) -> Controller:
        """The backend instance (for tools and tests; behaviors should not need it)."""
        return self._ctl

    @property
    def closed(self) -> bool:
        return self._ctl.closed

    # ---------------------------------------------------------- kinematics
    @property
    def kinematics(self) -> Kinematics:
        """FK, Jacobians, TF snapshots and IK of this robot (host-side, the same on every backend).

        ``positions=None`` means the latest measured state; see :mod:`agentsdk.kinematics`.
        """
        if self._kinematics is None:
            from .kinematics import Kinematics

            self._kinematics = Kinematics.for_robot(self)
        return self._kinematics

    @property
    def link_names(self) -> tuple[str, ...]:
        """Every link (frame) of the robot, the root link first, fixed-joint links included."""
        return self.kinematics.link_names

    # -------------------------------------------------------------- direct
    async def read(self) -> JointState:
        """The latest measured joint state (position, velocity, effort, stamp)."""
        self._ctl.check_open()
        self.safety.check_fault()
        return self._ctl.snapshot()

    async def command(self, cmd: JointCommand) -> JointCommand:
        """Apply a direct command now; returns the command actually applied.

        Raises a :class:`CommandRejected` subclass (state unchanged) for unknown
        joints, NaN/inf, wrong length, unsupported modes, limit violations under
        the reject policy, or joints owned by a running trajectory; raises
        :class:`EStopActive` while the e-stop is latched.
        """
        ctl = self._ctl
        ctl.check_open()
        async with ctl.lock:
            ctl.check_open()
            self.safety.check_motion_allowed()
            idx, values, vel, eff = ctl.resolve(cmd)
            owner = self._motions.owner_of(idx)
            if owner is not None:
                raise CommandRejected(
                    f"joint {ctl.names[owner[0]]!r} is driven by a running trajectory; "
                    "cancel it (motion.cancel()) before sending direct commands"
                )
            values = self.safety.limit_command(cmd.mode, idx, values)
            vel, eff = self.safety.limit_feedforward(idx, vel, eff)
            ctl.apply(cmd.mode, idx, values, vel, eff)
            self.safety.feed(cmd.mode, idx)
            names = ctl.names
            applied = {names[i]: v for i, v in zip(idx.tolist(), values.tolist(), strict=True)}
            return JointCommand._trusted(cmd.mode, applied)

    # ---------------------------------------------------------- trajectory
    def follow(self, trajectory: Trajectory, tolerances: Tolerances | None = None) -> Motion:
        """Start following ``trajectory``; returns an awaitable :class:`Motion` handle at once.

        A running trajectory on overlapping joints is preempted (its result is
        PREEMPTED) and the new one starts from its current desired state.
        """
        self._ctl.check_open()
        self.safety.check_motion_allowed()
        return self._motions.follow(trajectory, tolerances)

    async def move_to(
        self,
        positions: Mapping[str, float],
        duration: float | None = None,
        tolerances: Tolerances | None = None,
    ) -> MotionResult:
        """Plan from the current desired state to ``positions`` and follow it to the end."""
        self._ctl.check_open()
        self.safety.check_motion_allowed()
        motion = self._motions.move_to(positions, duration, tolerances)
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
        self._ctl.check_open()
        await self.safety.estop(category)

    def estop_threadsafe(self, category: int = 0) -> None:
        """Latch an e-stop from any thread (no event loop needed for category 0)."""
        self.safety.estop_threadsafe(category)

    async def reset(self) -> None:
        """Clear a latched e-stop or fault. Never moves the robot: call :meth:`enable` next."""
        self._ctl.check_open()
        await self.safety.reset()

    async def enable(self) -> None:
        """Re-enable motion after :meth:`reset`: holds the current position with torque on."""
        self._ctl.check_open()
        await self.safety.enable()

    # ----------------------------------------------------------- lifecycle
    async def close(self) -> None:
        """Stop motions, leave actuators safe, release the backend. Idempotent; runs to completion if cancelled."""
        if self._ctl.closed:
            return
        try:
            self._motions.abort_all()
        finally:
            self.safety.shutdown()
            await self._ctl.stop()

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
    robot: str | Path,
    realtime: bool | None,
    safety: SafetyConfig | Mapping[str, Any] | None,
    options: dict[str, Any],
) -> Robot:
    cls = load_backend(backend)
    config, description = resolve_robot(robot)
    joints = apply_overrides(description, config)
    safety_cfg = SafetyConfig.from_sources(config.safety, safety)
    ctl = cls(config, description, joints, realtime=realtime, **options)
    layer = SafetyLayer(ctl, safety_cfg)
    try:
        await ctl.start()
    except AgentSDKError:
        layer.shutdown()
        raise
    except Exception as exc:
        layer.shutdown()
        raise BackendStartError(f"backend {backend!r} failed to start: {exc}") from exc
    layer.start()
    log.debug("connected %s on %s (%d joints)", description.name, backend, len(joints))
    return Robot(ctl, layer)


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
    robot: str | Path = "arm3",
    *,
    realtime: bool | None = None,
    safety: SafetyConfig | Mapping[str, Any] | None = None,
    **options: Any,
) -> _Connection:
    """Connect to ``robot`` on ``backend``.

    ``robot`` is a name from ``robots/`` or a path to a ``.urdf``, ``.xacro`` or
    ``robot.yaml``. ``realtime=None`` picks the backend's default (lockstep for
    simulators). ``safety`` overrides fields of the robot.yaml ``safety`` section;
    other keyword options go to the backend (they override robot.yaml
    ``backends.<name>``). Use as ``async with connect(...) as robot`` or
    ``robot = await connect(...)`` (then ``await robot.close()``).
    """
    return _Connection((backend, robot, realtime, safety, dict(options)))


