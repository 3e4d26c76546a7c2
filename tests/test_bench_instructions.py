"""``agentsdk bench --only instructions``: its arithmetic, its skip without valgrind, and the loops its children run."""

from __future__ import annotations

import pytest

import agentsdk.loop
from agentsdk.bench import instructions


def test_instructions_per_cycle_are_the_difference_of_two_runs(monkeypatch: pytest.MonkeyPatch) -> None:
    counts = {100: 5_000_000, 1100: 5_000_000 + 1000 * 2_718}
    monkeypatch.setattr(instructions, "_instructions", lambda valgrind, what, n, robot: counts[n])
    assert instructions.per_cycle("valgrind", "sdk", "arm3", 100, 1100) == 2_718


def test_without_valgrind_nothing_is_measured_and_it_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(instructions.shutil, "which", lambda name: None)
    section = instructions.run(quick=True)
    assert section.status == "skipped" and not section.comparisons
    assert "valgrind" in section.notes[0]


@pytest.mark.parametrize("what", ["sdk", "raw"])
def test_a_child_runs_its_loop(what: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The child sets the lease budget for valgrind's speed; here (natively) it just runs the cycles."""
    monkeypatch.setattr(agentsdk.loop, "BATCH_SECONDS", agentsdk.loop.BATCH_SECONDS)
    monkeypatch.setenv("AGENTSDK_BENCH_BATCH", "0.002")
    instructions._child(what, 5, "arm3")
    assert agentsdk.loop.BATCH_SECONDS == 0.002
