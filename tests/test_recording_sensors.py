"""Sensors in recordings (issue 25 item 5): ``/sensors/<name>`` topics as their ROS messages, read back,
decoded by rosbags, plotted. Lockstep MuJoCo on the sensor_arm fixture (a guarded move down to the table)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk.loop import Phase
from agentsdk.recording import Recorder, read_recording
from agentsdk.sensors import force_above

pytestmark = pytest.mark.timeout(300)

FIXTURES = Path(__file__).parent / "fixtures"
ARM = FIXTURES / "sensor_arm" / "nocam.yaml"
ARM_CAM = FIXTURES / "sensor_arm" / "robot.yaml"
SAFETY = {"stall_timeout": 5.0}
KINDS = {"wrist_ft": "force_torque", "tool_contact": "contact", "carriage_imu": "imu",
         "lift_position": "joint_position", "height": "rangefinder"}
TYPES = {"wrist_ft": "geometry_msgs/msg/WrenchStamped", "tool_contact": "agentsdk_msgs/msg/Contact",
         "carriage_imu": "sensor_msgs/msg/Imu", "lift_position": "agentsdk_msgs/msg/JointSensor",
         "height": "sensor_msgs/msg/Range"}


async def _guarded_run(path: Path, **rec: Any) -> tuple[dict[str, dict[int, np.ndarray]], Recorder]:
    """Record a guarded move down to the table; returns every tick's published sensor values by stamp."""
    seen: dict[str, dict[int, np.ndarray]] = {n: {} for n in KINDS}
    async with agentsdk.connect("mujoco", ARM, safety=SAFETY) as robot:
        recorder = Recorder.attach(robot, path, **rec)

        def watch(t: float, st: object, sp: object) -> None:
            for name in KINDS:
                seen[name][round(robot.sensors.stamp(name) * 1e9)] = robot.sensors.values(name).copy()

        robot.add_tick_hook(Phase.OBSERVE, watch, order=500)
        await robot.move_to({"lift": 0.3}, 0.3)
        result = await robot.move_to({"lift": 0.1}, 3.0, until=force_above("wrist_ft", 5.0, tare=True))
        assert result.ok and "force_above" in result.message
        await robot.clock.sleep(0.2)
    recorder.finish()
    return seen, recorder


async def test_sensors_recorded_at_their_stamps_and_read_back(tmp_path: Path) -> None:
    path = tmp_path / "guarded.mcap"
    seen, rec = await _guarded_run(path)
    data = read_recording(path)
    assert set(data.sensors) == set(KINDS)
    for name, series in data.sensors.items():
        assert series.type == KINDS[name] and series.msg_type == TYPES[name]
        assert rec.counts[f"/sensors/{name}"] == len(series.time) > 0
        # bounded: at most the sensor record rate (50 Hz) over the run
        assert len(series.time) <= data.duration * 50 + 2
        assert np.all(np.diff(series.time) > 0)
        for t, v in zip(series.time.tolist(), series.values, strict=True):
            want = seen[name][t]
            if name == "height":  # sensor_msgs/Range stores float32
                np.testing.assert_allclose(v, want.astype(np.float32), rtol=0, atol=0)
            else:
                np.testing.assert_array_equal(v, want)
    # the guarded move pressed on the table: the recording shows the force and the contact
    ft = data.sensors["wrist_ft"].values
    assert np.abs(ft[:, 2]).max() > 5.0 * 0.5  # well above the noise-free rest reading's change
    assert data.sensors["tool_contact"].values[:, 1].max() >= 1
    assert data.sensors["wrist_ft"].frame_id == "tool"
    # the joint states are unchanged by the sensors
    assert len(data.state_time) and data.names == ("yaw", "lift")


async def test_sensor_rate_bounds_messages_and_slower_sensors_write_each_sample_once(tmp_path: Path) -> None:
    path = tmp_path / "fast.mcap"
    seen, _ = await _guarded_run(path, sensor_rate=100.0)
    data = read_recording(path)
    ft = data.sensors["wrist_ft"].time  # a 500 Hz sensor, recorded at 100 Hz
    assert data.duration * 100 - 2 <= len(ft) <= data.duration * 100 + 2
    for name, series in data.sensors.items():
        assert len(np.unique(series.time)) == len(series.time), name
        assert set(series.time.tolist()) <= set(seen[name]), name


def _rosbags_store(path: Path) -> Any:
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    store = get_typestore(Stores.EMPTY)
    for schema in summary.schemas.values():
        store.register(get_types_from_msg(schema.data.decode().split("=" * 80)[0], schema.name))
        text = schema.data.decode()
        for part in text.split("=" * 80 + "\n")[1:]:
            head, _, body = part.partition("\n")
            name = head.removeprefix("MSG: ")
            full = name.replace("/", "/msg/", 1) if "/msg/" not in name else name
            store.register(get_types_from_msg(body, full))
    return store


