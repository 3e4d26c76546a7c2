"""What a user sees from the CLI (issue 10, items 15-18): behavior loading, the real-time factor,
no PyBullet noise in the user's output, plain numbers in errors, the plotted target of a trajectory."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from agentsdk.backends.pybullet.quiet import filtered_native_output, is_noise

ROOT = Path(__file__).resolve().parents[1]


def run_cli(*args: str, cwd: Path = ROOT, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "agentsdk", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout)


# ------------------------------------------------------------------ 17. PyBullet's C-level prints
def test_pybullet_prints_nothing_of_its_own(tmp_path: Path) -> None:
    """Before: 'pybullet build time: ...' on every run, and b3Warning lines merged into the user's."""
    behavior = tmp_path / "talk.py"
    behavior.write_text(
        "async def main(robot):\n"
        "    print('first line of mine')\n"
        "    await robot.clock.sleep(0.05)\n"
        "    print('second line of mine')\n"
    )
    proc = run_cli("run", str(behavior), "--backend", "pybullet", "-q")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "first line of mine\nsecond line of mine\n"
    assert proc.stderr == ""


def test_the_filter_keeps_every_user_line_and_drops_pybullets(capfd: pytest.CaptureFixture[str]) -> None:
    # (written to the file descriptors, as a program's print does outside pytest's capture)
    def user_thread() -> None:  # the user's program printing while PyBullet loads
        os.write(1, b"user from a thread\n")

    with filtered_native_output():
        os.write(1, b"user before\n")
        os.write(1, b"pybullet build time: Jan 29 2025 23:17:20\n")
        os.write(2, b"b3Warning[examples/Importers/ImportURDFDemo/BulletUrdfImporter.cpp,126]:\n")
        os.write(2, b"No inertial data for link, using mass=1, localinertiadiagonal = 1,1,1\n")
        os.write(1, b"user start of a line, ")
        os.write(1, b"b3Printf: Removing link\n")
        os.write(1, b"and its end\n")
        t = threading.Thread(target=user_thread)
        t.start()
        t.join()
        os.write(2, b"user error line\n")
        os.write(2, b"no newline at the end")
    out, err = capfd.readouterr()
    assert out == "user before\nuser start of a line, and its end\nuser from a thread\n"
    assert err == "user error line\nno newline at the end"


@pytest.mark.parametrize(
    ("line", "noise"),
    [
        ("pybullet build time: Jan 29 2025 23:17:20", True),
        ("b3Warning[examples/SharedMemory/PhysicsServerCommandProcessor.cpp,2345]:", True),
        ("b3Printf: b3Warning[x.cpp,1]:", True),
        ("the robot moved", False),
        ("Warning: my own warning", False),
    ],
)
def test_noise_patterns(line: str, noise: bool) -> None:
    assert is_noise(line) is noise


# ------------------------------------------------------------------ 15. behavior loading
@pytest.mark.parametrize(
    ("source", "expected"),
    [
        ("async def main(robot)\n    pass\n", r"bad\.py:1:\d+: SyntaxError: "),
        ("import os\n\nraise RuntimeError('boom at import')\n", r"bad\.py:3: importing the behavior failed: "
                                                                r"RuntimeError: boom at import"),
        ("def main(robot):\n    return None\n", r"bad\.py:1: `main` must be an `async def main\(robot\)`"),
        ("async def main():\n    pass\n", r"bad\.py:1: `main` must take exactly one argument"),
        ("ROBOT = 'arm3'\n", r"bad\.py does not define `async def main\(robot\)`"),
    ],
    ids=["syntax", "import-fails", "not-async", "no-argument", "no-main"],
)
def test_a_bad_behavior_is_reported_in_one_line_when_it_loads(tmp_path: Path, source: str, expected: str) -> None:
    """Before: a syntax error printed a traceback; a non-async main failed after connecting with
    ``TypeError: a coroutine was expected`` (and the robot had been started for nothing)."""
    import re

    bad = tmp_path / "bad.py"
    bad.write_text(source)
    proc = run_cli("run", str(bad), "--backend", "mock", "-q")
    assert proc.returncode == 3, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert re.search(expected, lines[0]), lines[0]
    assert "Traceback" not in proc.stderr and proc.stdout == ""


