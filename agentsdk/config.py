"""robot.yaml schema (pydantic v2), in the spirit of ros2_control's YAML.

Example::

    description: arm3.urdf.xacro        # relative to the robot.yaml
    xacro_args: {link1_length: "0.3"}
    update_rate: 500                    # Hz, like controller_manager.update_rate
    gains:                              # joint servo gains, like ros2_control pid gains
      default: {p: 400.0, d: 10.0}      # (joints without: an MJCF position actuator's, else from the model)
      joint3: {p: 20.0, d: 0.5}
    model_gains: {bandwidth: 10.0, damping_ratio: 1.0}   # Hz; see agentsdk.dynamics.model_gains
    gravity_compensation: true          # or per joint: {default: true, gripper: false}
    joint_limits:                       # like ros2_control joint_limits.yaml
      default: {max_acceleration: 5.0, max_jerk: 100.0}
      joint1: {max_velocity: 1.5}
    initial_positions: {joint2: 0.2}
    initial_group_state: home           # else a named pose: MJCF keyframe or SRDF <group_state> (default:
                                        # home/stand/standing/ready/... when the model has one)
    floating_base: false                # true: free base on a ground plane (simulators; an MJCF free joint floats)
    ground_friction: 0.8                # ground contact friction coefficient (floating base)
    safety: {command_timeout: 0.2}      # see agentsdk.safety.SafetyConfig
    strict: false                       # true: refuse descriptions that need repairs
    trusted: false                      # true: a file you trust (xacro unchecked, files outside its package)
    self_collision: auto                # auto | true | false, the same on every simulator
    srdf: arm3.srdf                     # <disable_collisions> pairs (default: an SRDF beside the URDF)
    backends:                           # backend-specific sections, free-form per backend
      mujoco: {timestep: 0.001}
      pybullet: {timestep: 0.001}
"""

from __future__ import annotations

import difflib
import math
import types
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, ValidationError, field_validator

from .errors import ConfigurationError

__all__ = [
    "MAX_GAIN",
    "MAX_UPDATE_RATE",
    "MIN_UPDATE_RATE",
    "Gains",
    "JointLimitsOverride",
    "ModelGains",
    "RobotConfig",
    "did_you_mean",
    "format_value",
    "load_robot_config",
    "validation_problems",
]

#: highest accepted control rate (Hz); ros2_control robots run at 1 kHz, a few at 4-8 kHz
MAX_UPDATE_RATE = 10_000.0
#: lowest accepted control rate (Hz): below it the command watchdog and stops cannot act in time
MIN_UPDATE_RATE = 1.0
#: largest accepted servo gain (N·m/rad, N·m·s/rad or N/m, N·s/m): beyond any real joint servo
MAX_GAIN = 1e9


#: smallest velocity (rad/s), acceleration (rad/s^2) and jerk (rad/s^3) limit accepted in robot.yaml
MIN_MOTION_LIMIT = 1e-3


class _Strict(BaseModel):
    # every number must be finite: a NaN or inf setting has no meaning (NaN compares false
    # with every bound, so it would silently disable the check it configures)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Gains(_Strict):
    """Joint servo gains: ``effort = p*(q_des - q) + d*(v_des - v) + effort_ff``."""

    p: float = Field(ge=0.0, le=MAX_GAIN)
    d: float = Field(ge=0.0, le=MAX_GAIN)
    #: velocity-mode gain (``effort = v*(v_des - v)``); defaults to ``d``
    v: float | None = Field(default=None, ge=0.0, le=MAX_GAIN)


class ModelGains(_Strict):
    """How servo gains are computed from the model for joints robot.yaml gives no gains for.

    Per joint, from the joint-space inertia at the start pose: a position loop of
    ``bandwidth`` Hz with damping ratio ``damping_ratio``, bounded by the effort limit
    and by what the simulator's timestep integrates stably (see
    :func:`agentsdk.dynamics.model_gains` for the formula).
    """

    #: closed-loop bandwidth of each joint's position servo (Hz)
    bandwidth: PositiveFloat = 10.0
    #: damping ratio of each joint's position servo (1: critically damped)
    damping_ratio: PositiveFloat = 1.0


