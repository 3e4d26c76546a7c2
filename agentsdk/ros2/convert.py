"""Conversions between ROS 2 messages and agentsdk values (trajectories, tolerances, results)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..errors import InvalidValueError
from ..motion import Feedback, MotionResult, ResultCode, Tolerances
from ..trajectory import Trajectory, TrajectoryPoint
from .msgs import (
    Duration,
    FollowJointTrajectory_Goal,
    FollowJointTrajectory_Result,
    JointTolerance,
    JointTrajectory,
    JointTrajectoryPoint,
    Time,
)

__all__ = [
    "GOAL_ABORTED", "GOAL_ACCEPTED", "GOAL_CANCELED", "GOAL_CANCELING", "GOAL_EXECUTING", "GOAL_SUCCEEDED",
    "GOAL_UNKNOWN", "goal_status", "point_msg", "result_msg", "tolerances_from_goal", "trajectory_from_msg",
]

#: ``action_msgs/GoalStatus`` codes
GOAL_UNKNOWN, GOAL_ACCEPTED, GOAL_EXECUTING, GOAL_CANCELING, GOAL_SUCCEEDED, GOAL_CANCELED, GOAL_ABORTED = range(7)


def trajectory_from_msg(msg: JointTrajectory) -> Trajectory:
    """A :class:`Trajectory` from a ``trajectory_msgs/JointTrajectory`` (JTC's rules).

    Empty ``velocities``/``accelerations`` mean "not given"; ``effort`` is ignored (agentsdk
    trajectories are position trajectories). Raises :class:`InvalidValueError` (naming the
    point) for the wrong lengths, NaN or inf, or no points.
    """
    if not msg.points:
        raise InvalidValueError("trajectory has no points")
    points = []
    for k, p in enumerate(msg.points):
        t = p.time_from_start.sec + p.time_from_start.nanosec * 1e-9
        vel = list(p.velocities) if len(p.velocities) else None
        acc = list(p.accelerations) if len(p.accelerations) else None
        values = [*p.positions, *(vel or ()), *(acc or ())]
        if not all(math.isfinite(x) for x in values):
            raise InvalidValueError(f"point {k}: positions/velocities/accelerations must be finite (NaN or inf given)")
        points.append(TrajectoryPoint(t, list(p.positions), vel, acc))
    return Trajectory(list(msg.joint_names), points)


def _tolerance_map(tols: Sequence[JointTolerance], names: Sequence[str], what: str) -> dict[str, float]:
    """``{joint: position tolerance}`` from JointTolerance entries (0: default, < 0: not checked)."""
    out: dict[str, float] = {}
    known = set(names)
    for tol in tols:
        if tol.name not in known:
            raise InvalidValueError(f"{what} tolerance names joint {tol.name!r}, which is not in the trajectory")
        if math.isnan(tol.position):
            raise InvalidValueError(f"{what} tolerance of {tol.name!r} is NaN")
        if tol.position < 0:
            out[tol.name] = math.inf
        elif tol.position > 0:
            out[tol.name] = tol.position
    return out


def tolerances_from_goal(goal: FollowJointTrajectory_Goal, default: Tolerances) -> Tolerances:
    """The goal's path/goal/goal-time tolerances over ``default`` (JTC: 0 keeps the default, -1 disables)."""
    names = list(goal.trajectory.joint_names)
    path = _tolerance_map(goal.path_tolerance, names, "path")
    goal_tol = _tolerance_map(goal.goal_tolerance, names, "goal")
    gt = goal.goal_time_tolerance.sec + goal.goal_time_tolerance.nanosec * 1e-9

    def merged(base: float | dict[str, float] | None, override: dict[str, float]) -> float | dict[str, float] | None:
        if not override:
            return base
        if base is None:
            return override
        if isinstance(base, dict):
            return {**base, **override}
        return {n: override.get(n, base) for n in names}

    return Tolerances(
        path=merged(default.path, path),  # type: ignore[arg-type]
        goal=merged(default.goal, goal_tol),  # type: ignore[arg-type]
        goal_time=gt if gt > 0 else default.goal_time,
    )


def goal_status(code: ResultCode) -> int:
    """The final ``GoalStatus`` of a motion result: SUCCEEDED, CANCELED or ABORTED."""
    if code is ResultCode.SUCCESSFUL:
        return GOAL_SUCCEEDED
    if code is ResultCode.CANCELED:
        return GOAL_CANCELED
    return GOAL_ABORTED


def result_msg(result: MotionResult) -> FollowJointTrajectory_Result:
    """``FollowJointTrajectory_Result``: ``error_code`` is the :class:`ResultCode` value, one to one.

    SUCCESSFUL 0, INVALID_GOAL -1, INVALID_JOINTS -2, PATH_TOLERANCE_VIOLATED -4 and
    GOAL_TOLERANCE_VIOLATED -5 are control_msgs' constants; CANCELED -10, PREEMPTED -11 and
    ABORTED -12 are agentsdk's (their GoalStatus is CANCELED or ABORTED).
    """
    text = result.message or result.code.name
    return FollowJointTrajectory_Result(int(result.code), text)


def point_msg(positions: np.ndarray, velocities: np.ndarray | None = None, t: float = 0.0) -> JointTrajectoryPoint:
    """A ``JointTrajectoryPoint`` with positions (and velocities)."""
    return JointTrajectoryPoint(
        positions=[float(x) for x in positions],
        velocities=[] if velocities is None else [float(x) for x in velocities],
        time_from_start=Duration.from_seconds(t),
    )


def feedback_points(fb: Feedback) -> tuple[JointTrajectoryPoint, JointTrajectoryPoint, JointTrajectoryPoint]:
    """``(desired, actual, error)`` points of a motion's feedback."""
    desired = point_msg(fb.desired_positions, fb.desired_velocities)
    actual = point_msg(fb.actual_positions, fb.actual_velocities)
    error = point_msg(fb.error, np.asarray(fb.desired_velocities) - np.asarray(fb.actual_velocities))
    return desired, actual, error


def time_msg(t: float) -> Time:
    """``builtin_interfaces/Time`` of ``t`` seconds."""
    return Time.from_seconds(t)
