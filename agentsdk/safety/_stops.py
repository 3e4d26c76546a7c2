"""Emergency stops (IEC 60204-1 categories 0, 1, 2), their ramps to rest, reset and enable."""

from __future__ import annotations

import asyncio
from typing import Any, Literal

import numpy as np

from ..errors import (
    EStopActive,
    InvalidValueError,
    RobotClosedError,
)
from ..limits import StepLimiter
from ..loop import ControlLoop
from ._config import SafetyConfig
from ._filter import CommandFilter
from ._state import _POS, SafetyCore, SafetyState, StopPort, log


class Stops:
    """Runs e-stops and controlled stops; clears the latch (reset) and restarts (enable).

    Latches through ``core``, ends the direct position ramps of ``command_filter`` and stops
    the motions through ``motions`` (the stop port). Also the loop's fault listener
    (:meth:`on_fault`): a fault ends a stop that is waiting for rest.
    """

    def __init__(
        self, loop: ControlLoop, config: SafetyConfig, limiter: StepLimiter, core: SafetyCore,
        command_filter: CommandFilter, motions: StopPort,
    ) -> None:
        self._loop = loop
        self._config = config
        self._core = core
        self._filter = command_filter
        #: the stop port of the motion manager (replaced by SafetyLayer.attach_motions)
        self.motions = motions
        self._vmax = limiter.vmax
        self._stop_tasks: set[asyncio.Task[None]] = set()
        #: the controlled stop (category 1 or 2) in progress and the category its end state follows
        self._ramp_stop: asyncio.Task[None] | None = None
        self._ramp_category = 2
        self._fault_waiters: set[asyncio.Future[BaseException]] = set()
        #: the robot's event loop (set by :meth:`bind`): where estop_threadsafe schedules a controlled stop
        self._aloop: asyncio.AbstractEventLoop | None = None
        #: a sensor fault since the last reset: stops start from the reference, not the measurement
        self._distrust_measurement = False

    def bind(self, aloop: asyncio.AbstractEventLoop) -> None:
        """The robot's event loop runs (called by SafetyLayer.start)."""
        self._aloop = aloop

    def distrust_measurement(self) -> None:
        """A sensor failed: until the next reset, stops start from the reference, not the measurement."""
        self._distrust_measurement = True

    @property
    def stop_in_progress(self) -> bool:
        """True while a controlled stop (category 1 or 2) is decelerating the robot."""
        return any(not t.done() for t in self._stop_tasks)

    def on_fault(self, exc: BaseException) -> None:
        """The control loop died (the loop's fault listener): FAULT, every motion fails, stops stop waiting."""
        core = self._core
        core.fault(exc)
        self._filter.cancel_ramps()
        core.record("fault", str(exc))
        self.motions.fail_all(exc)
        for fut in self._fault_waiters:
            if not fut.done():
                fut.set_result(exc)

    async def cancel(self) -> None:
        """End every stop task (awaited): the robot closes."""
        tasks = list(self._stop_tasks)
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)

    def _hold(self, idx: np.ndarray) -> None:
        loop = self._loop
        if self._config.hold == "position" and "position" in loop.backend.capabilities.modes:
            loop.hold_current(idx)
        else:
            loop.damp(idx, loop.gain_v[idx])

    def begin_stop(self, category: int, source: str) -> asyncio.Task[None]:
        """Loop side: latch, record and start the stop task of ``category``.

        A controlled stop already in progress is joined, not restarted (restarting its
        ramp would end the first one early, at speed); a category 1 request makes it end
        with torque off, a category 0 request removes torque at once.
        """
        core = self._core
        core.latch(category)
        core.take_latch()
        core.record("estop", f"category {category} requested" + ("" if source == "api" else f" ({source})"))
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
        task = self.begin_stop(category, "api")
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
        scale = self._config.stop_deceleration_scale
        acc = np.array([j.max_acceleration for j in self._loop.joints]) * scale
        jerk = np.array([j.max_jerk for j in self._loop.joints])
        t = self._vmax / acc + acc / jerk
        t = t[np.isfinite(t)]
        return 2.0 * float(t.max()) + 0.5 if t.size else 5.0

    async def _stop(self, category: int) -> None:
        loop = self._loop
        motions = self.motions
        if category == 0 or loop.fault is not None or loop.closed:
            self._filter.cancel_ramps()
            motions.abort_all("e-stop")
            self._torque_off()
            if category != 0:
                self._core.record("estop", f"category {category}: control loop not running; torque removed")
            return
        damp_only = "position" not in loop.backend.capabilities.modes
        if damp_only:
            self._filter.cancel_ramps()
            motions.abort_all("e-stop")
        # running motions are not aborted first: the stop ramp starts from their state
        outcome = await self._ramp_to_rest(damp_only)
        if outcome == "fault":
            # the control loop died during the stop; it removed torque itself (category 0)
            self._core.record("estop", f"category {category}: interrupted by a fault; torque removed")
            return
        if outcome == "timeout":
            bound = self._stop_time_bound()
            self._core.record("estop", f"category {category}: not at rest after {bound:g} s; ending the stop anyway")
            log.warning("e-stop category %d: joints not at rest after %g s", category, bound)
        category = min(category, self._ramp_category)  # escalated while stopping
        if category == 1:
            self._torque_off()
            self._core.record("estop", "category 1: stopped, torque removed")
        else:
            self._hold_where_stopped()
            self._core.record("estop", "category 2: stopped, holding with torque on")

    async def _ramp_to_rest(self, damp_only: bool) -> Literal["rest", "fault", "timeout"]:
        """Decelerate every joint to rest within its limits (bounded in robot time); how it ended."""
        loop = self._loop
        ramping = self._filter.end_ramps()
        if ramping.any() and not damp_only:
            # joints ramping to a direct position goal stop from where the ramp would be at
            # the next tick, at the ramp's velocity (not from rest: that would be a step)
            loop.set_reference(*self._filter.ramp_next(ramping))
        aloop = asyncio.get_running_loop()
        fault: asyncio.Future[BaseException] = aloop.create_future()
        self._fault_waiters.add(fault)
        bound = self._stop_time_bound()
        ramp = aloop.create_task(
            self.motions.stop_all_ramp(damp_only=damp_only, damping=self._config.stop_damping,
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
        deadline = clock.now() + self._config.rest_timeout
        while np.abs(vel).max(initial=0.0) >= self._config.rest_velocity:
            if clock.now() >= deadline or loop.fault is not None or loop.closed:
                return "fault" if loop.fault is not None else "timeout"
            await clock.sleep(loop.period)
        return "rest"

    def _hold_where_stopped(self) -> None:
        """End of a category 2 stop: hold with torque on at the stop ramp's final desired position.

        (Re-targeting to the measured position instead would step the setpoint by the
        servo's tracking error, e.g. the gravity sag, and let the joint sag further.)
        """
        loop = self._loop
        sp = loop.setpoint
        pos = np.flatnonzero((sp.mode == _POS) & sp.enabled)
        keep = sp.position[pos].copy()
        loop.hold_current()
        loop.hold_at(pos, keep)

    def _torque_off(self) -> None:
        self._loop.remove_torque()

    def estop_threadsafe(self, category: int = 0) -> None:
        """Latch an e-stop from any thread. Category 0 acts at once in the calling thread;
        categories 1 and 2 are scheduled on the robot's event loop (category 0 if it is gone).
        """
        if category not in (0, 1, 2):
            raise InvalidValueError(f"stop category must be 0, 1 or 2 (IEC 60204-1), got {category!r}")
        aloop = self._aloop
        loop = self._loop
        if category != 0 and aloop is not None and not aloop.is_closed() and not loop.closed:
            self._core.latch(category)

            def _start() -> None:
                if not loop.closed:
                    self.begin_stop(category, "threadsafe")

            try:
                aloop.call_soon_threadsafe(_start)
                return
            except RuntimeError:  # the event loop closed meanwhile: stop here
                pass
        self._core.latch(0)
        if loop.closed:
            return
        loop.emergency_stop(0)
        self._core.record("estop", f"category {category} (threadsafe): torque removed at once")

    async def reset(self) -> None:
        """Clear the latch (ESTOP -> DISABLED) or recover a FAULT. Never moves the robot.

        A stop in progress completes first. Anything still driving the joints over time
        (a trajectory, a stop ramp) ends here; the setpoint stays exactly as the stop
        left it: torque off stays off, a hold keeps holding where it is.
        """
        core = self._core
        # what this reset clears: the latch and the FAULT it began with, not one that comes meanwhile
        latches, faulted = core.latch_count, core._state is SafetyState.FAULT
        await self.wait_stopped()
        if core._state is SafetyState.FAULT:
            if not faulted:  # a fault while the stop in progress completed stands
                core.check_fault()
            await self._loop.recover()
            core.recovered()
            if core.latch_count != latches:  # recovered, but an e-stop latched meanwhile: that is the state now
                core.enter(SafetyState.ESTOP)
        self._check_no_new_latch(latches)
        if core.latched and not core._latch_handled:
            self._filter.enforce_latch()
        if not core.latched and core._state in (SafetyState.OK, SafetyState.HOLD):
            # nothing latched: the robot may be moving (a trajectory, a velocity stream, a
            # position ramp). DISABLED means nothing moves: bring it to rest first (as a
            # category 2 stop would, torque stays on), never freeze it at speed.
            if "position" in self._loop.backend.capabilities.modes and self._loop.fault is None:
                outcome = await self._ramp_to_rest(damp_only=False)
                if outcome == "rest":
                    self._hold_where_stopped()
            if core.state is SafetyState.FAULT:  # a fault while coming to rest stands
                core.check_fault()
            self._check_no_new_latch(latches)
            self.motions.abort_all("reset")
        self.motions.end_all("reset")
        core.clear_latch()
        self._filter.cancel_ramps()
        self._distrust_measurement = False
        core.enter(SafetyState.DISABLED)
        core.record("reset", "latch cleared; call enable() to allow motion")

    def _check_no_new_latch(self, latches: int) -> None:
        """Raise EStopActive if an e-stop latched since ``latch_count`` was ``latches`` (it stands)."""
        if self._core.latch_count != latches:
            raise EStopActive("an e-stop latched while reset() ran; it stands (call `await robot.reset()` again)")

    async def enable(self) -> None:
        """Allow motion again: hold the current position with torque on (ESTOP must be reset first)."""
        core = self._core
        if core.state is SafetyState.ESTOP:
            raise EStopActive("e-stop is latched; call `await robot.reset()` before `await robot.enable()`")
        core.check_fault()
        loop = self._loop
        await loop.enable(veto=core.refusal)  # a fault or an e-stop (any category) meanwhile stands
        self._filter.restart(loop.state.position)
        self._filter.cancel_ramps()
        core.enter(SafetyState.OK)
        core.record("enable", "motion enabled; holding current position")