class JointLimitsOverride(_Strict):
    """Per-joint limit overrides; unset fields keep the URDF value.

    Names follow ros2_control's joint_limits.yaml. Every value is finite; position,
    velocity and effort limits can only narrow the URDF's (see
    :func:`agentsdk.description.apply_overrides`).
    """

    min_position: float | None = None
    max_position: float | None = None
    # (a floor, not just > 0: ruckig cannot time a stop under a subnormal limit, and a stop
    # that takes hours is no stop)
    max_velocity: float | None = Field(default=None, ge=MIN_MOTION_LIMIT)
    max_acceleration: float | None = Field(default=None, ge=MIN_MOTION_LIMIT)
    max_jerk: float | None = Field(default=None, ge=MIN_MOTION_LIMIT)
    max_effort: float | None = Field(default=None, gt=0.0)


class RobotConfig(_Strict):
    """Validated content of a robot.yaml."""

    name: str = ""
    description: str
    xacro_args: dict[str, str] = Field(default_factory=dict)
    #: control rate (Hz), like controller_manager.update_rate
    update_rate: float = Field(default=500.0, ge=MIN_UPDATE_RATE, le=MAX_UPDATE_RATE)
    #: explicit servo gains by joint (or ``default``); joints without any get gains from the model
    gains: dict[str, Gains] = Field(default_factory=dict)
    #: bandwidth and damping ratio of the gains computed from the model
    model_gains: ModelGains = Field(default_factory=ModelGains)
    #: add the model's gravity torque g(q) to every joint's servo law (``true``/``false``, or per joint
    #: ``{default: true, joint: false}``)
    gravity_compensation: bool | dict[str, bool] = True
    #: add the inverse dynamics of the desired motion (``M(q) q̈* + C(q, q̇*) q̇*`` and the joints' damping
    #: and friction at ``q̇*``) to the servo law (a backend option ``inverse_dynamics`` overrides it; see
    #: :mod:`agentsdk.feedforward`)
    inverse_dynamics: bool = True
    joint_limits: dict[str, JointLimitsOverride] = Field(default_factory=dict)
    initial_positions: dict[str, float] = Field(default_factory=dict)
    #: an SRDF ``<group_state>`` the joints start in (those not in ``initial_positions``)
    initial_group_state: str | None = None
    #: simulators: a free-floating base standing on a ground plane instead of a base fixed to the world
    floating_base: bool = False
    #: Coulomb friction coefficient of the robot on the ground plane (floating base), the same on every simulator
    ground_friction: PositiveFloat = 0.8
    safety: dict[str, Any] = Field(default_factory=dict)
    #: sensors beside those the description declares (validated by :mod:`agentsdk.sensors`)
    sensors: list[dict[str, Any]] = Field(default_factory=list)
    #: seed of the sensors' simulated noise (deterministic in lockstep)
    sensor_seed: int = 0
    backends: dict[str, dict[str, Any]] = Field(default_factory=dict)
    #: refuse a description that needs repairs (DescriptionError) instead of repairing it with a warning
    strict: bool = False
    #: load the description as trusted code: xacro expressions unchecked, files outside the package roots
    #: allowed (default false: robot files are data; see README "Bring your own robot")
    trusted: bool = False
    #: self-collision on every simulator: ``auto`` (on, except pairs that are adjacent, rigidly attached,
    #: touching at the start pose or disabled in the SRDF), ``true`` (on, except adjacent, rigidly
    #: attached and SRDF pairs), ``false`` (links of the robot never collide with each other)
    self_collision: Literal["auto"] | bool = "auto"
    #: SRDF whose ``<disable_collisions>`` are honoured (relative to this file); default: one beside the URDF
    srdf: str | None = None
    #: directory the relative ``description`` path is resolved against
    base_dir: Path = Field(default=Path("."), exclude=True)
    #: the robot.yaml this was read from (None for a bare description); named in error messages
    source: Path | None = Field(default=None, exclude=True)

    @field_validator("xacro_args", mode="before")
    @classmethod
    def _stringify_args(cls, v: Any) -> Any:
        if isinstance(v, dict):
            return {str(k): str(val) for k, val in v.items()}
        return v

    @property
    def description_path(self) -> Path:
        """The ``description`` file as an absolute path."""
        return (self.base_dir / self.description).resolve()

    @property
    def srdf_path(self) -> Path | None:
        """The robot.yaml ``srdf`` as an absolute path (None when not given)."""
        return (self.base_dir / self.srdf).resolve() if self.srdf else None

    def with_update_rate(self, update_rate: float) -> RobotConfig:
        """This configuration at another control rate (Hz), validated like robot.yaml's ``update_rate``."""
        rate = float(update_rate)
        if not MIN_UPDATE_RATE <= rate <= MAX_UPDATE_RATE:  # NaN fails too
            raise ConfigurationError(
                f"{self.label}: update_rate {update_rate!r} Hz is outside [{MIN_UPDATE_RATE:g}, {MAX_UPDATE_RATE:g}]"
            )
        return self.model_copy(update={"update_rate": rate})

    @property
    def control_period(self) -> float:
        """Seconds per control tick (``1 / update_rate``)."""
        return 1.0 / self.update_rate

    @property
    def label(self) -> str:
        """How error messages name this configuration: the robot.yaml path, else the robot."""
        return str(self.source) if self.source is not None else f"robot {self.name!r}"

    def gains_for(self, joint: str) -> Gains | None:
        """The robot.yaml gains of ``joint`` (its own, else ``default``); None: computed from the model."""
        return self.gains.get(joint) or self.gains.get("default")

    def gravity_compensation_for(self, joint: str) -> bool:
        """Whether ``joint``'s servo law adds the model's gravity torque (robot.yaml ``gravity_compensation``)."""
        gc = self.gravity_compensation
        if isinstance(gc, bool):
            return gc
        return gc.get(joint, gc.get("default", True))

    def backend_options(self, backend: str) -> dict[str, Any]:
        """The robot.yaml ``backends.<backend>`` section (a copy; empty when absent)."""
        return dict(self.backends.get(backend, {}))


