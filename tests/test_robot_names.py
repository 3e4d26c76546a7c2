"""Robots by name (issue 27): shipped robots, example-robot-data, Menagerie, ``agentsdk.robots`` entry points."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import agentsdk
from agentsdk.description import resolve_robot
from agentsdk.description.catalog import example_robot_data_dir, find_robot, installed_robots
from agentsdk.description.robot_yaml import default_robots_dir, list_robots
from agentsdk.errors import ConfigurationError

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
needs_erd = pytest.mark.skipif(example_robot_data_dir() is None, reason="example-robot-data is not installed")


def _cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    import os

    full = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    return subprocess.run([sys.executable, "-m", "agentsdk", *args], capture_output=True, text=True, timeout=120,
                          cwd=ROOT, env=full, check=False)


def test_shipped_names_come_first() -> None:
    entries = installed_robots()
    shipped = list_robots(default_robots_dir())
    assert {"arm3", "humanoid", "mit_leg"} <= set(shipped)
    assert [e.name for e in entries[: len(shipped)]] == shipped
    assert {e.source for e in entries[: len(shipped)]} == {"shipped"}
    assert len({e.name for e in entries}) == len(entries)  # unique names


@needs_erd
def test_example_robot_data_by_name() -> None:
    for name, file in (("ur5", "ur5_robot.urdf"), ("ur10", "ur10_robot.urdf"), ("panda", "panda.urdf"),
                       ("ur3", "ur3.urdf"), ("ur3_robot", "ur3_robot.urdf")):
        entry = find_robot(name)
        assert entry is not None and entry.source == "example-robot-data" and entry.path is not None
        assert entry.path.name == file
    _, desc = resolve_robot("ur5")
    assert len(desc.joints) == 6 and desc.joints[0].name == "shoulder_pan_joint"


@needs_erd
async def test_connect_by_installed_name() -> None:
    async with agentsdk.connect("mock", robot="panda") as robot:
        assert "panda_joint1" in robot.joint_names


def test_unknown_name_lists_the_known_ones() -> None:
    with pytest.raises(ConfigurationError) as info:
        resolve_robot("arm4")
    text = str(info.value)
    assert "did you mean 'arm3'?" in text and "arm3, humanoid" in text and "mit_leg" in text and "robots --all" in text
    if example_robot_data_dir() is not None:
        assert "ur5" in text


def test_menagerie_root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    robot_dir = tmp_path / "acme_arm"
    shutil.copytree(HERE / "fixtures" / "mjcf_arm", robot_dir)
    xml = next(p for p in robot_dir.glob("*.xml") if not p.stem.startswith("scene"))
    (robot_dir / "scene.xml").write_text(f'<mujoco><include file="{xml.name}"/></mujoco>')
    monkeypatch.setenv("MENAGERIE_ROOT", str(tmp_path))
    monkeypatch.setenv("ROBOT_DESCRIPTIONS_CACHE", str(tmp_path / "none"))
    entry = find_robot(xml.stem)
    assert entry is not None and entry.source == "menagerie" and entry.path == xml
    assert find_robot("scene") is None  # scenes are not robots
    _, desc = resolve_robot(xml.stem)
    assert desc.joints


def test_entry_point_robots(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    urdf = ROOT / "robots" / "arm3" / "robot.yaml"  # an entry point may name a robot.yaml too
    (tmp_path / "acme_robots.py").write_text(
        "from pathlib import Path\n"
        f"ARM = Path({str(urdf)!r})\n"
        "def broken():\n    raise RuntimeError('no such robot here')\n"
    )
    dist = tmp_path / "acme_robots-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-robots\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(
        "[agentsdk.robots]\nacme_arm = acme_robots:ARM\nacme_broken = acme_robots:broken\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        entry = find_robot("acme_arm")
        assert entry is not None and entry.source == "entry point" and entry.provider == "acme-robots"
        _, desc = resolve_robot("acme_arm")
        assert [j.name for j in desc.joints] == ["joint1", "joint2", "joint3"]
        with pytest.raises(ConfigurationError, match=r"acme_broken.*broken.*no such robot here"):
            resolve_robot("acme_broken")
        # one broken plugin does not hide the others
        assert find_robot("arm3") is not None and find_robot("acme_arm") is not None
    finally:
        sys.modules.pop("acme_robots", None)


def test_cli_robots_all_lists_sources() -> None:
    out = _cli("robots", "--all")
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].split()[:2] == ["arm3", "shipped"]
    if example_robot_data_dir() is not None:
        assert any(line.split()[:2] == ["ur5", "example-robot-data"] for line in lines)


def test_cli_unknown_robot_names_the_known_ones() -> None:
    out = _cli("describe", "ur6")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "unknown robot 'ur6'" in out.stderr and "arm3" in out.stderr
