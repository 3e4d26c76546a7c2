"""Humanoid wave: raise the right arm, wave three times, look at the hand, lower the arm.

    agentsdk run behaviors/humanoid_wave.py                    # MuJoCo, lockstep, robot "humanoid"
    agentsdk run behaviors/humanoid_wave.py --backend pybullet

The wave itself is one :class:`Trajectory`: the shoulder roll and the elbow
follow ``c + A cos(2 pi f t)``, given at every quarter period with exact
positions and velocities (cubic Hermite interpolation between them), starting
and ending at rest at the outer extreme. Raising and lowering use
``robot.move_to`` (jerk-limited, minimum time or a given duration).
"""

from __future__ import annotations

import math

from agentsdk import MotionResult, Robot, Tolerances, Trajectory, TrajectoryPoint
from agentsdk.errors import ConfigurationError

ROBOT = "humanoid"

# see humanoid.urdf.xacro: shoulder_pitch < 0 swings the arm forward(-up); the right
# shoulder_roll < 0 swings it outward; elbow < 0 flexes
RAISED = {"right_shoulder_pitch": -2.6, "right_shoulder_roll": -0.35, "right_elbow": -0.5, "head_yaw": -0.5}
REST = {"right_shoulder_pitch": 0.0, "right_shoulder_roll": 0.0, "right_elbow": 0.0, "head_yaw": 0.0}
WAVE_JOINTS = ("right_shoulder_roll", "right_elbow")
WAVE_AMPLITUDE = (0.25, 0.35)  # rad; the wave swings between RAISED and RAISED - 2 * amplitude
WAVE_FREQUENCY = 0.55  # Hz: the cubic pieces peak at ~1.23 A (2 pi f)^2 = 5.2 rad/s^2, under the 6 limit
WAVES = 3


def wave_trajectory(start: dict[str, float]) -> Trajectory:
    """``WAVES`` cycles of ``c + A cos(w t)`` on WAVE_JOINTS, from rest at ``start`` (= c + A) back to it."""
    w = 2 * math.pi * WAVE_FREQUENCY
    quarter = 0.25 / WAVE_FREQUENCY
    amp = WAVE_AMPLITUDE
    center = [start[j] - a for j, a in zip(WAVE_JOINTS, amp, strict=True)]
    points = []
    for k in range(1, 4 * WAVES + 1):
        t = k * quarter
        points.append(
            TrajectoryPoint(
                t,
                [c + a * math.cos(w * t) for c, a in zip(center, amp, strict=True)],
                [0.0 if k % 2 == 0 else -a * w * math.sin(w * t) for a in amp],  # exact 0 at the extremes
            )
        )
    return Trajectory(WAVE_JOINTS, points)


def report(step: str, result: MotionResult) -> None:
    worst = max(abs(e) for e in result.error.values())
    print(f"  {step:<8s} {result.code.name:<22s} t={result.time:6.3f} s  max error {worst:.4f} rad")
    if not result.ok:
        raise RuntimeError(f"humanoid_wave: {step} failed: {result.code.name} {result.message}")


async def main(robot: Robot) -> None:
    missing = [j for j in RAISED if j not in robot.joint_names]
    if missing:
        raise ConfigurationError(f"humanoid_wave needs the humanoid's joints; {robot.name!r} lacks {missing}")
    print(f"humanoid wave on {robot.name} ({robot.backend})")
    report("raise", await robot.move_to(RAISED, duration=1.5))
    report("wave", await robot.follow(wave_trajectory(RAISED), Tolerances(path=0.15, goal=0.03)))
    await robot.clock.sleep(0.2)
    report("lower", await robot.move_to(REST, duration=1.5))
