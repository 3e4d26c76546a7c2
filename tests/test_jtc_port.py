"""Behavioural cases of ros2_controllers' JointTrajectoryController (JTC) test suite, ported to agentsdk.

Source: ros-controls/ros2_controllers, ``joint_trajectory_controller/test/``
(``test_trajectory_controller.cpp``, ``test_trajectory_actions.cpp``, ``test_trajectory.cpp``,
``test_tolerances.cpp``). Each test names the JTC test it ports in its docstring and says where our
semantics differ on purpose (see the README's trajectory section). JTC's "separate command and
state" hardware (a robot that never moves) is the mock backend's ``frozen_joints``; its action
server is ``robot.follow`` and the awaited :class:`MotionResult`.

Every case runs on the mock backend and on MuJoCo, in lockstep (simulated time, exact instants);
the per-tick setpoint and measured state are recorded by an OBSERVE-phase tick hook.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk import (
    CommandRejected,
    InvalidValueError,
    JointCommand,
    LimitViolation,
    ResultCode,
    Tolerances,
    Trajectory,
    TrajectoryPoint,
    UnknownJointError,
)
from agentsdk.statemachine import State, StateMachine
from agentsdk.trajectory import TrajectorySampler


def _unavailable(backend: str) -> str | None:
    try:
        agentsdk.load_backend(backend)
    except agentsdk.BackendUnavailableError as exc:
        return str(exc)
    return None


BACKENDS = [
    pytest.param(b, marks=pytest.mark.skipif(_unavailable(b) is not None, reason=f"{b}: {_unavailable(b)}"))
    for b in ("mock", "mujoco")
]
#: the stall watchdog measures wall time; a loaded test machine may starve a lockstep run briefly
SAFETY = {"stall_timeout": 5.0}
TURNTABLE = Path(__file__).parent / "fixtures" / "turntable" / "robot.yaml"
ACC_RTOL = 1e-3


@pytest.fixture(params=BACKENDS)
def backend(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.fixture
async def robot(backend: str) -> AsyncIterator[agentsdk.Robot]:
    async with agentsdk.connect(backend, robot="arm3", safety=SAFETY) as bot:
        yield bot


class Log:
    """Per control tick: the time the setpoint was written for, desired q/v, measured q/v after the tick."""

    def __init__(self, robot: agentsdk.Robot) -> None:
        self.dt = robot.control_period
        self.rows: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.handle = robot.add_tick_hook(agentsdk.Phase.OBSERVE, self)

    def __call__(self, stamp: float, st: agentsdk.StateView, sp: agentsdk.SetpointView) -> None:
        self.rows.append(
            (stamp - self.dt, sp.position.copy(), sp.velocity.copy(), st.position.copy(), st.velocity.copy())
        )

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            "t": np.array([r[0] for r in self.rows]),
            "q_des": np.array([r[1] for r in self.rows]),
            "v_des": np.array([r[2] for r in self.rows]),
            "q": np.array([r[3] for r in self.rows]),
            "v": np.array([r[4] for r in self.rows]),
        }


def limits(robot: agentsdk.Robot, names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    infos = {j.name: j for j in robot.joints}
    names = list(names) if names is not None else list(robot.joint_names)
    return {
        "lo": np.array([infos[n].lower for n in names]),
        "hi": np.array([infos[n].upper for n in names]),
        "v": np.array([infos[n].max_velocity for n in names]),
        "a": np.array([infos[n].max_acceleration for n in names]),
    }


def assert_velocity_continuous(robot: agentsdk.Robot, v_des: np.ndarray, names: Sequence[str] | None = None) -> None:
    """The desired velocity never changes faster than the acceleration limit allows (no jump)."""
    idx = [robot.joint_index[n] for n in (names or robot.joint_names)]
    amax = limits(robot, names)["a"]
    acc = np.abs(np.diff(v_des[:, idx], axis=0)) / robot.control_period
    assert np.all(acc <= amax * (1 + ACC_RTOL) + 1e-9), f"max |dv/dt| {acc.max(axis=0)} > {amax}"


async def assert_holds(robot: agentsdk.Robot, at: np.ndarray | None = None, tol: float = 0.01,
                       seconds: float = 0.3) -> np.ndarray:
    """Over ``seconds``: constant setpoint at zero velocity, measured within ``tol`` of ``at`` (if given)."""
    log = Log(robot)
    await robot.clock.sleep(seconds)
    log.handle.remove()
    d = log.arrays()
    assert np.all(d["q_des"] == d["q_des"][0]), "the hold setpoint moved"
    assert np.all(d["v_des"] == 0.0)
    if at is not None:
        err = np.abs(d["q"] - at).max()
        assert err <= tol, f"held {err:.4f} away from {at}"
    return d["q_des"][0]


# ----------------------------------------------------------------- start-up and success


async def test_hold_on_startup(robot: agentsdk.Robot) -> None:
    """JTC ``hold_on_startup``: after activation the command is the position at startup."""
    st = await robot.read()
    sp = robot.setpoint
    np.testing.assert_allclose(sp.position, st.position, atol=1e-9)
    await assert_holds(robot, st.position, tol=0.01)


@pytest.mark.parametrize("with_velocity", [False, True])
async def test_success_single_point_sendgoal(robot: agentsdk.Robot, with_velocity: bool) -> None:
    """JTC ``test_success_single_point_sendgoal`` / ``..._with_velocity_sendgoal``: one point is reached,
    SUCCESSFUL, then held. With a moving last point (``allow_nonzero_velocity_at_end``) we decelerate to
    rest after it instead of holding a point with a velocity (which a position servo cannot do)."""
    goal = np.array([0.4, 0.3, -0.2])
    vel = [0.2, 0.2, 0.2] if with_velocity else None
    traj = Trajectory(robot.joint_names, [TrajectoryPoint(1.0, goal, vel)])
    motion = robot.follow(traj, allow_nonzero_velocity_at_end=with_velocity)
    result = await motion
    assert result.code is ResultCode.SUCCESSFUL, result
    held = await assert_holds(robot)
    if with_velocity:
        assert np.all(held > goal)  # it went on past the point, then stopped
        assert np.all(held - goal < 0.2**2 / 2 / 8.0 + 0.01)
    else:
        np.testing.assert_allclose(held, goal, atol=1e-9)


async def test_success_multi_point_sendgoal(robot: agentsdk.Robot) -> None:
    """JTC ``test_success_multi_point_sendgoal``: feedback progresses through the points, the last is held."""
    q0 = (await robot.read()).position
    pts = [TrajectoryPoint(0.6, q0 + np.array([0.2, 0.1, 0.2])), TrajectoryPoint(1.2, q0 + np.array([0.4, 0.2, 0.4]))]
    motion = robot.follow(Trajectory(robot.joint_names, pts))
    fbs = [fb async for fb in motion.feedback(rate=100.0)]
    result = await motion
    assert result.ok, result
    progress = [fb.progress for fb in fbs]
    assert progress == sorted(progress) and progress[-1] == 1.0
    await assert_holds(robot, q0 + np.array([0.4, 0.2, 0.4]), tol=0.01)


# ----------------------------------------------------------------- validation


def _good(robot: agentsdk.Robot) -> tuple[str, ...]:
    return robot.joint_names


async def test_invalid_message(robot: agentsdk.Robot) -> None:
    """JTC ``invalid_message``: each malformed trajectory is refused with a specific CommandRejected and
    nothing starts; a well-formed one ending in the future is accepted."""
    names = _good(robot)
    with pytest.raises(UnknownJointError, match="bad_name"):
        robot.follow(Trajectory(["bad_name"], [TrajectoryPoint(0.25, [0.1])]))
    with pytest.raises(InvalidValueError, match="no points"):
        Trajectory(names, [])
    with pytest.raises(InvalidValueError, match="point 0: 2 positions for 3 joints"):
        Trajectory(names, [TrajectoryPoint(0.25, [0.1, 0.2])])
    with pytest.raises(InvalidValueError, match="point 0: 4 positions for 3 joints"):
        Trajectory(names, [TrajectoryPoint(0.25, [0.1, 0.2, 0.3, 0.4])])
    with pytest.raises(InvalidValueError, match="point 0: 2 velocities"):
        Trajectory(names, [TrajectoryPoint(0.25, [0.1, 0.2, 0.3], [0.0, 0.0])])
    with pytest.raises(InvalidValueError, match="point 0: 2 accelerations"):
        Trajectory(names, [TrajectoryPoint(0.25, [0.1, 0.2, 0.3], [0, 0, 0], [0.0, 0.0])])
    with pytest.raises(InvalidValueError, match="not after point 0"):
        Trajectory(names, [TrajectoryPoint(0.25, [0.1, 0.2, 0.3]), TrajectoryPoint(0.25, [0.1, 0.2, 0.3])])
    good = Trajectory(names, [TrajectoryPoint(2.0, [0.1, 0.2, 0.3])])
    with pytest.raises(InvalidValueError, match="ended"):  # end time in the past
        robot.follow(good, start_time=robot.clock.now() - 10.0)
    assert not robot.busy
    slow = Trajectory(names, [TrajectoryPoint(10.0, [0.1, 0.2, 0.3])])
    motion = robot.follow(slow, start_time=robot.clock.now())  # ends in the future: accepted
    motion.cancel()
    assert (await motion).code is ResultCode.CANCELED


async def test_nonzero_end_velocity_rejected_unless_allowed(robot: agentsdk.Robot) -> None:
    """JTC ``expect_invalid_when_message_with_nonzero_end_velocity_and_when_param_false`` and
    ``test_allow_nonzero_velocity_at_trajectory_end_false``/``_true``."""
    names = _good(robot)
    q0 = (await robot.read()).position
    pts = [TrajectoryPoint(0.5, q0 + 0.2, [0.3, 0.3, 0.3]), TrajectoryPoint(1.0, q0 + 0.4, [0.3, 0.3, 0.3])]
    traj = Trajectory(names, pts)
    with pytest.raises(InvalidValueError, match=r"point 1 \(the last\): joint 'joint1' velocity 0.3 is not zero"):
        robot.follow(traj)
    assert not robot.busy
    at_rest = Trajectory(names, [pts[0], TrajectoryPoint(1.0, q0 + 0.4, [0.0, 0.0, 0.0])])
    assert (await robot.follow(at_rest)).ok
    back = Trajectory(names, [TrajectoryPoint(1.0, q0, [0.3, 0.3, 0.3])])
    result = await robot.follow(back, allow_nonzero_velocity_at_end=True)
    assert result.ok, result
    await assert_holds(robot)


async def test_point_acceleration_over_the_limit_is_rejected(robot: agentsdk.Robot) -> None:
    """Issue 14 (JTC does not check this): waypoints at 0.2 and 0.3 rad with accelerations of 1e6
    overshot to 1.96 rad and reported SUCCESSFUL; the point's acceleration is checked against
    max_acceleration, naming the point and the joint."""
    traj = Trajectory(["joint1"], [TrajectoryPoint(0.5, [0.2], [0.0], [1e6]),
                                   TrajectoryPoint(1.0, [0.3], [0.0], [0.0])])
    with pytest.raises(LimitViolation, match=r"point 0: joint 'joint1' acceleration 1e\+06 exceeds max_acceleration 8"):
        robot.follow(traj)
    assert not robot.busy


async def test_interpolated_motion_over_the_limits_is_rejected_or_stretched(robot: agentsdk.Robot) -> None:
    """Issue 14: one point 0 -> 1.5 rad in 1 s peaks at 2.81 rad/s between the points (limit 2.5): refused,
    naming the segment and the joint; ``stretch_to_limits=True`` slows it down until it fits."""
    traj = Trajectory(["joint1"], [TrajectoryPoint(1.0, [1.5])])
    with pytest.raises(LimitViolation, match=r"segment start state -> point 0 .*joint 'joint1' velocity reaches 2.81"):
        robot.follow(traj)
    q3 = float(robot.setpoint.position[2])
    with pytest.raises(LimitViolation, match=r"segment point 0 -> point 1 .*joint 'joint3' acceleration"):
        robot.follow(Trajectory(["joint3"], [TrajectoryPoint(0.0, [q3], [0.0]),
                                             TrajectoryPoint(0.3, [q3 + 0.5], [0.0])]))
    with pytest.raises(LimitViolation, match=r"point 0 -> point 1 .*joint 'joint2' position reaches .* outside its"):
        # both points inside the limits [-2, 2]; the cubic between them overshoots to 2.048
        robot.follow(Trajectory(["joint2"], [TrajectoryPoint(1.5, [1.9], [1.0]), TrajectoryPoint(2.5, [1.9], [0.0])]))
    assert not robot.busy
    log = Log(robot)
    motion = robot.follow(traj, stretch_to_limits=True)
    assert motion.trajectory.duration > 1.0
    result = await motion
    assert result.ok, result
    d = log.arrays()
    lim = limits(robot)
    assert np.all(np.abs(d["v_des"]) <= lim["v"] * (1 + 1e-6))
    assert_velocity_continuous(robot, d["v_des"])


# ----------------------------------------------------------------- aborts stop from the measured state


@pytest.mark.parametrize("timed", [False, True], ids=["first_point_at_0", "timed_points"])
async def test_state_tolerances_fail(robot: agentsdk.Robot, timed: bool) -> None:
    """JTC ``test_state_tolerances_fail`` and ``test_no_time_from_start_state_tolerance_fail``: a path
    tolerance violated at once aborts with PATH_TOLERANCE_VIOLATED and the robot holds where it was
    (JTC: ``expectCommandPoint(INITIAL_POS_JOINTS)``). Issue 14: the stop starts from the measured state;
    with timed points no joint passes the trajectory's last point or leaves its range."""
    log = Log(robot)
    q0 = (await robot.read()).position.copy()
    if timed:
        pts = [TrajectoryPoint(0.5, q0 + [0.3, 0.3, 0.3]), TrajectoryPoint(1.0, q0 + [0.6, 0.6, 0.6])]  # noqa: RUF005
    else:
        pts = [TrajectoryPoint(0.0, q0 + [0.3, 0.3, 0.4]), TrajectoryPoint(0.5, q0 + [0.5, 0.5, 0.6])]  # noqa: RUF005
    result = await robot.follow(Trajectory(robot.joint_names, pts), Tolerances(path=1e-4))
    assert result.code is ResultCode.PATH_TOLERANCE_VIOLATED, result
    assert result.time < 0.5
    await robot.clock.sleep(0.5)
    d = log.arrays()
    assert np.abs(d["q"][-1] - q0).max() <= 0.05, d["q"][-1] - q0
    last = np.asarray(pts[-1].positions)
    lim = limits(robot)
    assert np.all(d["q"] <= last + 1e-9), "a joint passed the trajectory's last point"
    assert np.all((d["q"] >= lim["lo"]) & (d["q"] <= lim["hi"]))
    assert np.all(d["q_des"] <= last + 1e-9)
    await assert_holds(robot, d["q"][-1], tol=0.01)
    assert not any(e.kind == "clip" for e in robot.safety.events)


