"""Kinematics on a connected robot and Cartesian motion: move_to_pose, straight lines, the square behavior.

Corpus arms (UR5, Panda) run with a test robot.yaml: gravity off and stiffer gains, because
bare URDFs get p=100 and no gravity compensation until the model-based servo lands (issue 13);
what is tested here is the kinematics and the line, not the servo. UR5 runs on MuJoCo only:
the PyBullet backend crashes loading its COLLADA meshes (URDF_MAINTAIN_LINK_ORDER).
"""

from __future__ import annotations

import asyncio
import importlib.metadata
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import agentsdk
from agentsdk import (
    EStopActive,
    InvalidValueError,
    LimitViolation,
    Pose,
    ResultCode,
    Robot,
    UnknownLinkError,
)
from agentsdk.behaviors import square

CORPUS = Path(
    str(importlib.metadata.distribution("example-robot-data").locate_file("cmeel.prefix/share/example-robot-data/robots"))
)
SAFETY = {"stall_timeout": 5.0}  # lockstep runs on a loaded test machine

UR5_YAML = """
description: {root}/ur_description/urdf/ur5_robot.urdf
update_rate: 500
gains:
  default: {{p: 3000.0, d: 60.0}}
initial_positions: {{shoulder_lift_joint: -1.2, elbow_joint: 1.5, wrist_1_joint: -1.9, wrist_2_joint: -1.57}}
backends:
  mujoco: {{gravity: [0, 0, 0]}}
  pybullet: {{gravity: [0, 0, 0]}}
"""
PANDA_YAML = """
description: {root}/panda_description/urdf/panda.urdf
update_rate: 500
gains:
  default: {{p: 2000.0, d: 40.0}}
initial_positions: {{panda_joint2: -0.5, panda_joint4: -2.2, panda_joint6: 1.8, panda_joint7: 0.8,
                    panda_finger_joint1: 0.02}}
backends:
  mujoco: {{gravity: [0, 0, 0]}}
  pybullet: {{gravity: [0, 0, 0]}}
"""


