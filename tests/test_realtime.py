"""agentsdk.realtime: the timerfd deadline timer and real-time scheduling (no wall-clock thresholds)."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agentsdk.errors import ConfigurationError
from agentsdk.realtime import DeadlineTimer, set_realtime_priority, timerfd_available

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(not timerfd_available(), reason="no timerfd (not Linux)")
async def test_deadline_timer_wakes_sleepers_in_deadline_order_never_early() -> None:
    timer = DeadlineTimer()
    try:
        woke: list[int] = []
        base = time.monotonic()
        deadlines = {0: base + 0.006, 1: base + 0.002, 2: base + 0.004, 3: base - 1.0}

        async def sleeper(k: int) -> None:
            await timer.sleep_until(deadlines[k])
            assert time.monotonic() >= deadlines[k]  # never before its deadline
            woke.append(k)

        async with asyncio.TaskGroup() as tg:
            for k in deadlines:
                tg.create_task(sleeper(k))
        assert woke == [3, 1, 2, 0]
    finally:
        timer.close()
    assert timer.closed


@pytest.mark.skipif(not timerfd_available(), reason="no timerfd (not Linux)")
async def test_deadline_timer_cancelled_sleep_leaves_the_others() -> None:
    timer = DeadlineTimer()
    try:
        fut = timer.sleep_until(time.monotonic() + 0.003)
        fut.cancel()
        await timer.sleep_until(time.monotonic() + 0.005)
        assert fut.cancelled()
    finally:
        timer.close()


@pytest.mark.skipif(not timerfd_available(), reason="no timerfd (not Linux)")
async def test_deadline_timer_and_realtime_sleeps_read_no_clock(monkeypatch: pytest.MonkeyPatch) -> None:
    """A realtime tick's sleep costs no clock read (a system call without a vDSO, e.g. user-mode Linux):
    the timerfd is armed at the absolute deadline, and its expiry says which sleepers are due."""
    import types

    import agentsdk.realtime as rt
    from agentsdk.clock import RealtimeClock

    clock = RealtimeClock()
    reads = 0

    def counted() -> float:
        nonlocal reads
        reads += 1
        return time.monotonic()

    # the realtime module's clock (the timer's wake-ups) and the robot clock's now(), counted
    monkeypatch.setattr(rt, "time", types.SimpleNamespace(monotonic=counted, CLOCK_MONOTONIC=time.CLOCK_MONOTONIC))
    now = clock.now
    monkeypatch.setattr(clock, "now", lambda: (counted(), now())[1])
    try:
        start = now()
        for k in range(1, 6):  # like the control loop: each deadline a period after the last
            await clock.sleep_until(start + 0.002 * k)
            assert now() >= start + 0.002 * k  # never early
        await clock.sleep_until(start)  # a deadline already past returns at the next wake-up
        await clock.sleep_until(-1.0)
        await clock.sleep_until(-float("inf"))
    finally:
        clock.release()
    assert reads == 0


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="no SCHED_FIFO on this platform")
def test_set_realtime_priority_rejects_bad_priority_and_cpus() -> None:
    with pytest.raises(ConfigurationError, match=r"priority must be an integer in 1\.\.99"):
        set_realtime_priority(0)
    with pytest.raises(ConfigurationError, match="priority must be an integer"):
        set_realtime_priority(2.5)  # type: ignore[arg-type]
    before = os.sched_getaffinity(0)
    with pytest.raises(ConfigurationError, match=r"cannot pin the process to CPUs \[100000\].*available"):
        set_realtime_priority(10, cpus=[100000])
    assert os.sched_getaffinity(0) == before  # left as it was


_PROBE = """
import os, sys
from agentsdk.errors import ConfigurationError
from agentsdk.realtime import set_realtime_priority
import resource
if os.geteuid() == 0:  # drop root (and with it CAP_SYS_NICE) to see the message an ordinary user gets
    resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
    os.setgid(65534)
    os.setuid(65534)
try:
    s = set_realtime_priority(10)
except ConfigurationError as exc:
    print(exc)
    sys.exit(3)
s.restore()
"""


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="no SCHED_FIFO on this platform")
def test_set_realtime_priority_says_what_to_change_where_not_permitted() -> None:
    proc = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=60, cwd=ROOT)
    if proc.returncode == 0:
        pytest.skip("this process may use SCHED_FIFO even unprivileged (rtprio limit)")
    assert proc.returncode == 3, proc.stderr
    msg = proc.stdout
    assert "not permitted to use SCHED_FIFO priority 10" in msg
    assert "CAP_SYS_NICE" in msg and "rtprio" in msg  # the two ways to permit it
    assert "still runs without it" in msg


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="no SCHED_FIFO on this platform")
def test_set_realtime_priority_applies_and_restores_where_permitted() -> None:
    before = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, os.sched_getaffinity(0))
    try:
        settings = set_realtime_priority(5, cpus=sorted(before[2])[:1])
    except ConfigurationError as exc:
        pytest.skip(f"not permitted here: {exc}")
    try:
        assert os.sched_getscheduler(0) == os.SCHED_FIFO
        assert os.sched_getparam(0).sched_priority == 5
        assert os.sched_getaffinity(0) == set(sorted(before[2])[:1])
    finally:
        settings.restore()
    assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, os.sched_getaffinity(0)) == before


def test_cli_run_rejects_a_malformed_cpu_list() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "agentsdk", "run", str(ROOT / "behaviors" / "wave.py"), "--backend", "mock",
         "--cpus", "two"],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )
    assert proc.returncode != 0
    assert "--cpus must be a comma-separated list of CPU numbers, got 'two'" in proc.stdout + proc.stderr
