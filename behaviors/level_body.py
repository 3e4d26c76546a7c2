"""Level body: a four-legged robot keeps its body level on a tilted floor using its IMU.

    agentsdk run behaviors/level_body.py                  # MuJoCo, lockstep
    agentsdk run behaviors/level_body.py --backend pybullet

The leveler stands on a floor tilted 10° (robots/leveler/robot.yaml). At rest its IMU's specific
force points straight up (against gravity); in the body frame that direction gives the body's
tilt (pitch ``atan2(-f_x, f_z)``, roll ``atan2(f_y, f_z)``). A 50 Hz feedback agent reads the IMU
and integrates each telescopic leg's length so that the tilt goes to zero: a leg at ``(x, y)``
from the body's centre changes by ``k * (x * pitch - y * roll)`` per second.
On a backend without an IMU (mock) there is nothing to level and the behavior only reports that.
"""

from __future__ import annotations

import logging
import math
from typing import ClassVar

from agentsdk import JointCommand, JointState, Robot
from agentsdk.feedback import FeedbackAgent, FeedbackState, run_feedback
from agentsdk.sensors import Imu

ROBOT = "leveler"

log = logging.getLogger("behaviors.level_body")

#: leg positions (x, y) in the body frame (m), as in leveler.urdf
LEGS = {"fl": (0.15, 0.1), "fr": (0.15, -0.1), "rl": (-0.15, 0.1), "rr": (-0.15, -0.1)}
#: integral gain (1/s): leg length rate per metre of lever arm per radian of tilt (the tilt decays
#: with a time constant of about 1 / GAIN)
GAIN = 2.5
#: low-pass filter of the specific force (per period): the legs' own motion accelerates the body
SMOOTHING = 0.2


def tilt(imu: Imu) -> tuple[float, float]:
    """(pitch, roll) of the body from the IMU's specific force (rad; zero when level)."""
    return tilt_of(*(float(v) for v in imu.linear_acceleration))


def tilt_of(fx: float, fy: float, fz: float) -> tuple[float, float]:
    """(pitch, roll) of the body from a specific force in the body frame."""
    return math.atan2(-fx, fz), math.atan2(fy, fz)


class Leveler(FeedbackAgent):
    """Integrates the leg lengths from the IMU tilt at 50 Hz."""

    rate = 50.0
    sensors: ClassVar[tuple[str, ...]] = ("imu",)

    def __init__(self) -> None:
        self.lengths = dict.fromkeys(LEGS, 0.0)
        self.pitch = self.roll = 0.0
        self.force: list[float] | None = None

    async def update(self, state: JointState) -> JointCommand | None:
        assert isinstance(state, FeedbackState)
        imu = state.sensors["imu"]
        assert isinstance(imu, Imu)
        f = [float(v) for v in imu.linear_acceleration]
        if self.force is None:
            self.force = f
        else:
            self.force = [a + SMOOTHING * (b - a) for a, b in zip(self.force, f, strict=True)]
        self.pitch, self.roll = tilt_of(*self.force)
        dt = 1.0 / self.rate
        for leg, (x, y) in LEGS.items():
            step = GAIN * (x * self.pitch - y * self.roll) * dt
            self.lengths[leg] = min(0.055, max(-0.055, self.lengths[leg] + step))
        return JointCommand("position", dict(self.lengths))


async def main(robot: Robot) -> None:
    if "imu" not in robot.sensors:
        log.info("no IMU on %s: nothing to level", robot.backend)
        return
    await robot.clock.sleep(0.5)  # settle on the slope
    imu = robot.sensors.read("imu")
    assert isinstance(imu, Imu)
    before = tilt(imu)
    agent = Leveler()
    await run_feedback(robot, agent, duration=4.0)
    after = (agent.pitch, agent.roll)
    log.info("body tilt (pitch, roll) before %.4f, %.4f rad, after %.4f, %.4f rad; legs %s", *before, *after,
             {k: round(v, 4) for k, v in agent.lengths.items()})
    if max(abs(after[0]), abs(after[1])) > 0.01:
        raise RuntimeError(f"the body is not level: pitch {after[0]:.4f} rad, roll {after[1]:.4f} rad")