async def test_path_tolerance_abort_drops_the_reference_of_a_stuck_joint() -> None:
    """JTC ``test_state_tolerances_fail`` with one stuck joint (mock ``frozen_joints``): the stuck joint's
    setpoint goes back to where it is at once (JTC holds the current position), the others decelerate
    within their limits, then everything holds."""
    async with agentsdk.connect("mock", robot="arm3", frozen_joints=["joint2"], safety=SAFETY) as robot:
        log = Log(robot)
        q0 = (await robot.read()).position.copy()
        traj = Trajectory(["joint1", "joint2"], [TrajectoryPoint(1.0, [0.8, 0.8])])
        result = await robot.follow(traj, Tolerances(path=0.05))
        assert result.code is ResultCode.PATH_TOLERANCE_VIOLATED and "joint2" in result.message
        d = log.arrays()
        k = int(np.flatnonzero(d["v_des"][:, 1] != 0.0)[-1]) + 1  # the abort tick
        assert np.all(d["q_des"][k:, 1] == q0[1])
        assert_velocity_continuous(robot, d["v_des"][:k], ["joint1"])
        assert_velocity_continuous(robot, d["v_des"][k:], ["joint1"])
        await assert_holds(robot)


async def test_goal_tolerances_fail(backend: str) -> None:
    """JTC ``test_goal_tolerances_fail``: the goal is not reached within goal_time -> GOAL_TOLERANCE_VIOLATED,
    then the robot holds where it is, not at the goal it failed to reach (issue 14: within 0.02 rad of the
    measured position at the abort)."""
    options: dict[str, Any] = {"lag": 0.08} if backend == "mock" else {}
    async with agentsdk.connect(backend, robot="arm3", safety=SAFETY, **options) as robot:
        q0 = (await robot.read()).position
        at_abort: list[np.ndarray] = []
        motion = robot.follow(Trajectory(robot.joint_names, [TrajectoryPoint(1.0, q0 + np.array([0.4, 0.3, -0.4]))]),
                              Tolerances(goal=1e-6, goal_time=0.01))

        def watch(t: float, st: agentsdk.StateView, sp: agentsdk.SetpointView) -> None:
            if motion.done() and not at_abort:
                at_abort.append(st.position.copy())

        robot.add_tick_hook(agentsdk.Phase.OBSERVE, watch)
        result = await motion
        assert result.code is ResultCode.GOAL_TOLERANCE_VIOLATED, result
        assert result.time == pytest.approx(1.0 + 0.01, abs=2 * robot.control_period)
        await robot.clock.sleep(0.5)
        measured = (await robot.read()).position
        assert np.abs(measured - at_abort[0]).max() <= 0.02
        await assert_holds(robot, measured, tol=0.005)


