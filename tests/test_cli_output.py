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
