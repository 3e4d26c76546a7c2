"""Issue 14 and issue 10 (item 4): trajectories are validated on their whole motion, and no numeric
input reaches a backend as NaN or drives a joint out of its limits.

* ``peaks()`` finds the exact extremes of the interpolated motion (checked against dense sampling);
* property test: over random trajectories (positions, +velocities, +accelerations; random times,
  options), every trajectory ``follow()`` accepts produces per-tick setpoints within the position
  bounds, the velocity limits and (for the smooth kinds) the acceleration limits; every refusal is a
  :class:`CommandRejected` naming the point or segment and the joint;
* property test: NaN, inf, negative and huge values in every numeric field of ``TrajectoryPoint``,
  ``Trajectory``, ``Tolerances``, ``follow(start_time=...)``, ``move_to(duration=...)`` and the speed
  scaling are refused with a one-line :class:`AgentSDKError`, or run with finite setpoints inside the
  limits, and the motion can always be cancelled.

Lockstep mock robots (simulated time); one short-lived robot per example.
"""

from __future__ import annotations

import asyncio
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import agentsdk
from agentsdk import (
    AgentSDKError,
    CommandRejected,
    InvalidValueError,
    ResultCode,
    Tolerances,
    Trajectory,
    TrajectoryPoint,
)
from agentsdk.trajectory import MAX_TIME_FROM_START, TrajectorySampler, check_motion_limits

SAFETY = {"stall_timeout": None}
NAMES = ("joint1", "joint2", "joint3")


# ----------------------------------------------------------------- exact extremes


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 4),
    kind=st.sampled_from(["pos", "vel", "acc"]),
    seed=st.integers(0, 2**32 - 1),
)
@example(n=1, kind="vel", seed=146)  # two velocity extrema inside one grid cell: missed by bisection alone
def test_peaks_are_the_extremes_of_dense_sampling(n: int, kind: str, seed: int) -> None:
    """The extremes ``peaks()`` reports bound every sample and are reached (to sampling resolution)."""
    rng = np.random.default_rng(seed)
    times = np.cumsum(rng.uniform(0.1, 1.0, n))
    pts = [
        TrajectoryPoint(
            float(t),
            rng.uniform(-1, 1, 2),
            None if kind == "pos" else rng.uniform(-2, 2, 2),
            rng.uniform(-5, 5, 2) if kind == "acc" else None,
        )
        for t in times
    ]
    sampler = TrajectorySampler(Trajectory(["a", "b"], pts), 0.0, rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2),
                                rng.uniform(-3, 3, 2))
    pk = sampler.peaks()
    ts = np.linspace(0.0, sampler.end_time, 20001)
    out = np.array([np.vstack(sampler.sample(t)) for t in ts])  # (T, 3, 2)
    eps = 1e-9
    assert np.all(out[:, 0] >= pk.q_min.min(axis=0) - eps) and np.all(out[:, 0] <= pk.q_max.max(axis=0) + eps)
    assert np.all(np.abs(out[:, 1]) <= pk.v_peak.max(axis=0) + eps)
    inside = ~np.isin(ts, sampler._knots)  # accelerations step at the knots of linear/cubic pieces
    assert np.all(np.abs(out[inside, 2]) <= pk.a_peak.max(axis=0) + 1e-6)
    # and reached: the dense samples come within the grid's resolution of them
    step = ts[1] - ts[0]
    assert np.all(np.abs(out[:, 1]).max(axis=0) >= pk.v_peak.max(axis=0) - step * pk.a_peak.max(axis=0) - 1e-9)