async def test_goal_tolerance_abort_does_not_pull_a_stuck_joint_to_the_goal() -> None:
    """JTC ``test_goal_tolerances_fail`` with a joint that never moves: the hold is its measured position."""
    # (the following-error check is off: a stuck joint latches it, this test is about the goal tolerance)
    safety = {**SAFETY, "following_error_window": None}
    async with agentsdk.connect("mock", robot="arm3", frozen_joints=["joint2"], safety=safety) as robot:
        q0 = (await robot.read()).position.copy()
        result = await robot.follow(Trajectory(["joint1", "joint2"], [TrajectoryPoint(0.5, [0.3, 0.3])]),
                                    Tolerances(goal=0.02, goal_time=0.1))
        assert result.code is ResultCode.GOAL_TOLERANCE_VIOLATED and "joint2" in result.message
        await robot.clock.sleep(0.1)
        assert robot.setpoint.position[1] == q0[1]
        await assert_holds(robot, np.array([0.3, q0[1], q0[2]]), tol=1e-6)


@pytest.mark.parametrize("category", [1, 2])
async def test_category_stop_from_measured_state_within_deceleration_limit(backend: str, category: int) -> None:
    """Issue 14 (JTC ``decelerate_to_hold_position_*``): a category 1/2 stop decelerates every joint from
    where it is within its deceleration limit (never beyond it), then holds (2) or removes torque (1)."""
    async with agentsdk.connect(backend, robot="arm3", safety=SAFETY) as robot:
        motion = robot.follow(Trajectory(["joint1", "joint3"], [TrajectoryPoint(2.5, [2.5, -2.5])]))
        await robot.clock.sleep(0.9)
        log = Log(robot)
        await robot.estop(category)
        assert (await motion).code is ResultCode.ABORTED
        d = log.arrays()
        acc = np.abs(np.diff(d["v_des"], axis=0)) / robot.control_period
        amax = limits(robot)["a"] * robot.safety.config.stop_deceleration_scale
        assert np.all(acc <= amax * (1 + ACC_RTOL) + 1e-9), acc.max(axis=0)
        if backend == "mock":  # an ideal servo: the measured motion is the desired one
            acc_meas = np.abs(np.diff(d["v"][1:], axis=0)) / robot.control_period
            assert np.all(acc_meas <= amax * 1.05 + 1e-6), acc_meas.max(axis=0)
        assert np.all(np.abs(d["v_des"][-1]) == 0.0)


