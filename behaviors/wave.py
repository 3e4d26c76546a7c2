"""Wave: move arm3 through a few poses with direct position commands and read the state back.

    agentsdk run behaviors/wave.py                 # MuJoCo, lockstep
    agentsdk run behaviors/wave.py --backend pybullet
"""

from __future__ import annotations

import logging

from agentsdk import JointCommand, Robot

ROBOT = "arm3"

log = logging.getLogger("behaviors.wave")

POSES: list[dict[str, float]] = [
    {"joint1": 0.0, "joint2": 0.6, "joint3": 0.0},
    {"joint1": 0.8, "joint2": 0.9, "joint3": 1.0},
    {"joint1": -0.8, "joint2": 0.9, "joint3": -1.0},
    {"joint1": 0.8, "joint2": 0.9, "joint3": 1.0},
    {"joint1": 0.0, "joint2": 0.4, "joint3": 0.0},
]


async def main(robot: Robot) -> None:
    names = [j.name for j in robot.joints]
    for pose in POSES:
        # tolerate robots whose first three joints are named differently (e.g. mit_leg): map the
        # poses onto their first joints, kept a little inside each joint's range
        target = pose if set(pose) <= set(names) else dict(zip(names, pose.values(), strict=False))
        target = {n: _inside(robot, n, q) for n, q in target.items()}
        applied = await robot.command(JointCommand("position", target))
        await robot.clock.sleep(1.5)
        state = await robot.read()
        errors = {n: applied.values[n] - state.positions()[n] for n in applied.values}
        log.info("t=%.2f pose %s error %s", state.stamp, target, errors)


def _inside(robot: Robot, name: str, q: float, margin: float = 0.1) -> float:
    """``q`` clipped into joint ``name``'s limits, ``margin`` (or a quarter of the range) inside them."""
    j = robot.joints[robot.joint_names.index(name)]
    m = min(margin, (j.upper - j.lower) / 4)
    return min(max(q, j.lower + m), j.upper - m)
