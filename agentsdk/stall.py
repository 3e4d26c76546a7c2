"""The event-loop stall watchdog: a heartbeat on the event loop and an OS thread that watches it.

If the event loop stops beating for ``timeout`` seconds of wall time (a blocking call in a
coroutine), the watchdog thread reports the stall (``on_stall``, with the time of the last
heartbeat and where the loop thread was: the safety layer latches its e-stop there,
:mod:`agentsdk.safety`), then removes torque itself (``emergency_stop``), then logs. In that
order, whoever sees the actuators stopped also sees the latch and the report, as with any
other e-stop from another thread. While ``idle()`` is true (torque off, robot closed) there
is nothing to protect and the thread only looks every ``timeout / 2``.

The beats cost the loop as little as possible (every wake-up and clock read is a system call
where there is no vDSO, e.g. user-mode Linux): a realtime control loop beats on every tick with
the time it read anyway (:meth:`StallWatchdog.tick_beats`), and a timer on the event loop beats
only every ``timeout / 10`` then (every ``min(5 ms, timeout / 10)`` without ticks). The thread
sleeps until the newest beat it saw would be ``timeout`` old, so it wakes about once per
``timeout``, never per cycle. A stall is detected ``timeout`` after the last beat, and the last
beat before a stall is at most one control period (or the timer's interval) old.
"""

from __future__ import annotations

import asyncio
import logging
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

__all__ = ["StallWatchdog", "format_stack"]

log = logging.getLogger("agentsdk.safety")


