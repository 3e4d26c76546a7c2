"""Many robots per process: N lockstep robots in one event loop, aggregate control steps/s beside one robot's.

Not a test. Each robot is ``agentsdk.connect("mujoco", "arm3")`` in lockstep (its own
simulated clock); all of them run in one ``asyncio`` event loop, each with its own
behavior task:

hold    ``await robot.clock.sleep(T)`` after a position command
track   ``robot.follow(trajectory)`` through random waypoints, then sleep to its end

Aggregate control steps/s = control ticks of all robots / wall time, beside one robot
doing the same alone (same run, interleaved). The raw row does the same with bare
MuJoCo models (N models stepped round-robin in one Python loop vs one), to show how the
simulator itself scales. A ratio near 1 means the SDK adds little per extra robot.
"""

from __future__ import annotations

import asyncio
import sys
import time
from typing import Any

import agentsdk
from agentsdk import JointCommand
from agentsdk.bench.common import Comparison, Section, Table, fmt, median, progress

ROBOT = "arm3"
BACKEND = "mujoco"
COUNTS = (1, 8)


async def _run_robots(n: int, scenario: str, sim_s: float, traj: Any) -> tuple[int, float]:
    """(total control ticks, wall seconds) of ``n`` robots running ``scenario`` concurrently."""
    robots = [await agentsdk.connect(BACKEND, ROBOT) for _ in range(n)]
    try:
        for r in robots:
            # connecting the next robot blocks the event loop (description loading, model compile),
            # which the stall watchdog of a robot already running may take for a stall: re-arm it
            if r.safety.state is not agentsdk.SafetyState.OK:
                await r.reset()
                await r.enable()
        ticks0 = [r.ticks for r in robots]

        async def behave(r: agentsdk.Robot) -> None:
            if scenario == "hold":
                await r.command(JointCommand("position", (await r.read()).position.tolist()))
                await r.clock.sleep(sim_s)
            else:
                r.follow(traj)
                await r.clock.sleep(sim_s)

        t0 = time.perf_counter()
        async with asyncio.TaskGroup() as tg:
            for r in robots:
                tg.create_task(behave(r))
        wall = time.perf_counter() - t0
        ticks = sum(r.ticks - k for r, k in zip(robots, ticks0, strict=True))
    finally:
        for r in robots:
            await r.close()
    return ticks, wall


def _raw(n: int, sim_s: float) -> tuple[int, float]:
    """(total steps, wall s) of ``n`` bare MuJoCo models (the backend's model), stepped round-robin."""
    from agentsdk.bench.overhead import RawMujoco, load_robot

    rb = load_robot(ROBOT)
    sims = [RawMujoco(rb) for _ in range(n)]
    ticks = round(sim_s / rb.period)
    q0 = [s.positions() for s in sims]
    for s, q in zip(sims, q0, strict=True):
        s.ctrl[:] = s.kp * q
    t0 = time.perf_counter()
    for _ in range(ticks):
        for s in sims:
            d = s.data
            _q = d.qpos[s.qadr]
            _v = d.qvel[s.dadr]
            d.ctrl[:] = s.ctrl
            s.mj.mj_step(s.model, d, nstep=s.nsub)
    return ticks * n, time.perf_counter() - t0


def measure(sim_s: float, repeats: int) -> dict[str, Any]:
    from agentsdk.bench.overhead import load_robot, waypoints

    rb = load_robot(ROBOT)
    _wps, traj = waypoints(rb, sim_s)
    res: dict[str, dict[int, list[float]]] = {k: {n: [] for n in COUNTS} for k in ("hold", "track", "raw")}
    for rep in range(repeats):
        order = COUNTS if rep % 2 == 0 else tuple(reversed(COUNTS))
        for n in order:
            for scenario in ("hold", "track"):
                progress(f"multi: {n} x {ROBOT} on {BACKEND}, {scenario} {sim_s:g} s simulated (run {rep + 1})")
                ticks, wall = asyncio.run(_run_robots(n, scenario, sim_s, traj))
                res[scenario][n].append(ticks / wall)
            ticks, wall = _raw(n, sim_s)
            res["raw"][n].append(ticks / wall)
    return {"sim_seconds": sim_s, "repeats": repeats, "steps_per_s": res}


def run(quick: bool = False) -> Section:
    """Entry point of ``agentsdk bench``."""
    sim_s, repeats = (1.0, 1) if quick else (5.0, 3)
    res = measure(sim_s, repeats)
    sps = res["steps_per_s"]
    one, many = COUNTS
    sec = Section("multi", f"{many} lockstep robots in one event loop vs one ({ROBOT} on {BACKEND}, "
                           f"{sim_s:g} s simulated each, median of {repeats})")
    for scenario, what in (("hold", "holding"), ("track", "tracking a trajectory")):
        sec.comparisons.append(Comparison(
            f"{many} x {ROBOT}, {what}: aggregate control steps/s", "steps/s",
            median(sps[scenario][one]), median(sps[scenario][many]),
            baseline_label="1 robot", sdk_label=f"{many} robots", lower_is_better=False, ratio_target=0.8,
        ))
    sec.comparisons.append(Comparison(
        f"{many} raw MuJoCo models round-robin: aggregate steps/s", "steps/s",
        median(sps["raw"][one]), median(sps["raw"][many]),
        baseline_label="1 raw model", sdk_label=f"{many} raw models", lower_is_better=False,
    ))
    sec.tables.append(Table("steps/s per run", ("scenario", "robots", "runs", "median"), [
        [k, n, ", ".join(fmt(x) for x in v), fmt(median(v))] for k, per in sps.items() for n, v in per.items()
    ]))
    sec.notes.append(
        "each robot has its own lockstep clock; a control loop runs ticks back to back while none of them wakes "
        "another task, so robots take turns in batches and the event loop's own cost is paid per batch, not per tick."
    )
    sec.data = {**res, "steps_per_s": {k: {str(n): v for n, v in per.items()} for k, per in sps.items()}}
    return sec


if __name__ == "__main__":
    print(run("--quick" in sys.argv).render())
