"""Realtime pacing: precise wake-ups for asyncio without a busy spin, and real-time scheduling.

asyncio's own timers are only about a millisecond precise on Linux (``epoll_wait``
takes its timeout in whole milliseconds, rounded up), too coarse for a 1 kHz
control loop. Spinning on the event loop for the last part of every period
(what :class:`~agentsdk.clock.RealtimeClock` used to do) is precise but burns a
core. :class:`DeadlineTimer` instead arms one Linux ``timerfd`` (absolute
``CLOCK_MONOTONIC``, the clock behind ``time.monotonic``) at the earliest pending
deadline and lets the event loop watch it with ``loop.add_reader``: the loop
sleeps in ``epoll_wait`` until the kernel's high-resolution timer fires, then
wakes the sleepers that are due. No thread, no spin, no ``call_soon_threadsafe``
hand-off. (Measured against the alternatives -- a pacing thread in
``clock_nanosleep`` handing ticks over with ``call_soon_threadsafe``, plain
``asyncio.sleep``, the old sleep-then-spin -- in ``agentsdk bench --only
realtime``.) Where there is no ``timerfd`` (macOS, Windows), sleeps fall back to
``asyncio.sleep`` with its platform precision.

:func:`set_realtime_priority` puts the process on the ``SCHED_FIFO`` real-time
scheduling class (``os.sched_setscheduler``) and optionally pins it to CPUs
(``os.sched_setaffinity``), the usual way to keep a control loop's wake-up
latency low on a loaded machine; it raises a
:class:`~agentsdk.errors.ConfigurationError` that says what to change when the
system does not permit it. The CLI exposes it as ``agentsdk run --rt-priority N
--cpus 2,3``.
"""

from __future__ import annotations

import asyncio
import ctypes
import heapq
import itertools
import math
import os
import sys
import time
import weakref
from collections.abc import Iterable
from typing import Any

from .errors import ConfigurationError

__all__ = ["DeadlineTimer", "RealtimeSettings", "set_realtime_priority", "timerfd_available"]

_CLOCK_MONOTONIC = 1
_TFD_TIMER_ABSTIME = 1


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


class _TimerFd:
    """A non-blocking ``timerfd`` on ``CLOCK_MONOTONIC`` (``os.timerfd_*`` on Python 3.13+, else libc via ctypes)."""

    def __init__(self) -> None:
        flags = os.O_NONBLOCK | os.O_CLOEXEC  # TFD_NONBLOCK and TFD_CLOEXEC are defined as these
        if hasattr(os, "timerfd_create"):
            self._libc = None
            self.fd: int = os.timerfd_create(time.CLOCK_MONOTONIC, flags=flags)
        else:
            libc = _libc()
            if libc is None:
                raise OSError("timerfd is not available")
            fd = libc.timerfd_create(_CLOCK_MONOTONIC, flags)
            if fd < 0:
                err = ctypes.get_errno()
                raise OSError(err, f"timerfd_create: {os.strerror(err)}")
            self._libc = libc
            self.fd = fd
        self._spec = _Itimerspec()

    def arm(self, deadline_ns: int) -> None:
        """Fire once at ``deadline_ns`` (absolute CLOCK_MONOTONIC nanoseconds); 0 disarms."""
        if self._libc is None:
            os.timerfd_settime_ns(self.fd, flags=os.TFD_TIMER_ABSTIME, initial=deadline_ns)  # type: ignore[attr-defined]
            return
        spec = self._spec
        spec.it_value.tv_sec, spec.it_value.tv_nsec = divmod(deadline_ns, 1_000_000_000)
        if self._libc.timerfd_settime(self.fd, _TFD_TIMER_ABSTIME, ctypes.byref(spec), None) < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_settime: {os.strerror(err)}")

    def drain(self) -> bool:
        """Consume the expiration count (the fd is readable until then); False when the timer had not expired."""
        try:
            os.read(self.fd, 8)
        except BlockingIOError:
            return False
        return True

    def close(self) -> None:
        os.close(self.fd)


_LIBC: Any = None


def _libc() -> Any:
    global _LIBC
    if _LIBC is None:
        if not sys.platform.startswith("linux"):
            _LIBC = False
        else:
            try:
                lib = ctypes.CDLL(None, use_errno=True)  # libc is in the process already (find_library spawns ldconfig)
                lib.timerfd_create.argtypes = [ctypes.c_int, ctypes.c_int]
                lib.timerfd_create.restype = ctypes.c_int
                lib.timerfd_settime.argtypes = [
                    ctypes.c_int, ctypes.c_int, ctypes.POINTER(_Itimerspec), ctypes.POINTER(_Itimerspec),
                ]
                lib.timerfd_settime.restype = ctypes.c_int
                _LIBC = lib
            except (OSError, AttributeError):
                _LIBC = False
    return _LIBC or None


if not hasattr(os, "timerfd_create"):
    # bind libc's timerfd calls now, not when a running control loop first sleeps (under a slow kernel,
    # e.g. user-mode Linux, the first binding took long enough for the stall watchdog to fire)
    _libc()


def timerfd_available() -> bool:
    """True where :class:`DeadlineTimer` works (Linux)."""
    return hasattr(os, "timerfd_create") or _libc() is not None