@pytest.mark.parametrize("fmt", ["mcap", "ros2"])
async def test_rosbags_decodes_the_sensor_messages(tmp_path: Path, fmt: str) -> None:
    from rosbags.rosbag2 import Reader

    path = tmp_path / f"guarded-{fmt}.mcap"
    seen, _ = await _guarded_run(path, format=fmt)
    store = _rosbags_store(path)
    got: dict[str, list[Any]] = {}
    with Reader(path) as bag:
        for conn, _t, raw in bag.messages():
            if conn.topic.startswith("/sensors/"):
                got.setdefault(conn.topic.removeprefix("/sensors/"), []).append(
                    store.deserialize_cdr(raw, conn.msgtype))
    # the ros2 format has only the standard message types
    want = set(KINDS) if fmt == "mcap" else {"wrist_ft", "carriage_imu", "height"}
    assert set(got) == want
    for msg in got["wrist_ft"]:
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        v = seen["wrist_ft"][stamp]
        f, tq = msg.wrench.force, msg.wrench.torque
        assert [f.x, f.y, f.z, tq.x, tq.y, tq.z] == v.tolist()
        assert msg.header.frame_id == "tool"
    for msg in got["carriage_imu"]:
        v = seen["carriage_imu"][msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec]
        o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
        assert [o.x, o.y, o.z, o.w, w.x, w.y, w.z, a.x, a.y, a.z] == v.tolist()
        assert len(msg.orientation_covariance) == 9
    for msg in got["height"]:
        v = seen["height"][msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec]
        assert msg.range == pytest.approx(float(v[0]), rel=1e-6) and msg.max_range == 2.0
    if fmt == "mcap":
        for msg in got["tool_contact"]:
            v = seen["tool_contact"][msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec]
            assert (msg.force, msg.contacts) == (v[0], int(v[1]))
        for msg in got["lift_position"]:
            v = seen["lift_position"][msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec]
            assert (msg.joint, msg.value) == ("lift", v[0])


async def test_plot_has_a_panel_per_sensor(tmp_path: Path) -> None:
    from agentsdk.plot import plot_run

    path = tmp_path / "guarded.mcap"
    await _guarded_run(path)
    data = read_recording(path)
    png = tmp_path / "run.png"
    fig = plot_run(data, png)
    assert len(fig.axes) == len(data.names) + 1 + len(data.sensors)
    labels = [ax.get_ylabel() for ax in fig.axes]
    for name in KINDS:
        assert any(lbl.startswith(name) for lbl in labels), (name, labels)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


async def test_a_robot_without_sensors_records_no_sensor_channels(tmp_path: Path) -> None:
    path = tmp_path / "plain.mcap"
    async with agentsdk.connect("mujoco", "arm3") as robot:
        assert len(robot.sensors) == 0
        rec = Recorder.attach(robot, path)
        await robot.move_to({robot.joint_names[0]: 0.2}, 0.5)
    rec.finish()
    data = read_recording(path)
    assert data.sensors == {}
    assert "sensors" not in data.metadata
    assert not any(topic.startswith("/sensors/") for topic in rec.counts)
    assert math.isfinite(data.duration)


def test_the_tick_hook_with_sensors_allocates_nothing_between_hand_offs(monkeypatch: pytest.MonkeyPatch) -> None:
    import asyncio
    import tracemalloc

    from agentsdk.recording import _recorder as recorder_module

    monkeypatch.setattr(recorder_module, "FLUSH_INTERVAL", 1e9)  # no wall-clock hand-off in the window

    async def run() -> tuple[int, list[str]]:
        async with agentsdk.connect("mujoco", ARM, safety={"stall_timeout": None}) as robot:
            rec = Recorder.attach(robot, keep=True, tf_rate=None)
            assert len(rec.sensor_tracks) == 5
            await robot.clock.sleep(0.1)
            tracemalloc.start()
            try:
                before = tracemalloc.take_snapshot()
                for _ in range(200):  # 200 ticks: inside one block
                    await robot.clock.sleep(robot.control_period)
                after = tracemalloc.take_snapshot()
            finally:
                tracemalloc.stop()
            where = [str(s) for s in after.compare_to(before, "lineno")
                     if "_recorder.py" in str(s.traceback) and s.size_diff > 0]
            k = rec._k
        rec.finish()
        return k, where

    k, where = asyncio.run(run())
    assert k > 200  # no hand-off happened in the measured window
    assert where == []


