"""``agentsdk check`` and ``agentsdk describe`` as a user runs them: a subprocess, its output and exit status."""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
from pathlib import Path

import pytest

FIXTURES = Path(__file__).parent / "fixtures"


def corpus_root() -> Path:
    dist = importlib.metadata.distribution("example-robot-data")
    return Path(str(dist.locate_file("cmeel.prefix/share/example-robot-data/robots")))


def _agentsdk(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "agentsdk", *args], capture_output=True, text=True, timeout=300, check=False
    )


def test_check_a_shipped_robot() -> None:
    r = _agentsdk("check", "arm3")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "robot 'arm3' (URDF)" in out and "joint1 [revolute]" in out
    assert "repairs: none" in out
    assert "masses: 5.1 kg" in out
    assert "start pose (3 joints at 0):" in out and "joint1=0" in out
    assert "servo gains on mujoco (robot.yaml" in out and "joint2 p=800 d=10" in out
    assert "self-collision (auto):" in out and "left out, adjacent" in out
    assert "mujoco    ✓ loads, holds and moves (following error ≤ " in out
    assert "pybullet  ✓ loads, holds and moves (following error ≤ " in out
    assert out.rstrip().endswith("ok")


def test_check_a_corpus_robot_with_repairs() -> None:
    r = _agentsdk("check", str(corpus_root() / "allegro_hand_description" / "urdf" / "allegro_left_hand.urdf"))
    assert r.returncode == 0, r.stderr
    assert "repairs (4, so that every simulator can load it" in r.stdout
    assert "link 'link_11.0' (line 127): principal moments" in r.stdout and "MuJoCo balanceinertia" in r.stdout
    assert "mujoco    ✓" in r.stdout and "pybullet  ✓" in r.stdout
    strict = _agentsdk("check", "--strict", str(corpus_root() / "allegro_hand_description" / "urdf" /
                                                   "allegro_left_hand.urdf"))
    assert strict.returncode == 1
    errors = strict.stderr.strip().splitlines()
    assert len(errors) == 5 and all(line.startswith("error: ") for line in errors)
    assert "strict mode refuses the 4 repairs" in errors[0]


def test_check_an_mjcf_file() -> None:
    r = _agentsdk("check", str(FIXTURES / "mjcf_arm" / "scene.xml"))
    assert r.returncode == 0, r.stderr
    assert "robot 'mjcf_arm scene' (MJCF)" in r.stdout
    assert "joints from the model's home keyframe" in r.stdout and "shoulder_pitch=0.3" in r.stdout
    assert "self-collision (the model's own contact settings)" in r.stdout
    assert "mujoco    ✓ loads, holds and moves" in r.stdout


def test_check_a_broken_file_fails_with_one_line_per_problem(tmp_path: Path) -> None:
    broken = tmp_path / "broken.urdf"
    broken.write_text('<robot name="b">\n  <link name="base"/>\n  <joint name="j" type="revolute">\n'
                      '    <parent link="base"/><child link="missing"/>\n  </joint>\n</robot>\n')
    r = _agentsdk("check", str(broken))
    assert r.returncode == 1
    assert r.stdout == ""
    assert r.stderr.strip().splitlines() == [
        f"error: {broken}, line 4: joint 'j': child link 'missing' is not defined"
    ]


@pytest.mark.parametrize("robot", [str(FIXTURES / "mjcf_arm" / "scene.xml"), "humanoid"])
def test_describe_accepts_urdf_and_mjcf(robot: str) -> None:
    r = _agentsdk("describe", robot)
    assert r.returncode == 0, r.stderr
    assert "Successfully parsed" in r.stdout and "actuated joints" in r.stdout


def test_check_reports_a_joint_that_does_not_follow() -> None:
    """Issue 20.8: a robot whose joint does not follow its command (here a hold with gains far too low for
    its load) is never reported ✓: the check names the joint and the error against its window, and fails."""
    r = _agentsdk("check", str(FIXTURES / "following" / "weak.yaml"))
    assert r.returncode == 1
    for backend in ("mujoco", "pybullet"):
        line = next(ln for ln in r.stdout.splitlines() if ln.strip().startswith(backend + " "))
        assert "✗ loads, but does not follow: joint 'shoulder' is " in line, r.stdout
        assert "(window 0.5)" in line
        assert f"error: {backend}: does not follow its commands: joint 'shoulder'" in r.stderr
    # the same arm with model gains: both simulators follow, PyBullet too, which simulates the wrist motor's
    # rotor inertia (MJCF armature) its gains are sized with (before: the wrist ran away there)
    armature = _agentsdk("check", str(FIXTURES / "following" / "healthy.yaml"))
    assert armature.returncode == 0, armature.stdout + armature.stderr
    for backend in ("mujoco", "pybullet"):
        assert f"{backend:<9} ✓ loads, holds and moves (following error ≤ " in armature.stdout, armature.stdout
