"""Issue acceptance: trajectory execution (agentsdk.motion) on every simulated backend, in lockstep.

Every test records the servo setpoint (desired position and velocity) and the
measured position at every control tick through an OBSERVE-phase tick hook
(or the motion's own feedback), so the checks are on the exact per-tick signals.
Time is simulated (lockstep): nothing here depends on the wall clock.
"""

from __future__ import annotations

import asyncio
import itertools
import math
from collections.abc import AsyncIterator, Sequence

import numpy as np
import pytest
from conftest import lockstep_backends

import agentsdk
from agentsdk import (
    AgentTimeoutError,
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

#: every lockstep backend in the registry (gated on capabilities, see conftest)
BACKENDS = lockstep_backends()

#: the event-loop stall watchdog measures wall time; on a loaded test machine a lockstep run can be
#: starved for its default 0.25 s without anything being wrong, so it gets more slack here
SAFETY = {"stall_timeout": 5.0}

#: relative slack on acceleration bounds (finite differences of exact polynomials, float noise)
ACC_RTOL = 1e-3


@pytest.fixture(params=BACKENDS)
def backend(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.fixture
async def robot(backend: str) -> AsyncIterator[agentsdk.Robot]:
    async with agentsdk.connect(backend, robot="arm3", safety=SAFETY) as bot:
        yield bot


class TickLog:
    """Per control tick: time ``t`` the setpoint was written for, desired q/v, and the measured q after the tick."""

    def __init__(self, robot: agentsdk.Robot) -> None:
        self.dt = robot.control_period
        self.rows: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = []
        robot.add_tick_hook(agentsdk.Phase.OBSERVE, self)

    def __call__(self, stamp: float, st: agentsdk.StateView, sp: agentsdk.SetpointView) -> None:
        self.rows.append((stamp - self.dt, sp.position.copy(), sp.velocity.copy(), st.position.copy()))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        t = np.array([r[0] for r in self.rows])
        return (
            t,
            np.array([r[1] for r in self.rows]),
            np.array([r[2] for r in self.rows]),
            np.array([r[3] for r in self.rows]),
        )


def quintic_trajectory(names: Sequence[str], q0: np.ndarray, q1: np.ndarray, duration: float, n: int) -> Trajectory:
    """Minimum-jerk (quintic) path q0 -> q1 sampled at n+1 points with exact velocities and accelerations."""
    pts = []
    dq = q1 - q0
    for i in range(n + 1):
        t = duration * i / n
        s = t / duration
        p = 10 * s**3 - 15 * s**4 + 6 * s**5
        dp = (30 * s**2 - 60 * s**3 + 30 * s**4) / duration
        ddp = (60 * s - 180 * s**2 + 120 * s**3) / duration**2
        pts.append(TrajectoryPoint(t, q0 + dq * p, dq * dp, dq * ddp))
    return Trajectory(names, pts)


def far_move(robot: agentsdk.Robot, duration: float = 2.0) -> Trajectory:
    """joint1 +2.5 rad and joint3 -2.5 rad in ``duration`` s: fast enough to have speed to stop from."""
    return Trajectory(["joint1", "joint3"], [TrajectoryPoint(duration, [2.5, -2.5])])


def decel_limits(robot: agentsdk.Robot, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    scale = robot.safety.config.stop_deceleration_scale
    infos = {j.name: j for j in robot.joints}
    amax = np.array([infos[n].max_acceleration * scale for n in names])
    jmax = np.array([infos[n].max_jerk for n in names])
    return amax, jmax


def stop_time_bound(v0: np.ndarray, a0: np.ndarray, amax: np.ndarray, jmax: np.ndarray, dt: float) -> float:
    """Upper bound of a jerk-limited stop from (v0, a0): ramp a0 to -amax, brake, ramp back to 0.

    With a0 pointing along v0 the speed first grows by a0^2 / (2 jmax) while the
    acceleration ramps down; two control ticks of slack for sampling.
    """
    along = np.maximum(0.0, np.sign(v0) * a0)
    peak = np.abs(v0) + along**2 / (2 * jmax)
    t = (along + amax) / jmax + amax / jmax + peak / amax
    return float(np.max(t)) + 2 * dt


def check_stop(
    robot: agentsdk.Robot, log: TickLog, names: Sequence[str], t_cancel: float, result: agentsdk.MotionResult
) -> float:
    """Desired velocity after ``t_cancel``: |dv/dt| within the deceleration limit, at rest in time. Returns t_rest."""
    idx = [robot.joint_index[n] for n in names]
    amax, jmax = decel_limits(robot, names)
    dt = log.dt
    t, q, v, _ = log.arrays()
    v = v[:, idx]
    k0 = int(np.searchsorted(t, t_cancel - 1e-9))  # first tick written after the cancel
    assert k0 >= 2, "cancelled before the motion started"
    # no faster than the deceleration limit allows (the whole motion, the switch included)
    acc = np.diff(v[k0 - 2 :], axis=0) / dt
    assert np.all(np.abs(acc) <= amax * (1 + ACC_RTOL) + 1e-9), f"max |dv/dt| {np.abs(acc).max(0)} > {amax}"
    # ... and no slower than it requires
    v0 = v[k0]
    a0 = (v[k0] - v[k0 - 1]) / dt
    assert np.all(np.abs(v0) > 0.5), f"cancel at too low a speed to test anything: {v0}"
    still = np.all(np.abs(v[k0:]) < 1e-9, axis=1)
    assert still.any(), "never came to rest"
    k_rest = k0 + int(np.argmax(still))
    assert still[k_rest - k0 :].all(), "moved again after coming to rest"
    t_rest = t[k_rest]
    bound = stop_time_bound(v0, a0, amax, jmax, dt)
    assert t_rest - t_cancel <= bound, f"stop took {t_rest - t_cancel:.4f} s > bound {bound:.4f} s"
    assert t_rest - t_cancel >= np.max(np.abs(v0) / amax) - 2 * dt  # physically impossible otherwise
    assert result.time <= t_rest + 2 * dt
    # the desired position moves consistently with the desired velocity (no jump, no stall)
    qq = q[k0 - 2 :, idx]
    vv = v[k0 - 2 :]
    step = np.diff(qq, axis=0) - 0.5 * (vv[1:] + vv[:-1]) * dt
    assert np.abs(step).max() < 1e-4, f"desired position inconsistent with desired velocity: {np.abs(step).max()}"
    return t_rest


async def check_holds(robot: agentsdk.Robot, names: Sequence[str], seconds: float = 0.5, tol: float = 0.01) -> None:
    """Over ``seconds``: setpoint constant with zero velocity; measured position within ``tol`` of it."""
    idx = [robot.joint_index[n] for n in names]
    log = TickLog(robot)
    await robot.clock.sleep(seconds)
    _, q, v, x = log.arrays()
    q, v, x = q[:, idx], v[:, idx], x[:, idx]
    assert np.all(q == q[0]), "hold setpoint moved"
    assert np.all(v == 0.0), "hold with non-zero desired velocity"
    err = np.abs(x - q[0]).max()
    assert err <= tol, f"drifted {err:.4f} rad from the hold position"


# --------------------------------------------------------------------------- 1. tracking


async def test_quintic_trajectory_tracks_within_rms(robot: agentsdk.Robot) -> None:
    st = await robot.read()
    q0 = st.position.copy()
    q1 = q0 + np.array([1.0, 0.6, -1.0])
    traj = quintic_trajectory(robot.joint_names, q0, q1, duration=2.0, n=8)
    assert traj.velocities is not None and traj.accelerations is not None
    motion = robot.follow(traj)
    errors = []
    async for fb in motion.feedback(rate=1.0 / robot.control_period):  # every control tick
        errors.append(fb.desired_positions - fb.actual_positions)
    result = await motion
    assert result.code is ResultCode.SUCCESSFUL, result
    err = np.array(errors)
    assert len(err) >= 2.0 / robot.control_period
    rms = np.sqrt(np.mean(err**2, axis=0))
    assert np.all(rms < 0.01), f"RMS tracking error {dict(zip(robot.joint_names, rms.round(5), strict=True))}"
    final = await robot.read()
    assert np.abs(final.position - q1).max() < 0.02


# --------------------------------------------------------------------------- 2. cancel


@pytest.mark.parametrize("how", ["cancel", "task_cancel", "clock_timeout"])
async def test_cancel_decelerates_within_limits_then_holds(robot: agentsdk.Robot, how: str) -> None:
    log = TickLog(robot)
    motion = robot.follow(far_move(robot))
    t_stop_at = 0.8
    if how == "cancel":
        await robot.clock.sleep(t_stop_at)
        t_cancel = robot.clock.now()
        motion.cancel()
    elif how == "task_cancel":

        async def waiter() -> agentsdk.MotionResult:
            return await motion

        task = asyncio.create_task(waiter())
        await robot.clock.sleep(t_stop_at)
        t_cancel = robot.clock.now()
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
    else:
        with pytest.raises(AgentTimeoutError):
            async with robot.clock.timeout(t_stop_at):
                await motion
        t_cancel = robot.clock.now()
    assert not motion.done()  # decelerating, not frozen
    result = await motion
    assert result.code is ResultCode.CANCELED, result
    check_stop(robot, log, ["joint1", "joint3"], t_cancel, result)
    await check_holds(robot, ["joint1", "joint2", "joint3"])


# --------------------------------------------------------------------------- 3. preemption


@pytest.mark.parametrize("overlap", ["same_joints", "subset"])
async def test_preemption_keeps_desired_velocity_continuous(robot: agentsdk.Robot, overlap: str) -> None:
    log = TickLog(robot)
    first = robot.follow(far_move(robot))
    await robot.clock.sleep(0.8)
    t_switch = robot.clock.now()
    if overlap == "same_joints":
        second = robot.follow(Trajectory(["joint1", "joint3"], [TrajectoryPoint(2.0, [0.2, -0.2])]))
    else:  # joint3 is left out: it comes to rest on its own within its limits
        second = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(2.0, [0.2])]))
    r1 = await first
    assert r1.code is ResultCode.PREEMPTED, r1
    assert r1.time == pytest.approx(t_switch)
    r2 = await second
    assert r2.code is ResultCode.SUCCESSFUL, r2

    amax, _ = decel_limits(robot, ["joint1", "joint3"])
    idx = [robot.joint_index["joint1"], robot.joint_index["joint3"]]
    dt = log.dt
    t, q, v, _ = log.arrays()
    k = int(np.searchsorted(t, t_switch - 1e-9))  # the first tick of the new trajectory
    v_before, v_after = v[k - 1, idx], v[k, idx]
    assert np.all(np.abs(v_before) > 0.5)
    # continuous: changes by no more than the acceleration limit allows in one tick
    assert np.all(np.abs(v_after - v_before) <= amax * dt * (1 + ACC_RTOL)), (v_before, v_after)
    # and the desired position keeps moving at that velocity (no stall, no jump)
    step = q[k, idx] - q[k - 1, idx]
    assert np.allclose(step, 0.5 * (v_before + v_after) * dt, atol=1e-5), (step, v_before * dt)
    # around the switch (and for joint3 coming to rest in "subset") within the acceleration limits
    acc = np.diff(v[k - 5 : k + 200, idx], axis=0) / dt
    assert np.all(np.abs(acc) <= amax * (1 + ACC_RTOL) + 1e-9), np.abs(acc).max(0)
    if overlap == "subset":
        assert abs(v[-1, idx[1]]) < 1e-9  # joint3 at rest and holding
        await check_holds(robot, ["joint3"])


