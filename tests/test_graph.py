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


RUN_BEHAVIOR = '''
from agentsdk.statemachine import State, StateMachine


class Hop(StateMachine):
    start = State(initial=True)
    hop = State()
    landed = State(final=True)
    crashed = State(final=True)
    go = start.to(hop)
    down = hop.to(landed)
    fall = hop.to(crashed)

    async def on_start(self, ctx):
        return "go"

    async def on_hop(self, ctx):
        await ctx.robot.move_to({"joint1": 0.2}, duration=0.5)
        return "down"


async def main(robot):
    await Hop(robot).run()
'''


def test_graph_of_a_recorded_run_highlights_the_visited_states(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 26 (introspection): `agentsdk graph BEHAVIOR --run RUN.mcap` draws the run on the diagram."""
    behavior = tmp_path / "hop.py"
    behavior.write_text(RUN_BEHAVIOR)
    run = tmp_path / "hop.mcap"
    assert cli_main(["run", str(behavior), "--backend", "mock", "--record", str(run), "-q"]) == 0
    capsys.readouterr()
    assert cli_main(["graph", str(behavior), "--run", str(run)]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln]
    assert "    classDef visited fill:#ffd966,stroke:#b45f06,stroke-width:2px" in lines
    assert lines[-1] == "    class hop,landed,start visited"  # not "crashed": the run never entered it
