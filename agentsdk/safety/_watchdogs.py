"""The watchdogs of every tick (checks, command watchdog, sensor faults) and of the event loop (stall)."""

from __future__ import annotations

import traceback
from types import EllipsisType

import numpy as np

from ..backend import SetpointView
from ..checks import MeasuredPositionCheck, SafetyCheck
from ..clock import RealtimeClock
from ..errors import (
    InvalidValueError,
    SensorFault,
)
from ..following import FollowingErrorCheck
from ..loop import ControlLoop, HookHandle, Phase, StateView
from ..plausibility import SensorGate
from ..stall import StallWatchdog, format_stack
from ..types import MODES
from ._config import SafetyConfig
from ._filter import CommandFilter
from ._state import _POS, SafetyCore, SafetyState, StopPort, log
from ._stops import Stops


class FusedChecks:
    """The built-in checks' common tick as one comparison: the measured-position limits and the
    following-error window (in that order, nothing else registered).

    Every tick, one ``less_equal`` of the rows ``[lo, q, |q - q_ref|, tiny]`` against ``[q, hi, window, kp]``
    (``tiny`` the smallest positive float: ``tiny <= kp`` is ``kp > 0``; NaN fails every row) and one bytes
    compare. When every element holds, while every joint is armed and in position mode with torque on and
    the following check's state allows it (:meth:`FollowingErrorCheck.fused_ready`), both checks would
    return None: the measured check changes nothing, the following check only takes its peak and the time
    (:meth:`FollowingErrorCheck.fused_pass`). Anything else (a NaN, a joint outside, an unarmed joint)
    answers False, and the checks run one by one as before, producing the same events. The rows are
    copies and constants, so the pass costs three ufuncs fewer than the checks' own (four against seven).
    """

    def __init__(self, measured: MeasuredPositionCheck, following: FollowingErrorCheck, n: int) -> None:
        self._measured = measured
        self._following = following
        lo, hi = measured.fused_bounds()
        tiny = np.nextafter(0.0, 1.0)
        self._left = np.vstack([lo, np.zeros(n), np.zeros(n), np.full(n, tiny)])
        self._right = np.vstack([np.zeros(n), hi, following.windows, np.zeros(n)])
        self._q_left, self._err = self._left[1], self._left[2]
        self._q_right, self._kp = self._right[0], self._right[3]
        #: the bytes of the kp row last copied into the comparison
        self._kp_bytes = self._kp.tobytes()
        self._ok = np.zeros((4, n), dtype=bool)
        self._all_ok = np.ones((4, n), dtype=bool).tobytes()
        self._all_position = np.full(n, _POS, dtype=np.int8).tobytes()
        self._all_on = np.ones(n, dtype=bool).tobytes()

    def passes(self, t: float, q: np.ndarray, sp: SetpointView) -> bool:
        """True when both checks would pass this tick (their bookkeeping done).

        Call only with every joint in position mode and torque on.
        """
        following = self._following
        if not self._measured.block_ready() or not following.fused_ready(self._all_position, self._all_on):
            return False
        self._q_left[...] = q
        self._q_right[...] = q
        # (the gains rarely change: a bytes compare is half a row write; no bytes kept alive across the
        # comparison below, which makes its own: the tick's peak allocation stays one small object)
        if sp.kp.tobytes() != self._kp_bytes:
            self._kp[...] = sp.kp
            self._kp_bytes = self._kp.tobytes()
        err = self._err
        np.subtract(q, sp.position, out=err)  # the following check's own error, op for op
        np.abs(err, out=err)
        if np.less_equal(self._left, self._right, out=self._ok).tobytes() != self._all_ok:
            return False
        following.fused_pass(t, err)
        return True


