"""Tests for agentsdk.trajectory: value types, JTC-style interpolation, planning."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agentsdk.errors import CommandRejected, InvalidValueError, LimitViolation, UnknownJointError
from agentsdk.trajectory import (
    Trajectory,
    TrajectoryPoint,
    TrajectorySampler,
    plan,
    plan_point_to_point,
    plan_stop,
)
from agentsdk.types import JointInfo

# --------------------------------------------------------------------------- helpers


def J(name: str, **kw: float) -> JointInfo:
    return JointInfo(
        name=name,
        type="revolute",
        lower=kw.get("lower", -3.0),
        upper=kw.get("upper", 3.0),
        max_velocity=kw.get("v", 2.0),
        max_effort=10.0,
        max_acceleration=kw.get("a", 5.0),
        max_jerk=kw.get("j", 100.0),
    )


JOINTS2 = [J("j1"), J("j2")]

# a 7-joint arm with Franka-like position/velocity limits, moderate acceleration/jerk limits
ARM_LOWER = np.array([-2.8, -1.7, -2.8, -3.0, -2.8, 0.0, -2.8])
ARM_UPPER = np.array([2.8, 1.7, 2.8, -0.07, 2.8, 3.7, 2.8])
ARM_VMAX = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
ARM_AMAX = np.array([7.5, 3.75, 5.0, 6.25, 7.5, 10.0, 10.0])
ARM_JMAX = np.array([100.0, 100.0, 100.0, 100.0, 200.0, 200.0, 200.0])
ARM = [
    J(f"a{i}", lower=ARM_LOWER[i], upper=ARM_UPPER[i], v=ARM_VMAX[i], a=ARM_AMAX[i], j=ARM_JMAX[i]) for i in range(7)
]


def arm_waypoints(seed: int, n: int = 10) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return ARM_LOWER + (ARM_UPPER - ARM_LOWER) * (0.1 + 0.8 * rng.random((n, 7)))


def sample_grid(s: TrajectorySampler, n: int = 4001, pad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    ts = np.linspace(s.start_time - pad, s.end_time + pad, n)
    out = np.array([np.vstack(s.sample(float(t))) for t in ts])  # (n, 3, joints)
    return ts, out


def limits(joints: list[JointInfo]) -> tuple[np.ndarray, ...]:
    return (
        np.array([j.lower for j in joints]),
        np.array([j.upper for j in joints]),
        np.array([j.max_velocity for j in joints]),
        np.array([j.max_acceleration for j in joints]),
        np.array([j.max_jerk for j in joints]),
    )


def assert_within_limits(traj: Trajectory, joints: list[JointInfo], n: int = 20001) -> None:
    lo, hi, vmax, amax, jmax = limits(joints)
    s = TrajectorySampler(traj, 0.0)
    ts, out = sample_grid(s, n)
    q, qd, qdd = out[:, 0], out[:, 1], out[:, 2]
    assert np.all(q >= lo - 1e-6) and np.all(q <= hi + 1e-6)
    assert np.all(np.abs(qd) <= vmax * (1 + 1e-3))
    assert np.all(np.abs(qdd) <= amax * (1 + 1e-3))
    if traj.duration > 0:
        jerk = np.diff(qdd, axis=0) / (ts[1] - ts[0])  # mean-value estimate: bounded by the true max jerk
        assert np.all(np.abs(jerk) <= jmax * (1 + 1e-3))


def assert_hits_in_order(traj: Trajectory, waypoints: np.ndarray, tol: float = 1e-6) -> list[float]:
    """Every waypoint appears as a point, in order; returns their times."""
    times, k = [], 0
    P = traj.positions
    for i, w in enumerate(waypoints):
        while k < len(P) and np.max(np.abs(P[k] - w)) > tol:
            k += 1
        assert k < len(P), f"waypoint {i} not reached in order"
        times.append(float(traj.times[k]))  # k is not advanced: repeated waypoints may share a point
    return times


# --------------------------------------------------------------------------- value types and validation


def test_point_stores_tuples_and_trajectory_arrays() -> None:
    p = TrajectoryPoint(1, np.array([1.0, 2.0]), [0, 0])
    assert p.positions == (1.0, 2.0) and p.velocities == (0.0, 0.0) and p.accelerations is None
    assert isinstance(p.time_from_start, float)
    tr = Trajectory(["j1", "j2"], [TrajectoryPoint(0.5, [0, 0], [1, 1]), p])
    assert tr.duration == 1.0 and tr.joint_names == ("j1", "j2")
    assert tr.positions.shape == (2, 2) and not tr.positions.flags.writeable
    assert tr.velocities is not None and tr.accelerations is None
    other = Trajectory(("j1", "j2"), (TrajectoryPoint(0.5, [0, 0], [1, 1]), TrajectoryPoint(1.0, [1, 2], [0, 0])))
    assert tr == other
    hash(tr)


def test_point_rejects_non_numbers() -> None:
    with pytest.raises(InvalidValueError):
        TrajectoryPoint(0.0, ["a", 1.0])
    with pytest.raises(InvalidValueError):
        TrajectoryPoint("soon", [1.0])  # type: ignore[arg-type]
    with pytest.raises(InvalidValueError):
        TrajectoryPoint(0.0, [[1.0, 2.0]])


def test_empty_points() -> None:
    with pytest.raises(InvalidValueError, match="no points"):
        Trajectory(["j1"], [])


def test_empty_and_duplicate_joint_names() -> None:
    with pytest.raises(InvalidValueError, match="no joint_names"):
        Trajectory([], [TrajectoryPoint(1.0, [])])
    with pytest.raises(InvalidValueError, match="duplicate joint name 'j1'"):
        Trajectory(["j1", "j1"], [TrajectoryPoint(1.0, [0, 0])])
    with pytest.raises(InvalidValueError):
        Trajectory("j1", [TrajectoryPoint(1.0, [0])])


def test_unknown_joint_lists_known() -> None:
    tr = Trajectory(["j1", "elbow"], [TrajectoryPoint(1.0, [0, 0])])
    with pytest.raises(UnknownJointError, match=r"'elbow'.*known joints.*'j1'.*'j2'") as exc:
        tr.validate(JOINTS2)
    assert isinstance(exc.value, KeyError) and isinstance(exc.value, CommandRejected)


@pytest.mark.parametrize(
    ("point", "match"),
    [
        (TrajectoryPoint(1.0, [0.0]), "point 1: 1 positions for 2 joints"),
        (TrajectoryPoint(1.0, [0, 0], [0.0, 0, 0]), "point 1: 3 velocities for 2 joints"),
    ],
)
def test_length_mismatch(point: TrajectoryPoint, match: str) -> None:
    first = TrajectoryPoint(0.5, [0, 0], None if point.velocities is None else [0, 0])
    with pytest.raises(InvalidValueError, match=match):
        Trajectory(["j1", "j2"], [first, point])


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_names_point_and_joint(bad: float) -> None:
    with pytest.raises(InvalidValueError, match=r"point 1: position of joint 'j2' is"):
        Trajectory(["j1", "j2"], [TrajectoryPoint(0.5, [0, 0]), TrajectoryPoint(1.0, [0, bad])])
    with pytest.raises(InvalidValueError, match=r"point 0: velocitie?y? of joint 'j1' is"):
        Trajectory(["j1", "j2"], [TrajectoryPoint(0.5, [0, 0], [bad, 0])])
    with pytest.raises(InvalidValueError, match=r"point 0: time_from_start .* not finite"):
        Trajectory(["j1", "j2"], [TrajectoryPoint(bad, [0, 0])])


def test_times_must_be_non_negative_and_increasing() -> None:
    with pytest.raises(InvalidValueError, match=r"point 0: time_from_start -0\.1 s is negative"):
        Trajectory(["j1"], [TrajectoryPoint(-0.1, [0])])
    with pytest.raises(InvalidValueError, match=r"point 2: .*not after point 1"):
        Trajectory(["j1"], [TrajectoryPoint(0.0, [0]), TrajectoryPoint(1.0, [0]), TrajectoryPoint(1.0, [0])])
    with pytest.raises(InvalidValueError, match="point 1"):
        Trajectory(["j1"], [TrajectoryPoint(2.0, [0]), TrajectoryPoint(1.0, [0])])
    # first point at 0 or > 0 are both fine
    Trajectory(["j1"], [TrajectoryPoint(0.0, [0]), TrajectoryPoint(1.0, [0])])
    Trajectory(["j1"], [TrajectoryPoint(0.3, [0]), TrajectoryPoint(1.0, [0])])


def test_mixing_points_with_and_without_velocities() -> None:
    with pytest.raises(InvalidValueError, match="point 1: lacks velocities"):
        Trajectory(["j1"], [TrajectoryPoint(0.5, [0], [0]), TrajectoryPoint(1.0, [0])])
    with pytest.raises(InvalidValueError, match="point 1: has velocities"):
        Trajectory(["j1"], [TrajectoryPoint(0.5, [0]), TrajectoryPoint(1.0, [0], [0])])
    with pytest.raises(InvalidValueError, match="accelerations"):
        Trajectory(["j1"], [TrajectoryPoint(0.5, [0], [0], [0]), TrajectoryPoint(1.0, [0], [0])])
    with pytest.raises(InvalidValueError, match="accelerations given without velocities"):
        Trajectory(["j1"], [TrajectoryPoint(0.5, [0], None, [0])])


def test_position_limit_violation_names_joint_point_value_limit() -> None:
    tr = Trajectory(["j2", "j1"], [TrajectoryPoint(0.5, [0, 0]), TrajectoryPoint(1.0, [0, 3.5])])
    with pytest.raises(LimitViolation, match=r"point 1: joint 'j1' position 3.5 .*\[-3, 3\]"):
        tr.validate(JOINTS2)


def test_velocity_limit_violation() -> None:
    tr = Trajectory(["j1", "j2"], [TrajectoryPoint(1.0, [0, 0], [0, -2.5])])
    with pytest.raises(LimitViolation, match=r"point 0: joint 'j2' velocity -2.5 exceeds max_velocity 2"):
        tr.validate(JOINTS2)
    at_limits = Trajectory(["j1", "j2"], [TrajectoryPoint(1.0, [3, -3], [2, -2])])
    at_limits.validate(JOINTS2, allow_nonzero_velocity_at_end=True)  # at the limits: fine


# --------------------------------------------------------------------------- interpolation

TIMES = [0.0, 1.0, 1.5, 3.0]
POS = [[0.0, 1.0], [1.0, -1.0], [2.0, 0.5], [1.5, 0.0]]
VEL = [[0.0, 0.0], [1.5, -0.5], [0.2, 0.3], [0.0, 0.0]]
ACC = [[0.0, 0.0], [1.0, 2.0], [-3.0, 0.0], [0.0, 0.0]]


def _traj(vel: bool, acc: bool, t_shift: float = 0.0) -> Trajectory:
    return Trajectory(
        ["j1", "j2"],
        [
            TrajectoryPoint(t + t_shift, p, v if vel else None, a if acc else None)
            for t, p, v, a in zip(TIMES, POS, VEL, ACC, strict=True)
        ],
    )


def _continuity(s: TrajectorySampler, t: float, order: int, eps: float = 1e-7) -> None:
    before = np.vstack(s.sample(t - eps))
    after = np.vstack(s.sample(t + eps))
    for k in range(order + 1):
        np.testing.assert_allclose(before[k], after[k], atol=1e-4, err_msg=f"derivative {k} jumps at t={t}")


@pytest.mark.parametrize(
    ("vel", "acc", "interpolation", "order"),
    [
        (False, False, "linear", 0),
        (True, False, "linear", 1),
        (True, True, "linear", 2),
        (False, False, "spline", 2),
    ],
)
def test_segments_hit_waypoints_and_are_continuous(vel: bool, acc: bool, interpolation: str, order: int) -> None:
    t0 = 100.0
    s = TrajectorySampler(_traj(vel, acc), t0, interpolation=interpolation)  # type: ignore[arg-type]
    for i, t in enumerate(TIMES):
        q, qd, qdd = s.sample(t0 + t)
        np.testing.assert_allclose(q, POS[i], atol=1e-12)
        if vel:
            np.testing.assert_allclose(qd, VEL[i], atol=1e-12)
        if acc:
            np.testing.assert_allclose(qdd, ACC[i], atol=1e-12)
        if 0 < i < len(TIMES) - 1:
            _continuity(s, t0 + t, order)
    # the derivatives agree with finite differences of the position inside segments
    ts = np.linspace(t0 + 0.05, t0 + 2.95, 40)
    for t in ts:
        h = 1e-6
        qd = s.sample(t)[1]
        fd = (s.sample(t + h)[0] - s.sample(t - h)[0]) / (2 * h)
        np.testing.assert_allclose(qd, fd, atol=1e-5)


def test_linear_segment_velocity_is_the_slope() -> None:
    s = TrajectorySampler(_traj(False, False), 0.0)
    q, qd, qdd = s.sample(1.25)
    np.testing.assert_allclose(q, [1.5, -0.25])
    np.testing.assert_allclose(qd, [2.0, 3.0])
    np.testing.assert_allclose(qdd, [0.0, 0.0])


def test_cubic_is_cubic_hermite() -> None:
    s = TrajectorySampler(_traj(True, False), 0.0)
    # segment 1.0 -> 1.5 of joint 1: p0=1, v0=1.5, p1=2, v1=0.2, T=0.5, evaluate at the middle
    T, tau = 0.5, 0.25
    h00, h10, h01, h11 = 0.5, 0.125, 0.5, -0.125  # Hermite basis at s=1/2
    expected = h00 * 1.0 + h10 * T * 1.5 + h01 * 2.0 + h11 * T * 0.2
    assert s.sample(1.0 + tau)[0][0] == pytest.approx(expected, abs=1e-12)


def test_spline_mode_matches_a_clamped_cubic_spline() -> None:
    scipy_interpolate = pytest.importorskip("scipy.interpolate")
    s = TrajectorySampler(_traj(False, False), 0.0, interpolation="spline")
    ref = scipy_interpolate.CubicSpline(TIMES, POS, bc_type="clamped")
    for t in np.linspace(0.0, 1.5, 31):  # the last segment arrives with zero acceleration instead
        q, qd, qdd = s.sample(float(t))
        np.testing.assert_allclose(q, ref(t), atol=1e-9)
        np.testing.assert_allclose(qd, ref(t, 1), atol=1e-9)
        np.testing.assert_allclose(qdd, ref(t, 2), atol=1e-8)
    # ... and holding the end is smooth
    np.testing.assert_allclose(np.vstack(s.sample(3.0 - 1e-7)), np.vstack(s.sample(3.0)), atol=1e-5)


@pytest.mark.parametrize(
    ("vel", "acc", "interpolation"),
    [(False, False, "linear"), (True, False, "linear"), (True, True, "linear"), (False, False, "spline")],
)
def test_first_segment_starts_from_start_state_without_jump(vel: bool, acc: bool, interpolation: str) -> None:
    # point 0 at 0.5 s: a quintic segment from the (moving) start state to point 0
    traj = _traj(vel, acc, t_shift=0.5)
    q0, v0, a0 = np.array([-0.5, 1.2]), np.array([1.8, -1.0]), np.array([-2.0, 3.0])
    t0 = 7.0
    s = TrajectorySampler(traj, t0, q0, v0, a0, interpolation=interpolation)  # type: ignore[arg-type]
    assert s.duration == pytest.approx(3.5) and s.end_time == pytest.approx(10.5)
    q, qd, qdd = s.sample(t0)
    np.testing.assert_allclose(q, q0, atol=1e-12)
    np.testing.assert_allclose(qd, v0, atol=1e-12)
    np.testing.assert_allclose(qdd, a0, atol=1e-12)
    # before the start: the start state; just after: continuous position and velocity
    np.testing.assert_allclose(np.vstack(s.sample(t0 - 1.0)), np.vstack([q0, v0, a0]))
    h = 1e-6
    np.testing.assert_allclose(s.sample(t0 + h)[1], v0, atol=1e-4)
    np.testing.assert_allclose((s.sample(t0 + h)[0] - q0) / h, v0, atol=1e-4)
    # reaches point 0 exactly, and continues continuously into the trajectory
    q, qd, qdd = s.sample(t0 + 0.5)
    np.testing.assert_allclose(q, POS[0], atol=1e-12)
    if vel:
        np.testing.assert_allclose(qd, VEL[0], atol=1e-12)
    _continuity(s, t0 + 0.5, 0 if not vel and interpolation == "linear" else 1)


def test_point_at_time_zero_ignores_start_state() -> None:
    s = TrajectorySampler(_traj(True, True), 1.0, [9.0, 9.0], [9.0, 9.0])
    np.testing.assert_allclose(s.sample(1.0)[0], POS[0])
    np.testing.assert_allclose(s.sample(0.0)[0], POS[0])


def test_start_positions_required_when_first_point_is_later() -> None:
    with pytest.raises(InvalidValueError, match="start_positions"):
        TrajectorySampler(_traj(False, False, t_shift=0.5), 0.0)


@pytest.mark.parametrize(("vel", "acc"), [(False, False), (True, False), (True, True)])
def test_hold_after_end(vel: bool, acc: bool) -> None:
    pts = [TrajectoryPoint(0.0, [0.0, 0.0], [0, 0] if vel else None, [0, 0] if acc else None)]
    pts.append(TrajectoryPoint(1.0, [1.0, -2.0], [0.5, 0.0] if vel else None, [0.1, 0.0] if acc else None))
    s = TrajectorySampler(Trajectory(["j1", "j2"], pts), 2.0)
    assert not s.finished(2.9999) and s.finished(3.0) and s.finished(10.0)
    for t in (3.0, 3.5, 1e6):
        q, qd, qdd = s.sample(t)
        np.testing.assert_array_equal(q, [1.0, -2.0])
        np.testing.assert_array_equal(qd, [0.5, 0.0] if vel else [0.0, 0.0])  # JTC holds the last point as given
        np.testing.assert_array_equal(qdd, [0.1, 0.0] if acc else [0.0, 0.0])
    np.testing.assert_array_equal(s.final_positions, [1.0, -2.0])


def test_single_point_trajectory() -> None:
    tr = Trajectory(["j1"], [TrajectoryPoint(2.0, [1.0])])
    s = TrajectorySampler(tr, 0.0, [0.0], [0.5])
    q, qd, _ = s.sample(0.0)
    assert q[0] == 0.0 and qd[0] == 0.5
    assert s.sample(2.0)[0][0] == 1.0 and s.sample(2.0)[1][0] == 0.0
    s = TrajectorySampler(Trajectory(["j1"], [TrajectoryPoint(0.0, [1.0])]), 5.0)
    assert s.duration == 0.0 and s.finished(5.0) and s.sample(4.0)[0][0] == 1.0


def test_joint_order_names_indices_and_mappings() -> None:
    traj = _traj(False, False, t_shift=1.0)  # joints j1, j2
    robot = ["j0", "j2", "j1"]
    q_robot = [9.0, 0.3, -0.2]
    v_robot = [9.0, 0.1, 0.4]
    by_name = TrajectorySampler(traj, 0.0, q_robot, v_robot, joint_order=robot)
    by_index = TrajectorySampler(traj, 0.0, q_robot, v_robot, joint_order=[2, 1])
    by_map = TrajectorySampler(traj, 0.0, {"j1": -0.2, "j2": 0.3, "j0": 9.0}, {"j1": 0.4, "j2": 0.1})
    np.testing.assert_array_equal(by_name.indices, [2, 1])
    for s in (by_name, by_index, by_map):
        np.testing.assert_allclose(s.sample(0.0)[0], [-0.2, 0.3])
        np.testing.assert_allclose(s.sample(0.0)[1], [0.4, 0.1])
    full = np.zeros(3)
    full[by_name.indices] = by_name.sample(0.0)[0]
    np.testing.assert_allclose(full, [0.0, 0.3, -0.2])
    with pytest.raises(UnknownJointError, match="j2"):
        TrajectorySampler(traj, 0.0, q_robot, joint_order=["j0", "j1"])
    with pytest.raises(InvalidValueError, match="start_positions"):
        TrajectorySampler(traj, 0.0, [0.0, 0.0], joint_order=robot)
    with pytest.raises(InvalidValueError, match="missing joint"):
        TrajectorySampler(traj, 0.0, {"j1": 0.0})
    with pytest.raises(InvalidValueError, match="interpolation"):
        TrajectorySampler(traj, 0.0, [0, 0], interpolation="cubic")  # type: ignore[arg-type]


def test_sample_into_matches_sample() -> None:
    s = TrajectorySampler(_traj(True, True, t_shift=0.2), 0.0, [0.1, 0.2], [0.3, 0.4])
    out = np.empty((3, 2))
    for t in np.linspace(-1.0, 4.0, 57):
        r = s.sample_into(float(t), out)
        assert r is out
        np.testing.assert_array_equal(out, np.vstack(s.sample(float(t))))


# --------------------------------------------------------------------------- plan()


def test_plan_7_joints_10_waypoints_respects_limits_and_hits_waypoints() -> None:
    wp = arm_waypoints(0)
    traj = plan(wp, ARM)
    traj.validate(ARM)
    assert traj.joint_names == tuple(j.name for j in ARM)
    assert traj.velocities is not None and traj.accelerations is not None
    assert_within_limits(traj, ARM)
    times = assert_hits_in_order(traj, wp)
    assert times[0] == 0.0 and times[-1] == traj.duration
    # executing the trajectory passes through the waypoints at those times
    s = TrajectorySampler(traj, 0.0)
    for t, w in zip(times, wp, strict=True):
        np.testing.assert_allclose(s.sample(t)[0], w, atol=1e-6)
    # starts and ends at rest
    np.testing.assert_allclose(traj.velocities[[0, -1]], 0.0, atol=1e-12)
    np.testing.assert_allclose(traj.accelerations[[0, -1]], 0.0, atol=1e-12)
    # durations come from the limits: no segment is faster than the slowest joint's min time
    for i in range(len(wp) - 1):
        d = np.abs(wp[i + 1] - wp[i])
        lower_bound = np.max(d / ARM_VMAX)  # cannot be faster than at max velocity all the way
        assert times[i + 1] - times[i] >= lower_bound
    # carrying velocity through waypoints is faster than stopping at every one
    stop_each = sum(plan(wp[i : i + 2], ARM).duration for i in range(len(wp) - 1))
    assert traj.duration < stop_each


def test_plan_interpolation_reproduces_planned_points() -> None:
    """Between breakpoints each joint is one cubic: the quintic interpolation is exact."""
    traj = plan(arm_waypoints(3, 4), ARM)
    s = TrajectorySampler(traj, 0.0)
    mids = 0.5 * (traj.times[1:] + traj.times[:-1])
    # reference: the state at each breakpoint integrated from the previous one with constant jerk
    for k, t in enumerate(mids):
        dt = t - traj.times[k]
        jerk = (traj.accelerations[k + 1] - traj.accelerations[k]) / (traj.times[k + 1] - traj.times[k])
        a0, v0, p0 = traj.accelerations[k], traj.velocities[k], traj.positions[k]
        q = p0 + v0 * dt + a0 * dt**2 / 2 + jerk * dt**3 / 6
        np.testing.assert_allclose(s.sample(float(t))[0], q, atol=1e-9)


def test_plan_from_a_moving_start_state() -> None:
    wp = arm_waypoints(1, 5)
    q0 = 0.5 * (ARM_LOWER + ARM_UPPER)
    v0 = 0.5 * ARM_VMAX * np.array([1, -1, 1, -1, 1, -1, 1])
    a0 = np.array([1.0, -1.0, 0.5, 0.0, 0.0, 2.0, -2.0])
    traj = plan(wp, ARM, start=(q0, v0, a0))
    np.testing.assert_allclose(traj.positions[0], q0)
    np.testing.assert_allclose(traj.velocities[0], v0)
    np.testing.assert_allclose(traj.accelerations[0], a0)
    assert traj.times[0] == 0.0
    assert_within_limits(traj, ARM)
    assert_hits_in_order(traj, wp)
    # the executor samples it from the same state: no jump at the start
    s = TrajectorySampler(traj, 5.0, q0, v0, a0)
    np.testing.assert_allclose(np.vstack(s.sample(5.0)), np.vstack([q0, v0, a0]), atol=1e-12)
    np.testing.assert_allclose(s.sample(5.0 + 1e-6)[1], v0, atol=1e-3)


def test_plan_with_mappings_and_subset_of_joints() -> None:
    wps = [{"a2": 0.0, "a0": 0.0}, {"a0": 1.0, "a2": -1.0}, {"a0": 2.0, "a2": 0.5}]
    traj = plan(wps, ARM, start=({"a0": -0.5, "a2": 0.0}, None, None))
    assert traj.joint_names == ("a0", "a2")
    assert_hits_in_order(traj, np.array([[0.0, 0.0], [1.0, -1.0], [2.0, 0.5]]))
    np.testing.assert_allclose(traj.positions[0], [-0.5, 0.0])
    with pytest.raises(InvalidValueError, match="waypoint 1"):
        plan([{"a0": 0.0}, {"a1": 1.0}], ARM)
    with pytest.raises(UnknownJointError, match="nope"):
        plan([{"nope": 0.0}], ARM)


def test_plan_scales_and_single_joint_time_from_limits() -> None:
    j = [J("j1")]  # v=2, a=5, jerk=100
    traj = plan([[-2.0], [2.0]], j)
    # rest to rest over 4 rad: cruise at v_max; t = d/v + v/a + a/j (planned inside the limits by
    # PLAN_LIMIT_MARGIN and the breakpoint-merge margin 2 * max_jerk * MIN_GAP, < 1e-4 relative here: issue 20.5)
    rel = 2e-4
    assert traj.duration == pytest.approx(4 / 2 + 2 / 5 + 5 / 100, rel=rel)
    assert traj.duration > 4 / 2 + 2 / 5 + 5 / 100
    slow = plan([[-2.0], [2.0]], j, velocity_scale=0.5, acceleration_scale=0.5)
    assert slow.duration == pytest.approx(4 / 1 + 1 / 2.5 + 2.5 / 100, rel=rel)
    assert np.max(np.abs(slow.velocities)) == pytest.approx(1.0, rel=rel)
    assert np.max(np.abs(slow.accelerations)) == pytest.approx(2.5, rel=rel)
    assert np.max(np.abs(slow.velocities)) < 1.0 and np.max(np.abs(slow.accelerations)) < 2.5
    with pytest.raises(InvalidValueError, match="velocity_scale"):
        plan([[0.0], [1.0]], j, velocity_scale=0.0)


def test_plan_stays_within_position_limits_near_a_limit() -> None:
    # j1 approaches its upper limit while j2's long move stretches the last segment: carrying j1's
    # velocity through 2.9 would make it overshoot 3.0 to use up the time; it must be reduced instead
    joints = [J("j1", a=2.0, j=50.0), J("j2", a=2.0, j=50.0)]
    wp = np.array([[0.0, 0.0], [2.9, 0.5], [2.99, 3.0]])
    traj = plan(wp, joints)
    assert_within_limits(traj, joints)
    assert_hits_in_order(traj, wp)
    assert traj.duration < plan(wp[:2], joints).duration + plan(wp[1:], joints).duration  # still carries speed
    # a single joint going monotonically towards the limit
    j = [J("j1", a=2.0, j=50.0)]
    wp = np.array([[-2.5], [2.9], [2.999], [2.5]])
    assert_within_limits(plan(wp, j), j)


def test_plan_without_jerk_limit_ramps_acceleration() -> None:
    j = [J("j1", j=math.inf)]
    traj = plan([[-2.0], [2.0]], j)
    # (planned inside the limits: by ~1e-3 without a jerk limit, see joint_limits)
    assert traj.duration == pytest.approx(4 / 2 + 2 / 5 + 0.002, rel=2e-3)
    assert_within_limits(traj, [J("j1", j=5 / 0.002)])


def test_plan_rejects_bad_waypoints_and_start() -> None:
    with pytest.raises(LimitViolation, match=r"waypoint 1: joint 'j2' position 3.2 .*\[-3, 3\]"):
        plan([[0, 0], [0, 3.2]], JOINTS2)
    with pytest.raises(InvalidValueError, match="waypoint 1: value of joint 'j1' is nan"):
        plan([[0, 0], [math.nan, 0]], JOINTS2)
    with pytest.raises(InvalidValueError, match="shape"):
        plan([[0, 0, 0]], JOINTS2)
    with pytest.raises(LimitViolation, match="start: joint 'j1' velocity 3 exceeds"):
        plan([[0, 0]], JOINTS2, start=([0, 0], [3, 0], None))
    with pytest.raises(LimitViolation, match="joint 'j1' cannot reach waypoint 0"):
        plan([[2.9, 0]], JOINTS2, start=([2.8, 0], [2.0, 0], None))
    with pytest.raises(InvalidValueError, match="start must be"):
        plan([[0, 0]], JOINTS2, start=[0.0, 0.0])  # type: ignore[arg-type]


@settings(max_examples=25, deadline=None, database=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 6))
def test_plan_property_limits_and_waypoints(seed: int, n: int) -> None:
    wp = arm_waypoints(seed, n)
    traj = plan(wp, ARM)
    traj.validate(ARM)
    assert_within_limits(traj, ARM, n=4001)
    assert_hits_in_order(traj, wp)


# --------------------------------------------------------------------------- plan_point_to_point()


def test_point_to_point_min_time_synchronized() -> None:
    traj = plan_point_to_point(([-2.0, 0.0], None, None), [2.0, 0.5], JOINTS2)
    # j1 limits the time (planned inside the limits by PLAN_LIMIT_MARGIN + the merge margin)
    assert traj.duration == pytest.approx(4 / 2 + 2 / 5 + 5 / 100, rel=5e-5)
    np.testing.assert_array_equal(traj.positions[-1], [2.0, 0.5])
    np.testing.assert_array_equal(traj.velocities[-1], [0.0, 0.0])
    assert_within_limits(traj, JOINTS2)
    # time-synchronized: j2 is still moving shortly before the end (it was slowed, not finished early)
    s = TrajectorySampler(traj, 0.0)
    assert abs(s.sample(traj.duration * 0.9)[1][1]) > 1e-3


def test_point_to_point_with_duration() -> None:
    traj = plan_point_to_point(([-2.0, 0.0], None, None), [2.0, 0.5], JOINTS2, 4.0)
    assert traj.duration == pytest.approx(4.0)
    np.testing.assert_array_equal(traj.positions[-1], [2.0, 0.5])
    assert_within_limits(traj, JOINTS2)


def test_point_to_point_infeasible_duration() -> None:
    too_short = r"duration 2 s is too short: joint 'j1' needs at least 2.450\d* s .*max_velocity 2, "
    with pytest.raises(LimitViolation, match=too_short):
        plan_point_to_point(([-2.0, 0.0], None, None), [2.0, 0.5], JOINTS2, 2.0)
    with pytest.raises(InvalidValueError, match="duration"):
        plan_point_to_point(([-2.0, 0.0], None, None), [2.0, 0.5], JOINTS2, -1.0)
    with pytest.raises(LimitViolation, match="goal: joint 'j1'"):
        plan_point_to_point(([0.0, 0.0], None, None), [4.0, 0.5], JOINTS2)


def test_point_to_point_overshoot_is_checked_against_limits() -> None:
    # from 1.0 at 2 rad/s to 1.2: the joint brakes at full deceleration, reverses at 1.4495 (inside a
    # constant-acceleration phase, which ruckig 0.19's own position_extrema misses: it reports 1.373)
    with pytest.raises(LimitViolation, match=r"joint 'j1' would leave its limits \[-3, 1.4\].*1.449[45]"):
        plan_point_to_point(([1.0], [2.0], None), [1.2], [J("j1", upper=1.4)])
    traj = plan_point_to_point(([1.0], [2.0], None), [1.2], [J("j1", upper=1.5)])
    assert_within_limits(traj, [J("j1", upper=1.5)])
    _, out = sample_grid(TrajectorySampler(traj, 0.0), 20001)
    assert np.max(out[:, 0, 0]) == pytest.approx(1.4494791666, abs=1e-4)  # (braking a little inside the limit)


def test_point_to_point_from_moving_start() -> None:
    q0, v0, a0 = [0.0, 0.0], [1.5, -1.0], [-1.0, 2.0]
    traj = plan_point_to_point((q0, v0, a0), [-1.0, 1.0], JOINTS2)
    s = TrajectorySampler(traj, 0.0, q0, v0, a0)
    np.testing.assert_allclose(np.vstack(s.sample(0.0)), np.vstack([q0, v0, a0]), atol=1e-12)
    np.testing.assert_allclose(s.sample(1e-6)[1], v0, atol=1e-3)
    np.testing.assert_allclose(s.sample(traj.duration)[0], [-1.0, 1.0])
    assert_within_limits(traj, JOINTS2)


# --------------------------------------------------------------------------- plan_stop()


def test_stop_uses_full_deceleration() -> None:
    joints = [J("j1", a=5.0, j=100.0), J("j2", a=2.0, j=100.0), J("j3")]
    v0 = np.array([2.0, -1.5, 0.0])
    q0 = np.array([0.5, -0.5, 1.0])
    traj = plan_stop(q0, v0, None, joints)
    s = TrajectorySampler(traj, 0.0)
    # each joint: jerk ramp a/j, constant decel, jerk ramp: t = |v0|/a + a/j
    t_stop = np.abs(v0) / np.array([5.0, 2.0, 5.0]) + np.array([5.0, 2.0, 5.0]) / 100.0
    t_stop[2] = 0.0
    assert traj.duration == pytest.approx(t_stop.max(), rel=1e-9)
    ts, out = sample_grid(s, 4001)
    qd, qdd = out[:, 1], out[:, 2]
    for j in range(2):
        stopped = np.abs(qd[:, j]) < 1e-9
        first = ts[np.argmax(stopped)]
        assert first == pytest.approx(t_stop[j], abs=2 * (ts[1] - ts[0]))
        assert np.max(np.abs(qdd[:, j])) == pytest.approx(joints[j].max_acceleration, rel=0.02)
        # velocity decreases monotonically in magnitude (no overshoot)
        assert np.all(np.diff(np.abs(qd[:, j])) <= 1e-12)
    np.testing.assert_allclose(traj.velocities[-1], 0.0, atol=1e-12)
    np.testing.assert_allclose(traj.accelerations[-1], 0.0, atol=1e-12)
    # symmetric velocity profile: distance = v0 * t_stop / 2; the last point is where it stops
    np.testing.assert_allclose(traj.positions[-1], q0 + v0 * t_stop / 2, atol=1e-9)
    np.testing.assert_allclose(s.sample(100.0)[0], traj.positions[-1])
    np.testing.assert_allclose(s.sample(100.0)[1], 0.0)


def test_stop_decel_scale_and_fast_start() -> None:
    j = [J("j1")]
    full = plan_stop([0.0], [2.0], [0.0], j)
    half = plan_stop([0.0], [2.0], [0.0], j, decel_scale=0.5)
    assert full.duration == pytest.approx(2 / 5 + 5 / 100)
    assert half.duration == pytest.approx(2 / 2.5 + 2.5 / 100)
    assert np.max(np.abs(half.accelerations)) == pytest.approx(2.5, rel=1e-6)
    # a joint faster than its velocity limit still stops, at full deceleration
    fast = plan_stop([0.0], [3.0], [0.0], j)
    assert fast.duration == pytest.approx(3 / 5 + 5 / 100)
    # already at rest: a single point
    rest = plan_stop([0.2], [0.0], None, j)
    assert len(rest.points) == 1 and rest.duration == 0.0


def test_stop_with_initial_acceleration() -> None:
    j = [J("j1")]
    traj = plan_stop([0.0], [1.0], [4.0], j)  # still accelerating: must ramp the acceleration down first
    s = TrajectorySampler(traj, 0.0)
    _, out = sample_grid(s, 4001)
    assert np.all(np.abs(out[:, 2, 0]) <= 5.0 * (1 + 1e-6))
    assert np.max(out[:, 1, 0]) > 1.0  # velocity keeps rising while the acceleration ramps down
    assert traj.velocities[-1][0] == 0.0
