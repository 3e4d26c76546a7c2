"""Square: draw a square with the end effector through ``move_to_pose(linear=True)``.

    agentsdk run behaviors/square.py                       # arm3 on MuJoCo
    agentsdk run behaviors/square.py --backend pybullet
    agentsdk run behaviors/square.py --robot path/to/panda/robot.yaml

Works on any arm: the end effector is the link named like a tool frame (``tool0``,
``*_tcp``, ``ee_link``, ...) or else the link moved by the most joints. The behavior
moves (in joint space) to a well-conditioned configuration, then draws a square of side
``SIDE`` in the plane the end effector moves best in (the two strongest directions of its
position Jacobian), corner to corner along straight lines, keeping the orientation fixed
on arms with 6 or more joints. On arms with fewer joints only the position is controlled,
and the corners are snapped to the nearest reachable points (arm3's end effector lives on
a sphere: its square is drawn on a plane cutting that sphere, and its sides, straight
lines, stay within ``path_tolerance`` of it).

It logs and returns a :class:`SquareReport`: the largest distance of the end effector from
the side it was drawing, sampled every control period, and how far the square's end is
from its start. A leg that fails raises :class:`RuntimeError` naming it.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass

import numpy as np

from agentsdk import Pose, Robot, Tolerances, UnreachablePoseError
from agentsdk.kinematics import Kinematics

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
_TOOL_NAMES = ("tool0", "tcp", "ee_link", "end_effector", "eef", "flange", "tool")

log = logging.getLogger("behaviors.square")


@dataclass(frozen=True)
class SquareReport:
    """What the run measured (metres)."""

    link: str
    corners: tuple[tuple[float, float, float], ...]
    #: largest distance of the measured end-effector position from the side being drawn
    max_deviation: float
    #: distance between the measured end position and the first corner
    closing_error: float


def end_effector(kin: Kinematics) -> str:
    """The tool frame: a link named like one, else the link moved by the most joints (the deepest)."""
    for link in reversed(kin.link_names):
        low = link.lower()
        if any(low == name or low.endswith("_" + name) for name in _TOOL_NAMES):
            return link
    return max(kin.link_names, key=lambda link: len(kin.chain(link)))


def ready_configuration(kin: Kinematics, link: str, full: bool, start: np.ndarray, samples: int = 300) -> np.ndarray:
    """A configuration near ``start`` where the end effector moves well in a plane.

    Maximises the product of the two largest singular values of the position Jacobian (of all
    six for a full-pose arm) over configurations within 0.6 rad of ``start`` (so the move there
    stays short and away from self-collisions), inside the limits, with the end effector not
    below the root.
    """
    rng = np.random.default_rng(0)
    lo = np.where(np.isfinite(kin.lower), kin.lower, -np.pi)
    hi = np.where(np.isfinite(kin.upper), kin.upper, np.pi)
    margin = 0.05 * (hi - lo)
    best, best_q = -1.0, start
    for k in range(samples):
        q = start if k == 0 else np.clip(start + rng.uniform(-0.6, 0.6, len(start)), lo + margin, hi - margin)
        if kin.fk(link, q).position[2] < 0.0:
            continue
        jac = kin.jacobian(link, q)
        sv = np.linalg.svd(jac if full else jac[:3], compute_uv=False)
        score = float(np.prod(sv[:6] if full else sv[:2]))
        if score > best:
            best, best_q = score, q
    return best_q


async def main(robot: Robot) -> SquareReport:
    kin = robot.kinematics
    link = end_effector(kin)
    chain = kin.chain(link)
    full = len(chain) >= 6
    state = await robot.read()
    q_ready = ready_configuration(kin, link, full, np.array(state.position))
    tight = Tolerances(goal=0.004, goal_time=2.0)
    result = await robot.move_to({j: float(q_ready[kin.joint_names.index(j)]) for j in chain}, tolerances=tight)
    if not result.ok:
        raise RuntimeError(f"square: could not reach the start configuration: {result.message}")

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
    log.info("drawing a %.3g m square with %r (%s) around %s", SIDE, link,
             "full pose" if full else "position only", np.round(center.position, 4).tolist())

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
    log.info("square done: max deviation from the sides %.3g mm, closing error %.3g mm",
             deviation * 1e3, closing * 1e3)
    return report
