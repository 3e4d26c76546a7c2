"""Recordings you can watch and that survive a crash (issue 15 items 3-4, issue 10 items 11 and 18).

* the default format carries every link's transform (``tf2_msgs/msg/TFMessage`` on ``/tf``)
  and the URDF (``/robot_description``), read back with the ``mcap`` reader;
* ``--record-format ros2`` is read back by ``rosbags`` (an independent rosbag2 implementation):
  joint values and transforms;
* a SIGKILLed ``agentsdk run --record`` leaves a file readable up to its last chunk;
* ``keep=True`` reads back from the file instead of growing in memory;
* plots of trajectory runs show the real targets.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

import agentsdk
from agentsdk import Trajectory, TrajectoryPoint
from agentsdk.cli import main
from agentsdk.recording import Recorder, read_recording

pytestmark = pytest.mark.timeout(120)


def _messages(path: Path, topic: str) -> list[tuple[int, Any]]:
    """Messages of a standard ROS 2 type, decoded by rosbags (an independent CDR implementation)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    with open(path, "rb") as f:
        reader = make_reader(f)
        messages = reader.iter_messages(topics=[topic])
        return [(m.log_time, store.deserialize_cdr(m.data, s.name)) for s, _c, m in messages]


def _summary(path: Path):
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return summary


async def _wave(robot: agentsdk.Robot) -> None:
    await robot.move_to({"joint1": 0.6, "joint2": 0.4, "joint3": -0.5}, duration=0.8)
    await robot.move_to({"joint1": -0.3, "joint2": 0.9, "joint3": 0.2}, duration=0.8)


