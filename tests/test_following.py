"""Issue 20.8: following error. A position-servoed joint whose measured position stays outside a window
around its command latches a stop naming the joint, on every backend (a check in the safety layer).

Fixtures: ``tests/fixtures/following`` - a pendulum arm (MJCF) with model-derived gains (healthy.yaml)
and with gains far too low to hold its load (weak.yaml). The mock backend follows perfectly, so the
check's own behaviour (window, persistence, what is watched) is shown by feeding it states directly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import agentsdk
from agentsdk import ConfigurationError, JointCommand, ResultCode, SafetyState, Trajectory, TrajectoryPoint
from agentsdk.loop import StateView

FIXTURES = Path(__file__).parent / "fixtures" / "following"
SIMULATORS = ("mujoco", "pybullet")


def _following_events(robot: agentsdk.Robot) -> list[agentsdk.SafetyEvent]:
    return [e for e in robot.safety.events if e.kind == "following_error"]


@pytest.mark.parametrize("backend", SIMULATORS)
async def test_a_hold_with_gains_too_low_latches_a_following_error_within_half_a_second(backend: str) -> None:
    async with agentsdk.connect(backend, robot=FIXTURES / "weak.yaml") as robot:
        t0 = robot.clock.now()
        await robot.clock.sleep(0.5)
        assert robot.safety.state is SafetyState.ESTOP
        (ev,) = _following_events(robot)
        assert ev.joint == "shoulder"
        assert ev.time - t0 <= 0.5
        assert "joint 'shoulder' is " in ev.detail and "from its position command (window 0.5)" in ev.detail
        with pytest.raises(agentsdk.EStopActive):
            await robot.move_to({"shoulder": 0.0})


async def test_healthy_tracking_holds_and_moves_without_a_following_error() -> None:
    async with agentsdk.connect("mujoco", robot=FIXTURES / "healthy.yaml") as robot:
        await robot.clock.sleep(0.5)
        result = await robot.move_to({"shoulder": -0.5, "wrist": 2.0})
        assert result.ok
        await robot.clock.sleep(0.3)
        following = robot.safety.following
        assert following is not None
        assert robot.safety.state is SafetyState.OK and not _following_events(robot)
        assert (following.peak < 0.2 * following.windows).all(), (following.peak, following.windows)


@pytest.mark.parametrize("backend", SIMULATORS)
async def test_a_motor_with_armature_follows_on_both_simulators(backend: str) -> None:
    """The wrist's rotor inertia (MJCF armature, 10 000 times the tool's) is part of the model its gains come
    from; both simulators simulate it (PyBullet through its implicit step), so the wrist follows its move on
    both, where PyBullet's wrist used to run away and latch."""
    async with agentsdk.connect(backend, robot=FIXTURES / "healthy.yaml") as robot:
        result = await robot.move_to({"wrist": 2.0})
        assert result.ok, result
        assert robot.safety.state is SafetyState.OK and not _following_events(robot)
        assert abs((await robot.read()).position[1] - 2.0) < 0.02


@pytest.mark.parametrize("backend", SIMULATORS)
async def test_joints_not_position_servoed_are_not_watched(backend: str) -> None:
    """An effort command (here zero: the shoulder falls) has no position to follow: no following error."""
    async with agentsdk.connect(backend, robot=FIXTURES / "weak.yaml") as robot:
        for _ in range(50):
            await robot.command(JointCommand("effort", {"shoulder": 0.0, "wrist": 0.0}))
            await robot.clock.sleep(0.02)
        assert abs((await robot.read()).position[0] - 0.8) > 0.5  # it did fall away from where it was
        assert not _following_events(robot)


def _feed(robot: agentsdk.Robot, offsets: np.ndarray, t: float) -> agentsdk.safety.SafetyViolation | None:
    check = robot.safety.following
    assert check is not None
    q = robot.setpoint.position + offsets
    return check(t, StateView(q, np.zeros_like(q), np.zeros_like(q)))


async def test_window_and_persistence_on_mock() -> None:
    """The check itself, on the perfect mock: a joint outside its window latches only once it stayed outside
    for following_error_time; coming back inside resets the timer; windows derive from gains and effort."""
    safety = {"following_error_window": {"joint3": 0.3}, "following_error_time": 0.1}
    async with agentsdk.connect("mock", robot="arm3", safety=safety) as robot:
        check = robot.safety.following
        assert check is not None
        # joint1: 2 * 20 N·m / 100 = 0.4; joint2: 2 * 20 / 800 = 0.05 -> the minimum 0.25; joint3: configured
        assert check.windows.tolist() == pytest.approx([0.4, 0.25, 0.3])
        dt = robot.control_period
        off = np.array([0.0, 0.3, 0.0])
        t = 10.0
        for k in range(round(0.1 / dt)):
            assert _feed(robot, off, t + k * dt) is None
        assert _feed(robot, np.zeros(3), t + 0.1) is None  # back inside: the timer restarts
        t = 11.0
        for k in range(round(0.1 / dt)):
            assert _feed(robot, -off, t + k * dt) is None
        v = _feed(robot, -off, t + 0.1)
        assert v is not None and v.joint == "joint2" and v.kind == "following_error" and v.category == 2
        assert "joint 'joint2' is 0.3 from its position command (window 0.25) for 0.1 s" in v.detail


async def test_a_stuck_joint_latches_on_mock() -> None:
    """On the mock too (a joint frozen in place, as a blocked or disconnected one): the stop latches,
    naming the joint, in the configured category; the goal-tolerance result never gets that far."""
    async with agentsdk.connect("mock", robot="arm3", frozen_joints=["joint2"],
                                safety={"following_error_stop": 1}) as robot:
        motion = robot.follow(Trajectory(["joint1", "joint2"], [TrajectoryPoint(0.5, [0.3, 0.3])]))
        t0 = robot.clock.now()
        result = await motion
        assert result.code is ResultCode.ABORTED
        assert robot.safety.state is SafetyState.ESTOP
        (ev,) = _following_events(robot)
        assert ev.joint == "joint2" and ev.time - t0 < 0.5
        assert any("category 1" in e.detail for e in robot.safety.events if e.kind == "estop")


async def test_configuration() -> None:
    async with agentsdk.connect("mock", robot="arm3", safety={"following_error_window": None}) as robot:
        assert robot.safety.following is None
    async with agentsdk.connect("mock", robot="arm3", safety={"following_error_window": 0.25}) as robot:
        assert robot.safety.following is not None
        assert robot.safety.following.windows.tolist() == [0.25, 0.25, 0.25]
    with pytest.raises(ConfigurationError, match="unknown joint"):
        await agentsdk.connect("mock", robot="arm3", safety={"following_error_window": {"elbow": 0.2}})
    with pytest.raises(ConfigurationError, match="following_error_min"):
        await agentsdk.connect("mock", robot="arm3", safety={"following_error_min": 1.0})
    with pytest.raises(ConfigurationError, match="following_error_window"):
        await agentsdk.connect("mock", robot="arm3", safety={"following_error_window": -1.0})
