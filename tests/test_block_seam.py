"""Block lockstep, the planning seam on a running robot (issue 28 item 1).

At many ticks of real motions (a planned move, a hand-written trajectory, a stop ramp after a
cancel; arm3 and humanoid on MuJoCo) the executor predicts the
references of the coming ticks at once (:meth:`BlockPlanner.reference`) where nothing else is
runnable (a block starts after the event loop settled), bounded by the clock's next wake-up
(:meth:`LockstepClock.ticks_until_wake`); the ticks that then run write exactly those setpoints,
bit for bit.
"""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk import Phase, Trajectory, TrajectoryPoint
from agentsdk.errors import BackendUnavailableError
from agentsdk.loop import _ready_queue


def _goal(robot: agentsdk.Robot, frac: float) -> list[float]:
    out = []
    for j in robot.joints:
        lo = j.lower if np.isfinite(j.lower) else -1.0
        hi = j.upper if np.isfinite(j.upper) else 1.0
        out.append(lo + (hi - lo) * frac)
    return out


class _Probe:
    """Predicts at the end of every ``every``-th tick; records every tick's setpoint."""

    def __init__(self, robot: agentsdk.Robot, every: int, rng: np.random.Generator) -> None:
        self.robot = robot
        self.loop = robot._loop
        self.planner = robot._motions.block_planner
        self.table = robot._motions._table
        self.every = every
        self.rng = rng
        #: the setpoint's position, velocity and acceleration rows as written at each tick
        self.written: dict[int, np.ndarray] = {}
        #: (tick the prediction starts at, joints, the predicted samples, how many are pre-planned)
        self.predictions: list[tuple[int, np.ndarray, np.ndarray, int, str]] = []
        robot.add_tick_hook(Phase.OBSERVE, self._tick, order=-(1 << 30))

    def _tick(self, t: float, st: Any, sp: Any) -> None:
        clock = self.loop.clock
        tick = clock.ticks  # this tick's number (its setpoint was written for time (tick - 1) * period)
        self.written[tick - 1] = np.vstack([sp.position, sp.velocity, sp.acceleration])
        if tick % self.every:
            return
        if len(_ready_queue(asyncio.get_running_loop())):
            return  # this tick woke a task (or resolved a future): it runs before the next tick, as a block starts
        K = clock.ticks_until_wake(int(self.rng.integers(1, 400)))
        ts = (tick + np.arange(K)) * self.loop.period
        assert ts[0] == self.loop.stamp
        for ex in dict.fromkeys(o for o in self.table.owner if o is not None):
            out = np.empty((K, 3, len(ex.idx)))
            taus = np.empty(K)
            k = self.planner.reference(ex, ts, taus, out)
            self.predictions.append((tick, ex.idx.copy(), out[:k].copy(), k, ex.phase.name))


async def _run(robot_name: str, seed: int) -> _Probe:
    try:
        robot_cm = agentsdk.connect("mujoco", robot=robot_name)
        robot = await robot_cm.__aenter__()
    except BackendUnavailableError as exc:  # pragma: no cover
        pytest.skip(str(exc))
    try:
        probe = _Probe(robot, every=7 + seed, rng=np.random.default_rng(seed))
        names = list(robot.joint_names)
        clock = robot.clock
        await robot.move_to(dict(zip(names, _goal(robot, 0.55), strict=True)))
        plan = Trajectory(names, [TrajectoryPoint(0.6, _goal(robot, 0.6)), TrajectoryPoint(1.1, _goal(robot, 0.4))])
        await robot.follow(plan, stretch_to_limits=True)
        m = robot.follow(plan, stretch_to_limits=True)
        await clock.sleep(0.35)
        m.cancel()
        await m
        await clock.sleep(0.1)
    finally:
        await robot_cm.__aexit__(None, None, None)
    return probe


@pytest.mark.timeout(300)
@pytest.mark.parametrize("robot_name", ["arm3", "humanoid"])
async def test_the_predicted_references_are_what_the_ticks_write(robot_name: str) -> None:
    planned = {"FOLLOW": 0, "STOPPING": 0}
    for seed in range(2):
        probe = await _run(robot_name, seed)
        for tick, idx, out, k, phase in probe.predictions:
            planned[phase] = planned.get(phase, 0) + k
            for j in range(k):
                got = probe.written[tick + j][:, idx]
                assert got.tobytes() == np.ascontiguousarray(out[j]).tobytes(), (phase, tick, j, k)
    # the seam is not vacuous: many ticks of a running trajectory and of a stop ramp were predicted
    assert planned["FOLLOW"] > 500
    assert planned["STOPPING"] > 20


async def test_ticks_until_wake_is_the_tick_that_wakes_the_sleeper() -> None:
    async with agentsdk.connect("mock", robot="arm3") as robot:
        clock = robot.clock
        loop = robot._loop
        for dt in (0.0005, 0.001, 0.00123, 0.01, 0.037, 0.5, 1.0 / 3.0, loop.period, 2 * loop.period):
            woken: list[int] = []

            async def sleeper(dt: float = dt, woken: list[int] = woken) -> None:
                await clock.sleep(dt)
                woken.append(clock.ticks)

            start = clock.ticks
            async with asyncio.TaskGroup() as tg:
                tg.create_task(sleeper())
                await asyncio.sleep(0)
                await asyncio.sleep(0)
                predicted = clock.ticks_until_wake(1 << 20)
                assert clock.ticks_until_wake(2) == min(2, predicted)
                assert clock.wakes_next_tick() == (predicted == 1)
            assert woken == [start + predicted], (dt, loop.period)


async def test_advance_ticks_is_advance_called_that_many_times() -> None:
    """``LockstepClock.advance_ticks(n)``: the ticks and the sleepers woken at each, as n ``advance()`` calls."""
    from agentsdk.clock import LockstepClock

    rng = np.random.default_rng(11)
    for case in range(200):
        period = float(rng.choice([0.001, 0.002, 0.00123, 1.0 / 3.0]))
        clocks = (LockstepClock(period), LockstepClock(period))
        start = int(rng.integers(0, 1000))
        futs: list[list[asyncio.Future[None]]] = [[], []]
        deadlines = start * period + rng.uniform(0, 60 * period, int(rng.integers(0, 6)))
        cancel = rng.random(len(deadlines)) < 0.3
        for clock, fs in zip(clocks, futs, strict=True):
            clock._tick = start
            for dl, off in zip(deadlines, cancel, strict=True):
                fut = clock._enqueue(float(dl))
                if off:
                    fut.cancel()
                fs.append(fut)
        one, many = clocks
        for _ in range(int(rng.integers(1, 4))):
            count = int(rng.integers(1, 40))
            woke = sum(one.advance() for _ in range(count))
            assert many.advance_ticks(count) == woke, case
            assert many.ticks == one.ticks
            assert [f.done() for f in futs[1]] == [f.done() for f in futs[0]], case
            live = [sorted(d for d, _, f in c._heap if not f.done()) for c in clocks]
            assert live[0] == live[1], case