async def test_a_first_point_far_from_the_robot_is_aborted_not_clipped(robot: agentsdk.Robot) -> None:
    """Issue 14: a planned step the position-step limiter would have clipped silently (JTC jumps to a
    first point at ``time_from_start`` 0) aborts before anything moves, with a safety event."""
    q0 = (await robot.read()).position.copy()
    log = Log(robot)
    result = await robot.follow(Trajectory(["joint1"], [TrajectoryPoint(0.0, [q0[0] + 0.3]),
                                                        TrajectoryPoint(1.0, [q0[0] + 0.5])]))
    assert result.code is ResultCode.ABORTED and "max_position_step" in result.message, result
    assert any(e.kind == "step" and e.joint == "joint1" for e in robot.safety.events)
    d = log.arrays()
    assert np.abs(d["q_des"][:, 0] - q0[0]).max() < 1e-9  # the setpoint never moved
    await assert_holds(robot, q0, tol=0.01)


# ----------------------------------------------------------------- cancel and preemption


async def test_cancel_decelerate_to_hold_position(robot: agentsdk.Robot) -> None:
    """JTC ``test_cancel_hold_position`` / ``test_cancel_decelerate_to_hold_position``: cancel after half of
    the trajectory -> CANCELED; the joints ramp to zero velocity within their limits, then hold."""
    log = Log(robot)
    motion = robot.follow(Trajectory(robot.joint_names, [TrajectoryPoint(1.0, [0.8, 0.6, -0.8])]))
    await robot.clock.sleep(0.5)
    motion.cancel()
    result = await motion
    assert result.code is ResultCode.CANCELED
    d = log.arrays()
    assert_velocity_continuous(robot, d["v_des"])
    assert np.all(d["v_des"][-1] == 0.0)
    held = await assert_holds(robot)
    assert np.all(np.abs(held) < [0.8, 0.6, 0.8])