class DeadlineTimer:
    """Precise sleeps on an asyncio event loop: one ``timerfd`` armed at the earliest pending deadline.

    ``await timer.sleep_until(t)`` (``t`` on ``time.monotonic``) returns at the
    first wake-up at or after ``t``; many sleepers share the timer (a heap, like
    asyncio's own timers). Create it from a running event loop; :meth:`close`
    it when done (pending sleepers are cancelled).
    """

    def __init__(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        self._loop = loop or asyncio.get_running_loop()
        self._fd = _TimerFd()
        self._heap: list[tuple[float, int, asyncio.Future[None]]] = []
        self._seq = itertools.count()
        self._armed = math.inf
        self._closed = False
        self._loop.add_reader(self._fd.fd, self._on_ready)
        self._finalizer = weakref.finalize(self, _release, self._loop, self._fd)

    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._closed

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop the timer wakes."""
        return self._loop

    def sleep_until(self, deadline: float) -> asyncio.Future[None]:
        """A future resolved at the first wake-up at or after ``deadline`` (``time.monotonic`` seconds)."""
        fut: asyncio.Future[None] = self._loop.create_future()
        if self._closed:
            fut.cancel()
            return fut
        heapq.heappush(self._heap, (deadline, next(self._seq), fut))
        if deadline < self._armed:
            self._arm(deadline)
        return fut

    def _arm(self, deadline: float) -> None:
        self._armed = deadline
        # round up: the kernel then never wakes before the deadline
        self._fd.arm(max(1, math.ceil(deadline * 1e9)))

    def _on_ready(self) -> None:
        if not self._fd.drain():
            return  # not expired (re-armed since the event was reported): nothing is due yet
        # The kernel woke us because the deadline it was armed at has passed: every sleeper up to it
        # is due, without a clock read (a system call where there is no vDSO, e.g. user-mode Linux).
        # A later deadline that passed meanwhile is re-armed in the past and fires at the next wake-up.
        due = self._armed
        self._armed = math.inf
        heap = self._heap
        while heap and (heap[0][0] <= due or heap[0][2].done()):
            _, _, fut = heapq.heappop(heap)
            if not fut.done():
                fut.set_result(None)
        if heap:
            self._arm(heap[0][0])

    def close(self) -> None:
        """Stop watching the timer, close it and cancel the pending sleepers. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for _, _, fut in self._heap:
            fut.cancel()
        self._heap.clear()
        self._finalizer()


def _release(loop: asyncio.AbstractEventLoop, fd: _TimerFd) -> None:
    if not loop.is_closed():
        loop.remove_reader(fd.fd)
    fd.close()


class RealtimeSettings:
    """What :func:`set_realtime_priority` applied (and what it replaced, for :meth:`restore`)."""

    def __init__(self, policy: int, priority: int, cpus: frozenset[int], previous: tuple[int, int, frozenset[int]]):
        #: the scheduling policy now in effect (``os.SCHED_FIFO``)
        self.policy = policy
        #: the real-time priority (1..99)
        self.priority = priority
        #: the CPUs the process may run on
        self.cpus = cpus
        self._previous = previous

    def restore(self) -> None:
        """Return to the scheduling policy, priority and CPU set in effect before."""
        policy, priority, cpus = self._previous
        os.sched_setscheduler(0, policy, os.sched_param(priority))
        os.sched_setaffinity(0, cpus)

    def __repr__(self) -> str:
        return f"RealtimeSettings(SCHED_FIFO, priority={self.priority}, cpus={sorted(self.cpus)})"


def set_realtime_priority(priority: int = 50, cpus: Iterable[int] | None = None) -> RealtimeSettings:
    """Run this process with the ``SCHED_FIFO`` real-time policy at ``priority`` (1..99), pinned to ``cpus``.

    Call it before connecting (threads started later, e.g. the stall watchdog,
    inherit it). A busy ``SCHED_FIFO`` thread can starve the rest of the system on
    its CPUs; Linux reserves 5 % for others by default
    (``/proc/sys/kernel/sched_rt_runtime_us``). Raises
    :class:`~agentsdk.errors.ConfigurationError` with what to change where the
    system does not permit it (not Linux, no ``CAP_SYS_NICE`` and no ``rtprio``
    limit, an unknown CPU).
    """
    if not hasattr(os, "sched_setscheduler") or not hasattr(os, "SCHED_FIFO"):
        raise ConfigurationError(
            f"real-time scheduling (SCHED_FIFO) is not available on {sys.platform}; it needs Linux"
        )
    lo, hi = os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)
    if not isinstance(priority, int) or not lo <= priority <= hi:
        raise ConfigurationError(f"SCHED_FIFO priority must be an integer in {lo}..{hi}, got {priority!r}")
    previous = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, frozenset(os.sched_getaffinity(0)))
    wanted = previous[2] if cpus is None else frozenset(int(c) for c in cpus)
    if cpus is not None:
        try:
            os.sched_setaffinity(0, wanted)
        except (OSError, ValueError) as exc:
            raise ConfigurationError(
                f"cannot pin the process to CPUs {sorted(wanted)}: {exc} (this machine has CPUs "
                f"{sorted(os.sched_getaffinity(0))} available)"
            ) from exc
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError as exc:
        if cpus is not None:
            os.sched_setaffinity(0, previous[2])
        import resource

        soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
        raise ConfigurationError(
            f"not permitted to use SCHED_FIFO priority {priority} ({exc.strerror}): the process needs "
            f"CAP_SYS_NICE (run as root, or `sudo setcap cap_sys_nice+ep {os.path.realpath(sys.executable)}`) "
            f"or an rtprio limit of at least {priority} (now {soft}; e.g. '@realtime - rtprio 95' in "
            "/etc/security/limits.conf, or `ulimit -r 95` in a root shell); in a container, also "
            "--cap-add=SYS_NICE. The loop still runs without it, with ordinary scheduling latency."
        ) from exc
    except OSError as exc:
        if cpus is not None:
            os.sched_setaffinity(0, previous[2])
        raise ConfigurationError(f"cannot set SCHED_FIFO priority {priority}: {exc}") from exc
    return RealtimeSettings(os.SCHED_FIFO, priority, frozenset(os.sched_getaffinity(0)), previous)
