"""The lockstep hot path's machinery (issue 16), checked without timing anything.

- Batching: the lockstep loop runs many ticks per pass through the event loop. It must
  compute exactly what one tick per pass computes: same ticks, same setpoints, same
  measured states, with motions, the command watchdog, cancellation and sleepers that wake
  mid-run all evaluated tick by tick.
- Allocation-free ticks: the COMMAND/LIMIT phases (motion executor, safety filter) and the
  OBSERVE phase (safety checks, command watchdog) allocate no arrays per tick, and the
  backend's write/step/read allocate nothing beyond the step coroutine. Checked with
  tracemalloc's peak between probes (a numpy array costs >= 100 bytes; the probes themselves
  cost nothing measurable).
"""

from __future__ import annotations

import asyncio
import sys
import tracemalloc
from typing import Any

import numpy as np
import pytest
from conftest import lockstep_backends

import agentsdk
from agentsdk import JointCommand, Phase, Trajectory, TrajectoryPoint
from agentsdk.errors import BackendUnavailableError
from agentsdk.registry import load_backend

#: every lockstep backend in the registry (gated on capabilities, see conftest)
BACKENDS = lockstep_backends()


def _available(backend: str) -> bool:
    try:
        load_backend(backend)
    except BackendUnavailableError:
        return False
    return True


async def _scenario(backend: str, batch: bool) -> tuple[int, np.ndarray, list[str]]:
    """A run exercising motions, preemption, cancel, streamed commands and the command watchdog.

    Returns the tick count, every tick's [t, setpoint position/velocity/enabled, measured
    position/velocity] as one array, and the safety events' kinds.
    """
    rows: list[np.ndarray] = []
    safety = {"command_timeout": 0.05, "stall_timeout": 10.0}
    async with agentsdk.connect(backend, robot="arm3", safety=safety) as robot:
        if not batch:
            robot._loop.batch_seconds = 0.0  # one tick per pass through the event loop
        names = list(robot.joint_names)

        def record(t: float, st: Any, sp: Any) -> None:
            rows.append(np.concatenate(([t], sp.position, sp.velocity, sp.enabled, st.position, st.velocity)))

        robot.add_tick_hook(Phase.OBSERVE, record)
        n = len(names)
        # a trajectory, preempted half way by another one
        first = robot.follow(Trajectory(names, [TrajectoryPoint(0.8, [0.4] * n), TrajectoryPoint(1.6, [-0.2] * n)]))
        await robot.clock.sleep(0.5)
        second = robot.follow(Trajectory(names, [TrajectoryPoint(1.5, [0.1] * n)]), stretch_to_limits=True)
        await first
        await second
        # a motion cancelled part way (decelerate and hold)
        third = robot.follow(Trajectory(names, [TrajectoryPoint(2.0, [0.6] * n)]))
        sleeper = asyncio.create_task(robot.clock.sleep(0.123))
        await robot.clock.sleep(0.2)
        await sleeper
        third.cancel()
        await third
        # a velocity stream that stops being fed: the command watchdog holds the joint
        await robot.command(JointCommand("velocity", {names[0]: 0.3}))
        await robot.clock.sleep(0.25)
        ticks = robot.ticks
        kinds = [e.kind for e in robot.safety.events]
    return ticks, np.array(rows), kinds


@pytest.mark.parametrize("backend", BACKENDS)
async def test_batched_lockstep_matches_one_tick_per_pass(backend: str) -> None:
    if not _available(backend):
        pytest.skip(f"{backend} not installed")
    ticks_b, rows_b, events_b = await _scenario(backend, batch=True)
    ticks_s, rows_s, events_s = await _scenario(backend, batch=False)
    assert ticks_b == ticks_s
    assert rows_b.shape == rows_s.shape
    assert np.array_equal(rows_b, rows_s)  # bit for bit: same ticks, same setpoints, same states
    assert events_b == events_s
    assert "watchdog" in events_b  # the watchdog did act inside the run (the scenario covers it)


# ------------------------------------------------------------------- allocations
class _Probes:
    """tracemalloc peaks of the tick's segments, from hooks at the ends of the phases.

    Segment ``hooks``: the end of one tick's OBSERVE phase -> the end of the next LIMIT phase
    (COMMAND hooks: motions; LIMIT hooks: the safety filter; the loop's own code between ticks).
    Segment ``backend``: -> the start of OBSERVE (write, step, clock advance, read).
    Segment ``observe``: -> the end of OBSERVE (safety checks, command watchdog, ...).
    """

    def __init__(self, robot: agentsdk.Robot) -> None:
        self.seg: dict[str, list[int]] = {"hooks": [], "backend": [], "observe": [], "empty": []}
        big = 1 << 30
        robot.add_tick_hook(Phase.LIMIT, self._end_of("hooks"), order=big)
        robot.add_tick_hook(Phase.OBSERVE, self._end_of("backend"), order=-big)
        robot.add_tick_hook(Phase.OBSERVE, self._end_of("observe"), order=big)
        # two probes back to back: what the probes themselves cost
        robot.add_tick_hook(Phase.OBSERVE, self._end_of("empty"), order=big + 1)

    def _end_of(self, name: str) -> Any:
        out = self.seg[name]

        def probe(t: float, st: Any, sp: Any) -> None:
            if tracemalloc.is_tracing():
                cur, peak = tracemalloc.get_traced_memory()
                out.append(peak - cur)
                tracemalloc.reset_peak()

        return probe

    def median(self, name: str) -> float:
        return float(np.median(self.seg[name][3:]))


@pytest.mark.parametrize(
    "what",
    [
        "hold",
        "trajectory",
    ],
)
async def test_mujoco_tick_allocates_no_arrays(what: str) -> None:
    if not _available("mujoco"):
        pytest.skip("mujoco not installed")
    async with agentsdk.connect("mujoco", robot="arm3", safety={"stall_timeout": 10.0}) as robot:
        names = list(robot.joint_names)
        probes = _Probes(robot)
        if what == "trajectory":
            motion = robot.follow(Trajectory(names, [TrajectoryPoint(2.0, [0.5] * len(names))]))
        await robot.clock.sleep(0.05)  # warm up (first-tick views, caches)
        step = robot.backend.step(robot.control_period)
        coroutine = sys.getsizeof(step)
        step.close()
        tracemalloc.start()
        try:
            await robot.clock.sleep(0.5)
        finally:
            tracemalloc.stop()
        if what == "trajectory":
            assert not motion.done()  # still following: the executor ran in every sampled tick
            motion.cancel()
            await motion
    n = len(probes.seg["hooks"])
    assert n >= 200
    empty = probes.median("empty")
    assert empty <= 96, f"the probes allocate {empty} bytes"
    # no arrays in the hooks (a numpy array is >= 100 bytes); at most an iterator or a small int
    assert probes.median("hooks") <= empty + 64, probes.seg["hooks"][:20]
    assert probes.median("observe") <= empty + 64, probes.seg["observe"][:20]
    # the backend: nothing beyond the step coroutine (plus tracemalloc's per-block header)
    assert probes.median("backend") <= empty + coroutine + 64, probes.seg["backend"][:20]