def _stop_distance(v: float, a: float, j: float) -> float:
    """Distance to rest from speed ``v`` at zero acceleration, deceleration limit ``a``, jerk limit ``j``
    (JTC's ``v**2 / (2 a)`` plus the jerk-limited ramps: trapezoidal or triangular acceleration)."""
    v = abs(v)
    return v * v / (2 * a) + v * a / (2 * j) if v >= a * a / j else v * math.sqrt(v / j)


async def test_decelerate_to_hold_position_per_joint_calculation(robot: agentsdk.Robot) -> None:
    """JTC ``decelerate_to_hold_position_positive_velocity``, ``..._negative_velocity``,
    ``..._per_joint_calculation`` and ``..._velocity_command_ramps_to_zero``: cancelled while joint1 moves
    forward, joint2 backward and joint3 stands still, each joint stops on its own at its own distance in
    the direction it moved -- exactly where its limits put it -- its velocity ramps monotonically to zero,
    and the stationary joint holds where it was.

    Differs on purpose: JTC holds at ``p0 + v0**2 / (2 max_deceleration_on_cancel)`` (only with
    ``decelerate_on_cancel``); we always decelerate, at ``max_acceleration * stop_deceleration_scale``
    and jerk-limited, so the distance adds the jerk ramps (computed here analytically)."""
    names = robot.joint_names
    infos = {j.name: j for j in robot.joints}
    scale = robot.safety.config.stop_deceleration_scale
    q0 = robot.setpoint.position.copy()
    v0 = np.array([0.3, -0.2, 0.0])
    # cruise at constant velocity between t=1 and t=2 (a cubic with equal end velocities on a line)
    traj = Trajectory(names, [TrajectoryPoint(1.0, q0 + v0 * 0.5, v0),
                              TrajectoryPoint(2.0, q0 + v0 * 1.5, v0),
                              TrajectoryPoint(3.0, q0 + v0 * 2.0, [0.0, 0.0, 0.0])])
    motion = robot.follow(traj)
    await robot.clock.sleep(1.5)
    log = Log(robot)
    motion.cancel()
    result = await motion
    assert result.code is ResultCode.CANCELED
    d = log.arrays()
    cruising = np.flatnonzero(np.all(np.abs(d["v_des"] - v0) < 1e-12, axis=1))
    start = int(cruising[-1])  # the stop's first sample: the cruise state, at zero acceleration
    q_c = d["q_des"][start]
    held = await assert_holds(robot)
    for k, n in enumerate(names):
        expect = q_c[k] + math.copysign(_stop_distance(v0[k], infos[n].max_acceleration * scale,
                                                       infos[n].max_jerk), v0[k])
        assert held[k] == pytest.approx(expect, abs=1e-6), n
        speed = np.abs(d["v_des"][start:, k])
        assert np.all(np.diff(speed) <= 1e-12), f"{n}: the velocity command did not ramp down monotonically"
    assert held[2] == q0[2]
    assert_velocity_continuous(robot, d["v_des"])


async def test_preempted_goal_receives_a_result(robot: agentsdk.Robot) -> None:
    """JTC ``preempted_goal_receives_aborted_result``: goal A is ended when B arrives, B succeeds. JTC
    reports A as ABORTED/INVALID_GOAL; we report PREEMPTED (and B starts from A's desired state)."""
    a = robot.follow(Trajectory(robot.joint_names, [TrajectoryPoint(2.0, [0.8, 0.5, 0.6])]))
    await robot.clock.sleep(0.2)
    b = robot.follow(Trajectory(robot.joint_names, [TrajectoryPoint(0.8, [0.1, 0.1, 0.1])]))
    assert (await a).code is ResultCode.PREEMPTED
    assert (await b).ok


async def test_trajectory_replace(robot: agentsdk.Robot) -> None:
    """JTC ``test_trajectory_replace`` (allow_partial_joints_goal): after the old trajectory, a partial one
    moves only its joint; the others keep the old trajectory's end."""
    old = Trajectory(robot.joint_names, [TrajectoryPoint(0.5, [0.2, 0.3, 0.4], [0.0, 0.0, 0.0])])
    assert (await robot.follow(old)).ok
    assert (await robot.follow(Trajectory(["joint1"], [TrajectoryPoint(0.5, [0.15], [0.0])]))).ok
    sp = robot.setpoint.position
    np.testing.assert_allclose(sp, [0.15, 0.3, 0.4], atol=1e-9)


