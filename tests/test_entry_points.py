"""A third-party backend, installed as a distribution with an ``agentsdk.backends`` entry point (issue 11).

The distribution is laid out on disk the way pip installs one (``*.dist-info`` with
``entry_points.txt``) in a temporary directory put on ``sys.path``: ``importlib.metadata``
finds it exactly as it finds an installed package, and ``connect()`` loads the backend by name.
"""

from __future__ import annotations

import shutil
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

import agentsdk
from agentsdk.registry import available_backends

HERE = Path(__file__).resolve().parent


@pytest.fixture
def third_party(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    shutil.copy(HERE / "tiny_backend.py", tmp_path / "acme_tiny_backend.py")
    dist = tmp_path / "acme_tiny-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-tiny\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[agentsdk.backends]\nacme = acme_tiny_backend:TinyController\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "acme"
    sys.modules.pop("acme_tiny_backend", None)


async def test_an_entry_point_backend_is_listed_and_connects(third_party: str) -> None:
    assert third_party in available_backends()
    async with agentsdk.connect(third_party, robot="arm3") as robot:
        assert robot.backend.name == "tiny"  # the class's own name; the entry point's name selects it
        await robot.move_to({"joint1": 0.2}, duration=0.5)
        assert abs((await robot.read()).positions()["joint1"] - 0.2) < 0.01


@pytest.fixture
def broken_plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """A third-party backend whose import raises RuntimeError (not ImportError)."""
    (tmp_path / "acme_broken_backend.py").write_text("raise RuntimeError('firmware blob missing')\n")
    dist = tmp_path / "acme_broken-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-broken\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[agentsdk.backends]\nbroken = acme_broken_backend:Broken\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "broken"
    sys.modules.pop("acme_broken_backend", None)


async def test_a_plugin_that_raises_at_import_is_named_and_the_others_still_load(broken_plugin: str) -> None:
    assert broken_plugin in available_backends()
    with pytest.raises(agentsdk.BackendUnavailableError, match=r"'broken'.*RuntimeError: firmware blob missing"):
        await agentsdk.connect(broken_plugin, robot="arm3")
    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        await robot.move_to({"joint1": 0.1})


def test_check_reports_a_broken_plugin(broken_plugin: str) -> None:
    from agentsdk.check import check_robot

    report = check_robot("arm3", backends=["mujoco"])
    assert any("'broken'" in p and "RuntimeError" in p for p in report.problems), report.problems
    assert any("mujoco" in line and "✓" in line for line in report.lines), report.lines


@pytest.mark.parametrize(("backend", "module", "distribution"),
                         [("pybullet", "pybullet", "pybullet"), ("can", "can", "python-can")])
def test_a_missing_optional_dependency_gives_the_install_command(backend: str, module: str, distribution: str) -> None:
    import subprocess

    code = (
        f"import sys; sys.modules[{module!r}] = None\n"  # as if the extra were not installed
        "import asyncio, agentsdk\n"
        "async def fails():\n"
        "    try:\n"
        f"        await agentsdk.connect({backend!r}, robot='arm3')\n"
        "    except agentsdk.BackendUnavailableError as exc:\n"
        "        print('ERR', exc)\n"
        "asyncio.run(fails())\n"
        "async def main():\n"
        "    async with agentsdk.connect('mujoco', robot='arm3') as robot:\n"
        "        await robot.clock.sleep(0.01)\n"
        "asyncio.run(main()); print('MUJOCO OK')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout
    assert f"ERR backend {backend!r} is not available: {distribution} is not installed" in out, out
    assert f"pip install 'agentsdk[{backend}]'" in out, out
    assert "MUJOCO OK" in out
