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
        assert robot.backend == "tiny"  # the class's own name; the entry point's name selects it
        await robot.move_to({"joint1": 0.2}, duration=0.5)
        assert abs((await robot.read()).positions()["joint1"] - 0.2) < 0.01