# --------------------------------------------------------------------------- 4. path tolerance


async def test_frozen_joint_aborts_with_path_tolerance_violated_and_holds() -> None:
    async with agentsdk.connect("mock", robot="arm3", frozen_joints=["joint2"], safety=SAFETY) as robot:
        log = TickLog(robot)
        traj = Trajectory(["joint1", "joint2"], [TrajectoryPoint(1.0, [0.8, 0.8])])
        result = await robot.follow(traj, Tolerances(path=0.05))
        assert result.code is ResultCode.PATH_TOLERANCE_VIOLATED, result
        assert "joint2" in result.message
        assert result.time < 1.0  # aborted early, not at the end
        assert abs(result.error["joint2"]) > 0.05
        # the reference was dropped at once: the stuck joint's setpoint went back to where it is
        # (at rest), the tracking joint decelerated within its limits; then both hold
        t, q, v, x = log.arrays()
        k = int(np.searchsorted(t, result.time - 1e-9))
        moved = np.flatnonzero(v[:, 1] != 0.0)
        abort = int(moved[-1]) + 1  # the first tick after the abort
        assert 0 < abort < k
        assert np.all(q[abort:, 1] == x[0, 1]) and np.all(v[abort:, 1] == 0.0)
        amax, _ = decel_limits(robot, ["joint1"])
        acc = np.diff(v[:k, 0]) / log.dt
        assert np.all(np.abs(acc) <= amax * (1 + ACC_RTOL) + 1e-9)
        assert np.all(v[-1, :2] == 0.0)
        await check_holds(robot, ["joint1"])
        sp = robot.setpoint
        held = sp.position[:2].copy()
        await robot.clock.sleep(0.2)
        assert np.array_equal(robot.setpoint.position[:2], held)  # joint2's hold does not creep