async def test_lidar_scans_recorded_as_laser_scans(tmp_path: Path) -> None:
    import yaml
    from rosbags.rosbag2 import Reader

    data = yaml.safe_load(ARM.read_text())
    data["description"] = str(FIXTURES / "sensor_arm" / "sensor_arm.urdf")
    data["sensors"] = [{
        "name": "scan", "type": "lidar", "link": "carriage", "xyz": [0.1, 0.0, 0.0],
        "rpy": [0.0, 1.5707963267948966, 0.0], "rate": 20.0,
        "ray": {"samples": 21, "min_angle": -0.6, "max_angle": 0.6, "range_max": 0.3},
    }]
    robot_yaml = tmp_path / "robot.yaml"
    robot_yaml.write_text(yaml.safe_dump(data))
    path = tmp_path / "scan.mcap"
    seen: dict[int, np.ndarray] = {}
    async with agentsdk.connect("mujoco", robot_yaml, safety=SAFETY) as robot:
        rec = Recorder.attach(robot, path)
        robot.add_tick_hook(Phase.OBSERVE, lambda t, st, sp: seen.__setitem__(
            round(robot.sensors.stamp("scan") * 1e9), robot.sensors.values("scan").copy()), order=500)
        await robot.move_to({"lift": 0.36}, 1.0)  # the scan's edge rays leave its 0.3 m range
    rec.finish()
    run = read_recording(path)
    scan = run.sensors["scan"]
    assert scan.msg_type == "sensor_msgs/msg/LaserScan" and scan.values.shape[1] == 21
    # a 20 Hz sensor under the 50 Hz sensor rate: every sample, once
    assert abs(len(scan.time) - run.duration * 20) <= 2
    for t, v in zip(scan.time.tolist(), scan.values, strict=True):
        np.testing.assert_array_equal(v, seen[t].astype(np.float32))
    assert np.isinf(scan.values).any() and np.isfinite(scan.values).any()
    store = _rosbags_store(path)
    with Reader(path) as bag:
        msgs = [store.deserialize_cdr(raw, c.msgtype) for c, _t, raw in bag.messages() if c.topic == "/sensors/scan"]
    assert len(msgs) == len(scan.time)
    m = msgs[0]
    assert (m.angle_min, m.angle_max, m.range_max) == pytest.approx((-0.6, 0.6, 0.3))
    assert m.angle_increment == pytest.approx(0.06) and m.scan_time == pytest.approx(0.05)
    np.testing.assert_array_equal(m.ranges, scan.values[0].astype(np.float32))


def test_cli_plot_and_record_of_the_guarded_move(tmp_path: Path) -> None:
    from agentsdk.cli import main

    behavior = Path(__file__).resolve().parents[1] / "behaviors" / "guarded_move.py"
    png, rec = tmp_path / "guarded.png", tmp_path / "guarded.mcap"
    assert main(["run", str(behavior), "--record", str(rec), "--plot", str(png), "-q"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = read_recording(rec)
    assert "wrist_ft" in data.sensors and len(data.sensors["wrist_ft"].time) > 10
    # the plot is as tall as the joint, error and sensor panels need (one panel per sensor)
    from matplotlib.image import imread

    height = imread(png).shape[0]
    assert height >= 100 * 1.9 * (len(data.names) + 1 + len(data.sensors))


@pytest.mark.parametrize("image_format", ["png", "jpeg"])
async def test_camera_frames_recorded_compressed_at_the_camera_rate(tmp_path: Path, image_format: str) -> None:
    from rosbags.rosbag2 import Reader

    path = tmp_path / f"cam-{image_format}.mcap"
    frames: dict[int, np.ndarray] = {}
    async with agentsdk.connect("mujoco", ARM_CAM, safety={"stall_timeout": None}) as robot:
        rec = Recorder.attach(robot, path, camera_rate=10.0, image_format=image_format)

        def watch(t: float, st: object, sp: object) -> None:
            stamp = round(robot.sensors.stamp("overhead") * 1e9)
            if stamp not in frames:
                frames[stamp] = robot.sensors.read("overhead").data  # type: ignore[union-attr]

        robot.add_tick_hook(Phase.OBSERVE, watch, order=500)
        await robot.move_to({"lift": 0.2, "yaw": 0.5}, 1.5)
    rec.finish()
    assert rec.dropped_frames == 0
    data = read_recording(path)
    assert "overhead" not in data.sensors  # images are not sensor series
    cam = data.images["overhead"]
    assert cam.format == image_format and cam.frame_id == "world"
    assert abs(len(cam.time) - data.duration * 10) <= 2  # 10 Hz of a 50 Hz camera
    assert np.all(np.diff(cam.time) > 0)
    for i, t in enumerate(cam.time.tolist()):
        img = cam.frame(i)
        assert img.shape == (240, 320, 3)
        if image_format == "png":  # lossless
            np.testing.assert_array_equal(img, frames[t])
        else:
            assert np.abs(img.astype(float) - frames[t]).mean() < 4.0
    # compression made them small
    assert max(len(b) for b in cam.data) < 240 * 320 * 3 / 2
    store = _rosbags_store(path)
    with Reader(path) as bag:
        msgs = [store.deserialize_cdr(raw, c.msgtype) for c, _t, raw in bag.messages()
                if c.topic == "/sensors/overhead"]
    assert [m.format for m in msgs] == [image_format] * len(cam.time)
    assert bytes(msgs[0].data) == cam.data[0]
    assert msgs[0].header.stamp.sec * 10**9 + msgs[0].header.stamp.nanosec == cam.time[0]


async def test_camera_rate_zero_records_no_images(tmp_path: Path) -> None:
    path = tmp_path / "nocam.mcap"
    async with agentsdk.connect("mujoco", ARM_CAM, safety={"stall_timeout": None}) as robot:
        rec = Recorder.attach(robot, path, camera_rate=0)
        await robot.clock.sleep(0.3)
    rec.finish()
    data = read_recording(path)
    assert data.images == {} and "/sensors/overhead" not in rec.counts and "wrist_ft" in data.sensors
