"""A live progress line for long runs: simulated time, wall time and real-time factor.

The display (rich) is driven by a small thread that samples ``clock()`` (robot
time) a few times per second, so the control loop does no work for it. It
appears only after ``delay`` seconds of wall time (short runs never show it),
is transient (erased when the run ends), and is off when stdout is not a
terminal or with ``--quiet``::

    progress = RunProgress(robot.clock.now, label="wave.py on arm3")
    progress.start()
    ...
    progress.stop()
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from typing import IO, Any

__all__ = ["RunProgress", "progress_enabled"]


def progress_enabled(quiet: bool = False, stream: IO[str] | None = None) -> bool:
    """True when a progress bar should be shown: not quiet and ``stream`` (stdout) is a terminal."""
    if quiet:
        return False
    stream = sys.stdout if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed or replaced streams
        return False


class RunProgress:
    """Show ``sim <t> s | wall <t> s | <rtf>x real time`` while a run is in progress.

    ``total`` (robot seconds, e.g. the length of a recording being replayed)
    turns the pulsing bar into a bar with a percentage.
    """

    def __init__(
        self,
        clock: Callable[[], float],
        *,
        label: str = "running",
        total: float | None = None,
        delay: float = 2.0,
        refresh_hz: float = 4.0,
        console: Any = None,
    ) -> None:
        self._clock = clock
        self._label = label
        self._total = total
        self._delay = delay
        self._interval = 1.0 / refresh_hz
        self._console = console
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.perf_counter()
        self._sim0 = 0.0
        #: set once the display has been drawn
        self.displayed = threading.Event()

    def start(self) -> RunProgress:
        """Start the display thread and the wall/simulated time origins; returns ``self``."""
        self._t0 = time.perf_counter()
        self._sim0 = self._clock()
        self._thread = threading.Thread(target=self._run, name="agentsdk-progress", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Remove the display and join the thread. Idempotent."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)

    def __enter__(self) -> RunProgress:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def fields(self) -> dict[str, float]:
        """Simulated seconds, wall seconds and the real-time factor since :meth:`start`."""
        sim = self._clock() - self._sim0
        wall = time.perf_counter() - self._t0
        return {"sim": sim, "wall": wall, "rtf": sim / wall if wall > 0 else 0.0}

    def _run(self) -> None:
        if self._stop.wait(self._delay):
            return
        from rich.progress import BarColumn, Progress, SpinnerColumn, TaskProgressColumn, TextColumn

        columns: list[Any] = [SpinnerColumn(), TextColumn("[bold]{task.description}"), BarColumn()]
        if self._total:
            columns.append(TaskProgressColumn())
        columns.append(
            TextColumn(
                "sim {task.fields[sim]:8.2f} s  wall {task.fields[wall]:7.1f} s  {task.fields[rtf]:6.2f}x real time"
            )
        )
        progress = Progress(*columns, console=self._console, transient=True, auto_refresh=False)
        task = progress.add_task(self._label, total=self._total or None, **self.fields())  # type: ignore[arg-type]
        progress.start()
        try:
            while True:
                f = self.fields()
                progress.update(task, completed=f["sim"] if self._total else None, **f)  # type: ignore[arg-type]
                progress.refresh()
                self.displayed.set()
                if self._stop.wait(self._interval):
                    break
        finally:
            progress.stop()