async def test_partial_joint_list(robot: agentsdk.Robot) -> None:
    """JTC ``test_partial_joint_list``: a trajectory naming a subset (in another order) moves those joints;
    joint3's command stays exactly its current position (velocity 0)."""
    before = robot.setpoint.position.copy()
    log = Log(robot)
    assert (await robot.follow(Trajectory(["joint2", "joint1"], [TrajectoryPoint(0.8, [0.25, 0.5])]))).ok
    d = log.arrays()
    assert np.all(d["q_des"][:, 2] == before[2]) and np.all(d["v_des"][:, 2] == 0.0)
    np.testing.assert_allclose(robot.setpoint.position[:2], [0.5, 0.25], atol=1e-9)


async def test_jumbled_joint_order(robot: agentsdk.Robot) -> None:
    """JTC ``test_jumbled_joint_order``: joint names in another order than the robot's map to the right joints."""
    traj = Trajectory(["joint2", "joint3", "joint1"],
                      [TrajectoryPoint(0.75, [0.2, 0.3, 0.1], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])])
    assert (await robot.follow(traj)).ok
    np.testing.assert_allclose(robot.setpoint.position, [0.1, 0.2, 0.3], atol=1e-9)


async def test_direct_command_rejected_while_a_start_is_scheduled(robot: agentsdk.Robot) -> None:
    """A scheduled trajectory reserves its joints (like an active JTC goal owns its command interfaces)."""
    motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(0.5, [0.2])]), start_time=robot.clock.now() + 1.0)
    with pytest.raises(CommandRejected, match="driven by a running trajectory"):
        await robot.command(JointCommand("position", {"joint1": 0.1}))
    motion.cancel()
    assert (await motion).code is ResultCode.CANCELED


# ----------------------------------------------------------------- scheduled start (header.stamp)


async def test_execute_partial_traj_in_future(robot: agentsdk.Robot) -> None:
    """JTC ``test_execute_partial_traj_in_future`` (trajectory replacement with a future ``header.stamp``):
    the running trajectory continues until the new one's start time, which then replaces it from its
    desired state (PREEMPTED at that instant, velocity continuous) and reaches its point on schedule."""
    log = Log(robot)
    first = robot.follow(Trajectory(robot.joint_names, [TrajectoryPoint(2.0, [1.0, 0.6, -1.0])]))
    await robot.clock.sleep(0.4)
    t_start = robot.clock.now() + 0.5
    second = robot.follow(Trajectory(["joint1", "joint2"], [TrajectoryPoint(1.0, [0.2, 0.2])]), start_time=t_start)
    assert second.start_time == t_start
    r1 = await first
    assert r1.code is ResultCode.PREEMPTED and r1.time == pytest.approx(t_start, abs=1e-9)
    r2 = await second
    assert r2.ok, r2
    assert r2.time == pytest.approx(t_start + 1.0, abs=1e-9)
    d = log.arrays()
    # until t_start the first trajectory ran undisturbed: the same as a sampler of it
    assert_velocity_continuous(robot, d["v_des"])
    np.testing.assert_allclose(d["q_des"][-1][:2], [0.2, 0.2], atol=1e-9)


async def test_scheduled_start_holds_until_its_time(robot: agentsdk.Robot) -> None:
    """JTC trajectory replacement, first example (``new_trajectory.png``): between now and the
    trajectory's start the position hold is kept exactly; it starts at its start time."""
    log = Log(robot)
    held = robot.setpoint.position.copy()
    t0 = robot.clock.now()
    motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(0.5, [0.3])]), start_time=t0 + 0.3)
    result = await motion
    assert result.ok and result.time == pytest.approx(t0 + 0.8, abs=1e-9)
    d = log.arrays()
    before = d["t"] < t0 + 0.3 - 1e-9
    assert before.sum() >= 140
    assert np.all(d["q_des"][before] == held) and np.all(d["v_des"][before] == 0.0)
    assert np.any(d["q_des"][~before, 0] != held[0])


async def test_ignore_old_trajectory(robot: agentsdk.Robot) -> None:
    """JTC ``test_ignore_old_trajectory``: a trajectory that ended before now is refused; the robot keeps
    its hold."""
    assert (await robot.follow(Trajectory(robot.joint_names, [TrajectoryPoint(0.5, [0.2, 0.3, 0.4])]))).ok
    with pytest.raises(InvalidValueError, match="ended"):
        robot.follow(Trajectory(robot.joint_names, [TrajectoryPoint(0.5, [-0.1, -0.2, -0.3])]),
                     start_time=robot.clock.now() - 0.6)
    await assert_holds(robot, np.array([0.2, 0.3, 0.4]), tol=0.01)


async def test_partial_old_trajectory_skips_what_has_elapsed(robot: agentsdk.Robot) -> None:
    """JTC ``test_ignore_partial_old_trajectory`` / ``trajectory_replacement_past.png``: a start in the past
    discards the points whose time has passed and realizes the rest on their original schedule. (JTC's
    test stamps the new goal so far back on the ROS clock that its *end* has passed: ignored; that case
    is ``test_ignore_old_trajectory`` here.)"""
    log = Log(robot)
    now = robot.clock.now()
    traj = Trajectory(["joint1"], [TrajectoryPoint(0.5, [-0.3]), TrajectoryPoint(1.5, [0.6])])
    motion = robot.follow(traj, start_time=now - 0.6)
    assert len(motion.trajectory.points) == 1
    result = await motion
    assert result.ok, result
    assert result.time == pytest.approx(now - 0.6 + 1.5, abs=1e-9)
    d = log.arrays()
    assert d["q_des"][:, 0].min() >= -1e-9  # never went to the elapsed point at -0.3


