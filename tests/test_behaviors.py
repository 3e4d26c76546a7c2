"""Every shipped behavior runs to completion through the CLI, in lockstep, on mock and MuJoCo.

The CLI runs its own event loop (``asyncio.run``), so these tests are synchronous.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from test_behaviors_any_arm import EXPECT, check_report

import agentsdk.robot
from agentsdk.cli import load_behavior
from agentsdk.cli import main as cli_main

BEHAVIORS_DIR = Path(__file__).resolve().parents[1] / "behaviors"
BEHAVIORS = sorted(p for p in BEHAVIORS_DIR.glob("*.py") if p.name != "__init__.py")
BACKENDS = ["mock", "mujoco"]
#: the event-loop stall watchdog measures wall time; on a loaded test machine a lockstep run can be
#: starved for its default 0.25 s without anything being wrong, so it gets more slack here
SAFETY = {"stall_timeout": 5.0}


@pytest.fixture(autouse=True)
def connections(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, Any]]:
    """Record (backend, robot) of every connect() the CLI makes."""
    seen: list[tuple[str, Any]] = []
    real = agentsdk.robot.connect

    def recording(backend: str = "mujoco", robot: Any = "arm3", **kw: Any) -> Any:
        seen.append((backend, robot))
        kw.setdefault("safety", SAFETY)
        return real(backend, robot, **kw)

    monkeypatch.setattr(agentsdk.robot, "connect", recording)
    return seen


def test_every_behavior_is_collected() -> None:
    names = {p.stem for p in BEHAVIORS}
    assert {"pick_place", "patrol", "track", "humanoid_wave"} <= names


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("path", BEHAVIORS, ids=lambda p: p.stem)
def test_behavior_runs(
    path: Path, backend: str, connections: list[tuple[str, Any]], capsys: pytest.CaptureFixture[str]
) -> None:
    code = cli_main(["run", str(path), "--backend", backend, "--quiet"])
    out = capsys.readouterr()
    assert code == 0, out.err
    expected_robot = getattr(load_behavior(str(path)), "ROBOT", "arm3")
    assert connections == [(backend, expected_robot)]
    if path.stem in EXPECT:  # the arm behaviors' report (tests/test_behaviors_any_arm.py runs them on other arms)
        check_report(path.stem, out.out)


def test_humanoid_wave_defaults_to_the_humanoid(connections: list[tuple[str, Any]]) -> None:
    assert load_behavior(str(BEHAVIORS_DIR / "humanoid_wave.py")).ROBOT == "humanoid"
    assert cli_main(["run", str(BEHAVIORS_DIR / "humanoid_wave.py"), "--backend", "mock", "--quiet"]) == 0
    assert connections == [("mock", "humanoid")]


def test_track_reports_timing(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["run", str(BEHAVIORS_DIR / "track.py"), "--backend", "mock", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "timing:" in out and "missed deadlines 0" in out and "2000 periods" in out


def test_patrol_fault_state_gives_up_on_a_stuck_joint(capsys: pytest.CaptureFixture[str]) -> None:
    path = str(BEHAVIORS_DIR / "patrol.py")
    assert cli_main(["run", path, "--backend", "mock", "-o", "frozen_joints=[joint2]", "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "fault #3" in captured.out and "'failed'" in captured.out
    assert "patrol failed" in captured.err


def test_patrol_graph(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["graph", str(BEHAVIORS_DIR / "patrol.py")]) == 0
    out = capsys.readouterr().out
    assert "stateDiagram-v2" in out and "moving --> fault : timeout" in out


@pytest.mark.parametrize("backend", ["mock", "mujoco", "pybullet"])
def test_pick_place_state_machine_resumes_where_it_was_paused(
    backend: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 26 acceptance 2: the Concurrence/history/userdata pick-and-place on both simulators."""
    assert cli_main(["run", str(BEHAVIORS_DIR / "pick_place_sm.py"), "--backend", backend, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "-> pause" in out and "-> resume" in out
    assert "ended in 'done'" in out and "grasps 1, resumed" in out and "placed 'cube'" in out
