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
frames), latches the e-stop and records the loop thread's stack.
"""

from __future__ import annotations

import asyncio
import enum
import logging
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .controller import MODE_CODES, Controller, Setpoint, StateBuffer
from .errors import (
    ConfigurationError,
    EStopActive,
    InvalidValueError,
    LimitViolation,
    RobotClosedError,
    SafetyFault,
)
from .types import MODES, CommandMode

if TYPE_CHECKING:
    from .motion import MotionManager

__all__ = ["SafetyConfig", "SafetyEvent", "SafetyLayer", "SafetyState"]

log = logging.getLogger("agentsdk.safety")


class SafetyConfig(BaseModel):
    """Safety settings (robot.yaml ``safety:``, overridable in ``connect(safety=...)``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: what to do with an out-of-limit command: clamp it (and record) or reject it
    limit_policy: Literal["clamp", "reject"] = "clamp"
    #: soft margin inside the URDF position limits (rad or m)
    position_margin: float = Field(default=0.0, ge=0.0)
    #: max change of a position setpoint per control cycle; "auto" = max_velocity * period; None = off
    max_position_step: float | Literal["auto"] | None = "auto"
    #: a streamed command older than this puts its joints in HOLD (robot time, s)
    command_timeout: float = Field(default=0.25, gt=0.0)
    #: command modes the command watchdog applies to (position targets hold by themselves)
    watchdog_modes: tuple[CommandMode, ...] = ("velocity", "effort")
    #: HOLD keeps position ("position") or only damps ("damping")
    hold: Literal["position", "damping"] = "position"
    #: event-loop stall watchdog (wall-clock seconds); None disables the thread
    stall_timeout: float | None = Field(default=0.25, gt=0.0)
    #: damping gain used by category 1 where position control is absent (N·m·s/rad)
    stop_damping: float = Field(default=5.0, ge=0.0)
    #: scale of the joints' max_acceleration used when decelerating to a stop
    stop_deceleration_scale: float = Field(default=1.0, gt=0.0, le=1.0)
    #: minimum seconds between two identical clamp warnings in the log
    warn_interval: float = Field(default=1.0, ge=0.0)

    @classmethod
    def from_sources(
        cls, yaml_section: Mapping[str, Any] | None, override: SafetyConfig | Mapping[str, Any] | None
    ) -> SafetyConfig:
        data = dict(yaml_section or {})
        if isinstance(override, SafetyConfig):
            data.update(override.model_dump(exclude_unset=True))
        elif override:
            data.update(override)
        try:
            return cls(**data)
        except ValidationError as exc:
            raise ConfigurationError(f"invalid safety configuration:\n{exc}") from exc


class SafetyState(enum.Enum):
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


_POS, _VEL, _EFF = (MODE_CODES[m] for m in MODES)


class SafetyLayer:
    """Wraps one Controller. Created by :func:`agentsdk.connect`; reach it as ``robot.safety``."""

    def __init__(self, ctl: Controller, config: SafetyConfig) -> None:
        self.ctl = ctl
        self.config = config
        self.events: deque[SafetyEvent] = deque(maxlen=10_000)
        self._state = SafetyState.OK
        self._cause: BaseException | None = None
        self._latched = threading.Event()  # set from any thread
        self._latch_lock = threading.Lock()
        #: lowest stop category latched since the last reset (None: not latched)
        self._latch_category: int | None = None
        #: the loop side has taken over the current latch (see _enforce_latch)
        self._latch_handled = False
        self._pending_thread_events: deque[SafetyEvent] = deque()
        self.stall_traceback: str | None = None
        self.motions: MotionManager | None = None
        n = len(ctl.joints)
        m = config.position_margin
        self._lo = np.where(np.isfinite(ctl.lower), ctl.lower + m, -np.inf)
        self._hi = np.where(np.isfinite(ctl.upper), ctl.upper - m, np.inf)
        if np.any(self._lo > self._hi):
            raise ConfigurationError("safety position_margin is larger than half a joint's range")
        step = config.max_position_step
        if step == "auto":
            self._step = ctl.max_velocity * ctl.period
        elif step is None:
            self._step = None
        else:
            self._step = np.full(n, float(step))
        #: watched[mode code] -> True if the command watchdog applies to that mode
        self._watched = np.array([m in config.watchdog_modes for m in MODES], dtype=bool)
        self._fed = np.zeros(n)  # robot time of the last command per joint
        self._written = ctl.state.position.copy()
        #: goal of a direct position command being ramped (max_position_step), per joint
        self._goal = ctl.setpoint.position.copy()
        self._ramping = np.zeros(n, dtype=bool)
        #: joints put on hold by the command watchdog (not watched again until commanded)
        self._held = np.zeros(n, dtype=bool)
        self._vmax = np.where(np.isnan(ctl.max_velocity), np.inf, ctl.max_velocity)
        self._emax = np.where(np.isnan(ctl.max_effort), np.inf, ctl.max_effort)
        self._vmin = -self._vmax
        self._emin = -self._emax
        self._last_warn: dict[tuple[str, int], float] = {}
        self._stop_tasks: set[asyncio.Task[None]] = set()
        #: the controlled stop (category 1 or 2) in progress and the category its end state follows
        self._ramp_stop: asyncio.Task[None] | None = None
        self._ramp_category = 2
        self._fault_waiters: set[asyncio.Future[BaseException]] = set()
        # stall watchdog
        self._beat = time.monotonic()
        self._beat_handle: asyncio.TimerHandle | None = None
        self._thread: threading.Thread | None = None
        self._thread_stop = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread_id = threading.get_ident()
        self.stall_detected_at: float | None = None
        self.stall_latency: float | None = None
        ctl.setpoint_filters.append(self._filter)
        ctl.tick_hooks.append(self._on_tick)
        ctl.fault_hooks.append(self._on_fault)

    # ---------------------------------------------------------- lifecycle
    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._loop_thread_id = threading.get_ident()
        self._written = self.ctl.setpoint.position.copy()
        self._goal = self._written.copy()
        if self.config.stall_timeout is not None:
            self._beat = time.monotonic()
            self._schedule_beat()
            self._thread = threading.Thread(
                target=self._watch_stall, name=f"agentsdk-stall-watchdog-{self.ctl.name}", daemon=True
            )
            self._thread.start()

    def shutdown(self) -> None:
        """Stop the watchdog thread (joined) and heartbeat; called by Robot.close()."""
        self._thread_stop.set()
        if self._beat_handle is not None:
            self._beat_handle.cancel()
            self._beat_handle = None
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._thread = None
        for task in list(self._stop_tasks):
            task.cancel()

    # --------------------------------------------------------------- state
    @property
    def state(self) -> SafetyState:
        # no side effect here: the loop side must still see a latch set from another thread
        if self._state is SafetyState.FAULT:
            return SafetyState.FAULT
        if self._latched.is_set():
            return SafetyState.ESTOP  # possibly latched from another thread, not handled yet
        return self._state

    @property
    def cause(self) -> BaseException | None:
        return self._cause

    def record(self, kind: str, detail: str, joint: str | None = None) -> SafetyEvent:
        ev = SafetyEvent(self.ctl.stamp, kind, joint, detail)
        self.events.append(ev)
        return ev

    def _drain_thread_events(self) -> None:
        while self._pending_thread_events:
            self.events.append(self._pending_thread_events.popleft())

    def check_fault(self) -> None:
        if self._state is SafetyState.FAULT:
            raise SafetyFault(f"safety FAULT: {self._cause}") from self._cause

    def check_motion_allowed(self) -> None:
        st = self.state
        if st is SafetyState.OK or st is SafetyState.HOLD:
            return
        if st is SafetyState.FAULT:
            self.check_fault()
        if st is SafetyState.DISABLED:
            raise EStopActive("robot is disabled after reset(); call `await robot.enable()` to allow motion")
        raise EStopActive("e-stop is latched; call `await robot.reset()` then `await robot.enable()`")

    # -------------------------------------------------------------- limits
    def _warn(self, kind: str, j: int, msg: str) -> None:
        """Log a warning at most once per ``warn_interval`` (wall time) per (kind, joint)."""
        now = time.monotonic()
        key = (kind, j)
        if now - self._last_warn.get(key, -1e9) >= self.config.warn_interval:
            self._last_warn[key] = now
            log.warning(msg)

    def limit_command(self, mode: CommandMode, idx: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Check a validated command against limits: returns the (possibly clamped) values or raises."""
        ctl = self.ctl
        if mode == "position":
            lo, hi = self._lo[idx], self._hi[idx]
            what, unit = "position", "rad"
        elif mode == "velocity":
            hi = ctl.max_velocity[idx]
            lo = -hi
            what, unit = "velocity", "rad/s"
        else:
            hi = ctl.max_effort[idx]
            lo = -hi
            what, unit = "effort", "N·m"
        out = np.minimum(np.maximum(values, lo), hi)
        bad = out != values
        reject = self.config.limit_policy == "reject"
        if reject and bad.any():
            k = int(np.argmax(bad))
            raise LimitViolation(
                f"{what} command {values[k]:.4g} {unit} for joint {ctl.names[int(idx[k])]!r} is outside "
                f"[{lo[k]:.4g}, {hi[k]:.4g}]"
            )
        if mode == "position" and self._step is not None and reject:
            jump = np.abs(values - self._written[idx]) > self._step[idx] + 1e-12
            if jump.any():
                k = int(np.argmax(jump))
                j = int(idx[k])
                raise LimitViolation(
                    f"position step for joint {ctl.names[j]!r} is {abs(values[k] - self._written[j]):.4f} rad, "
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
            name = self.ctl.names[j]
            msg = f"{what} command {values[k]:.4g} {unit} for joint {name!r} is outside [{lo[k]:.4g}, {hi[k]:.4g}]"
            self.record("clamp", f"{msg}; clamped to {out[k]:.4g}", name)
            self._warn(f"clamp {what}", j, msg + "; clamped")

    def limit_feedforward(
        self, idx: np.ndarray, velocity: np.ndarray | None, effort: np.ndarray | None
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Check position-mode feed-forward terms against the velocity and effort limits.

        Same policy as :meth:`limit_command`: clamp (and record) or raise :class:`LimitViolation`.
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
                        f"{what} {arr[k]:.4g} {unit} for joint {self.ctl.names[int(idx[k])]!r} is outside "
                        f"[{-hi[k]:.4g}, {hi[k]:.4g}]"
                    )
                self._record_clamps(what, unit, idx, arr, clipped, -hi, hi)
                arr = clipped
            out.append(arr)
        return out[0], out[1]

    def feed(self, mode: CommandMode, idx: np.ndarray) -> None:
        """A command was applied to these joints: refresh the command watchdog, start position ramps.

        A direct position command becomes the *goal* of a ramp limited to
        ``max_position_step`` per cycle; the setpoint keeps showing where the
        ramp is, so a stop started before the next tick starts from there.
        """
        self._fed[idx] = self.ctl.stamp
        self._held[idx] = False
        if mode == "position":
            sp = self.ctl.setpoint
            self._goal[idx] = sp.position[idx]
            sp.position[idx] = self._written[idx]
            self._ramping[idx] = True
        else:
            self._ramping[idx] = False
        if self._state is SafetyState.HOLD:
            self._state = SafetyState.OK
            self.record("resume", "command received; leaving HOLD")

    def check_trajectory_point(self, positions: np.ndarray, idx: np.ndarray) -> None:
        bad = (positions < self._lo[idx]) | (positions > self._hi[idx])
        if bad.any():
            k = int(np.argmax(bad))
            j = int(idx[k])
            raise LimitViolation(
                f"trajectory position {positions[k]:.4g} for joint {self.ctl.names[j]!r} is outside "
                f"[{self._lo[j]:.4g}, {self._hi[j]:.4g}]"
            )

    # ---------------------------------------------------------- per cycle
    def _filter(self, t: float, st: StateBuffer, sp: Setpoint) -> None:
        """Setpoint filter, every tick: keep position setpoints in limits and ramp their steps.

        A joint with a direct position command ramps towards its goal (see :meth:`feed`);
        every other position-mode joint (trajectory, stop ramp, hold) is limited to what
        its writer put in the setpoint for this cycle. Feed-forward terms are clipped to
        the velocity and effort limits as a backstop.
        """
        if self._latched.is_set() and not self._latch_handled:
            self._enforce_latch()
        pos_mode = (sp.mode == _POS) & sp.enabled
        written = self._written
        # joints not in position mode track the measured position (bumpless switch)
        np.copyto(written, st.position, where=~pos_mode)
        ramping = self._ramping
        ramping &= pos_mode
        if self.motions is not None:
            ramping &= ~self.motions.owned_mask
        target = np.where(ramping, self._goal, sp.position)
        # (ufuncs with out=: np.clip costs several µs of dispatch on small arrays)
        np.maximum(target, self._lo, out=target)
        np.minimum(target, self._hi, out=target)
        if self._step is not None:
            out = np.maximum(target, written - self._step)
            np.minimum(out, written + self._step, out=out)
        else:
            out = target
        np.copyto(sp.position, out, where=pos_mode)
        ramping &= out != target
        np.copyto(written, out, where=pos_mode)
        np.maximum(sp.velocity, self._vmin, out=sp.velocity)
        np.minimum(sp.velocity, self._vmax, out=sp.velocity)
        np.maximum(sp.effort, self._emin, out=sp.effort)
        np.minimum(sp.effort, self._emax, out=sp.effort)

    def _on_tick(self, t: float, st: StateBuffer) -> None:
        if self._pending_thread_events:
            self._drain_thread_events()
        sp = self.ctl.setpoint
        # the ramp origin of joints outside position mode is their fresh measurement
        np.copyto(self._written, st.position, where=(sp.mode != _POS) | ~sp.enabled)
        if self._state is not SafetyState.OK and self._state is not SafetyState.HOLD:
            return
        # in HOLD too: another joint's stream may go stale while the first one is held
        streamed = self._watched[sp.mode] & sp.enabled & ~self._held
        if not streamed.any():
            return
        if self.motions is not None:
            streamed &= ~self.motions.owned_mask
        stale = streamed & (t - self._fed > self.config.command_timeout)
        if stale.any():
            idx = np.flatnonzero(stale)
            self._hold(idx)
            self._held[idx] = True
            self._state = SafetyState.HOLD
            names = ", ".join(self.ctl.names[i] for i in idx.tolist())
            self.record("watchdog", f"no command for {self.config.command_timeout:g} s; holding {names}")
            log.warning("command watchdog: holding %s", names)

    def _hold(self, idx: np.ndarray) -> None:
        ctl = self.ctl
        if self.config.hold == "position" and "position" in ctl.capabilities.modes:
            ctl.hold_current(idx)
        else:
            sp = ctl.setpoint
            sp.mode[idx] = _VEL
            sp.kp[idx] = 0.0
            sp.kd[idx] = ctl.gain_v[idx]
            sp.velocity[idx] = 0.0
            sp.effort[idx] = 0.0

    def _on_fault(self, exc: BaseException) -> None:
        self._state = SafetyState.FAULT
        self._cause = exc
        self._ramping[:] = False
        self.record("fault", str(exc))
        if self.motions is not None:
            self.motions.fail_all(exc)
        for fut in self._fault_waiters:
            if not fut.done():
                fut.set_result(exc)

    # --------------------------------------------------------------- e-stop
    def _latch(self, category: int, source: str) -> bool:
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
            if self.motions is not None:
                self.motions.abort_all("e-stop")

    def _begin_stop(self, category: int, source: str) -> asyncio.Task[None]:
        """Loop side: latch, record and start the stop task of ``category``.

        A controlled stop already in progress is joined, not restarted (restarting its
        ramp would end the first one early, at speed); a category 1 request makes it end
        with torque off, a category 0 request removes torque at once.
        """
        self._latch(category, source)
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

    def _stop_time_bound(self) -> float:
        """Robot seconds a controlled stop may take before the safety layer stops waiting for rest."""
        scale = self.config.stop_deceleration_scale
        acc = np.array([j.max_acceleration for j in self.ctl.joints]) * scale
        jerk = np.array([j.max_jerk for j in self.ctl.joints])
        t = self._vmax / acc + acc / jerk
        t = t[np.isfinite(t)]
        return 2.0 * float(t.max()) + 0.5 if t.size else 5.0

    async def _stop(self, category: int) -> None:
        ctl = self.ctl
        motions = self.motions
        ramping = self._ramping.copy()
        self._ramping[:] = False
        if category == 0 or motions is None or ctl.fault is not None or ctl.closed:
            if motions is not None:
                motions.abort_all("e-stop")
            self._torque_off()
            if category != 0:
                self.record("estop", f"category {category}: control loop not running; torque removed")
            return
        damp_only = "position" not in ctl.capabilities.modes
        if damp_only:
            motions.abort_all("e-stop")
        elif ramping.any():
            # joints ramping to a direct position goal stop from where the ramp would be at
            # the next tick, at the ramp's velocity (not from rest: that would be a step)
            sp = ctl.setpoint
            step = self._step if self._step is not None else np.inf
            nxt = np.clip(np.clip(self._goal, self._lo, self._hi), self._written - step, self._written + step)
            np.copyto(sp.velocity, (nxt - self._written) / ctl.period, where=ramping)
            np.copyto(sp.position, nxt, where=ramping)
        # running motions are not aborted first: the stop ramp starts from their desired state
        loop = asyncio.get_running_loop()
        fault: asyncio.Future[BaseException] = loop.create_future()
        self._fault_waiters.add(fault)
        bound = self._stop_time_bound()
        ramp = loop.create_task(motions.stop_all_ramp(damp_only=damp_only), name="agentsdk-stop-ramp")
        timer = loop.create_task(ctl.clock.sleep(bound), name="agentsdk-stop-bound")
        try:
            await asyncio.wait({ramp, fault, timer}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            self._fault_waiters.discard(fault)
            for t in (ramp, timer):
                t.cancel()
            await asyncio.gather(ramp, timer, return_exceptions=True)
        if fault.done() or ctl.fault is not None:
            # the control loop died during the stop; it removed torque itself (category 0)
            self.record("estop", f"category {category}: interrupted by a fault; torque removed")
            return
        if ramp.cancelled() or ramp.exception() is not None:
            self.record("estop", f"category {category}: not at rest after {bound:g} s; ending the stop anyway")
            log.warning("e-stop category %d: joints not at rest after %g s", category, bound)
        category = min(category, self._ramp_category)  # escalated while stopping
        if category == 1:
            self._torque_off()
            self.record("estop", "category 1: stopped, torque removed")
        else:
            self._hold_where_stopped()
            self.record("estop", "category 2: stopped, holding with torque on")

    def _hold_where_stopped(self) -> None:
        """End of a category 2 stop: hold with torque on at the stop ramp's final desired position.

        (Re-targeting to the measured position instead would step the setpoint by the
        servo's tracking error, e.g. the gravity sag, and let the joint sag further.)
        """
        ctl = self.ctl
        sp = ctl.setpoint
        pos = (sp.mode == _POS) & sp.enabled
        keep = sp.position.copy()
        ctl.hold_current()
        np.copyto(sp.position, keep, where=pos)
        np.copyto(ctl.target, keep, where=pos)

    def _torque_off(self) -> None:
        ctl = self.ctl
        ctl.setpoint.enabled[:] = False
        ctl.setpoint.kp[:] = 0.0
        ctl.setpoint.kd[:] = 0.0
        ctl.setpoint.effort[:] = 0.0
        ctl.emergency_stop(0)

    def estop_threadsafe(self, category: int = 0) -> None:
        """Latch an e-stop from any thread. Category 0 acts at once in the calling thread;
        categories 1 and 2 are scheduled on the robot's event loop (category 0 if it is gone)."""
        if category not in (0, 1, 2):
            raise InvalidValueError(f"stop category must be 0, 1 or 2 (IEC 60204-1), got {category!r}")
        loop = self._loop
        if category != 0 and loop is not None and not loop.is_closed() and not self.ctl.closed:
            self._latch(category, "thread")

            def _start() -> None:
                if not self.ctl.closed:
                    self._begin_stop(category, "threadsafe")

            try:
                loop.call_soon_threadsafe(_start)
                return
            except RuntimeError:  # the loop closed meanwhile: stop here
                pass
        self._latch(0, "thread")
        if self.ctl.closed:
            return
        self.ctl.emergency_stop(0)
        self._pending_thread_events.append(
            SafetyEvent(self.ctl.stamp, "estop", None, f"category {category} (threadsafe): torque removed at once")
        )

    async def reset(self) -> None:
        """Clear the latch (ESTOP -> DISABLED) or recover a FAULT. Never moves the robot."""
        if self._stop_tasks:
            # a stop in progress completes first
            await asyncio.gather(*self._stop_tasks, return_exceptions=True)
        if self._state is SafetyState.FAULT:
            await self.ctl.recover()
            self._cause = None
        with self._latch_lock:
            self._latched.clear()
            self._latch_category = None
        self._latch_handled = False
        self.stall_traceback = None
        self._ramping[:] = False
        # stay exactly as the stop left us: torque off stays off, a hold keeps holding
        self._state = SafetyState.DISABLED
        self._beat = time.monotonic()
        self.record("reset", "latch cleared; call enable() to allow motion")

    async def enable(self) -> None:
        """Allow motion again: hold the current position with torque on (ESTOP must be reset first)."""
        st = self.state
        if st is SafetyState.ESTOP:
            raise EStopActive("e-stop is latched; call `await robot.reset()` before `await robot.enable()`")
        self.check_fault()
        ctl = self.ctl
        await ctl.enable_hook()
        ctl.hold_current()
        self._written = ctl.state.position.copy()
        self._goal = self._written.copy()
        self._ramping[:] = False
        self._held[:] = False
        self._fed[:] = ctl.stamp
        self._state = SafetyState.OK
        self.record("enable", "motion enabled; holding current position")

    # ------------------------------------------------------ stall watchdog
    def _schedule_beat(self) -> None:
        loop = self._loop
        if loop is None or self._thread_stop.is_set():
            return
        interval = min(0.005, (self.config.stall_timeout or 1.0) / 10)

        def _beat() -> None:
            self._beat = time.monotonic()
            self._schedule_beat()

        self._beat_handle = loop.call_later(interval, _beat)

    def _watch_stall(self) -> None:
        timeout = self.config.stall_timeout
        assert timeout is not None
        poll = min(0.002, timeout / 20)
        while not self._thread_stop.wait(poll):
            last = self._beat
            now = time.monotonic()
            if now - last <= timeout or self._latched.is_set():
                continue
            # the event loop is stuck: stop the actuators from this thread
            try:
                self.ctl.emergency_stop(0)
            except Exception:
                log.exception("emergency stop hook failed in the stall watchdog")
            stopped = time.monotonic()
            self._latch(0, "stall")
            self.stall_latency = stopped - last
            self.stall_detected_at = stopped
            frame = sys._current_frames().get(self._loop_thread_id)
            stack = "".join(traceback.format_stack(frame)) if frame is not None else "(loop thread not found)"
            self.stall_traceback = stack
            where = _innermost_user_frame(frame)
            detail = (
                f"event loop stalled for more than {timeout:g} s (last heartbeat {stopped - last:.3f} s ago); "
                f"e-stop category 0 latched; loop was at {where}"
            )
            self._pending_thread_events.append(SafetyEvent(self.ctl.stamp, "stall", None, detail))
            log.error("%s\n%s", detail, stack)


def _innermost_user_frame(frame: Any) -> str:
    if frame is None:
        return "unknown"
    summary = traceback.extract_stack(frame)
    for fs in reversed(summary):
        if "asyncio" not in fs.filename and "agentsdk/safety" not in fs.filename:
            return f"{fs.filename}:{fs.lineno} in {fs.name}"
    fs = summary[-1]
    return f"{fs.filename}:{fs.lineno} in {fs.name}"
