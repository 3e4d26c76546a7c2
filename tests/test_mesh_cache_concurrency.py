"""The mesh cache is shared by every process of a user: writers of the same mesh must not trip each other up."""

from __future__ import annotations

import threading
from pathlib import Path

import mujoco
import pytest

from agentsdk.description import mjcf

MESH_XML = """
<mujoco>
  <asset>
    <mesh name="m" vertex="{vertices}"/>
  </asset>
  <worldbody><body><geom type="mesh" mesh="m"/></body></worldbody>
</mujoco>
"""


def _model() -> mujoco.MjModel:
    # a mesh big enough that writing it takes a while (the window another writer can fall into)
    vertices = " ".join(f"{(i * 0.37) % 1:.4f} {(i * 0.71) % 1:.4f} {(i * 0.13) % 1:.4f}" for i in range(3000))
    return mujoco.MjModel.from_xml_string(MESH_XML.format(vertices=vertices))


def test_concurrent_writers_of_one_mesh_all_get_the_whole_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    model = _model()
    expected: str | None = None
    for round_ in range(20):
        cache = tmp_path / f"cache{round_}"
        cache.mkdir()
        monkeypatch.setenv("AGENTSDK_CACHE_DIR", str(cache))
        barrier = threading.Barrier(8)
        paths: list[Path] = []
        errors: list[BaseException] = []

        def write(barrier: threading.Barrier = barrier, paths: list[Path] = paths,
                  errors: list[BaseException] = errors) -> None:
            barrier.wait()
            try:
                paths.append(mjcf._mesh_file(model, 0))
            except BaseException as exc:  # the point of the test: no writer fails
                errors.append(exc)

        threads = [threading.Thread(target=write) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert not errors, errors
        assert len(set(paths)) == 1
        text = paths[0].read_text()
        assert text.endswith("\n") and text.count("\nf ") > 0
        expected = expected or text
        assert text == expected
        assert sorted(p.name for p in cache.iterdir()) == [paths[0].name], "a temporary file was left behind"
