"""Robot clocks: simulated lockstep time and precise wall-clock time.

Both share one interface (``now``, ``sleep``, ``sleep_until``, ``timeout``), so a
behavior written against ``robot.clock`` runs unchanged in either time model.

* :class:`LockstepClock` — simulated time. It only moves when the controller's
  control loop advances it, one control period at a time, and only when every
  task on the event loop is waiting. Sleepers wake at the first control tick at
  or after their deadline, in deadline order (ties: first come, first served).
  Runs as fast as the CPU allows and is deterministic.
* :class:`RealtimeClock` — ``time.monotonic`` since connect. ``sleep_until``
  wakes within tens of microseconds of the deadline without spinning: asyncio's
  own timers are only ~1 ms precise, so it sleeps on a Linux ``timerfd``
  (:class:`agentsdk.realtime.DeadlineTimer`) watched by the event loop;
  elsewhere it falls back to ``asyncio.sleep``.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import math
import time
from abc import ABC, abstractmethod
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

from .errors import AgentTimeoutError, InvalidValueError
from .realtime import DeadlineTimer, timerfd_available

__all__ = ["Clock", "LockstepClock", "RealtimeClock"]

def _check_duration(dt: float) -> float:
    try:
        dt = float(dt)
    except (TypeError, ValueError):
        raise InvalidValueError(f"sleep duration must be a number of seconds, got {dt!r}") from None
    if math.isnan(dt) or dt < 0.0:
        raise InvalidValueError(f"sleep duration must be a number >= 0 (seconds), got {dt}")
    return dt


def _check_deadline(deadline: float) -> float:
    try:
        deadline = float(deadline)
    except (TypeError, ValueError):
        raise InvalidValueError(f"deadline must be a robot time in seconds, got {deadline!r}") from None
    if math.isnan(deadline):
        raise InvalidValueError("deadline must be a robot time in seconds, got nan")
    return deadline


class Clock(ABC):
    """Time as the robot sees it, in seconds.

    Once the robot is closed (or its control loop died) every ``sleep`` and
    ``sleep_until``, pending or new, raises the reason (:class:`RobotClosedError`,
    or the fault) instead of waiting for time that will never come. ``inf``
    sleeps until cancelled; NaN raises :class:`InvalidValueError`.
    """

    #: True when time is simulated and only advances in control ticks
    lockstep: bool = False

    def __init__(self) -> None:
        self._error: BaseException | None = None
        self._final = False
        #: futures of sleepers that no deadline will wake (``inf``) or that wait on a timer
        self._parked: set[asyncio.Future[None]] = set()

    @abstractmethod
    def now(self) -> float:
        """Current robot time in seconds (0 at connect)."""

    @abstractmethod
    async def sleep_until(self, deadline: float) -> None:
        """Wait until ``now() >= deadline``."""

    async def sleep(self, dt: float) -> None:
        """Wait ``dt`` seconds of robot time."""
        dt = _check_duration(dt)
        self._check_running()
        await self.sleep_until(self.now() + dt)

    @property
    def stopped(self) -> BaseException | None:
        """Why sleeping is impossible (robot closed, control loop faulted), or None while time runs."""
        return self._error

    def _check_running(self) -> None:
        if self._error is not None:
            raise _fresh(self._error)

    def fail(self, exc: BaseException, *, final: bool = False) -> None:
        """Wake every sleeper with ``exc``; later sleeps raise it too, until :meth:`resume` (not after ``final``).

        Used by the control loop: ``final=True`` when the robot closes, else when
        the loop faults (a recovered loop calls :meth:`resume`).
        """
        if self._final:
            return
        self._error = exc
        self._final = final
        self._fail_pending(exc)

    def resume(self) -> None:
        """Time runs again (the control loop was restarted after a fault)."""
        if not self._final:
            self._error = None

    def _fail_pending(self, exc: BaseException) -> None:
        parked, self._parked = self._parked, set()
        for fut in parked:
            if not fut.done():
                fut.set_exception(_fresh(exc))

    async def _park(self, delay: float | None) -> None:
        """Wait ``delay`` seconds of wall time (None: until cancelled), or until :meth:`fail`."""
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()
        handle = None if delay is None else loop.call_later(delay, _set_done, fut)
        self._parked.add(fut)
        try:
            await fut
        finally:
            self._parked.discard(fut)
            if handle is not None:
                handle.cancel()

    @asynccontextmanager
    async def timeout(self, dt: float) -> AsyncIterator[None]:
        """Like ``asyncio.timeout`` but in robot time; raises :class:`AgentTimeoutError`."""
        dt = _check_duration(dt)
        self._check_running()
        task = asyncio.current_task()
        assert task is not None
        expired = False

        async def _watch() -> None:
            nonlocal expired
            await self.sleep(dt)
            expired = True
            task.cancel()

        watcher = asyncio.get_running_loop().create_task(_watch())
        try:
            yield
        except asyncio.CancelledError:
            if expired and task.uncancel() == 0:
                raise AgentTimeoutError(f"timed out after {dt:g} s of robot time") from None
            raise
        finally:
            watcher.cancel()
            await asyncio.gather(watcher, return_exceptions=True)


def _set_done(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


def _end_lease(lease: asyncio.Future[bool]) -> None:
    if not lease.done():
        lease.set_result(False)


def _fresh(exc: BaseException) -> BaseException:
    """A new exception like ``exc`` (one instance raised in many tasks would collect their tracebacks)."""
    try:
        new = type(exc)(*exc.args)
    except Exception:
        return exc
    new.__cause__ = exc.__cause__
    return new


class RealtimeClock(Clock):
    """Wall-clock time (``time.monotonic``) since the clock was created."""

    lockstep = False

    def __init__(self) -> None:
        super().__init__()
        self._t0 = time.monotonic()
        self._timer: DeadlineTimer | None = None
        self._timer_failed = False

    def now(self) -> float:
        """Seconds since this clock was created (``time.monotonic`` based)."""
        return time.monotonic() - self._t0

    @property
    def origin(self) -> float:
        """``time.monotonic()`` at robot time 0: robot time ``t`` is monotonic time ``origin + t``."""
        return self._t0

    async def sleep_until(self, deadline: float) -> None:
        """Sleep until ``deadline`` (clock seconds) on the timerfd, no spin (else ``asyncio.sleep`` precision)."""
        deadline = _check_deadline(deadline)
        self._check_running()
        if deadline == math.inf:
            await self._park(None)  # until cancelled, or until the clock fails
            return
        if deadline <= 0.0:  # robot time starts at 0: long past (-inf included)
            await asyncio.sleep(0)
            self._check_running()
            return
        timer = self._timer
        if timer is None or timer.closed or timer.loop is not asyncio.get_running_loop():
            timer = self._precise_timer()
        if timer is None:  # no timerfd: the event loop's timer precision
            remaining = deadline - self.now()
            if remaining <= 0.0:
                await asyncio.sleep(0)
                self._check_running()
                return
            await self._park(remaining)
            return
        # the timerfd is armed at the absolute deadline: one already past fires at the next wake-up, so
        # no clock read here (the realtime control loop sleeps once per tick; a read is a system call
        # where there is no vDSO, e.g. user-mode Linux)
        fut = timer.sleep_until(self._t0 + deadline)
        self._parked.add(fut)  # fail() (robot closed, loop faulted) wakes it with the reason
        try:
            await fut
        finally:
            self._parked.discard(fut)

    def _precise_timer(self) -> DeadlineTimer | None:
        if self._timer_failed or not timerfd_available():
            return None
        try:
            self._timer = DeadlineTimer(asyncio.get_running_loop())
        except OSError:
            self._timer_failed = True
            return None
        return self._timer

    def release(self) -> None:
        """Close the clock's timer (the robot closed); later sleeps use ``asyncio.sleep``."""
        self._timer_failed = True
        if self._timer is not None:
            self._timer.close()
            self._timer = None