async def test_path_tolerance_violated_on_tight_tolerance(robot: agentsdk.Robot) -> None:
    result = await robot.follow(far_move(robot), Tolerances(path=1e-5))
    assert result.code is ResultCode.PATH_TOLERANCE_VIOLATED, result
    assert result.time < 2.0
    await check_holds(robot, ["joint1", "joint3"])


# --------------------------------------------------------------------------- 5. goal, validation, move_to, feedback


async def test_frozen_joint_goal_tolerance_violated() -> None:
    # (the following-error check is off: a stuck joint latches it, this test is about the goal tolerance)
    safety = {**SAFETY, "following_error_window": None}
    async with agentsdk.connect("mock", robot="arm3", frozen_joints=["joint2"], safety=safety) as robot:
        traj = Trajectory(["joint1", "joint2"], [TrajectoryPoint(0.5, [0.3, 0.3])])
        result = await robot.follow(traj, Tolerances(path=None, goal=0.02, goal_time=0.25))
        assert result.code is ResultCode.GOAL_TOLERANCE_VIOLATED, result
        assert "joint2" in result.message
        assert result.time == pytest.approx(0.5 + 0.25, abs=2 * robot.control_period)
        assert result.error["joint2"] == pytest.approx(0.3)
        assert abs(result.error["joint1"]) < 0.02


