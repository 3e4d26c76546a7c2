"""A new user's first hour (issue 27): CLI output through subprocesses, as a user sees it."""

from __future__ import annotations

import errno
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _cli(*args: str, cwd: Path = ROOT, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("DISPLAY", None)
    return subprocess.run([sys.executable, "-m", "agentsdk", *args], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=timeout, check=False)


def relaxed_arm3(tmp_path: Path) -> str:
    """arm3 with a stall watchdog that a loaded test machine does not trip (wall-clock slack only)."""
    import yaml

    config = yaml.safe_load((ROOT / "robots" / "arm3" / "robot.yaml").read_text())
    config["description"] = str(ROOT / "robots" / "arm3" / config["description"])
    config["safety"] = {**config.get("safety", {}), "stall_timeout": 5.0}
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(config))
    return str(path)


def _last_line(text: str) -> str:
    lines = [line for line in text.splitlines() if line.strip()]
    return lines[-1] if lines else ""


def test_a_blocking_sleep_is_named_in_the_last_line(tmp_path: Path) -> None:
    script = tmp_path / "sleepy.py"
    script.write_text(
        "import time\n\n\nasync def main(robot):\n    await robot.clock.sleep(0.1)\n    time.sleep(1)\n"
        "    await robot.move_to({'joint1': 0.3})\n"
    )
    # realtime: the stall watchdog guards robots that move in real time (in lockstep a stalled loop
    # cannot advance simulated time, so it is off there unless `stall_in_lockstep: true`)
    out = _cli("run", str(script), "--backend", "mock", "--realtime")
    assert out.returncode != 0
    last = _last_line(out.stderr)
    assert last.startswith("error:"), out.stderr
    assert "stalled" in last and "sleepy.py:6" in last and "robot.clock.sleep" in last, last


def _has_socketcan() -> bool:
    try:
        socket.socket(socket.PF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (OSError, AttributeError):
        return False
    return True


@pytest.mark.skipif(_has_socketcan(), reason="this host has SocketCAN")
def test_emulate_can_without_can_points_to_vcan() -> None:
    out = _cli("emulate-can", "--robot", "mit_leg", "--channel", "vcan0")
    assert out.returncode == 1 and "Traceback" not in out.stderr
    assert "no SocketCAN" in out.stderr and "agentsdk vcan" in out.stderr


def test_can_open_hints() -> None:
    from agentsdk.backends.can.hints import bus_open_hint

    assert "agentsdk vcan" in bus_open_hint("socketcan", "vcan0", OSError(errno.EAFNOSUPPORT, "x"))
    assert "ip link add dev can1 type vcan" in bus_open_hint("socketcan", "can1", OSError(errno.ENODEV, "x"))
    assert bus_open_hint("virtual", "x", OSError(errno.EAFNOSUPPORT, "x")) == ""


def test_bench_prints_a_summary_not_json() -> None:
    out = _cli("bench", "--quick", "--only", "planning")
    assert out.returncode == 0, out.stderr
    assert not any(line.lstrip().startswith(("{", "[", '"')) for line in out.stdout.splitlines()), out.stdout
    assert "pybullet build time" not in out.stdout + out.stderr
    assert len(out.stdout.splitlines()) < 40, out.stdout
    assert "summary" in out.stdout


def test_pybullet_is_imported_quietly_by_the_video_renderer() -> None:
    code = ("import agentsdk.video, inspect; src = inspect.getsource(agentsdk.video._PybulletRenderer.__init__); "
            "from agentsdk.description import resolve_robot; _, d = resolve_robot('arm3'); "
            "agentsdk.video._PybulletRenderer(d, tuple(j.name for j in d.joints), 64, 48)")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120,
                         check=False)
    assert "pybullet build time" not in out.stdout + out.stderr


def test_recording_line_lists_its_messages(tmp_path: Path) -> None:
    out = _cli("run", "behaviors/wave.py", "--backend", "mock", "--robot", relaxed_arm3(tmp_path),
               "--record", str(tmp_path / "run.mcap"))
    assert out.returncode == 0, out.stderr
    line = next(x for x in out.stdout.splitlines() if x.startswith("recorded "))
    assert "()" not in line and re.search(r"\(/joint_states \d+, ", line), line


def test_check_start_pose_reads_naturally() -> None:
    out = _cli("check", "arm3", "--backend", "mujoco")
    assert "start pose (3 joints at 0):" in out.stdout, out.stdout


def test_describe_mentions_overrides_only_with_a_robot_yaml() -> None:
    bare = _cli("describe", str(ROOT / "tests" / "fixtures" / "mjcf_arm" / "arm.xml"))
    assert bare.returncode == 0 and "overrides" not in bare.stdout, bare.stdout + bare.stderr
    shipped = _cli("describe", "arm3")
    assert "(after robot.yaml overrides)" in shipped.stdout


def test_run_help_names_mjcf() -> None:
    out = _cli("run", "--help")
    assert "MJCF" in out.stdout and "--web" in out.stdout
