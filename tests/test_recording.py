"""Recording (MCAP), replay, plots, progress bar and --view of ``agentsdk run``.

The wave behavior on arm3 runs 5 poses x 1.5 s = 7.5 s of lockstep time at
500 Hz = 3750 control ticks; it is recorded once per module.
"""

from __future__ import annotations

import io
import json
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from agentsdk import cli, progress
from agentsdk.cli import main
from agentsdk.plot import plot_run
from agentsdk.recording import TOPICS, read_recording

WAVE_TICKS = 3750  # 7.5 s at 500 Hz


def _summary(path: Path) -> tuple[dict[str, int], dict[str, Any], dict[str, str]]:
    """(message count per topic, channel per topic, agentsdk metadata) of an MCAP file."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        counts = {ch.topic: summary.statistics.channel_message_counts.get(ch.id, 0) for ch in summary.channels.values()}
        channels = {ch.topic: (ch, summary.schemas[ch.schema_id]) for ch in summary.channels.values()}
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return counts, channels, meta["agentsdk"]


@pytest.fixture(scope="module")
def wave_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("wave")
    paths = {"mcap": d / "run.mcap", "png": d / "run.png"}
    rc = main(["run", "wave", "--backend", "mujoco", "--record", str(paths["mcap"]), "--plot", str(paths["png"]), "-q"])
    assert rc == 0
    return paths


SM_BEHAVIOR = """
    from agentsdk import JointCommand
    from agentsdk.statemachine import State, StateContext, StateMachine

    ROBOT = "arm3"

    class Reach(StateMachine):
        idle = State(initial=True)
        reach = State()
        done = State(final=True)
        go = idle.to(reach)
        finish = reach.to(done)

        async def on_idle(self, ctx: StateContext) -> str:
            await ctx.robot.clock.sleep(0.1)
            return "go"

        async def on_reach(self, ctx: StateContext) -> str:
            await ctx.robot.command(JointCommand("position", {"joint1": 99.0}))  # clamped -> safety event
            await ctx.robot.clock.sleep(0.2)
            return "finish"

    async def main(robot):
        await Reach(robot).run()
"""

SHORT_BEHAVIOR = """
    async def main(robot):
        await robot.clock.sleep(0.05)
"""


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return p


# ----------------------------------------------------------------- recording
def _rosbags_decoder(path: Path) -> Any:
    """A rosbags type store knowing every message type of the file, registered from its own ros2msg schemas."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    for schema in summary.schemas.values():
        if schema.name.startswith("agentsdk_msgs/"):
            store.register(get_types_from_msg(schema.data.decode().split("=" * 80)[0], schema.name))
    return store


def test_recording_has_cdr_channels_with_ros2msg_schemas(wave_run: dict[str, Path]) -> None:
    counts, channels, meta = _summary(wave_run["mcap"])
    assert set(counts) == set(TOPICS)
    assert counts["/joint_states"] == WAVE_TICKS // 10  # decimated to 50 Hz by default
    # change-based commands: at least the first and last tick, never more than one per tick
    assert 2 <= counts["/joint_commands"] <= WAVE_TICKS
    assert counts["/safety/events"] == 0 and counts["/behavior/transitions"] == 0
    for ch, schema in channels.values():
        assert ch.message_encoding == "cdr" and schema.encoding == "ros2msg"
    assert channels["/joint_states"][1].name == "sensor_msgs/msg/JointState"
    assert channels["/joint_commands"][1].name == "agentsdk_msgs/msg/JointCommand"
    assert channels["/tf"][1].name == "tf2_msgs/msg/TFMessage"
    assert meta["robot"] == "arm3" and meta["backend"] == "mujoco" and meta["control_period"] == "0.002"
    assert meta["format"] == "agentsdk-recording/3" and meta["record_rate"] == "50.0"
    assert json.loads(meta["joints"]) == ["joint1", "joint2", "joint3"]
    assert meta["behavior"].endswith("wave.py")

    # decoded by an independent CDR implementation from the file's own schemas
    store = _rosbags_decoder(wave_run["mcap"])
    first: dict[str, Any] = {}
    with open(wave_run["mcap"], "rb") as f:
        for schema, ch, msg in make_reader(f).iter_messages():
            if ch.topic not in first:
                first[ch.topic] = (msg.log_time, store.deserialize_cdr(msg.data, schema.name))
    t, state = first["/joint_states"]
    assert t == 20_000_000  # the first 50 Hz sample, robot time in ns
    assert (state.header.stamp.sec, state.header.stamp.nanosec) == (0, 20_000_000)
    assert list(state.name) == ["joint1", "joint2", "joint3"] and len(state.position) == 3
    t, cmd = first["/joint_commands"]
    assert t == 0 and cmd.mode.tolist() == [0, 0, 0] and cmd.enabled.tolist() == [True] * 3
    assert cmd.target.tolist() == [0.0, 0.6, 0.0]  # wave's first pose; the setpoint ramps towards it
    assert 0.0 < cmd.position[1] < 0.6
    assert cmd.kp.tolist() == [100.0, 800.0, 20.0]