def test_graph_reports_a_bad_behavior_the_same_way(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("x = (\n")
    proc = run_cli("graph", str(bad))
    assert proc.returncode == 3 and "SyntaxError" in proc.stderr and "Traceback" not in proc.stderr


def test_load_behavior_accepts_an_async_callable_object(tmp_path: Path) -> None:
    from agentsdk.cli import load_behavior

    ok = tmp_path / "ok.py"
    ok.write_text("class Main:\n    async def __call__(self, robot):\n        pass\n\nmain = Main()\n")
    assert callable(load_behavior(str(ok)).main)


# ------------------------------------------------------------------ 16. the real-time factor
async def test_real_time_factor_counts_the_behavior_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: the wall time started before connect (description load, simulator build: ~1 s),
    so a 40x run was shown as 0.4-8x. A fake wall clock makes the split exact."""
    import contextlib

    import agentsdk.cli as cli
    import agentsdk.robot as robot_mod

    wall = [1000.0]
    monkeypatch.setattr(cli.time, "perf_counter", lambda: wall[0])
    real_connect = robot_mod.connect

    @contextlib.asynccontextmanager
    async def slow_connect(*args, **kwargs):  # type: ignore[no-untyped-def]
        async with real_connect(*args, **kwargs) as bot:
            wall[0] += 50.0  # a slow description load / simulator build
            yield bot
            wall[0] += 30.0  # a slow stop and close
    monkeypatch.setattr(robot_mod, "connect", slow_connect)

    async def behavior(robot):  # type: ignore[no-untyped-def]
        await robot.clock.sleep(1.0)
        wall[0] += 0.25

    summary = await cli.run_behavior(behavior, backend="mock", robot="arm3")
    assert summary.wall_time == pytest.approx(0.25)
    assert summary.sim_time == pytest.approx(1.0, abs=0.011)
    assert summary.real_time_factor == pytest.approx(4.0, rel=0.02)


def test_printed_simulated_time_is_the_behaviors(tmp_path: Path) -> None:
    behavior = tmp_path / "nap.py"
    behavior.write_text("async def main(robot):\n    await robot.clock.sleep(0.5)\n")
    proc = run_cli("run", str(behavior), "--backend", "mock")
    assert proc.returncode == 0, proc.stderr
    assert "simulated time 0.50" in proc.stdout, proc.stdout


# ------------------------------------------------------------------ 14/17. plain errors
def test_move_to_with_a_huge_duration_is_one_plain_line(tmp_path: Path) -> None:
    """Before: ``behavior failed: ValueError: -101 is not a valid Result.``"""
    behavior = tmp_path / "slow.py"
    behavior.write_text("async def main(robot):\n    await robot.move_to({'joint1': 0.3}, duration=1e300)\n")
    proc = run_cli("run", str(behavior), "--backend", "mock", "-q")
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        "error: duration 1e+300 s is longer than 7600 s, the longest move ruckig times; "
        "split the motion or use a trajectory"
    ]


async def test_move_to_durations_up_to_ruckigs_ceiling_work_and_beyond_are_refused() -> None:
    import numpy as np

    import agentsdk
    from agentsdk.trajectory import MAX_PROFILE_DURATION, plan_point_to_point

    async with agentsdk.connect("mock", robot="arm3") as robot:
        joints = [robot.joints[0]]
        zero = np.zeros(1)
        traj = plan_point_to_point((zero, zero, zero), np.array([0.01]), joints, duration=MAX_PROFILE_DURATION)
        assert traj.duration == pytest.approx(MAX_PROFILE_DURATION)
        with pytest.raises(agentsdk.InvalidValueError, match="longer than 7600 s"):
            await robot.move_to({"joint1": 0.01}, duration=MAX_PROFILE_DURATION * 1.01)
        assert robot.safety.state is agentsdk.SafetyState.OK  # refused, nothing else happened
        await robot.move_to({"joint1": 0.01}, duration=0.5)


async def test_numpy_values_in_errors_are_plain_numbers() -> None:
    """Before: ``move_to: non-finite target in {'joint1': np.float64(nan)}``."""
    import numpy as np

    import agentsdk

    async with agentsdk.connect("mock", robot="arm3") as robot:
        with pytest.raises(agentsdk.InvalidValueError) as info:
            await robot.move_to({"joint1": np.float64(np.nan), "joint2": 0.0})
        assert str(info.value) == "move_to: non-finite target nan for joint 'joint1'"
        with pytest.raises(agentsdk.InvalidValueError) as info:
            await robot.command(agentsdk.JointCommand("position", {"joint2": np.float64(np.inf)}))
        assert "np." not in str(info.value) and "inf" in str(info.value)
