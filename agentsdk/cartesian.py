"""Cartesian motion: ``robot.move_to_pose`` and the straight-line planner behind ``linear=True``.

``move_to_pose(link, pose)`` solves IK (seeded with the current desired joint positions)
and runs an ordinary joint-space ``move_to``. With ``linear=True`` the link's origin
follows the straight line from where it is to ``pose`` (orientation: the shortest-arc
slerp), as MoveIt's ``computeCartesianPath`` does:

1. the line is sampled every millimetre (and every 0.01 rad of rotation), and IK is solved
   at every sample from the previous solution, so the joint path is continuous and stays
   on one IK branch; a sample whose IK residual exceeds ``path_tolerance`` (a line that
   leaves the workspace) or a joint jump (a singularity on the way) makes the plan fail;
2. the path is timed from the joint limits: with ``q(s)``, ``s`` in [0, 1], the path speed
   ``s'``, acceleration and jerk are bounded so that ``q' s'`` stays within every joint's
   velocity limit and ``q'' s'^2 + q' s''`` within its acceleration limit, and ``s(t)`` is a
   jerk-limited ruckig profile between those bounds (or stretched to ``duration``);
3. the samples become a :class:`Trajectory` with positions, velocities and accelerations
   (quintic interpolation), executed by ``robot.follow``: cancel, preemption, tolerances
   and the safety layer apply unchanged.

Unreachable targets (no IK solution, or a line that cannot be followed) end the call with a
``MotionResult`` whose code is ``INVALID_GOAL`` and whose message names the residual; nothing
moves. Bad arguments (unknown link, malformed pose, a duration too short for the limits)
raise, like ``move_to``.
"""

from __future__ import annotations

import math
from collections.abc import Generator, Sequence
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from .errors import InvalidValueError, LimitViolation, RobotClosedError, UnreachablePoseError
from .ik import IK_ORIENTATION_TOLERANCE, IK_POSITION_TOLERANCE, IKSolver, ik_target, run_async
from .kinematics import Kinematics
from .pose import Pose, quat_from_rotation_vector, quat_multiply, rotation_vector
from .trajectory import Trajectory, TrajectoryPoint, TrajectorySampler, plan_point_to_point
from .types import FloatArray, JointInfo

if TYPE_CHECKING:
    from .motion import MotionResult, Tolerances
    from .robot import Robot

__all__ = ["LINE_STEP", "LINE_STEP_ANGLE", "move_to_pose", "plan_linear"]

#: spacing of the IK samples along a straight line (m and rad)
LINE_STEP = 1e-3
LINE_STEP_ANGLE = 0.01
#: largest joint change between two samples before the plan is declared to cross a singularity
_MAX_JOINT_STEP = 0.15
_MAX_SAMPLES = 20000
#: iterations per line sample (seeded with the previous sample's solution, 1-3 are typical)
_SAMPLE_ITERATIONS = 30


def _slerp(q0: FloatArray, q1: FloatArray, s: float) -> FloatArray:
    inv = np.array([-q0[0], -q0[1], -q0[2], q0[3]])
    delta = rotation_vector(quat_multiply(inv, q1))
    return quat_multiply(q0, quat_from_rotation_vector(delta * s))


