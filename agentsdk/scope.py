"""Motion scopes: whoever opened a scope owns the motions started inside it.

The robot calls :func:`register` every time a motion starts (``robot.follow(...)``).
If the calling task runs inside a :class:`MotionScope` (held in a
:mod:`contextvars` variable, so it follows the task and the tasks it spawns),
the motion is added to that scope; outside any scope ``register`` does nothing.

Closing a scope asks every motion that is still running to decelerate and hold
(``motion.cancel()``), then waits until they have all stopped, bounded by a
timeout measured on a :class:`ClockLike`.  If they do not stop in time,
:class:`MotionStopTimeoutError` is raised: the caller must escalate (e.g. e-stop).

The state machine engine opens a fresh scope for every state body, so leaving a
state -- by any transition, a timeout, an exception or cancellation -- stops the
motions that state started.  Scripts can use a scope directly::

    async with MotionScope("pick", clock=robot.clock):
        robot.follow(trajectory)        # registered here
        await some_condition()
    # here the motion has been stopped (decelerate-and-hold) and awaited
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
from collections.abc import Generator
from types import TracebackType
from typing import Any, Protocol, runtime_checkable

from .errors import AgentTimeoutError

__all__ = [
    "DEFAULT_STOP_TIMEOUT",
    "ClockLike",
    "LoopClock",
    "MotionScope",
    "MotionStopTimeoutError",
    "StoppableMotion",
    "current_scope",
    "register",
]

_log = logging.getLogger(__name__)

DEFAULT_STOP_TIMEOUT = 10.0
"""Seconds (of the scope's clock) a motion gets to decelerate and hold."""


class ClockLike(Protocol):
    """Time source: ``robot.clock`` (simulated time) or :class:`LoopClock`."""

    def now(self) -> float:
        """Current time in seconds."""

    async def sleep(self, dt: float) -> None:
        """Sleep ``dt`` seconds on this clock."""


class LoopClock:
    """The default clock: the running asyncio loop's monotonic time."""

    def now(self) -> float:
        """The running event loop's monotonic time."""
        return asyncio.get_running_loop().time()

    async def sleep(self, dt: float) -> None:
        """``asyncio.sleep(dt)``."""
        await asyncio.sleep(dt)

    def __repr__(self) -> str:
        return "LoopClock()"


@runtime_checkable
class StoppableMotion(Protocol):
    """What a scope needs from a motion handle.

    ``cancel()`` requests decelerate-and-hold and returns at once; awaiting the
    motion resolves once the robot has stopped.
    """

    def cancel(self) -> None:
        """Request decelerate-and-hold; returns at once."""

    def done(self) -> bool:
        """True once the motion has ended."""

    def __await__(self) -> Generator[Any, None, Any]: ...


class MotionStopTimeoutError(AgentTimeoutError):
    """Motions were asked to stop but did not stop in time; escalate (e-stop)."""

    def __init__(self, message: str, motions: list[StoppableMotion]) -> None:
        super().__init__(message)
        self.motions = motions


_current: contextvars.ContextVar[MotionScope | None] = contextvars.ContextVar("agentsdk_motion_scope", default=None)


def current_scope() -> MotionScope | None:
    """The scope motions started by the current task belong to, if any."""
    return _current.get()


def register(motion: StoppableMotion) -> None:
    """Add ``motion`` to the current scope (called by the robot when a motion starts).

    No-op outside a scope.  A motion started in a scope that is already closed
    (e.g. by a stray task of a state that has exited) is cancelled immediately.
    """
    scope = _current.get()
    if scope is not None:
        scope.add(motion)


class MotionScope:
    """The motions started by one state body (or one ``async with`` block)."""

    def __init__(
        self,
        name: str = "",
        *,
        clock: ClockLike | None = None,
        stop_timeout: float = DEFAULT_STOP_TIMEOUT,
    ) -> None:
        self.name = name
        self.clock: ClockLike = clock if clock is not None else LoopClock()
        self.stop_timeout = stop_timeout
        self._motions: list[StoppableMotion] = []
        self._cancelled: set[int] = set()  # ids of motions already asked to stop (motions are kept alive)
        self._closed = False
        self._token: contextvars.Token[MotionScope | None] | None = None

    def __repr__(self) -> str:
        return f"MotionScope({self.name!r}, motions={len(self._motions)}, closed={self._closed})"

    @property
    def closed(self) -> bool:
        """True once the scope has exited (new motions are stopped at once)."""
        return self._closed

    @property
    def motions(self) -> tuple[StoppableMotion, ...]:
        """Every motion registered so far (finished ones included)."""
        return tuple(self._motions)

    def add(self, motion: StoppableMotion) -> None:
        """Register ``motion`` to be stopped when the scope exits (stopped at once if already closed)."""
        if self._closed:
            _log.warning("motion %r started in closed scope %r: stopping it", motion, self.name)
            motion.cancel()
            return
        self._motions.append(motion)

    def activate(self) -> None:
        """Make this the current scope of the calling task (and of tasks it creates later).

        Used by the state machine inside the state body's own task, whose
        context is private, so no reset is needed.
        """
        _current.set(self)

    def cancel_all(self) -> list[StoppableMotion]:
        """Request decelerate-and-hold on every running motion (synchronous).

        Each motion is asked once.  Returns the motions that were still running.
        """
        running = [m for m in self._motions if not m.done()]
        for motion in running:
            if id(motion) not in self._cancelled:
                self._cancelled.add(id(motion))
                motion.cancel()
        return running

    async def aclose(self) -> None:
        """Close the scope: stop every running motion and wait until it has stopped.

        Idempotent.  Raises :class:`MotionStopTimeoutError` if the motions do not
        stop within ``stop_timeout`` seconds of ``clock``.  If the caller is
        cancelled while waiting, the stop requests stay in effect and the
        cancellation propagates.
        """
        self._closed = True
        self.cancel_all()
        running = [m for m in self._motions if not m.done()]
        if not running:
            return
        async with asyncio.TaskGroup() as tg:
            waiters = [tg.create_task(_settle(m), name=f"settle {m!r}") for m in running]
            all_stopped = tg.create_task(asyncio.wait(waiters), name=f"{self.name}: stop")
            deadline = tg.create_task(self.clock.sleep(self.stop_timeout), name=f"{self.name}: stop timeout")
            await asyncio.wait((all_stopped, deadline), return_when=asyncio.FIRST_COMPLETED)
            timed_out = not all_stopped.done()
            for task in (all_stopped, deadline, *waiters):
                task.cancel()
        if timed_out:
            stuck = [m for m in running if not m.done()]
            raise MotionStopTimeoutError(
                f"{self.name or 'scope'}: {len(stuck)} motion(s) did not stop within {self.stop_timeout:g} s",
                stuck,
            )

    async def __aenter__(self) -> MotionScope:
        if self._token is not None:
            raise RuntimeError(f"{self!r} is already entered")
        self._token = _current.set(self)
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._token is not None:
            _current.reset(self._token)
            self._token = None
        try:
            await self.aclose()
        except MotionStopTimeoutError:
            if exc is None or isinstance(exc, Exception):
                raise  # the more urgent problem (the original stays as __context__)
            # never replace a propagating CancelledError/KeyboardInterrupt
            _log.error("%s: motions did not stop while %s propagated", self.name, exc_type.__name__ if exc_type else "")


async def _settle(motion: StoppableMotion) -> None:
    """Wait until ``motion`` has stopped, whatever it resolves to."""
    try:
        await motion
    except asyncio.CancelledError:
        task = asyncio.current_task()
        if task is not None and task.cancelling():
            raise  # we are being cancelled
        # the motion's own future was cancelled: it has ended, which is all we wait for
    except Exception:
        _log.debug("motion %r ended with an error while stopping", motion, exc_info=True)
