"""The safety layer's configuration (``safety:`` in a robot's config)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..config import MAX_GAIN
from ..errors import (
    ConfigurationError,
)
from ..types import CommandMode

if TYPE_CHECKING:
    pass



#: shortest accepted stall_timeout (s): the heartbeat runs every stall_timeout / 10
MIN_STALL_TIMEOUT = 0.01


class SafetyConfig(BaseModel):
    """Safety settings (robot.yaml ``safety:``, overridable in ``connect(safety=...)``).

    Every number must be finite and within its range: a NaN compares false with
    every bound (it would silently disable the check it configures), a negative
    step would make the ramp itself drive the robot.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    #: what to do with an out-of-limit command: clamp it (and record) or reject it
    limit_policy: Literal["clamp", "reject"] = "clamp"
    #: soft margin inside the URDF position limits (rad or m)
    position_margin: float = Field(default=0.0, ge=0.0)
    #: max change of a position setpoint per control cycle (rad or m, > 0); "auto" = max_velocity * period;
    #: None = off
    max_position_step: Annotated[float, Field(gt=0.0)] | Literal["auto"] | None = "auto"
    #: a streamed command older than this puts its joints in HOLD (robot time, s)
    command_timeout: float = Field(default=0.25, gt=0.0)
    #: command modes the command watchdog applies to (position targets hold by themselves)
    watchdog_modes: tuple[CommandMode, ...] = ("velocity", "effort")
    #: HOLD keeps position ("position") or only damps ("damping")
    hold: Literal["position", "damping"] = "position"
    #: event-loop stall watchdog (wall-clock seconds, at least 10 ms); None disables the thread
    stall_timeout: Annotated[float, Field(ge=MIN_STALL_TIMEOUT)] | None = 0.25
    #: run the stall watchdog in lockstep too (off by default: a stalled loop cannot advance simulated
    #: time, so the simulated robot cannot move; turn it on to catch blocking calls in simulation)
    stall_in_lockstep: bool = False
    #: damping gain used by category 1 where position control is absent (N·m·s/rad)
    stop_damping: float = Field(default=5.0, ge=0.0, le=MAX_GAIN)
    #: scale of the joints' max_acceleration used when decelerating to a stop
    #: (at least 1 %: a stop under a vanishing deceleration never ends)
    stop_deceleration_scale: float = Field(default=1.0, ge=0.01, le=1.0)
    #: minimum seconds between two identical clamp warnings in the log
    warn_interval: float = Field(default=1.0, ge=0.0)
    #: a controlled stop is achieved once every measured speed is below this (rad/s or m/s) ...
    rest_velocity: float = Field(default=0.05, gt=0.0)
    #: ... waiting at most this long (robot s) after the deceleration ramp ended
    rest_timeout: float = Field(default=1.0, ge=0.0)
    #: a measured position this far (rad or m) beyond a joint's limits is a protective stop; None = off
    position_limit_tolerance: Annotated[float, Field(gt=0.0)] | None = 0.1
    #: stop category of that protective stop (IEC 60204-1)
    position_limit_stop: Literal[0, 1, 2] = 2
    #: plausibility of every reading (agentsdk.plausibility): a value the physics cannot explain is a
    #: sensor fault, never a position; False takes readings as they are
    sensor_check: bool = True
    #: a position may move at most margin x max(max_velocity, abs(velocity)) x elapsed time (+ floor) per reading
    sensor_jump_margin: float = Field(default=2.0, ge=1.0, le=1000.0)
    #: ... plus this much (rad or m: encoder noise, quantization, backlash)
    sensor_jump_floor: float = Field(default=0.02, ge=0.0, le=10.0)
    #: stop category of a sensor fault: 2 (default) stops from the reference and holds; 0 removes
    #: torque at once (for robots that are safe limp)
    sensor_fault_stop: Literal[0, 1, 2] = 2
    #: stop category of the e-stop buttons of user interfaces (the web view's E-STOP)
    ui_stop_category: Literal[0, 1, 2] = 1
    #: following-error window (rad or m) around a position-servoed joint's command: "auto" (from the
    #: gains and effort limits, see agentsdk.following), one number, {joint: window} (others "auto"),
    #: or None (off)
    following_error_window: (
        Literal["auto"] | Annotated[float, Field(gt=0.0)] | dict[str, Annotated[float, Field(gt=0.0)]] | None
    ) = "auto"
    #: bounds of the "auto" window (rad or m)
    following_error_min: float = Field(default=0.25, gt=0.0)
    following_error_max: float = Field(default=0.5, gt=0.0)
    #: robot seconds a joint must stay outside its window before the stop latches
    following_error_time: float = Field(default=0.1, ge=0.0, le=10.0)
    #: stop category of the following-error stop (IEC 60204-1)
    following_error_stop: Literal[0, 1, 2] = 2

    @classmethod
    def from_sources(
        cls,
        yaml_section: Mapping[str, Any] | None,
        override: SafetyConfig | Mapping[str, Any] | None,
        *,
        source: str = "robot.yaml",
    ) -> SafetyConfig:
        """The robot.yaml ``safety`` section with ``connect(safety=...)`` on top, validated.

        Raises :class:`ConfigurationError` with one line per problem, naming where
        the value came from (``source``: the robot.yaml, or ``connect(safety=...)``).
        """
        data = dict(yaml_section or {})
        given: dict[str, Any] = {}
        if isinstance(override, SafetyConfig):
            given = override.model_dump(exclude_unset=True)
        elif override:
            if not isinstance(override, Mapping):
                raise ConfigurationError(
                    f"connect(safety=...) expects a mapping or a SafetyConfig, got {type(override).__name__}"
                )
            given = dict(override)
        data.update(given)
        try:
            return cls(**data)
        except ValidationError as exc:
            from ..config import validation_problems

            lines = []
            for line in validation_problems(exc, cls):
                key = line.split(":", 1)[0].split(".", 1)[0]
                where = "connect(safety=...)" if key in given else f"{source}: safety"
                lines.append(f"{where}.{line}" if where.endswith("safety") else f"{where}: {line}")
            raise ConfigurationError("\n".join(lines)) from None
