"""Realtime pacing: the control loop's period error, missed deadlines and CPU at 500 Hz and 1 kHz.

Not a test: wall-clock figures depend on the machine and its load. In one process,
one after the other, for each rate, ``duration`` seconds each:

raw pacing loops (no robot; the mechanisms an application could pace itself with)
    ``asyncio.sleep``      sleep until each absolute deadline with asyncio's timers
                           (``epoll_wait`` rounds its timeout up to whole milliseconds)
    ``sleep + spin``       asyncio.sleep until 1.5 ms before the deadline, then yield to
                           the loop in a tight loop (the SDK's pacing before this benchmark)
    ``thread``             a pacing thread sleeping to each deadline (``time.sleep`` is
                           ``clock_nanosleep`` on Linux) and handing the tick to the event
                           loop with ``call_soon_threadsafe``
    ``timerfd``            a Linux timerfd armed at each absolute deadline, watched by the
                           event loop with ``add_reader`` (no thread, no spin)
the SDK control loop
    ``agentsdk.connect("mock", arm3, realtime=True)`` with ``update_rate`` set to the rate
    (mock backend: the tick's own work is small), holding position; each tick's start is
    stamped by a LIMIT-phase hook. Its pacing is :class:`agentsdk.realtime.DeadlineTimer`
    (the timerfd mechanism above). Run once with ordinary scheduling and, where the
    system permits it, once with ``SCHED_FIFO`` (``agentsdk.realtime.set_realtime_priority``).

Period error = ``|t[k+1] - t[k] - period|`` over consecutive tick starts (p50, p99, max);
missed = deadlines skipped (the control loop's ``missed_deadlines``; for the raw loops,
periods that started more than a period late). CPU = process CPU time / wall time (for
the SDK: the tick work, the pacing and the stall-watchdog thread together).
"""

from __future__ import annotations

import asyncio
import ctypes
import os
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

import agentsdk
from agentsdk.bench.common import Comparison, Section, Table, fmt, progress
from agentsdk.loop import Phase

RATES = (500.0, 1000.0)
SPIN_WINDOW = 0.0015


