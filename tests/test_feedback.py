"""The fixed-rate feedback agent (agentsdk.feedback).

Lockstep tests are exact (simulated time). The realtime test only checks the
structure and sanity of the statistics: no wall-clock thresholds.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import AsyncIterator

import numpy as np
import pytest
from conftest import lockstep_backends

import agentsdk
from agentsdk import ConfigurationError, EStopActive, InvalidValueError, JointCommand, JointState
from agentsdk.feedback import FeedbackAgent, LoopStats, run_feedback

#: the event-loop stall watchdog measures wall time; on a loaded test machine a run can be
#: starved for its default 0.25 s without anything being wrong, so it gets more slack here
SAFETY = {"stall_timeout": 5.0}


@pytest.fixture
async def mock_arm() -> AsyncIterator[agentsdk.Robot]:
    async with agentsdk.connect("mock", robot="arm3", safety=SAFETY) as robot:
        yield robot


class SineTracker(FeedbackAgent):
    """Position + velocity feed-forward tracking of a sine on joint1; logs what it saw and sent."""

    rate = 250.0

    def __init__(self, amplitude: float = 0.4, freq: float = 1.0) -> None:
        self.amplitude = amplitude
        self.freq = freq
        self.log: list[tuple[float, tuple[float, ...], float]] = []
        self.setup_calls = 0
        self.teardown_calls = 0

    async def setup(self, robot: agentsdk.Robot) -> None:
        self.setup_calls += 1
        self.t0 = robot.clock.now()

    async def update(self, state: JointState) -> JointCommand | None:
        w = 2 * math.pi * self.freq
        t = state.stamp - self.t0
        q = self.amplitude * math.sin(w * t)
        self.log.append((state.stamp, tuple(state.position.tolist()), q))
        return JointCommand("position", {"joint1": q}, velocity={"joint1": self.amplitude * w * math.cos(w * t)})

    async def teardown(self, robot: agentsdk.Robot) -> None:
        self.teardown_calls += 1


def _check_structure(stats: LoopStats) -> None:
    assert isinstance(stats.count, int) and isinstance(stats.missed_deadlines, int) and isinstance(stats.overruns, int)
    assert stats.period == pytest.approx(1.0 / stats.rate)
    for name in ("period_error", "latency"):
        p50, p99, mx, mean = (getattr(stats, f"{name}_{s}") for s in ("p50", "p99", "max", "mean"))
        assert all(math.isfinite(x) and x >= 0.0 for x in (p50, p99, mx, mean)), name
        assert p50 <= p99 <= mx + 1e-15, name
        assert mean <= mx + 1e-15, name
    assert 0.0 <= stats.update_time_mean <= stats.update_time_max + 1e-15
    d = stats.as_dict()
    assert d["count"] == stats.count and "achieved_rate" in d
    assert str(stats.count) in stats.summary()


@pytest.mark.parametrize("backend", lockstep_backends(deterministic=True))
async def test_lockstep_is_deterministic(backend: str) -> None:
    runs = []
    for _ in range(2):
        async with agentsdk.connect(backend, robot="arm3", safety=SAFETY) as robot:
            agent = SineTracker()
            stats = await run_feedback(robot, agent, duration=1.0)
            final = (await robot.read()).position.copy()
        runs.append((agent.log, stats, final))
    (log_a, stats_a, final_a), (log_b, stats_b, final_b) = runs
    assert len(log_a) == 250
    assert log_a == log_b  # bit-identical states and commands
    assert np.array_equal(final_a, final_b)
    assert stats_a == stats_b
    # simulated time: every period starts exactly on its deadline
    stamps = np.array([row[0] for row in log_a])
    np.testing.assert_allclose(np.diff(stamps), 1 / 250.0, rtol=0, atol=1e-12)
    assert stats_a.count == 250 and stats_a.duration == pytest.approx(1.0)
    assert stats_a.realtime is False and stats_a.end_reason == "duration"
    assert stats_a.period_error_max == 0.0 and stats_a.latency_max == 0.0
    assert stats_a.missed_deadlines == 0 and stats_a.overruns == 0
    _check_structure(stats_a)
    # and it really tracked the sine (the command went through to the robot)
    errs = [abs(pos[0] - q) for _, pos, q in log_a[25:]]
    assert max(errs) < 0.05


async def test_realtime_500hz_reports_stats() -> None:
    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety=SAFETY) as robot:
        assert robot.realtime
        agent = SineTracker()
        stats = await agent.run(robot, rate=500.0, duration=0.3)
        assert agent.stats is stats
    _check_structure(stats)
    assert stats.realtime is True and stats.end_reason == "duration"
    assert stats.count > 0
    # every scheduled period either ran or was counted as missed
    assert stats.count + stats.missed_deadlines == round(0.3 * 500)
    assert stats.duration >= 0.3 - 1e-9  # returns after the full duration, never early
    assert agent.setup_calls == agent.teardown_calls == 1


async def test_realtime_missed_deadlines_and_overruns_are_counted() -> None:
    class Blocking(FeedbackAgent):
        calls = 0

        async def update(self, state: JointState) -> JointCommand | None:
            self.calls += 1
            if self.calls == 5:
                time.sleep(0.006)  # noqa: ASYNC251 - deliberately block the loop for 3 periods of 2 ms
            return None

    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety=SAFETY) as robot:
        stats = await run_feedback(robot, Blocking(), 500.0, duration=0.1)
    _check_structure(stats)
    assert stats.overruns >= 1
    assert stats.missed_deadlines >= 2  # at least two deadlines were entirely past when it returned
    assert stats.update_time_max >= 0.006
    assert stats.count + stats.missed_deadlines == 50


async def test_lockstep_overrun_skips_deadlines_deterministically(mock_arm: agentsdk.Robot) -> None:
    class Slow(FeedbackAgent):
        rate = 250.0
        calls = 0

        def __init__(self, robot: agentsdk.Robot) -> None:
            self.robot = robot

        async def update(self, state: JointState) -> JointCommand | None:
            self.calls += 1
            if self.calls == 3:
                await self.robot.clock.sleep(0.010)  # 2.5 periods of 4 ms
            return None

    stats = await run_feedback(mock_arm, Slow(mock_arm), duration=0.1)
    # deadline 0.008 ran until 0.018: 0.012 is skipped, 0.016 runs at once (0.002 late), then on time
    assert stats.overruns == 1
    assert stats.missed_deadlines == 1
    assert stats.count == 25 - 1
    assert stats.latency_max == pytest.approx(0.002)
    assert stats.update_time_max == pytest.approx(0.010)


async def test_lockstep_rate_must_divide_the_control_rate(mock_arm: agentsdk.Robot) -> None:
    assert mock_arm.control_period == pytest.approx(0.002)
    with pytest.raises(ConfigurationError, match="whole multiple"):
        await run_feedback(mock_arm, SineTracker(), 300.0, duration=0.1)
    with pytest.raises(ConfigurationError):
        await run_feedback(mock_arm, SineTracker(), 1000.0, duration=0.1)  # faster than the control loop
    for bad in (0.0, -5.0, math.nan, math.inf):
        with pytest.raises(InvalidValueError):
            await run_feedback(mock_arm, SineTracker(), bad, duration=0.1)
    with pytest.raises(InvalidValueError):
        await run_feedback(mock_arm, SineTracker(), 100.0, duration=-1.0)
    stats = await run_feedback(mock_arm, SineTracker(), 100.0, duration=0.1)  # 5 control periods
    assert stats.count == 10


async def test_stop_event_wakes_the_sleeping_loop(mock_arm: agentsdk.Robot) -> None:
    stop = asyncio.Event()
    agent = SineTracker()

    async def stopper() -> None:
        await mock_arm.clock.sleep(0.25)
        stop.set()

    task = asyncio.create_task(stopper())
    t0 = mock_arm.clock.now()
    stats = await run_feedback(mock_arm, agent, 10.0, stop=stop)  # periods of 0.1 s
    await task
    assert stats.end_reason == "stop"
    assert mock_arm.clock.now() - t0 == pytest.approx(0.25)  # not at the next deadline (0.3)
    assert stats.count == 3  # 0.0, 0.1, 0.2
    assert agent.teardown_calls == 1
    # already set: returns at once
    stats = await run_feedback(mock_arm, SineTracker(), 10.0, stop=stop)
    assert stats.count == 0 and stats.end_reason == "stop"


async def test_commands_go_through_the_safety_layer(mock_arm: agentsdk.Robot) -> None:
    """Velocity streaming feeds the command watchdog; out-of-limit values are clamped; exit holds."""

    async def spin(state: JointState) -> JointCommand:
        return JointCommand("velocity", {"joint1": 0.5, "joint3": 99.0})

    stats = await run_feedback(mock_arm, spin, rate=100.0, duration=1.0)  # 4x the command timeout
    assert stats.count == 100
    safety = mock_arm.safety
    assert safety.state is agentsdk.SafetyState.OK
    kinds = [e.kind for e in safety.events]
    assert "watchdog" not in kinds  # fed every period
    assert "clamp" in kinds  # 99 rad/s was limited to max_velocity
    # on exit the streamed joints hold their measured position (not left to the watchdog)
    j1, j3 = mock_arm.joint_index["joint1"], mock_arm.joint_index["joint3"]
    assert mock_arm.setpoint.mode[j1] == mock_arm.setpoint.mode[j3] == 0  # position
    held = (await mock_arm.read()).position.copy()
    await mock_arm.clock.sleep(0.5)
    after = (await mock_arm.read()).position
    assert abs(after[j1] - held[j1]) < 1e-9 and abs(after[j3] - held[j3]) < 1e-9
    assert held[j1] == pytest.approx(0.5, abs=0.05)  # it did move at 0.5 rad/s for 1 s


async def test_update_error_propagates_after_teardown(mock_arm: agentsdk.Robot) -> None:
    class Failing(SineTracker):
        async def update(self, state: JointState) -> JointCommand | None:
            if len(self.log) == 10:
                raise RuntimeError("boom")
            return await super().update(state)

    agent = Failing()
    with pytest.raises(RuntimeError, match="boom"):
        await run_feedback(mock_arm, agent, duration=1.0)
    assert agent.teardown_calls == 1
    assert agent.stats is not None and agent.stats.count == 10 and agent.stats.end_reason == "error"


async def test_estop_stops_the_loop(mock_arm: agentsdk.Robot) -> None:
    agent = SineTracker()

    async def estop_later() -> None:
        await mock_arm.clock.sleep(0.2)
        await mock_arm.estop(category=2)

    task = asyncio.create_task(estop_later())
    with pytest.raises(EStopActive):
        await run_feedback(mock_arm, agent, duration=5.0)
    await task
    assert agent.teardown_calls == 1
    assert agent.stats is not None and 0.2 * 250 <= agent.stats.count < 0.4 * 250


async def test_cancelling_the_task_runs_teardown(mock_arm: agentsdk.Robot) -> None:
    agent = SineTracker()
    task = asyncio.create_task(run_feedback(mock_arm, agent))  # no duration: runs until cancelled
    await mock_arm.clock.sleep(0.1)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert agent.teardown_calls == 1
    assert agent.stats is not None and agent.stats.end_reason == "cancelled" and agent.stats.count == 25


def test_stats_from_wake_times() -> None:
    wakes = [0.0, 0.0021, 0.0040, 0.0065, 0.0080]
    stats = LoopStats.from_wake_times(wakes, 0.002)
    assert stats.count == 5
    assert stats.period_error_max == pytest.approx(0.0005)
    assert stats.period_error_mean == pytest.approx((0.0001 + 0.0001 + 0.0005 + 0.0005) / 4)
    assert stats.duration == pytest.approx(0.008)
    _check_structure(stats)


async def test_setup_may_take_robot_time_and_plain_functions_work(mock_arm: agentsdk.Robot) -> None:
    class MovesFirst(SineTracker):
        async def setup(self, robot: agentsdk.Robot) -> None:
            assert (await robot.move_to({"joint1": 0.3})).ok  # takes robot time
            await super().setup(robot)

    agent = MovesFirst()
    t0 = mock_arm.clock.now()
    stats = await run_feedback(mock_arm, agent, duration=0.2)
    assert agent.t0 > t0  # the periods are counted from the end of setup: none was missed
    assert stats.count == 50 and stats.missed_deadlines == 0 and stats.latency_max == 0.0

    seen: list[float] = []

    def sync_update(state: JointState) -> None:  # a plain function, no command
        seen.append(state.stamp)

    stats = await run_feedback(mock_arm, sync_update, rate=50.0, duration=0.2)
    assert stats.count == len(seen) == 10

    class NotAsync(FeedbackAgent):
        def update(self, state: JointState) -> None:  # type: ignore[override]
            return None

    with pytest.raises(InvalidValueError, match="async def update"):
        await run_feedback(mock_arm, NotAsync(), duration=0.1)


async def test_without_exit_hold_the_watchdog_takes_over(mock_arm: agentsdk.Robot) -> None:
    async def spin(state: JointState) -> JointCommand:
        return JointCommand("velocity", {"joint1": 0.5})

    await run_feedback(mock_arm, spin, rate=100.0, duration=0.2, hold_on_exit=False)
    assert mock_arm.setpoint.mode[mock_arm.joint_index["joint1"]] == 1  # still streaming velocity
    await mock_arm.clock.sleep(0.5)  # > command_timeout
    assert "watchdog" in [e.kind for e in mock_arm.safety.events]
