"""The safety layer around every backend.

Semantics are identical in lockstep simulation and in real time:

=========  ==================================================================
state      meaning
=========  ==================================================================
OK         commands and trajectories are accepted
HOLD       a streamed command went stale (command watchdog): the joints hold
           position (or damp); the next command returns to OK
ESTOP      an e-stop is latched: every command/follow/move_to raises
           :class:`EStopActive`; ``reset()`` clears the latch -> DISABLED
DISABLED   latch cleared, torque as the stop left it; nothing moves until
           ``enable()`` (deliberate restart, ISO 13850)
FAULT      the backend failed (simulation diverged, motor error, bus lost);
           ``reset()`` recovers if the backend can, else reconnect
=========  ==================================================================

Stop categories (IEC 60204-1): 0 removes torque at once; 1 decelerates within
the joints' deceleration limits (damps where position control is absent) and
then removes torque; 2 decelerates and holds with torque on.

A loop-stall watchdog runs in its own OS thread: if the event loop stops
beating for ``stall_timeout`` seconds of wall time, the thread latches the
e-stop and records the loop thread's stack, then calls the backend's
synchronous ``_emergency_stop(0)`` hook itself (for CAN: disable frames): whoever
sees the actuators stopped sees the e-stop latched. It runs where
wall time moves the robot: in real time (hardware, realtime simulation). In
lockstep simulated time a stalled loop cannot advance the robot's clock, so the
simulated robot cannot move while it stalls and there is nothing to protect:
the watchdog is off there unless ``stall_in_lockstep`` is set (to catch a
behavior's blocking calls in simulation before they reach hardware).

The package, one job a module, each importing only the ones above it in this list; each module
holds one object, none a subclass of another (the facade builds them and passes each its collaborators):

* :mod:`._config`: :class:`SafetyConfig`
* :mod:`._state`: ``SafetyCore`` (the state machine, the latch, the event log), the :class:`StopPort` motions implement
* :mod:`._filter`: ``CommandFilter`` (command limiting and the per-tick filter, through
  :class:`~agentsdk.limits.StepLimiter`)
* :mod:`._stops`: ``Stops`` (e-stops and controlled stops, reset and enable)
* :mod:`._watchdogs`: ``Watchdogs`` (the per-tick checks, the command watchdog, sensor faults, the loop-stall watchdog)
* :mod:`._block`: ``SafetyBlock`` (block lockstep: the filter's, the gate's and the checks' rules over K ticks)
* :mod:`._layer`: :class:`SafetyLayer`, the facade that builds and wires them, and its command gate
  :meth:`SafetyLayer.admit`
"""

from __future__ import annotations

from ..checks import MeasuredPositionCheck, SafetyCheck, SafetyViolation
from ..limits import PositionBounds
from ._config import MIN_STALL_TIMEOUT as MIN_STALL_TIMEOUT
from ._config import SafetyConfig
from ._layer import SafetyLayer
from ._state import SAFETY_OBSERVE_ORDER, SafetyEvent, SafetyState, StopPort

__all__ = [
    "SAFETY_OBSERVE_ORDER",
    "MeasuredPositionCheck",
    "PositionBounds",
    "SafetyCheck",
    "SafetyConfig",
    "SafetyEvent",
    "SafetyLayer",
    "SafetyState",
    "SafetyViolation",
    "StopPort",
]
