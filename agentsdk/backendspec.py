"""What a backend is built from, as one immutable value: :class:`BackendSpec`.

The joints with their limits after robot.yaml overrides, the validated options, the start pose,
the servo gains, the gravity-compensation and inverse-dynamics flags of the servo law, the control
period, the time model and the robot's one host-side model (:class:`HostModelSource`: compiled
once, shared by the kinematics and the dynamics). :meth:`BackendSpec.build` derives it from the
robot's configuration and description; a backend is constructed from it (``Backend(spec)``,
``backend.spec``), so a backend reads ready values instead of computing them in its constructor,
and the derivation is one function that can be called (and tested) without a backend.
"""

from __future__ import annotations

import inspect
import logging
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from .types import FloatArray, JointInfo

if TYPE_CHECKING:
    from .config import Gains, RobotConfig
    from .description import RobotDescription
    from .description.start import StartPose
    from .dynamics import GainReport
    from .hostmodel import HostModel

__all__ = ["BackendSpec", "HostModelSource"]

#: gravity of the host model when the backend has no ``gravity`` option (m/s², world frame)
STANDARD_GRAVITY = (0.0, 0.0, -9.81)

log = logging.getLogger("agentsdk")


def _readonly(values: Any) -> FloatArray:
    arr = np.array(values, dtype=np.float64)
    arr.flags.writeable = False
    return arr


class SpecHooks(Protocol):
    """What :meth:`BackendSpec.derive` reads of the backend being built (an instance before construction).

    ``agentsdk.backend.Backend`` implements it: the hooks may read ``config``, ``description``,
    ``joints``, ``names``, ``index``, ``period``, ``realtime`` and ``options``, which ``derive``
    sets first.
    """

    @property
    def name(self) -> str: ...

    @property
    def capabilities(self) -> Any: ...

    config: RobotConfig
    description: RobotDescription
    joints: tuple[JointInfo, ...]
    realtime: bool
    names: tuple[str, ...]
    index: dict[str, int]
    period: float
    options: Any

    @classmethod
    def default_realtime(cls, config: RobotConfig, options: dict[str, Any]) -> bool: ...

    def _validate_options(self, options: dict[str, Any], given: frozenset[str] = ...) -> Any: ...

    @property
    def servo_timestep(self) -> float | None: ...

    @property
    def floating_base(self) -> bool: ...


def takes_spec(cls: type, base: type) -> bool:
    """True when ``cls(spec)`` constructs the backend class ``cls`` (a subclass of ``base``).

    No ``__init__`` of its own, one whose first parameter is ``spec``, or one passing ``*args``
    on; False for an ``__init__(self, config, description, joints, ...)`` of earlier releases.
    """
    for klass in cls.__mro__:
        if klass is base:
            return True
        init = klass.__dict__.get("__init__")
        if init is None:
            continue
        params = list(inspect.signature(init).parameters.values())[1:]
        positional = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
        if positional:
            return positional[0].name == "spec"
        return any(p.kind is p.VAR_POSITIONAL for p in params)
    return True


class HostModelSource:
    """The robot's one host-side model (:class:`~agentsdk.hostmodel.HostModel`), compiled on first use.

    :meth:`get` compiles the description once (thread-safe) and returns the same model to every
    caller: the servo gains, the backend's :attr:`~agentsdk.backend.Backend.dynamics` and the
    robot's :attr:`~agentsdk.Robot.kinematics`. A description MuJoCo cannot build raises
    :class:`~agentsdk.errors.DescriptionError` at every call (the error is kept, not retried).
    """

    def __init__(
        self,
        description: RobotDescription,
        joints: Sequence[JointInfo],
        *,
        gravity: Sequence[float] = STANDARD_GRAVITY,
        floating_base: bool = False,
    ) -> None:
        self.description = description
        self.joints = tuple(joints)
        #: the host model's gravity vector (a simulator's ``gravity`` option, else standard gravity)
        self.gravity = tuple(float(v) for v in gravity)
        #: the host model frees the root body (the backend's floating base)
        self.floating_base = bool(floating_base)
        self._lock = threading.Lock()
        self._model: HostModel | None = None
        self._error: Exception | None = None

    @property
    def built(self) -> bool:
        """True once the model was compiled."""
        return self._model is not None

    def get(self) -> HostModel:
        """The compiled host model (compiled by the first call)."""
        model = self._model
        if model is not None:
            return model
        with self._lock:
            if self._model is None and self._error is None:
                from .hostmodel import HostModel

                try:
                    self._model = HostModel.compile(
                        self.description, self.joints, gravity=self.gravity, floating_base=self.floating_base
                    )
                except Exception as exc:
                    self._error = exc
            if self._error is not None:
                raise self._error
            assert self._model is not None
            return self._model

    def __repr__(self) -> str:
        return f"<HostModelSource {self.description.name!r}{' (compiled)' if self.built else ''}>"


