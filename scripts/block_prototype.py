"""Block lockstep, a prototype measurement (issue 28 item 1): what a hold costs per tick as a block.

Not a row of ``agentsdk bench`` (and a developer script, not shipped code: it reaches into the
SDK's private objects), from before the loop ran blocks (``bench/block.py`` measures those). This puts the pieces
that exist together by hand, on a robot holding still in lockstep on MuJoCo, and times them
against the SDK's tick-by-tick hold and the raw loop in the same run (CPU time per control tick,
best of ``--rounds``; the ratio to the raw loop is the figure, absolute times move with the load):

* ``tick-by-tick``: ``await robot.clock.sleep(K * period)`` while a position hold runs;
* ``block``: :class:`~agentsdk.backends.mujoco.block.BlockStepper` stepping K ticks with the hold's
  setpoint, then the LIMIT filter's, the sensor gate's and every check's block form over the K
  states (what a block must compute; its commit and the loop's bookkeeping are not included);
* ``raw``: ``backend.write``, ``mj_step``, ``backend.read`` per tick.

Run: ``python scripts/block_prototype.py [--ticks 500] [--rounds 5] [robot ...]``.
"""

from __future__ import annotations

import argparse
import asyncio
import time
from collections.abc import Awaitable, Callable

import mujoco
import numpy as np

import agentsdk
from agentsdk import JointCommand
from agentsdk.backends.mujoco.block import BlockStepper


def _best(fn: Callable[[], object], rounds: int, ticks: int) -> float:
    """Least CPU time of ``rounds`` calls of ``fn``, per tick (µs)."""
    best = float("inf")
    for _ in range(rounds):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best / ticks * 1e6


async def _best_async(fn: Callable[[], Awaitable[object]], rounds: int, ticks: int) -> float:
    best = float("inf")
    for _ in range(rounds):
        t0 = time.process_time()
        await fn()
        best = min(best, time.process_time() - t0)
    return best / ticks * 1e6


async def measure(robot_name: str, ticks: int, rounds: int) -> dict[str, float]:
    """CPU µs per tick of the three ways to hold ``robot_name`` (see the module documentation)."""
    async with agentsdk.connect("mujoco", robot=robot_name) as robot:
        b, loop = robot.backend, robot._loop
        m, d, nsub, n = b.model, b.data, b._nsub, len(b.names)
        await robot.command(JointCommand("position", (await robot.read()).position.tolist()))
        await robot.clock.sleep(0.2)  # the command's ramp (if any) has ended: a plain hold
        spv = loop.setpoint
        sdk = await _best_async(lambda: robot.clock.sleep(ticks * loop.period), rounds, ticks)

        def raw() -> None:
            for _ in range(ticks):
                b.write(spv)
                mujoco.mj_step(m, d, nstep=nsub)
                b.read()

        stepper = BlockStepper(b, ticks)
        readings = np.empty((ticks, 3, n))
        limit, gate = robot.safety._filter, loop.sensor_gate
        checks = list(robot.safety._watchdogs._checks)
        rows = np.broadcast_to(spv.position, (ticks, n))
        block_rows = np.stack([np.broadcast_to(r, (ticks, n)) for r in (spv.position, spv.velocity, spv.effort)],
                              axis=1)

        def block() -> None:
            stepper.run(lambda k: b.write(spv), ticks, readings)
            ts = (loop.clock.ticks + 1 + np.arange(ticks)) * loop.period  # the OBSERVE phase's times
            limit.block_quiet(block_rows, spv.mode, spv.enabled)
            if gate is not None:
                gate.block_quiet(ts, readings)
            for check in checks:
                check.block_quiet(ts, readings, rows)  # type: ignore[attr-defined]

        return {"tick-by-tick": sdk, "block": _best(block, rounds, ticks), "raw": _best(raw, rounds, ticks)}


def main() -> None:
    """Print the three figures and their ratios to the raw loop for each robot."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("robots", nargs="*", default=["arm3", "humanoid"])
    ap.add_argument("--ticks", type=int, default=500)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    for name in args.robots:
        r = asyncio.run(measure(name, args.ticks, args.rounds))
        raw = r["raw"]
        sdk, block = r["tick-by-tick"], r["block"]
        print(f"{name:10s} hold, CPU per tick: tick-by-tick {sdk:6.1f} µs ({sdk / raw:.2f}x raw)"
              f"  block {block:6.1f} µs ({block / raw:.2f}x raw)  raw {raw:6.1f} µs")


if __name__ == "__main__":
    main()
