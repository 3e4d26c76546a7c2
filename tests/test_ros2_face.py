"""The ROS 2 face in one process (no external toolchain): encoders, names, validation, lockstep time.

A second participant in the test process (``DdsNode``, loopback only, a random domain) plays the
ROS side. The interop with independent DDS implementations is ``tests/test_ros2_interop.py``.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from ros_domains import random_domain

import agentsdk
from agentsdk import InvalidValueError
from agentsdk.ros2 import expose
from agentsdk.ros2.dds import QOS_LATCHED, QOS_SENSOR, DdsNode, normalize_namespace, resolve_domain_id
from agentsdk.ros2.msgs import (
    Clock,
    DiagnosticArray,
    JointState,
    JointTrajectoryControllerState,
    ParticipantEntitiesInfo,
    String,
    TFMessage,
    Time,
)

pytestmark = pytest.mark.timeout(120)
SAFETY = {"stall_timeout": 5.0}


def test_namespaces_and_domain_ids(monkeypatch: pytest.MonkeyPatch) -> None:
    assert normalize_namespace("") == ""
    assert normalize_namespace("/") == ""
    assert normalize_namespace("arm1") == "/arm1"
    assert normalize_namespace("/robots/arm_1/") == "/robots/arm_1"
    for bad in ("1arm", "/a b", "/arm-1", "/ok/ä"):
        with pytest.raises(InvalidValueError, match="namespace"):
            normalize_namespace(bad)
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert resolve_domain_id(None) == 42
    assert resolve_domain_id(3) == 3
    monkeypatch.delenv("ROS_DOMAIN_ID")
    assert resolve_domain_id(None) == 0
    for bad_id in (-1, 233, 1.5, True):
        with pytest.raises(InvalidValueError):
            resolve_domain_id(bad_id)  # type: ignore[arg-type]


async def test_rates_are_checked() -> None:
    async with agentsdk.connect("mock", robot="arm3") as robot:
        for kwargs in ({"rate": 0.0}, {"rate": float("nan")}, {"rate": 10_000.0}, {"tf_rate": -1.0}):
            with pytest.raises(InvalidValueError):
                expose(robot, **kwargs)  # type: ignore[arg-type]


async def test_fixed_layout_encoders_equal_the_messages() -> None:
    """tf and controller_state bytes are the messages' own serialisation, for any robot shape."""
    async with agentsdk.connect("mock", robot="humanoid") as robot:
        face = expose(robot)
        face._prepare_tf()
        face._prepare_controller_state()
        rng = np.random.default_rng(7)
        pairs = face._tf_pairs
        assert pairs
        q = rng.uniform(-0.4, 0.4, len(robot.joints))
        values = robot.kinematics.relative_transforms(pairs, list(q)).ravel()
        data = bytes(face._tf_layout.encode(values, 12.25))  # type: ignore[union-attr]
        msg = TFMessage.deserialize(data)
        poses = robot.kinematics.link_poses(list(q))
        assert [(t.header.frame_id, t.child_frame_id) for t in msg.transforms] == pairs
        for t, (parent, child) in zip(msg.transforms, pairs, strict=True):
            assert t.header.stamp == Time(12, 250_000_000)
            rel = poses.relative(child, parent)
            np.testing.assert_allclose([t.transform.translation.x, t.transform.translation.y,
                                        t.transform.translation.z], rel.position, atol=1e-12)
            quat = np.array([t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
                             t.transform.rotation.w])
            assert abs(abs(float(quat @ rel.orientation)) - 1.0) < 1e-12
        assert data == msg.serialize() + b"\0" * (-len(msg.serialize()) % 4)
        n = len(robot.joints)
        cs_values = rng.normal(size=12 * n)
        cs = JointTrajectoryControllerState.deserialize(
            bytes(face._cs_layout.encode(cs_values, 3.5)))
        assert cs.joint_names == list(robot.joint_names)
        assert cs.reference.positions == list(cs_values[:n]) and cs.actual.velocities == list(cs_values[11 * n:])


class Peer:
    """The ROS side: a second participant in this process, subscribed to the face's topics."""

    def __init__(self, domain: int, namespace: str) -> None:
        self.domain, self.namespace = domain, namespace
        self.got: dict[str, list[Any]] = {}
        self.node: DdsNode | None = None

    async def __aenter__(self) -> Peer:
        loop = asyncio.get_running_loop()
        self.node = DdsNode(self.domain, self.namespace, loop)
        return self

    def subscribe(self, name: str, data_type: Any, qos: Any = None) -> None:
        assert self.node is not None
        box = self.got.setdefault(name, [])
        cb: Callable[[Any], None] = box.append
        if qos is None:
            self.node.subscribe(name, data_type, cb)
        else:
            self.node.subscribe(name, data_type, cb, qos)

    async def __aexit__(self, *exc: object) -> None:
        assert self.node is not None
        self.node.close()

    async def wait_for(self, name: str, count: int = 1, limit: float = 20.0) -> list[Any]:
        async with asyncio.timeout(limit):
            while len(self.got.get(name, ())) < count:  # noqa: ASYNC110 -- filled by the reader thread
                await asyncio.sleep(0.02)
        return self.got[name]


