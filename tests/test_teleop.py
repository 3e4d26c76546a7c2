"""Leader-follower teleoperation (issue 27 acceptance 2): a mock leader streams a trajectory, MuJoCo follows."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import agentsdk
from agentsdk import Trajectory, TrajectoryPoint
from agentsdk.errors import ConfigurationError
from agentsdk.teleop import follow_leader, parse_endpoint

# runs alone, not beside another test worker: realtime timing (see the 'serial' marker in pyproject.toml)
pytestmark = pytest.mark.serial

SAFETY = {"stall_timeout": 5.0}


def _wave() -> Trajectory:
    pts = [TrajectoryPoint(1.0 + 0.5 * k, [0.4 * np.sin(k), 0.3 + 0.2 * np.cos(k), 0.3 * np.sin(k)])
           for k in range(8)]
    return Trajectory(["joint1", "joint2", "joint3"], pts)


async def test_mujoco_follows_a_mock_leader_and_stops_with_it() -> None:
    # a leader arm and its follower share the wall clock: both run in realtime
    async with (agentsdk.connect("mock", robot="arm3", safety=SAFETY, realtime=True) as leader,
                agentsdk.connect("mujoco", robot="arm3", safety=SAFETY, realtime=True) as follower):
        errors: list[float] = []

        async def stream() -> None:
            result = await leader.follow(_wave())
            assert result.ok, result
            await leader.clock.sleep(0.5)

        async def compare() -> None:
            while True:
                q_l = np.array(leader.latest_state().position)
                q_f = np.array(follower.latest_state().position)
                errors.append(float(np.max(np.abs(q_l - q_f))))
                await follower.clock.sleep(0.01)

        async with asyncio.TaskGroup() as tg:
            streamer = tg.create_task(stream())
            watcher = tg.create_task(compare())
            session = tg.create_task(follow_leader(leader, follower, duration=30.0))
            await streamer
            watcher.cancel()
            # the leader stops streaming (it is unplugged): the follower holds and the session ends
            leader_stop_at = follower.clock.now()
            await leader.close()
            report = await session
        assert report.ended == "leader stopped", report
        assert follower.clock.now() - leader_stop_at < 0.5
        assert report.commands > 100
        # tracking: the follower stays within 0.02 rad of the leader while it streams
        assert max(errors[10:]) < 0.02, max(errors)
        # and comes to rest where it was left
        await follower.clock.sleep(0.5)
        st = follower.latest_state()
        assert float(np.max(np.abs(st.velocity))) < 0.01


def test_endpoints_are_checked() -> None:
    assert parse_endpoint("mujoco:arm3", "leader") == ("mujoco", "arm3")
    assert parse_endpoint("mock:/a/b:c.urdf", "leader") == ("mock", "/a/b:c.urdf")
    with pytest.raises(ConfigurationError, match="BACKEND:ROBOT"):
        parse_endpoint("arm3", "follower")


def test_cli_teleop_with_a_scripted_leader(tmp_path: Path) -> None:
    import yaml

    root = Path(__file__).resolve().parents[1]
    config = yaml.safe_load((root / "robots" / "arm3" / "robot.yaml").read_text())
    config["description"] = str(root / "robots" / "arm3" / config["description"])
    config["safety"] = {"stall_timeout": 5.0}  # wall-clock slack for a loaded test machine
    robot = tmp_path / "robot.yaml"
    robot.write_text(yaml.safe_dump(config))
    out = subprocess.run(
        [sys.executable, "-m", "agentsdk", "teleop", "--leader", f"mock:{robot}", "--follower", f"mujoco:{robot}",
         "--leader-behavior", str(root / "behaviors" / "wave.py")],
        capture_output=True, text=True, timeout=300, cwd=root, env={**os.environ, "PYTHONPATH": str(root)},
        check=False,
    )
    assert out.returncode == 0, out.stderr
    assert "teleop ended (leader stopped)" in out.stdout and "joint1->joint1" in out.stdout
    assert "Traceback" not in out.stderr
