"""The safety state machine and its latch, the event log, and the stop port motions implement."""

from __future__ import annotations

import enum
import logging
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ..backend import ModeCode
from ..errors import (
    EStopActive,
    SafetyFault,
)
from ..loop import ControlLoop

log = logging.getLogger("agentsdk.safety")


class SafetyState(enum.Enum):
    """State of the safety layer (see the module documentation)."""

    OK = "ok"
    HOLD = "hold"
    ESTOP = "estop"
    DISABLED = "disabled"
    FAULT = "fault"


@dataclass(frozen=True, slots=True)
class SafetyEvent:
    """One recorded safety event. ``time`` is robot time (s)."""

    time: float
    kind: str
    joint: str | None
    detail: str


#: mode codes as plain ints (numpy compares arrays with an IntEnum member slowly, through enum attribute lookups)
_POS, _VEL, _EFF = int(ModeCode.POSITION), int(ModeCode.VELOCITY), int(ModeCode.EFFORT)


#: OBSERVE-phase order of the safety layer's watchdogs: after recorders and other observers
SAFETY_OBSERVE_ORDER = 1000


class StopPort(Protocol):
    """What the safety layer needs from whoever runs planned motions (the motion manager).

    The safety layer defines this port and the motion layer implements it, so the safety layer
    imports nothing above it: it stops, aborts and fails motions only through these calls.
    """

    #: joints currently driven by a motion or a stop ramp (read-only)
    owned_mask: np.ndarray

    def owner_of(self, idx: np.ndarray) -> tuple[int, Any] | None:
        """The first of joints ``idx`` a motion drives or reserves, with that motion; None if none."""

    def limiter_clipped(self, idx: np.ndarray, detail: str) -> None:
        """The filter clipped the planned reference of joints ``idx``: abort what drives them."""

    def fail_all(self, exc: BaseException) -> None:
        """The backend failed: every motion ends with ``exc``."""

    def abort_all(self, reason: str = ...) -> None:
        """End every motion ABORTED now (torque already off or going off)."""

    def end_all(self, reason: str) -> None:
        """Forget every motion and stop ramp (a reset)."""

    async def stop_all_ramp(self, damp_only: bool = False, damping: float = 5.0, *,
                            from_reference: bool = False) -> None:
        """Decelerate every joint to rest within its limits; returns when at rest."""


class _NoMotions:
    """The stop port of a safety layer no motion manager is attached to (yet)."""

    def __init__(self, n: int) -> None:
        self.owned_mask = np.zeros(n, dtype=bool)

    def owner_of(self, idx: np.ndarray) -> tuple[int, Any] | None:
        """Nothing runs: no joint is owned."""
        return None

    def limiter_clipped(self, idx: np.ndarray, detail: str) -> None:
        """Nothing runs: nothing to abort."""

    def fail_all(self, exc: BaseException) -> None:
        """Nothing runs: nothing to fail."""

    def abort_all(self, reason: str = "") -> None:
        """Nothing runs: nothing to abort."""

    def end_all(self, reason: str) -> None:
        """Nothing runs: nothing to end."""

    async def stop_all_ramp(self, damp_only: bool = False, damping: float = 5.0, *,
                            from_reference: bool = False) -> None:
        """Nothing runs: at rest already."""


