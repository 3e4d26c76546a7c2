"""Guarded move: lower the tool until the wrist force-torque sensor feels 5 N, then lift off.

    agentsdk run behaviors/guarded_move.py                  # MuJoCo, lockstep
    agentsdk run behaviors/guarded_move.py --backend pybullet

``move_to(..., until=force_above("wrist_ft", 5.0, tare=True))`` ends the motion SUCCESSFUL as
soon as the force measured since the move started (the tool's own weight tared away) exceeds
5 N, decelerating within the joint limits. On a backend without a force-torque sensor (mock) the
move runs to its goal above the table.
"""

from __future__ import annotations

import logging

from agentsdk import Robot
from agentsdk.sensors import WrenchStamped, force_above

ROBOT = "sensor_arm"

log = logging.getLogger("behaviors.guarded_move")

#: lift position to approach from, and the guarded move's goal (below the table top: contact stops it first)
ABOVE, THROUGH = 0.30, 0.10


async def main(robot: Robot) -> None:
    await robot.move_to({"lift": ABOVE}, 1.0)
    if "wrist_ft" not in robot.sensors:
        log.info("no wrist force-torque sensor on %s: moving down to 0.2 m without guarding", robot.backend)
        await robot.move_to({"lift": 0.2}, 1.0)
        return
    result = await robot.move_to({"lift": THROUGH}, 3.0, until=force_above("wrist_ft", 5.0, tare=True))
    state = await robot.read()
    ft = robot.sensors.read("wrist_ft")
    assert isinstance(ft, WrenchStamped)
    log.info("guarded move %s at lift %.4f m (%s); wrist force %s N",
             result.code.name, state.position[robot.joint_index["lift"]], result.message,
             [round(float(f), 2) for f in ft.wrench.force])
    if not result.ok or "force_above" not in result.message:
        raise RuntimeError(f"the guarded move did not stop on contact: {result}")
    await robot.move_to({"lift": ABOVE}, 1.5)  # lift off