# ----------------------------------------------------------------- speed scaling


async def test_setting_scaling_factor_works_correctly(robot: agentsdk.Robot) -> None:
    """JTC ``setting_scaling_factor_works_correctly``: 0.765 is taken, 0.0 is a valid edge case; a
    negative value is refused (JTC ignores it) and the previous factor stays. We also refuse > 1 and NaN."""
    assert robot.speed_scaling == 1.0
    robot.set_speed_scaling(0.765)
    assert robot.speed_scaling == 0.765
    robot.set_speed_scaling(0.0)
    assert robot.speed_scaling == 0.0
    robot.set_speed_scaling(0.45)
    for bad in (-0.12, 1.5, math.nan, math.inf, "fast"):
        with pytest.raises(InvalidValueError, match="speed scaling"):
            robot.set_speed_scaling(bad)  # type: ignore[arg-type]
    assert robot.speed_scaling == 0.45


@pytest.mark.parametrize("factor", [0.25, 0.87, 1.0])
async def test_scaling_sampling_is_correct(robot: agentsdk.Robot, factor: float) -> None:
    """JTC ``test_scaling_sampling_is_correct`` and ``test_scaling_execution_time_succeeds``: with a constant
    factor the reference is the trajectory sampled at ``t0 + factor * (t - t0)``, exactly, and the motion
    takes ``duration / factor``."""
    robot.set_speed_scaling(factor)
    q0, v0 = robot.setpoint.position.copy(), np.zeros(3)
    traj = Trajectory(robot.joint_names, [TrajectoryPoint(0.5, q0 + np.array([0.2, 0.1, -0.2])),
                                          TrajectoryPoint(1.0, q0 + np.array([0.4, 0.2, -0.4]))])
    t0 = robot.clock.now()
    log = Log(robot)
    result = await robot.follow(traj, Tolerances(goal=1e-3, goal_time=0.1))
    assert result.ok, result
    assert result.time == pytest.approx(t0 + 1.0 / factor, abs=robot.control_period + 1e-9)
    ref = TrajectorySampler(traj, t0, q0, v0, v0)
    d = log.arrays()
    for t, q in zip(d["t"], d["q_des"], strict=True):
        if t <= t0 + 1.0 / factor:
            np.testing.assert_allclose(q, ref.sample(t0 + factor * (t - t0))[0], atol=1e-9)


async def test_speed_scaling_pause_and_resume(backend: str) -> None:
    """Issue 14 (JTC speed scaling, the UR speed slider): a factor of 0 pauses a running trajectory, 1
    resumes it, without a velocity jump; while paused the reference stands still exactly, the path
    tolerance holds and goal_time does not run out; the motion then completes SUCCESSFUL."""
    async with agentsdk.connect(backend, robot="arm3", safety=SAFETY) as robot:
        log = Log(robot)
        motion = robot.follow(Trajectory(["joint1", "joint3"], [TrajectoryPoint(2.0, [2.0, -2.0])]),
                              Tolerances(path=0.05, goal_time=0.05))
        await robot.clock.sleep(0.8)
        robot.set_speed_scaling(0.0)
        t_pause = robot.clock.now()
        await robot.clock.sleep(1.5)
        assert not motion.done()
        robot.set_speed_scaling(1.0)
        t_resume = robot.clock.now()
        result = await motion
        assert result.ok, result
        d = log.arrays()
        assert_velocity_continuous(robot, d["v_des"])
        paused = (d["t"] > t_pause + 0.6) & (d["t"] < t_resume - 1e-9)
        assert paused.sum() > 400
        assert np.all(d["v_des"][paused] == 0.0)
        assert np.all(d["q_des"][paused] == d["q_des"][paused][0])
        speed = np.abs(d["v_des"][:, 0])
        before = (d["t"] > t_pause - 0.1) & (d["t"] <= t_pause)
        assert speed[before].min() > 0.5  # it was moving when paused
        # JTC semantics: the motion took the trajectory time plus the paused time (and the ramps)
        assert result.time > 2.0 + (t_resume - t_pause)


async def test_speed_scaling_from_another_task_and_a_state_machine(robot: agentsdk.Robot) -> None:
    """Speed scaling is usable from any task and from a state machine state: a supervisor halves the speed
    while the behavior awaits its motion; a state body sets it for the motions it starts."""

    async def supervisor() -> None:
        await robot.clock.sleep(0.1)
        robot.set_speed_scaling(0.5)

    t0 = robot.clock.now()
    task = asyncio.create_task(supervisor())
    result = await robot.follow(Trajectory(["joint1"], [TrajectoryPoint(1.0, [0.5])]))
    await task
    assert result.ok and result.time - t0 > 1.5

    class Slow(StateMachine):
        go = State(initial=True)
        done = State(final=True)
        finish = go.to(done)

        async def on_go(self, ctx: Any) -> str:
            ctx.robot.set_speed_scaling(0.25)
            t = ctx.robot.clock.now()
            res = await ctx.robot.follow(Trajectory(["joint1"], [TrajectoryPoint(1.0, [0.0])]))
            assert res.ok and res.time - t >= 4.0 - 1e-9
            ctx.robot.set_speed_scaling(1.0)
            return "finish"

    assert await Slow(robot).run() == "done"
    assert robot.speed_scaling == 1.0