@dataclass(frozen=True, eq=False)
class BackendSpec:
    """The ready values a backend is built from (every array read-only, in ``joints`` order)."""

    #: the validated robot.yaml (or defaults for a bare description)
    config: RobotConfig
    #: the loaded robot description
    description: RobotDescription
    #: actuated joints in order, with limits after robot.yaml overrides
    joints: tuple[JointInfo, ...]
    #: True when paced to the wall clock, False in lockstep
    realtime: bool
    #: the validated backend options (an instance of the backend's ``options_model``, or None)
    options: Any
    #: control period (s)
    period: float
    #: joint names in ``joints`` order
    names: tuple[str, ...]
    #: position limits, velocity and effort limits per joint
    lower: FloatArray
    upper: FloatArray
    max_velocity: FloatArray
    max_effort: FloatArray
    #: the start pose and where each joint's value came from (:mod:`agentsdk.description.start`)
    start_pose: StartPose
    #: where the joints start: robot.yaml ``initial_positions``, an SRDF group state, the model's
    #: home pose, else 0 -- always inside the limits
    initial_positions: FloatArray
    #: per joint: the servo law adds the model's gravity torque (robot.yaml ``gravity_compensation``,
    #: a backend option ``gravity_compensation`` overrides it for every joint)
    gravity_compensation: np.ndarray
    #: the servo law adds the inverse dynamics of the desired motion (robot.yaml ``inverse_dynamics``,
    #: or the backend option of that name)
    inverse_dynamics: bool
    #: the robot's base floats (robot.yaml ``floating_base``, a free joint at an MJCF root, or the
    #: backend's option): the host model frees its root body and the gains carry the body
    floating_base: bool
    #: the step at which the servo law is integrated (a simulator's physics timestep), or None
    servo_timestep: float | None
    #: the robot's one host-side model, compiled on first use and shared (kinematics, dynamics, gains)
    host: HostModelSource
    #: servo gains per joint: robot.yaml ``gains`` (the joint's, else ``default``), else from the model
    servo_gains: tuple[Gains, ...]
    #: the model-based gains at the start pose and what bounded each (None when robot.yaml sets every
    #: joint's gains: then :attr:`~agentsdk.backend.Backend.model_gain_report` computes it on demand)
    gain_report: GainReport | None

    @classmethod
    def derive(
        cls,
        backend: SpecHooks,
        config: RobotConfig,
        description: RobotDescription,
        joints: tuple[JointInfo, ...],
        realtime: bool | None,
        options: dict[str, Any],
    ) -> BackendSpec:
        """The spec of ``backend`` (an instance of its class, not yet constructed) for this robot.

        Checks the time model (``realtime=None``: the class's ``default_realtime``), merges
        robot.yaml ``backends.<name>`` with ``options``, validates them through the backend's
        ``_validate_options`` hook, and builds the spec with its ``servo_timestep`` and
        ``floating_base`` for those options. Sets the attributes the hooks read (see
        :class:`SpecHooks`) on ``backend``.
        """
        from .errors import ConfigurationError

        caps = backend.capabilities
        merged = {**config.backend_options(backend.name), **options}
        if realtime is None:
            realtime = type(backend).default_realtime(config, merged)
        if realtime and not caps.realtime:
            raise ConfigurationError(f"backend {backend.name!r} does not support realtime=True")
        if not realtime and not caps.lockstep:
            raise ConfigurationError(f"backend {backend.name!r} runs in real time only; lockstep is not supported")
        backend.config, backend.description, backend.joints = config, description, joints
        backend.realtime = bool(realtime)
        backend.names = tuple(j.name for j in joints)
        backend.index = {n: i for i, n in enumerate(backend.names)}
        backend.period = config.control_period
        validated = backend._validate_options(merged, given=frozenset(options))
        backend.options = validated  # servo_timestep and floating_base may read the options
        return cls.build(config, description, joints, validated, realtime=backend.realtime,
                         servo_timestep=backend.servo_timestep, floating_base=backend.floating_base)

    @classmethod
    def build(
        cls,
        config: RobotConfig,
        description: RobotDescription,
        joints: tuple[JointInfo, ...],
        options: Any,
        *,
        realtime: bool,
        servo_timestep: float | None = None,
        floating_base: bool | None = None,
    ) -> BackendSpec:
        """Derive the spec from the configuration, the description, the joints and the validated options.

        ``servo_timestep`` and ``floating_base`` are the backend's (its physics step, whether its
        base floats; default: none, and robot.yaml's ``floating_base`` or a free joint at an MJCF
        root). The servo gains are computed here (compiling the host model when a joint has no
        robot.yaml gains). Logs the start pose's warning (a joint whose start value had to be
        moved into its limits).
        """
        from .description.start import start_pose

        start = start_pose(description, config, joints)
        warning = start.warning(config.name or description.name)
        if warning:
            log.warning("%s", warning)
        gc = np.array([config.gravity_compensation_for(j.name) for j in joints], dtype=bool)
        override = getattr(options, "gravity_compensation", None)  # a backend option may switch it
        if override is not None:
            gc[:] = bool(override)
        gc.flags.writeable = False
        id_override = getattr(options, "inverse_dynamics", None)  # connect(..., inverse_dynamics=...)
        if floating_base is None:
            floating_base = bool(config.floating_base) or description.free_root is not None
        gravity = getattr(options, "gravity", None)  # a simulator's gravity option: the host model's too
        host = HostModelSource(
            description, joints, gravity=STANDARD_GRAVITY if gravity is None else gravity, floating_base=floating_base
        )
        initial = _readonly([start.positions[j.name] for j in joints])
        gains, report = _servo_gains(config, description, joints, host, initial, servo_timestep, floating_base)
        return cls(
            config=config,
            description=description,
            joints=joints,
            realtime=bool(realtime),
            options=options,
            period=config.control_period,
            names=tuple(j.name for j in joints),
            lower=_readonly([j.lower for j in joints]),
            upper=_readonly([j.upper for j in joints]),
            max_velocity=_readonly([j.max_velocity for j in joints]),
            max_effort=_readonly([j.max_effort for j in joints]),
            start_pose=start,
            initial_positions=initial,
            gravity_compensation=gc,
            inverse_dynamics=bool(config.inverse_dynamics if id_override is None else id_override),
            floating_base=bool(floating_base),
            servo_timestep=servo_timestep,
            host=host,
            servo_gains=gains,
            gain_report=report,
        )


