"""The stall watchdog's cost per control cycle: ticks beat, the loop timer and the idle thread stay slow.

Where every clock read and thread wake-up is a system call into another kernel (user-mode Linux,
CI's VM) the watchdog's own heartbeat every 5 ms and a 2 ms idle poll were a large part of the
CAN host's CPU. These tests pin the rule, not a speed: a realtime tick is a beat (at the time the
tick read, no clock read of its own), the event-loop timer beats every ``timeout / 10`` then, and
the thread looks every ``timeout / 2`` while there is nothing to watch; a blocked loop is still
stopped ``timeout`` after its last beat.
"""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Any

import pytest

import agentsdk
from agentsdk import JointCommand
from agentsdk.stall import StallWatchdog

pytestmark = pytest.mark.timeout(60)


def _watchdog(timeout: float, idle: bool, stalls: list[float]) -> StallWatchdog:
    return StallWatchdog(
        timeout, "agentsdk-stall-watchdog-test", idle=lambda: idle, emergency_stop=lambda: None,
        on_stall=lambda last, stopped, stack, where: stalls.append(stopped - last),
    )


def test_a_tick_beats_at_the_time_it_read_and_never_back() -> None:
    wd = _watchdog(0.25, True, [])
    origin = time.monotonic()
    beat = wd.tick_beats(origin)
    beat(5.0, None, None)
    assert wd._beat == origin + 5.0
    beat(4.0, None, None)  # an older stamp never moves the beat back
    assert wd._beat == origin + 5.0
    assert wd._interval == pytest.approx(0.025)  # the loop timer only covers a loop that stops ticking


def test_without_ticks_the_loop_timer_keeps_its_short_interval() -> None:
    assert _watchdog(0.25, True, [])._interval == pytest.approx(0.005)
    assert _watchdog(0.02, True, [])._interval == pytest.approx(0.002)


async def test_the_idle_thread_looks_every_half_timeout_not_every_few_ms(monkeypatch: pytest.MonkeyPatch) -> None:
    stalls: list[float] = []
    wd = _watchdog(0.2, True, stalls)
    waits: list[float] = []
    stop = wd._thread_stop
    real_wait = stop.wait

    def wait(timeout: float | None = None) -> bool:
        if threading.current_thread() is not threading.main_thread():
            waits.append(timeout if timeout is not None else -1.0)
        return real_wait(timeout)

    monkeypatch.setattr(stop, "wait", wait)
    wd.start()
    try:
        while len(waits) < 3:  # noqa: ASYNC110 - polling a list another thread fills
            await asyncio.sleep(0.02)
    finally:
        await wd.stop()
    assert all(w == pytest.approx(0.1) for w in waits[:3]), waits
    assert stalls == []


async def test_a_realtime_robot_blocked_after_ticking_is_stopped_a_timeout_after_its_last_tick() -> None:
    """Ticks beat (the loop timer every timeout / 10 only): a blocked loop still latches the e-stop
    from the thread, measured from the last beat, and the stop comes while the loop is blocked."""
    timeout = 0.2
    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety={"stall_timeout": timeout}) as robot:
        safety: Any = robot.safety
        stall = safety._watchdogs._stall  # the stall thread's wiring lives in the safety layer's watchdogs
        assert stall is not None and stall._interval == pytest.approx(timeout / 10)
        await robot.command(JointCommand("position", {"joint1": 0.0}))
        await robot.clock.sleep(0.1)
        t0 = time.monotonic()
        time.sleep(0.6)  # noqa: ASYNC251 - the blocking call under test
        t1 = time.monotonic()
        assert safety.stall_detected_at is not None
        assert t0 < safety.stall_detected_at < t1
        assert safety.stall_latency >= timeout
        assert not robot.torque_enabled


@pytest.mark.parametrize("report_fails", [False, True])
async def test_the_thread_reports_then_stops_and_a_failing_report_never_prevents_the_stop(report_fails: bool) -> None:
    """The report (the safety layer's latch) comes before the stop, so whoever sees the actuators
    stopped sees the e-stop too; a report that raises still ends in the stop."""
    order: list[str] = []
    reports: list[tuple[float, str]] = []

    def on_stall(last: float, detected: float, stack: Any, where: str) -> str:
        order.append("report")
        reports.append((detected - last, where))
        if report_fails:
            raise RuntimeError("a broken report")
        return "stalled"

    wd = StallWatchdog(0.05, "agentsdk-stall-watchdog-test", idle=lambda: "stop" in order,  # torque off: idle
                       emergency_stop=lambda: order.append("stop"), on_stall=on_stall)
    wd.start()
    try:
        await asyncio.sleep(0.01)
        time.sleep(0.3)  # noqa: ASYNC251 - the stall under test
    finally:
        await wd.stop()
    assert order == ["report", "stop"]
    # (checked here: an assertion inside on_stall would be caught by the thread's guard)
    ((age, where),) = reports
    assert age > 0.05
    assert "test_stall_watchdog.py" in where  # the loop thread's own frame, found without reading files
