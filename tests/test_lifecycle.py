"""Lifecycle: the robot clock after close and faults (issue 10, item 10), connect off the event loop (item 9)."""

from __future__ import annotations

import asyncio
import math

import pytest

import agentsdk
from agentsdk import InvalidValueError, JointCommand, RobotClosedError, SafetyState

LOCKSTEP = ["mock", "mujoco", "pybullet"]

#: guards against a hang (the bug); never a timing assertion
HANG_GUARD = 30.0


@pytest.mark.parametrize("backend", LOCKSTEP)
async def test_clock_sleep_after_close_raises(backend: str) -> None:
    robot = await agentsdk.connect(backend, robot="arm3")
    await robot.close()
    async with asyncio.timeout(HANG_GUARD):
        with pytest.raises(RobotClosedError):
            await robot.clock.sleep(0.1)
        with pytest.raises(RobotClosedError):
            await robot.clock.sleep_until(robot.clock.now() + 1.0)
        with pytest.raises(RobotClosedError):
            async with robot.clock.timeout(1.0):
                pass


@pytest.mark.parametrize("realtime", [False, True])
async def test_pending_sleepers_are_woken_by_close(realtime: bool) -> None:
    robot = await agentsdk.connect("mock", robot="arm3", realtime=realtime)
    sleepers = [asyncio.ensure_future(robot.clock.sleep(dt)) for dt in (1000.0, math.inf)]
    await asyncio.sleep(0.01)
    await robot.close()
    async with asyncio.timeout(HANG_GUARD):
        for task in sleepers:
            with pytest.raises(RobotClosedError):
                await task


@pytest.mark.parametrize("realtime", [False, True])
async def test_nan_deadlines_raise(realtime: bool) -> None:
    async with agentsdk.connect("mock", robot="arm3", realtime=realtime) as robot:
        async with asyncio.timeout(HANG_GUARD):
            for bad in (math.nan, "soon", None):
                with pytest.raises(InvalidValueError):
                    await robot.clock.sleep_until(bad)  # type: ignore[arg-type]
                with pytest.raises(InvalidValueError):
                    await robot.clock.sleep(bad)  # type: ignore[arg-type]
            with pytest.raises(InvalidValueError):
                await robot.clock.sleep(-1.0)


async def test_infinite_sleep_waits_without_driving_lockstep_time() -> None:
    async with agentsdk.connect("mock", robot="arm3") as robot:
        forever = asyncio.ensure_future(robot.clock.sleep(math.inf))
        for _ in range(50):
            await asyncio.sleep(0)
        assert robot.ticks == 0 and not forever.done()
        await robot.clock.sleep(0.1)  # other sleepers still drive time
        assert not forever.done()
        forever.cancel()
        with pytest.raises(asyncio.CancelledError):
            await forever


async def test_sleep_during_a_fault_raises_and_works_after_recovery() -> None:
    async with agentsdk.connect("mock", robot="arm3") as robot:
        robot.controller.step_error = True  # the mock's fault knob
        with pytest.raises(agentsdk.BackendFault):
            await robot.clock.sleep(0.1)
        assert robot.safety.state is SafetyState.FAULT
        async with asyncio.timeout(HANG_GUARD):
            with pytest.raises(agentsdk.BackendFault, match="injected step error"):
                await robot.clock.sleep(0.1)  # the dead loop would never wake it
        await robot.reset()
        await robot.enable()
        t0 = robot.clock.now()
        await robot.clock.sleep(0.1)
        assert robot.clock.now() == pytest.approx(t0 + 0.1, abs=robot.control_period)
        await robot.command(JointCommand("position", {"joint1": 0.1}))