def model_gain_report(
    config: RobotConfig,
    host: HostModelSource,
    initial_positions: FloatArray,
    servo_timestep: float | None,
    floating_base: bool,
) -> GainReport:
    """The model-based gains of every joint at ``initial_positions`` (:func:`agentsdk.dynamics.model_gains`)."""
    from .dynamics import DynamicsModel

    mg = config.model_gains
    model = host.get()
    return DynamicsModel(model.description, model.joints, host=model).gains(
        initial_positions,
        bandwidth=mg.bandwidth,
        damping_ratio=mg.damping_ratio,
        timestep=servo_timestep,
        floating_base=floating_base,
    )


def gain_sources(
    config: RobotConfig, description: RobotDescription, joints: tuple[JointInfo, ...]
) -> tuple[str, ...]:
    """Where each joint's servo gains come from, in the order they are looked for.

    ``"robot.yaml"`` (the joint's entry, else ``default``), ``"description"`` (the position servo
    the description declares for the joint, :attr:`RobotDescription.declared_gains`: an MJCF
    position actuator's ``kp``/``kv``, the robot author's gains, as a ros2_control user takes the
    controller YAML the robot ships; lowered only where the simulator's timestep could not
    integrate them, :func:`agentsdk.dynamics.declared_gains`) or ``"model"``
    (:func:`~agentsdk.dynamics.model_gains`).
    """
    declared = description.declared_gains
    return tuple(
        "robot.yaml" if config.gains_for(j.name) is not None else "description" if j.name in declared else "model"
        for j in joints
    )


def _servo_gains(
    config: RobotConfig,
    description: RobotDescription,
    joints: tuple[JointInfo, ...],
    host: HostModelSource,
    initial_positions: FloatArray,
    servo_timestep: float | None,
    floating_base: bool,
) -> tuple[tuple[Gains, ...], GainReport | None]:
    """robot.yaml ``gains`` per joint (its own, else ``default``), else the description's servo's, else the model's."""
    from .config import MAX_GAIN
    from .errors import DescriptionError

    explicit = [config.gains_for(j.name) for j in joints]
    if all(g is not None for g in explicit):
        return tuple(g for g in explicit if g is not None), None
    report = model_gain_report(config, host, initial_positions, servo_timestep, floating_base)
    declared = description.declared_gains
    if any(j.name in declared for j in joints):  # the description's own position servos (MJCF actuators)
        from .dynamics import declared_gains

        damping = np.array([description.joint_record(j.name).damping for j in joints])
        own = declared_gains([declared.get(j.name) for j in joints], report, damping, servo_timestep,
                             config.model_gains.damping_ratio)
        explicit = [g if g is not None else own[k] for k, g in enumerate(explicit)]
        if all(g is not None for g in explicit):
            return tuple(g for g in explicit if g is not None), report
    bad = [
        f"{j.name} (kp {p:g}, kd {d:g})"
        for j, p, d, g in zip(joints, report.kp, report.kd, explicit, strict=True)
        if g is None and not (math.isfinite(p) and math.isfinite(d) and 0 <= p <= MAX_GAIN and 0 <= d <= MAX_GAIN)
    ]
    if bad:  # a degenerate mass model (an inertia of 1e30 beside one of 1e-4): no usable servo
        raise DescriptionError(
            f"{description.source}: the model's masses and inertias give no usable servo gains for "
            f"{', '.join(bad)}; fix the description's <inertial> values or set gains for them in robot.yaml"
        )
    model = report.as_gains()
    return tuple(g if g is not None else model[k] for k, g in enumerate(explicit)), report