async def test_goal_tolerance_violated(backend: str) -> None:
    options = {"lag": 0.05} if backend == "mock" else {}  # an ideal mock reaches any goal exactly
    async with agentsdk.connect(backend, robot="arm3", **options, safety=SAFETY) as robot:
        traj = Trajectory(["joint1", "joint3"], [TrajectoryPoint(0.5, [0.3, -0.3])])
        result = await robot.follow(traj, Tolerances(goal=1e-7, goal_time=0.05))
        assert result.code is ResultCode.GOAL_TOLERANCE_VIOLATED, result
        assert result.time == pytest.approx(0.55, abs=2 * robot.control_period)
        ok = await robot.follow(Trajectory(["joint1"], [TrajectoryPoint(0.5, [0.0])]), Tolerances(goal=0.02))
        assert ok.code is ResultCode.SUCCESSFUL  # the robot is usable afterwards


def _setpoint(robot: agentsdk.Robot) -> tuple[np.ndarray, ...]:
    sp = robot.setpoint
    return sp.position.copy(), sp.velocity.copy(), sp.mode.copy()


@pytest.mark.parametrize(
    ("make", "exc", "match"),
    [
        (lambda: Trajectory(["joint1", "elbow"], [TrajectoryPoint(1.0, [0.1, 0.1])]), UnknownJointError, "elbow"),
        (lambda: Trajectory(["joint1"], [TrajectoryPoint(1.0, [5.0])]), LimitViolation, "joint1"),
        (lambda: Trajectory(["joint2"], [TrajectoryPoint(0.5, [-2.5])]), LimitViolation, "joint2"),
        (
            lambda: Trajectory(["joint1"], [TrajectoryPoint(0.5, [0.1], [0.0]), TrajectoryPoint(1.0, [0.2], [9.0])]),
            LimitViolation,
            "velocity",
        ),
    ],
    ids=["unknown_joint", "position_out_of_limits", "below_lower_limit", "velocity_over_limit"],
)
async def test_invalid_trajectories_rejected_state_unchanged(
    robot: agentsdk.Robot, make: object, exc: type[Exception], match: str
) -> None:
    before = _setpoint(robot)
    with pytest.raises(exc, match=match):
        robot.follow(make())  # type: ignore[operator]
    assert not robot.busy  # nothing started
    await robot.clock.sleep(0.05)
    after = _setpoint(robot)
    assert all(np.array_equal(a, b) for a, b in zip(before, after, strict=True))


