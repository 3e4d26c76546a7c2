"""Run blocking work (model loading, simulator compiles, imports) off the event loop.

``asyncio.to_thread`` would do, but its default executor keeps its worker threads
alive for the life of the event loop; a connect should leave no thread behind.
:func:`run_blocking` runs the function in a short-lived thread of its own, awaits
its result without blocking the loop, and returns once the thread has ended::

    model = await run_blocking(spec.compile, name="mujoco-compile")

Other tasks on the loop (a realtime robot already running, its watchdogs) keep
running meanwhile. Python code in the worker holds the GIL in slices of
``sys.getswitchinterval()`` (5 ms by default); while workers run, the interval is
lowered to :data:`SWITCH_INTERVAL` so that a realtime control loop waiting for the
GIL gets it within a fraction of its period, and restored when the last one ends.
"""

from __future__ import annotations

import asyncio
import sys
import threading
from collections.abc import Callable
from typing import Any, TypeVar

__all__ = ["SWITCH_INTERVAL", "run_blocking"]

_T = TypeVar("_T")

#: GIL switch interval (s) while blocking work runs in a worker thread
SWITCH_INTERVAL = 0.0002

_active = 0
_saved_interval: float | None = None
_lock = threading.Lock()


def _enter() -> None:
    global _active, _saved_interval
    with _lock:
        if _active == 0:
            _saved_interval = sys.getswitchinterval()
            sys.setswitchinterval(min(_saved_interval, SWITCH_INTERVAL))
        _active += 1


def _exit() -> None:
    global _active, _saved_interval
    with _lock:
        _active -= 1
        if _active == 0 and _saved_interval is not None:
            sys.setswitchinterval(_saved_interval)
            _saved_interval = None


async def run_blocking(fn: Callable[..., _T], *args: Any, name: str = "agentsdk-worker") -> _T:
    """Run ``fn(*args)`` in a dedicated thread and return its result (or raise its exception).

    The thread has ended when this returns. Cancelling the awaiting task does not
    interrupt ``fn`` (nothing can interrupt C code): it waits for ``fn`` to finish,
    then raises :class:`asyncio.CancelledError`, so nothing keeps running behind the
    caller's back (the caller cleans up what ``fn`` built).
    """
    loop = asyncio.get_running_loop()
    done: asyncio.Future[_T] = loop.create_future()

    def _deliver(ok: bool, value: Any) -> None:
        if done.done():
            return
        if ok:
            done.set_result(value)
        else:
            done.set_exception(value)

    def _work() -> None:
        value: Any
        try:
            result = fn(*args)
        except BaseException as exc:  # handed to the awaiting task, re-raised there
            ok, value = False, exc
        else:
            ok, value = True, result
        try:
            loop.call_soon_threadsafe(_deliver, ok, value)
        except RuntimeError:  # the event loop was closed meanwhile: nobody is waiting
            pass

    thread = threading.Thread(target=_work, name=name, daemon=True)
    cancelled = False
    _enter()
    try:
        thread.start()
        while not done.done() or thread.is_alive():
            try:
                if not done.done():
                    await asyncio.shield(done)
                else:  # the thread only has to return now: wait for it without blocking the loop
                    await asyncio.sleep(0.0005)
            except asyncio.CancelledError:
                cancelled = True  # let fn finish first (see the docstring)
            except BaseException:  # fn's own exception: re-raised from done.result() below
                continue
    finally:
        _exit()
    if cancelled:
        raise asyncio.CancelledError
    return done.result()
