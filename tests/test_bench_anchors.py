"""The anchors benchmark's plumbing (bench/anchors.py, bench/peers.py): no network, no venv, no pip.

* the subprocess protocol: rows written by ``peers.write_output`` parse back, noise lines are skipped;
* dm_control's rows when their interpreter is missing, broken or has no dm_control: one "cannot run"
  row per task, at the task's frame skip, saying why (and nothing is created on disk);
* the verdict of an agentsdk row against the peer rows of the same frame skip.
"""

from __future__ import annotations

import io
import sys
from pathlib import Path
from typing import Any

import pytest

from agentsdk.bench import anchors, peers
from agentsdk.bench.peers import PeerRow


def _row(stack: str, env: str, fs: int, raw: list[float], run: list[float], error: str = "") -> PeerRow:
    return PeerRow(stack, env, fs, raw_cpu_us=raw, env_cpu_us=run, raw_wall_us=raw, env_wall_us=run, error=error)


def test_a_row_survives_the_subprocess_protocol() -> None:
    rows = [_row("dm_control", "cheetah-run", 1, [7.5, 7.0], [31.0, 36.2]),
            PeerRow("dm_control", "humanoid-walk", 5, error="cannot load it: AttributeError: x")]
    out = io.StringIO()
    peers.write_output(rows, "dm_control 1.0.50 with MuJoCo 3.17.0", out)
    text = "WARNING:absl:some chatter\n" + out.getvalue() + '{"kind": "row", "env": "no stack"}\nnot json {\n'
    parsed, versions = peers.parse_output(text)
    assert versions == "dm_control 1.0.50 with MuJoCo 3.17.0"
    assert parsed == rows  # the row missing its required fields is skipped, not half-read
    assert anchors.ratio(parsed[0]) == pytest.approx((31.0 / 7.5 + 36.2 / 7.0) / 2)


def test_dm_control_cannot_run_without_its_interpreter(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(anchors.DM_PYTHON_ENV, str(tmp_path / "no-such-python"))
    rows, what = anchors.dm_control_rows(steps=10, repeats=1, setup=True)
    assert what == ""
    assert [(r.stack, r.env, r.frame_skip) for r in rows] == [
        ("dm_control", "reacher-easy", 1), ("dm_control", "cheetah-run", 1), ("dm_control", "humanoid-walk", 5)]
    for r in rows:
        assert r.error.startswith("cannot run: ") and anchors.DM_PYTHON_ENV in r.error, r.error
        assert not r.env_cpu_us and not r.raw_cpu_us
    assert list(tmp_path.iterdir()) == []


def test_the_pinned_environment_is_not_created_unless_asked(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(anchors.DM_PYTHON_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert anchors.dm_venv_dir() == tmp_path / "agentsdk" / "bench-dm_control"
    python, why = anchors.dm_python(setup=False)
    assert python is None
    assert "--only anchors" in why and str(tmp_path) in why
    rows, _ = anchors.dm_control_rows(steps=10, repeats=1, setup=False)
    assert len(rows) == 3 and all("not set up" in r.error for r in rows)
    assert list(tmp_path.iterdir()) == []


def test_a_failing_interpreter_gives_cannot_run_rows() -> None:
    false = Path("/bin/false")
    if not false.exists():
        pytest.skip("no /bin/false")
    rows, _ = anchors.dm_control_rows(steps=10, repeats=1, setup=False, python=false)
    assert len(rows) == 3 and all("exited 1" in r.error for r in rows), [r.error for r in rows]


def test_the_peer_script_runs_under_a_plain_interpreter() -> None:
    """``peers.py`` under this interpreter (no agentsdk imports; -I): dm_control absent or unloadable -> cannot run."""
    rows, what = anchors.dm_control_rows(steps=20, repeats=1, setup=False, python=Path(sys.executable))
    assert [r.env for r in rows] == ["reacher-easy", "cheetah-run", "humanoid-walk"]
    for r in rows:  # measured where this interpreter's dm_control works, else why not
        assert r.error or (len(r.env_cpu_us) == 1 and len(r.raw_cpu_us) == 1 and r.frame_skip >= 1), r
    if all(r.error for r in rows):
        assert all("dm_control" in r.error for r in rows), [r.error for r in rows]
    else:
        assert "dm_control" in what


def test_verdict_against_the_peers_of_the_same_frame_skip() -> None:
    rows = [
        _row("gymnasium", "Reacher-v5", 1, [10.0], [25.0]),  # 2.5x
        _row("dm_control", "cheetah-run", 1, [8.0], [32.0]),  # 4x
        _row("gymnasium", "Pusher-v5 (its default)", 5, [30.0], [48.0]),  # 1.6x
        PeerRow("dm_control", "humanoid-walk", 5, error="cannot run: no interpreter"),
        _row("agentsdk", "arm3 1000 Hz hold", 1, [4.0], [8.0]),  # 2x: below both at fs 1
        _row("agentsdk", "arm3 200 Hz follow()", 5, [15.0], [30.0]),  # 2x: above Pusher's 1.6x
        _row("agentsdk", "arm3 333 Hz hold", 3, [5.0], [5.0]),  # no peer at fs 3
    ]
    v = {c.figure.split(",")[0]: c for c in anchors.verdicts(rows)}
    hold, track = v["agentsdk arm3 1000 Hz hold"], v["agentsdk arm3 200 Hz follow()"]
    lone = v["agentsdk arm3 333 Hz hold"]
    assert "frame skip: yes (worst peer ratio 2.50x: Reacher-v5)" in hold.figure
    assert hold.baseline == pytest.approx(2.5) and hold.sdk == pytest.approx(2.0) and hold.target_met
    assert "frame skip: no (worst peer ratio 1.60x: Pusher-v5 (its default); 1 peer" in track.figure
    assert not track.target_met and "not measured: dm_control humanoid-walk" in track.note
    assert track.figure.endswith("; 1 peer row(s) not measured)")
    assert "no peer row measured there" in lone.figure and lone.baseline is None
    lines = anchors.comparability(rows)
    assert any(ln.startswith("frame skip 5:") and "humanoid-walk (not measured)" in ln for ln in lines), lines


def test_a_plain_quick_run_leaves_the_anchors_out(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """``agentsdk bench --quick`` (the test suite runs it) must not reach for pip; ``--only anchors`` may."""
    import json

    from agentsdk.bench import __main__ as cli

    calls: list[tuple[bool, bool]] = []

    def fake_anchors(quick: bool, setup: bool = False) -> list[Any]:
        calls.append((quick, setup))
        return []

    monkeypatch.setattr(cli, "BENCHMARKS", {"anchors": ("the anchors", fake_anchors)})
    monkeypatch.setattr(cli, "SETS_UP_WHEN_NAMED", {"anchors": fake_anchors})
    out = tmp_path / "quick.json"
    assert cli.main(["--quick", "--json", str(out)]) == 0
    assert calls == []
    (sec,) = json.loads(out.read_text())["sections"]
    assert sec["status"] == "skipped" and "--only anchors" in sec["notes"][0]
    assert cli.main(["--quick", "--only", "anchors", "--json", str(out)]) == 0
    assert calls == [(True, True)]  # named: it runs, and may set up its environment
    assert cli.main(["--json", str(out)]) == 0
    assert calls[-1] == (False, False)  # a full run: only an environment that already exists