@pytest.fixture(scope="module")
def corpus_yamls(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    base = tmp_path_factory.mktemp("corpus")
    out = {}
    for name, text in (("ur5", UR5_YAML), ("panda", PANDA_YAML)):
        d = base / name
        d.mkdir()
        (d / "robot.yaml").write_text(text.format(root=CORPUS))
        out[name] = str(d / "robot.yaml")
    yield out


class LineWatch:
    """Samples the measured end-effector pose every control period; distance from the segment a-b."""

    def __init__(self, robot: Robot, link: str, a: np.ndarray, b: np.ndarray, orientation: Pose | None) -> None:
        self.robot, self.link, self.a, self.b, self.orientation = robot, link, a, b, orientation
        self.deviation = 0.0
        self.angle = 0.0
        self.samples = 0

    async def run(self) -> None:
        kin = self.robot.kinematics
        ab = self.b - self.a
        while True:
            pose = kin.fk(self.link)
            t = float(np.clip(np.dot(pose.position - self.a, ab) / np.dot(ab, ab), 0.0, 1.0))
            self.deviation = max(self.deviation, float(np.linalg.norm(pose.position - (self.a + t * ab))))
            if self.orientation is not None:
                self.angle = max(self.angle, pose.distance(self.orientation)[1])
            self.samples += 1
            await self.robot.clock.sleep(self.robot.control_period)


async def linear_move(robot: Robot, link: str, target: Pose, **kw: object) -> tuple[agentsdk.MotionResult, LineWatch]:
    start = robot.kinematics.fk(link)
    watch = LineWatch(robot, link, start.position, target.position,
                      None if kw.get("position_only") else target)
    task = asyncio.create_task(watch.run())
    try:
        result = await robot.move_to_pose(link, target, linear=True, **kw)  # type: ignore[arg-type]
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    return result, watch


# --------------------------------------------------------------------------- kinematics on a robot


async def test_robot_kinematics_uses_the_measured_state(mock_arm: Robot) -> None:
    assert mock_arm.link_names == ("world", "base_link", "link1", "link2", "ee_link")
    await mock_arm.move_to({"joint1": 0.4, "joint2": 0.7})
    state = await mock_arm.read()
    kin = mock_arm.kinematics
    assert kin.fk("ee_link").isclose(kin.fk("ee_link", state), 1e-12, 1e-12)
    assert kin.fk("ee_link").isclose(kin.fk("ee_link", list(state.position)), 1e-12, 1e-12)
    tf = kin.link_poses()
    assert tf.stamp == state.stamp
    assert tf["ee_link"].isclose(kin.fk("ee_link"), 1e-12, 1e-12)
    assert kin.link_poses(state).stamp == state.stamp
    with pytest.raises(UnknownLinkError):
        await mock_arm.move_to_pose("gripper", Pose([0.1, 0.0, 0.5]))


@pytest.mark.parametrize("backend", ["mock", "mujoco", "pybullet"])
async def test_same_kinematics_on_every_backend(backend: str) -> None:
    async with agentsdk.connect(backend, robot="humanoid", safety=SAFETY) as robot:
        assert len(robot.link_names) == 17 and robot.link_names[0] == "world"
        q = np.linspace(-0.3, 0.3, len(robot.joints))
        poses = robot.kinematics.link_poses(q)
        assert set(poses) == set(robot.link_names)


# --------------------------------------------------------------------------- move_to_pose


@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
async def test_move_to_pose_joint_space(backend: str) -> None:
    async with agentsdk.connect(backend, robot="arm3", safety=SAFETY) as robot:
        kin = robot.kinematics
        goal = kin.fk("ee_link", [0.6, 0.8, 0.0]).position
        result = await robot.move_to_pose("ee_link", goal)  # a position: position-only
        assert result.code is ResultCode.SUCCESSFUL, result
        await robot.clock.sleep(0.3)
        assert np.linalg.norm(kin.fk("ee_link").position - goal) < 2e-3


async def test_unreachable_pose_is_an_invalid_goal_naming_the_residual() -> None:
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
        await robot.move_to({"joint2": 0.5})
        before = (await robot.read()).position.copy()
        for linear in (False, True):
            result = await robot.move_to_pose("ee_link", [1.0, 0.0, 0.3], linear=linear)
            assert result.code is ResultCode.INVALID_GOAL
            assert "residual" in result.message and "ee_link" in result.message
            assert not result.ok
        await robot.clock.sleep(0.2)
        assert np.allclose((await robot.read()).position, before, atol=2e-3)  # nothing moved


async def test_move_to_pose_bad_input(mock_arm: Robot) -> None:
    kin = mock_arm.kinematics
    await mock_arm.move_to({"joint2": 0.5})
    goal = kin.fk("ee_link", [0.1, 0.55, 0.0]).position
    with pytest.raises(InvalidValueError):
        await mock_arm.move_to_pose("ee_link", [0.1, 0.2])
    with pytest.raises(InvalidValueError):
        await mock_arm.move_to_pose("ee_link", goal, linear=True, velocity_scale=0.0)
    with pytest.raises(InvalidValueError):
        await mock_arm.move_to_pose("ee_link", goal, path_tolerance=-1.0)
    with pytest.raises(LimitViolation, match="too short"):
        await mock_arm.move_to_pose("ee_link", goal, linear=True, duration=0.01)
    await mock_arm.estop(0)
    with pytest.raises(EStopActive):
        await mock_arm.move_to_pose("ee_link", goal)


# --------------------------------------------------------------------------- straight lines


@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
async def test_linear_arm3_stays_on_the_line(backend: str) -> None:
    async with agentsdk.connect(backend, robot="arm3", safety=SAFETY) as robot:
        await robot.move_to({"joint1": 0.5, "joint2": 0.6})
        await robot.clock.sleep(0.3)
        kin = robot.kinematics
        q = np.array((await robot.read()).position)
        # a chord of arm3's reachable sphere: every point of the line is within ~0.3 mm of it
        target = Pose(kin.fk("ee_link", q + np.array([0.12, 0.08, 0.0])).position)
        result, watch = await linear_move(robot, "ee_link", target, position_only=True)
        assert result.code is ResultCode.SUCCESSFUL, result
        assert watch.samples > 100
        assert watch.deviation < 2e-3, watch.deviation
        await robot.clock.sleep(0.3)
        assert np.linalg.norm(kin.fk("ee_link").position - target.position) < 2e-3


@pytest.mark.parametrize("robot_name,backend,link", [
    ("ur5", "mujoco", "tool0"),
    ("panda", "mujoco", "panda_hand_tcp"),
    ("panda", "pybullet", "panda_hand_tcp"),
])
async def test_linear_corpus_arm_keeps_pose_on_the_line(
    robot_name: str, backend: str, link: str, corpus_yamls: dict[str, str]
) -> None:
    async with agentsdk.connect(backend, robot=corpus_yamls[robot_name], safety=SAFETY) as robot:
        kin = robot.kinematics
        start = kin.fk(link)
        target = Pose(start.position + np.array([0.06, -0.05, -0.04]), start.orientation)
        result, watch = await linear_move(robot, link, target, velocity_scale=0.5, acceleration_scale=0.25)
        assert result.code is ResultCode.SUCCESSFUL, result
        assert watch.deviation < 2e-3, watch.deviation
        assert watch.angle < 0.01, watch.angle
        # a rotation on the way: slerp of the orientation along the line
        yaw = Pose.from_xyz_rpy([0, 0, 0], [0.0, 0.0, 0.3])
        turned = Pose(target.position + np.array([0.0, 0.05, 0.0]), (yaw @ target).orientation)
        result = await robot.move_to_pose(link, turned, linear=True)
        assert result.code is ResultCode.SUCCESSFUL, result
        await robot.clock.sleep(0.3)
        dist, angle = kin.fk(link).distance(turned)
        assert dist < 2e-3 and angle < 0.01


async def test_linear_motion_cancels_and_is_preempted_like_any_trajectory() -> None:
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
        await robot.move_to({"joint1": 0.5, "joint2": 0.6})
        kin = robot.kinematics
        q = np.array((await robot.read()).position)
        target = Pose(kin.fk("ee_link", q + np.array([0.12, 0.08, 0.0])).position)
        slow = {"linear": True, "position_only": True, "velocity_scale": 0.05, "acceleration_scale": 0.05}
        # cancel: the awaiting task is cancelled, the arm decelerates and holds
        task = asyncio.create_task(robot.move_to_pose("ee_link", target, **slow))  # type: ignore[arg-type]
        await robot.clock.sleep(0.3)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        await robot.clock.sleep(1.0)
        state = await robot.read()
        assert np.abs(state.velocity).max() < 0.02
        assert np.linalg.norm(kin.fk("ee_link").position - target.position) > 0.005  # stopped on the way
        # preemption: a newer motion on the same joints
        task = asyncio.create_task(robot.move_to_pose("ee_link", target, **slow))  # type: ignore[arg-type]
        await robot.clock.sleep(0.2)
        other = await robot.move_to({"joint1": 0.0})
        result = await task
        assert result.code is ResultCode.PREEMPTED
        assert other.ok


# --------------------------------------------------------------------------- the square behavior


@pytest.mark.parametrize("backend", ["mujoco", "pybullet", "mock"])
async def test_square_on_arm3(backend: str) -> None:
    async with agentsdk.connect(backend, robot="arm3", safety=SAFETY) as robot:
        report = await square.main(robot)
    assert report.link == "ee_link"
    assert report.closing_error < 2e-3
    assert report.max_deviation < 2e-3
    corners = np.array(report.corners)
    sides = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
    assert np.all(np.abs(sides - sides.mean()) < 2e-3) and sides.mean() > 0.03


@pytest.mark.parametrize("robot_name,backend", [("ur5", "mujoco"), ("panda", "mujoco"), ("panda", "pybullet")])
async def test_square_on_a_corpus_arm(robot_name: str, backend: str, corpus_yamls: dict[str, str]) -> None:
    async with agentsdk.connect(backend, robot=corpus_yamls[robot_name], safety=SAFETY) as robot:
        report = await square.main(robot)
    assert report.link == {"ur5": "tool0", "panda": "panda_hand_tcp"}[robot_name]
    assert report.closing_error < 2e-3
    assert report.max_deviation < 2e-3
    corners = np.array(report.corners)
    sides = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
    assert np.allclose(sides, square.SIDE, atol=1e-4)


async def test_cartesian_motion_is_deterministic_in_lockstep() -> None:
    """IK and line planning yield to the event loop on wall-clock slices; lockstep time stands still meanwhile."""
    finals = []
    for _ in range(2):
        async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
            report = await square.main(robot)
            state = await robot.read()
            finals.append((report, state.stamp, state.position.tobytes()))
    assert finals[0] == finals[1]