def test_peaks_find_extremes_closer_than_any_grid() -> None:
    """Velocity roots 1e-9..1e-2 apart, and a double root: each extreme is found, none overstated.

    The root search has no grid to fall between: the derivative's own turning points split each
    segment into monotone pieces (``poly_roots``), down from the linear derivative.
    """
    from agentsdk.trajectory._peaks import derivative, poly_range, poly_roots

    rng = np.random.default_rng(7)
    n = 400
    r = rng.uniform(0.05, 0.9, n)
    gap = np.concatenate([10.0 ** rng.uniform(-9, -2, n - 1), [0.0]])  # the last: a double root
    coeffs, truth = [], []
    for i in range(n):
        dq = np.poly1d([1.0])
        for root in (r[i], r[i] + gap[i], -1.0 - i / n, 2.0 + i / n):
            dq = dq * np.poly1d([1.0, -root])
        q = np.polyint(dq) * rng.choice([-1.0, 1.0])
        coeffs.append(q.coeffs[::-1])
        truth.append(np.polyval(q, [0.0, r[i], r[i] + gap[i], 1.0]))
    c = np.array(coeffs)[:, :, None]  # (segments, 6, 1): one joint
    T = np.ones(n)
    derivs = [c]
    for _ in range(4):
        derivs.append(derivative(derivs[-1]))
    roots = poly_roots(derivs[4], np.full((n, 0, 1), np.nan), T)
    for k in (3, 2, 1):
        roots = poly_roots(derivs[k], roots[0], T)
    lo, hi, _ = poly_range(c, *roots)
    truth_arr = np.array(truth)
    tol = 1e-15 * np.abs(truth_arr).max(axis=1)
    assert np.all(hi[:, 0] >= truth_arr.max(axis=1) - tol)
    assert np.all(lo[:, 0] <= truth_arr.min(axis=1) + tol)
    # every value reported is the polynomial's at some point of [0, 1]: never beyond its true range
    assert np.all(hi[:, 0] <= truth_arr.max(axis=1) + tol) and np.all(lo[:, 0] >= truth_arr.min(axis=1) - tol)


def test_non_finite_motion_is_refused() -> None:
    """A segment too short to represent is refused when the trajectory is built; a polynomial that is not
    finite (e.g. a start segment overflowing) is refused by the limits check, never read as in range."""
    with pytest.raises(InvalidValueError, match=r"point 1: time_from_start 1e-300 s is less than 1e-09 s after"):
        Trajectory(["a"], [TrajectoryPoint(0.0, [0.0]), TrajectoryPoint(1e-300, [1.0])])
    sampler = TrajectorySampler(Trajectory(["a"], [TrajectoryPoint(1e-6, [1e300])]), 0.0, [-1e300])
    with pytest.raises(agentsdk.LimitViolation, match=r"segment start state -> point 0 .*joint 'a'.*not finite"):
        check_motion_limits(sampler, [-np.inf], [np.inf], [1.0], [1.0])


# ----------------------------------------------------------------- accepted => within the limits


@st.composite
def random_follow(draw: st.DrawFn) -> dict[str, Any]:
    k = draw(st.integers(1, 3))
    names = draw(st.permutations(NAMES))[:k]
    n = draw(st.integers(1, 4))
    kind = draw(st.sampled_from(["pos", "vel", "acc"]))
    first = draw(st.sampled_from([0.0, 0.05, 0.3, 0.8, 1.5]))
    gaps = draw(st.lists(st.floats(0.02, 1.5), min_size=n - 1, max_size=n - 1))
    times = np.cumsum([first, *gaps]) if first > 0 else np.cumsum([0.0, *gaps])
    if first == 0.0 and n == 1:
        times = np.array([0.5])
    pos = st.floats(-2.2, 2.2)
    vel = st.floats(-3.0, 3.0)
    acc = st.floats(-12.0, 12.0)
    pts = []
    for i, t in enumerate(times):
        p = [draw(pos) for _ in names]
        v = [0.0 if draw(st.booleans()) else draw(vel) for _ in names] if kind != "pos" else None
        a = [0.0 if draw(st.booleans()) else draw(acc) for _ in names] if kind == "acc" else None
        if t == 0.0:  # a first point at time 0: the current state (the robot starts at rest at 0)
            p, v, a = [0.0] * k, None if v is None else [0.0] * k, None if a is None else [0.0] * k
        if i == n - 1 and v is not None and draw(st.booleans()):
            v = [0.0] * k
        pts.append(TrajectoryPoint(float(t), p, v, a))
    return {
        "traj": Trajectory(names, pts),
        "kind": kind,
        "allow": draw(st.booleans()),
        "stretch": draw(st.booleans()),
        "scale": draw(st.sampled_from([1.0, 1.0, 0.5])),
    }


