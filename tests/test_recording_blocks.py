"""Recordings of block lockstep runs are byte-equal to tick-by-tick ones (issue 28 acceptance 4).

The same behavior (a hold, a follow of a multi-point trajectory, a direct command, a cancelled
follow and its stop ramp, an e-stop during a follow, then reset, enable and a hold) is recorded on
MuJoCo arm3 and humanoid (and on PyBullet, two of the cases) with block lockstep off and on; the two
files must be equal byte for byte, and the block run must actually have run blocks (the recorder's hook takes them:
:class:`agentsdk.block.BlockObserver`). The recorder's blocks are small (100 rows), so that its
hand-offs fall inside lockstep blocks; the wall-clock flush is either never due (hand-offs where
blocks fill only) or always due (a hand-off every 16th row, where the per-tick hook checks it),
so that both runs cut their chunks at the same ticks. The ``created`` metadata (the wall-clock
date) is fixed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk import JointCommand, Trajectory, TrajectoryPoint
from agentsdk.block import BlockObserver
from agentsdk.loop import Phase
from agentsdk.recording import Recorder, read_recording
from agentsdk.recording import _recorder as recorder_module

SAFETY = {"stall_timeout": None}
#: recorder rows per block: hand-offs inside the lockstep blocks (up to 128 ticks)
ROWS = 100


async def _behavior(robot: Any) -> None:
    names = list(robot.joint_names)
    n = len(names)
    lo = np.array([j.lower if np.isfinite(j.lower) else -1.0 for j in robot.joints])
    hi = np.array([j.upper if np.isfinite(j.upper) else 1.0 for j in robot.joints])
    lo, hi = lo + 0.2 * (hi - lo), hi - 0.2 * (hi - lo)
    rng = np.random.default_rng(7)

    def points(*times: float) -> list[TrajectoryPoint]:
        return [TrajectoryPoint(t, rng.uniform(lo, hi).tolist()) for t in times]

    await robot.clock.sleep(0.3)  # a hold
    await robot.follow(Trajectory(names, points(0.4, 0.8, 1.1)), stretch_to_limits=True)  # to its end and settled
    await robot.clock.sleep(0.1)
    goal = np.clip(np.asarray((await robot.read()).position) + rng.uniform(-0.1, 0.1, n), lo, hi)
    await robot.command(JointCommand("position", goal.tolist()))  # a direct command: the filter's ramp
    await robot.clock.sleep(0.2)
    motion = robot.follow(Trajectory(names, points(0.5, 1.0)), stretch_to_limits=True)
    await robot.clock.sleep(0.25)
    motion.cancel()  # its stop ramp
    await robot.clock.sleep(0.3)
    motion = robot.follow(Trajectory(names, points(0.5, 0.9)), stretch_to_limits=True)
    await robot.clock.sleep(0.2)
    await robot.estop(1)
    await robot.safety.wait_stopped()
    await robot.clock.sleep(0.1)
    await robot.reset()
    await robot.enable()
    await robot.clock.sleep(0.3)  # a hold again


async def _record(robot_name: str, path: Path, block: bool, rate: float | None,
                  backend: str = "mujoco") -> dict[str, Any]:
    async with agentsdk.connect(backend, robot=robot_name, safety=SAFETY) as robot:
        rec = Recorder(robot, path, rate=rate, block_ticks=ROWS, metadata={"created": "fixed"})
        runner = robot.block_lockstep(capacity=128) if block else None
        await _behavior(robot)
        ticks = robot.ticks
        hooks = robot._loop.hook_functions(Phase.OBSERVE)
        stats = {"ticks": ticks, "blocks": 0, "block_ticks": 0}
        if runner is not None:
            stats.update(blocks=runner.blocks, block_ticks=runner.block_ticks, rollbacks=runner.rollbacks)
            runner.close()
    rec.finish()
    stats.update(recorded=rec.ticks, dropped=rec.dropped_ticks, counts=rec.counts,
                 block_hook=any(isinstance(fn, BlockObserver) and getattr(fn, "_tick", None) == rec._on_tick
                                for fn in hooks))
    return stats


@pytest.mark.timeout(300)
@pytest.mark.parametrize(("robot_name", "rate", "flush", "backend"), [
    ("arm3", None, "never", "mujoco"), ("arm3", 50.0, "every 16 rows", "mujoco"),
    ("humanoid", None, "every 16 rows", "mujoco"), ("humanoid", 50.0, "never", "mujoco"),
    ("arm3", 50.0, "never", "pybullet"), ("humanoid", None, "every 16 rows", "pybullet"),
])
async def test_a_recording_with_blocks_is_byte_equal_to_the_tick_by_tick_one(
    robot_name: str, rate: float | None, flush: str, backend: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    if backend == "pybullet":
        pytest.importorskip("pybullet")
    monkeypatch.setattr(recorder_module, "FLUSH_INTERVAL", 1e9 if flush == "never" else -1.0)
    (tmp_path / "ticks").mkdir()
    (tmp_path / "blocks").mkdir()
    a, b = tmp_path / "ticks" / "run.mcap", tmp_path / "blocks" / "run.mcap"  # (the name is in the file)
    plain = await _record(robot_name, a, block=False, rate=rate, backend=backend)
    blocked = await _record(robot_name, b, block=True, rate=rate, backend=backend)
    # the block run ran blocks (the recorder did not force it tick by tick), and recorded every tick
    assert blocked["block_hook"]
    assert blocked["blocks"] > 10 and blocked["block_ticks"] > blocked["ticks"] // 2, blocked
    assert plain["ticks"] == blocked["ticks"] == plain["recorded"] == blocked["recorded"]
    assert plain["dropped"] == blocked["dropped"] == 0
    # the behavior reached the file: a stop and its events, many commands
    counts = plain["counts"]
    assert counts["/safety/events"] > 0 and counts["/joint_commands"] > 1000, counts
    data = read_recording(a)
    assert len(data.state_time) == (plain["ticks"] if rate is None else int(plain["ticks"] * 0.002 * rate) + 1)
    x, y = a.read_bytes(), b.read_bytes()
    if x != y:
        where = next(i for i, (p, q) in enumerate(zip(x, y, strict=False)) if p != q) if len(x) == len(y) else -1
        pytest.fail(f"{robot_name} on {backend}: the recordings differ ({len(x)} vs {len(y)} bytes, "
                    f"first difference at {where})")


class _WallClock:
    """The recorder module's ``time``, with a ``perf_counter`` that stands still or jumps ``step`` s per call."""

    def __init__(self, step: float) -> None:
        self.now, self.step = 0.0, step

    def perf_counter(self) -> float:
        self.now += self.step
        return self.now