class StallWatchdog:
    """Heartbeat plus watcher thread of one robot's event loop (see the module documentation).

    ``on_stall(last_beat, detected_at, stack, where)`` runs in the watchdog thread, just before
    ``emergency_stop()``: ``last_beat`` and ``detected_at`` are ``time.monotonic`` times, ``stack``
    the loop thread's stack (source lines not read yet: no file access before the stop) and
    ``where`` its innermost frame outside asyncio and the safety layer. It must not block. What it
    returns, if anything, is logged as an error with the stack once torque is off.
    """

    def __init__(
        self,
        timeout: float,
        name: str,
        idle: Callable[[], bool],
        emergency_stop: Callable[[], None],
        on_stall: Callable[[float, float, traceback.StackSummary, str], str | None],
    ) -> None:
        self.timeout = timeout
        self._name = name
        self._idle = idle
        self._emergency_stop = emergency_stop
        self._on_stall = on_stall
        self._beat = time.monotonic()
        self._beat_handle: asyncio.TimerHandle | None = None
        self._thread: threading.Thread | None = None
        self._thread_stop = threading.Event()
        self._aloop: asyncio.AbstractEventLoop | None = None
        self._loop_thread_id = threading.get_ident()
        #: interval of the event-loop timer's beats (longer once the control loop's ticks beat)
        self._interval = min(0.005, timeout / 10)

    def tick_beats(self, origin: float) -> Callable[[float, object, object], None]:
        """An OBSERVE hook for a realtime control loop: each tick is a beat, at robot time ``t``
        (``origin + t`` on ``time.monotonic``, the time the tick read anyway: no clock read here).

        With it, the event loop's own heartbeat timer runs every ``timeout / 10`` only (it keeps
        beating while the loop runs without ticking).
        """
        self._interval = self.timeout / 10

        def beat(t: float, _state: object, _setpoint: object) -> None:
            b = origin + t
            if b > self._beat:
                self._beat = b

        return beat

    def start(self) -> None:
        """Start the heartbeat on the running event loop and the watcher thread."""
        self._aloop = asyncio.get_running_loop()
        self._loop_thread_id = threading.get_ident()
        self._beat = time.monotonic()
        self._schedule_beat()
        self._thread = threading.Thread(target=self._watch, name=self._name, daemon=True)
        self._thread.start()

    def beat(self) -> None:
        """Count now as a heartbeat (after a reset: the stall that latched is over)."""
        self._beat = time.monotonic()

    def stop_now(self) -> threading.Thread | None:
        """Signal the thread to stop and cancel the heartbeat (no event loop needed); returns the thread."""
        self._thread_stop.set()
        if self._beat_handle is not None:
            self._beat_handle.cancel()
            self._beat_handle = None
        thread, self._thread = self._thread, None
        return thread

    async def stop(self) -> None:
        """:meth:`stop_now`, then wait (without blocking the event loop) until the thread has ended."""
        thread = self.stop_now()
        if thread is not None and thread is not threading.current_thread():
            # the thread polls its stop event every few ms; wait for it without blocking the event loop
            deadline = time.monotonic() + 2.0
            while thread.is_alive() and time.monotonic() < deadline:  # noqa: ASYNC110 - polling a thread
                await asyncio.sleep(0.002)
            if thread.is_alive():
                log.error("the stall watchdog thread did not stop within 2 s")

    def _schedule_beat(self) -> None:
        aloop = self._aloop
        if aloop is None or self._thread_stop.is_set():
            return
        interval = self._interval

        def _beat() -> None:
            self._beat = time.monotonic()
            self._schedule_beat()

        self._beat_handle = aloop.call_later(interval, _beat)

    def _watch(self) -> None:
        timeout = self.timeout
        # while idle: a look every timeout / 2 (a 2 ms poll cost the loop thread a GIL hand-off
        # each time); a stall that begins just after torque comes on is still caught ``timeout``
        # after the last beat, since the next look comes before that
        idle_wait = min(timeout / 2, 1.0)
        wait = idle_wait
        # The thread sleeps until the heartbeat it last saw would be ``timeout`` old (not a poll
        # every few ms: with several robots in a process, each thread's wake-ups cost the loop
        # thread a GIL hand-off).
        while not self._thread_stop.wait(wait):
            last = self._beat
            now = time.monotonic()
            wait = idle_wait
            # watched as long as torque is on: a category 2 stop holds with torque on
            if self._idle():
                continue
            if now - last <= timeout:
                # (at most 1 s: a huge stall_timeout would overflow the wait; a wake-up a second is free)
                wait = min(max(last + timeout - now, 0.0) + 1e-4, 1.0)
                continue
            # the event loop is stuck: report it (the latch), then stop the actuators from this thread
            message: str | None = None
            stack = traceback.StackSummary()
            try:
                stack = _stack_of(sys._current_frames().get(self._loop_thread_id))
                message = self._on_stall(last, now, stack, _innermost_user_frame(stack))
            except Exception:  # the stop below comes whatever the report did
                log.exception("the stall report failed in the stall watchdog; stopping anyway")
            try:
                self._emergency_stop()
            except Exception:
                log.exception("emergency stop hook failed in the stall watchdog")
            if message:
                log.error("%s\n%s", message, format_stack(stack))


def _stack_of(frame: Any) -> traceback.StackSummary:
    """The stack of ``frame``, outermost first, without reading source files (looked up when formatted)."""
    if frame is None:
        return traceback.StackSummary()
    stack = traceback.StackSummary.extract(traceback.walk_stack(frame), lookup_lines=False)
    stack.reverse()
    return stack


def format_stack(stack: traceback.StackSummary) -> str:
    """``stack`` as ``traceback.format_stack`` prints it (source lines read at the first call, then kept).

    A stall's stack is formatted twice: for the watchdog thread's log line and for
    ``robot.safety.stall_traceback``; the text (and the source files it reads) is made once.
    """
    text: str | None = getattr(stack, "_agentsdk_text", None)
    if text is None:
        text = "".join(stack.format()) or "(loop thread not found)"
        stack._agentsdk_text = text  # type: ignore[attr-defined]  # (a list subclass: it takes attributes)
    return text


def _innermost_user_frame(summary: traceback.StackSummary) -> str:
    if not summary:
        return "unknown"
    ours = ("asyncio", "agentsdk/safety", "agentsdk/stall")
    for fs in reversed(summary):
        if not any(part in fs.filename for part in ours):
            return f"{fs.filename}:{fs.lineno} in {fs.name}"
    fs = summary[-1]
    return f"{fs.filename}:{fs.lineno} in {fs.name}"