class LockstepClock(Clock):
    """Simulated time advanced by the controller's control loop."""

    lockstep = True

    def __init__(self, period: float) -> None:
        super().__init__()
        self.period = period
        self._tick = 0
        self._heap: list[tuple[float, int, asyncio.Future[None]]] = []
        self._seq = itertools.count()
        #: set whenever a new sleeper arrives, so an idle control loop wakes up
        self.wakeup = asyncio.Event()
        #: the inline tick (see :meth:`lend`): the control loop's tick, run by a behavior's sleep; None: never
        self.inline_tick: Callable[[], bool] | None = None
        #: while the control loop is lent (:meth:`lend`): its lease, the handle that ends it, the event
        #: loop's ready queue, and the wall time (``time.perf_counter``) the lease ends
        self._lease: asyncio.Future[bool] | None = None
        self._release: asyncio.Handle | None = None
        self._ready: Any = None
        self._lease_end = 0.0
        #: the last sleeper queued wakes at the next tick (a behavior that sleeps one period per tick)
        self.one_tick_sleeper = False
        #: ticks run by sleepers (:meth:`lend`) so far
        self.inline_ticks = 0

    def now(self) -> float:
        """Simulated time: ticks elapsed times the control period (no accumulated drift)."""
        # tick count * period: no accumulated floating-point drift
        return self._tick * self.period

    @property
    def ticks(self) -> int:
        """Control ticks elapsed since the start."""
        return self._tick

    async def sleep(self, dt: float) -> None:
        """Wait ``dt`` seconds of simulated time: :meth:`sleep_until` of ``now() + dt``.

        A behavior that sleeps one period per tick calls this every tick, so it checks once
        what :meth:`Clock.sleep` and :meth:`sleep_until` would both check (a float ``dt >= 0``
        needs no conversion) and queues the wake-up itself.
        """
        if type(dt) is not float or not dt >= 0.0:  # anything else (NaN, negative, an int) as Clock.sleep
            dt = _check_duration(dt)
        if self._error is not None:
            raise _fresh(self._error)
        now = self._tick * self.period
        deadline = now + dt
        if deadline <= now:
            await asyncio.sleep(0)
        elif math.isinf(deadline):
            await self._park(None)  # no tick ever reaches it: wait until cancelled or closed
        elif deadline <= (self._tick + 1) * self.period + 1e-12:  # the next tick wakes it (advance's test)
            if self._lease is not None and (ran := self._inline()):
                if ran == 2:
                    await self._after_inline()
                return
            self.one_tick_sleeper = True
            await self._enqueue(deadline)
        else:
            self.one_tick_sleeper = False
            await self._enqueue(deadline)

    async def sleep_until(self, deadline: float) -> None:
        """Resume once the control loop has advanced simulated time to ``deadline``."""
        deadline = _check_deadline(deadline)
        self._check_running()
        if deadline <= self.now():
            await asyncio.sleep(0)
            return
        if math.isinf(deadline):
            # no tick ever reaches it: wait (without driving simulated time) until cancelled or closed
            await self._park(None)
            return
        if deadline <= (self._tick + 1) * self.period + 1e-12:  # the next tick wakes it (advance's test)
            if self._lease is not None and (ran := self._inline()):
                if ran == 2:
                    await self._after_inline()
                return
            self.one_tick_sleeper = True
        else:
            self.one_tick_sleeper = False
        await self._enqueue(deadline)

    async def lend(self, ready: Any, budget: float) -> bool:
        """Park the control loop while a behavior that sleeps one period per tick runs the ticks itself.

        The control loop calls this after a tick that woke the only sleeper, one that slept until
        that tick (:attr:`one_tick_sleeper`). Until the lease ends, that behavior's next sleep
        until the next tick runs the tick in its own task (:attr:`inline_tick`) and returns
        without passing through the event loop, as long as nothing else could have run first:
        the event loop's ``ready`` queue holds only this lease's end, nobody else sleeps, and
        less than ``budget`` seconds of wall time have passed (asyncio timers and I/O then run,
        as between the control loop's batches). That is the tick the control loop would have
        run next, with the same inputs: what it saves is the hand-off (a future, two
        wake-ups, two passes through the event loop) per tick.

        The lease ends when that behavior waits for anything else, or anyone else becomes
        runnable: the handle queued here runs then and wakes the control loop. Returns True
        when an inline tick faulted the loop (the control loop then ends, as after a fault
        in its own tick).
        """
        loop = asyncio.get_running_loop()
        lease: asyncio.Future[bool] = loop.create_future()
        self._lease, self._ready = lease, ready
        self._release = release = loop.call_soon(_end_lease, lease)
        self._lease_end = time.perf_counter() + budget
        try:
            return await lease
        finally:
            release.cancel()
            if self._lease is lease:
                self._lease = self._release = None

    def _inline(self) -> int:
        """Run the next tick here if nothing else could run before it (:meth:`lend`).

        0: not run. 1: run. 2: run, and the sleeper must pass through the event loop before it
        returns (:meth:`_after_inline`): the tick made another task ready (a hook resolved a future,
        a fault listener woke a waiter), which would have run before the sleeper's wake-up, or
        the sleeper's own cancellation came during the tick, or the tick faulted the loop.
        """
        lease = self._lease
        assert lease is not None and self.inline_tick is not None
        ready = self._ready
        if lease.done() or len(ready) != 1 or ready[0] is not self._release:
            return 0
        if self._heap and self.next_deadline() is not None:
            return 0  # a task that ran before the sleeper (queued ahead of the lease's end) sleeps too
        if time.perf_counter() >= self._lease_end:
            return 0
        task = asyncio.current_task()
        if task is None or task.cancelling():
            return 0  # a cancellation is pending: it lands at the sleep, before the tick (as it would there)
        if not self.inline_tick():
            return 0  # (its step may suspend)
        self.inline_ticks += 1
        if self._error is not None:  # the tick faulted the loop: the control loop ends, this sleeper gets the fault
            if not lease.done():
                lease.set_result(True)
            return 2
        return 2 if len(ready) != 1 or task.cancelling() else 1

    async def _after_inline(self) -> None:
        """After an inline tick that woke another task, was cancelled or faulted: let the others run, then the fault."""
        await asyncio.sleep(0)
        if self._error is not None:
            raise _fresh(self._error)

    def _enqueue(self, deadline: float) -> asyncio.Future[None]:
        """A future the first tick at or after ``deadline`` resolves (and wake an idle control loop)."""
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        heapq.heappush(self._heap, (deadline, next(self._seq), fut))
        self.wakeup.set()
        return fut  # cancellation cancels fut; advance() skips it

    def next_deadline(self) -> float | None:
        """The earliest pending sleeper's deadline, or None when nobody waits."""
        heap = self._heap
        while heap and heap[0][2].done():
            heapq.heappop(heap)
        return heap[0][0] if heap else None

    def wakes_next_tick(self) -> bool:
        """The next :meth:`advance` wakes a sleeper (``ticks_until_wake(limit) == 1`` for any ``limit >= 1``).

        Block lockstep's first refusal (a behavior sleeping one period per tick), with
        :meth:`advance`'s own comparison.
        """
        deadline = self.next_deadline()
        return deadline is not None and deadline <= (self._tick + 1) * self.period + 1e-12

    def ticks_until_wake(self, limit: int) -> int:
        """How many ticks (at most ``limit``) :meth:`advance` can run before one wakes a sleeper, that one included.

        The seam of block lockstep: a block of ticks may run at once only up to the first tick
        that makes another task runnable. Decided with :meth:`advance`'s own comparison, so the
        answer is exact, not an estimate.
        """
        deadline = self.next_deadline()
        if deadline is None or limit <= 0:
            return max(limit, 0)
        period, tick = self.period, self._tick
        # a first guess from the division, then the exact test advance() makes, stepped to the boundary
        j = max(1, min(limit, math.ceil((deadline - 1e-12) / period) - tick))
        while j > 1 and deadline <= (tick + j - 1) * period + 1e-12:
            j -= 1
        while j < limit and not deadline <= (tick + j) * period + 1e-12:
            j += 1
        return j

    def advance_ticks(self, count: int) -> int:
        """What ``count`` calls of :meth:`advance` do (block lockstep commits a block's ticks); how many woke.

        The ticks before one that wakes a sleeper (:meth:`ticks_until_wake`, the same comparison)
        change nothing but the tick count, so they are counted at once.
        """
        woke = 0
        while count > 0:
            j = self.ticks_until_wake(count)
            self._tick += j - 1
            woke += self.advance()
            count -= j
        return woke

    def advance(self) -> int:
        """Move time forward one control period and wake due sleepers; returns how many woke."""
        self._tick += 1
        now = self.now() + 1e-12
        woke = 0
        heap = self._heap
        while heap and heap[0][0] <= now:
            _, _, fut = heapq.heappop(heap)
            if not fut.done():
                fut.set_result(None)
                woke += 1
        return woke

    def _fail_pending(self, exc: BaseException) -> None:
        super()._fail_pending(exc)
        for _, _, fut in self._heap:
            if not fut.done():
                fut.set_exception(_fresh(exc))
        self._heap.clear()
