"""Pick and place on arm3 as a state machine: parallel arm and gripper, history, userdata.

    agentsdk run behaviors/pick_place_sm.py                    # MuJoCo, lockstep
    agentsdk run behaviors/pick_place_sm.py --backend pybullet
    agentsdk graph behaviors/pick_place_sm.py                  # Mermaid diagram

Shows the state-machine constructs of the README on one task:

* a SMACH ``Concurrence``-style parallel state: the arm moves above the object while the
  gripper opens (two regions); an outcome map turns the regions' results into one event
  (``ready`` when both succeeded, ``missed`` when the arm did not arrive);
* history: an operator ``pause`` (sent during the transfer) leaves the whole cycle; ``resume``
  re-enters it where it was left (``history="deep"``), so the object is not picked twice;
* userdata: the object's name and the gripper state flow between the machines through
  ``remap=``, each step's target pose is an argument (``args=``), and the final state's
  ``data=`` hands the place pose to the enclosing machine;
* declared outcomes (``Literal`` return annotation, checked when the class is defined), entry
  and exit actions, and the fault state (a failed step lands there; the run exits 1).

arm3 has no gripper: the gripper region stands for one (it takes GRIP_TIME of robot time and
records its state in userdata); on a robot with a gripper joint it would command that joint.
"""

from __future__ import annotations

import asyncio
from typing import Literal

from agentsdk import Robot
from agentsdk.statemachine import State, StateContext, StateMachine

ROBOT = "arm3"

HOME = {"joint1": 0.0, "joint2": 0.3, "joint3": 0.0}
ABOVE_PICK = {"joint1": 0.8, "joint2": 0.5, "joint3": 0.4}
AT_PICK = {"joint1": 0.8, "joint2": 0.95, "joint3": 0.4}
ABOVE_PLACE = {"joint1": -0.8, "joint2": 0.5, "joint3": -0.4}
AT_PLACE = {"joint1": -0.8, "joint2": 0.95, "joint3": -0.4}
GRIP_TIME = 0.3  # s of robot time the gripper takes to open or close
PAUSE_AT = "transfer"  # the operator pauses the cycle PAUSE_AFTER s into this state...
PAUSE_AFTER = 0.4
PAUSE_FOR = 0.5  # ...for this many seconds of robot time


class ArmTo(StateMachine):
    """Move the arm to ``userdata["pose"]``; final ``there`` (with the pose as done data) or ``missed``."""

    moving = State(initial=True)
    there = State(final=True, data=("pose",))
    missed = State(final=True)

    arrived = moving.to(there)
    failed = moving.to(missed)

    async def on_moving(self, ctx: StateContext) -> Literal["arrived", "failed"]:
        result = await ctx.robot.move_to(ctx.userdata["pose"])
        return "arrived" if result.ok else "failed"


class Gripper(StateMachine):
    """Open or close (``userdata["command"]``); the state reached is written to ``userdata["gripper"]``."""

    actuating = State(initial=True)
    done = State(final=True)

    ok = actuating.to(done)

    async def on_actuating(self, ctx: StateContext) -> Literal["ok"]:
        await ctx.sleep(GRIP_TIME)
        return "ok"

    def on_exit_actuating(self, ctx: StateContext) -> None:
        ctx.userdata["gripper"] = ctx.userdata["command"]


def arm_to(pose: dict[str, float], arrived: str) -> State:
    """A state running ArmTo toward ``pose``; fires ``arrived`` or ``missed``."""
    return State(machine=ArmTo, args={"pose": pose}, done={"there": arrived, "missed": "missed"})


def gripper(command: str, done: str) -> State:
    return State(machine=Gripper, args={"command": command}, remap={"gripper": "gripper"}, done=done)


