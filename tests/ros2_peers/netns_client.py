"""The remote agent of ``tests/test_ros2_netns.py``: plain cyclonedds against a served robot's topics.

Run inside its own network namespace: ``python netns_client.py DOMAIN NAMESPACE OWN_ADDR SERVER_ADDR LEASE``.
It talks on one line per step (JSON) on stdout and waits for the test on stdin around the
partition. It uses only the face's ROS interface: joint_states, diagnostics, the JTC topic,
the ``reset``/``enable`` services (rmw_cyclonedds request format) and a lease (heartbeats).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import sys
import time
from typing import Any

DOMAIN, NAMESPACE, OWN, SERVER, LEASE = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4], float(sys.argv[5])

from agentsdk.ros2.dds import network_config  # noqa: E402 -- the config must be set before the first participant

os.environ["CYCLONEDDS_URI"] = network_config(int(DOMAIN), OWN, [SERVER])

from agentsdk.ros2.dds import QOS_SERVICE, DdsNode, service_wire_type, unwrap  # noqa: E402
from agentsdk.ros2.lease import Heartbeat  # noqa: E402
from agentsdk.ros2.msgs import (  # noqa: E402
    DiagnosticArray,
    Duration,
    Header,
    JointState,
    JointTrajectory,
    JointTrajectoryPoint,
    RequestHeader,
    Trigger_Request,
    Trigger_Response,
)


def say(**what: Any) -> None:
    sys.stdout.write(json.dumps(what) + "\n")
    sys.stdout.flush()


class Client:
    def __init__(self) -> None:
        self.node = DdsNode(int(DOMAIN), NAMESPACE, asyncio.get_running_loop())
        self.states: list[JointState] = []
        self.diag: dict[str, str] = {}
        self.replies: dict[int, Trigger_Response] = {}
        self.seq = itertools.count(1)
        node = self.node
        node.subscribe("joint_states", JointState, self.states.append)
        node.subscribe("diagnostics", DiagnosticArray, self._on_diag)
        self.cmd = node.writer("joint_trajectory_controller/joint_trajectory", JointTrajectory)
        self.services: dict[str, Any] = {}
        for srv in ("reset", "enable"):
            self.services[srv] = node.writer(f"{srv}Request", service_wire_type(Trigger_Request), QOS_SERVICE,
                                             prefix="rq/")
            node.subscribe(f"{srv}Reply", service_wire_type(Trigger_Response), self._on_reply, QOS_SERVICE,
                           prefix="rr/")
        self.heartbeat = Heartbeat(node, LEASE, client_id="netns-agent")
        self.sent = 0
        node.start()

    def _on_diag(self, msg: DiagnosticArray) -> None:
        if msg.status:
            self.diag = {kv.key: kv.value for kv in msg.status[0].values}

    def _on_reply(self, sample: Any) -> None:
        header, body = unwrap(Trigger_Response, sample)
        self.replies[header.seq] = body

    async def call(self, srv: str) -> Trigger_Response:
        seq = next(self.seq)
        request = service_wire_type(Trigger_Request)(request_header=RequestHeader(0x5EED, seq),
                                                     structure_needs_at_least_one_member=0)
        for _ in range(100):  # a service request may be sent before its reader matched: repeat until answered
            self.services[srv].write(request)
            for _ in range(20):
                if seq in self.replies:
                    return self.replies[seq]
                await asyncio.sleep(0.05)
        raise TimeoutError(f"no reply from {srv}")

    def position(self) -> list[float]:
        return list(self.states[-1].position)

    def send(self, joint: int, target: float, seconds: float) -> None:
        q = self.position()
        q[joint] = target
        names = list(self.states[-1].name)
        self.sent += 1
        self.cmd.write(JointTrajectory(Header(), names, [
            JointTrajectoryPoint(positions=q, time_from_start=Duration.from_seconds(seconds))]))

    async def until(self, what: str, cond: Any, limit: float) -> None:
        deadline = time.monotonic() + limit
        while not cond():
            if time.monotonic() > deadline:
                raise TimeoutError(f"waiting for {what} ({limit} s); last joint_states {self.states[-1:]}, "
                                   f"diagnostics {self.diag}")
            await asyncio.sleep(0.02)

    async def reach(self, joint: int, target: float, seconds: float, limit: float) -> None:
        self.send(joint, target, seconds)
        await self.until(f"joint {joint} at {target}", lambda: abs(self.position()[joint] - target) < 1e-3
                         and max(abs(v) for v in self.states[-1].velocity) < 1e-3, limit)


async def main() -> None:
    c = Client()
    try:
        await c.until("joint_states (discovery)", lambda: len(c.states) > 5 and c.diag, 60)
        c.heartbeat.start()
        # 1. over the impaired link (delay + loss): remote trajectories succeed
        await c.reach(0, 0.5, 1.0, 30)
        await c.reach(0, -0.3, 1.0, 30)
        say(step="impaired", ok=True, position=c.position()[0])
        # 2. a long trajectory, then the test partitions the link
        c.send(0, 1.5, 6.0)
        await c.until("moving", lambda: abs(c.states[-1].velocity[0]) > 0.05, 20)
        say(step="partition", moving=True)
        line = await asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)
        healed = json.loads(line)
        # 3. after the partition: the robot stopped (e-stop latched by the dead-man), at rest
        n = len(c.states)
        await c.until("joint_states after the partition", lambda: len(c.states) > n + 20, 30)
        await c.until("diagnostics after the partition", lambda: c.diag.get("safety_state") == "ESTOP", 10)
        after = c.states[-1]
        say(step="after", safety_state=c.diag.get("safety_state"), deadman=c.diag.get("deadman"),
            tripped_at=float(c.diag.get("deadman_tripped_at") or "nan"), partition_at=healed["partition_at"],
            began=healed["began"],
            position=after.position[0], velocity=max(abs(v) for v in after.velocity))
        # 4. commands are refused until reset
        rejected = int(c.diag["trajectories_rejected"])
        held = c.position()[0]
        c.send(0, 0.0, 1.0)
        await c.until("the refusal", lambda: int(c.diag["trajectories_rejected"]) > rejected, 10)
        await asyncio.sleep(1.0)
        say(step="refused", moved=abs(c.position()[0] - held))
        # 5. a deliberate reset (and enable): commands are accepted again
        reset = await c.call("reset")
        enable = await c.call("enable")
        await c.reach(0, 0.0, 1.0, 30)
        say(step="reset", reset=reset.success, enable=enable.success, position=c.position()[0],
            safety_state=c.diag.get("safety_state"))
        # 6. every trajectory sent over the lossy link was applied or refused exactly once
        n = c.sent

        def counted() -> int:
            return int(c.diag["trajectories_accepted"]) + int(c.diag["trajectories_rejected"])

        await c.until("the diagnostics' counts", lambda: counted() >= n, 10)
        await asyncio.sleep(1.5)  # a duplicate would show up by now
        say(step="counts", sent=n, accepted=int(c.diag["trajectories_accepted"]),
            rejected=int(c.diag["trajectories_rejected"]))
    finally:
        await c.heartbeat.aclose()
        await asyncio.sleep(0.5)
        c.node.close()


if __name__ == "__main__":
    asyncio.run(main())
