"""Square: draw a square with the end effector through ``move_to_pose(linear=True)``.

    agentsdk run behaviors/square.py                       # arm3 on MuJoCo
    agentsdk run behaviors/square.py --backend pybullet
    agentsdk run behaviors/square.py --robot ur5            # or panda, or path/to/robot.yaml

Works on any arm (see :mod:`agentsdk.arm`): the end effector is the link named like a tool
frame (``tool0``, ``*_tcp``, ``ee_link``, ...) or else the link moved by the most joints. The behavior
moves (in joint space) to a well-conditioned configuration, then draws a square of side
``SIDE`` in the plane the end effector moves best in (the two strongest directions of its
position Jacobian), corner to corner along straight lines, keeping the orientation fixed
on arms with 6 or more joints. On arms with fewer joints only the position is controlled,
and the corners are snapped to the nearest reachable points (arm3's end effector lives on
a sphere: its square is drawn on a plane cutting that sphere, and its sides, straight
lines, stay within ``path_tolerance`` of it).

It prints and returns a :class:`SquareReport`: the largest distance of the end effector from
the side it was drawing, sampled every control period, and how far the square's end is
from its start. A leg that fails raises :class:`RuntimeError` naming it.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

import numpy as np

from agentsdk import Pose, Robot, Tolerances, UnreachablePoseError
from agentsdk.arm import end_effector, ready_configuration_steps
from agentsdk.cartesian import plan_linear
from agentsdk.errors import LimitViolation
from agentsdk.kinematics import Kinematics, run_async

ROBOT = "arm3"
#: side of the square (m)
SIDE = 0.04
#: how far a straight side may pass from the reachable set (m); see Robot.move_to_pose
PATH_TOLERANCE = 1e-3
#: drawing is a precision task: slower than the joint limits allow, like MoveIt's default scaling
VELOCITY_SCALE = 0.5
ACCELERATION_SCALE = 0.25
#: a position-only corner may be moved this far to make it reachable (m)
SNAP = 0.005
#: configurations tried (each checked by planning the whole square on the host) before giving up
ATTEMPTS = 8


@dataclass(frozen=True)
class SquareReport:
    """What the run measured (metres)."""

    link: str
    corners: tuple[tuple[float, float, float], ...]
    #: largest distance of the measured end-effector position from the side being drawn
    max_deviation: float
    #: distance between the measured end position and the first corner
    closing_error: float


def square_corners(kin: Kinematics, link: str, full: bool, q_ready: np.ndarray) -> list[Pose]:
    """The four corners around the end effector at ``q_ready``, in the plane it moves best in."""
    center = kin.fk(link, q_ready)
    u_mat, _, _ = np.linalg.svd(kin.jacobian(link, q_ready)[:3])
    u, v = u_mat[:, 0], u_mat[:, 1]
    h = SIDE / 2
    corners: list[Pose] = []
    for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        point = center.position + h * (a * u + b * v)
        if full:
            corners.append(Pose(point, center.orientation))
        else:  # the nearest reachable point, staying on the ready configuration's branch
            try:
                sol = kin.ik(link, point, seed=q_ready, restarts=0)
            except UnreachablePoseError as exc:  # IK's best attempt is the nearest point it found
                if exc.result is None or exc.result.position_error > SNAP:
                    raise
                sol = exc.result
            corners.append(Pose(kin.fk(link, sol).position, center.orientation))
    return corners


async def drawable(robot: Robot, link: str, full: bool, q_ready: np.ndarray, corners: list[Pose]) -> bool:
    """Whether every side plans as a straight line from ``q_ready`` (host-side kinematics only)."""
    kin = robot.kinematics
    try:
        q = np.array(q_ready, dtype=float)
        sol = await kin.ik_async(link, corners[0] if full else corners[0].position, seed=q, restarts=0)
        for j, value in sol.items():
            q[kin.joint_names.index(j)] = value
        for k in range(1, 5):
            traj = await run_async(plan_linear(kin, link, corners[k % 4], q, robot.joints, position_only=not full,
                                        path_tolerance=PATH_TOLERANCE))
            if traj is not None:
                for j, value in zip(traj.joint_names, traj.points[-1].positions, strict=True):
                    q[kin.joint_names.index(j)] = value
    except (UnreachablePoseError, LimitViolation):
        return False
    return True


async def main(robot: Robot) -> SquareReport:
    kin = robot.kinematics
    link = end_effector(kin)
    chain = kin.chain(link)
    full = len(chain) >= 6
    state = await robot.read()
    # the best-conditioned configuration near the start whose square can be drawn (a few tries)
    for attempt in range(ATTEMPTS):
        q_ready = await run_async(ready_configuration_steps(kin, link, np.array(state.position), full=full,
                                                            seed=attempt, reach=0.6 + 0.2 * attempt))
        corners = square_corners(kin, link, full, q_ready)
        if await drawable(robot, link, full, q_ready, corners):
            break
    else:
        raise RuntimeError(f"square: found no place near the start pose of {robot.name} where {link!r} can draw "
                           f"a {SIDE * 100:.3g} cm square in {ATTEMPTS} tries")
    center = kin.fk(link, q_ready)
    tight = Tolerances(goal=0.004, goal_time=2.0)
    result = await robot.move_to({j: float(q_ready[kin.joint_names.index(j)]) for j in chain}, tolerances=tight)
    if not result.ok:
        raise RuntimeError(f"square: could not reach the start configuration: {result.message}")

    print(f"square on {robot.name} ({robot.backend}): a {SIDE * 100:.3g} cm square with {link!r} "
          f"({'full pose' if full else 'position only'}) around {np.round(center.position, 3).tolist()} m")

    result = await robot.move_to_pose(link, corners[0], tolerances=tight, position_only=not full)
    if not result.ok:
        raise RuntimeError(f"square: could not reach the first corner: {result.message}")
    await robot.clock.sleep(0.5)  # settle: the goal tolerance lets a move end before the arm is still

    deviation = 0.0
    side = (corners[0].position, corners[0].position)

    async def watch() -> None:
        nonlocal deviation
        while True:
            p = kin.fk(link).position
            a, b = side
            ab = b - a
            t = float(np.clip(np.dot(p - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
            deviation = max(deviation, float(np.linalg.norm(p - (a + t * ab))))
            await robot.clock.sleep(robot.control_period)

    watcher = asyncio.create_task(watch())
    try:
        for k in range(1, 5):
            target = corners[k % 4]
            side = (corners[k - 1].position, target.position)
            result = await robot.move_to_pose(link, target, linear=True, tolerances=tight,
                                              position_only=not full, path_tolerance=PATH_TOLERANCE,
                                              velocity_scale=VELOCITY_SCALE, acceleration_scale=ACCELERATION_SCALE)
            if not result.ok:
                raise RuntimeError(f"square: side {k} failed: {result.code.name}: {result.message}")
        await robot.clock.sleep(0.3)  # settle on the last corner
    finally:
        watcher.cancel()
        await asyncio.gather(watcher, return_exceptions=True)
    closing = float(np.linalg.norm(kin.fk(link).position - corners[0].position))
    report = SquareReport(link, tuple(tuple(c.position.tolist()) for c in corners), deviation, closing)
    print(f"square done: max deviation from the sides {deviation * 1e3:.3g} mm, "
          f"closing error {closing * 1e3:.3g} mm")
    return report