def _stats(stamps: np.ndarray, period: float, missed: int, cpu: float, wall: float) -> dict[str, Any]:
    per = np.diff(stamps)
    err = np.abs(per - period) * 1e6
    if len(err) == 0:
        err = np.zeros(1)
    return {
        "ticks": len(stamps),
        "p50_us": float(np.percentile(err, 50)),
        "p99_us": float(np.percentile(err, 99)),
        "max_us": float(err.max()),
        "missed": int(missed),
        "cpu_percent": 100.0 * cpu / wall if wall > 0 else float("nan"),
        "achieved_hz": (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 else 0.0,
    }


def _missed(stamps: np.ndarray, t0: float, period: float) -> int:
    """Periods that started more than a period after their deadline (raw loops never skip: they burst)."""
    deadlines = t0 + period * np.arange(len(stamps))
    return int(np.count_nonzero(stamps - deadlines > period))


# ------------------------------------------------------------------ raw pacing loops
async def raw_asyncio(rate: float, duration: float) -> dict[str, Any]:
    period, n = 1.0 / rate, round(duration * rate)
    stamps = np.zeros(n)
    c0 = time.process_time()
    t0 = time.monotonic() + period
    for k in range(n):
        deadline = t0 + k * period
        remaining = deadline - time.monotonic()
        if remaining > 0:
            await asyncio.sleep(remaining)
        stamps[k] = time.monotonic()
    return _stats(stamps, period, _missed(stamps, t0, period), time.process_time() - c0, stamps[-1] - t0 + period)


async def raw_spin(rate: float, duration: float) -> dict[str, Any]:
    period, n = 1.0 / rate, round(duration * rate)
    stamps = np.zeros(n)
    c0 = time.process_time()
    t0 = time.monotonic() + period
    for k in range(n):
        deadline = t0 + k * period
        remaining = deadline - time.monotonic()
        if remaining > SPIN_WINDOW:
            await asyncio.sleep(remaining - SPIN_WINDOW)
        while time.monotonic() < deadline:  # noqa: ASYNC110 - the spin being measured
            await asyncio.sleep(0)
        stamps[k] = time.monotonic()
    return _stats(stamps, period, _missed(stamps, t0, period), time.process_time() - c0, stamps[-1] - t0 + period)


async def raw_thread(rate: float, duration: float) -> dict[str, Any]:
    period, n = 1.0 / rate, round(duration * rate)
    stamps = np.zeros(n)
    loop = asyncio.get_running_loop()
    done = loop.create_future()
    count = [0]

    def on_tick() -> None:
        k = count[0]
        stamps[k] = time.monotonic()
        count[0] = k + 1
        if k + 1 == n and not done.done():
            done.set_result(None)

    t0 = time.monotonic() + period

    def pace() -> None:
        for k in range(n):
            remaining = t0 + k * period - time.monotonic()
            if remaining > 0:
                time.sleep(remaining)  # clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME) inside CPython
            loop.call_soon_threadsafe(on_tick)

    c0 = time.process_time()
    thread = threading.Thread(target=pace, name="bench-pacer", daemon=True)
    thread.start()
    await done
    await asyncio.to_thread(thread.join)
    return _stats(stamps, period, _missed(stamps, t0, period), time.process_time() - c0, stamps[-1] - t0 + period)


class _Timerfd:
    """A bare periodic timerfd (Linux) through ctypes, for the raw loop: no SDK code."""

    def __init__(self) -> None:
        self.libc = ctypes.CDLL(None, use_errno=True)
        self.fd = self.libc.timerfd_create(1, os.O_NONBLOCK | os.O_CLOEXEC)  # CLOCK_MONOTONIC
        if self.fd < 0:
            raise OSError(ctypes.get_errno(), "timerfd_create")

    def start(self, first: float, period: float) -> None:
        spec = (ctypes.c_long * 4)(0, round(period * 1e9), 0, 0)
        spec[2], spec[3] = divmod(round(first * 1e9), 1_000_000_000)
        if self.libc.timerfd_settime(self.fd, 1, spec, None) < 0:  # TFD_TIMER_ABSTIME
            raise OSError(ctypes.get_errno(), "timerfd_settime")

    def close(self) -> None:
        os.close(self.fd)


async def raw_timerfd(rate: float, duration: float) -> dict[str, Any]:
    period, n = 1.0 / rate, round(duration * rate)
    stamps = np.zeros(n)
    loop = asyncio.get_running_loop()
    done = loop.create_future()
    count = [0]
    skipped = [0]
    tfd = _Timerfd()

    def on_ready() -> None:
        try:
            expirations = int.from_bytes(os.read(tfd.fd, 8), sys.byteorder)
        except BlockingIOError:
            return
        skipped[0] += expirations - 1
        k = count[0]
        if k < n:
            stamps[k] = time.monotonic()
            count[0] = k + 1
        if k + 1 >= n and not done.done():
            done.set_result(None)

    c0 = time.process_time()
    t0 = time.monotonic() + period
    loop.add_reader(tfd.fd, on_ready)
    try:
        tfd.start(t0, period)
        await done
    finally:
        loop.remove_reader(tfd.fd)
        tfd.close()
    return _stats(stamps, period, skipped[0], time.process_time() - c0, stamps[-1] - t0 + period)


# ------------------------------------------------------------------ the SDK
def _robot_yaml(directory: Path, rate: float) -> Path:
    """arm3's robot.yaml with ``update_rate`` set to ``rate``."""
    import agentsdk.robots

    src = Path(agentsdk.robots.__file__).resolve().parent / "arm3"
    cfg = yaml.safe_load((src / "robot.yaml").read_text())
    cfg["description"] = str(src / cfg["description"])
    cfg["update_rate"] = rate
    path = directory / f"arm3_{rate:g}hz.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


async def sdk_loop(robot_yaml: Path, rate: float, duration: float) -> dict[str, Any]:
    period = 1.0 / rate
    async with agentsdk.connect("mock", robot_yaml, realtime=True) as robot:
        n = round(duration * rate) + 100
        stamps = np.zeros(n)
        count = [0]

        def stamp(t: float, st: Any, sp: Any) -> None:
            k = count[0]
            if k < n:
                stamps[k] = time.monotonic()
                count[0] = k + 1

        await robot.clock.sleep(0.2)  # settle
        handle = robot.add_tick_hook(Phase.LIMIT, stamp)
        missed0 = robot.missed_deadlines
        c0 = time.process_time()
        w0 = time.monotonic()
        await robot.clock.sleep(duration)
        cpu, wall = time.process_time() - c0, time.monotonic() - w0
        handle.remove()
        missed = robot.missed_deadlines - missed0
        state = robot.safety.state.name
    res = _stats(stamps[: count[0]], period, missed, cpu, wall)
    res["safety_state"] = state
    return res


def _fifo() -> Any:
    """SCHED_FIFO priority 50 if the system permits it, else (None, why)."""
    from agentsdk.errors import ConfigurationError
    from agentsdk.realtime import set_realtime_priority

    try:
        return set_realtime_priority(50), None
    except ConfigurationError as exc:
        return None, str(exc)


LOOPS = ("asyncio.sleep", "sleep + spin", "thread", "timerfd")


def measure(duration: float, rates: tuple[float, ...] = RATES, fifo: bool = True) -> dict[str, Any]:
    rows: list[dict[str, Any]] = []
    fifo_note = None
    with tempfile.TemporaryDirectory(prefix="bench-realtime-") as tmp:
        for rate in rates:
            yaml_path = _robot_yaml(Path(tmp), rate)
            for name, fn in zip(LOOPS, (raw_asyncio, raw_spin, raw_thread, raw_timerfd), strict=True):
                progress(f"realtime: {rate:g} Hz, raw {name} ({duration:g} s)")
                rows.append({"rate": rate, "loop": f"raw {name}", **asyncio.run(fn(rate, duration))})
            progress(f"realtime: {rate:g} Hz, SDK control loop ({duration:g} s)")
            rows.append({"rate": rate, "loop": "SDK control loop", **asyncio.run(sdk_loop(yaml_path, rate, duration))})
            if fifo:
                settings, why = _fifo()
                if settings is None:
                    fifo_note = why
                else:
                    try:
                        progress(f"realtime: {rate:g} Hz, SDK control loop with SCHED_FIFO ({duration:g} s)")
                        rows.append({"rate": rate, "loop": "SDK control loop, SCHED_FIFO 50",
                                     **asyncio.run(sdk_loop(yaml_path, rate, duration))})
                        rows.append({"rate": rate, "loop": "raw timerfd, SCHED_FIFO 50",
                                     **asyncio.run(raw_timerfd(rate, duration))})
                    finally:
                        settings.restore()
    return {"duration_s": duration, "results": rows, "fifo_not_permitted": fifo_note,
            "loadavg": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}


HEADERS = ("rate Hz", "loop", "ticks", "p50 err µs", "p99 err µs", "max err µs", "missed", "CPU %")


def run(quick: bool = False) -> Section:
    """Entry point of ``agentsdk bench``."""
    duration = 0.5 if quick else 10.0  # quick: 12 rows of 0.5 s (250-500 ticks each), same rows
    res = measure(duration)
    rows = res["results"]
    sec = Section("realtime", f"realtime control loop pacing at 500 Hz and 1 kHz, {duration:g} s each, vs raw pacing "
                              "loops")
    for rate in RATES:
        base = next(r for r in rows if r["rate"] == rate and r["loop"] == "raw timerfd")
        sdk = next(r for r in rows if r["rate"] == rate and r["loop"] == "SDK control loop")
        spin = next(r for r in rows if r["rate"] == rate and r["loop"] == "raw sleep + spin")
        for key, label in (("p50_us", "p50"), ("p99_us", "p99"), ("max_us", "max")):
            sec.comparisons.append(Comparison(
                f"{rate:g} Hz control loop: period error {label}", "µs", base[key], sdk[key],
                baseline_label="raw timerfd loop", sdk_label="control loop",
                sdk_target=100.0 if (label == "p99" and rate == 1000.0) else None,
            ))
        sec.comparisons.append(Comparison(
            f"{rate:g} Hz control loop: missed deadlines in {duration:g} s", "count", float(base["missed"]),
            float(sdk["missed"]), baseline_label="raw timerfd loop", sdk_label="control loop",
            sdk_target=0.0 if rate == 1000.0 else None,
        ))
        sec.comparisons.append(Comparison(
            f"{rate:g} Hz control loop: process CPU", "% of a core", spin["cpu_percent"], sdk["cpu_percent"],
            baseline_label="raw sleep + spin", sdk_label="control loop (tick work included)",
            sdk_target=50.0 if rate == 1000.0 else None,
        ))
        fifo = next((r for r in rows if r["rate"] == rate and r["loop"] == "SDK control loop, SCHED_FIFO 50"), None)
        fifo_base = next((r for r in rows if r["rate"] == rate and r["loop"] == "raw timerfd, SCHED_FIFO 50"), None)
        if fifo is not None and fifo_base is not None:
            sec.comparisons.append(Comparison(
                f"{rate:g} Hz control loop, SCHED_FIFO: period error p99", "µs", fifo_base["p99_us"], fifo["p99_us"],
                baseline_label="raw timerfd loop, SCHED_FIFO", sdk_label="control loop",
            ))
    sec.tables.append(Table("every loop", HEADERS, [
        [fmt(r["rate"]), r["loop"], r["ticks"], fmt(r["p50_us"]), fmt(r["p99_us"]), fmt(r["max_us"]), r["missed"],
         fmt(r["cpu_percent"])] for r in rows
    ]))
    sec.notes.append(
        "the control loop paces with a timerfd watched by the event loop (agentsdk.realtime.DeadlineTimer): "
        "precise like the spin, at the CPU cost of asyncio.sleep. The pacing thread is as precise but every tick "
        "crosses threads (call_soon_threadsafe: a self-pipe write and a second wake-up), and it needs the GIL."
    )
    if res["fifo_not_permitted"]:
        sec.notes.append(f"SCHED_FIFO rows skipped: {res['fifo_not_permitted']}")
    else:
        sec.notes.append("SCHED_FIFO rows: the process ran with agentsdk.realtime.set_realtime_priority(50) "
                         "(restored afterwards).")
    sec.data = res
    return sec


if __name__ == "__main__":
    s = run("--quick" in sys.argv)
    print(s.render())
