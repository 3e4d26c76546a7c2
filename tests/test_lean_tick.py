"""The LIMIT tick's short paths (issue 28 item 3): what they skip must not change what the tick does."""

from __future__ import annotations

import agentsdk
from agentsdk import JointCommand, ResultCode, Trajectory, TrajectoryPoint


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
