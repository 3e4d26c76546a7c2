"""Every Python example in the README is executed (no stale docs)."""

from __future__ import annotations

import asyncio
import re
import textwrap
from pathlib import Path

import pytest

from agentsdk.cli import run_behavior

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_has_examples() -> None:
    assert len(BLOCKS) >= 5


@pytest.mark.parametrize("index", range(len(BLOCKS)))
@pytest.mark.parametrize("backend", ["mock", "mujoco"])
def test_readme_example_runs(index: int, backend: str, capsys: pytest.CaptureFixture[str]) -> None:
    source = textwrap.dedent(BLOCKS[index])
    if "asyncio.run(" in source and backend != "mujoco":
        pytest.skip("self-contained script: runs once, on the backend it names")
    namespace: dict[str, object] = {"__name__": f"readme_example_{index}"}
    exec(compile(source, f"README.md[python block {index}]", "exec"), namespace)
    main = namespace.get("main")
    if callable(main):
        asyncio.run(run_behavior(main, backend=backend, robot="arm3"))
