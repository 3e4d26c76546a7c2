"""Sensor conditions for guarded moves: ``robot.move_to(..., until=force_above("wrist", 5.0))``.

A condition is any callable ``cond(sensors) -> bool`` evaluated every control tick on the
latest published readings (:class:`~agentsdk.sensors.Sensors`); the helpers here read the
values without allocating and describe themselves in the motion's result message.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InvalidValueError

if TYPE_CHECKING:
    from ._hub import Sensors

__all__ = ["Condition", "contact", "force_above", "range_below", "torque_above"]

#: what ``until=`` accepts: called every tick with ``robot.sensors``; True ends the motion
Condition = Callable[["Sensors"], bool]


def _positive(value: float, what: str) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InvalidValueError(f"{what} must be a number, got {value!r}") from None
    if not (math.isfinite(value) and value >= 0.0):
        raise InvalidValueError(f"{what} must be a finite number >= 0, got {value!r}")
    return value


class _Norm:
    """|values[part]| (or one signed axis) above a threshold."""

    def __init__(self, sensor: str, threshold: float, kinds: dict[str, slice], what: str, unit: str,
                 axis: int | None, tare: bool = False) -> None:
        self.sensor = sensor
        self.tare = bool(tare)
        self._zero = np.zeros(3)
        self._diff = np.zeros(3)
        self.threshold = _positive(threshold, what)
        self._kinds = kinds
        self._what = what
        self._unit = unit
        self._axis = axis
        self._bound: tuple[object, object] | None = None

    def start(self, sensors: Sensors) -> None:
        """Bind to ``sensors`` and, with ``tare``, take the current reading as zero (called when a move starts)."""
        kind = sensors[self.sensor].type
        if kind not in self._kinds:
            raise InvalidValueError(
                f"{self._what} needs a {' or '.join(self._kinds)} sensor; {self.sensor!r} is a {kind} sensor"
            )
        part = sensors.values(self.sensor)[self._kinds[kind]]
        n = len(part)
        self._zero = part.copy() if self.tare else np.zeros(n)
        self._diff = np.zeros(n)
        self._bound = (sensors, part)

    def __call__(self, sensors: Sensors) -> bool:
        bound = self._bound
        if bound is None or bound[0] is not sensors:
            self.start(sensors)
            bound = self._bound
            assert bound is not None
        part = bound[1]
        diff = self._diff
        np.subtract(part, self._zero, out=diff)  # type: ignore[call-overload]
        if self._axis is not None:
            return abs(float(diff[self._axis])) > self.threshold
        return math.sqrt(float(diff.dot(diff))) > self.threshold

    def __repr__(self) -> str:
        tare = ", tared" if self.tare else ""
        return f"{self._what}({self.sensor!r}, {self.threshold:g} {self._unit}{tare})"


def force_above(sensor: str, newtons: float, *, axis: int | None = None, tare: bool = False) -> Condition:
    """True once the force measured by ``sensor`` exceeds ``newtons`` (``|force|``, or ``|force[axis]|``).

    Works on force-torque, force and contact sensors (a contact sensor: its normal force).
    ``tare=True`` measures from the reading when the move starts (a tool's own weight on a wrist
    force-torque sensor is then not counted), like zeroing a real F/T sensor before a guarded move.
    """
    if axis is not None and axis not in (0, 1, 2):
        raise InvalidValueError(f"axis must be 0, 1 or 2, got {axis!r}")
    return _Norm(sensor, newtons, {"force_torque": slice(0, 3), "force": slice(0, 3), "contact": slice(0, 1)},
                 "force_above", "N", axis, tare)


def torque_above(sensor: str, newton_metres: float, *, axis: int | None = None, tare: bool = False) -> Condition:
    """True once the torque measured by ``sensor`` (force-torque or torque) exceeds ``newton_metres``.

    ``tare``: as for :func:`force_above`.
    """
    if axis is not None and axis not in (0, 1, 2):
        raise InvalidValueError(f"axis must be 0, 1 or 2, got {axis!r}")
    return _Norm(sensor, newton_metres, {"force_torque": slice(3, 6), "torque": slice(0, 3)}, "torque_above",
                 "N·m", axis, tare)


def contact(sensor: str, min_force: float = 0.0) -> Condition:
    """True once contact sensor ``sensor`` feels more than ``min_force`` newtons."""
    return _Norm(sensor, min_force, {"contact": slice(0, 1)}, "contact", "N", None)


class _Below:
    def __init__(self, sensor: str, metres: float) -> None:
        self.sensor = sensor
        self.metres = _positive(metres, "range_below")

    def __call__(self, sensors: Sensors) -> bool:
        if sensors[self.sensor].type != "rangefinder":
            raise InvalidValueError(f"range_below needs a rangefinder; {self.sensor!r} is not one")
        return float(sensors.values(self.sensor)[0]) < self.metres

    def __repr__(self) -> str:
        return f"range_below({self.sensor!r}, {self.metres:g} m)"


def range_below(sensor: str, metres: float) -> Condition:
    """True once rangefinder ``sensor`` measures less than ``metres``."""
    return _Below(sensor, metres)