async def test_lockstep_robot_publishes_sim_time_clock_and_states() -> None:
    """A lockstep robot: stamps are robot time, clock carries it; diagnostics name the safety state."""
    domain = random_domain()
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot, Peer(domain, "/sim") as peer:
        peer.subscribe("joint_states", JointState)
        peer.subscribe("clock", Clock, QOS_SENSOR)
        peer.subscribe("robot_description", String, QOS_LATCHED)
        peer.subscribe("diagnostics", DiagnosticArray)
        assert peer.node is not None
        peer.node.start()
        async with expose(robot, "/sim", domain_id=domain, rate=250.0) as face:
            assert face.stamp_offset == 0.0
            await asyncio.sleep(1.0)  # discovery
            for _ in range(3):
                await robot.move_to({"joint1": 0.5})
                await robot.move_to({"joint1": -0.5})
                await asyncio.sleep(0.3)  # wall time: a lockstep robot stands still meanwhile
            states = await peer.wait_for("joint_states", 5)
            clocks = await peer.wait_for("clock", 5)
            diag = await peer.wait_for("diagnostics", 1)
            desc = await peer.wait_for("robot_description", 1)
            now = robot.clock.now()
        stamps = [s.header.stamp.sec + s.header.stamp.nanosec * 1e-9 for s in states]
        assert stamps == sorted(stamps) and 0.0 < stamps[-1] <= now + 1e-9
        ticks = np.array(stamps) / robot.control_period
        np.testing.assert_allclose(ticks, np.round(ticks), atol=1e-6)  # robot time, tick by tick
        assert [c.clock.to_seconds() for c in clocks] == sorted(c.clock.to_seconds() for c in clocks)
        assert any(s.position[0] > 0.1 for s in states) and any(s.position[0] < -0.1 for s in states)
        status = diag[-1].status[0]
        assert {kv.key: kv.value for kv in status.values}["safety_state"] in ("OK", "HOLD")
        assert status.level == 0
        assert desc[0].data == robot.description.urdf_xml


async def test_close_is_idempotent_and_robot_stays_usable() -> None:
    domain = random_domain()
    async with agentsdk.connect("mock", robot="arm3") as robot:
        face = expose(robot, "/x", domain_id=domain)
        await face.start()
        await face.aclose()
        await face.aclose()
        result = await robot.move_to({"joint1": 0.2})
        assert result.ok



async def test_ros_discovery_info_names_the_node_and_its_endpoints() -> None:
    """What ``ros2 node list`` reads: the node's name and namespace, its readers' and writers' ids."""
    domain = random_domain()
    async with agentsdk.connect("mock", robot="arm3") as robot, Peer(domain, "") as peer:
        assert peer.node is not None
        got: list[ParticipantEntitiesInfo] = []
        peer.node.subscribe("ros_discovery_info", ParticipantEntitiesInfo, got.append, QOS_LATCHED, prefix="")
        peer.node.start()
        async with expose(robot, "/arm7", domain_id=domain) as face:
            async with asyncio.timeout(20):
                while not any(i.node_entities_info_seq for i in got):  # noqa: ASYNC110 -- filled by the reader thread
                    await asyncio.sleep(0.02)
            info = next(i for i in got if i.node_entities_info_seq)
            node = info.node_entities_info_seq[0]
            assert (node.node_namespace, node.node_name) == ("/arm7", face.node_name) == ("/arm7", "agentsdk_arm3")
            # readers: the JTC topic, the lease's heartbeat and release, the ros2 backend's command stream and
            # 6 service request readers; writers: 12 topics and 6 service reply writers
            assert len(node.reader_gid_seq) == 10 and len(node.writer_gid_seq) >= 15
            assert all(bytes(g.data)[:12] == bytes(info.gid.data)[:12] for g in node.writer_gid_seq)


async def test_state_machine_transitions_are_published_live() -> None:
    """Issue 26's introspection on the ROS 2 face: every history record of this robot's machines."""
    import json

    from agentsdk.statemachine import State, StateContext, StateMachine

    class Reach(StateMachine):
        idle = State(initial=True)
        reach = State()
        done = State(final=True)
        go = idle.to(reach)
        arrived = reach.to(done)

        async def on_idle(self, ctx: StateContext) -> str:
            return "go"

        async def on_reach(self, ctx: StateContext) -> str:
            await ctx.robot.move_to({"joint1": 0.3})
            return "arrived"

    domain = random_domain()
    async with agentsdk.connect("mock", robot="arm3") as robot, Peer(domain, "/sm") as peer:
        peer.subscribe("behavior/transitions", String)
        assert peer.node is not None
        peer.node.start()
        async with expose(robot, "/sm", domain_id=domain):
            await asyncio.sleep(1.0)  # discovery
            other = await agentsdk.connect("mock", robot="arm3")  # another robot's machine is not published
            try:
                assert await Reach(other).run() == "done"
            finally:
                await other.close()
            assert await Reach(robot).run() == "done"
            got = await peer.wait_for("behavior/transitions", 3)
            await asyncio.sleep(0.3)
        records = [json.loads(m.data) for m in peer.got["behavior/transitions"]]
    assert [(r["source"], r["target"], r["event"]) for r in records] == [
        (None, "idle", None), ("idle", "reach", "go"), ("reach", "done", "arrived")
    ], got
    assert {r["machine"] for r in records} == {"Reach"}
    assert records[-1]["configuration"] == "Reach/done" and records[-1]["duration"] > 0
