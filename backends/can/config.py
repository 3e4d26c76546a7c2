"""Schema of the ``backends.can`` section of a robot.yaml (MIT-protocol motors on one CAN bus).

Example::

    backends:
      can:
        interface: socketcan
        channel: vcan0
        bitrate: 1000000
        profile: cubemars        # reply layout: cubemars | damiao | katz
        master_id: 0             # arbitration id of the replies
        timeout: 0.025           # motor-side command timeout [s] (firmware setting; emulator)
        motors:
          hip_abduction: {id: 1, model: AK80-9, direction: 1, zero_offset: 0.0, gear_ratio: 1.0}
          knee:          {id: 3, model: AK70-10, ranges: {t_min: -20.0, t_max: 20.0}}

Motor keys are joint names. ``direction``, ``zero_offset`` and ``gear_ratio`` map the joint
frame to the motor frame, ``q_motor = direction * gear_ratio * q_joint + zero_offset``
(``zero_offset`` is in motor radians; the convention of the CAN controller). The emulator
works in the motor frame.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from agentsdk.backends.can.mit import PROFILES, MotorRanges, VendorProfile, profile_for, ranges_for
from agentsdk.config import RobotConfig, load_robot_config
from agentsdk.errors import ConfigurationError
from agentsdk.robots import ROBOTS_DIR as _SHIPPED_ROBOTS

__all__ = ["ROBOTS_DIR", "CanBusConfig", "CanMotorConfig", "load_can_config", "parse_can_config", "robot_yaml_path"]

#: Where robot names are looked up: ``<ROBOTS_DIR>/<name>/robot.yaml`` (the shipped robots).
ROBOTS_DIR: Path = _SHIPPED_ROBOTS

_MAX_STD_ID = 0x7FF
#: longest accepted motor-side command timeout (s): beyond it a motor keeps running on a dead bus
MAX_TIMEOUT = 10.0
_T = TypeVar("_T")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class CanMotorConfig(_Strict):
    """One MIT motor: CAN id, model (ranges table key) and the motor -> joint mapping."""

    id: int = Field(ge=1, le=_MAX_STD_ID)
    model: str
    direction: Literal[1, -1] = 1
    #: motor radians at joint zero
    zero_offset: float = Field(default=0.0, ge=-1e3, le=1e3)
    #: motor turns per joint turn (gains scale with its square: kept within [0.01, 1000])
    gear_ratio: float = Field(default=1.0, ge=0.01, le=1000.0)
    #: per-field overrides of the model's ranges (``p_min``, ``t_max`` ...), for other firmware
    ranges: dict[str, float] | None = None
    #: motor-side command timeout [s]; ``None`` = the bus-level ``timeout``
    timeout: Annotated[float, Field(gt=0.0, le=MAX_TIMEOUT)] | None = None

    @field_validator("model")
    @classmethod
    def _known_model(cls, v: str) -> str:
        _as_value_error(ranges_for, v)
        return v

    @model_validator(mode="after")
    def _valid_ranges(self) -> CanMotorConfig:
        if self.ranges:
            _as_value_error(ranges_for, self.model, self.ranges)
        return self

    @property
    def motor_ranges(self) -> MotorRanges:
        """The model's ranges with this motor's overrides applied."""
        return ranges_for(self.model, self.ranges)


class CanBusConfig(_Strict):
    """The ``backends.can`` section: bus parameters, reply layout and the motors by joint name."""

    interface: str = "socketcan"
    channel: str = "vcan0"
    #: nominal bit rate (bit/s; classic CAN tops out at 1 Mbit/s)
    bitrate: int = Field(default=1_000_000, ge=10_000, le=1_000_000)
    profile: str = "cubemars"
    master_id: int = Field(default=0, ge=0, le=_MAX_STD_ID)
    #: motor-side command timeout [s] (Katz firmware CAN_TIMEOUT, ~25 ms)
    timeout: float = Field(default=0.025, gt=0.0, le=MAX_TIMEOUT)
    motors: dict[str, CanMotorConfig] = Field(min_length=1)

    @field_validator("profile")
    @classmethod
    def _known_profile(cls, v: str) -> str:
        return _as_value_error(profile_for, v).name

    @model_validator(mode="after")
    def _unique_ids(self) -> CanBusConfig:
        seen: dict[int, str] = {}
        reply_ids: dict[int, str] = {}
        mask = self.vendor_profile.id_mask
        for joint, m in self.motors.items():
            if m.id == self.master_id:
                raise ValueError(f"motor {joint!r}: id {m.id} equals master_id (the reply id)")
            if m.id in seen:
                raise ValueError(f"motors {seen[m.id]!r} and {joint!r} share CAN id {m.id}")
            seen[m.id] = joint
            # The reply names its motor by byte 0, which carries only the low bits of the id.
            other = reply_ids.setdefault(m.id & mask, joint)
            if other != joint:
                raise ValueError(
                    f"motors {other!r} (id {self.motors[other].id}) and {joint!r} (id {m.id}) are indistinguishable"
                    f" in {self.profile} replies (byte 0 carries id & {mask:#x})"
                )
        return self

    @property
    def vendor_profile(self) -> VendorProfile:
        """The vendor profile (value ranges, special frames) this motor speaks."""
        return PROFILES[self.profile]

    def motor_timeout(self, joint: str) -> float:
        """Motor-side command timeout of ``joint`` [s]."""
        t = self.motors[joint].timeout
        return self.timeout if t is None else t


def _as_value_error(fn: Callable[..., _T], *args: Any) -> _T:
    """Run ``fn``; a ConfigurationError becomes a ValueError so pydantic reports it with its field."""
    try:
        return fn(*args)
    except ConfigurationError as exc:
        raise ValueError(str(exc)) from None


def parse_can_config(section: Mapping[str, Any] | None, *, source: str = "robot.yaml") -> CanBusConfig:
    """Validate a ``backends.can`` mapping; errors raise ConfigurationError naming ``source`` and the field."""
    if not section:
        raise ConfigurationError(f"{source}: no backends.can section (needed by the CAN backend)")
    try:
        return CanBusConfig.model_validate(dict(section))
    except ValidationError as exc:
        from agentsdk.config import validation_problems

        lines = validation_problems(exc, CanBusConfig, source=source, prefix="backends.can")
        raise ConfigurationError("\n".join(lines)) from None


def robot_yaml_path(robot: str | Path) -> Path:
    """The robot.yaml of ``robot``: a robot.yaml path, a directory holding one, or a name under :data:`ROBOTS_DIR`."""
    p = Path(robot)
    if p.suffix in {".yaml", ".yml"}:
        return p
    if p.is_dir():
        return p / "robot.yaml"
    if isinstance(robot, str) and "/" not in robot and (ROBOTS_DIR / robot).is_dir():
        return ROBOTS_DIR / robot / "robot.yaml"
    known = sorted(d.name for d in ROBOTS_DIR.iterdir() if (d / "robot.yaml").is_file()) if ROBOTS_DIR.is_dir() else []
    raise ConfigurationError(f"unknown robot {robot!r}: not a robot.yaml or directory; robots: {', '.join(known)}")


def load_can_config(robot: str | Path) -> tuple[RobotConfig, CanBusConfig]:
    """Load the robot.yaml of ``robot`` (see :func:`robot_yaml_path`) and validate its ``backends.can``."""
    path = robot_yaml_path(robot)
    cfg = load_robot_config(path)
    return cfg, parse_can_config(cfg.backend_options("can"), source=str(path))