@pytest.mark.parametrize(
    "times",
    [[0.5, 0.5], [1.0, 0.5], [-0.1, 0.5]],
    ids=["repeated_time", "decreasing_time", "negative_time"],
)
async def test_non_increasing_times_rejected(robot: agentsdk.Robot, times: list[float]) -> None:
    # rejected when the Trajectory is built, i.e. before follow() could start anything
    with pytest.raises(InvalidValueError, match="time_from_start"):
        robot.follow(Trajectory(["joint1"], [TrajectoryPoint(t, [0.1 * (i + 1)]) for i, t in enumerate(times)]))
    assert not robot.busy


async def test_direct_command_rejected_on_joint_driven_by_trajectory(robot: agentsdk.Robot) -> None:
    motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(0.5, [0.3])]))
    with pytest.raises(CommandRejected, match="driven by a running trajectory"):
        await robot.command(JointCommand("position", {"joint1": 0.0}))
    await robot.command(JointCommand("position", {"joint2": 0.1}))  # other joints are free
    assert (await motion).ok


async def test_move_to_with_and_without_duration(robot: agentsdk.Robot) -> None:
    t0 = robot.clock.now()
    fast = await robot.move_to({"joint1": 1.0, "joint2": 0.4})
    assert fast.ok, fast
    t_fast = fast.time - t0
    assert t_fast < 1.5  # minimum time under the limits: 2.5 rad/s, 10 rad/s^2
    st = await robot.read()
    assert abs(st.positions()["joint1"] - 1.0) < 0.02 and abs(st.positions()["joint2"] - 0.4) < 0.02

    t1 = robot.clock.now()
    slow = await robot.move_to({"joint1": 0.0, "joint2": 0.0}, duration=2.5)
    assert slow.ok, slow
    # follows for exactly the duration, then settles within the goal tolerance (goal_time 1 s at most)
    assert 2.5 - 2 * robot.control_period <= slow.time - t1 <= 2.5 + 1.0
    assert max(abs(e) for e in slow.error.values()) <= 0.02

    with pytest.raises(LimitViolation, match="too short"):
        await robot.move_to({"joint1": 3.0}, duration=0.1)
    with pytest.raises(UnknownJointError):
        await robot.move_to({"wrist": 0.1})


async def test_feedback_progress_desired_actual_error(robot: agentsdk.Robot) -> None:
    motion = robot.follow(Trajectory(["joint1", "joint3"], [TrajectoryPoint(1.0, [0.5, -0.5])]))
    fbs = [fb async for fb in motion.feedback(rate=50.0)]
    result = await motion
    assert result.ok
    assert len(fbs) >= 45  # ~50 Hz over 1 s (+ settling)
    progress = [fb.progress for fb in fbs]
    assert progress[0] < 0.05
    assert progress[-1] == 1.0
    assert all(b >= a for a, b in itertools.pairwise(progress))
    times = [fb.time for fb in fbs]
    assert all(b > a for a, b in itertools.pairwise(times))
    for fb in fbs:
        assert fb.joint_names == ("joint1", "joint3")
        for arr in (fb.desired_positions, fb.desired_velocities, fb.actual_positions, fb.actual_velocities):
            assert arr.shape == (2,)
        np.testing.assert_allclose(fb.error, fb.desired_positions - fb.actual_positions)
    mid = min(fbs, key=lambda fb: abs(fb.progress - 0.5))
    assert np.all(np.abs(mid.desired_velocities) > 0.1)  # moving halfway through
    np.testing.assert_allclose(fbs[-1].desired_positions, [0.5, -0.5], atol=1e-9)
    assert math.isclose(fbs[-1].progress, 1.0)


async def test_feedback_progress_stays_below_one_when_cancelled(robot: agentsdk.Robot) -> None:
    motion = robot.follow(far_move(robot))

    async def cancel_later() -> None:
        await robot.clock.sleep(0.8)
        motion.cancel()

    task = asyncio.create_task(cancel_later())
    fbs = [fb async for fb in motion.feedback(rate=100.0)]
    await task
    assert (await motion).code is ResultCode.CANCELED
    progress = [fb.progress for fb in fbs]
    assert all(b >= a for a, b in itertools.pairwise(progress))  # the stop ramp does not restart it
    assert 0.3 < progress[-1] < 0.6  # cancelled at 0.8 s of 2 s; the trajectory was not completed
    assert np.all(np.abs(fbs[-1].desired_velocities) < 1e-9)  # the last feedback is at rest