async def _run_random(case: dict[str, Any]) -> None:
    async with agentsdk.connect("mock", robot="arm3", safety=SAFETY) as robot:
        dt = robot.control_period
        rows: list[tuple[np.ndarray, np.ndarray]] = []
        robot.add_tick_hook(agentsdk.Phase.OBSERVE, lambda t, s, sp: rows.append((sp.position.copy(),
                                                                                  sp.velocity.copy())))
        robot.set_speed_scaling(case["scale"])
        traj: Trajectory = case["traj"]
        try:
            motion = robot.follow(traj, Tolerances(goal=0.05, goal_time=0.5),
                                  allow_nonzero_velocity_at_end=case["allow"], stretch_to_limits=case["stretch"])
        except CommandRejected as exc:
            msg = str(exc)
            assert "\n" not in msg
            assert ("point" in msg or "segment" in msg) and any(f"'{n}'" in msg for n in traj.joint_names), msg
            assert not robot.busy
            return
        result = await motion
        assert result.code in (ResultCode.SUCCESSFUL, ResultCode.GOAL_TOLERANCE_VIOLATED), result
        await robot.clock.sleep(0.05)
        q = np.array([r[0] for r in rows])
        v = np.array([r[1] for r in rows])
        infos = robot.joints
        lo = np.array([j.lower for j in infos])
        hi = np.array([j.upper for j in infos])
        vmax = np.array([j.max_velocity for j in infos])
        amax = np.array([j.max_acceleration for j in infos])
        assert np.isfinite(q).all() and np.isfinite(v).all()
        assert np.all((q >= lo - 1e-9) & (q <= hi + 1e-9)), "a setpoint left the position limits"
        assert np.all(np.abs(v) <= vmax * (1 + 1e-6) + 1e-9), np.abs(v).max(axis=0)
        assert np.all(np.abs(np.diff(q, axis=0)) <= vmax * dt * (1 + 1e-5) + 1e-9)
        if case["kind"] != "pos":  # positions only: linear like JTC, velocity steps at the points by design
            acc = np.abs(np.diff(v, axis=0)) / dt
            assert np.all(acc <= amax * (1 + 1e-3) + 1e-6), acc.max(axis=0)
        assert not any(e.kind in ("clip", "step") for e in robot.safety.events), robot.safety.events


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=random_follow())
def test_no_accepted_trajectory_exceeds_a_limit(case: dict[str, Any]) -> None:
    """Issue 14: over random trajectories, an accepted trajectory's per-tick setpoints stay within the
    position, velocity and acceleration limits; a refused one names the point/segment and the joint."""
    asyncio.run(_run_random(case))


# ----------------------------------------------------------------- issue 10, item 4: numeric garbage

GARBAGE = st.sampled_from([math.nan, math.inf, -math.inf, -1.0, 0.0, 1e-300, -1e-300, 1e300, -1e300, 1e9, 2.0**53])
NUMBER = st.one_of(GARBAGE, st.floats(-5.0, 5.0))


@st.composite
def garbage_case(draw: st.DrawFn) -> dict[str, Any]:
    field = draw(st.sampled_from(["time", "position", "velocity", "acceleration", "path", "goal", "goal_time",
                                  "duration", "start_time", "speed"]))
    return {"field": field, "value": draw(NUMBER), "second_time": draw(st.sampled_from([1.0, 1e300, 1e-300]))}