async def test_stops_are_never_slowed_by_speed_scaling(robot: agentsdk.Robot) -> None:
    """A cancel while slowed decelerates at the joints' limits, not at the scaled speed."""
    motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(1.5, [2.0])]))
    await robot.clock.sleep(0.7)
    robot.set_speed_scaling(0.3)
    await robot.clock.sleep(0.5)
    log = Log(robot)
    motion.cancel()
    t = robot.clock.now()
    result = await motion
    assert result.code is ResultCode.CANCELED
    d = log.arrays()
    assert_velocity_continuous(robot, d["v_des"])
    assert result.time - t < 0.3


# ----------------------------------------------------------------- continuous joints (urdf_rrrbot_continuous)


@pytest.fixture
async def turntable(backend: str) -> AsyncIterator[agentsdk.Robot]:
    async with agentsdk.connect(backend, robot=TURNTABLE, safety=SAFETY) as bot:
        yield bot


async def test_position_error_angle_wraparound(turntable: agentsdk.Robot) -> None:
    """JTC ``position_error_angle_wraparound``, ``compute_error_angle_wraparound_true`` and
    ``TestWrapAroundJoint.wraparound_single_joint``: a continuous joint sent from 0 to 3*pi/2 takes the
    shortest way (-pi/2: at most pi/2 + 0.05 rad of travel), its errors wrap around, and the result's
    error is the wrapped one. The revolute joint is not wrapped (``..._angle_wraparound_false``)."""
    robot = turntable
    log = Log(robot)
    motion = robot.follow(Trajectory(["spin", "tilt"], [TrajectoryPoint(3.0, [1.5 * math.pi, 1.5 * math.pi])]),
                          Tolerances(path=0.1, goal=0.02))
    fbs = [fb async for fb in motion.feedback(rate=50.0)]
    result = await motion
    assert result.ok, result
    d = log.arrays()
    spin, tilt = d["q"][:, 0], d["q"][:, 1]
    assert spin.max() - spin.min() <= math.pi / 2 + 0.05
    assert abs(math.remainder(spin[-1] - 1.5 * math.pi, 2 * math.pi)) < 0.02
    assert tilt.max() - tilt.min() >= 1.5 * math.pi - 0.02  # revolute: the whole way, not wrapped
    assert all(abs(fb.error[0]) < 0.1 for fb in fbs)
    assert abs(result.error["spin"]) < 0.02 and abs(result.error["tilt"]) < 0.02


async def test_compute_error_wraps_for_continuous_joints_only(turntable: agentsdk.Robot) -> None:
    """JTC ``compute_error_angle_wraparound_true/false``: a goal 2*pi away from where a continuous joint is
    is already reached (no motion, SUCCESSFUL, error ~0: ``wraparound_all_joints_no_offset``); at exactly
    half a turn it turns towards the target's raw value (JTC's singularity rule)."""
    robot = turntable
    log = Log(robot)
    result = await robot.follow(Trajectory(["spin"], [TrajectoryPoint(0.5, [2 * math.pi])]), Tolerances(goal=0.01))
    assert result.ok and abs(result.error["spin"]) < 0.01
    assert np.abs(log.arrays()["q_des"][:, 0]).max() < 1e-9
    result = await robot.follow(Trajectory(["spin"], [TrajectoryPoint(2.5, [math.pi])]), Tolerances(goal=0.02))
    assert result.ok, result
    assert robot.setpoint.position[0] == pytest.approx(math.pi)  # +pi, not -pi
    result = await robot.move_to({"spin": -0.5 * math.pi})  # move_to takes the shortest angle too
    assert result.ok
    assert robot.setpoint.position[0] == pytest.approx(1.5 * math.pi)


# ----------------------------------------------------------------- tolerances (test_tolerances.cpp)


def test_invalid_tolerances() -> None:
    """JTC ``test_invalid_tolerances`` and issue 10: NaN, zero or negative tolerances and goal times are
    refused when the Tolerances are built (``Tolerances(path={j: nan})`` used to disable the check)."""
    for bad in (math.nan, 0.0, -0.1, "x"):
        with pytest.raises(InvalidValueError, match="path"):
            Tolerances(path=bad)  # type: ignore[arg-type]
        with pytest.raises(InvalidValueError, match="goal"):
            Tolerances(goal={"joint1": bad})  # type: ignore[dict-item]
        with pytest.raises(InvalidValueError, match="path"):
            Tolerances(path={"joint1": bad})  # type: ignore[dict-item]
    for bad in (math.nan, -1.0, "soon"):
        with pytest.raises(InvalidValueError, match="goal_time"):
            Tolerances(goal_time=bad)  # type: ignore[arg-type]
    Tolerances(path=math.inf, goal={"joint1": 0.1}, goal_time=0.0)


@pytest.mark.parametrize("which", ["path", "goal"])
async def test_invalid_joints_tolerance(robot: agentsdk.Robot, which: str) -> None:
    """JTC ``test_invalid_joints_path_tolerance`` / ``test_invalid_joints_goal_tolerance``: a tolerance for
    a joint that is not in the trajectory is refused."""
    tol = Tolerances(**{which: {"joint1": 0.1, "not_a_joint": 0.1}})  # type: ignore[arg-type]
    with pytest.raises(UnknownJointError, match="not_a_joint"):
        robot.follow(Trajectory(["joint1"], [TrajectoryPoint(0.5, [0.1])]), tol)
    assert not robot.busy
