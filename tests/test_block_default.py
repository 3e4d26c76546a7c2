"""Block lockstep is on by default (issue 28 item 1): a plain ``connect`` in lockstep runs blocks (MuJoCo, PyBullet).

``connect(..., block_lockstep=False)`` (``agentsdk run --no-block-lockstep``) turns it off: no runner,
every tick on its own. Both ways the same short program (a hold, a move, a cancelled move, a hold)
gives the same per-tick times, setpoints and states (hashed by an OBSERVE hook that takes blocks),
the same results and the same safety events.
"""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk import Phase, Trajectory, TrajectoryPoint
from agentsdk.errors import ConfigurationError


class _Hasher:
    """sha256 of every tick's time, setpoint rows and measured state; takes blocks (``BlockObserver``)."""

    def __init__(self) -> None:
        self.h = hashlib.sha256()
        self.ticks = 0

    def __call__(self, t: float, st: Any, sp: Any) -> None:
        rows = (sp.position, sp.velocity, sp.effort, sp.kp, sp.kd, sp.target, sp.acceleration)
        self._one(t, rows, sp, st.position, st.velocity, st.effort)

    def observe_block(self, ts: np.ndarray, states: np.ndarray, rows: np.ndarray, sp: Any) -> None:
        for k in range(len(ts)):
            self._one(float(ts[k]), rows[k], sp, states[k, 0], states[k, 1], states[k, 2])

    def _one(self, t: float, rows: Any, sp: Any, q: np.ndarray, v: np.ndarray, e: np.ndarray) -> None:
        self.h.update(np.float64(t).tobytes())
        for a in (*rows, sp.enabled, sp.mode, q, v, e):
            self.h.update(np.ascontiguousarray(a).tobytes())
        self.ticks += 1


async def _run(robot_name: str, backend: str = "mujoco",
               **kwargs: Any) -> tuple[tuple[Any, ...], dict[str, int] | None]:
    async with agentsdk.connect(backend, robot=robot_name, **kwargs) as robot:
        runner = robot.block_runner
        hasher = _Hasher()
        robot.add_tick_hook(Phase.OBSERVE, hasher, order=1 << 30)
        names = list(robot.joint_names)
        q0 = np.asarray((await robot.read()).position)
        lo = np.array([j.lower if np.isfinite(j.lower) else -1.0 for j in robot.joints])
        hi = np.array([j.upper if np.isfinite(j.upper) else 1.0 for j in robot.joints])
        goal = np.clip(q0 + 0.3, lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo))
        await robot.clock.sleep(0.3)  # a hold
        held = None if runner is None else runner.block_ticks
        plan = Trajectory(names, [TrajectoryPoint(0.8, goal.tolist())])
        first = await robot.follow(plan, stretch_to_limits=True)
        back = Trajectory(names, [TrajectoryPoint(1.0, q0.tolist())])
        m = robot.follow(back, stretch_to_limits=True)
        await robot.clock.sleep(0.4)
        m.cancel()
        second = await m
        await robot.clock.sleep(0.3)
        final = await robot.read()
        results = [(r.code.name, r.message, r.time, sorted(r.error.items())) for r in (first, second)]
        events = [(e.kind, e.detail, e.time) for e in robot.safety.events]
        stats = None
        if runner is not None:
            assert robot.block_runner is runner
            stats = {"held": held or 0, "blocks": runner.blocks, "block_ticks": runner.block_ticks,
                     "motion_ticks": runner.motion_ticks}
        out = (hasher.h.hexdigest(), hasher.ticks, robot.clock.ticks, results, events,
               final.position.tobytes(), final.velocity.tobytes(), final.effort.tobytes())
    assert robot.block_runner is None  # closed with the robot
    return out, stats


@pytest.mark.parametrize("robot_name", ["arm3", "humanoid"])
@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
async def test_a_plain_connect_runs_blocks_and_the_opt_out_does_not_bit_for_bit(robot_name: str, backend: str) -> None:
    if backend == "pybullet":
        pytest.importorskip("pybullet")
    on, stats = await _run(robot_name, backend)
    off, none = await _run(robot_name, backend, block_lockstep=False)
    assert none is None  # opted out: no runner
    assert stats is not None and stats["held"] > 0 and stats["motion_ticks"] > 0 and stats["blocks"] > 1, stats
    assert on == off
    # the blocks did most of the work: the hold and the moves' middles
    assert stats["block_ticks"] > on[1] // 2, (stats, on[1])


async def test_realtime_robots_run_without_blocks_and_a_bad_opt_out_is_refused() -> None:
    async with agentsdk.connect("mujoco", robot="arm3", realtime=True) as robot:
        assert robot.block_runner is None
    with pytest.raises(ConfigurationError, match="block_lockstep"):
        async with agentsdk.connect("mujoco", robot="arm3", block_lockstep="no"):  # type: ignore[arg-type]
            pass


@pytest.mark.parametrize("flag", [[], ["--no-block-lockstep"], ["-o", "block_lockstep=false"]])
def test_agentsdk_run_has_blocks_unless_told_not_to(tmp_path: Path, flag: list[str]) -> None:
    behavior = tmp_path / "probe.py"
    behavior.write_text(
        "async def main(robot):\n"
        "    await robot.clock.sleep(0.2)\n"
        "    runner = robot.block_runner\n"
        "    print('blocks' if runner is not None and runner.block_ticks > 0 else 'none')\n"
    )
    proc = subprocess.run([sys.executable, "-m", "agentsdk", "run", str(behavior), "-q", *flag],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == ("blocks\n" if not flag else "none\n")


async def test_a_replaced_backend_step_is_not_bypassed_by_blocks() -> None:
    """A block steps MuJoCo itself: where the backend's ``_step`` was replaced, every tick goes through it."""
    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        runner = robot.block_runner
        assert runner is not None
        await robot.clock.sleep(0.2)
        ran = runner.block_ticks
        assert ran > 0
        b = robot.backend
        original = b._step
        calls = 0

        async def counting_step(dt: float) -> None:
            nonlocal calls
            calls += 1
            await original(dt)

        b._step = counting_step  # type: ignore[method-assign]
        ticks = robot.clock.ticks
        await robot.clock.sleep(0.3)
        assert calls == robot.clock.ticks - ticks > 100
        assert runner.block_ticks == ran
        del b._step  # the backend's own again: blocks again
        await robot.clock.sleep(0.3)
        assert runner.block_ticks > ran