async def _run_garbage(case: dict[str, Any]) -> None:
    async with agentsdk.connect("mock", robot="arm3", safety=SAFETY) as robot:
        bad_setpoints: list[str] = []
        lo = np.array([j.lower for j in robot.joints])
        hi = np.array([j.upper for j in robot.joints])

        def watch(t: float, s: agentsdk.StateView, sp: agentsdk.SetpointView) -> None:
            if not (np.isfinite(sp.position).all() and np.isfinite(sp.velocity).all()):
                bad_setpoints.append(f"non-finite setpoint at {t}")
            elif not np.all((sp.position >= lo - 1e-9) & (sp.position <= hi + 1e-9)):
                bad_setpoints.append(f"setpoint outside the limits at {t}")

        robot.add_tick_hook(agentsdk.Phase.OBSERVE, watch)
        f, x = case["field"], case["value"]
        motion = None
        try:
            if f == "speed":
                robot.set_speed_scaling(x)
                motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(1.0, [0.3])]))
            elif f == "duration":  # the public API; a motion that runs is cancelled with its task below
                move = asyncio.create_task(robot.move_to({"joint1": 0.3}, duration=x))
                async with asyncio.timeout(60):  # wall-clock guard only
                    await robot.clock.sleep(1.5)
                    if not move.done():
                        move.cancel()
                    await asyncio.wait([move])
                if not move.cancelled():
                    move.result()  # raises the refusal, checked below
            else:
                t1 = x if f == "time" else 1.0
                p = x if f == "position" else 0.3
                v = x if f == "velocity" else 0.0
                a = x if f == "acceleration" else 0.0
                pts = [TrajectoryPoint(t1, [p], [v], [a]), TrajectoryPoint(case["second_time"] + abs(t1)
                                                                          if math.isfinite(t1) else 2.0,
                                                                          [0.3], [0.0], [0.0])]
                tol = Tolerances(
                    path=x if f == "path" else None,
                    goal={"joint1": x} if f == "goal" else 0.02,
                    goal_time=x if f == "goal_time" else 0.5,
                )
                motion = robot.follow(Trajectory(["joint1"], pts), tol,
                                      start_time=robot.clock.now() + x if f == "start_time" else None)
        except AgentSDKError as exc:
            assert "\n" not in str(exc) and str(exc), repr(exc)
        if motion is not None:
            async with asyncio.timeout(60):  # wall-clock guard only; robot time is bounded below
                await robot.clock.sleep(1.5)
                motion.cancel()
                motion.cancel()  # idempotent, never raises
                await motion
        assert not bad_setpoints, bad_setpoints[:3]
        robot.set_speed_scaling(1.0)
        assert (await robot.move_to({"joint1": 0.1})).ok  # usable afterwards


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=garbage_case())
def test_numeric_garbage_is_refused_or_harmless(case: dict[str, Any]) -> None:
    """Issue 10 item 4: every numeric field of TrajectoryPoint/Trajectory/Tolerances, follow's start_time,
    move_to's duration and the speed scaling: a one-line error, or a run without NaN or limit violations."""
    asyncio.run(_run_garbage(case))


async def test_huge_time_from_start_is_refused_and_cancel_keeps_working() -> None:
    """Issue 10 item 4: ``time_from_start=1e300`` overflowed to NaN setpoints, after which ``cancel()``
    raised InvalidValueError and later cancels did nothing."""
    with pytest.raises(InvalidValueError, match=r"time_from_start 1e\+300 s is beyond the supported"):
        Trajectory(["joint1"], [TrajectoryPoint(1e300, [0.3])])
    Trajectory(["joint1"], [TrajectoryPoint(MAX_TIME_FROM_START, [0.3])])
    async with agentsdk.connect("mock", robot="arm3", safety=SAFETY) as robot:
        motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(1e5, [0.3])]))
        await robot.clock.sleep(0.1)
        motion.cancel()
        motion.cancel()
        assert (await motion).code is ResultCode.CANCELED
        assert np.isfinite(robot.setpoint.position).all()


