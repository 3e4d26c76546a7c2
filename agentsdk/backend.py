"""The backend contract: what a backend author implements, documented in one place.

A backend is a subclass of :class:`Backend` that implements a few narrow hooks.
The control loop (:mod:`agentsdk.loop`) owns everything else -- the setpoint and
state buffers, the clocks, the tick phases, the torque-off rule, validation --
the way python-can's ``BusABC.recv`` owns the logic around ``_recv_internal``:
the loop calls the public, final methods :meth:`Backend.open`, :meth:`~Backend.close`,
:meth:`~Backend.write`, :meth:`~Backend.step`, :meth:`~Backend.read`,
:meth:`~Backend.emergency_stop`, :meth:`~Backend.enable` and :meth:`~Backend.recover`,
which call the hooks (a subclass implements the hooks and never overrides those).
Hooks receive values and return values; none of them sees the loop's buffers::

    class MyBackend(Backend):
        name = "mine"
        capabilities = Capabilities(modes=frozenset({"position", "velocity", "effort"}),
                                    lockstep=True, realtime=True, deterministic=True)

        async def _open(self) -> None: ...                  # connect / build the simulation
        async def _close(self) -> None: ...                 # leave actuators safe; idempotent
        def _write(self, sp: SetpointView) -> None: ...     # apply the servo setpoint (read-only arrays)
        async def _step(self, dt: float) -> None: ...       # advance one control period / bus cycle
        def _read(self) -> JointReading: ...                # (position, velocity, effort) arrays
        def _emergency_stop(self, category: int) -> None: ...  # sync, thread-safe, no event loop

Optional hooks: ``async _enable()`` (re-arm after an e-stop), ``async _recover()`` (default: not recoverable).

Sensors (:mod:`agentsdk.sensors`): a backend declares the kinds it can sample in
``sensor_kinds`` and implements ``_read_sensors(channels)``, which writes each due channel's
sample into its preallocated arrays; :attr:`Backend.sensors` lists the declared sensors it
serves (joint sensors are filled by the loop for every backend).

The joint servo law every backend implements is the MIT / ros2_control one, plus the
model's gravity torque::

    effort = kp * (q_des - q) + kd * (v_des - v) + effort_ff + tau_model     (clamped to +-max_effort)

where ``tau_model`` is ``g(q)`` at the measured position for the joints whose
:attr:`Backend.gravity_compensation` flag is set (robot.yaml ``gravity_compensation``, on by
default; see :mod:`agentsdk.dynamics`; the MuJoCo backend lets MuJoCo add it inside every physics
step where that expresses the law exactly), plus, when :attr:`Backend.inverse_dynamics` is set
(on by default), the inverse dynamics of the desired motion ``M a_des + C v_des`` with the joints'
damping and friction at ``v_des`` (:class:`agentsdk.feedforward.InverseDynamicsTerm`; none for an
effort-mode joint). A joint whose ``enabled`` flag is False produces no torque (no gravity
compensation either). Position, velocity and effort commands are all expressed in this law
(velocity: kp = 0; effort: kp = kd = 0), so a backend needs one code path. The loop enforces the
torque-off rule itself: after an emergency stop every setpoint it writes has ``enabled`` all False
until the robot is deliberately re-enabled, and if an emergency stop from another thread lands
while ``_write`` runs, the loop calls ``_emergency_stop(0)`` again before stepping.

A backend is constructed from one ready value, its :class:`~agentsdk.backendspec.BackendSpec`
(``Backend(spec)``; :meth:`Backend.create` derives it with :meth:`Backend.make_spec` first): options,
joints and limits, start pose, servo gains, gravity flags and the robot's one host-side model. A
subclass's ``__init__(self, spec)`` calls ``super().__init__(spec)``; the earlier
``(config, description, joints, **options)`` form still works and warns.
Read-only information a backend may use (the spec's values): :attr:`Backend.description`,
:attr:`~Backend.config`, :attr:`~Backend.joints` (limits after robot.yaml overrides),
:attr:`~Backend.names`, :attr:`~Backend.index`, :attr:`~Backend.period`, :attr:`~Backend.realtime`,
:attr:`~Backend.options` (validated by :attr:`~Backend.options_model`),
:attr:`~Backend.initial_positions` (a simulator starts exactly there),
:attr:`~Backend.gravity_compensation`, :attr:`~Backend.inverse_dynamics`, :attr:`~Backend.servo_gains`
(robot.yaml's, the description's or the model's), :attr:`~Backend.dynamics` (the rigid-body model on the
robot's host model, for backends without a simulator), and the limit arrays :attr:`~Backend.lower`,
:attr:`~Backend.upper`, :attr:`~Backend.max_velocity`, :attr:`~Backend.max_effort`.

A simulator overrides :attr:`~Backend.servo_timestep` (its physics step: the model-based gains
stay within what it integrates stably) and, for a floating base, :meth:`~Backend.base_state`.
Capabilities are read from the instance (``__init__`` may narrow ``self.capabilities``).
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import functools
import logging
import warnings
from abc import ABC, abstractmethod
from collections.abc import Awaitable, Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, TypeAlias, final

import numpy as np
from pydantic import BaseModel, ValidationError

from .backendspec import BackendSpec, takes_spec
from .errors import AgentSDKError, BackendFault, BackendStartError, ConfigurationError
from .pose import BaseState, Pose
from .types import MODES, CommandMode, FloatArray, JointInfo

if TYPE_CHECKING:
    from .config import Gains, RobotConfig
    from .description import RobotDescription
    from .description.start import StartPose
    from .dynamics import DynamicsModel, GainReport
    from .sensors._channel import SensorChannel
    from .sensors._spec import SensorSpec

log = logging.getLogger("agentsdk")

__all__ = ["MAX_SUBSTEPS", "Backend", "Capabilities", "JointReading", "ModeCode", "SetpointView", "substeps"]

#: most physics steps a simulator backend runs per control period
MAX_SUBSTEPS = 1000


class ModeCode(enum.IntEnum):
    """Command mode of a joint, as stored per joint in the servo setpoint (``SetpointView.mode``)."""

    POSITION = 0
    VELOCITY = 1
    EFFORT = 2

    @classmethod
    def of(cls, mode: CommandMode) -> ModeCode:
        """The code of a command mode name (``"position"``, ``"velocity"``, ``"effort"``)."""
        return _CODE_OF[mode]

    @property
    def mode(self) -> CommandMode:
        """The command mode name of this code."""
        return MODES[self.value]


_CODE_OF: dict[str, ModeCode] = {m: ModeCode(i) for i, m in enumerate(MODES)}


@dataclass(frozen=True, slots=True)
class Capabilities:
    """What a backend declares; the conformance kit gates its tests on this (never on names)."""

    #: command modes the backend accepts
    modes: frozenset[CommandMode]
    #: runs in lockstep simulated time
    lockstep: bool
    #: runs paced to the wall clock
    realtime: bool
    #: True when the same inputs always give bit-identical states (lockstep simulators)
    deterministic: bool = False
    #: False when the backend drives something outside this process that a test must provide (a robot on
    #: another host, a bus with motors): generic "every backend" tests then leave it to its own fixtures
    standalone: bool = True


class SetpointView:
    """The per-joint servo setpoint a backend's ``_write`` receives, in ``joints`` order.

    Every attribute is a read-only ``numpy`` array (the loop reuses the same
    object every tick; copy what you keep): ``position``, ``velocity``,
    ``effort`` (feed-forward), ``kp``, ``kd``, ``enabled`` (bool) and ``mode``
    (int8 :class:`ModeCode` values, informational: the servo law covers every mode),
    ``target`` (the last commanded value per joint, informational) and ``acceleration``
    (the reference's desired acceleration this tick, 0 where nothing feeds one forward: the
    inverse-dynamics term of the servo law, :attr:`Backend.inverse_dynamics`).
    """

    __slots__ = ("acceleration", "effort", "enabled", "kd", "kp", "mode", "position", "target", "velocity")

    position: FloatArray
    velocity: FloatArray
    effort: FloatArray
    kp: FloatArray
    kd: FloatArray
    enabled: np.ndarray
    mode: np.ndarray
    target: FloatArray
    acceleration: FloatArray

    def __init__(self, **arrays: np.ndarray) -> None:
        for name in self.__slots__:
            view = arrays[name].view()
            view.flags.writeable = False
            object.__setattr__(self, name, view)

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"SetpointView is read-only (cannot set {name!r})")

    def __repr__(self) -> str:
        return (
            f"SetpointView(position={self.position.tolist()}, velocity={self.velocity.tolist()}, "
            f"effort={self.effort.tolist()}, kp={self.kp.tolist()}, kd={self.kd.tolist()}, "
            f"enabled={self.enabled.tolist()}, mode={self.mode.tolist()})"
        )


#: what ``Backend._read`` returns: ``(position, velocity, effort)``, each shape ``(n_joints,)``.
#: The arrays may be the backend's own (the loop copies them at once).
JointReading: TypeAlias = tuple[np.ndarray, np.ndarray, np.ndarray]


class Backend(ABC):
    """Base class of every backend. Users never see it directly: they get a :class:`~agentsdk.Robot`.

    Construction only validates (options, capabilities); hardware or simulators
    are opened by :meth:`open` (the ``_open`` hook), called by the loop from a
    running event loop. The public methods below are final: a backend implements
    the ``_hooks`` they call.
    """

    #: the public methods the loop calls; a subclass implements the hooks instead
    _FINAL: ClassVar[tuple[str, ...]] = (
        "open", "close", "write", "step", "read", "emergency_stop", "enable", "recover", "read_sensors",
        "step_runs_inline",
    )

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        overridden = [name for name in Backend._FINAL if name in cls.__dict__]
        if overridden:
            raise TypeError(
                f"{cls.__name__} overrides {', '.join(overridden)} of agentsdk.Backend; implement the hooks "
                f"({', '.join('_' + n for n in overridden)}) instead"
            )

    #: entry-point name, set by subclasses
    name: ClassVar[str] = ""
    #: declared capabilities; read from the instance (a backend may narrow them per instance)
    capabilities: Capabilities
    #: pydantic model validating the backend options (robot.yaml ``backends.<name>`` + connect kwargs)
    options_model: ClassVar[type[BaseModel] | None] = None
    #: sensor kinds the backend samples in ``_read_sensors`` (joint sensors are served by the loop for every backend)
    sensor_kinds: ClassVar[frozenset[str]] = frozenset()
    step_never_suspends: ClassVar[bool] = False  #: this class's ``_step`` never suspends: lockstep may run it inline

    def __str__(self) -> str:
        return self.name

    def __eq__(self, other: object) -> bool:  # ``robot.backend`` was the name (a str) in 0.1
        if isinstance(other, str):
            warnings.warn(f"comparing a Backend with a string: use robot.backend.name == {other!r}",
                          DeprecationWarning, stacklevel=2)
            return self.name == other
        return NotImplemented  # (identity)

    def __hash__(self) -> int:  # the name's: ``robot.backend in {"mujoco", "pybullet"}`` keeps working
        return hash(self.name)

    # the read-only values a backend is built from (set from its spec, see ``_adopt``)
    config: RobotConfig
    description: RobotDescription
    joints: tuple[JointInfo, ...]
    realtime: bool
    names: tuple[str, ...]
    index: dict[str, int]
    period: float
    options: Any

    def __init__(
        self,
        spec: BackendSpec | RobotConfig,
        description: RobotDescription | None = None,
        joints: tuple[JointInfo, ...] | None = None,
        *,
        realtime: bool | None = None,
        **options: Any,
    ) -> None:
        """Construct the backend from its ready :class:`~agentsdk.backendspec.BackendSpec` (:meth:`make_spec`).

        The form ``Backend(config, description, joints, realtime=..., **options)`` of earlier
        releases still works, deprecated (it warns with a ``DeprecationWarning``): the spec is then
        derived here. Build backends with :meth:`create` (or ``cls(cls.make_spec(...))``).
        """
        if isinstance(spec, BackendSpec):
            if description is not None or joints is not None or realtime is not None or options:
                raise TypeError(f"{type(self).__name__}(spec) takes the BackendSpec alone")
        else:
            if description is None or joints is None:
                raise TypeError(f"{type(self).__name__}() takes a BackendSpec (see Backend.make_spec)")
            warnings.warn(
                f"{type(self).__name__}: constructing a backend from (config, description, joints, **options) is "
                "deprecated; a backend is constructed from its BackendSpec: Backend.create(config, description, "
                "joints, **options), or cls(cls.make_spec(...)); a subclass __init__ takes (self, spec) and calls "
                "super().__init__(spec)",
                DeprecationWarning,
                stacklevel=2,
            )
            spec = BackendSpec.derive(self, spec, description, joints, realtime, options)
        self._adopt(spec)

    @classmethod
    def make_spec(cls, config: RobotConfig, description: RobotDescription, joints: tuple[JointInfo, ...], *,
                  realtime: bool | None = None, **options: Any) -> BackendSpec:
        """The ready values this backend class is built from (:meth:`BackendSpec.derive`; nothing is opened)."""
        draft = cls.__new__(cls)  # holds what the hooks may read, before construction
        return BackendSpec.derive(draft, config, description, joints, realtime, options)

    @classmethod
    def create(cls, config: RobotConfig, description: RobotDescription, joints: tuple[JointInfo, ...], *,
               realtime: bool | None = None, **options: Any) -> Backend:
        """The backend for a robot: its spec (:meth:`make_spec`), then ``cls(spec)``.

        A subclass whose ``__init__`` takes ``(config, description, joints, ...)`` (earlier releases)
        is called that way and warns.
        """
        if takes_spec(cls, Backend):
            return cls(cls.make_spec(config, description, joints, realtime=realtime, **options))
        return cls(config, description, joints, realtime=realtime, **options)

    @classmethod
    def default_realtime(cls, config: RobotConfig, options: dict[str, Any]) -> bool:
        """The time model when ``realtime`` is not given: lockstep where the backend supports it.

        ``options``: robot.yaml ``backends.<name>`` merged with the connect options, not validated
        (a backend whose time model depends on the remote side reads them, ``ros2``).
        """
        return not cls.capabilities.lockstep

    def _adopt(self, spec: BackendSpec) -> None:
        """Take the spec's ready values as this backend's read-only attributes (documented on BackendSpec)."""
        #: every ready value this backend is built from (limits, start pose, gains, servo-law flags, options)
        self.spec: BackendSpec = spec
        self.config, self.description, self.joints = spec.config, spec.description, spec.joints
        self.realtime, self.period, self.options = spec.realtime, spec.period, spec.options
        self.names = spec.names
        #: joint name -> index
        self.index = {n: i for i, n in enumerate(self.names)}
        self.lower, self.upper = spec.lower, spec.upper
        self.max_velocity, self.max_effort = spec.max_velocity, spec.max_effort
        self.start_pose: StartPose = spec.start_pose
        self.initial_positions = spec.initial_positions
        self.gravity_compensation: np.ndarray = spec.gravity_compensation
        self.inverse_dynamics: bool = spec.inverse_dynamics
        self._backend_open = False
        #: joints whose reading frame the backend is changing on purpose (see :meth:`frame_change`),
        #: and how many changes are in progress (one list item: the gate checks it every tick)
        self.frame_changing = np.zeros(len(spec.joints), dtype=bool)
        self.frame_changes = [0]

    # ------------------------------------------------------------ model-based information
    @property
    def servo_timestep(self) -> float | None:
        """The step at which the servo law is integrated (a simulator's physics timestep), or None.

        None (the default) means the servo runs in continuous time or in motor firmware; the
        model-based gains then have no discrete-time bound.
        """
        return None

    @property
    def floating_base(self) -> bool:
        """True when the robot's base floats (robot.yaml ``floating_base``, or a free joint at the root of an MJCF).

        A simulator's option may override robot.yaml.
        """
        return bool(self.config.floating_base) or self.description.free_root is not None

    @functools.cached_property
    def dynamics(self) -> DynamicsModel:
        """The description's rigid-body model (``g(q)``, ``M(q)``) on the robot's one host model (:attr:`spec`).

        Its own scratch data on the model the robot's kinematics share (compiled at most once).
        """
        from .dynamics import DynamicsModel

        return DynamicsModel(self.description, self.joints, host=self.spec.host.get())

    @functools.cached_property
    def model_gain_report(self) -> GainReport:
        """The model-based gains of every joint at the start pose and what bounded each."""
        if self.spec.gain_report is not None:
            return self.spec.gain_report
        from .backendspec import model_gain_report

        spec = self.spec
        return model_gain_report(spec.config, spec.host, spec.initial_positions, spec.servo_timestep,
                                 spec.floating_base)

    @functools.cached_property
    def gain_sources(self) -> tuple[str, ...]:
        """Where each joint's servo gains come from: ``"robot.yaml"``, ``"description"`` or ``"model"``."""
        from .backendspec import gain_sources

        return gain_sources(self.config, self.description, self.joints)

    @property
    def servo_gains(self) -> tuple[Gains, ...]:
        """Servo gains per joint: robot.yaml's, else the description's own servo's, else the model's.

        See :func:`agentsdk.backendspec.gain_sources` for the order; :attr:`gain_sources` says which.
        """
        return self.spec.servo_gains

    @functools.cached_property
    def sensors(self) -> tuple[SensorSpec, ...]:
        """The sensors this backend serves: the declared ones of a kind in :attr:`sensor_kinds` or a joint sensor.

        Declared sensors of other kinds are left out (one warning naming them); a backend adds
        sensors of its own (motor temperatures) with :meth:`_backend_sensors`.
        """
        from .sensors import JOINT_KINDS, declared_sensors

        served: list[SensorSpec] = []
        skipped: list[str] = []
        for spec in (*declared_sensors(self.description, self.config), *self._backend_sensors()):
            if spec.kind in JOINT_KINDS and spec.joint in self.index:
                served.append(spec)
            elif spec.kind in self.sensor_kinds and spec.kind not in JOINT_KINDS:
                served.append(spec)
            else:
                skipped.append(f"{spec.name} ({spec.kind})")
        if skipped:
            log.warning("backend %r does not serve the sensors %s of robot %r; they are left out",
                        self.name, ", ".join(skipped), self.description.name)
        names = [s.name for s in served]
        return tuple(s for k, s in enumerate(served) if s.name not in names[:k])

    def _backend_sensors(self) -> tuple[SensorSpec, ...]:
        """Optional: sensors the backend itself provides beside the declared ones (e.g. motor temperatures)."""
        return ()

    def joint_source(self, index: int) -> str | None:
        """Where joint ``index`` is measured, for messages (e.g. ``"motor id 2 on socketcan:vcan0"``).

        None (the default, simulators) when the joint name says it all; hardware backends name
        the device so that a fault points at the motor, connector or bus to check.
        """
        return None

    @contextlib.contextmanager
    def frame_change(self, index: int) -> Iterator[None]:
        """Wrap a deliberate change of joint ``index``'s reading frame (e.g. a new encoder zero).

        Inside the block the plausibility gate takes that joint's readings as they are (finite
        values only): the jump to the new frame is the backend's doing, not a sensor fault.
        """
        self.frame_changing[index] = True
        self.frame_changes[0] += 1
        try:
            yield
        finally:
            self.frame_changes[0] -= 1
            if not self.frame_changes[0]:
                self.frame_changing[:] = False

    def reading_age(self, now: float | None = None) -> FloatArray | None:
        """How old (s) each joint's latest reading is, or None when every reading is current (the default).

        The plausibility gate (:mod:`agentsdk.plausibility`) bounds a joint's move between two
        readings by the time between their samples. A backend whose :meth:`read` can return old data
        (a bus: the newest reply may predate this cycle, or be delayed) reports its age here, after :meth:`read`, with
        ``now`` the ``time.monotonic()`` of that read when the caller has it (None: read the clock).
        """
        return None

    def base_state(self) -> BaseState:
        """The base's pose and velocity in the world; a fixed base (the default) is the identity at rest."""
        return BaseState(Pose())

    def _validate_options(self, options: dict[str, Any], given: frozenset[str] = frozenset()) -> Any:
        """Validate the merged options with :attr:`options_model`; one error line per problem.

        ``given`` names the options passed to ``connect()`` (or ``-o``); the others
        came from the robot.yaml ``backends.<name>`` section, and the message says which.
        """
        model = self.options_model
        if model is None:
            if options:
                raise ConfigurationError(f"backend {self.name!r} takes no options, got {', '.join(sorted(options))}")
            return None
        try:
            return model(**options)
        except ValidationError as exc:
            from .config import validation_problems

            lines = []
            for line in validation_problems(exc, model):
                key = line.split(":", 1)[0].split(".", 1)[0]
                if key in given:
                    lines.append(f"backend {self.name!r} option {line.replace(': unknown key', ': unknown option', 1)}")
                else:
                    lines.append(f"{self.config.label}: backends.{self.name}.{line}")
            raise ConfigurationError("\n".join(lines)) from None

    # ------------------------------------------------------------ public, final: what the loop calls
    @final
    async def open(self) -> None:
        """Connect to the hardware or build the simulation (the ``_open`` hook).

        On failure the backend is closed again (``_close``) and the error raised:
        an :class:`~agentsdk.errors.AgentSDKError` as it is, anything else as a
        :class:`~agentsdk.errors.BackendStartError` naming the backend and the robot.
        """
        self._backend_open = True  # a failed open is closed like an open one
        try:
            await self._open()
        except (asyncio.CancelledError, AgentSDKError):
            await self.close()
            raise
        except Exception as exc:
            await self.close()
            raise BackendStartError(
                f"backend {self.name!r} failed to start robot {self.description.name!r}: {exc}"
            ) from exc

    @final
    async def close(self) -> None:
        """Leave actuators safe and release resources (the ``_close`` hook). Idempotent: runs once per open."""
        if not self._backend_open:
            return
        self._backend_open = False
        await self._close()

    @final
    def write(self, sp: SetpointView) -> None:
        """Apply the servo setpoint (the ``_write`` hook); once per tick, before :meth:`step`."""
        self._write(sp)

    @final
    def step(self, dt: float) -> Awaitable[None]:
        """Advance one control period (the ``_step`` hook); returns its awaitable."""
        return self._step(dt)

    @final
    def step_runs_inline(self) -> bool:
        """The next :meth:`step` never suspends: it is the ``_step`` of the class declaring ``step_never_suspends``.

        Not a subclass's that did not declare it again, nor one set on the instance (a test's fault injection).
        """
        return getattr(self._step, "__func__", None) is _never_suspending_step(type(self))

    @final
    def read(self) -> JointReading:
        """The latest measured ``(position, velocity, effort)`` (the ``_read`` hook; the arrays may be reused)."""
        return self._read()

    @final
    def emergency_stop(self, category: int = 0) -> None:
        """Remove actuator torque now (the ``_emergency_stop`` hook): synchronous, thread-safe, no event loop."""
        self._emergency_stop(category)

    @final
    def read_sensors(self, channels: Sequence[SensorChannel]) -> None:
        """Fill the due sensor channels (the ``_read_sensors`` hook); once per tick after :meth:`read`."""
        self._read_sensors(channels)

    @final
    async def enable(self) -> None:
        """Re-arm the actuators after an emergency stop (the ``_enable`` hook)."""
        await self._enable()

    @final
    async def recover(self) -> None:
        """Bring a faulted backend back (the ``_recover`` hook); raises BackendFault if it cannot."""
        await self._recover()

    # ------------------------------------------------------------------ hooks
    @abstractmethod
    async def _open(self) -> None:
        """Connect to the hardware or build the simulation; raise BackendStartError on failure."""

    @abstractmethod
    async def _close(self) -> None:
        """Leave actuators safe and release resources. Idempotent; also called after a failed open."""

    @abstractmethod
    def _write(self, sp: SetpointView) -> None:
        """Apply the servo setpoint (called once per tick, before ``_step``)."""

    @abstractmethod
    async def _step(self, dt: float) -> None:
        """Advance one control period (simulation step, or one bus cycle)."""

    @abstractmethod
    def _read(self) -> JointReading:
        """The latest measured ``(position, velocity, effort)``, each of shape ``(n_joints,)``."""

    @abstractmethod
    def _emergency_stop(self, category: int) -> None:
        """Remove actuator torque now: synchronous, thread-safe, needs no event loop.

        Called from any thread (the loop-stall watchdog, ``estop_threadsafe``).
        Categories 1 and 2 are driven by the safety layer through setpoints; this
        hook does what the backend can do without the loop (always torque off).
        """

    def _read_sensors(self, channels: Sequence[SensorChannel]) -> None:  # noqa: B027 - optional hook
        """Optional: write the sample of every channel whose ``due`` flag is set (see :class:`SensorChannel`).

        ``channels[k].spec`` is one of :attr:`sensors`; ``channels[k].index`` its position there.
        Called in the control tick after ``_read``: write into the channel's arrays in place.
        """

    async def _enable(self) -> None:  # noqa: B027 - optional hook
        """Optional: re-arm actuators after an e-stop (CAN: enter motor mode again)."""

    async def _recover(self) -> None:
        """Optional: bring a faulted backend back to a usable state (simulators: reset the world)."""
        raise BackendFault(f"backend {self.name!r} cannot recover from a fault; close and reconnect")


@functools.cache
def _never_suspending_step(cls: type[Backend]) -> Callable[..., Any] | None:
    """The ``_step`` that ``step_never_suspends`` speaks for: that of the class declaring it (None: none)."""
    for klass in cls.__mro__:
        if "step_never_suspends" in vars(klass):
            return vars(klass).get("_step") if klass.step_never_suspends else None  # type: ignore[attr-defined]
    return None


def substeps(period: float, timestep: float, simulator: str, source: str) -> int:
    """Physics steps per control period; raises ConfigurationError unless a whole number in [1, MAX_SUBSTEPS].

    For simulator backends: the control period (robot.yaml ``update_rate``) must be a
    whole multiple of the physics ``timestep``.
    """
    nsub = round(period / timestep)
    if nsub < 1 or abs(nsub * timestep - period) > 1e-9 * max(1.0, period):
        raise ConfigurationError(
            f"{source}: the control period {period:g} s (update_rate {1.0 / period:g} Hz) is not a whole multiple "
            f"of the {simulator} timestep {timestep:g} s; change the backend's timestep or update_rate"
        )
    if nsub > MAX_SUBSTEPS:
        raise ConfigurationError(
            f"{source}: the {simulator} timestep {timestep:g} s needs {nsub} physics steps per control period "
            f"{period:g} s (at most {MAX_SUBSTEPS}); raise the timestep or update_rate"
        )
    return nsub