def load_robot_config(path: str | Path) -> RobotConfig:
    """Read and validate a robot.yaml; errors name the file and the field."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise ConfigurationError(f"robot config not found: {path}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigurationError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason})") from exc
    except OSError as exc:
        raise ConfigurationError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    except yaml.YAMLError as exc:
        raise ConfigurationError(f"{path}: invalid YAML: {exc}") from exc
    except RecursionError as exc:
        raise ConfigurationError(f"{path}: invalid YAML: nested too deeply") from exc
    if not isinstance(raw, dict):
        raise ConfigurationError(f"{path}: expected a mapping at the top level")
    raw.setdefault("name", path.parent.name)
    bad = [str(k) for k in raw if not isinstance(k, str)]
    if bad:
        raise ConfigurationError(f"{path}: top-level keys must be names, got {', '.join(bad)}")
    for key in ("base_dir", "source"):
        if key in raw:  # set by the loader, not in the file
            raise ConfigurationError(f"{path}: {key}: unknown key{did_you_mean(key, _file_keys())}")
    try:
        return RobotConfig(**raw, base_dir=path.parent, source=path)
    except ValidationError as exc:
        raise ConfigurationError("\n".join(validation_problems(exc, RobotConfig, source=str(path)))) from None


def _file_keys() -> list[str]:
    return [k for k in RobotConfig.model_fields if k not in ("base_dir", "source")]


# ------------------------------------------------------------------ error messages
def format_value(value: Any) -> str:
    """A value as a user wrote it: ``nan``, ``inf``, ``0.5``, ``'text'`` (never ``np.float64(nan)``)."""
    if isinstance(value, bool) or value is None:
        return {True: "true", False: "false", None: "null"}[value]
    if isinstance(value, str):
        return repr(value)
    try:
        import numpy as np

        if isinstance(value, np.generic):
            value = value.item()
    except ImportError:  # pragma: no cover - numpy is a dependency
        pass
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return f"{value:g}" if abs(value) >= 1e-4 or value == 0 else repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{k}: {format_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    return repr(value)


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the closest of ``choices``, else ``"; expected one of: ..."``."""
    options = sorted({str(c) for c in choices})
    close = difflib.get_close_matches(str(word), options, n=1, cutoff=0.6)
    if close:
        return f"; did you mean {close[0]!r}?"
    if options:
        return f"; expected one of: {', '.join(options)}"
    return ""


_OPS = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}