class SafetyCore:
    """The state machine, the e-stop latch and the event log: the bottom object every other one reads.

    The latch may be set from any thread (the stall watchdog's, a signal handler's through
    ``estop_threadsafe``): :meth:`latch` and :meth:`clear_latch` take its lock, and :attr:`state`
    shows a latch set elsewhere at once. Events are recorded from any thread too.
    """

    def __init__(self, loop: ControlLoop) -> None:
        #: the robot time of the latest state (``loop.stamp``) stamps every event
        self._loop = loop
        self._events: deque[SafetyEvent] = deque(maxlen=10_000)
        self._event_count = 0
        self._events_lock = threading.Lock()
        self._state = SafetyState.OK
        self._cause: BaseException | None = None
        #: the e-stop latch: set from any thread (under ``_latch_lock``), read every tick. A plain bool (a
        #: store is atomic and seen at once by the other threads): ``threading.Event.is_set`` is a Python call,
        #: and nobody waits on the latch
        self.latched = False
        self._latch_lock = threading.Lock()
        #: latches so far (each from an unlatched state): a reset clears only the latch it began with
        self._latches = 0
        #: lowest stop category latched since the last reset (None: not latched)
        self._latch_category: int | None = None
        #: the loop side has taken over the current latch (see CommandFilter.enforce_latch)
        self._latch_handled = False

    @property
    def state(self) -> SafetyState:
        """OK, HOLD, ESTOP, DISABLED or FAULT (an e-stop latched from another thread shows at once)."""
        if self._state is SafetyState.FAULT:
            return SafetyState.FAULT
        if self.latched:
            return SafetyState.ESTOP
        return self._state

    @property
    def cause(self) -> BaseException | None:
        """The exception behind a FAULT, or None."""
        return self._cause

    def enter(self, state: SafetyState) -> None:
        """Set the state machine's own state (the latch is separate: :meth:`latch`, :meth:`clear_latch`)."""
        self._state = state

    def fault(self, exc: BaseException) -> None:
        """Enter FAULT because of ``exc`` (reported by :attr:`cause` and :meth:`check_fault`)."""
        self._state = SafetyState.FAULT
        self._cause = exc

    def recovered(self) -> None:
        """The backend recovered from its fault: forget the cause (the state is set by the caller)."""
        self._cause = None

    def take_latch(self) -> None:
        """The loop side handles the current latch now: ESTOP (unless in FAULT)."""
        self._latch_handled = True
        if self._state is not SafetyState.FAULT:
            self._state = SafetyState.ESTOP

    # --------------------------------------------------------------- events
    @property
    def events(self) -> tuple[SafetyEvent, ...]:
        """Recorded safety events, oldest first (the last 10,000), including ones from the watchdog thread."""
        with self._events_lock:
            return tuple(self._events)

    @property
    def event_count(self) -> int:
        """How many events were ever recorded (a cursor for :meth:`events_since`)."""
        return self._event_count

    def events_since(self, count: int) -> list[SafetyEvent]:
        """Events recorded after the first ``count`` (``count`` from :attr:`event_count`)."""
        with self._events_lock:
            new = self._event_count - count
            if new <= 0:
                return []
            return list(self._events)[-min(new, len(self._events)):]

    def record(self, kind: str, detail: str, joint: str | None = None) -> SafetyEvent:
        """Append an event (any thread) stamped with the robot time of the latest state."""
        ev = SafetyEvent(self._loop.stamp, kind, joint, detail)
        with self._events_lock:
            self._events.append(ev)
            self._event_count += 1
        return ev

    def check_fault(self) -> None:
        """Raise :class:`SafetyFault` (with the cause) while in FAULT."""
        if self._state is SafetyState.FAULT:
            raise SafetyFault(f"safety FAULT: {self._cause}") from self._cause

    def check_motion_allowed(self) -> None:
        """Raise :class:`EStopActive` / :class:`SafetyFault` unless commands are accepted (OK or HOLD)."""
        st = self.state
        if st is SafetyState.OK or st is SafetyState.HOLD:
            return
        if st is SafetyState.FAULT:
            self.check_fault()
        if st is SafetyState.DISABLED:
            raise EStopActive("robot is disabled after reset(); call `await robot.enable()` to allow motion")
        cause = self.latch_cause()
        raise EStopActive(f"e-stop is latched{f' ({cause})' if cause else ''}; "
                          "call `await robot.reset()` then `await robot.enable()`")

    def latch_cause(self) -> str:
        """The detail of the event that latched the e-stop (the first stopping event since the last reset)."""
        with self._events_lock:
            events = list(self._events)
        cause = ""
        for ev in events:
            if ev.kind in ("reset", "enable"):
                cause = ""
            elif not cause and ev.kind not in ("clamp", "watchdog", "resume"):
                cause = ev.detail if ev.kind in ("estop", "stall") else f"{ev.kind}: {ev.detail}"
        return cause

    # --------------------------------------------------------------- latch
    def latch(self, category: int, *, handled: bool | None = None) -> bool:
        """Latch the e-stop (any thread). Returns False if it was already latched.

        ``handled``: also say whether the loop side has taken the latch over (None: unchanged).
        """
        with self._latch_lock:
            first = not self.latched
            if first:
                self._latches += 1
            if self._latch_category is None or category < self._latch_category:
                self._latch_category = category
            self.latched = True
        if handled is not None:
            self._latch_handled = handled
        return first

    @property
    def latch_count(self) -> int:
        """How many times the e-stop latched from an unlatched state (any thread)."""
        return self._latches

    def refusal(self) -> BaseException | None:
        """Why motion cannot be switched on now: the FAULT (SafetyFault) or the latch (EStopActive), else None."""
        if self._state is SafetyState.FAULT:
            exc = SafetyFault(f"safety FAULT: {self._cause}")
            exc.__cause__ = self._cause
            return exc
        if self.latched:
            return EStopActive("an e-stop is latched; call `await robot.reset()` before `await robot.enable()`")
        return None

    def clear_latch(self) -> None:
        """Clear the latch (a reset): nothing latched, no category, nothing for the loop side to take over."""
        with self._latch_lock:
            self.latched = False
            self._latch_category = None
        self._latch_handled = False
