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
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from .errors import AgentTimeoutError, InvalidValueError
from .realtime import DeadlineTimer, timerfd_available

__all__ = ["Clock", "LockstepClock", "RealtimeClock"]

def _check_duration(dt: float) -> float:
    dt = float(dt)
    if math.isnan(dt) or dt < 0.0:
        raise InvalidValueError(f"sleep duration must be a finite number >= 0, got {dt!r}")
    return dt


class Clock(ABC):
    """Time as the robot sees it, in seconds."""

    #: True when time is simulated and only advances in control ticks
    lockstep: bool = False

    @abstractmethod
    def now(self) -> float:
        """Current robot time in seconds (0 at connect)."""

    @abstractmethod
    async def sleep_until(self, deadline: float) -> None:
        """Wait until ``now() >= deadline``."""

    async def sleep(self, dt: float) -> None:
        """Wait ``dt`` seconds of robot time."""
        await self.sleep_until(self.now() + _check_duration(dt))

    @asynccontextmanager
    async def timeout(self, dt: float) -> AsyncIterator[None]:
        """Like ``asyncio.timeout`` but in robot time; raises :class:`AgentTimeoutError`."""
        dt = _check_duration(dt)
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


class RealtimeClock(Clock):
    """Wall-clock time (``time.monotonic``) since the clock was created."""

    lockstep = False

    def __init__(self) -> None:
        self._t0 = time.monotonic()
        self._timer: DeadlineTimer | None = None
        self._timer_failed = False

    def now(self) -> float:
        """Seconds since this clock was created (``time.monotonic`` based)."""
        return time.monotonic() - self._t0

    async def sleep_until(self, deadline: float) -> None:
        """Sleep until ``deadline`` (clock seconds): an asyncio sleep, then a short cooperative spin for precision."""
        remaining = deadline - self.now()
        if remaining <= 0.0:
            await asyncio.sleep(0)
            return
        timer = self._timer
        if timer is None or timer.closed or timer.loop is not asyncio.get_running_loop():
            timer = self._precise_timer()
        if timer is None:
            await asyncio.sleep(remaining)  # no timerfd: the event loop's timer precision
            return
        await timer.sleep_until(self._t0 + deadline)

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
        self.period = period
        self._tick = 0
        self._heap: list[tuple[float, int, asyncio.Future[None]]] = []
        self._seq = itertools.count()
        #: set whenever a new sleeper arrives, so an idle control loop wakes up
        self.wakeup = asyncio.Event()

    def now(self) -> float:
        """Simulated time: ticks elapsed times the control period (no accumulated drift)."""
        # tick count * period: no accumulated floating-point drift
        return self._tick * self.period

    @property
    def ticks(self) -> int:
        """Control ticks elapsed since the start."""
        return self._tick

    async def sleep_until(self, deadline: float) -> None:
        """Resume once the control loop has advanced simulated time to ``deadline``."""
        if deadline <= self.now():
            await asyncio.sleep(0)
            return
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        heapq.heappush(self._heap, (deadline, next(self._seq), fut))
        self.wakeup.set()
        await fut  # cancellation cancels fut; advance() skips it

    def next_deadline(self) -> float | None:
        """The earliest pending sleeper's deadline, or None when nobody waits."""
        heap = self._heap
        while heap and heap[0][2].done():
            heapq.heappop(heap)
        return heap[0][0] if heap else None

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

    def cancel_all(self, exc: BaseException) -> None:
        """Fail every pending sleeper (used when the robot closes or faults)."""
        for _, _, fut in self._heap:
            if not fut.done():
                fut.set_exception(exc)
        self._heap.clear()