def _expected(err: Mapping[str, Any]) -> str:
    kind = err["type"]
    ctx = err.get("ctx") or {}
    if kind in _OPS:
        bound = next(iter(ctx.values()), "?")
        return f"expected a number {_OPS[kind]} {format_value(bound)}"
    simple = {
        "finite_number": "expected a finite number",
        "float_parsing": "expected a number",
        "float_type": "expected a number",
        "int_parsing": "expected an integer",
        "int_type": "expected an integer",
        "int_from_float": "expected an integer",
        "bool_parsing": "expected true or false",
        "bool_type": "expected true or false",
        "string_type": "expected a string",
        "dict_type": "expected a mapping",
        "model_type": "expected a mapping",
        "model_attributes_type": "expected a mapping",
        "tuple_type": "expected a list",
        "list_type": "expected a list",
        "missing": "required but missing",
    }
    if kind in simple:
        return simple[kind]
    if kind == "literal_error":
        return f"expected {ctx.get('expected', '?')}"
    msg = str(err.get("msg", kind))
    for prefix in ("Value error, ", "Assertion failed, "):
        if msg.startswith(prefix):
            return msg[len(prefix):]
    if msg.startswith("Input should be "):
        return "expected " + msg[len("Input should be "):]
    return msg[:1].lower() + msg[1:]


def _unwrap(tp: Any) -> Any:
    while typing.get_origin(tp) is Annotated:
        tp = typing.get_args(tp)[0]
    return tp


def _bounds(field: Any) -> str:
    """The numeric bounds declared on a pydantic field, as text (``>= 1 and <= 10000``)."""
    parts = []
    for meta in getattr(field, "metadata", ()):
        for attr, op in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            bound = getattr(meta, attr, None)
            if bound is not None:
                parts.append(f"{op} {format_value(bound)}")
    return " and ".join(parts)


def _walk(model: Any, loc: tuple[Any, ...]) -> tuple[list[str], Any, bool, Any]:
    """Follow a pydantic error location through the model's types.

    Returns ``(path, owner, extra, field)``: the user's key path (union member
    tags removed), the model the last key belongs to (for "did you mean"),
    whether the last key is an unknown key of that model, and the pydantic field
    of the last model key on the way (for its bounds).
    """
    path: list[str] = []
    tp: Any = model
    parent: Any = None
    last_field: Any = None
    for elem in loc:
        tp = _unwrap(tp)
        origin = typing.get_origin(tp)
        if origin in (Union, types.UnionType):
            members = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(members) > 1:
                tp = None  # pydantic names the union member it tried: not a key of the user's
                continue
            tp = _unwrap(members[0])
            origin = typing.get_origin(tp)
        path.append(str(elem))
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            parent = tp
            field = tp.model_fields.get(str(elem))
            if field is None:
                return path, parent, True, None
            tp = field.annotation
            last_field = field
        elif origin in (dict, Mapping):
            parent, tp = None, typing.get_args(tp)[1] if typing.get_args(tp) else None
        elif origin in (list, tuple):
            args = [a for a in typing.get_args(tp) if a is not Ellipsis]
            parent, tp = None, (args[0] if len(set(args)) == 1 else None)
        else:
            parent, tp = None, None
    return path, parent, False, last_field


def validation_problems(
    exc: ValidationError,
    model: type[BaseModel],
    *,
    source: str = "",
    prefix: str = "",
) -> list[str]:
    """One line per problem of a pydantic ``ValidationError``: ``source: key.path: expected ..., got ...``.

    ``prefix`` is prepended to every key path (``backends.mujoco``); an unknown
    key gets a "did you mean ...?" from the keys the model accepts there.
    Errors on one key (e.g. each member of ``float | "auto"``) share one line.
    """
    lines: dict[str, tuple[list[str], str]] = {}
    for err in exc.errors():
        path, owner, extra, field = _walk(model, tuple(err["loc"]))
        key = ".".join([prefix, *path] if prefix else path) or "(top level)"
        if err["type"] == "extra_forbidden" or extra:
            known = list(owner.model_fields) if owner is not None else []
            known = [k for k in known if not (owner is RobotConfig and k in ("base_dir", "source"))]
            text = f"unknown key{did_you_mean(path[-1] if path else '', known)}"
            got = ""
        else:
            text = _expected(err)
            bounds = _bounds(field) if err["type"] in ("finite_number", *_OPS) else ""
            if bounds:
                kind = "an integer" if _unwrap(getattr(field, "annotation", None)) is int else "a finite number"
                text = f"expected {kind} {bounds}"
            got = "" if err["type"] == "missing" else f", got {format_value(err.get('input'))}"
        expected, _ = lines.setdefault(key, ([], got))
        if text not in expected:
            expected.append(text)
    where = f"{source}: " if source else ""
    out = []
    for key, (expected, got) in lines.items():
        merged = " or ".join([expected[0], *(e.removeprefix("expected ") for e in expected[1:])])
        out.append(f"{where}{key}: {merged}{got}")
    return out
