"""The safety state machine and its latch, the event log, and the stop port motions implement."""

from __future__ import annotations

import asyncio
import enum
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from ..backend import ModeCode
from ..checks import SafetyCheck
from ..errors import (
    EStopActive,
    SafetyFault,
)
from ..limits import PositionBounds, StepLimiter
from ..loop import ControlLoop
from ..plausibility import SensorGate
from ..stall import StallWatchdog
from ..types import MODES
from ._config import SafetyConfig

if TYPE_CHECKING:
    pass



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


class _SafetyCore:
    """The safety layer's state: the state machine, the e-stop latch and the event log."""

    #: the plausibility gate of every reading (None: sensor_check off), installed by the layer
    sensor_gate: SensorGate | None

    def __init__(
        self, loop: ControlLoop, config: SafetyConfig, bounds: PositionBounds, motions: StopPort | None = None
    ) -> None:
        self.loop = loop
        self.config = config
        #: the stop port of the motion manager (see :meth:`attach_motions`)
        self.motions: StopPort = _NoMotions(len(loop.joints)) if motions is None else motions
        self._events: deque[SafetyEvent] = deque(maxlen=10_000)
        self._event_count = 0
        self._events_lock = threading.Lock()
        self._state = SafetyState.OK
        self._cause: BaseException | None = None
        self._latched = threading.Event()  # set from any thread
        self._latch_lock = threading.Lock()
        #: lowest stop category latched since the last reset (None: not latched)
        self._latch_category: int | None = None
        #: the loop side has taken over the current latch (see _enforce_latch)
        self._latch_handled = False
        #: stack of the event-loop thread when the stall watchdog fired
        self.stall_traceback: str | None = None
        n = len(loop.joints)
        #: the one limiting rule (position bounds, step per period, velocity and effort limits)
        self.limiter = limiter = StepLimiter.for_joints(loop.joints, bounds, config.max_position_step, loop.period)
        self._lo, self._hi = limiter.lo, limiter.hi
        self._step = limiter.step
        #: watched[mode code] -> True if the command watchdog applies to that mode
        self._watched = np.array([m in config.watchdog_modes for m in MODES], dtype=bool)
        self._watch_position = "position" in config.watchdog_modes
        self._fed = np.zeros(n)  # robot time of the last command per joint
        #: the limiter's origin: the position setpoint written last tick (always updated in place)
        self._written = loop.state.position.copy()
        #: goal of a direct position command being ramped (max_position_step), per joint
        self._goal = loop.setpoint.position.copy()
        self._ramping = np.zeros(n, dtype=bool)
        #: joints put on hold by the command watchdog (not watched again until commanded)
        self._held = np.zeros(n, dtype=bool)
        self._vmax, self._emax = limiter.vmax, limiter.emax
        #: scratch of the per-tick filter's slow path (a joint ramping or outside position mode)
        self._target = np.zeros(n)
        self._limited = np.zeros(n)
        #: scratch masks of the per-tick paths (joints in position mode with torque on; streamed joints;
        #: stale streams) and the command age per joint: no arrays allocated per tick
        self._n = n
        #: ``tobytes()`` of a mode row with every joint in position mode, of an all-true / all-false mask:
        #: the per-tick checks compare bytes (no array, ~5x cheaper than ufunc + np.count_nonzero)
        self._all_position = np.full(n, _POS, dtype=np.int8).tobytes()
        self._all_true = np.ones(n, dtype=bool).tobytes()
        self._all_false = np.zeros(n, dtype=bool).tobytes()
        self._streamed = np.zeros(n, dtype=bool)
        self._stale = np.zeros(n, dtype=bool)
        self._age = np.zeros(n)
        #: views of the loop's setpoint rows (made once per setpoint object, not per tick)
        self._rows_of: object = None
        self._rows: np.ndarray | None = None
        #: deceleration available to stop a velocity stream before a position limit
        self._amax = np.array([j.max_acceleration for j in loop.joints]) * config.stop_deceleration_scale
        self._last_warn: dict[tuple[str, int], float] = {}
        self._stop_tasks: set[asyncio.Task[None]] = set()
        #: the controlled stop (category 1 or 2) in progress and the category its end state follows
        self._ramp_stop: asyncio.Task[None] | None = None
        self._ramp_category = 2
        self._fault_waiters: set[asyncio.Future[BaseException]] = set()
        self._checks: list[SafetyCheck] = []
        self._aloop: asyncio.AbstractEventLoop | None = None
        #: the event-loop stall watchdog (None: not watched, see :attr:`stall_watchdog_active`)
        self._stall: StallWatchdog | None = None
        #: wall-clock time (time.monotonic) the stall watchdog fired, and how long after the last heartbeat
        self.stall_detected_at: float | None = None
        self.stall_latency: float | None = None
        #: a sensor fault since the last reset: stops start from the reference, not the measurement
        self._distrust_measurement = False

    @property
    def state(self) -> SafetyState:
        """OK, HOLD, ESTOP, DISABLED or FAULT (an e-stop latched from another thread shows at once)."""
        if self._state is SafetyState.FAULT:
            return SafetyState.FAULT
        if self._latched.is_set():
            return SafetyState.ESTOP
        return self._state

    @property
    def cause(self) -> BaseException | None:
        """The exception behind a FAULT, or None."""
        return self._cause

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

    @property
    def stop_in_progress(self) -> bool:
        """True while a controlled stop (category 1 or 2) is decelerating the robot."""
        return any(not t.done() for t in self._stop_tasks)

    def record(self, kind: str, detail: str, joint: str | None = None) -> SafetyEvent:
        """Append an event (any thread) stamped with the robot time of the latest state."""
        ev = SafetyEvent(self.loop.stamp, kind, joint, detail)
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

    # --------------------------------------------------------------- e-stop
    def _latch(self, category: int) -> bool:
        """Latch the e-stop (any thread). Returns False if it was already latched."""
        with self._latch_lock:
            first = not self._latched.is_set()
            if self._latch_category is None or category < self._latch_category:
                self._latch_category = category
            self._latched.set()
        return first

    def _enforce_latch(self) -> None:
        """Loop side, once per latch set from another thread (stall watchdog, estop_threadsafe).

        Category 0: torque is already off; running motions end ABORTED. Categories 1
        and 2: the stop task scheduled on the loop decelerates them (no freeze here).
        """
        self._latch_handled = True
        if self._state is not SafetyState.FAULT:
            self._state = SafetyState.ESTOP
        if self._latch_category == 0:
            self._ramping[:] = False
            self.motions.abort_all("e-stop")

    def _on_fault(self, exc: BaseException) -> None:
        self._state = SafetyState.FAULT
        self._cause = exc
        self._ramping[:] = False
        self.record("fault", str(exc))
        self.motions.fail_all(exc)
        for fut in self._fault_waiters:
            if not fut.done():
                fut.set_result(exc)

    # -------------------------------------------------------------- limits
    def _warn(self, kind: str, j: int, msg: str) -> None:
        """Log a warning at most once per ``warn_interval`` (wall time) per (kind, joint)."""
        now = time.monotonic()
        key = (kind, j)
        if now - self._last_warn.get(key, -1e9) >= self.config.warn_interval:
            self._last_warn[key] = now
            log.warning(msg)
