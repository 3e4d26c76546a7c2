"""Patrol: a state machine that moves an arm between waypoints until told to stop.

    agentsdk run behaviors/patrol.py                      # arm3 on MuJoCo, lockstep
    agentsdk run behaviors/patrol.py --backend mock
    agentsdk run behaviors/patrol.py --robot ur5          # any arm: panda, path/to/robot.yaml...
    agentsdk graph behaviors/patrol.py                    # Mermaid diagram

The park pose and the waypoints are derived from the robot (:mod:`agentsdk.arm`): a
well-conditioned configuration near its start, turned left and right about its first arm
joint with the end effector a little lower, and straight ahead. States start motions
(``robot.move_to``); leaving a state stops its motion (decelerate and hold) before the next
one starts. Shows:

* per-state timeouts: ``moving`` must arrive within MOVE_TIMEOUT (else -> fault);
  ``dwell`` *uses* its timeout to end (the body just waits);
* an external stop event: a task sends ``"stop"`` after STOP_AFTER seconds of
  robot time; whatever the machine is doing, it parks and finishes;
* a fault state: a failed motion or a timeout lands there; it retries from
  ``start`` (which parks the arm) at most MAX_FAULTS times, then gives up (final
  state ``failed``: the behavior exits with an error). Try it with a stuck joint:
  ``agentsdk run behaviors/patrol.py --backend mock -o "frozen_joints=[joint2]"``.
"""

from __future__ import annotations

import asyncio

import numpy as np

from agentsdk import Robot
from agentsdk.arm import layout_steps
from agentsdk.kinematics import run_async
from agentsdk.statemachine import State, StateContext, StateMachine

ROBOT = "arm3"

#: rad the first arm joint turns to each side, m the end effector goes down at the side waypoints
SPREAD = 0.9
DROP = 0.05
MOVE_TIMEOUT = 4.0  # s of robot time a move may take
DWELL = 0.4  # s spent at each waypoint
STOP_AFTER = 5.0  # s of robot time until the external "stop"
MAX_FAULTS = 2


class MotionFailed(RuntimeError):
    pass


class Patrol(StateMachine):
    start = State(initial=True, timeout=MOVE_TIMEOUT)
    moving = State(timeout=MOVE_TIMEOUT)
    dwell = State(timeout=DWELL)
    parking = State(timeout=MOVE_TIMEOUT)
    fault = State(fault=True)
    done = State(final=True)
    failed = State(final=True)

    ready = start.to(moving)
    arrived = moving.to(dwell)
    timeout = start.to(fault) | moving.to(fault) | dwell.to(moving) | parking.to(failed)
    stop = start.to(parking) | moving.to(parking) | dwell.to(parking)
    parked = parking.to(done)
    recover = fault.to(start, guard="can_retry") | fault.to(failed)

    def __init__(self, robot: Robot, park: dict[str, float], waypoints: list[dict[str, float]]) -> None:
        super().__init__(robot)  # robot.clock is the machine clock: timeouts are in robot time
        self.park = park
        self.waypoints = waypoints
        self.next_waypoint = 0
        self.laps = 0
        self.faults = 0

    async def _move(self, ctx: StateContext, pose: dict[str, float]) -> None:
        result = await ctx.robot.move_to(pose)
        if not result.ok:
            raise MotionFailed(f"{ctx.name}: {result.code.name} {result.message}")

    async def on_start(self, ctx: StateContext) -> str:
        await self._move(ctx, self.park)
        return "ready"

    async def on_moving(self, ctx: StateContext) -> str:
        await self._move(ctx, self.waypoints[self.next_waypoint])
        print(f"  t={ctx.clock.now():6.3f} s  at waypoint {self.next_waypoint}")
        self.next_waypoint = (self.next_waypoint + 1) % len(self.waypoints)
        if self.next_waypoint == 0:
            self.laps += 1
        return "arrived"

    async def on_dwell(self, ctx: StateContext) -> None:
        return None  # hold here until the state's timeout moves us on

    async def on_parking(self, ctx: StateContext) -> str:
        print(f"  t={ctx.clock.now():6.3f} s  parking ({ctx.event})")
        await self._move(ctx, self.park)
        return "parked"

    async def on_fault(self, ctx: StateContext) -> str:
        self.faults += 1
        print(f"  t={ctx.clock.now():6.3f} s  fault #{self.faults}: {ctx.error!r}")
        return "recover"

    def can_retry(self) -> bool:
        return self.faults <= MAX_FAULTS


async def main(robot: Robot) -> None:
    state = await robot.read()
    arm = await run_async(layout_steps(robot.kinematics, np.array(state.position), angle=SPREAD, drop=DROP))
    machine = Patrol(robot, arm.home, [arm.left_low, arm.home, arm.right_low])

    async def stop_later() -> None:
        await robot.clock.sleep(STOP_AFTER)
        print(f"  t={robot.clock.now():6.3f} s  -> stop")
        machine.send("stop")

    print(f"patrol on {robot.name} ({robot.backend}) with {arm.link!r} ({len(arm.joints)} joints); "
          f"stop after {STOP_AFTER:g} s")
    stopper = asyncio.create_task(stop_later())
    try:
        final = await machine.run()
    finally:
        stopper.cancel()
        await asyncio.gather(stopper, return_exceptions=True)
    print(
        f"patrol ended in {final!r} at t={robot.clock.now():.3f} s after {machine.laps} lap(s), "
        f"{machine.faults} fault(s)"
    )
    for rec in machine.history:
        print(f"    {rec.time:7.3f}  {rec.source} -> {rec.target}  [{rec.event}] {rec.note}")
    if final != "done":
        raise RuntimeError(f"patrol failed: {machine.last_error!r}")
