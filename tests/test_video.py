"""Headless video: ``agentsdk run ... --video`` writes a file whose frames change, with no display."""

from __future__ import annotations

import itertools
import subprocess
from pathlib import Path

import numpy as np
import pytest

import agentsdk.robot
from agentsdk.cli import main as cli_main
from agentsdk.video import _gl_context_class

BEHAVIOR = '''
from agentsdk import Robot

ROBOT = "arm3"


async def main(robot: Robot) -> None:
    await robot.move_to({"joint1": 1.0, "joint2": 0.8}, duration=1.0)
'''


@pytest.fixture(autouse=True)
def headless(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    real = agentsdk.robot.connect

    def relaxed(*args: object, **kw: object) -> object:
        kw.setdefault("safety", {"stall_timeout": 5.0})  # lockstep on a loaded test machine
        return real(*args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(agentsdk.robot, "connect", relaxed)


@pytest.fixture
def behavior(tmp_path: Path) -> Path:
    path = tmp_path / "swing.py"
    path.write_text(BEHAVIOR)
    return path


def read_frames(path: Path, width: int, height: int) -> list[np.ndarray]:
    if path.suffix == ".gif":
        from PIL import Image, ImageSequence

        with Image.open(path) as img:
            return [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(img)]
    import imageio_ffmpeg  # its ffmpeg binary decodes the file independently of the writer

    raw = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-i", str(path), "-f", "rawvideo",
                          "-pix_fmt", "rgb24", "-"], capture_output=True, check=True).stdout
    frames = np.frombuffer(raw, dtype=np.uint8).reshape(-1, height, width, 3)
    return list(frames)


def test_offscreen_opengl_is_available() -> None:
    """The project's install (scripts/test.sh) provides EGL or OSMesa: MuJoCo renders without a display."""
    assert _gl_context_class() is not None


@pytest.mark.parametrize("backend,suffix", [("mujoco", ".mp4"), ("pybullet", ".gif"), ("mock", ".mp4"),
                                            ("mujoco", ".gif")])
def test_video_frames_change_over_time(backend: str, suffix: str, behavior: Path, tmp_path: Path) -> None:
    out = tmp_path / f"run{suffix}"
    code = cli_main(["run", str(behavior), "--backend", backend, "--quiet", "--video", str(out),
                     "--video-size", "160x120", "--video-fps", "20"])
    assert code == 0
    frames = read_frames(out, 160, 120)
    assert 20 <= len(frames) <= 40  # ~1.3 s of robot time at 20 fps
    assert frames[0].shape == (120, 160, 3)
    first, last = frames[0].astype(int), frames[-1].astype(int)
    assert np.abs(first - last).mean() > 1.0  # the arm moved
    assert frames[0].std() > 5.0  # not a blank image
    changed = sum(np.abs(a.astype(int) - b).mean() > 0.05 for a, b in itertools.pairwise(frames))
    assert changed >= len(frames) // 3


def test_video_bad_arguments(behavior: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["run", str(behavior), "--backend", "mock", "--quiet", "--video", str(tmp_path / "x.avi")]) != 0
    assert ".mp4 or .gif" in capsys.readouterr().err
    assert cli_main(["run", str(behavior), "--backend", "mock", "--quiet", "--video", str(tmp_path / "x.mp4"),
                     "--video-size", "big"]) != 0
    assert "WIDTHxHEIGHT" in capsys.readouterr().err
    assert not (tmp_path / "x.mp4").exists()


async def test_video_recorder_api_with_progress_bar(tmp_path: Path) -> None:
    from agentsdk.video import VideoRecorder

    async with agentsdk.connect("mock", robot="humanoid", safety={"stall_timeout": 5.0}) as robot:
        rec = VideoRecorder.attach(robot, tmp_path / "h.gif", fps=10, size=(96, 72))
        await robot.move_to({robot.joint_names[0]: 0.5, robot.joint_names[3]: -0.5}, duration=1.0)
    assert 9 <= len(rec.frames) <= 13
    assert rec.finish(progress=True) == tmp_path / "h.gif"
    frames = read_frames(tmp_path / "h.gif", 96, 72)
    assert len(frames) == len(rec.frames)
    assert np.abs(frames[0].astype(int) - frames[-1]).mean() > 0.5


async def test_can_robot_has_kinematics_and_video(tmp_path: Path) -> None:
    """The CAN backend (emulated MIT motors on python-can's virtual bus) is drawn from FK like the mock."""
    from agentsdk.backends.can.testing import EmulatedCanConformance
    from agentsdk.video import VideoRecorder

    async with EmulatedCanConformance().open_robot() as robot:
        kin = robot.kinematics
        link = kin.link_names[-1]
        rec = VideoRecorder.attach(robot, tmp_path / "leg.mp4", fps=10, size=(96, 72))
        await robot.move_to({robot.joint_names[0]: 0.6}, duration=1.0)
        state = await robot.read()
        assert kin.fk(link).isclose(kin.fk(link, state), 1e-12, 1e-12)
    assert len(rec.frames) >= 8
    rec.finish()
    frames = read_frames(tmp_path / "leg.mp4", 96, 72)
    assert len(frames) == len(rec.frames)
    assert np.abs(frames[0].astype(int) - frames[-1]).mean() > 0.2
