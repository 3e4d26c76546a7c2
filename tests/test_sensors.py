"""Sensors (issue 25): declaration, reading on MuJoCo and PyBullet with the same conventions, realism,
safety limits and guarded moves. Lockstep and deterministic; analytic expected values."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import agentsdk
from agentsdk import ConfigurationError, InvalidValueError
from agentsdk.description import resolve_robot
from agentsdk.loop import Phase
from agentsdk.motion import ResultCode
from agentsdk.sensors import (
    ContactState,
    Imu,
    JointSensorReading,
    Range,
    UnknownSensorError,
    Vector3Stamped,
    WrenchStamped,
    contact,
    declared_sensors,
    force_above,
)

pytestmark = pytest.mark.timeout(300)

FIXTURES = Path(__file__).parent / "fixtures"
ARM = FIXTURES / "sensor_arm" / "nocam.yaml"
ARM_CAM = FIXTURES / "sensor_arm" / "robot.yaml"
SIMS = ["mujoco", "pybullet"]
G = 9.81
PAYLOAD = 0.5  # kg, the sensor_arm's tool
CONTACT_LIFT = 0.18  # lift position at which the tool (r 0.03, 0.05 below the sensor) touches the table top (0.10)
SAFETY = {"stall_timeout": 5.0}


# --------------------------------------------------------------------------- declaring
def test_declared_from_gazebo_ros2_control_and_robot_yaml() -> None:
    config, description = resolve_robot(ARM_CAM)
    specs = {s.name: s for s in declared_sensors(description, config)}
    assert [(s.kind, s.link, s.joint, s.source) for s in specs.values()] == [
        ("force_torque", "tool", "ft_joint", "gazebo"),
        ("contact", "tool", None, "gazebo"),
        ("imu", "carriage", None, "ros2_control"),
        ("camera", "world", None, "robot.yaml"),
        ("joint_position", "carriage", "lift", "robot.yaml"),
        ("rangefinder", "carriage", None, "robot.yaml"),
    ]
    assert list(specs) == ["wrist_ft", "tool_contact", "carriage_imu", "overhead", "lift_position", "height"]
    cam = specs["overhead"].camera
    assert cam is not None and (cam.width, cam.height, cam.depth) == (320, 240, True)
    assert specs["wrist_ft"].rate == 500.0


def test_declared_from_mjcf_sensor_elements() -> None:
    config, description = resolve_robot(FIXTURES / "mjcf_sensors" / "sensors.xml")
    kinds = {s.name: (s.kind, s.link, s.joint) for s in declared_sensors(description, config)}
    assert kinds == {
        "acc": ("accelerometer", "post", None),
        "gyro": ("gyro", "post", None),
        "quat": ("orientation", "post", None),
        "hand_force": ("force", "hand", None),
        "hand_torque": ("torque", "hand", None),
        "floor_range": ("rangefinder", "post", None),
        "swing_pos": ("joint_position", "post", "swing"),
        "swing_vel": ("joint_velocity", "post", "swing"),
        "swing_torque": ("joint_effort", "post", "swing"),
    }


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ({"name": "x", "type": "imu", "link": "nope"}, "unknown link 'nope'"),
        ({"name": "x", "type": "joint_position"}, "needs a joint"),
        ({"name": "x", "type": "imu", "link": "tool", "max_force": 3.0}, "max_force applies to"),
        ({"name": "x", "type": "sonar", "link": "tool"}, "type"),
        ({"name": "x", "type": "imu", "link": "tool", "noise": -1.0}, "noise"),
    ],
)
def test_bad_sensor_entries_are_named(tmp_path: Path, entry: dict[str, object], message: str) -> None:
    import yaml

    data = yaml.safe_load(ARM.read_text())
    data["description"] = str(FIXTURES / "sensor_arm" / "sensor_arm.urdf")
    data["sensors"] = [entry]
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(data))
    config, description = resolve_robot(path)
    with pytest.raises(ConfigurationError, match=message) as info:
        declared_sensors(description, config)
    assert "sensors[0]" in str(info.value)


async def test_robot_sensors_lists_names_types_frames_and_rejects_unknown() -> None:
    async with agentsdk.connect("mujoco", ARM, safety=SAFETY) as robot:
        infos = {i.name: (i.type, i.frame_id, i.rate) for i in robot.sensors}
        assert infos["wrist_ft"] == ("force_torque", "tool", 500.0)
        assert infos["carriage_imu"][:2] == ("imu", "carriage")
        assert "wrist_ft" in robot.sensors and len(robot.sensors) == 5
        with pytest.raises(UnknownSensorError, match="wrist_ft"):
            robot.sensors.read("nope")
        with pytest.raises(InvalidValueError, match="contact"):
            robot.sensors.add_limit("carriage_imu", max_force=5.0)
        with pytest.raises(InvalidValueError, match="force_torque"):
            await robot.move_to({"lift": 0.2}, until=force_above("carriage_imu", 1.0))
        assert robot.safety.state.name == "OK"


async def test_mock_backend_serves_joint_sensors_only() -> None:
    async with agentsdk.connect("mock", ARM) as robot:
        assert robot.sensors.names == ("lift_position",)
        await robot.move_to({"lift": 0.25}, 0.5)
        reading = robot.sensors.read("lift_position")
        assert isinstance(reading, JointSensorReading)
        assert reading.value == pytest.approx((await robot.read()).position[1], abs=1e-12)
        assert reading.header.stamp == robot.clock.now()


async def test_a_robot_without_sensors_registers_no_hook() -> None:
    async with agentsdk.connect("mujoco", "arm3") as robot:
        assert robot.sensors.names == ()
        assert robot.sensors._hub._handle is None


# --------------------------------------------------------------------------- IMU
@pytest.mark.parametrize("backend", SIMS)
async def test_imu_on_a_floating_base_at_rest_reads_gravity(backend: str) -> None:
    async with agentsdk.connect(backend, FIXTURES / "imu_box" / "robot.yaml", safety=SAFETY) as robot:
        await robot.clock.sleep(1.0)
        imu = robot.sensors.read("imu")
        assert isinstance(imu, Imu)
        assert imu.header.frame_id == "body" and imu.header.stamp == pytest.approx(1.0)
        np.testing.assert_allclose(imu.linear_acceleration, [0.0, 0.0, G], atol=0.01 * G)
        assert np.linalg.norm(imu.angular_velocity) < 1e-3
        np.testing.assert_allclose(np.abs(imu.orientation), [0.0, 0.0, 0.0, 1.0], atol=1e-3)


@pytest.mark.parametrize("backend", SIMS)
async def test_imu_spinning_about_one_axis_reads_rate_and_centripetal_force(backend: str) -> None:
    """The IMU sits 0.05 m off the spin axis, rolled 90° about x: its y axis is up."""
    w, r = 2.0, 0.05
    async with agentsdk.connect(backend, FIXTURES / "imu_turntable" / "robot.yaml", safety=SAFETY) as robot:
        at_rest = robot.sensors.read("table_imu")
        assert isinstance(at_rest, Imu)
        s = math.sqrt(0.5)
        np.testing.assert_allclose(at_rest.orientation, [s, 0.0, 0.0, s], atol=1e-6)
        np.testing.assert_allclose(at_rest.linear_acceleration, [0.0, G, 0.0], atol=0.01 * G)
        for _ in range(15):  # a velocity stream (refreshed before the command watchdog's 0.25 s)
            await robot.command(agentsdk.JointCommand("velocity", {"spin": w}))
            await robot.clock.sleep(0.1)
        imu = robot.sensors.read("table_imu")
        assert isinstance(imu, Imu)
        np.testing.assert_allclose(imu.angular_velocity, [0.0, w, 0.0], atol=0.01 * w)
        np.testing.assert_allclose(imu.linear_acceleration[1], G, rtol=0.01)
        assert imu.linear_acceleration[0] == pytest.approx(-w * w * r, rel=0.01)
        assert abs(imu.linear_acceleration[2]) < 0.01 * w * w * r + 1e-3
        # the orientation is the table's yaw (w t) composed with the mount's roll
        yaw = float((await robot.read()).position[0])
        expected = [s * math.cos(yaw / 2), s * math.sin(yaw / 2), s * math.sin(yaw / 2), s * math.cos(yaw / 2)]
        q = imu.orientation * np.sign(imu.orientation[3] * expected[3])
        np.testing.assert_allclose(q, expected, atol=2e-2)


# --------------------------------------------------------------------------- force-torque
def _rotated_arm(tmp_path: Path) -> Path:
    """sensor_arm with the tool frame turned (rpy 0.3, pi/2, 0) and its centre of mass off axis."""
    urdf = (FIXTURES / "sensor_arm" / "sensor_arm.urdf").read_text()
    urdf = urdf.replace('<parent link="carriage"/><child link="tool"/><origin xyz="0 0 0"/>',
                        '<parent link="carriage"/><child link="tool"/><origin xyz="0 0 0" rpy="0.3 1.5707963 0"/>')
    urdf = urdf.replace('<inertial><origin xyz="0 0 -0.05"/><mass value="0.5"/>',
                        '<inertial><origin xyz="0.01 0.02 -0.05" rpy="0.4 0.2 0.1"/><mass value="0.5"/>')
    (tmp_path / "sensor_arm.urdf").write_text(urdf)
    yaml_text = ARM.read_text().replace("initial_positions: {yaw: 0.0, lift: 0.3}",
                                        "initial_positions: {yaw: 0.7, lift: 0.3}")
    (tmp_path / "robot.yaml").write_text(yaml_text)
    return tmp_path / "robot.yaml"


@pytest.mark.parametrize("backend", SIMS)
async def test_wrist_ft_reads_the_payload_weight(backend: str) -> None:
    async with agentsdk.connect(backend, ARM, safety=SAFETY) as robot:
        await robot.clock.sleep(0.5)
        ft = robot.sensors.read("wrist_ft")
        assert isinstance(ft, WrenchStamped) and ft.header.frame_id == "tool"
        # the wrench the tool exerts on the carriage: its weight, downwards
        assert np.linalg.norm(ft.wrench.force) == pytest.approx(PAYLOAD * G, rel=0.02)
        np.testing.assert_allclose(ft.wrench.force, [0.0, 0.0, -PAYLOAD * G], atol=0.02 * PAYLOAD * G)
        assert np.linalg.norm(ft.wrench.torque) < 1e-3


@pytest.mark.parametrize("backend", SIMS)
async def test_wrist_ft_frame_and_moments_match_the_analytic_wrench(backend: str, tmp_path: Path) -> None:
    from agentsdk.description.model import rotation_from_rpy

    async with agentsdk.connect(backend, _rotated_arm(tmp_path), safety=SAFETY) as robot:
        await robot.clock.sleep(0.5)
        ft = robot.sensors.read("wrist_ft")
        assert isinstance(ft, WrenchStamped)
        yaw = float((await robot.read()).position[0])
        rot = rotation_from_rpy((0.0, 0.0, yaw)) @ rotation_from_rpy((0.3, 1.5707963, 0.0))  # tool in world
        weight = rot.T @ np.array([0.0, 0.0, -PAYLOAD * G])  # in the tool frame
        torque = np.cross([0.01, 0.02, -0.05], weight)  # about the sensor origin
        np.testing.assert_allclose(ft.wrench.force, weight, atol=0.02 * PAYLOAD * G)
        np.testing.assert_allclose(ft.wrench.torque, torque, atol=2e-3)


# --------------------------------------------------------------------------- guarded moves, contact limits
@pytest.mark.parametrize("backend", SIMS)
async def test_guarded_move_stops_at_first_contact(backend: str) -> None:
    async with agentsdk.connect(backend, ARM, safety=SAFETY) as robot:
        first: list[float] = []

        def watch(t: float, st: object, sp: object) -> None:
            if not first and robot.sensors.values("tool_contact")[0] > 0.0:
                first.append(float(robot.latest_state().position[1]))

        robot.add_tick_hook(Phase.OBSERVE, watch)
        await robot.clock.sleep(0.2)
        result = await robot.move_to({"lift": 0.1}, 3.0, until=force_above("wrist_ft", 5.0, tare=True))
        assert result.code is ResultCode.SUCCESSFUL, result
        assert "force_above('wrist_ft', 5 N, tared)" in result.message
        await robot.clock.sleep(0.3)
        final = float((await robot.read()).position[1])
        assert first and abs(first[0] - CONTACT_LIFT) < 1e-3
        assert abs(final - first[0]) < 0.002
        touching = robot.sensors.read("tool_contact")
        assert isinstance(touching, ContactState) and touching.in_contact


@pytest.mark.parametrize("backend", SIMS)
@pytest.mark.parametrize(("duration", "limit"), [(10.0, 30.0), (6.0, 60.0)])
async def test_contact_force_limit_latches_a_protective_stop(backend: str, duration: float, limit: float) -> None:
    async with agentsdk.connect(backend, ARM, safety=SAFETY) as robot:
        peak = [0.0]

        def watch(t: float, st: object, sp: object) -> None:
            peak[0] = max(peak[0], float(robot.sensors.values("tool_contact")[0]))

        robot.add_tick_hook(Phase.OBSERVE, watch)
        robot.sensors.add_limit("tool_contact", max_force=limit)
        result = await robot.move_to({"lift": 0.1}, duration)  # through the table
        await robot.clock.sleep(0.5)
        assert result.code is ResultCode.ABORTED
        assert robot.safety.state.name == "ESTOP"
        events = [e for e in robot.safety.events if e.kind == "sensor_limit"]
        assert len(events) == 1 and "sensor 'tool_contact'" in events[0].detail
        assert limit < peak[0] <= 1.2 * limit


async def test_sensor_limit_from_robot_yaml_with_its_stop_category(tmp_path: Path) -> None:
    import yaml

    data = yaml.safe_load(ARM.read_text())
    data["description"] = str(FIXTURES / "sensor_arm" / "sensor_arm.urdf")
    data["sensors"].append({"name": "bump", "type": "contact", "link": "tool", "max_force": 30.0, "stop_category": 1})
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(data))
    async with agentsdk.connect("mujoco", path, safety=SAFETY) as robot:
        result = await robot.move_to({"lift": 0.1}, 10.0)
        assert result.code is ResultCode.ABORTED
        details = [e.detail for e in robot.safety.events]
        assert any("sensor 'bump'" in d and "30 N" in d for d in details)
        assert any("category 1" in d for d in details)


async def test_guarded_move_on_a_contact_sensor_and_no_contact_runs_to_the_goal() -> None:
    async with agentsdk.connect("mujoco", ARM, safety=SAFETY) as robot:
        result = await robot.move_to({"lift": 0.25}, 1.0, until=contact("tool_contact"))
        assert result.code is ResultCode.SUCCESSFUL and result.message == ""
        result = await robot.move_to({"lift": 0.1}, 3.0, until=contact("tool_contact", 1.0))
        assert result.code is ResultCode.SUCCESSFUL and "contact('tool_contact', 1 N)" in result.message


# --------------------------------------------------------------------------- range, joint sensors
@pytest.mark.parametrize("backend", SIMS)
async def test_rangefinder_and_joint_sensor(backend: str) -> None:
    async with agentsdk.connect(backend, ARM, safety=SAFETY) as robot:
        await robot.move_to({"lift": 0.35}, 1.0)
        await robot.clock.sleep(0.2)
        rng = robot.sensors.read("height")
        assert isinstance(rng, Range) and rng.max_range == 2.0
        lift = float((await robot.read()).position[1])
        assert rng.range == pytest.approx(lift - 0.1, abs=1e-3)  # table top at 0.10
        pos = robot.sensors.read("lift_position")
        assert isinstance(pos, JointSensorReading) and pos.value == pytest.approx(lift, abs=1e-12)


async def test_mjcf_sensors_read_as_written() -> None:
    async with agentsdk.connect("mujoco", FIXTURES / "mjcf_sensors" / "sensors.xml", safety=SAFETY) as robot:
        await robot.clock.sleep(0.5)
        acc = robot.sensors.read("acc")
        force = robot.sensors.read("hand_force")
        rng = robot.sensors.read("floor_range")
        assert isinstance(acc, Vector3Stamped) and isinstance(force, Vector3Stamped) and isinstance(rng, Range)
        np.testing.assert_allclose(acc.vector, [0.0, 0.0, G], atol=0.01 * G)
        np.testing.assert_allclose(force.vector, [0.0, 0.0, -0.2 * G], atol=0.02 * 0.2 * G)
        assert rng.range == pytest.approx(0.45, abs=1e-6)


# --------------------------------------------------------------------------- realism
def _realistic(tmp_path: Path, **fields: object) -> Path:
    import yaml

    data = yaml.safe_load(ARM.read_text())
    data["description"] = str(FIXTURES / "sensor_arm" / "sensor_arm.urdf")
    data["sensors"] = [{"name": "imu", "type": "imu", "link": "carriage", **fields}]
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


async def _imu_series(path: Path, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    async with agentsdk.connect("mujoco", path, safety=SAFETY) as robot:
        values: list[np.ndarray] = []
        stamps: list[float] = []

        def watch(t: float, st: object, sp: object) -> None:
            values.append(robot.sensors.values("imu").copy())
            stamps.append(robot.sensors.stamp("imu"))

        robot.add_tick_hook(Phase.OBSERVE, watch)
        await robot.clock.sleep(n * robot.control_period)
        return np.array(values), np.array(stamps)


async def test_noise_and_bias_are_seeded_and_deterministic(tmp_path: Path) -> None:
    path = _realistic(tmp_path, noise=0.05, bias=0.2)
    a, _ = await _imu_series(path)
    b, _ = await _imu_series(path)
    np.testing.assert_array_equal(a, b)
    acc_z = a[50:, 9]
    assert acc_z.mean() == pytest.approx(G + 0.2, abs=0.02)
    assert acc_z.std() == pytest.approx(0.05, rel=0.2)
    np.testing.assert_array_equal(a[:, 0:4], np.tile([0.0, 0.0, 0.0, 1.0], (len(a), 1)))  # orientation exact


async def test_rate_and_latency(tmp_path: Path) -> None:
    _, stamps = await _imu_series(_realistic(tmp_path, rate=100.0, latency=0.013), n=200)
    ticks = np.arange(1, len(stamps) + 1) * 0.002
    published = stamps[np.isfinite(stamps) & (stamps >= 0.02)]
    # samples every 10 ms of robot time, each published 13 ms (the first tick at or after) later
    grid = np.unique(published) / 0.01
    np.testing.assert_allclose(grid, np.round(grid), atol=1e-6)
    lag = ticks - stamps
    ok = np.isfinite(stamps) & (ticks > 0.05)
    assert lag[ok].min() == pytest.approx(0.014, abs=1e-9)
    assert lag[ok].max() == pytest.approx(0.022, abs=1e-9)


# --------------------------------------------------------------------------- feedback
async def test_sensors_in_feedback_loops_and_motion_feedback() -> None:
    from agentsdk.feedback import FeedbackState, run_feedback

    async with agentsdk.connect("mujoco", ARM, safety=SAFETY) as robot:
        seen: list[FeedbackState] = []

        async def update(state: agentsdk.JointState) -> None:
            assert isinstance(state, FeedbackState)
            seen.append(state)

        await run_feedback(robot, update, 100.0, duration=0.1, sensors=("wrist_ft", "carriage_imu"))
        assert len(seen) == 10
        for st in seen:
            ft = st.sensors["wrist_ft"]
            assert isinstance(ft, WrenchStamped) and ft.header.stamp == st.stamp
            assert isinstance(st.sensors["carriage_imu"], Imu)
        with pytest.raises(UnknownSensorError):
            await run_feedback(robot, update, 100.0, duration=0.1, sensors="nope")
        motion = robot.follow(agentsdk.Trajectory(
            joint_names=("lift",),
            points=[agentsdk.TrajectoryPoint(time_from_start=0.5, positions=[0.32], velocities=[0.0])],
        ))
        fbs = [fb async for fb in motion.feedback(50.0, sensors=("wrist_ft",))]
        assert fbs and all(isinstance(fb.sensors["wrist_ft"], WrenchStamped) for fb in fbs)
        assert (await motion).code is ResultCode.SUCCESSFUL


# --------------------------------------------------------------------------- cameras
@pytest.mark.parametrize("backend", SIMS)
async def test_camera_renders_headless_in_lockstep_with_depth_in_metres(backend: str) -> None:
    from agentsdk.sensors import Image

    async with agentsdk.connect(backend, ARM_CAM, safety={"stall_timeout": None}) as robot:
        info = robot.sensors["overhead"]
        assert (info.type, info.frame_id, info.rate) == ("camera", "world", 50.0)
        await robot.clock.sleep(0.1)
        img = robot.sensors.read("overhead")
        depth = robot.sensors.depth("overhead")
        assert isinstance(img, Image) and img.encoding == "rgb8" and img.data.shape == (240, 320, 3)
        assert depth.encoding == "32FC1" and depth.data.shape == (240, 320)
        assert img.header.stamp == pytest.approx(0.1) and depth.header.stamp == img.header.stamp
        assert img.data.std() > 0 or img.data.mean() > 0  # something was drawn
        # the camera looks straight down from 1.0 m at the table top (0.10 m): a plane 0.90 m away
        centre = depth.data[100:140, 140:180]
        np.testing.assert_allclose(centre, 0.9, rtol=0.01)
        with pytest.raises(InvalidValueError, match="no depth"):
            robot.sensors.depth("wrist_ft")


# --------------------------------------------------------------------------- CAN
def _mit_leg_with_torque_sensor(tmp_path: Path) -> Path:
    import yaml

    src = Path(__file__).resolve().parents[1] / "robots" / "mit_leg" / "robot.yaml"
    cfg = yaml.safe_load(src.read_text())
    cfg["description"] = str(src.parent / cfg["description"])
    cfg["sensors"] = [{"name": "knee_torque", "type": "joint_effort", "joint": "knee"}]
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


async def test_can_motors_report_temperature_and_torque_estimate_as_sensors(tmp_path: Path) -> None:
    import os

    import can

    from agentsdk.backends.can.emulator import MotorEmulator

    path = _mit_leg_with_torque_sensor(tmp_path)
    channel = f"agentsdk-sensor-test-{os.getpid()}"
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        emu = MotorEmulator.from_robot(path, bus)
        emu.start()
        try:
            async with agentsdk.connect("can", robot=path, interface="virtual", channel=channel,
                                        max_missed_replies=250, safety=SAFETY) as robot:
                names = robot.sensors.names
                assert names == ("knee_torque", "hip_abduction_temperature", "hip_pitch_temperature",
                                 "knee_temperature")
                await robot.clock.sleep(0.1)
                temp = robot.sensors.read("knee_temperature")
                assert isinstance(temp, JointSensorReading) and temp.joint == "knee"
                assert temp.value == pytest.approx(30.0, abs=1.0)  # the emulated motors report 30 °C
                torque = robot.sensors.read("knee_torque")
                assert isinstance(torque, JointSensorReading)
                assert torque.value == pytest.approx(float(robot.latest_state().effort[2]), abs=1e-9)
        finally:
            emu.stop()
    finally:
        bus.shutdown()


# --------------------------------------------------------------------------- the tick stays allocation-free
async def test_mujoco_sensor_sampling_allocates_no_arrays() -> None:
    """tracemalloc peak of the sensor hook's segment of the tick (IMU, F/T, contact, range, joint; noise on)."""
    import tracemalloc

    from agentsdk.sensors import SENSOR_OBSERVE_ORDER

    async with agentsdk.connect("mujoco", ARM, safety={"stall_timeout": 10.0}) as robot:
        seg: dict[str, list[int]] = {"sensors": [], "empty": []}

        def end_of(name: str) -> object:
            out = seg[name]

            def probe(t: float, st: object, sp: object) -> None:
                if tracemalloc.is_tracing():
                    cur, peak = tracemalloc.get_traced_memory()
                    out.append(peak - cur)
                    tracemalloc.reset_peak()

            return probe

        robot.add_tick_hook(Phase.OBSERVE, end_of("empty"), order=SENSOR_OBSERVE_ORDER - 2)
        robot.add_tick_hook(Phase.OBSERVE, end_of("empty"), order=SENSOR_OBSERVE_ORDER - 1)
        robot.add_tick_hook(Phase.OBSERVE, end_of("sensors"), order=SENSOR_OBSERVE_ORDER + 1)
        await robot.clock.sleep(0.05)  # warm up (the per-channel copy plans are made on first use)
        tracemalloc.start()
        try:
            await robot.clock.sleep(0.3)
        finally:
            tracemalloc.stop()
    empty = float(np.median(seg["empty"][3:]))
    # no arrays (a numpy array is >= 100 bytes); at most a few Python scalars
    assert float(np.median(seg["sensors"][3:])) <= empty + 64, seg["sensors"][:20]


