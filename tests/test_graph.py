"""`agentsdk graph behaviors/patrol.py` prints the Mermaid diagram of the declared Patrol machine."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from agentsdk.cli import main as cli_main

PATROL = Path(__file__).resolve().parents[1] / "behaviors" / "patrol.py"

# The graph as declared in behaviors/patrol.py (source, target, event, guard)
DECLARED = {
    ("start", "moving", "ready", None),
    ("moving", "dwell", "arrived", None),
    ("start", "fault", "timeout", None),
    ("moving", "fault", "timeout", None),
    ("dwell", "moving", "timeout", None),
    ("parking", "failed", "timeout", None),
    ("start", "parking", "stop", None),
    ("moving", "parking", "stop", None),
    ("dwell", "parking", "stop", None),
    ("parking", "done", "parked", None),
    ("fault", "start", "recover", "can_retry"),
    ("fault", "failed", "recover", None),
}

EDGE = re.compile(r"^\s*(\w+) --> (\w+) : (\w+)(?: \[(\w+)\])?$")


def test_patrol_mermaid_matches_declared_graph(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["graph", str(PATROL)]) == 0
    text = capsys.readouterr().out
    lines = text.splitlines()
    assert lines[0] == "stateDiagram-v2"
    edges = {(m[1], m[2], m[3], m[4]) for m in map(EDGE.match, lines) if m}
    assert edges == DECLARED
    assert "    [*] --> start" in lines
    assert {"    done --> [*]", "    failed --> [*]"} <= set(lines)
    assert sum("[*] -->" in ln for ln in lines) == 1
