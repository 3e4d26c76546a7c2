"""The LIMIT tick's short paths (issue 28 item 3): what they skip must not change what the tick does."""

from __future__ import annotations

import math

import numpy as np
import pytest

import agentsdk
from agentsdk import JointCommand, Phase, ResultCode, Trajectory, TrajectoryPoint
from agentsdk.backend import SetpointView
from agentsdk.loop import Setpoint


async def test_a_motion_takes_over_a_joint_still_ramping_to_a_direct_command() -> None:
    """A direct position command far away ramps over many ticks; a trajectory started on that joint
    meanwhile owns it: the ramp ends there (``ramping &= ~owned``), so the motion's setpoints go out as
    planned, not the old goal clipped to the step window (which the limiter would report, aborting)."""
    async with agentsdk.connect("mock", robot="arm3") as robot:
        q = (await robot.read()).position
        await robot.command(JointCommand("position", {"joint1": float(q[0]) + 1.0}))
        await robot.clock.sleep(3 * robot.control_period)
        assert robot.safety._filter._ramping.tolist() == [True, False, False]  # still on its way
        result = await robot.follow(Trajectory(["joint1"], [TrajectoryPoint(0.5, [float(q[0]) - 0.2])]))
        assert result.code is ResultCode.SUCCESSFUL, result
        assert not [e for e in robot.safety.events if e.kind == "clip"]


async def test_a_ramp_ends_on_the_tick_it_reaches_its_goal() -> None:
    """A direct command inside the step window reaches its goal on the next tick, and its ramp ends there
    (the ``pos == target`` bytes short cut clears the flags ``ramping &= pos != target`` would); a ramp
    left on would keep rewriting the goal over later writers and keep block lockstep off."""
    async with agentsdk.connect("mock", robot="arm3") as robot:
        q = (await robot.read()).position
        ramping = robot.safety._filter._ramping
        await robot.command(JointCommand("position", (q + 1e-4).tolist()))
        assert ramping.all()
        await robot.clock.sleep(robot.control_period)
        assert not ramping.any()
        assert robot.setpoint.position.tolist() == (q + 1e-4).tolist()
        await robot.command(JointCommand("position", {"joint1": float(q[0]) + 0.5}))  # beyond the window
        await robot.clock.sleep(robot.control_period)
        assert ramping.tolist() == [True, False, False]


async def test_a_hold_still_clips_what_a_hook_writes_into_its_rows() -> None:
    """A hold skips the bounds clip of rows that hold the bytes the last clip left; a COMMAND hook that
    writes an effort beyond the limit (the position row unchanged) is still clipped that very tick."""
    async with agentsdk.connect("mock", robot="arm3") as robot:
        emax = robot.joints[0].max_effort
        seen: list[float] = []

        def push(t: float, st: object, sp: Setpoint) -> None:
            if robot.clock.ticks == 20:
                sp.effort[0] = 10.0 * emax

        def watch(t: float, st: object, sp: SetpointView) -> None:
            seen.append(float(sp.effort[0]))

        robot.add_tick_hook(Phase.COMMAND, push)
        robot.add_tick_hook(Phase.OBSERVE, watch)
        await robot.clock.sleep(40 * robot.control_period)
        assert max(seen) == emax and seen.count(emax) >= 20


async def test_the_mujoco_servo_law_is_skipped_only_when_nothing_it_reads_changed() -> None:
    """MuJoCo's write of a hold keeps ctrl when the setpoint rows and ctrl hold last write's bytes; a new
    gain, a new feed-forward or ctrl written by someone else (the block stepper, an e-stop) recompute it."""
    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        backend = robot._loop.backend
        sp = robot._loop._sp
        ctrl = backend.data.ctrl

        def law() -> list[float]:
            return (sp.kp * sp.position + sp.kd * sp.velocity + sp.effort).tolist()

        for change in ("kp", "effort", "ctrl", "kd"):
            backend.write(sp.view)
            backend.write(sp.view)  # the memo is set: a hold
            assert ctrl.tolist() == law()
            if change == "ctrl":
                ctrl[:] = 123.0
            else:
                getattr(sp, change)[0] += 1.0
            backend.write(sp.view)
            assert ctrl.tolist() == law(), change


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("where", [0, -1])
async def test_the_mujoco_step_finds_one_non_finite_acceleration(bad: float, where: int) -> None:
    """The divergence check after each step (a sum of the accelerations, the elements if it is not
    finite) finds a single non-finite element wherever it is; finite values that overflow the sum are
    no divergence."""
    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        backend = robot._loop.backend
        qacc = backend._qacc
        backend._qacc = np.array([1e308, 1e308, 1e308])  # (not MuJoCo's array: the step leaves it)
        await backend.step(robot.control_period)
        backend._qacc = fake = np.zeros(len(qacc))
        fake[where] = bad
        with pytest.raises(agentsdk.SimulationDiverged):
            await backend.step(robot.control_period)
        backend._qacc = qacc
