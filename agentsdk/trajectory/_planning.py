"""Time parameterization: :func:`plan` through waypoints, :func:`plan_point_to_point`, :func:`plan_stop`."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt

from ..errors import CommandRejected, InvalidValueError, LimitViolation, UnknownJointError
from ..types import FloatArray, JointInfo
from ._ruckig import (
    MAX_PROFILE_DURATION,
    MIN_GAP,
    PLAN_POS_TOL,
    JointLimits,
    RuckigSolver,
    append_profile,
    check_positions,
    joint_limits,
    position_extrema,
    to_trajectory,
)
from ._types import VEL_RTOL, StartState, Trajectory, Values, vector


def _start_state(start: StartState | None, names: Sequence[str], all_names: Sequence[str]) -> tuple[FloatArray, ...]:
    if not isinstance(start, tuple | list) or len(start) != 3:
        raise InvalidValueError(
            f"start must be a (positions, velocities, accelerations) tuple (velocities/accelerations may be None), "
            f"got {start!r}"
        )
    out = []
    for values, what, default in zip(
        start, ("start positions", "start velocities", "start accelerations"), (None, 0.0, 0.0), strict=True
    ):
        if values is not None and not isinstance(values, Mapping):
            arr = np.asarray(values, dtype=np.float64)
            if arr.ndim == 1 and len(arr) == len(all_names) != len(names):
                idx = [list(all_names).index(nm) for nm in names]
                values = arr[idx]
        out.append(vector(values, names, what, default))
    return tuple(out)


def _select_joints(joints: Sequence[JointInfo], names: Sequence[str] | None) -> list[JointInfo]:
    by_name = {j.name: j for j in joints}
    if len(by_name) != len(joints):
        raise InvalidValueError("duplicate joint names in joints")
    if names is None:
        return list(joints)
    unknown = [nm for nm in names if nm not in by_name]
    if unknown:
        raise UnknownJointError(f"unknown joint(s) {unknown}; known joints: {sorted(by_name)}")
    wanted = set(names)
    return [j for j in joints if j.name in wanted]


def _waypoint_matrix(
    waypoints: Sequence[Mapping[str, float]] | npt.ArrayLike, joints: Sequence[JointInfo]
) -> tuple[list[JointInfo], FloatArray]:
    if isinstance(waypoints, Sequence) and waypoints and isinstance(waypoints[0], Mapping):
        keys = set(waypoints[0])
        infos = _select_joints(joints, list(waypoints[0]))
        names = [j.name for j in infos]
        rows = []
        for k, wp in enumerate(waypoints):
            if not isinstance(wp, Mapping):
                raise InvalidValueError(f"waypoint {k}: expected a mapping like waypoint 0, got {wp!r}")
            if set(wp) != keys:
                raise InvalidValueError(
                    f"waypoint {k}: names joints {sorted(wp)} but waypoint 0 names {sorted(keys)}; "
                    "every waypoint must name the same joints"
                )
            rows.append(vector(wp, names, f"waypoint {k}"))
        return infos, np.array(rows)
    try:
        arr = np.array(waypoints, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidValueError(f"waypoints: expected mappings or a 2-D array of floats, got {waypoints!r}") from exc
    infos = _select_joints(joints, None)
    if arr.ndim != 2 or arr.shape[1] != len(infos) or arr.shape[0] == 0:
        raise InvalidValueError(f"waypoints: expected shape (n_waypoints >= 1, {len(infos)} joints), got {arr.shape}")
    for k, row in enumerate(arr):
        bad = ~np.isfinite(row)
        if bad.any():
            j = int(np.argmax(bad))
            raise InvalidValueError(f"waypoint {k}: value of joint {infos[j].name!r} is {row[j]}")
    return infos, arr


def _through_velocity_estimate(Q: FloatArray, T: FloatArray, v_start: FloatArray, vmax: FloatArray) -> FloatArray:
    """Mean of adjacent slopes at knots where a joint keeps its direction, 0 where it reverses."""
    V = np.zeros_like(Q)
    V[0] = v_start
    if len(Q) > 2:
        Ts = np.where(T > 0, T, 1.0)[:, None]
        slopes = np.diff(Q, axis=0) / Ts
        s0, s1 = slopes[:-1], slopes[1:]
        same = np.sign(s0) * np.sign(s1) > 0
        V[1:-1] = np.clip(np.where(same, 0.5 * (s0 + s1), 0.0), -vmax, vmax)
    return V


_CANDIDATE_SCALES = (0.5, 1.0, 1.5, 2.0, 3.0)


def plan(
    waypoints: Sequence[Mapping[str, float]] | npt.ArrayLike,
    joints: Sequence[JointInfo],
    *,
    start: StartState | None = None,
    velocity_scale: float = 1.0,
    acceleration_scale: float = 1.0,
    jerk_scale: float = 1.0,
) -> Trajectory:
    """Time-parameterize a path through ``waypoints`` under the joints' limits.

    ``waypoints`` is a sequence of ``{joint name: position}`` mappings (all naming
    the same joints) or an array of shape (n, len(joints)) in ``joints`` order. The
    motion starts from ``start`` (``(q, v, a)``, e.g. the current desired state) or,
    if None, at rest at the first waypoint; it passes through every waypoint in order
    and ends at rest at the last one. Durations come from ``max_velocity *
    velocity_scale``, ``max_acceleration * acceleration_scale`` and ``max_jerk *
    jerk_scale`` (ruckig, jerk-limited, time-synchronized per segment); through
    velocities are chosen so that no joint leaves its position limits.

    Returns a trajectory whose point 0 (time 0) is the start state, with positions,
    velocities and accelerations at every profile breakpoint; waypoints appear
    exactly as points. Raises :class:`LimitViolation` for a waypoint or start outside
    the position limits (or a start velocity above ``max_velocity``).
    """
    infos, W = _waypoint_matrix(waypoints, joints)
    lim = joint_limits(infos, velocity_scale, acceleration_scale, jerk_scale)
    names = lim.names
    for k, row in enumerate(W):
        check_positions(row, lim, f"waypoint {k}")
    n = len(names)
    if start is None:
        q0, v0, a0 = W[0], np.zeros(n), np.zeros(n)
        Q = W
    else:
        q0, v0, a0 = _start_state(start, names, [j.name for j in joints])
        check_positions(q0, lim, "start", PLAN_POS_TOL)
        _check_start_velocity(v0, infos)
        Q = np.vstack([q0[None, :], W])
    rk = RuckigSolver(lim)
    zero = np.zeros(n)
    nseg = len(Q) - 1

    # rest-to-rest durations, for the through-velocity estimate
    T = np.array([rk.solve(Q[i], zero, zero, Q[i + 1], zero).duration for i in range(nseg)])
    base = _through_velocity_estimate(Q, T, v0, lim.vmax)
    V = np.zeros_like(Q)
    V[0] = v0

    def seg(i: int, vi: FloatArray, vj: FloatArray) -> tuple[float, int]:
        """(duration, -1) of segment i from (Q[i], vi) to (Q[i+1], vj), or (inf, joint leaving its limits)."""
        tr = rk.solve(Q[i], vi, a0 if i == 0 else zero, Q[i + 1], vj)
        j = rk.within_position_limits(tr)
        return (tr.duration, -1) if j < 0 else (math.inf, j)

    def knot_cost(i: int, cand: FloatArray) -> tuple[float, FloatArray]:
        """Duration of the two segments around knot i with velocity ``cand`` there, after reducing the
        velocity of any joint that would leave its position limits (halve twice, then 0); inf if that fails.
        """
        cand = cand.copy()
        for _ in range(3 * n + 1):
            d0, j = seg(i - 1, V[i - 1], cand)
            if j < 0:
                d1, j = seg(i, cand, V[i + 1])
                if j < 0:
                    return d0 + d1, cand
            if cand[j] == 0.0:
                break
            cand[j] = 0.5 * cand[j] if abs(cand[j]) > 0.2 * abs(base[i, j]) else 0.0
        return math.inf, cand

    # the first segment from a moving start must stay within limits with at least v=0 at its target
    if nseg > 0 and start is not None:
        tr = rk.solve(Q[0], v0, a0, Q[1], zero)
        j = rk.within_position_limits(tr)
        if j >= 0:
            lo, hi = position_extrema(tr)
            raise LimitViolation(
                f"joint {names[j]!r} cannot reach waypoint 0 from the start state (velocity {v0[j]:.6g}) "
                f"without leaving its limits [{lim.lower[j]:.6g}, {lim.upper[j]:.6g}] "
                f"(would reach [{lo[j]:.6g}, {hi[j]:.6g}])"
            )
    # coordinate descent over a scale of the estimate at each interior knot; every accepted
    # candidate keeps both adjacent segments within the position limits (v=0 always does)
    if nseg > 1:
        for _sweep in range(2):
            for i in range(1, nseg):
                if not base[i].any():
                    continue
                best, best_v = knot_cost(i, V[i])
                for scale in _CANDIDATE_SCALES:
                    cost, cand = knot_cost(i, np.clip(base[i] * scale, -lim.vmax, lim.vmax))
                    if cost < best - 1e-9:
                        best, best_v = cost, cand
                V[i] = best_v

    rows: list[tuple[float, FloatArray, FloatArray, FloatArray]] = [(0.0, q0.copy(), v0.copy(), a0.copy())]
    t = 0.0
    for i in range(nseg):
        tr = rk.solve(Q[i], V[i], a0 if i == 0 else zero, Q[i + 1], V[i + 1])
        if tr.duration < MIN_GAP:
            continue
        append_profile(rows, tr, t, Q[i + 1].copy(), V[i + 1].copy())
        t = rows[-1][0]
    return to_trajectory(names, rows)


def _check_start_velocity(v0: FloatArray, infos: Sequence[JointInfo]) -> None:
    for j, info in enumerate(infos):
        if abs(v0[j]) > info.max_velocity * (1.0 + VEL_RTOL):
            raise LimitViolation(
                f"start: joint {info.name!r} velocity {v0[j]:.6g} exceeds max_velocity {info.max_velocity:.6g}"
            )


def plan_point_to_point(
    start: StartState,
    goal: Values,
    joints: Sequence[JointInfo],
    duration: float | None = None,
    *,
    velocity_scale: float = 1.0,
    acceleration_scale: float = 1.0,
    jerk_scale: float = 1.0,
) -> Trajectory:
    """A synchronized, jerk-limited move from ``start`` = ``(q, v, a)`` to rest at ``goal``.

    ``joints`` are the moving joints; ``start``/``goal`` values are mappings by name or
    sequences in ``joints`` order. With ``duration=None`` the move is the
    minimum-time one under the (scaled) limits; with a duration, all joints arrive
    together after exactly that long, and :class:`LimitViolation` is raised if the
    limits need longer (naming the limiting joint and the minimum duration).
    """
    infos = _select_joints(joints, None)
    lim = joint_limits(infos, velocity_scale, acceleration_scale, jerk_scale)
    names = lim.names
    q0, v0, a0 = _start_state(start, names, names)
    q1 = vector(goal, names, "goal")
    check_positions(q0, lim, "start", PLAN_POS_TOL)
    check_positions(q1, lim, "goal")
    _check_start_velocity(v0, infos)
    if duration is not None and not (math.isfinite(duration) and duration > 0.0):
        raise InvalidValueError(f"duration must be a positive number of seconds, got {duration}")
    if duration is not None and duration > MAX_PROFILE_DURATION:
        raise InvalidValueError(
            f"duration {duration:g} s is longer than {MAX_PROFILE_DURATION:g} s, the longest move ruckig times; "
            "split the motion or use a trajectory"
        )
    rk = RuckigSolver(lim)
    zero = np.zeros(len(names))
    try:
        tr = rk.solve(q0, v0, a0, q1, zero, duration)
    except CommandRejected:
        if duration is not None:
            raise
        # ruckig's time synchronization fails on some degenerate start states (e.g. a target equal to a
        # start that is at rest up to rounding, the state at the very end of the previous move): stop
        # first, then move from rest (always solvable; slower only by the stop, which is ~0 there)
        return _stop_then_move(lim, q0, v0, a0, q1)
    if duration is not None and tr.duration > duration * (1.0 + 1e-9) + 1e-9:
        mins = list(tr.independent_min_durations)
        j = int(np.argmax(mins))
        if mins[j] > duration:
            raise LimitViolation(
                f"duration {duration:.6g} s is too short: joint {names[j]!r} needs at least {mins[j]:.6g} s "
                f"to move from {q0[j]:.6g} to {q1[j]:.6g} (max_velocity {infos[j].max_velocity * velocity_scale:.6g}, "
                f"max_acceleration {infos[j].max_acceleration * acceleration_scale:.6g}, max_jerk {lim.jmax[j]:.6g})"
            )
        raise LimitViolation(
            f"duration {duration:.6g} s is not feasible from this start state under the limits; "
            f"the nearest feasible duration is {tr.duration:.6g} s"
        )
    j = rk.within_position_limits(tr)
    if j >= 0:
        lo, hi = position_extrema(tr)
        raise LimitViolation(
            f"joint {names[j]!r} would leave its limits [{lim.lower[j]:.6g}, {lim.upper[j]:.6g}] on the way "
            f"to the goal (reaching [{lo[j]:.6g}, {hi[j]:.6g}]) from start velocity {v0[j]:.6g}"
        )
    rows: list[tuple[float, FloatArray, FloatArray, FloatArray]] = [(0.0, q0, v0, a0)]
    if tr.duration >= MIN_GAP:
        append_profile(rows, tr, 0.0, q1, zero)
    return to_trajectory(names, rows)


def _stop_then_move(lim: JointLimits, q0: FloatArray, v0: FloatArray, a0: FloatArray, q1: FloatArray) -> Trajectory:
    """The fallback of :func:`plan_point_to_point`: each joint brakes to rest, then all move to ``q1`` from rest."""
    zero = np.zeros(len(q0))
    stop = RuckigSolver(lim, velocity_interface=True, synchronize=False).solve(q0, v0, a0, None, zero)
    rows: list[tuple[float, FloatArray, FloatArray, FloatArray]] = [(0.0, q0, v0, a0)]
    q_rest = q0
    if stop.duration >= MIN_GAP:
        append_profile(rows, stop, 0.0, None, zero)
        q_rest = rows[-1][1]
    rk = RuckigSolver(lim)
    for tr in (stop, rk.solve(q_rest, zero, zero, q1, zero)):
        j = rk.within_position_limits(tr)
        if j >= 0:
            lo, hi = position_extrema(tr)
            raise LimitViolation(
                f"joint {lim.names[j]!r} would leave its limits [{lim.lower[j]:.6g}, {lim.upper[j]:.6g}] on the "
                f"way to the goal (reaching [{lo[j]:.6g}, {hi[j]:.6g}]) from start velocity {v0[j]:.6g}"
            )
    move = rk.traj
    if move.duration >= MIN_GAP:
        append_profile(rows, move, rows[-1][0], q1, zero)
    return to_trajectory(lim.names, rows)


def plan_stop(
    q: Values,
    v: Values,
    a: Values | None,
    joints: Sequence[JointInfo],
    *,
    decel_scale: float = 1.0,
) -> Trajectory:
    """Decelerate every joint to rest as fast as its limits allow (JTC's "stop").

    Each joint stops independently (ruckig velocity interface, target velocity and
    acceleration 0) using ``max_acceleration * decel_scale`` as its deceleration
    limit and ``max_jerk`` as its jerk limit. Point 0 (time 0) is the given state;
    the last point is where the robot comes to rest, held afterwards. Positions are
    not checked against limits: a stop must always be possible.
    """
    infos = _select_joints(joints, None)
    lim = joint_limits(infos, 1.0, decel_scale, 1.0, margin=False)
    names = lim.names
    q0 = vector(q, names, "positions")
    v0 = vector(v, names, "velocities")
    a0 = vector(a, names, "accelerations", 0.0)
    rk = RuckigSolver(lim, velocity_interface=True, synchronize=False)
    zero = np.zeros(len(names))
    tr = rk.solve(q0, v0, a0, None, zero)
    rows: list[tuple[float, FloatArray, FloatArray, FloatArray]] = [(0.0, q0, v0, a0)]
    if tr.duration >= MIN_GAP:
        append_profile(rows, tr, 0.0, None, zero)
    return to_trajectory(names, rows)