async def test_default_recording_has_transform_and_description_channels(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        rec = Recorder.attach(robot, path)
        await _wave(robot)
        kin = robot.kinematics
    rec.finish()
    summary = _summary(path)
    schemas = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
    assert schemas["/tf"] == "tf2_msgs/msg/TFMessage"
    assert schemas["/robot_description"] == "std_msgs/msg/String"
    (_t0, desc), = _messages(path, "/robot_description")
    assert '<robot name="arm3"' in desc.data
    tfs = _messages(path, "/tf")
    assert len(tfs) >= 35  # 1.6 s at 25 Hz
    data = read_recording(path)
    children = {link for link, parent in kin.parents.items()}
    for log_time, msg in tfs[:: max(1, len(tfs) // 10)]:
        # each TF sample is stamped like a joint state it comes from (25 Hz samples of the 50 Hz states)
        (row,) = np.flatnonzero(data.state_time == log_time)
        poses = kin.link_poses(data.position[row])
        assert {tr.child_frame_id for tr in msg.transforms} == children
        for tr in msg.transforms:
            assert tr.header.stamp.sec * 10**9 + tr.header.stamp.nanosec == log_time
            ref = poses.relative(tr.child_frame_id, tr.header.frame_id)
            got = tr.transform.translation
            np.testing.assert_allclose([got.x, got.y, got.z], ref.position, atol=1e-9)
            r = tr.transform.rotation
            dot = abs(np.dot([r.x, r.y, r.z, r.w], ref.orientation))
            assert dot == pytest.approx(1.0, abs=1e-9)
    # the joints move: the transform of the first joint's child changes over the run
    first = [m.transforms[-1].transform.rotation.w for _t, m in tfs]
    assert max(first) - min(first) > 1e-3


async def test_ros2_format_is_read_back_by_rosbags(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    path = tmp_path / "run.mcap"
    async with agentsdk.connect("mock", robot="arm3") as robot:
        rec = Recorder.attach(robot, path, format="ros2", keep=True)
        await _wave(robot)
        kin = robot.kinematics
        names = robot.joint_names
    rec.finish()
    ref = rec.data()  # the agentsdk-format copy of the same run
    store = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(path) as bag:
        types = {c.topic: c.msgtype for c in bag.connections}
        assert types["/joint_states"] == "sensor_msgs/msg/JointState"
        assert types["/tf"] == "tf2_msgs/msg/TFMessage"
        js, tf = {}, []
        for conn, t, raw in bag.messages():
            msg = store.deserialize_cdr(raw, conn.msgtype)
            if conn.topic == "/joint_states":
                assert list(msg.name) == list(names)
                assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == t
                js[t] = msg
            elif conn.topic == "/tf":
                tf.append((t, msg))
            elif conn.topic == "/robot_description":
                assert "<robot" in msg.data
    assert sorted(js) == ref.state_time.tolist()
    pos = np.array([js[t].position for t in ref.state_time.tolist()])
    vel = np.array([js[t].velocity for t in ref.state_time.tolist()])
    np.testing.assert_array_equal(pos, ref.position)
    np.testing.assert_array_equal(vel, ref.velocity)
    assert np.ptp(pos[:, 0]) > 0.5  # the values are the run's, not zeros
    assert len(tf) >= 35  # 1.6 s at 25 Hz
    for t, msg in tf[::10]:
        poses = kin.link_poses(js[t].position)
        for ts in msg.transforms:
            rel = poses.relative(ts.child_frame_id, ts.header.frame_id)
            tr = ts.transform.translation
            np.testing.assert_allclose([tr.x, tr.y, tr.z], rel.position, atol=1e-9)
            r = ts.transform.rotation
            assert abs(np.dot([r.x, r.y, r.z, r.w], rel.orientation)) == pytest.approx(1.0, abs=1e-9)


LONG_BEHAVIOR = """
    import math
    from agentsdk import JointCommand

    ROBOT = "arm3"

    async def main(robot):
        t = 0.0
        while True:  # runs until killed
            t += robot.control_period
            await robot.command(JointCommand("position", {"joint1": 0.5 * math.sin(t)}))
            await robot.clock.sleep(robot.control_period)
"""


def test_sigkilled_recording_is_readable_up_to_its_last_chunk(tmp_path: Path) -> None:
    behavior = tmp_path / "forever.py"
    behavior.write_text(textwrap.dedent(LONG_BEHAVIOR))
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "agentsdk", "run", str(behavior), "--backend", "mock", "--record", str(path), "-q"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        # wait (event-driven on the file, not a timing threshold) until a few chunks are on disk
        # (compressed chunks of a fast lockstep run are tens of kB: wait for three of them after
        # the first write, so that cutting the last one still leaves data to read)
        deadline = time.monotonic() + 60
        sizes: set[int] = set()
        while time.monotonic() < deadline and proc.poll() is None:
            if path.exists():
                sizes.add(path.stat().st_size)
            if len(sizes - {0}) >= 4 and max(sizes) > 30_000:
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
        if proc.stderr:
            proc.stderr.close()
    assert path.stat().st_size > 30_000
    data = read_recording(path)
    assert data.truncated
    assert data.duration > 1.0
    assert len(data.state_time) == round(data.duration * 50)  # every 50 Hz sample up to the cut
    assert np.all(np.diff(data.state_time) > 0)
    assert np.ptp(data.position[:, 0]) > 0.3
    # a file cut in the middle of a record is read too (what a kill during a write leaves)
    cut = tmp_path / "cut.mcap"
    raw = path.read_bytes()
    cut.write_bytes(raw[: len(raw) - 1000])
    partial = read_recording(cut)
    assert partial.truncated and 0 < len(partial.state_time) <= len(data.state_time)
    # `agentsdk replay` recovers it too
    rc = main(["replay", str(cut), "-q"])
    assert rc == 0


async def test_keep_true_memory_does_not_grow_with_the_run() -> None:
    # tracemalloc slows every allocation several times: the stall watchdog (wall clock) is off here
    async with agentsdk.connect("mock", robot="arm3", safety={"stall_timeout": None}) as robot:
        rec = Recorder.attach(robot, keep=True, tf_rate=None, rate=None)  # every tick
        try:
            async def run(seconds: float) -> None:
                traj = Trajectory(
                    joint_names=("joint1",),
                    points=[TrajectoryPoint(positions=[0.0], time_from_start=0.0),
                            TrajectoryPoint(positions=[0.5], time_from_start=seconds / 2),
                            TrajectoryPoint(positions=[0.0], time_from_start=seconds)],
                )
                await robot.follow(traj)

            await run(4.0)
            # both snapshots are taken with the writer caught up: what it holds while it encodes a
            # block (a few hundred KiB, how much depends on how far behind a loaded machine makes it)
            # is bounded by the block pool and is not what this test is about
            await rec.flush()
            tracemalloc.start()
            try:
                before = tracemalloc.take_snapshot()
                await run(40.0)  # 20 000 ticks: ~5 MB of rows if they were kept in memory
                await rec.flush()
                after = tracemalloc.take_snapshot()
            finally:
                tracemalloc.stop()
            stats = [s for s in after.compare_to(before, "lineno") if "recording" in str(s.traceback)]
            grown = sum(s.size_diff for s in stats)
            assert grown < 1_000_000, [str(s) for s in stats[:5]]
        finally:
            await robot.close()
            rec.finish()
    data = rec.data()
    assert len(data.state_time) == rec.ticks
    assert np.ptp(data.position[:, 0]) > 0.4


async def test_flush_puts_the_run_so_far_in_the_file(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    async with agentsdk.connect("mock", robot="arm3") as robot:
        rec = Recorder.attach(robot, path=path, tf_rate=None, rate=None)
        try:
            await robot.move_to({"joint1": 0.6})
            await rec.flush()
            ticks = rec.ticks
            data = read_recording(path)  # read by another reader while the recording goes on
            assert data.truncated  # no summary yet: the file is still being written
            assert len(data.state_time) >= ticks - 1  # the tick of the call itself may be in flight
            assert data.position[-1, 0] == pytest.approx(0.6, abs=0.02)
            await robot.move_to({"joint1": 0.0})
        finally:
            await robot.close()
            rec.finish()
        await rec.flush()  # after finish: nothing left to do
    data = read_recording(path)
    assert not data.truncated and len(data.state_time) == rec.ticks
    assert data.position[-1, 0] == pytest.approx(0.0, abs=0.02)


async def test_plot_of_a_trajectory_run_shows_its_targets(tmp_path: Path) -> None:
    from agentsdk.plot import plot_run

    async with agentsdk.connect("mock", robot="arm3") as robot:
        rec = Recorder.attach(robot, keep=True, tf_rate=None)
        traj = Trajectory(
            joint_names=("joint1", "joint2"),
            points=[TrajectoryPoint(positions=[0.8, 0.4], time_from_start=2.0),
                    TrajectoryPoint(positions=[-0.5, 0.9], time_from_start=4.0)],
        )
        await robot.follow(traj)
    rec.finish()
    data = rec.data()
    moving = data.cmd_time > 0.1e9
    # the recorded target is the trajectory's reference (what the loop drives towards), not 0
    np.testing.assert_allclose(data.cmd_target[moving, :2], data.cmd_position[moving, :2])
    assert np.ptp(data.cmd_target[:, 0]) > 1.0
    fig = plot_run(data, tmp_path / "traj.png")
    for ax, name in zip(fig.axes[:2], ("joint1", "joint2"), strict=True):
        for line in ax.get_lines():
            y = np.asarray(line.get_ydata(), dtype=float)
            y = y[np.isfinite(y)]
            # no flat line at 0 rad: every curve follows the trajectory
            assert np.ptp(y) > 0.3, (name, line.get_label())


async def test_block_boundaries_do_not_change_the_recorded_commands() -> None:
    """Blocks are cut by the wall clock (crash safety): where they fall must not change the content."""
    runs = []
    for block in (4096, 7):
        async with agentsdk.connect("mock", robot="arm3") as robot:
            rec = Recorder(robot, keep=True, tf_rate=None, block_ticks=block)
            await _wave(robot)
            await robot.clock.sleep(0.3)  # a hold at the end
        rec.finish()
        runs.append(rec.data())
    a, b = runs
    np.testing.assert_array_equal(a.cmd_time, b.cmd_time)
    np.testing.assert_array_equal(a.cmd_position, b.cmd_position)
    np.testing.assert_array_equal(a.state_time, b.state_time)
    np.testing.assert_array_equal(a.desired_position(), b.desired_position())
    assert a.cmd_time[-1] == a.state_time[-1] - round(a.period * 1e9)  # the last tick's setpoint is kept
