"""A participant with some identity (or none) for ``tests/test_ros2_security.py``: what can it see and do?

``python identity_client.py DOMAIN CONFIG_FILE|- NAMESPACE SECONDS JOINT TARGET``: joins DOMAIN
with the Cyclone DDS configuration in CONFIG_FILE (``-``: loopback, no tag), then for SECONDS
watches the DDS graph (every topic any discovered participant publishes), counts
``joint_states`` and sends a trajectory (JTC topic) and a FollowJointTrajectory goal
moving joint index JOINT to TARGET. Prints one JSON object.
"""

from __future__ import annotations

import asyncio
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

DOMAIN, CONFIG, NAMESPACE = int(sys.argv[1]), sys.argv[2], sys.argv[3]
SECONDS, JOINT, TARGET = float(sys.argv[4]), int(sys.argv[5]), float(sys.argv[6])

from agentsdk.ros2.dds import loopback_config  # noqa: E402 -- the configuration precedes the first participant

os.environ["CYCLONEDDS_URI"] = loopback_config(DOMAIN) if CONFIG == "-" else Path(CONFIG).read_text()

from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication  # noqa: E402

from agentsdk.ros2.dds import QOS_SERVICE, DdsNode, service_wire_type, unwrap  # noqa: E402
from agentsdk.ros2.msgs import (  # noqa: E402
    UUID,
    Duration,
    FollowJointTrajectory_Goal,
    FollowJointTrajectory_SendGoal_Request,
    FollowJointTrajectory_SendGoal_Response,
    Header,
    JointState,
    JointTrajectory,
    JointTrajectoryPoint,
    RequestHeader,
)

NAMES = ["joint1", "joint2", "joint3"]


async def main() -> None:
    node = DdsNode(DOMAIN, NAMESPACE, asyncio.get_running_loop())
    states: list[JointState] = []
    replies: list[Any] = []
    node.subscribe("joint_states", JointState, states.append)
    action = "joint_trajectory_controller/follow_joint_trajectory/_action"
    goal_w = node.writer(f"{action}/send_goalRequest", service_wire_type(FollowJointTrajectory_SendGoal_Request),
                         QOS_SERVICE, prefix="rq/")
    node.subscribe(f"{action}/send_goalReply", service_wire_type(FollowJointTrajectory_SendGoal_Response),
                   lambda s: replies.append(unwrap(FollowJointTrajectory_SendGoal_Response, s)[1]), QOS_SERVICE,
                   prefix="rr/")
    cmd = node.writer("joint_trajectory_controller/joint_trajectory", JointTrajectory)
    graph = BuiltinDataReader(node.participant, BuiltinTopicDcpsPublication)
    node.start()
    q = [0.0, 0.0, 0.0]
    q[JOINT] = TARGET
    trajectory = JointTrajectory(Header(), NAMES, [JointTrajectoryPoint(positions=q,
                                                                       time_from_start=Duration.from_seconds(0.5))])
    goal = FollowJointTrajectory_Goal(trajectory=trajectory)
    topics: set[str] = set()
    deadline = time.monotonic() + SECONDS
    seq = 0
    while time.monotonic() < deadline and not replies:
        seq += 1
        cmd.write(trajectory)
        goal_w.write(service_wire_type(FollowJointTrajectory_SendGoal_Request)(
            request_header=RequestHeader(0xC11E, seq), goal_id=UUID(bytes([seq % 256]) * 16), goal=goal))
        for p in graph.take(N=200):
            name = getattr(p, "topic_name", None)
            if name and getattr(p, "participant_key", None) != node.participant.guid:
                topics.add(name)
        await asyncio.sleep(0.25)
    await asyncio.sleep(0.5)
    for p in graph.take(N=200):
        name = getattr(p, "topic_name", None)
        if name and getattr(p, "participant_key", None) != node.participant.guid:
            topics.add(name)
    node.close()
    sys.stdout.write(json.dumps({"topics": sorted(topics), "joint_states": len(states),
                                 "goal_replies": [bool(r.accepted) for r in replies]}) + "\n")


if __name__ == "__main__":
    asyncio.run(main())