def plan_linear(
    kin: Kinematics,
    link: str,
    target: Pose,
    start: FloatArray,
    joints: Sequence[JointInfo],
    *,
    position_only: bool = False,
    duration: float | None = None,
    path_tolerance: float = 1e-3,
    path_orientation_tolerance: float = 0.01,
    velocity_scale: float = 1.0,
    acceleration_scale: float = 1.0,
) -> Generator[None, None, Trajectory | None]:
    """A straight-line Cartesian trajectory of ``link`` from ``start`` (joint positions) to ``target``.

    A cooperative computation (drive it with :func:`agentsdk.kinematics.run_async` or
    ``run_sync``). ``joints`` are the robot's joints (limits for timing); the trajectory
    covers the joints of ``kin.chain(link)``. Returns None when the link is already at
    the target. Raises :class:`UnreachablePoseError` when the line cannot be followed
    and :class:`LimitViolation` when ``duration`` is too short.
    """
    bid = kin.body_id(link)
    solver = IKSolver(kin)
    p0 = kin.fk(link, start)
    dist = float(np.linalg.norm(target.position - p0.position))
    angle = 0.0 if position_only else p0.distance(target)[1]
    n = max(2, math.ceil(dist / LINE_STEP), math.ceil(angle / LINE_STEP_ANGLE))
    if dist < 1e-7 and angle < 1e-7:
        return None
    if n > _MAX_SAMPLES:
        raise InvalidValueError(f"move_to_pose: a {dist:.3g} m / {angle:.3g} rad line is too long to sample")
    chain = kin.chain(link)
    cidx = np.array([kin.joint_names.index(j) for j in chain], dtype=np.intp)
    s = np.linspace(0.0, 1.0, n + 1)
    q_path = np.empty((n + 1, len(kin.joints)))
    q_path[0] = start
    q_prev = start
    for k in range(1, n + 1):
        pos = p0.position + s[k] * (target.position - p0.position)
        quat = target.orientation if (position_only or k == n) else _slerp(p0.orientation, target.orientation, s[k])
        goal = Pose.from_trusted_arrays(pos, quat)
        q, perr, rerr, _ = yield from solver.solve(
            bid, link, goal, q_prev, position_only, IK_POSITION_TOLERANCE * 0.1, IK_ORIENTATION_TOLERANCE * 0.1,
            _SAMPLE_ITERATIONS,
        )
        last = k == n
        ptol = IK_POSITION_TOLERANCE if last else path_tolerance
        rtol = IK_ORIENTATION_TOLERANCE if last else path_orientation_tolerance
        if perr > ptol or (not position_only and rerr > rtol):
            where = "the target" if last else f"{s[k] * dist:.4g} m along the {dist:.4g} m line"
            rot = "" if position_only else f", {rerr:.4g} rad orientation (tolerance {rtol:g} rad)"
            raise UnreachablePoseError(
                f"link {link!r} cannot follow the straight line to the target: at {where} the IK residual is "
                f"{perr:.4g} m position (tolerance {ptol:g} m){rot}; the line leaves the reachable workspace"
            )
        step = np.abs(q - q_prev)
        j = int(np.argmax(step))
        if step[j] > _MAX_JOINT_STEP:
            raise UnreachablePoseError(
                f"link {link!r} cannot follow the straight line to the target: joint {kin.joint_names[j]!r} would "
                f"jump by {step[j]:.3g} rad at {s[k] * dist:.4g} m along the line (a singularity or a joint limit "
                "on the way); residual of the last reachable sample "
                f"{float(np.linalg.norm(kin.fk(link, q_prev).position - pos)):.4g} m position"
            )
        q_path[k] = q
        q_prev = q
    q_path = q_path[:, cidx]
    infos = [joints[i] for i in cidx.tolist()]
    return _time_path(s, q_path, chain, infos, duration, velocity_scale, acceleration_scale)


def _time_path(
    s: FloatArray,
    q: FloatArray,
    names: Sequence[str],
    joints: Sequence[JointInfo],
    duration: float | None,
    velocity_scale: float = 1.0,
    acceleration_scale: float = 1.0,
) -> Trajectory:
    """Time the path ``q(s)`` from the joints' velocity/acceleration/jerk limits (see the module docstring)."""
    dq = np.gradient(q, s, axis=0, edge_order=2)
    ddq = np.gradient(dq, s, axis=0, edge_order=2)
    vmax = np.array([j.max_velocity for j in joints])
    amax = np.array([j.max_acceleration for j in joints])
    jmax = np.array([j.max_jerk for j in joints])
    vmax = np.where(np.isfinite(vmax) & (vmax > 0), vmax, 1.0) * velocity_scale
    amax = np.where(np.isfinite(amax) & (amax > 0), amax, 10.0) * acceleration_scale
    jmax = np.where(np.isfinite(jmax) & (jmax > 0), jmax, 200.0) * acceleration_scale
    adq = np.maximum(np.abs(dq), 1e-9)
    addq = np.abs(ddq)
    vs = float(np.min(vmax / adq))
    # leave half of each joint's acceleration for the path curvature term q'' s'^2
    curv = np.where(addq > 1e-9, np.sqrt(0.5 * amax / np.maximum(addq, 1e-12)), np.inf)
    vs = min(vs, float(np.min(curv)))
    acc = float(np.min((amax - addq * vs * vs) / adq))
    jerk = float(np.min(0.5 * jmax / adq))
    vs, acc, jerk = (min(x, 1e6) for x in (vs, acc, jerk))
    path = JointInfo("path", "prismatic", -1.0, 2.0, max_velocity=vs, max_effort=1.0, max_acceleration=acc,
                     max_jerk=jerk)
    try:
        profile = plan_point_to_point(([0.0], [0.0], [0.0]), [1.0], [path], duration=duration)
    except LimitViolation as exc:
        fastest = plan_point_to_point(([0.0], [0.0], [0.0]), [1.0], [path]).duration
        raise LimitViolation(
            f"move_to_pose: duration {duration:g} s is too short for this line under the joint limits; "
            f"it needs at least {fastest:.4g} s"
        ) from exc
    sampler = TrajectorySampler(profile, 0.0, [0.0], [0.0], [0.0])
    total = profile.duration
    grid = np.linspace(0.0, total, max(2000, 8 * len(s)))
    sg = np.array([sampler.sample(t)[0][0] for t in grid])
    sg = np.maximum.accumulate(sg) + np.arange(len(sg)) * 1e-15  # strictly increasing for the inverse
    times = np.interp(s, sg, grid)
    times[-1] = total
    points: list[TrajectoryPoint] = []
    prev_t = 0.0
    for k in range(1, len(s)):
        t = float(max(times[k], prev_t + 1e-6))
        _, sd, sdd = sampler.sample(t)
        v = dq[k] * sd[0]
        a = ddq[k] * sd[0] ** 2 + dq[k] * sdd[0]
        if k == len(s) - 1:
            v = np.zeros_like(v)
            a = np.zeros_like(a)
        points.append(TrajectoryPoint(t, q[k].tolist(), velocities=v.tolist(), accelerations=a.tolist()))
        prev_t = t
    return Trajectory(names, points)


