"""Pick and place on arm3 as a sequence of trajectories.

    agentsdk run behaviors/pick_place.py                    # MuJoCo, lockstep
    agentsdk run behaviors/pick_place.py --backend pybullet
    agentsdk run behaviors/pick_place.py --backend mock

Shows the three ways to describe a motion:

* ``robot.move_to(pose)``: a minimum-time, jerk-limited move planned for you
  (optionally with ``duration=``);
* a :class:`Trajectory` of positions only: each segment is interpolated for you
  (a single point = a smooth quintic from where the robot is, to rest);
* a :class:`Trajectory` with positions, velocities and accelerations at every
  point: you own the timing and the shape (here a minimum-jerk transfer from
  above the pick to above the place, with exact derivatives).

Every step prints its result code and final error; a failed step stops the
behavior with an error (exit code 1).
"""

from __future__ import annotations

import numpy as np

from agentsdk import MotionResult, Robot, Tolerances, Trajectory, TrajectoryPoint
from agentsdk.errors import ConfigurationError

ROBOT = "arm3"

JOINTS = ("joint1", "joint2", "joint3")
HOME = {"joint1": 0.0, "joint2": 0.3, "joint3": 0.0}
ABOVE_PICK = {"joint1": 0.8, "joint2": 0.5, "joint3": 0.4}
AT_PICK = {"joint1": 0.8, "joint2": 0.95, "joint3": 0.4}
ABOVE_PLACE = {"joint1": -0.8, "joint2": 0.5, "joint3": -0.4}
AT_PLACE = {"joint1": -0.8, "joint2": 0.95, "joint3": -0.4}
GRIP_TIME = 0.3  # s: the "gripper" closes/opens (arm3 has none: we dwell)


def _vec(pose: dict[str, float]) -> np.ndarray:
    return np.array([pose[j] for j in JOINTS])


def min_jerk_trajectory(start: dict[str, float], end: dict[str, float], duration: float, n: int = 6) -> Trajectory:
    """A straight joint-space minimum-jerk move sampled at n+1 points, with exact velocities and accelerations.

    Point 0 is at time 0 (the start pose, at rest): start it where the robot is.
    """
    q0, q1 = _vec(start), _vec(end)
    dq = q1 - q0
    points = []
    for i in range(n + 1):
        t = duration * i / n
        s = t / duration
        p = 10 * s**3 - 15 * s**4 + 6 * s**5
        dp = (30 * s**2 - 60 * s**3 + 30 * s**4) / duration
        ddp = (60 * s - 180 * s**2 + 120 * s**3) / duration**2
        points.append(TrajectoryPoint(t, q0 + dq * p, dq * dp, dq * ddp))
    return Trajectory(JOINTS, points)


def descend(pose: dict[str, float], duration: float) -> Trajectory:
    """Positions only, one point: a quintic from the current desired state to rest at ``pose``."""
    return Trajectory(JOINTS, [TrajectoryPoint(duration, _vec(pose))])


def approach(above: dict[str, float], at: dict[str, float], duration: float) -> Trajectory:
    """Positions and velocities (cubic Hermite): slow down through a pre-grasp point, stop at ``at``."""
    q_above, q_at = _vec(above), _vec(at)
    pre = q_above + 0.8 * (q_at - q_above)
    v_pre = 0.5 * (q_at - q_above) / duration  # still creeping down at the pre-grasp point
    return Trajectory(
        JOINTS,
        [
            TrajectoryPoint(0.0, q_above, np.zeros(3)),
            TrajectoryPoint(0.7 * duration, pre, v_pre),
            TrajectoryPoint(duration, q_at, np.zeros(3)),
        ],
    )


def report(step: str, result: MotionResult, t0: float) -> None:
    worst = max(abs(e) for e in result.error.values())
    print(
        f"  {step:<22s} {result.code.name:<24s} t={result.time:6.3f} s ({result.time - t0:5.3f} s)  "
        f"max error {worst:.4f} rad"
    )
    if not result.ok:
        raise RuntimeError(f"pick_place: step {step!r} failed: {result.code.name} {result.message}")


async def main(robot: Robot) -> None:
    missing = [j for j in JOINTS if j not in robot.joint_names]
    if missing:
        raise ConfigurationError(f"pick_place needs arm3's joints {JOINTS}; {robot.name} lacks {missing}")
    tight = Tolerances(path=0.1, goal=0.02, goal_time=1.0)
    clock = robot.clock
    print(f"pick and place on {robot.name} ({robot.backend})")

    t = clock.now()
    report("home (move_to)", await robot.move_to(HOME), t)
    t = clock.now()
    report("above pick (move_to)", await robot.move_to(ABOVE_PICK, duration=1.5), t)
    t = clock.now()
    report("approach pick", await robot.follow(approach(ABOVE_PICK, AT_PICK, 1.0), tight), t)
    await clock.sleep(GRIP_TIME)  # grasp
    print(f"  {'grasp':<22s} closed at t={clock.now():6.3f} s")
    t = clock.now()
    report("lift", await robot.follow(descend(ABOVE_PICK, 0.8), tight), t)
    t = clock.now()
    report("transfer (min-jerk)", await robot.follow(min_jerk_trajectory(ABOVE_PICK, ABOVE_PLACE, 2.0), tight), t)
    t = clock.now()
    report("descend to place", await robot.follow(descend(AT_PLACE, 0.8), tight), t)
    await clock.sleep(GRIP_TIME)  # release
    print(f"  {'release':<22s} opened at t={clock.now():6.3f} s")
    t = clock.now()
    report("retreat", await robot.follow(descend(ABOVE_PLACE, 0.8), tight), t)
    t = clock.now()
    report("home (move_to)", await robot.move_to(HOME), t)
    print(f"pick and place done at t={clock.now():.3f} s")