class Watchdogs:
    """Watches each tick's state and the event loop; starts a stop (through ``stops``) when a watch fires.

    Owns the registered checks, the command watchdog (when each joint was last commanded, which
    joints it holds), the reaction to a sensor fault reported by ``sensor_gate`` and the wiring of
    the loop-stall thread (:class:`~agentsdk.stall.StallWatchdog`), which latches ``core`` from its
    own thread.
    """

    def __init__(
        self, loop: ControlLoop, config: SafetyConfig, core: SafetyCore, command_filter: CommandFilter,
        stops: Stops, motions: StopPort, sensor_gate: SensorGate | None,
    ) -> None:
        self._loop = loop
        self._config = config
        self._core = core
        self._stops = stops
        self._sensor_gate = sensor_gate
        #: the stop port of the motion manager (replaced by SafetyLayer.attach_motions)
        self.motions = motions
        #: bound once: the per-tick calls into the objects below
        self._all_position_on = command_filter.all_position_on
        self._track_measured = command_filter.track_measured
        self._begin_stop = stops.begin_stop
        self._checks: list[SafetyCheck] = []
        #: the built-in checks' tick in one pass (None unless the checks are exactly those two)
        self._fused: FusedChecks | None = None
        #: bumped whenever a check is added or removed (block lockstep caches what it learnt of them)
        self.checks_version = 0
        n = len(loop.joints)
        #: watched[mode code] -> True if the command watchdog applies to that mode
        self._watched = np.array([m in config.watchdog_modes for m in MODES], dtype=bool)
        self._watch_position = "position" in config.watchdog_modes
        self._fed = np.zeros(n)  # robot time of the last command per joint
        #: joints put on hold by the command watchdog (not watched again until commanded)
        self._held = np.zeros(n, dtype=bool)
        #: scratch masks of the per-tick path (streamed joints, stale streams) and the command age
        #: per joint: no arrays allocated per tick
        self._all_false = np.zeros(n, dtype=bool).tobytes()
        self._streamed = np.zeros(n, dtype=bool)
        self._stale = np.zeros(n, dtype=bool)
        self._age = np.zeros(n)
        #: the event-loop stall watchdog (None: not watched, see :attr:`stall_watchdog_active`)
        self._stall: StallWatchdog | None = None
        #: stack of the event-loop thread when the stall watchdog fired (cleared by a reset); its
        #: source lines are read when :attr:`stall_traceback` is first asked for, never in the
        #: watchdog thread before it stops the actuators
        self._stall_stack: traceback.StackSummary | None = None
        self._stall_traceback: str | None = None
        #: wall-clock time (time.monotonic) the stall watchdog fired, and how long after the last heartbeat
        self.stall_detected_at: float | None = None
        self.stall_latency: float | None = None

    # --------------------------------------------------------------- checks
    def add_check(self, check: SafetyCheck) -> HookHandle:
        """Run ``check(t, state)`` every tick while motion is allowed; a returned violation latches an e-stop."""
        if not callable(check):
            raise InvalidValueError(f"a safety check must be callable, got {check!r}")
        self._checks.append(check)
        self.checks_version += 1
        checks = self._checks
        self._fuse()

        def remove() -> None:
            if check in checks:
                checks.remove(check)
                self.checks_version += 1
                self._fuse()

        return HookHandle(remove, lambda: check in checks)

    def _fuse(self) -> None:
        """The fused pass of the built-in checks, when they are the only ones (in registration order)."""
        checks = self._checks
        self._fused = None
        if (len(checks) == 2 and type(checks[0]) is MeasuredPositionCheck
                and type(checks[1]) is FollowingErrorCheck):
            self._fused = FusedChecks(checks[0], checks[1], len(self._loop.joints))

    # ------------------------------------------------------ command watchdog
    def feed(self, idx: np.ndarray | EllipsisType) -> None:
        """A command was applied to joints ``idx`` (indices, or ``...`` for every joint): they are watched from now;
        a HOLD ends.
        """
        self._fed[idx] = self._loop.stamp
        held = self._held
        if held.tobytes() != self._all_false:  # (none held, the common case: a bytes compare, no write)
            held[idx] = False
        core = self._core
        if core._state is SafetyState.HOLD:
            core.enter(SafetyState.OK)
            core.record("resume", "command received; leaving HOLD")

    def rearm_commands(self) -> None:
        """Motion was enabled: no joint is held, every joint counts as commanded now."""
        self._held[:] = False
        self._fed[:] = self._loop.stamp

    def rearm_after_reset(self) -> None:
        """The latch was cleared: forget the stall's stack and reported sensor faults, beat the heartbeat."""
        self._stall_stack = self._stall_traceback = None
        if self._sensor_gate is not None:
            self._sensor_gate.clear()  # a joint still reading nonsense is reported again
        if self._stall is not None:
            self._stall.beat()

    # --------------------------------------------------------------- per tick
    def tick(self, t: float, st: StateView, sp: SetpointView) -> None:
        """OBSERVE phase, every tick: sensor faults, the checks, then the command watchdog."""
        gate = self._sensor_gate
        if gate is not None and gate.pending:
            self._sensor_fault(gate)
        all_position = self._all_position_on(sp.mode, sp.enabled)
        if not all_position:
            # the ramp origin of joints outside position mode is their fresh measurement
            self._track_measured(st.position, (sp.mode != _POS) | ~sp.enabled)
        state = self._core._state
        if state is not SafetyState.OK and state is not SafetyState.HOLD:
            return
        if self._core.latched:
            return
        fused = self._fused
        # the built-in checks in one comparison when all of them pass (the common tick); else one by one
        if fused is None or not all_position or not fused.passes(t, st.position, sp):
            for check in self._checks:
                violation = check(t, st)
                if violation is not None:
                    self._core.record(violation.kind, violation.detail, violation.joint)
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
        np.greater(age, self._config.command_timeout, out=stale)
        np.logical_and(stale, streamed, out=stale)
        if stale.tobytes() != self._all_false:
            idx = np.flatnonzero(stale)
            self._stops._hold(idx)
            self._held[idx] = True
            self._core.enter(SafetyState.HOLD)
            names = ", ".join(self._loop.names[i] for i in idx.tolist())
            self._core.record("watchdog", f"no command for {self._config.command_timeout:g} s; holding {names}")
            log.warning("command watchdog: holding %s", names)

    def _sensor_fault(self, gate: SensorGate) -> None:
        """A reading failed the plausibility rule: latch FAULT (naming joint and device) and stop.

        The state still holds the joint's last plausible reading; the stop starts every joint
        from its reference (the measurement is not trusted), category ``sensor_fault_stop``.
        """
        loop = self._loop
        core = self._core
        first: SensorFault | None = None
        for r in gate.take_new():
            name = loop.names[r.index]
            src = loop.backend.joint_source(r.index)
            where = f" ({src})" if src else ""
            detail = f"sensor fault on joint {name!r}{where}: {r.reason}; the last plausible state is kept"
            core.record("sensor", detail, name)
            log.error("%s", detail)
            if first is None:
                first = SensorFault(detail, joint=name, source=src, quantity=r.quantity, value=r.value)
        if first is None:
            return
        self._stops.distrust_measurement()
        if core._state is not SafetyState.FAULT:
            core.fault(first)
        self._begin_stop(self._config.sensor_fault_stop, "sensor fault")

    # ------------------------------------------------------ stall watchdog
    @property
    def stall_watchdog_active(self) -> bool:
        """True if the stall watchdog watches this robot (see the package documentation).

        That is: a ``stall_timeout`` is set and the robot runs in real time, or in lockstep with
        ``stall_in_lockstep``.
        """
        cfg = self._config
        return cfg.stall_timeout is not None and (self._loop.realtime or cfg.stall_in_lockstep)

    def start_stall_watchdog(self) -> None:
        """Start the stall watchdog's thread (and its heartbeat on every real-time tick) if it is active."""
        timeout = self._config.stall_timeout
        if self.stall_watchdog_active and timeout is not None and self._stall is None:
            loop = self._loop
            self._stall = StallWatchdog(
                timeout, f"agentsdk-stall-watchdog-{loop.backend.name}",
                idle=lambda: loop.torque_off or loop.closed,
                emergency_stop=lambda: loop.emergency_stop(0),
                on_stall=self._on_stall,
            )
            if isinstance(loop.clock, RealtimeClock):  # every tick beats, at the time the tick read anyway
                loop.add_hook(Phase.OBSERVE, self._stall.tick_beats(loop.clock.origin))
            self._stall.start()

    def stop_stall_watchdog_now(self) -> None:
        """Signal the stall watchdog's thread to stop (no event loop needed)."""
        if self._stall is not None:
            self._stall.stop_now()

    async def stop_stall_watchdog(self) -> None:
        """Stop the stall watchdog's thread and wait for it."""
        if self._stall is not None:
            await self._stall.stop()

    @property
    def stall_traceback(self) -> str | None:
        """The event-loop thread's stack when the stall watchdog fired, formatted (None since the last reset)."""
        stack = self._stall_stack
        if stack is None:
            return None
        if self._stall_traceback is None:
            self._stall_traceback = format_stack(stack)
        return self._stall_traceback

    def _on_stall(self, last: float, detected: float, stack: traceback.StackSummary, where: str) -> str:
        """The stall watchdog's thread found the event loop stuck; it removes torque right after this.

        Latch and report first (no blocking, no file access), as :meth:`Stops.estop_threadsafe`
        latches before it stops: whoever sees torque off sees the e-stop and the stall's report.
        Returns the message the thread logs, with the stack, once torque is off.
        """
        timeout = self._config.stall_timeout
        self._core.latch(0, handled=False)  # the loop side still has to abort motions
        self._stall_traceback = None
        self._stall_stack = stack
        self.stall_latency = detected - last
        self.stall_detected_at = detected
        detail = (
            f"event loop stalled for more than {timeout:g} s (last heartbeat {detected - last:.3f} s ago); "
            f"e-stop category 0 latched; loop was at {where}: a blocking call (time.sleep, blocking I/O, "
            "a long computation) in a coroutine; use `await robot.clock.sleep()`, or `asyncio.to_thread()`"
        )
        self._core.record("stall", detail)
        return detail