async def _joint_move(
    robot: Robot, kin: Kinematics, link: str, q: FloatArray, duration: float | None, tolerances: Tolerances | None
) -> MotionResult:
    """``move_to`` of the joints that move ``link`` (a link no joint moves is already where IK says)."""
    from .motion import MotionResult, ResultCode

    goal = {j: float(q[kin.joint_names.index(j)]) for j in kin.chain(link)}
    if not goal:
        return MotionResult(ResultCode.SUCCESSFUL, {}, f"no joint moves link {link!r}", robot.clock.now())
    return await robot.move_to(goal, duration=duration, tolerances=tolerances)


async def move_to_pose(
    robot: Robot,
    link: str,
    pose: Pose | npt.ArrayLike,
    linear: bool = False,
    duration: float | None = None,
    tolerances: Tolerances | None = None,
    *,
    position_only: bool = False,
    path_tolerance: float = 1e-3,
    velocity_scale: float = 1.0,
    acceleration_scale: float = 1.0,
) -> MotionResult:
    """See :meth:`agentsdk.Robot.move_to_pose`."""
    from .motion import MotionResult, ResultCode

    if robot.closed:
        raise RobotClosedError(f"robot {robot.name!r} is closed")
    robot.safety.check_motion_allowed()
    kin = robot.kinematics
    kin.body_id(link)
    target, position_only = ik_target(pose, position_only)
    if not (isinstance(path_tolerance, int | float) and path_tolerance > 0 and math.isfinite(path_tolerance)):
        raise InvalidValueError(f"move_to_pose: path_tolerance must be a number > 0 (m), got {path_tolerance!r}")
    if duration is not None and not (math.isfinite(duration) and duration > 0.0):
        raise InvalidValueError(f"move_to_pose: duration must be a positive number of seconds, got {duration!r}")
    for what, scale in (("velocity_scale", velocity_scale), ("acceleration_scale", acceleration_scale)):
        if not (isinstance(scale, int | float) and 0.0 < scale <= 1.0):
            raise InvalidValueError(f"move_to_pose: {what} must be in (0, 1], got {scale!r}")
    start = _desired_positions(robot)
    try:
        if not linear:
            sol = await kin.ik_async(link, target, seed=start, position_only=position_only)
            goal = np.array([sol[j] for j in kin.joint_names])
            return await _joint_move(robot, kin, link, goal, duration, tolerances)
        joints = robot.joints
        traj = await run_async(
            plan_linear(kin, link, target, start, joints, position_only=position_only, duration=duration,
                        path_tolerance=path_tolerance, velocity_scale=velocity_scale,
                        acceleration_scale=acceleration_scale)
        )
    except UnreachablePoseError as exc:
        return MotionResult(ResultCode.INVALID_GOAL, {}, str(exc), robot.clock.now())
    if traj is None:  # already there
        return await _joint_move(robot, kin, link, start, duration, tolerances)
    return await robot.follow(traj, tolerances)


def _desired_positions(robot: Robot) -> FloatArray:
    """Where the robot is being driven now (a motion continues from its desired state, not the measured one)."""
    q, _, _ = robot.desired_state()
    kin = robot.kinematics
    clipped: FloatArray = np.clip(np.asarray(q, dtype=float), kin.lower, kin.upper)
    return clipped