def test_record_rate_sets_the_joint_state_rate_but_never_decimates_commands(
    wave_run: dict[str, Path], tmp_path: Path
) -> None:
    full, _, _ = _summary(wave_run["mcap"])
    every, slow = tmp_path / "every.mcap", tmp_path / "slow.mcap"
    assert main(["run", "wave", "--record", str(every), "--record-rate", "500", "-q"]) == 0  # the control rate
    assert main(["run", "wave", "--record", str(slow), "--record-rate", "20", "-q"]) == 0
    counts, _, meta = _summary(every)
    assert counts["/joint_states"] == WAVE_TICKS and meta["record_rate"] == ""
    assert counts["/joint_commands"] == full["/joint_commands"]
    counts, _, meta = _summary(slow)
    assert counts["/joint_states"] == WAVE_TICKS * 20 // 500 and meta["record_rate"] == "20.0"
    assert counts["/joint_commands"] == full["/joint_commands"]
    data = read_recording(slow)
    assert np.all(np.diff(data.state_time) == 50_000_000)
    np.testing.assert_array_equal(read_recording(every).state_time[24::25], data.state_time)


def test_safety_events_and_state_machine_transitions_are_recorded(tmp_path: Path) -> None:
    beh = _write(tmp_path, "reach.py", SM_BEHAVIOR)
    out = tmp_path / "reach.mcap"
    assert main(["run", str(beh), "--backend", "mock", "--record", str(out), "-q"]) == 0
    counts, _, _ = _summary(out)
    assert counts["/joint_states"] == 15  # 0.3 s at 50 Hz
    data = read_recording(out)
    assert [(e["kind"], e["joint"]) for e in data.events] == [("clamp", "joint1")]
    assert data.events[0]["time"] == pytest.approx(0.1)
    moves = [(tr["source"], tr["target"], tr["event"]) for tr in data.transitions]
    assert moves == [(None, "idle", None), ("idle", "reach", "go"), ("reach", "done", "finish")]
    assert [tr["time"] for tr in data.transitions] == pytest.approx([0.0, 0.1, 0.3])
    assert {tr["machine"] for tr in data.transitions} == {"Reach"}
    # introspection (issue 26): the active configuration after each record and the time spent in the source
    assert [tr["configuration"] for tr in data.transitions] == ["Reach/idle", "Reach/reach", "Reach/done"]
    assert [tr["duration"] for tr in data.transitions] == [None, pytest.approx(0.1), pytest.approx(0.2)]