async def test_move_to_huge_duration_is_a_clear_error() -> None:
    """Issue 10 item 14: ``move_to(duration=1e300)`` raised a raw ``ValueError: -101 is not a valid Result``."""
    async with agentsdk.connect("mock", robot="arm3", safety=SAFETY) as robot:
        for bad in (1e300, 1e4, math.inf, math.nan, -1.0, 0.0):
            with pytest.raises(InvalidValueError, match="duration") as info:
                await robot.move_to({"joint1": 0.3}, duration=bad)
            assert "is not a valid Result" not in str(info.value)
        assert not robot.busy
        assert (await robot.move_to({"joint1": 0.3}, duration=2.0)).ok


def test_tolerance_nan_no_longer_disables_the_path_check() -> None:
    """Issue 10 item 4: ``Tolerances(path={j: nan})`` silently disabled the path check."""
    with pytest.raises(InvalidValueError, match=r"path \('joint1'\) tolerance must be > 0"):
        Tolerances(path={"joint1": math.nan})


@pytest.mark.parametrize("start", [(0.42439251, 0.82285978, -8.0), (-0.23012203, -1.93438846, 8.0)])
async def test_a_move_planned_late_in_a_run_from_a_braking_state_passes_its_own_limit_check(
    start: tuple[float, float, float],
) -> None:
    # A move_to issued while a cancelled motion still brakes at max_acceleration starts with a
    # jerk phase of a few µs. The sampler used to take segment durations as differences of absolute
    # robot times, whose rounding (~eps * t) its quintic turned into an acceleration error of
    # 6 |v| eps t / T^2: 8.009 against a limit of 8 at t = 91 s, and move_to raised LimitViolation.
    from agentsdk.trajectory import plan_point_to_point

    async with agentsdk.connect("mock", robot="arm3", safety=SAFETY) as robot:
        j = robot.joints[0]
    assert j.max_acceleration == abs(start[2])
    q0, v0, a0 = start
    for q1 in np.linspace(-1.0, 1.0, 21):
        traj = plan_point_to_point(([q0], [v0], [a0]), [float(q1)], [j])
        for t0 in (0.0, 91.362, 3600.0 * 24):
            sampler = TrajectorySampler(traj, start_time=t0, start_positions=[q0], start_velocities=[v0],
                                        start_accelerations=[a0])
            check_motion_limits(sampler, [j.lower], [j.upper], [j.max_velocity], [j.max_acceleration])
            # the same motion whenever it starts: the peaks do not depend on the clock's reading
            ref = TrajectorySampler(traj, start_time=0.0, start_positions=[q0], start_velocities=[v0],
                                    start_accelerations=[a0]).peaks()
            assert np.allclose(sampler.peaks().a_peak, ref.a_peak, rtol=1e-9, atol=1e-9)


async def test_move_to_right_after_a_cancel_is_admitted_at_any_time_of_the_run() -> None:
    rng = np.random.default_rng(7)
    async with agentsdk.connect("mock", robot="arm3", safety=SAFETY) as robot:
        await robot.clock.sleep(90.0)  # the robot's clock reads ~90 s: the rounding above grows with it
        for _ in range(40):
            task = asyncio.ensure_future(robot.move_to({"joint1": float(rng.uniform(-1, 1)),
                                                        "joint2": float(rng.uniform(-0.5, 0.5))}))
            await robot.clock.sleep(float(rng.uniform(0.01, 0.4)))
            task.cancel()  # the robot brakes at max_acceleration (unless the move already ended)
            await asyncio.gather(task, return_exceptions=True)
            await robot.clock.sleep(float(rng.choice([0.0, 0.002, 0.004, 0.01])))
            result = await robot.move_to({"joint1": float(rng.uniform(-1, 1))})
            assert result.code == ResultCode.SUCCESSFUL, result
