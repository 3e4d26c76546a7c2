"""Issue 23 item 3: the dead-man between hosts (``agentsdk.ros2.lease``), on loopback in one process.

The lease bookkeeping runs on simulated time; the face tests use a second participant (the
client) on a random domain. The same over a real (emulated) network: ``tests/test_ros2_netns.py``.
"""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("cyclonedds")

from ros_domains import random_domain

import agentsdk
from agentsdk import InvalidValueError
from agentsdk.ros2 import expose
from agentsdk.ros2.dds import DdsNode
from agentsdk.ros2.lease import Heartbeat, LeaseRequired, LeaseTable, heartbeat_qos
from agentsdk.ros2.msgs import Duration, Header, JointTrajectory, JointTrajectoryPoint
from agentsdk.safety import SafetyState

pytestmark = [pytest.mark.timeout(120), pytest.mark.serial]
SAFETY = {"stall_timeout": 5.0}  # a loaded 2-core test machine


def test_lease_table_binds_live_clients_and_reports_lapses() -> None:
    t = LeaseTable(0.5)
    t.beat("a", 0.0)
    t.beat("b", 0.1)
    assert t.live(0.55) == {"b"} and t.bind(0.2) == {"a", "b"}
    t.beat("a", 0.4)
    assert t.lapsed(0.65) == ["b"] and t.lapsed(0.95) == ["a", "b"]
    t.release("b")  # leaving on purpose never trips
    assert t.lapsed(0.95) == ["a"]
    t.beat("a", 0.9)
    t.lost("a")  # DDS liveliness lost: lapsed at once
    assert t.lapsed(0.9) == ["a"]
    t.clear()
    assert t.lapsed(5.0) == [] and t.bound == frozenset()
    t.beat("c", 6.0)
    assert t.lapsed(9.0) == []  # never bound: its lapse stops nothing


def test_lease_values_are_checked() -> None:
    for bad in (0, -1.0, float("nan"), float("inf"), True, "1"):
        with pytest.raises(InvalidValueError, match="lease"):
            LeaseTable(bad)  # type: ignore[arg-type]
        with pytest.raises(InvalidValueError, match="lease"):
            heartbeat_qos(bad)  # type: ignore[arg-type]


async def test_face_options_are_checked() -> None:
    async with agentsdk.connect("mock", robot="arm3") as robot:
        with pytest.raises(InvalidValueError, match="category"):
            expose(robot, lease_category=2)
        with pytest.raises(InvalidValueError, match="lease"):
            expose(robot, lease=0.0)
        with pytest.raises(InvalidValueError, match="require_lease"):
            expose(robot, lease=None, require_lease=True)
        assert expose(robot, lease=None).deadman is None


def _trajectory(robot: agentsdk.Robot, joint: str, target: float, seconds: float) -> JointTrajectory:
    names = list(robot.joint_names)
    q = [float(x) for x in robot.latest_state().position]
    q[names.index(joint)] = target
    point = JointTrajectoryPoint(positions=q, time_from_start=Duration.from_seconds(seconds))
    return JointTrajectory(Header(), names, [point])


async def _until(cond: object, limit: float) -> None:
    async with asyncio.timeout(limit):
        while not cond():  # type: ignore[operator]  # noqa: ASYNC110 -- state changes on the loop
            await asyncio.sleep(0.01)


async def test_a_silent_commanding_client_stops_the_robot_until_reset() -> None:
    domain = random_domain()
    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety=SAFETY) as robot:
        async with expose(robot, "/dm", domain_id=domain, lease=0.4) as face:
            client = DdsNode(domain, "/dm", asyncio.get_running_loop())
            try:
                cmd = client.writer("joint_trajectory_controller/joint_trajectory", JointTrajectory)
                beat = Heartbeat(client, lease=0.4, client_id="agent-1")
                client.start()
                beat.start()
                deadman = face.deadman
                assert deadman is not None
                await _until(lambda: "agent-1" in deadman.table.live(deadman._clock()), 20)
                cmd.write(_trajectory(robot, "joint1", 1.0, 4.0))
                await _until(lambda: robot.busy, 20)
                assert deadman.table.bound == {"agent-1"}
                # the client vanishes (no release): its heartbeats stop mid-trajectory
                assert beat._task is not None
                beat._task.cancel()
                await _until(lambda: robot.safety.state is SafetyState.ESTOP, 5)
                await robot.safety.wait_stopped()
                assert deadman.trips == 1 and "agent-1" in deadman.last_trip
                assert any(e.kind == "deadman" for e in robot.safety.events)
                assert max(abs(v) for v in robot.latest_state().velocity) < 1e-3  # category 1: at rest
                assert robot.latest_state().position[0] < 0.9  # stopped short of the target
                # commands are refused until a deliberate reset
                rejected = face.rejected_trajectories
                cmd.write(_trajectory(robot, "joint1", 0.0, 0.5))
                await _until(lambda: face.rejected_trajectories > rejected, 10)
                assert "EStop" in face.last_rejection
                await robot.reset()
                await robot.enable()
                beat2 = Heartbeat(client, lease=0.4, client_id="agent-2")
                async with beat2:
                    await _until(lambda: "agent-2" in deadman.table.live(deadman._clock()), 20)
                    cmd.write(_trajectory(robot, "joint1", 0.2, 0.5))
                    await _until(lambda: robot.busy, 20)
                    await _until(lambda: not robot.busy, 20)
                # released on purpose: no trip
                await asyncio.sleep(1.0)
                assert deadman.trips == 1 and robot.safety.state is SafetyState.OK
                assert abs(robot.latest_state().position[0] - 0.2) < 1e-3
                await beat.aclose()
            finally:
                client.close()


async def test_require_lease_refuses_commands_without_a_live_lease() -> None:
    domain = random_domain()
    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety=SAFETY) as robot:
        async with expose(robot, "/rq", domain_id=domain, lease=0.5, require_lease=True) as face:
            with pytest.raises(LeaseRequired, match="heartbeat"):
                face._start(_trajectory(robot, "joint1", 0.3, 0.5), face.tolerances)
            client = DdsNode(domain, "/rq", asyncio.get_running_loop())
            try:
                cmd = client.writer("joint_trajectory_controller/joint_trajectory", JointTrajectory)
                client.start()
                await asyncio.sleep(0.5)  # discovery
                cmd.write(_trajectory(robot, "joint1", 0.3, 0.5))
                await _until(lambda: face.rejected_trajectories == 1, 20)
                assert "LeaseRequired" in face.last_rejection and not robot.busy
                async with Heartbeat(client, lease=0.5):
                    deadman = face.deadman
                    assert deadman is not None
                    await _until(lambda: bool(deadman.table.live(deadman._clock())), 20)
                    cmd.write(_trajectory(robot, "joint1", 0.3, 0.5))
                    await _until(lambda: robot.busy, 20)
                    await _until(lambda: not robot.busy, 20)
                assert abs(robot.latest_state().position[0] - 0.3) < 1e-3
            finally:
                client.close()
