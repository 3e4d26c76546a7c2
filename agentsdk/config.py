"""robot.yaml schema (pydantic v2), in the spirit of ros2_control's YAML.

Example::

    description: arm3.urdf.xacro        # relative to the robot.yaml
    xacro_args: {link1_length: "0.3"}
    update_rate: 500                    # Hz, like controller_manager.update_rate
    gains:                              # joint servo gains, like ros2_control pid gains
      default: {p: 400.0, d: 10.0}
      joint3: {p: 20.0, d: 0.5}
    joint_limits:                       # like ros2_control joint_limits.yaml
      default: {max_acceleration: 5.0, max_jerk: 100.0}
      joint1: {max_velocity: 1.5}
    initial_positions: {joint2: 0.2}
    safety: {command_timeout: 0.2}      # see agentsdk.safety.SafetyConfig
    strict: false                       # true: refuse descriptions that need repairs
    self_collision: auto                # auto | true | false, the same on every simulator
    srdf: arm3.srdf                     # <disable_collisions> pairs (default: an SRDF beside the URDF)
    backends:                           # backend-specific sections, free-form per backend
      mujoco: {timestep: 0.001}
      pybullet: {timestep: 0.001}
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, ValidationError, field_validator

from .errors import ConfigurationError

__all__ = ["Gains", "JointLimitsOverride", "RobotConfig", "load_robot_config"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Gains(_Strict):
    """Joint servo gains: ``effort = p*(q_des - q) + d*(v_des - v) + effort_ff``."""

    p: float = Field(ge=0.0)
    d: float = Field(ge=0.0)
    #: velocity-mode gain (``effort = v*(v_des - v)``); defaults to ``d``
    v: float | None = Field(default=None, ge=0.0)


class JointLimitsOverride(_Strict):
    """Per-joint limit overrides; unset fields keep the URDF value.

    Names follow ros2_control's joint_limits.yaml.
    """

    min_position: float | None = None
    max_position: float | None = None
    max_velocity: PositiveFloat | None = None
    max_acceleration: PositiveFloat | None = None
    max_jerk: PositiveFloat | None = None
    max_effort: PositiveFloat | None = None


class RobotConfig(_Strict):
    """Validated content of a robot.yaml."""

    name: str = ""
    description: str
    xacro_args: dict[str, str] = Field(default_factory=dict)
    update_rate: PositiveFloat = 500.0
    gains: dict[str, Gains] = Field(default_factory=lambda: {"default": Gains(p=100.0, d=5.0)})
    joint_limits: dict[str, JointLimitsOverride] = Field(default_factory=dict)
    initial_positions: dict[str, float] = Field(default_factory=dict)
    safety: dict[str, Any] = Field(default_factory=dict)
    backends: dict[str, dict[str, Any]] = Field(default_factory=dict)
    #: refuse a description that needs repairs (DescriptionError) instead of repairing it with a warning
    strict: bool = False
    #: self-collision on every simulator: ``auto`` (on, except pairs that are adjacent, rigidly attached,
    #: touching at the start pose or disabled in the SRDF), ``true`` (on, except adjacent, rigidly
    #: attached and SRDF pairs), ``false`` (links of the robot never collide with each other)
    self_collision: Literal["auto"] | bool = "auto"
    #: SRDF whose ``<disable_collisions>`` are honoured (relative to this file); default: one beside the URDF
    srdf: str | None = None
    #: directory the relative ``description`` path is resolved against
    base_dir: Path = Field(default=Path("."), exclude=True)

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

    @property
    def control_period(self) -> float:
        """Seconds per control tick (``1 / update_rate``)."""
        return 1.0 / self.update_rate

    def gains_for(self, joint: str) -> Gains:
        """The gains configured for ``joint`` (its own entry, else ``default``, else p=100, d=5)."""
        g = self.gains.get(joint) or self.gains.get("default")
        return g if g is not None else Gains(p=100.0, d=5.0)

    def backend_options(self, backend: str) -> dict[str, Any]:
        """A copy of the robot.yaml options for ``backend`` (empty when none)."""
        return dict(self.backends.get(backend, {}))


def load_robot_config(path: str | Path) -> RobotConfig:
    """Read and validate a robot.yaml; errors name the file and the field."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except FileNotFoundError as exc:
        raise ConfigurationError(f"robot config not found: {path}") from exc
    except yaml.YAMLError as exc:
        raise ConfigurationError(f"{path}: invalid YAML: {exc}") from exc
    if not isinstance(raw, dict):
        raise ConfigurationError(f"{path}: expected a mapping at the top level")
    raw.setdefault("name", path.parent.name)
    try:
        return RobotConfig(**raw, base_dir=path.parent)
    except ValidationError as exc:
        raise ConfigurationError(f"{path}: invalid robot config:\n{exc}") from exc
