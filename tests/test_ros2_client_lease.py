"""Issue 23: the ``ros2`` backend holds a dead-man lease with the agentsdk server it commands.

The served robot runs in this process (``expose``, so the test sees its safety state); the
client is another process (``connect("ros2")``), killed without a goodbye mid-motion.
"""

from __future__ import annotations

import asyncio
import os
import signal
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("cyclonedds")

from ros_domains import random_domain

import agentsdk
from agentsdk.ros2 import expose
from agentsdk.safety import SafetyState

pytestmark = [pytest.mark.timeout(180), pytest.mark.slow, pytest.mark.serial]
SAFETY = {"stall_timeout": 5.0}  # a loaded 2-core test machine

CLIENT = textwrap.dedent("""
    import asyncio, sys
    import agentsdk

    async def main() -> None:
        async with agentsdk.connect("ros2", robot="arm3", namespace="/lease", realtime=True, lease=0.5,
                                    stale_after=2.0, safety={"stall_timeout": 5.0}) as robot:
            assert robot.backend.interface == "agentsdk"
            move = asyncio.ensure_future(robot.move_to({"joint1": 1.5}, 8.0))
            await asyncio.sleep(1.0)
            print("moving", flush=True)
            if sys.argv[1] == "leave":
                move.cancel()
                try:
                    await move
                except asyncio.CancelledError:
                    pass
                return
            await move

    asyncio.run(main())
""")


async def _until(cond: object, limit: float) -> None:
    async with asyncio.timeout(limit):
        while not cond():  # type: ignore[operator]  # noqa: ASYNC110 -- state changes on the loop
            await asyncio.sleep(0.01)


async def _client(domain: int, how: str) -> asyncio.subprocess.Process:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    env["PYTHONPATH"] = os.pathsep.join([str(Path(agentsdk.__file__).parents[1]), env.get("PYTHONPATH", "")])
    return await asyncio.create_subprocess_exec(sys.executable, "-c", CLIENT, how, env=env,
                                                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL)


async def test_killing_the_ros2_client_stops_the_served_robot_and_leaving_does_not() -> None:
    domain = random_domain()
    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety=SAFETY) as robot:
        async with expose(robot, "/lease", domain_id=domain, lease=0.5) as face:
            deadman = face.deadman
            assert deadman is not None
            # a client that leaves on purpose releases its lease: the robot keeps running
            proc = await _client(domain, "leave")
            assert proc.stdout is not None
            async with asyncio.timeout(90):
                assert b"moving" in await proc.stdout.readline()
                assert await proc.wait() == 0
            await asyncio.sleep(1.5)
            assert deadman.trips == 0 and robot.safety.state is SafetyState.OK
            # a client killed mid-motion (no release): its heartbeats stop, the robot stops (category 1)
            proc = await _client(domain, "kill")
            assert proc.stdout is not None
            try:
                async with asyncio.timeout(90):
                    assert b"moving" in await proc.stdout.readline()
                assert len(deadman.table.bound) == 1  # its commands are bound to its lease
                start = robot.latest_state().position[0]
                proc.send_signal(signal.SIGKILL)
                await proc.wait()
                await _until(lambda: robot.safety.state is SafetyState.ESTOP, 5)
                await robot.safety.wait_stopped()
            finally:
                if proc.returncode is None:
                    proc.kill()
                    await proc.wait()
            assert deadman.trips == 1 and "lapsed" in deadman.last_trip
            assert any(e.kind == "deadman" for e in robot.safety.events)
            assert max(abs(v) for v in robot.latest_state().velocity) < 1e-3  # at rest
            assert start < robot.latest_state().position[0] < 1.4  # it moved, and stopped short of the target
            # commands are refused until a deliberate reset
            await robot.reset()
            await robot.enable()
            assert robot.safety.state is SafetyState.OK
