"""Guarded moves: a motion that ends SUCCESSFUL early, decelerating within the limits, once a sensor condition holds."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from ..errors import InvalidValueError
from ._hub import SENSOR_OBSERVE_ORDER

if TYPE_CHECKING:
    from ..backend import SetpointView
    from ..loop import ControlLoop, StateView
    from ..motion import Motion
    from ._conditions import Condition
    from ._hub import Sensors

__all__ = ["check_condition", "guard"]

log = logging.getLogger("agentsdk.sensors")


def check_condition(sensors: Sensors, until: Condition) -> bool:
    """Evaluate ``until`` once (before the motion starts): a wrong sensor name or type raises here, not in the tick."""
    if not callable(until):
        raise InvalidValueError(f"until must be a condition: a callable cond(robot.sensors) -> bool, got {until!r}")
    start = getattr(until, "start", None)
    if callable(start):
        start(sensors)  # bind, tare
    return bool(until(sensors))


def guard(loop: ControlLoop, sensors: Sensors, motion: Motion, until: Condition) -> None:
    """Watch ``until`` every tick after the sensors were sampled; when it holds, ``motion.stop_early``."""

    def _watch(t: float, st: StateView, sp: SetpointView) -> None:
        if motion.done():
            handle.remove()
            return
        try:
            hit = bool(until(sensors))
        except Exception as exc:  # a user condition failing in the tick: stop the motion, keep the loop alive
            log.error("guarded move: condition %r failed: %s; stopping the motion", until, exc)
            handle.remove()
            motion.cancel()
            return
        if hit:
            handle.remove()
            motion.stop_early(f"stopped: {until!r} held at t={t:.4f} s")

    from ..loop import Phase

    handle = loop.add_hook(Phase.OBSERVE, _watch, order=SENSOR_OBSERVE_ORDER + 1)
