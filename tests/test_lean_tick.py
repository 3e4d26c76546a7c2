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


async def test_a_pose_stream_still_clips_what_a_hook_writes_into_its_feed_forward_rows() -> None:
    """A behavior commanding every joint every tick ramps to each goal without the bounds clip of the rows
    while the velocity and effort rows hold the bytes the last clip left; a COMMAND hook that writes a
    velocity or an effort beyond its limit into them is still clipped that very tick."""
    async with agentsdk.connect("mock", robot="arm3") as robot:
        vmax, emax = robot.joints[1].max_velocity, robot.joints[2].max_effort
        q = (await robot.read()).position
        seen: list[tuple[int, float, float]] = []

        def push(t: float, st: object, sp: Setpoint) -> None:
            if robot.clock.ticks in (10, 11):
                sp.velocity[1] = 5.0 * vmax
            if robot.clock.ticks == 12:
                sp.effort[2] = -5.0 * emax

        def watch(t: float, st: object, sp: SetpointView) -> None:
            seen.append((robot.clock.ticks, float(sp.velocity[1]), float(sp.effort[2])))

        robot.add_tick_hook(Phase.COMMAND, push)
        robot.add_tick_hook(Phase.OBSERVE, watch)
        for k in range(20):
            await robot.command(JointCommand("position", (q + 1e-4 * k).tolist()))
            await robot.clock.sleep(robot.control_period)
        clipped = {tick: (v, e) for tick, v, e in seen if v or e}
        assert clipped == {11: (vmax, 0.0), 12: (vmax, 0.0), 13: (0.0, -emax)}
        assert robot.setpoint.position.tolist() == (q + 1e-4 * 19).tolist()


async def test_a_command_to_every_joint_puts_each_in_position_mode_with_torque_on() -> None:
    """A position command to every joint writes the mode and torque rows only when they say otherwise (a
    bytes compare first): a joint a velocity command or a hook left otherwise is set back."""
    async with agentsdk.connect("mock", robot="arm3") as robot:
        q = (await robot.read()).position
        sp = robot.setpoint

        def cut(t: float, st: object, sp: Setpoint) -> bool:
            sp.enabled[2] = False
            return False  # once

        await robot.command(JointCommand("velocity", {"joint2": 0.0}))
        robot.add_tick_hook(Phase.COMMAND, cut)
        await robot.clock.sleep(robot.control_period)
        assert sp.mode.tolist()[1] == int(agentsdk.backend.ModeCode.VELOCITY)
        assert sp.enabled.tolist() == [True, True, False]
        await robot.command(JointCommand("position", q.tolist()))
        assert sp.mode.tolist() == [int(agentsdk.backend.ModeCode.POSITION)] * 3
        assert sp.enabled.tolist() == [True, True, True]


async def test_a_clipped_command_s_values_are_its_own() -> None:
    """The clip of a command to every joint is computed in a scratch row: the values the command filter
    returns for a clipped command do not change when the next command is clipped."""
    async with agentsdk.connect("mock", robot="arm3") as robot:
        flt = robot.safety._filter
        idx = flt.full_index
        hi = np.array([j.upper for j in robot.joints])
        lo = np.array([j.lower for j in robot.joints])
        first = flt.limit_command("position", idx, hi + 1.0)
        assert first.tolist() == hi.tolist()
        assert flt.limit_command("position", idx, lo - 1.0).tolist() == lo.tolist()
        assert first.tolist() == hi.tolist()
        inside = (lo + hi) / 2
        assert flt.limit_command("position", idx, inside) is inside  # (nothing clipped: the values as they are)


@pytest.mark.parametrize("kd_bad", [None, math.inf, math.nan])
async def test_the_mujoco_servo_law_without_feed_forward_is_the_law_bit_for_bit(kd_bad: float | None) -> None:
    """Without feed-forward (velocity and effort rows all +0.0) and with finite damping gains, MuJoCo's write
    computes ``kp*q + 0.0`` in one ufunc: the same bits as ``(kp*q + kd*v) + effort``, signed zeros included;
    a non-finite kd (``kd*0`` is NaN) takes the whole law."""
    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        backend = robot._loop.backend
        sp = robot._loop._sp
        ctrl = backend.data.ctrl
        rng = np.random.default_rng(7)
        for k in range(40):
            sp.position[...] = rng.choice([0.0, -0.0, 0.3, -1.2, 1e-310], size=3)
            sp.kp[...] = rng.choice([0.0, -0.0, 40.0, 1e-300], size=3)
            sp.kd[...] = rng.choice([0.0, -0.0, 2.0, -3.0], size=3)
            if kd_bad is not None and k % 2:
                sp.kd[1] = kd_bad
            sp.velocity[...] = 0.0
            sp.effort[...] = 0.0 if k % 3 else -0.0  # (-0.0: the whole law)
            with np.errstate(invalid="ignore"):  # (inf * 0)
                backend.write(sp.view)
                law = (sp.kp * sp.position + sp.kd * sp.velocity) + sp.effort
            assert ctrl.tobytes() == law.tobytes(), (k, sp.block[:5].tolist(), ctrl.tolist(), law.tolist())


async def test_the_mujoco_servo_law_adds_the_inverse_dynamics_of_an_acceleration_from_rest() -> None:
    """Zero velocity and acceleration rows skip the inverse-dynamics term (it is zero); zero velocity with
    an acceleration (a motion's first tick from rest) does not."""
    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        backend = robot._loop.backend
        assert backend._inverse is not None
        sp = robot._loop._sp
        ctrl = backend.data.ctrl
        sp.velocity[...] = 0.0
        sp.effort[...] = 0.0
        sp.acceleration[...] = 0.0
        backend.write(sp.view)
        law = (sp.kp * sp.position + sp.kd * sp.velocity) + sp.effort
        assert ctrl.tolist() == law.tolist()
        sp.acceleration[0] = 2.0
        backend.write(sp.view)
        assert ctrl[0] != law[0]


async def test_a_restart_leaves_no_ramp() -> None:
    """The limiter's restart (start, enable) sets every goal to a measured position, maybe outside the bounds:
    it ends every ramp itself, so a ramping joint's goal is always a limited command (the LIMIT tick's short
    path relies on it)."""
    async with agentsdk.connect("mock", robot="arm3") as robot:
        flt = robot.safety._filter
        q = (await robot.read()).position
        await robot.command(JointCommand("position", (q + 0.5).tolist()))
        assert flt._ramping.all()
        flt.restart(q + 10.0)
        assert not flt._ramping.any()