class Cycle(StateMachine):
    """One pick and place; its userdata ``object``/``gripper``/``placed_at`` are shared with the parent."""

    approach = State(
        initial=True,
        parallel=[ArmTo, Gripper],
        args={"pose": ABOVE_PICK, "command": "open"},
        remap={"gripper": "gripper"},
        outcome_map={"ready": {"ArmTo": "there", "Gripper": "done"}, "missed": {"ArmTo": "missed"}},
    )
    descend = arm_to(AT_PICK, "at_pick")
    grasp = gripper("closed", "grasped")
    lift = arm_to(ABOVE_PICK, "lifted")
    transfer = arm_to(ABOVE_PLACE, "over_place")
    lower = arm_to(AT_PLACE, "at_place")
    release = gripper("open", "released")
    retreat = arm_to(ABOVE_PLACE, "clear")
    placed = State(final=True, data=("object", "placed_at"))
    dropped = State(final=True)

    ready = approach.to(descend)
    done_approach = approach.to(dropped)  # default outcome: neither map entry matched
    at_pick = descend.to(grasp)
    grasped = grasp.to(lift)
    lifted = lift.to(transfer)
    over_place = transfer.to(lower)
    at_place = lower.to(release)
    released = release.to(retreat)
    clear = retreat.to(placed)
    missed = (
        approach.to(dropped)
        | descend.to(dropped)
        | lift.to(dropped)
        | transfer.to(dropped)
        | lower.to(dropped)
        | retreat.to(dropped)
    )

    def on_exit_grasp(self, ctx: StateContext) -> None:
        self.userdata["grasps"] = self.userdata.get("grasps", 0) + 1
        print(f"  t={ctx.clock.now():6.3f} s  grasped {self.userdata['object']!r} (gripper {self.userdata['gripper']})")

    def on_enter_placed(self, ctx: StateContext) -> None:
        self.userdata["placed_at"] = dict(ctx.data["pose"])  # the retreat's done data: where the arm ended


class PickPlace(StateMachine):
    home = State(initial=True)
    cycle = State(
        machine=Cycle,
        history="deep",
        remap={"object": "object", "gripper": "gripper", "grasps": "grasps"},
        done={"placed": "placed", "dropped": "dropped"},
    )
    paused = State()
    done = State(final=True)
    failed = State(final=True)
    fault = State(fault=True)

    homed = home.to(cycle)
    pause = cycle.to(paused)
    resume = paused.to(cycle)
    placed = cycle.to(done)
    dropped = cycle.to(failed)
    give_up = fault.to(failed)

    async def on_home(self, ctx: StateContext) -> Literal["homed"]:
        result = await ctx.robot.move_to(HOME)
        if not result.ok:
            raise RuntimeError(f"homing failed: {result.code.name} {result.message}")
        return "homed"

    def on_enter_paused(self, ctx: StateContext) -> None:
        print(f"  t={ctx.clock.now():6.3f} s  paused (the arm stopped and holds)")

    report: dict[str, object]

    def on_enter_done(self, ctx: StateContext) -> None:
        self.report = dict(ctx.data)  # the Cycle's done data

    async def on_fault(self, ctx: StateContext) -> Literal["give_up"]:
        print(f"  fault: {ctx.error!r}")
        return "give_up"


async def main(robot: Robot) -> None:
    machine = PickPlace(robot)
    machine.userdata["object"] = "cube"
    machine.userdata["gripper"] = "unknown"

    async def operator() -> None:
        await machine.wait_state(PAUSE_AT)
        await robot.clock.sleep(PAUSE_AFTER)  # mid-move: the pause stops the arm (decelerate and hold)
        print(f"  t={robot.clock.now():6.3f} s  -> pause ({machine.state_path})")
        machine.send("pause")
        await machine.wait_state("paused")
        await robot.clock.sleep(PAUSE_FOR)
        print(f"  t={robot.clock.now():6.3f} s  -> resume")
        machine.send("resume")

    print(f"pick and place (state machine) on {robot.name} ({robot.backend})")
    pauser = asyncio.create_task(operator())
    try:
        final = await machine.run()
    finally:
        pauser.cancel()
        await asyncio.gather(pauser, return_exceptions=True)
    grasps = machine.userdata.get("grasps", 0)
    resumed = [r for r in machine.history if r.note == "history"]
    print(f"ended in {final!r} at t={robot.clock.now():.3f} s; grasps {grasps}, resumed {len(resumed)} machine(s)")
    if final != "done":
        raise RuntimeError(f"pick and place failed: {machine.last_error!r}")
    if grasps != 1 or not resumed or "Cycle/transfer" not in resumed[0].configuration:
        raise RuntimeError(f"the cycle did not resume where it was paused: {grasps} grasps, {resumed}")
    report = machine.report
    print(f"placed {report['object']!r} at {report['placed_at']}; gripper {machine.userdata['gripper']}")