# --------------------------------------------------------------------------- lidar, tilt limit
def _with_lidar(tmp_path: Path) -> Path:
    import yaml

    data = yaml.safe_load(ARM.read_text())
    data["description"] = str(FIXTURES / "sensor_arm" / "sensor_arm.urdf")
    # the scan plane is vertical: x points down, y along the world's y; the table top is 0.2 m below
    data["sensors"] = [{
        "name": "scan", "type": "lidar", "link": "carriage", "xyz": [0.1, 0.0, 0.0],
        "rpy": [0.0, 1.5707963267948966, 0.0],
        "ray": {"samples": 21, "min_angle": -0.6, "max_angle": 0.6, "range_max": 0.3},
    }]
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("backend", SIMS)
async def test_lidar_scan_of_a_plane(backend: str, tmp_path: Path) -> None:
    from agentsdk.sensors import LaserScan

    async with agentsdk.connect(backend, _with_lidar(tmp_path), safety=SAFETY) as robot:
        await robot.clock.sleep(0.1)
        scan = robot.sensors.read("scan")
        assert isinstance(scan, LaserScan) and len(scan.ranges) == 21
        assert scan.angle_increment == pytest.approx(0.06)
        angles = scan.angle_min + scan.angle_increment * np.arange(21)
        expected = 0.2 / np.cos(angles)
        expected[expected > 0.3] = np.inf  # beyond range_max: nothing in range
        finite = np.isfinite(expected)
        np.testing.assert_allclose(scan.ranges[finite], expected[finite], rtol=1e-3)
        assert np.all(np.isinf(scan.ranges[~finite]))


