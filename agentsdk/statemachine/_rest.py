"""A state is left at rest, whatever ends it: how the machine sees the robot's safety stops.

The robot's safety layer records every e-stop and fault as an event (``robot.safety.events``)
and runs each controlled stop as a task (``stop_in_progress``, ``wait_stopped()``). The machine
counts the events when a state is entered, is woken by a tick hook when the count changes, and
waits for the stop to reach rest before the next state starts. Duck-typed: a robot without a
safety layer (a test double) has no such exit.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

from ..errors import AgentSDKError
from ..loop import HookHandle, Phase
from ..scope import MotionScope
from ._errors import RobotStoppedError

#: OBSERVE-phase order of the machine's watcher: after the safety layer's own watchdogs (1000)
WATCH_ORDER = 2000
STOP_KINDS = ("estop", "fault")


def watch_safety(robot: Any, wake: Callable[[], None]) -> list[HookHandle]:
    """Call ``wake()`` on the tick after the safety layer records an event, and if the loop dies."""
    safety = getattr(robot, "safety", None)
    add_hook = getattr(robot, "add_tick_hook", None)
    if safety is None or add_hook is None or not hasattr(safety, "event_count"):
        return []
    seen = [safety.event_count]

    def on_tick(t: float, state: object, setpoint: object) -> None:
        n = safety.event_count  # an int compare per tick: allocation-free
        if n != seen[0]:
            seen[0] = n
            wake()

    def on_fault(exc: BaseException) -> None:
        wake()

    handles: list[HookHandle] = []
    try:
        handles.append(add_hook(Phase.OBSERVE, on_tick, order=WATCH_ORDER))
        handles.append(robot.add_fault_listener(on_fault))
    except AgentSDKError:  # a closed robot: nothing to watch (its commands raise)
        pass
    return handles


def safety_cursor(robot: Any) -> int:
    """How many safety events the robot has recorded so far (0 without a safety layer)."""
    count = getattr(getattr(robot, "safety", None), "event_count", 0)
    return count if isinstance(count, int) else 0


def stop_since(robot: Any, cursor: int, path: str) -> RobotStoppedError | None:
    """The e-stop / safety fault recorded after ``cursor``, as the error that leaves state ``path``."""
    events_since = getattr(getattr(robot, "safety", None), "events_since", None)
    if events_since is None:
        return None
    stops = [e for e in events_since(cursor) if e.kind in STOP_KINDS]
    if not stops:
        return None
    reason = "fault" if any(e.kind == "fault" for e in stops) else "estop"
    detail = "; ".join(f"{e.kind}: {e.detail}" for e in stops[:3])
    return RobotStoppedError(f"{path}: the robot was stopped while the state ran ({detail})", reason=reason, path=path)


async def wait_rest(robot: Any) -> None:
    """Wait until a safety stop in progress has brought the robot to rest (returns at once if none)."""
    safety = getattr(robot, "safety", None)
    if safety is not None and getattr(safety, "stop_in_progress", False) is True:
        await safety.wait_stopped()


def ignored_abort(scope: MotionScope) -> str | None:
    """The message of the last ABORTED motion of ``scope`` unless a motion after it succeeded."""
    aborted: str | None = None
    for motion in scope.motions:
        if not motion.done():
            continue
        get = getattr(motion, "result", None)
        try:
            result = get() if callable(get) else None
        except (Exception, asyncio.CancelledError):  # the motion's own failure: the body saw it raise
            continue
        code = getattr(getattr(result, "code", None), "name", None)
        if code == "ABORTED":
            aborted = str(getattr(result, "message", "") or "ABORTED")
        elif code == "SUCCESSFUL":
            aborted = None
    return aborted
