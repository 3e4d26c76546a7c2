"""The watchdogs of every tick (checks, command watchdog, sensor faults) and of the event loop (stall)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..backend import SetpointView
from ..errors import (
    SensorFault,
)
from ..loop import StateView
from ..plausibility import SensorGate
from ._state import _POS, SafetyState, log
from ._stops import _Stops

if TYPE_CHECKING:
    pass



class _Watchdogs(_Stops):
    """Watches each tick's state and the event loop; starts a stop when a watch fires."""

    # --------------------------------------------------------------- state
    @property
    def stall_watchdog_active(self) -> bool:
        """True if the stall watchdog watches this robot (see the module documentation).

        That is: a ``stall_timeout`` is set and the robot runs in real time, or in lockstep with
        ``stall_in_lockstep``.
        """
        cfg = self.config
        return cfg.stall_timeout is not None and (self.loop.realtime or cfg.stall_in_lockstep)

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
