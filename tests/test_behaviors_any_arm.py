"""The shipped arm behaviors run on arms nobody wrote them for, by name, on both simulators (issue 27).

``patrol``, ``pick_place`` and ``square`` derive their poses from the robot's kinematics
(:mod:`agentsdk.arm`); here they run on arm3 (shipped), UR5 and Panda (example-robot-data,
by name) on MuJoCo and PyBullet, in lockstep, through the CLI.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import agentsdk.robot
from agentsdk.arm import arm_joints, end_effector, layout_steps, lowered, spread
from agentsdk.cli import main as cli_main
from agentsdk.description import apply_overrides, resolve_robot
from agentsdk.description.catalog import example_robot_data_dir
from agentsdk.errors import UnreachablePoseError
from agentsdk.kinematics import Kinematics, run_sync

BEHAVIORS_DIR = Path(__file__).resolve().parents[1] / "behaviors"
ROBOTS = ["arm3", "ur5", "panda"]
SAFETY = {"stall_timeout": 5.0}  # a loaded test machine can starve a lockstep run (see test_behaviors)
needs_erd = pytest.mark.skipif(example_robot_data_dir() is None, reason="example-robot-data is not installed")


@pytest.fixture(autouse=True)
def _slack(monkeypatch: pytest.MonkeyPatch) -> None:
    real = agentsdk.robot.connect

    def relaxed(backend: str = "mujoco", robot: Any = "arm3", **kw: Any) -> Any:
        kw.setdefault("safety", SAFETY)
        return real(backend, robot, **kw)

    monkeypatch.setattr(agentsdk.robot, "connect", relaxed)


def _kin(name: str) -> Kinematics:
    config, desc = resolve_robot(name)
    return Kinematics(desc, apply_overrides(desc, config))


EXPECT = {
    "patrol": re.compile(r"patrol ended in 'done' .* 0 fault\(s\)"),
    "pick_place": re.compile(r"pick and place done at t="),
    "square": re.compile(r"square done: max deviation from the sides ([0-9.e+-]+) mm, closing error ([0-9.e+-]+) mm"),
}


def check_report(behavior: str, out: str) -> None:
    """The behavior printed its success line (and the square was drawn)."""
    match = EXPECT[behavior].search(out)
    assert match, out
    if behavior == "square":
        assert float(match.group(1)) < 3.0 and float(match.group(2)) < 1.0


#: arm3 (the behaviors' own robot) on MuJoCo is tests/test_behaviors.py's run of each behavior, which checks the same
#: report (check_report): it is not run twice
RUNS = [(robot, backend) for robot in ROBOTS for backend in ("mujoco", "pybullet")
        if (robot, backend) != ("arm3", "mujoco")]


@needs_erd
@pytest.mark.slow
@pytest.mark.parametrize(("robot", "backend"), RUNS, ids=[f"{r}-{b}" for r, b in RUNS])
@pytest.mark.parametrize("behavior", sorted(EXPECT))
def test_behavior_runs_on_any_arm(behavior: str, robot: str, backend: str, capsys: pytest.CaptureFixture[str]) -> None:
    code = cli_main(["run", str(BEHAVIORS_DIR / f"{behavior}.py"), "--robot", robot, "--backend", backend, "--quiet"])
    out = capsys.readouterr()
    assert code == 0, out.err
    check_report(behavior, out.out)


@needs_erd
@pytest.mark.parametrize("robot", ROBOTS)
def test_layout_is_within_limits_and_lowered(robot: str) -> None:
    kin = _kin(robot)
    start = np.clip(np.zeros(len(kin.joint_names)), kin.lower, kin.upper)
    arm = run_sync(layout_steps(kin, start, angle=0.8, drop=0.05))
    assert arm.link == end_effector(kin) and arm.joints == arm_joints(kin, arm.link)
    for pose in (arm.home, arm.left, arm.right, arm.left_low, arm.right_low):
        assert set(pose) == set(arm.joints)
        for j, q in pose.items():
            i = kin.joint_names.index(j)
            assert kin.lower[i] <= q <= kin.upper[i]

    def z(pose: dict[str, float]) -> float:
        return float(kin.fk(arm.link, pose).position[2])

    assert z(arm.left) - z(arm.left_low) >= 0.005 and z(arm.right) - z(arm.right_low) >= 0.005
    first = arm.joints[0]
    assert arm.left[first] > arm.home[first] > arm.right[first]


def test_end_effector_names() -> None:
    assert end_effector(_kin("arm3")) == "ee_link"
    if example_robot_data_dir() is not None:
        assert end_effector(_kin("ur5")) == "tool0"
        assert end_effector(_kin("panda")) == "panda_hand_tcp"


def test_lowering_that_cannot_happen_says_so() -> None:
    kin = _kin("arm3")
    q = spread(kin, "ee_link", np.zeros(3), 0.0)
    with pytest.raises(UnreachablePoseError, match=r"can only be lowered by .* cm of the 500.0 cm"):
        lowered(kin, "ee_link", q, 5.0)


def test_a_robot_without_an_arm_says_so() -> None:
    kin = _kin("arm3")
    with pytest.raises(UnreachablePoseError, match="needs an arm"):
        arm_joints(kin, kin.root_link)