@pytest.mark.parametrize("backend", SIMS)
async def test_tilt_limit_latches_a_stop_naming_the_imu(backend: str) -> None:
    async with agentsdk.connect(backend, FIXTURES / "imu_turntable" / "robot.yaml", safety=SAFETY) as robot:
        await robot.clock.sleep(0.05)
        assert robot.safety.state.name == "OK"
        robot.sensors.add_limit("table_imu", max_tilt=1.0, category=1)  # the mount is rolled 90°: tilt pi/2
        await robot.clock.sleep(0.05)
        assert robot.safety.state.name == "ESTOP"
        detail = next(e.detail for e in robot.safety.events if e.kind == "sensor_limit")
        assert "sensor 'table_imu'" in detail and "tilt 1.57 rad" in detail


async def test_latency_delays_the_same_noisy_samples(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    prompt, _ = await _imu_series(_realistic(tmp_path / "a", noise=0.05, bias=0.1), n=300)
    late, stamps = await _imu_series(_realistic(tmp_path / "b", noise=0.05, bias=0.1, latency=0.01), n=300)
    lag = 5  # 10 ms at 500 Hz
    # the same seeded samples, published 5 ticks later, with the stamps of when they were taken
    np.testing.assert_array_equal(late[lag + 1 :], prompt[1:-lag])
    np.testing.assert_allclose(stamps[lag + 1 :], np.arange(2, len(stamps) - lag + 1) * 0.002, atol=1e-9)


def _gazebo_camera_arm(tmp_path: Path) -> Path:
    urdf = (FIXTURES / "sensor_arm" / "sensor_arm.urdf").read_text().replace("</robot>", """
  <gazebo reference="column">
    <sensor name="side_cam" type="depth">
      <update_rate>25</update_rate>
      <pose>0.6 0 1.0 0 1.5707963267948966 0</pose>
      <camera><horizontal_fov>0.6</horizontal_fov><image><width>160</width><height>120</height></image>
        <clip><near>0.05</near><far>10</far></clip></camera>
    </sensor>
  </gazebo>
</robot>""")
    (tmp_path / "sensor_arm.urdf").write_text(urdf)
    (tmp_path / "robot.yaml").write_text(ARM.read_text())
    return tmp_path / "robot.yaml"


@pytest.mark.parametrize("backend", SIMS)
async def test_a_description_camera_renders_once_started(backend: str, tmp_path: Path) -> None:
    async with agentsdk.connect(backend, _gazebo_camera_arm(tmp_path), safety={"stall_timeout": None}) as robot:
        info = robot.sensors["side_cam"]
        assert (info.type, info.frame_id, info.rate, info.source) == ("camera", "column", 25.0, "gazebo")
        assert "side_cam" not in robot.sensors.started
        with pytest.raises(InvalidValueError, match="not started"):
            robot.sensors.read("side_cam")
        await robot.clock.sleep(0.02)
        await robot.sensors.start("side_cam")
        first = robot.sensors.depth("side_cam")
        assert first.header.stamp == pytest.approx(robot.clock.now())
        await robot.clock.sleep(0.1)
        later = robot.sensors.depth("side_cam")
        assert later.header.stamp > first.header.stamp and later.data.shape == (120, 160)
        np.testing.assert_allclose(later.data[50:70, 70:90], 0.9, rtol=0.01)
