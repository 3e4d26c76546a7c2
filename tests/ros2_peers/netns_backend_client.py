"""The agent of ``tests/test_ros2_netns.py``'s backend test: ``connect("ros2")`` across the impaired link.

Run inside its own network namespace: ``python netns_backend_client.py DOMAIN NAMESPACE OWN_ADDR SERVER_ADDR
LEASE``. Drives the served robot with agentsdk's ``ros2`` backend (its trajectories sent as
FollowJointTrajectory goals, its lease held) and prints one JSON line with the results.
"""

from __future__ import annotations

import asyncio
import json
import os
import sys
from typing import Any

DOMAIN, NAMESPACE, OWN, SERVER, LEASE = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4], float(sys.argv[5])

from agentsdk.ros2.dds import network_config  # noqa: E402 -- the config must be set before the first participant

os.environ["CYCLONEDDS_URI"] = network_config(int(DOMAIN), OWN, [SERVER])

import agentsdk  # noqa: E402
from agentsdk import Trajectory, TrajectoryPoint  # noqa: E402


async def main() -> None:
    out: dict[str, Any] = {}
    async with agentsdk.connect("ros2", robot="arm3", namespace=NAMESPACE, domain_id=int(DOMAIN), realtime=True,
                                timeout=60.0, lease=LEASE, stale_after=LEASE,  # a loaded one-vCPU guest
                                safety={"stall_timeout": 5.0}) as robot:
        backend: Any = robot.backend
        out["goals_available"] = backend.goals_available
        first = await robot.move_to({"joint1": 0.4, "joint2": -0.2}, duration=1.0)
        motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(1.0, [0.0]), TrajectoryPoint(2.0, [-0.3])]))
        feedback = [fb.desired_positions[0] async for fb in motion.feedback(rate=20)]
        second = await motion
        await robot.clock.sleep(0.5)
        out.update(first=first.code.name, second=second.code.name, goals_sent=backend.goals_sent,
                   feedback=len(feedback), position=(await robot.read()).position.tolist(),
                   safety=robot.safety.state.name)
    print(json.dumps(out), flush=True)


asyncio.run(main())
