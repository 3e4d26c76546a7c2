"""Sensor limits in the safety layer: a force, contact-force, torque or tilt limit latches a protective stop.

Like a cobot's collision detection: the check runs every tick after the sensors were sampled
(a :data:`~agentsdk.safety.SafetyCheck`), and the safety event names the sensor and the value.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InvalidValueError
from ._spec import SensorLimits, SensorSpec

if TYPE_CHECKING:
    from ..checks import SafetyViolation
    from ..loop import StateView
    from ._hub import Sensors

__all__ = ["SensorLimitCheck", "check_limits", "tilt"]

_FORCE_KINDS = ("force_torque", "force", "contact")
_TORQUE_KINDS = ("force_torque", "torque")
_TILT_KINDS = ("imu", "orientation")


def check_limits(spec: SensorSpec, limits: SensorLimits) -> None:
    """Raise :class:`InvalidValueError` when a limit does not apply to the sensor's kind or is not positive."""
    for what, value, kinds in (
        ("max_force", limits.max_force, _FORCE_KINDS),
        ("max_torque", limits.max_torque, _TORQUE_KINDS),
        ("max_tilt", limits.max_tilt, _TILT_KINDS),
    ):
        if value is None:
            continue
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise InvalidValueError(f"sensor {spec.name!r}: {what} must be a positive number, got {value!r}")
        if spec.kind not in kinds:
            raise InvalidValueError(
                f"sensor {spec.name!r} is a {spec.kind} sensor; {what} applies to {', '.join(kinds)} sensors"
            )
    if not limits.any:
        raise InvalidValueError(f"sensor {spec.name!r}: give max_force, max_torque or max_tilt")


def tilt(quat_xyzw: np.ndarray) -> float:
    """Angle (rad) between the frame's z axis and the world's up axis, from its quaternion (x, y, z, w)."""
    x, y = float(quat_xyzw[0]), float(quat_xyzw[1])
    n2 = float(quat_xyzw[0] ** 2 + quat_xyzw[1] ** 2 + quat_xyzw[2] ** 2 + quat_xyzw[3] ** 2) or 1.0
    # world z component of the frame's z axis: R[2, 2] = 1 - 2 (x² + y²) for a unit quaternion
    c = 1.0 - 2.0 * (x * x + y * y) / n2
    return math.acos(max(-1.0, min(1.0, c)))


class SensorLimitCheck:
    """A safety check on one sensor's published reading (see :meth:`Sensors.add_limit`)."""

    def __init__(self, sensors: Sensors, spec: SensorSpec, limits: SensorLimits) -> None:
        self.spec = spec
        self.limits = limits
        self._values = sensors.values(spec.name)
        kind = spec.kind
        self._force = (
            None if limits.max_force is None else (slice(0, 1) if kind == "contact" else slice(0, 3))
        )
        self._torque = None if limits.max_torque is None else (slice(3, 6) if kind == "force_torque" else slice(0, 3))

    def __call__(self, t: float, state: StateView) -> SafetyViolation | None:
        """The violation when the sensor's latest reading exceeds a limit, else None."""
        v, lim = self._values, self.limits
        if self._force is not None and lim.max_force is not None:
            part = v[self._force]
            f = math.sqrt(float(part.dot(part)))
            if f > lim.max_force:
                return self._violation(f"force {f:.3g} N above its limit {lim.max_force:g} N")
        if self._torque is not None and lim.max_torque is not None:
            part = v[self._torque]
            m = math.sqrt(float(part.dot(part)))
            if m > lim.max_torque:
                return self._violation(f"torque {m:.3g} N·m above its limit {lim.max_torque:g} N·m")
        if lim.max_tilt is not None:
            a = tilt(v[0:4])
            if a > lim.max_tilt:
                return self._violation(f"tilt {a:.3g} rad above its limit {lim.max_tilt:g} rad")
        return None

    def _violation(self, what: str) -> SafetyViolation:
        from ..checks import SafetyViolation

        return SafetyViolation(
            "sensor_limit", f"sensor {self.spec.name!r} ({self.spec.kind} on {self.spec.link}): {what}",
            None, self.limits.category,
        )
