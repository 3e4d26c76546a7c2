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
beating for ``stall_timeout`` seconds of wall time, the thread calls the
backend's synchronous ``_emergency_stop(0)`` hook itself (for CAN: disable
frames), latches the e-stop and records the loop thread's stack. It runs where
wall time moves the robot: in real time (hardware, realtime simulation). In
lockstep simulated time a stalled loop cannot advance the robot's clock, so the
simulated robot cannot move while it stalls and there is nothing to protect:
the watchdog is off there unless ``stall_in_lockstep`` is set (to catch a
behavior's blocking calls in simulation before they reach hardware).
"""

from __future__ import annotations

import asyncio
import enum
import logging
import threading
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Annotated, Any, Literal, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .backend import ModeCode, SetpointView
from .checks import MeasuredPositionCheck, SafetyCheck, SafetyViolation
from .commands import resolve_command
from .config import MAX_GAIN
from .errors import (
    CommandRejected,
    ConfigurationError,
    EStopActive,
    InvalidValueError,
    LimitViolation,
    RobotClosedError,
    SafetyFault,
    SensorFault,
)
from .limits import PositionBounds, StepGuard, StepLimiter
from .loop import ControlLoop, HookHandle, Phase, Setpoint, StateView
from .plausibility import SensorGate
from .stall import StallWatchdog
from .types import MODES, AppliedCommand, CommandMode, JointCommand

if TYPE_CHECKING:
    from .following import FollowingErrorCheck

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

log = logging.getLogger("agentsdk.safety")

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
            from .config import validation_problems

            lines = []
            for line in validation_problems(exc, cls):
                key = line.split(":", 1)[0].split(".", 1)[0]
                where = "connect(safety=...)" if key in given else f"{source}: safety"
                lines.append(f"{where}.{line}" if where.endswith("safety") else f"{where}: {line}")
            raise ConfigurationError("\n".join(lines)) from None


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


class SafetyLayer:
    """Wraps one control loop. Created by :func:`agentsdk.connect`; reach it as ``robot.safety``."""

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
        self._handles = [
            loop.add_hook(Phase.LIMIT, self._filter),
            loop.add_hook(Phase.OBSERVE, self._on_tick, order=SAFETY_OBSERVE_ORDER),
            loop.add_fault_listener(self._on_fault),
        ]
        origin = self._written.view()
        origin.flags.writeable = False
        #: what the motion manager checks its planned steps against before writing (a planned motion
        #: is never clipped silently; an abort that resets a reference to the measured state says so)
        self.step_guard = StepGuard(limiter, origin, self._rebase_reference, self.record)
        #: the plausibility gate of every reading (None: sensor_check off)
        self.sensor_gate = (
            loop.install_sensor_gate(
                margin=config.sensor_jump_margin, floor=config.sensor_jump_floor,
                tolerance=config.position_limit_tolerance,
            )
            if config.sensor_check
            else None
        )
        #: a sensor fault since the last reset: stops start from the reference, not the measurement
        self._distrust_measurement = False
        if config.position_limit_tolerance is not None:
            self.add_check(
                MeasuredPositionCheck(loop.joints, config.position_limit_tolerance, config.position_limit_stop)
            )
        #: the following-error check (None: ``following_error_window: null``), see :mod:`agentsdk.following`
        self.following: FollowingErrorCheck | None = None
        if config.following_error_window is not None:
            from .following import FollowingErrorCheck, following_windows

            windows = following_windows(loop.joints, loop.gain_p, config.following_error_window,
                                        config.following_error_min, config.following_error_max)
            self.following = FollowingErrorCheck(loop, windows, config.following_error_time,
                                                 config.following_error_stop)
            self.add_check(self.following)

    def attach_motions(self, motions: StopPort) -> None:
        """Connect the motion manager (through the :class:`StopPort` this layer defines)."""
        self.motions = motions

    # ---------------------------------------------------------- lifecycle
    def start(self) -> None:
        """Start the heartbeat and the stall watchdog thread (called by connect once the loop runs)."""
        self._aloop = asyncio.get_running_loop()
        np.copyto(self._written, self.loop.setpoint.position)
        self._goal = self._written.copy()
        timeout = self.config.stall_timeout
        if self.stall_watchdog_active and timeout is not None and self._stall is None:
            loop = self.loop
            self._stall = StallWatchdog(
                timeout, f"agentsdk-stall-watchdog-{loop.backend.name}",
                idle=lambda: loop.torque_off or loop.closed,
                emergency_stop=lambda: loop.emergency_stop(0),
                on_stall=self._on_stall,
            )
            self._stall.start()

    async def shutdown(self) -> None:
        """Stop the watchdog thread and heartbeat, end stop tasks (awaited); called by Robot.close()."""
        stall = self._stall
        if stall is not None:
            stall.stop_now()
        tasks = list(self._stop_tasks)
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)
        if stall is not None:
            await stall.stop()

    def shutdown_now(self) -> None:
        """Synchronous part of :meth:`shutdown` (no event loop): signal the watchdog thread to stop."""
        if self._stall is not None:
            self._stall.stop_now()

    # --------------------------------------------------------------- state
    @property
    def stall_watchdog_active(self) -> bool:
        """True if the stall watchdog watches this robot (see the module documentation).

        That is: a ``stall_timeout`` is set and the robot runs in real time, or in lockstep with
        ``stall_in_lockstep``.
        """
        cfg = self.config
        return cfg.stall_timeout is not None and (self.loop.realtime or cfg.stall_in_lockstep)

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

    # ---------------------------------------------------------- the command gate
    def admit(self, cmd: JointCommand) -> AppliedCommand:
        """The one way a direct command reaches the setpoint; returns the command actually applied.

        In order: motion must be allowed (no latched e-stop, no fault), the command is validated
        (:func:`~agentsdk.commands.resolve_command`), its joints must not be driven by a motion, its
        values are limited (clamped and recorded, or rejected under ``limit_policy: reject``), it
        is written into the setpoint (a position command starts its ramp where the limiter is),
        and the command watchdog is fed. Raises a :class:`CommandRejected` subclass or
        :class:`EStopActive` with the setpoint unchanged. The caller holds the loop's lock.
        """
        loop = self.loop
        backend = loop.backend
        self.check_motion_allowed()
        idx, values, vel, eff = resolve_command(cmd, loop.names, loop.index, backend.capabilities.modes, backend.name)
        assert isinstance(cmd, JointCommand)  # resolve_command checked it
        owner = self.motions.owner_of(idx)
        if owner is not None:
            raise CommandRejected(
                f"joint {loop.names[owner[0]]!r} is driven by a running trajectory (or reserved by a "
                "scheduled one); cancel it (motion.cancel()) before sending direct commands"
            )
        values = self._limit_command(cmd.mode, idx, values)
        vel, eff = self._limit_feedforward(idx, vel, eff)
        loop.apply(cmd.mode, idx, values, vel, eff, position_now=self._ramp_start(cmd.mode, idx))
        self._feed(cmd.mode, idx, values)
        names = [loop.names[i] for i in idx.tolist()]
        return AppliedCommand(
            cmd.mode,
            MappingProxyType(dict(zip(names, values.tolist(), strict=True))),
            None if vel is None else MappingProxyType(dict(zip(names, vel.tolist(), strict=True))),
            None if eff is None else MappingProxyType(dict(zip(names, eff.tolist(), strict=True))),
        )

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

    def add_check(self, check: SafetyCheck) -> HookHandle:
        """Run ``check(t, state)`` every tick while motion is allowed; a returned violation latches an e-stop."""
        if not callable(check):
            raise InvalidValueError(f"a safety check must be callable, got {check!r}")
        self._checks.append(check)
        checks = self._checks
        return HookHandle(lambda: checks.remove(check) if check in checks else None, lambda: check in checks)

    # -------------------------------------------------------------- limits
    def _warn(self, kind: str, j: int, msg: str) -> None:
        """Log a warning at most once per ``warn_interval`` (wall time) per (kind, joint)."""
        now = time.monotonic()
        key = (kind, j)
        if now - self._last_warn.get(key, -1e9) >= self.config.warn_interval:
            self._last_warn[key] = now
            log.warning(msg)

    def _limit_command(self, mode: CommandMode, idx: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Check a validated command against limits: returns the (possibly clamped) values or raises."""
        limiter = self.limiter
        lo, hi, what, unit = limiter.command_range(mode, idx)
        out = limiter.clamp_command(mode, idx, values)
        bad = out != values
        reject = self.config.limit_policy == "reject"
        names = self.loop.names
        if reject and bad.any():
            k = int(np.argmax(bad))
            raise LimitViolation(
                f"{what} command {values[k]:.4g} {unit} for joint {names[int(idx[k])]!r} is outside "
                f"[{lo[k]:.4g}, {hi[k]:.4g}]"
            )
        if mode == "position" and reject:
            jump = limiter.step_exceeded(values, self._written, idx)
            if jump is not None:
                assert self._step is not None
                k = int(np.argmax(jump))
                j = int(idx[k])
                raise LimitViolation(
                    f"position step for joint {names[j]!r} is {abs(values[k] - self._written[j]):.4f} rad, "
                    f"above max_position_step {self._step[j]:.4f} rad per cycle (stream smaller steps, "
                    "use robot.move_to, or set limit_policy='clamp' to ramp)"
                )
        if not bad.any():
            return values
        self._record_clamps(what, unit, idx, values, out, lo, hi)
        return out

    def _record_clamps(
        self, what: str, unit: str, idx: np.ndarray, values: np.ndarray, out: np.ndarray, lo: Any, hi: Any
    ) -> None:
        lo = np.broadcast_to(lo, values.shape)
        hi = np.broadcast_to(hi, values.shape)
        for k in np.flatnonzero(out != values).tolist():
            j = int(idx[k])
            name = self.loop.names[j]
            msg = f"{what} command {values[k]:.4g} {unit} for joint {name!r} is outside [{lo[k]:.4g}, {hi[k]:.4g}]"
            self.record("clamp", f"{msg}; clamped to {out[k]:.4g}", name)
            self._warn(f"clamp {what}", j, msg + "; clamped")

    def _limit_feedforward(
        self, idx: np.ndarray, velocity: np.ndarray | None, effort: np.ndarray | None
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Check position-mode feed-forward terms against the velocity and effort limits.

        Same policy as :meth:`_limit_command`: clamp (and record) or raise :class:`LimitViolation`.
        """
        out: list[np.ndarray | None] = []
        for what, unit, arr, lim in (
            ("velocity feed-forward", "rad/s", velocity, self._vmax),
            ("effort feed-forward", "N·m", effort, self._emax),
        ):
            if arr is None:
                out.append(None)
                continue
            hi = lim[idx]
            clipped = np.clip(arr, -hi, hi)
            bad = clipped != arr
            if bad.any():
                if self.config.limit_policy == "reject":
                    k = int(np.argmax(bad))
                    raise LimitViolation(
                        f"{what} {arr[k]:.4g} {unit} for joint {self.loop.names[int(idx[k])]!r} is outside "
                        f"[{-hi[k]:.4g}, {hi[k]:.4g}]"
                    )
                self._record_clamps(what, unit, idx, arr, clipped, -hi, hi)
                arr = clipped
            out.append(arr)
        return out[0], out[1]

    def _rebase_reference(self, idx: np.ndarray, positions: np.ndarray) -> None:
        """An abort reset the reference of joints ``idx`` to their measured ``positions``: the
        position-step limiter measures the next step from there (a jump back to where the
        joint is reduces the servo effort; it is not a step to limit).
        """
        self._written[idx] = positions

    def _ramp_start(self, mode: CommandMode, idx: np.ndarray) -> np.ndarray | None:
        """Where a direct position command's setpoint starts this tick (the ramp's current position)."""
        return self._written[idx] if mode == "position" else None

    def _feed(self, mode: CommandMode, idx: np.ndarray, values: np.ndarray) -> None:
        """A command was applied to these joints: refresh the command watchdog, start position ramps.

        A direct position command becomes the *goal* of a ramp limited to
        ``max_position_step`` per cycle; the setpoint keeps showing where the
        ramp is (:meth:`_ramp_start`), so a stop started before the next tick starts from there.
        """
        self._fed[idx] = self.loop.stamp
        self._held[idx] = False
        if mode == "position":
            self._goal[idx] = values
            self._ramping[idx] = True
        else:
            self._ramping[idx] = False
        if self._state is SafetyState.HOLD:
            self._state = SafetyState.OK
            self.record("resume", "command received; leaving HOLD")

    # ---------------------------------------------------------- per cycle
    def _filter(self, t: float, st: StateView, sp: Setpoint) -> None:
        """LIMIT phase, every tick: keep position setpoints in limits and ramp their steps.

        A joint with a direct position command ramps towards its goal (see :meth:`_feed`);
        every other position-mode joint (trajectory, stop ramp, hold) is limited to what
        its writer put in the setpoint for this cycle. Feed-forward terms are clipped to
        the velocity and effort limits as a backstop.

        Allocation-free: preallocated scratch arrays and ufuncs with ``out=`` (``np.clip``
        and ``ndarray.any`` cost microseconds of dispatch on small arrays); the common case,
        every joint in position mode with torque on and no ramp, skips the masks.
        """
        if self._latched.is_set() and not self._latch_handled:
            self._enforce_latch()
        ramping = self._ramping
        no_ramp = ramping.tobytes() == self._all_false
        if not no_ramp:
            np.greater(ramping, self.motions.owned_mask, out=ramping)  # ramping &= ~owned
        if no_ramp and self._all_position_on(sp.mode, sp.enabled):
            # position, velocity and effort (rows 0:3) into [lo, hi], +-max velocity, +-max effort at once
            # (ufunc input and out are the same array object: a second view would cost an overlap check)
            rows = self._rows
            if self._rows_of is not sp or rows is None:
                self._rows_of, self._rows = sp, sp.block[0:3]
                rows = self._rows
            limiter = self.limiter
            limiter.clamp_rows(rows)
            pos, written = sp.position, self._written
            if limiter.step is not None:
                limiter.clamp_step(pos, written, pos)
            written[...] = pos
            return
        pos_mode = (sp.mode == _POS) & sp.enabled
        written = self._written
        # joints not in position mode track the measured position (bumpless switch)
        np.copyto(written, st.position, where=~pos_mode)
        ramping &= pos_mode
        limiter = self.limiter
        target = self._target
        np.copyto(target, sp.position)
        np.copyto(target, self._goal, where=ramping)
        limiter.clamp_bounds(target, target)
        out = limiter.clamp_step(target, written, self._limited)
        owned = self.motions.owned_mask
        if owned.any():
            # a planned motion is never clipped silently (the motions check their steps first, so
            # this only fires for a writer that did not): report it, the motion aborts
            clipped = (out != sp.position) & owned & pos_mode
            if clipped.any():
                j = int(np.argmax(clipped))
                self.motions.limiter_clipped(
                    np.flatnonzero(clipped),
                    f"the limiter clipped the setpoint of joint {self.loop.names[j]!r} from {sp.position[j]:.6g} "
                    f"to {out[j]:.6g} (position bounds or max_position_step)",
                )
        np.copyto(sp.position, out, where=pos_mode)
        ramping &= out != target
        np.copyto(written, out, where=pos_mode)
        ff = sp.block[1:3]
        limiter.clamp_feedforward(ff)
        streamed = sp.enabled & (sp.mode != _POS)
        if streamed.any():
            self._limit_streams(st.position, sp, streamed)

    def _all_position_on(self, mode: np.ndarray, enabled: np.ndarray) -> bool:
        """Every joint in position mode with torque on (the common case)."""
        return mode.tobytes() == self._all_position and enabled.tobytes() == self._all_true

    def _limit_streams(self, q: np.ndarray, sp: Setpoint, streamed: np.ndarray) -> None:
        """Keep velocity and effort streams from driving a joint through its position limits.

        Like ros2_control's joint saturation limiter: a velocity command is limited so the
        joint can still stop (at its deceleration limit) before the limit,
        ``|v| <= sqrt(2 * a_max * distance)``; an effort command that pushes a joint at or
        beyond a limit further out is dropped (it may rest against its stop).
        """
        vel = streamed & (sp.mode == _VEL)
        if vel.any():
            up = np.sqrt(2.0 * self._amax * np.maximum(self._hi - q, 0.0))
            down = -np.sqrt(2.0 * self._amax * np.maximum(q - self._lo, 0.0))
            limited = np.minimum(np.maximum(sp.velocity, down), up)
            np.copyto(sp.velocity, limited, where=vel)
        eff = streamed & (sp.mode == _EFF)
        if eff.any():
            outward = ((q >= self._hi) & (sp.effort > 0.0)) | ((q <= self._lo) & (sp.effort < 0.0))
            sp.effort[eff & outward] = 0.0

    def _on_tick(self, t: float, st: StateView, sp: SetpointView) -> None:
        gate = self.sensor_gate
        if gate is not None and gate.pending:
            self._sensor_fault(gate)
        all_position = self._all_position_on(sp.mode, sp.enabled)
        if not all_position:
            # the ramp origin of joints outside position mode is their fresh measurement
            np.copyto(self._written, st.position, where=(sp.mode != _POS) | ~sp.enabled)
        if self._state is not SafetyState.OK and self._state is not SafetyState.HOLD:
            return
        if self._latched.is_set():
            return
        for check in self._checks:
            violation = check(t, st)
            if violation is not None:
                self.record(violation.kind, violation.detail, violation.joint)
                log.error("safety check: %s; e-stop category %d", violation.detail, violation.category)
                self._begin_stop(violation.category, violation.kind)
                return
        if all_position and not self._watch_position:
            return  # no joint is streamed: nothing for the command watchdog
        # in HOLD too: another joint's stream may go stale while the first one is held
        # streamed = watched[mode] & enabled & ~held & ~owned, in place (a & ~b is a > b on bools)
        streamed = self._streamed
        np.take(self._watched, sp.mode, out=streamed)
        np.logical_and(streamed, sp.enabled, out=streamed)
        np.greater(streamed, self._held, out=streamed)
        if streamed.tobytes() == self._all_false:
            return
        np.greater(streamed, self.motions.owned_mask, out=streamed)
        # stale = streamed & (t - fed > command_timeout)
        stale, age = self._stale, self._age
        np.subtract(t, self._fed, out=age)
        np.greater(age, self.config.command_timeout, out=stale)
        np.logical_and(stale, streamed, out=stale)
        if stale.tobytes() != self._all_false:
            idx = np.flatnonzero(stale)
            self._hold(idx)
            self._held[idx] = True
            self._state = SafetyState.HOLD
            names = ", ".join(self.loop.names[i] for i in idx.tolist())
            self.record("watchdog", f"no command for {self.config.command_timeout:g} s; holding {names}")
            log.warning("command watchdog: holding %s", names)

    def _sensor_fault(self, gate: SensorGate) -> None:
        """A reading failed the plausibility rule: latch FAULT (naming joint and device) and stop.

        The state still holds the joint's last plausible reading; the stop starts every joint
        from its reference (the measurement is not trusted), category ``sensor_fault_stop``.
        """
        loop = self.loop
        first: SensorFault | None = None
        for r in gate.take_new():
            name = loop.names[r.index]
            src = loop.backend.joint_source(r.index)
            where = f" ({src})" if src else ""
            detail = f"sensor fault on joint {name!r}{where}: {r.reason}; the last plausible state is kept"
            self.record("sensor", detail, name)
            log.error("%s", detail)
            if first is None:
                first = SensorFault(detail, joint=name, source=src, quantity=r.quantity, value=r.value)
        if first is None:
            return
        self._distrust_measurement = True
        if self._state is not SafetyState.FAULT:
            self._state = SafetyState.FAULT
            self._cause = first
        self._begin_stop(self.config.sensor_fault_stop, "sensor fault")

    def _hold(self, idx: np.ndarray) -> None:
        loop = self.loop
        if self.config.hold == "position" and "position" in loop.backend.capabilities.modes:
            loop.hold_current(idx)
        else:
            loop.damp(idx, loop.gain_v[idx])

    def _on_fault(self, exc: BaseException) -> None:
        self._state = SafetyState.FAULT
        self._cause = exc
        self._ramping[:] = False
        self.record("fault", str(exc))
        self.motions.fail_all(exc)
        for fut in self._fault_waiters:
            if not fut.done():
                fut.set_result(exc)

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

    def _begin_stop(self, category: int, source: str) -> asyncio.Task[None]:
        """Loop side: latch, record and start the stop task of ``category``.

        A controlled stop already in progress is joined, not restarted (restarting its
        ramp would end the first one early, at speed); a category 1 request makes it end
        with torque off, a category 0 request removes torque at once.
        """
        self._latch(category)
        self._latch_handled = True
        if self._state is not SafetyState.FAULT:
            self._state = SafetyState.ESTOP
        self.record("estop", f"category {category} requested" + ("" if source == "api" else f" ({source})"))
        running = self._ramp_stop
        if category != 0 and running is not None and not running.done():
            self._ramp_category = min(self._ramp_category, category)
            return running
        task = asyncio.get_running_loop().create_task(self._stop(category), name=f"agentsdk-estop-{category}")
        self._stop_tasks.add(task)
        task.add_done_callback(self._stop_tasks.discard)
        if category != 0:
            self._ramp_stop = task
            self._ramp_category = category
        return task

    async def estop(self, category: int = 1) -> None:
        """Latch an e-stop of the given category and wait until its end state is reached.

        The stop runs in its own task: cancelling the caller does not interrupt it.
        """
        if category not in (0, 1, 2):
            raise InvalidValueError(f"stop category must be 0, 1 or 2 (IEC 60204-1), got {category!r}")
        task = self._begin_stop(category, "api")
        try:
            await asyncio.shield(task)
        except asyncio.CancelledError:
            me = asyncio.current_task()
            if task.cancelled() and (me is None or not me.cancelling()):
                raise RobotClosedError("robot closed during the e-stop (actuators left safe by close)") from None
            raise

    async def wait_stopped(self) -> None:
        """Wait until every stop in progress has reached its end state (returns at once if none)."""
        while self._stop_tasks:
            await asyncio.gather(*list(self._stop_tasks), return_exceptions=True)

    def _stop_time_bound(self) -> float:
        """Robot seconds a controlled stop may take before the safety layer stops waiting for rest."""
        scale = self.config.stop_deceleration_scale
        acc = np.array([j.max_acceleration for j in self.loop.joints]) * scale
        jerk = np.array([j.max_jerk for j in self.loop.joints])
        t = self._vmax / acc + acc / jerk
        t = t[np.isfinite(t)]
        return 2.0 * float(t.max()) + 0.5 if t.size else 5.0

    async def _stop(self, category: int) -> None:
        loop = self.loop
        motions = self.motions
        if category == 0 or loop.fault is not None or loop.closed:
            self._ramping[:] = False
            motions.abort_all("e-stop")
            self._torque_off()
            if category != 0:
                self.record("estop", f"category {category}: control loop not running; torque removed")
            return
        damp_only = "position" not in loop.backend.capabilities.modes
        if damp_only:
            self._ramping[:] = False
            motions.abort_all("e-stop")
        # running motions are not aborted first: the stop ramp starts from their state
        outcome = await self._ramp_to_rest(damp_only)
        if outcome == "fault":
            # the control loop died during the stop; it removed torque itself (category 0)
            self.record("estop", f"category {category}: interrupted by a fault; torque removed")
            return
        if outcome == "timeout":
            bound = self._stop_time_bound()
            self.record("estop", f"category {category}: not at rest after {bound:g} s; ending the stop anyway")
            log.warning("e-stop category %d: joints not at rest after %g s", category, bound)
        category = min(category, self._ramp_category)  # escalated while stopping
        if category == 1:
            self._torque_off()
            self.record("estop", "category 1: stopped, torque removed")
        else:
            self._hold_where_stopped()
            self.record("estop", "category 2: stopped, holding with torque on")

    async def _ramp_to_rest(self, damp_only: bool) -> Literal["rest", "fault", "timeout"]:
        """Decelerate every joint to rest within its limits (bounded in robot time); how it ended."""
        loop = self.loop
        ramping = self._ramping.copy()
        self._ramping[:] = False
        if ramping.any() and not damp_only:
            # joints ramping to a direct position goal stop from where the ramp would be at
            # the next tick, at the ramp's velocity (not from rest: that would be a step)
            step = self._step if self._step is not None else np.inf
            nxt = np.clip(np.clip(self._goal, self._lo, self._hi), self._written - step, self._written + step)
            idx = np.flatnonzero(ramping)
            loop.set_reference(idx, nxt[idx], ((nxt - self._written) / loop.period)[idx])
        aloop = asyncio.get_running_loop()
        fault: asyncio.Future[BaseException] = aloop.create_future()
        self._fault_waiters.add(fault)
        bound = self._stop_time_bound()
        ramp = aloop.create_task(
            self.motions.stop_all_ramp(damp_only=damp_only, damping=self.config.stop_damping,
                                       from_reference=self._distrust_measurement),
            name="agentsdk-stop-ramp",
        )
        timer = aloop.create_task(loop.clock.sleep(bound), name="agentsdk-stop-bound")
        try:
            waits: set[asyncio.Future[Any]] = {ramp, fault, timer}
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        finally:
            self._fault_waiters.discard(fault)
            for t in (ramp, timer):
                t.cancel()
            await asyncio.gather(ramp, timer, return_exceptions=True)
        if fault.done() or loop.fault is not None:
            return "fault"
        if ramp.cancelled() or ramp.exception() is not None:
            return "timeout"
        # the reference is at rest; the stop is achieved when the joints are (IEC 60204-1)
        clock, vel = loop.clock, loop.state.velocity
        deadline = clock.now() + self.config.rest_timeout
        while np.abs(vel).max(initial=0.0) >= self.config.rest_velocity:
            if clock.now() >= deadline or loop.fault is not None or loop.closed:
                return "fault" if loop.fault is not None else "timeout"
            await clock.sleep(loop.period)
        return "rest"

    def _hold_where_stopped(self) -> None:
        """End of a category 2 stop: hold with torque on at the stop ramp's final desired position.

        (Re-targeting to the measured position instead would step the setpoint by the
        servo's tracking error, e.g. the gravity sag, and let the joint sag further.)
        """
        loop = self.loop
        sp = loop.setpoint
        pos = np.flatnonzero((sp.mode == _POS) & sp.enabled)
        keep = sp.position[pos].copy()
        loop.hold_current()
        loop.hold_at(pos, keep)

    def _torque_off(self) -> None:
        self.loop.remove_torque()

    def estop_threadsafe(self, category: int = 0) -> None:
        """Latch an e-stop from any thread. Category 0 acts at once in the calling thread;
        categories 1 and 2 are scheduled on the robot's event loop (category 0 if it is gone).
        """
        if category not in (0, 1, 2):
            raise InvalidValueError(f"stop category must be 0, 1 or 2 (IEC 60204-1), got {category!r}")
        aloop = self._aloop
        loop = self.loop
        if category != 0 and aloop is not None and not aloop.is_closed() and not loop.closed:
            self._latch(category)

            def _start() -> None:
                if not loop.closed:
                    self._begin_stop(category, "threadsafe")

            try:
                aloop.call_soon_threadsafe(_start)
                return
            except RuntimeError:  # the event loop closed meanwhile: stop here
                pass
        self._latch(0)
        if loop.closed:
            return
        loop.emergency_stop(0)
        self.record("estop", f"category {category} (threadsafe): torque removed at once")

    async def reset(self) -> None:
        """Clear the latch (ESTOP -> DISABLED) or recover a FAULT. Never moves the robot.

        A stop in progress completes first. Anything still driving the joints over time
        (a trajectory, a stop ramp) ends here; the setpoint stays exactly as the stop
        left it: torque off stays off, a hold keeps holding where it is.
        """
        await self.wait_stopped()
        if self._state is SafetyState.FAULT:
            await self.loop.recover()
            self._cause = None
        if self._latched.is_set() and not self._latch_handled:
            self._enforce_latch()
        if not self._latched.is_set() and self._state in (SafetyState.OK, SafetyState.HOLD):
            # nothing latched: the robot may be moving (a trajectory, a velocity stream, a
            # position ramp). DISABLED means nothing moves: bring it to rest first (as a
            # category 2 stop would, torque stays on), never freeze it at speed.
            if "position" in self.loop.backend.capabilities.modes and self.loop.fault is None:
                outcome = await self._ramp_to_rest(damp_only=False)
                if outcome == "rest":
                    self._hold_where_stopped()
            self.motions.abort_all("reset")
        self.motions.end_all("reset")
        with self._latch_lock:
            self._latched.clear()
            self._latch_category = None
        self._latch_handled = False
        self.stall_traceback = None
        self._ramping[:] = False
        self._distrust_measurement = False
        if self.sensor_gate is not None:
            self.sensor_gate.clear()  # a joint still reading nonsense is reported again
        self._state = SafetyState.DISABLED
        if self._stall is not None:
            self._stall.beat()
        self.record("reset", "latch cleared; call enable() to allow motion")

    async def enable(self) -> None:
        """Allow motion again: hold the current position with torque on (ESTOP must be reset first)."""
        st = self.state
        if st is SafetyState.ESTOP:
            raise EStopActive("e-stop is latched; call `await robot.reset()` before `await robot.enable()`")
        self.check_fault()
        loop = self.loop
        await loop.enable()
        np.copyto(self._written, loop.state.position)
        self._goal = self._written.copy()
        self._ramping[:] = False
        self._held[:] = False
        self._fed[:] = loop.stamp
        self._state = SafetyState.OK
        self.record("enable", "motion enabled; holding current position")

    # ------------------------------------------------------ stall watchdog
    def _on_stall(self, last: float, stopped: float, stack: str, where: str) -> None:
        """The stall watchdog's thread found the event loop stuck (torque is already off): latch and say where."""
        timeout = self.config.stall_timeout
        self._latch(0)
        self._latch_handled = False  # the loop side still has to abort motions
        self.stall_latency = stopped - last
        self.stall_detected_at = stopped
        self.stall_traceback = stack
        detail = (
            f"event loop stalled for more than {timeout:g} s (last heartbeat {stopped - last:.3f} s ago); "
            f"e-stop category 0 latched; loop was at {where}: a blocking call (time.sleep, blocking I/O, "
            "a long computation) in a coroutine; use `await robot.clock.sleep()`, or `asyncio.to_thread()`"
        )
        self.record("stall", detail)
        log.error("%s\n%s", detail, stack)