@pytest.mark.timeout(300)
@pytest.mark.parametrize(("capacity", "flush"), [(128, None), (77, None), (77, 0.065)])
async def test_where_a_lockstep_recording_is_cut_does_not_depend_on_the_wall_clock(
    capacity: int, flush: float | None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The chunks of a lockstep recording end at the same ticks on a fast machine and a slow one.

    The default flush interval, whole-size blocks: the hand-offs besides the last are the flush's. One run
    tick by tick on a wall clock that stands still, one in blocks on a wall clock that jumps a second per
    reading: the files are equal byte for byte, and the flush cut the run (every FLUSH_INTERVAL of robot time,
    at a 16th row: the lockstep blocks, of two sizes, end elsewhere). A flush interval of 0.065 s falls due
    33 rows after a hand-off: at the 48th row, not the 32nd.
    """
    if flush is not None:
        monkeypatch.setattr(recorder_module, "FLUSH_INTERVAL", flush)
    handoffs: list[list[int]] = []
    handoff = Recorder._handoff

    def counted(self: Recorder, final: bool = False) -> None:
        handoffs[-1].append(self._k)
        handoff(self, final)

    monkeypatch.setattr(Recorder, "_handoff", counted)
    files, stats = [], []
    for block, step in ((False, 0.0), (True, 1.0)):
        monkeypatch.setattr(recorder_module, "time", _WallClock(step))
        path = tmp_path / ("blocks" if block else "ticks") / "run.mcap"  # (the name is in the file)
        path.parent.mkdir()
        handoffs.append([])
        async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
            rec = Recorder(robot, path, metadata={"created": "fixed"})
            runner = robot.block_lockstep(capacity=capacity) if block else None
            await _behavior(robot)
            stats.append((robot.ticks, robot.clock.now(), runner.blocks if runner is not None else 0))
        rec.finish()
        files.append(path.read_bytes())
    (ticks, t_end, _), (_, _, blocks) = stats
    assert blocks > 10, stats
    # a hand-off every FLUSH_INTERVAL of robot time, at a 16th row (the 0.5 s flush at 500 Hz: 256 rows; 0.065 s: 48)
    assert handoffs[0] == handoffs[1], handoffs
    period = t_end / ticks
    assert len(handoffs[0]) >= int(t_end / (recorder_module.FLUSH_INTERVAL + 16 * period)) - 1, (handoffs, t_end)
    assert all(k % 16 == 0 for k in handoffs[0][:-1]), handoffs
    assert files[0] == files[1]


async def test_a_recorder_of_sensors_keeps_the_per_tick_hook(tmp_path: Path) -> None:
    """Sensor samples exist only in the tick: with recorded sensors the hook takes no blocks."""
    arm = Path(__file__).parent / "fixtures" / "sensor_arm" / "nocam.yaml"
    async with agentsdk.connect("mujoco", arm, safety=SAFETY) as robot:
        rec = Recorder(robot, tmp_path / "run.mcap")
        assert rec.sensor_tracks
        hooks = robot._loop.hook_functions(Phase.OBSERVE)
        assert rec._on_tick in hooks and not any(isinstance(fn, BlockObserver) for fn in hooks)
        await robot.clock.sleep(0.01)
    rec.finish()