# ----------------------------------------------------------------- replay
def test_replay_into_mujoco_reproduces_the_lockstep_recording(
    wave_run: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    replayed = tmp_path / "replayed.mcap"
    rc = main(
        ["replay", str(wave_run["mcap"]), "--backend", "mujoco", "--tolerance", "1e-6", "--record", str(replayed)]
    )
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "max |err|" in out and "joint3" in out
    # compare the two files independently of replay()'s own bookkeeping
    rec, rep = read_recording(wave_run["mcap"]), read_recording(replayed)
    rows = np.searchsorted(rep.state_time, rec.state_time)
    assert len(rec.state_time) == WAVE_TICKS // 10
    np.testing.assert_array_equal(rep.state_time[rows], rec.state_time)
    assert np.max(np.abs(rep.position[rows] - rec.position)) <= 1e-6
    assert np.max(np.abs(rep.velocity[rows] - rec.velocity)) <= 1e-6


def test_replay_reports_user_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(tmp_path / "missing.mcap")]) == 2
    assert "recording not found" in capsys.readouterr().err
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    assert main(["replay", str(junk)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: cannot read recording") and err.count("\n") == 1


def test_record_into_missing_directory_is_a_user_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "wave", "--record", str(tmp_path / "nope" / "run.mcap")]) == 2
    assert "does not exist" in capsys.readouterr().err


# ----------------------------------------------------------------- plot
def test_plot_has_one_panel_per_joint_plus_error(wave_run: dict[str, Path], tmp_path: Path) -> None:
    import matplotlib.image

    img = matplotlib.image.imread(wave_run["png"])
    assert img.ndim == 3 and img.shape[2] in (3, 4) and img.shape[0] > 400 and img.shape[1] > 400
    data = read_recording(wave_run["mcap"])
    fig = plot_run(data, tmp_path / "again.png")
    assert len(fig.axes) == len(data.names) + 1 == 4
    assert [ax.get_ylabel().split("\n")[0] for ax in fig.axes[:3]] == ["joint1", "joint2", "joint3"]
    assert "arm3" in fig.texts[0].get_text() and "mujoco" in fig.texts[0].get_text()
    desired = data.desired_position()
    assert np.isfinite(desired).all()  # wave keeps every joint position-servoed
    assert np.max(np.abs(desired[-1] - [0.0, 0.4, 0.0])) < 1e-9  # last pose reached by the setpoint


# ----------------------------------------------------------------- view & progress
def test_view_without_display_is_a_clear_user_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(cli.sys, "platform", "linux")
    assert main(["run", "wave", "--view"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("error: --view needs a display") and "DISPLAY" in err


class _Started:
    def __init__(self) -> None:
        self.labels: list[str] = []

    def patch(self, monkeypatch: pytest.MonkeyPatch) -> None:
        def start(p: progress.RunProgress) -> progress.RunProgress:
            self.labels.append(p._label)
            return p

        monkeypatch.setattr(progress.RunProgress, "start", start)


def test_no_progress_bar_when_stdout_is_not_a_terminal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    beh = _write(tmp_path, "short.py", SHORT_BEHAVIOR)
    started = _Started()
    started.patch(monkeypatch)
    assert main(["run", str(beh), "--backend", "mock"]) == 0
    assert started.labels == []  # captured stdout is not a tty
    assert "real time" not in capsys.readouterr().out
    # on a terminal the bar is set up, and --quiet turns it off
    monkeypatch.setattr(cli.sys.stdout, "isatty", lambda: True)
    assert main(["run", str(beh), "--backend", "mock"]) == 0
    assert started.labels == ["short.py on arm3 (mock)"]
    assert main(["run", str(beh), "--backend", "mock", "--quiet"]) == 0
    assert len(started.labels) == 1


def test_progress_display_shows_sim_time_and_real_time_factor() -> None:
    from rich.console import Console

    assert not progress.progress_enabled(False, io.StringIO())
    assert not progress.progress_enabled(True)
    buf = io.StringIO()
    readings = iter([0.0])  # the first reading (at start) is the origin, later ones 12.5 s after it

    def clock() -> float:
        return next(readings, 12.5)

    console = Console(file=buf, force_terminal=True, width=120)
    bar = progress.RunProgress(clock, label="demo", delay=0.0, console=console)
    with bar:
        assert bar.displayed.wait(timeout=30)
    text = buf.getvalue()
    assert "demo" in text and "sim    12.50 s" in text and "x real time" in text
