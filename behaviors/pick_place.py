"""Pick and place on any arm as a sequence of trajectories.

    agentsdk run behaviors/pick_place.py                    # arm3 on MuJoCo, lockstep
    agentsdk run behaviors/pick_place.py --backend pybullet
    agentsdk run behaviors/pick_place.py --robot ur5        # or panda, or path/to/robot.yaml

The poses come from the robot (:mod:`agentsdk.arm`): home is a well-conditioned
configuration near its start; the pick and the place are to its left and right (the first
arm joint turned by SPREAD), with the end effector DROP lower at the grasp.

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
from agentsdk.arm import layout_steps
from agentsdk.kinematics import run_async

ROBOT = "arm3"

#: rad the first arm joint turns from home to the pick (left) and to the place (right)
SPREAD = 0.8
#: m the end effector goes down from above the pick/place to the grasp
DROP = 0.06
GRIP_TIME = 0.3  # s: the "gripper" closes/opens (we dwell: not every arm has one)


def _vec(joints: tuple[str, ...], pose: dict[str, float]) -> np.ndarray:
    return np.array([pose[j] for j in joints])


def transfer_time(robot: Robot, start: dict[str, float], end: dict[str, float]) -> float:
    """A duration for a minimum-jerk move within every joint's velocity and acceleration limit (x1.25)."""
    limits = {j.name: j for j in robot.joints}
    t = 0.5
    for name, q0 in start.items():
        dq = abs(end[name] - q0)
        j = limits[name]
        # peak velocity 1.875 dq/T, peak acceleration 5.774 dq/T^2 for the quintic 10s^3-15s^4+6s^5
        t = max(t, 1.875 * dq / j.max_velocity, float(np.sqrt(5.774 * dq / j.max_acceleration)))
    return 1.25 * t


def min_jerk_trajectory(start: dict[str, float], end: dict[str, float], duration: float, n: int = 6) -> Trajectory:
    """A straight joint-space minimum-jerk move sampled at n+1 points, with exact velocities and accelerations.

    Point 0 is at time 0 (the start pose, at rest): start it where the robot is.
    """
    joints = tuple(start)
    q0, q1 = _vec(joints, start), _vec(joints, end)
    dq = q1 - q0
    points = []
    for i in range(n + 1):
        t = duration * i / n
        s = t / duration
        p = 10 * s**3 - 15 * s**4 + 6 * s**5
        dp = (30 * s**2 - 60 * s**3 + 30 * s**4) / duration
        ddp = (60 * s - 180 * s**2 + 120 * s**3) / duration**2
        points.append(TrajectoryPoint(t, q0 + dq * p, dq * dp, dq * ddp))
    return Trajectory(joints, points)


def descend(pose: dict[str, float], duration: float) -> Trajectory:
    """Positions only, one point: a quintic from the current desired state to rest at ``pose``."""
    joints = tuple(pose)
    return Trajectory(joints, [TrajectoryPoint(duration, _vec(joints, pose))])


def approach(above: dict[str, float], at: dict[str, float], duration: float) -> Trajectory:
    """Positions and velocities (cubic Hermite): slow down through a pre-grasp point, stop at ``at``."""
    joints = tuple(above)
    q_above, q_at = _vec(joints, above), _vec(joints, at)
    pre = q_above + 0.8 * (q_at - q_above)
    v_pre = 0.5 * (q_at - q_above) / duration  # still creeping down at the pre-grasp point
    zero = np.zeros(len(joints))
    return Trajectory(
        joints,
        [
            TrajectoryPoint(0.0, q_above, zero),
            TrajectoryPoint(0.7 * duration, pre, v_pre),
            TrajectoryPoint(duration, q_at, zero),
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
    state = await robot.read()
    arm = await run_async(layout_steps(robot.kinematics, np.array(state.position), angle=SPREAD, drop=DROP))
    home, above_pick, at_pick = arm.home, arm.left, arm.left_low
    above_place, at_place = arm.right, arm.right_low
    tight = Tolerances(path=0.1, goal=0.02, goal_time=1.0)
    clock = robot.clock
    print(f"pick and place on {robot.name} ({robot.backend}) with {arm.link!r} ({len(arm.joints)} joints)")

    t = clock.now()
    report("home (move_to)", await robot.move_to(home), t)
    t = clock.now()
    report("above pick (move_to)", await robot.move_to(above_pick, duration=1.5), t)
    t = clock.now()
    report("approach pick", await robot.follow(approach(above_pick, at_pick, 1.0), tight), t)
    await clock.sleep(GRIP_TIME)  # grasp
    print(f"  {'grasp':<22s} closed at t={clock.now():6.3f} s")
    t = clock.now()
    report("lift", await robot.follow(descend(above_pick, 0.8), tight), t)
    t = clock.now()
    duration = transfer_time(robot, above_pick, above_place)
    report("transfer (min-jerk)", await robot.follow(min_jerk_trajectory(above_pick, above_place, duration), tight), t)
    t = clock.now()
    report("descend to place", await robot.follow(descend(at_place, 0.8), tight), t)
    await clock.sleep(GRIP_TIME)  # release
    print(f"  {'release':<22s} opened at t={clock.now():6.3f} s")
    t = clock.now()
    report("retreat", await robot.follow(descend(above_place, 0.8), tight), t)
    t = clock.now()
    report("home (move_to)", await robot.move_to(home), t)
    print(f"pick and place done at t={clock.now():.3f} s")
