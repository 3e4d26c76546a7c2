"""Keep PyBullet's C-level prints off the user's terminal, without losing the user's own output.

PyBullet writes with C ``printf``/``fprintf`` straight to file descriptors 1 and 2
(``pybullet build time: ...`` on import, ``b3Warning[file,line]:`` and its message
while loading a model, thread chatter of the GUI), where Python's
``contextlib.redirect_stdout`` cannot reach, and it can land in the middle of a line
the user's program is printing. :func:`filtered_native_output` points fds 1 and 2 at
pipes while PyBullet calls that print run; a reader thread per pipe passes every line
through to the real stream except PyBullet's, which go to the ``agentsdk.backends.pybullet``
logger at DEBUG. Output written meanwhile by other threads (the user's prints) goes
through the same pipe, in order: nothing is lost. Nested and concurrent uses share
one redirection.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import re
import sys
import threading
from collections.abc import Iterator

__all__ = ["NOISE", "filtered_native_output", "is_noise"]

log = logging.getLogger("agentsdk.backends.pybullet")

#: lines PyBullet prints by itself (matched anywhere: a print can land mid-line)
NOISE = re.compile(
    r"pybullet build time: |b3Printf: |b3Warning\[|b3Error\[|argv\[0\]=|argc=|startThreads creating|"
    r"starting thread \d|started thread \d|ExampleBrowserThreadFunc started|X11 functions dynamically loaded|"
    r"MotionThreadFunc thread started|numActiveThreads = |stopping threads|Thread with taskId \d|"
    r"Thread TERMINATED|destroy semaphore|semaphore destroyed|destroy main semaphore|main semaphore destroyed|"
    r"^(?:Version|Vendor|Renderer|GL_VERSION|GL_SHADING_LANGUAGE_VERSION|ven) ?= |^finished$|"
    r"^pybullet \w+ thread"
)
#: a b3Warning/b3Error header: PyBullet prints its message on the next line
_HEADER = re.compile(r"b3(?:Warning|Error)\[[^\]]*\]:\s*$")


def is_noise(line: str) -> bool:
    """True for a line PyBullet printed by itself."""
    return NOISE.search(line) is not None


class _Pump:
    """Reads one redirected fd's pipe and forwards everything but PyBullet's lines to the real fd."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.saved = os.dup(fd)
        read_end, write_end = os.pipe()
        self._read_end = read_end
        os.dup2(write_end, fd)
        os.close(write_end)
        self._skip_next = False
        self._thread = threading.Thread(target=self._run, name=f"agentsdk-pybullet-fd{fd}", daemon=True)
        self._thread.start()

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.saved, view)
            except OSError:
                return  # the real stream is gone (closed pipe): nothing to keep
            view = view[n:]

    def _line(self, raw: bytes) -> None:
        text = raw.decode("utf-8", errors="replace")
        body = text.rstrip("\r\n")
        if self._skip_next:  # the message under a b3Warning header
            self._skip_next = False
            log.debug("pybullet: %s", body)
            return
        match = NOISE.search(body)
        if match is None:
            self._write(raw)
            return
        if _HEADER.search(body):
            self._skip_next = True
        log.debug("pybullet: %s", body[match.start():])
        if match.start() > 0:
            self._write(raw[: len(body[: match.start()].encode("utf-8", errors="replace"))])

    def _run(self) -> None:
        pending = b""
        try:
            while chunk := os.read(self._read_end, 65536):
                pending += chunk
                *lines, pending = pending.split(b"\n")
                for line in lines:
                    self._line(line + b"\n")
        finally:
            if pending:
                self._line(pending)
            os.close(self._read_end)

    def restore(self) -> None:
        """Point the fd back at the real stream; the reader drains the pipe and ends."""
        os.dup2(self.saved, self.fd)  # closes the pipe's last write end: the reader sees EOF
        # (a child process started meanwhile may still hold the write end: do not wait for it forever)
        self._thread.join(timeout=5.0)
        os.close(self.saved)


_lock = threading.Lock()
_users = 0
_pumps: list[_Pump] = []


def _flush_all() -> None:
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            if stream is not None:
                stream.flush()
    with contextlib.suppress(Exception):
        ctypes.CDLL(None).fflush(None)  # C stdio buffers (PyBullet's printf)


@contextlib.contextmanager
def filtered_native_output() -> Iterator[None]:
    """Filter PyBullet's own lines out of fds 1 and 2 while the block runs (see the module docstring)."""
    global _users
    with _lock:
        if _users == 0:
            _flush_all()
            try:
                _pumps.extend(_Pump(fd) for fd in (1, 2))
            except OSError:  # no fd 1/2 (e.g. a daemon): nothing to filter
                for pump in _pumps:
                    pump.restore()
                _pumps.clear()
        _users += 1
    try:
        yield
    finally:
        with _lock:
            _users -= 1
            if _users == 0:
                _flush_all()
                for pump in _pumps:
                    pump.restore()
                _pumps.clear()
