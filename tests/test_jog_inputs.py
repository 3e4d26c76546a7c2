"""Jogging from the terminal's keyboard (through a real pty, as over ssh) and from a gamepad (a fake joystick
device: the kernel's event bytes written into a pipe), with the key and axis mapping they share."""

from __future__ import annotations

import asyncio
import io
import os
import re
import subprocess
import sys
import termios
import time
from pathlib import Path

import numpy as np
import pytest

import agentsdk
from agentsdk.errors import InvalidValueError
from agentsdk.gamepad import EVENT_SIZE, GamepadMapping, GamepadState, encode_event, jog_with_gamepad, parse_events
from agentsdk.jog import JOG_STEP, JOINT_STEP, JogAction, Jogger, key_action

ROOT = Path(__file__).resolve().parents[1]
# a UR5 start pose away from the stretched-out singularity (a Cartesian jog is a straight line from here)
READY = {"shoulder_pan_joint": -0.54, "shoulder_lift_joint": 0.19, "elbow_joint": -0.59,
         "wrist_1_joint": -0.54, "wrist_2_joint": -0.57, "wrist_3_joint": 0.09}
SAFETY = {"stall_timeout": 5.0}


def _ur5_yaml(tmp_path: Path) -> Path:
    import yaml

    from agentsdk.description.catalog import find_robot

    ur5 = find_robot("ur5")
    if ur5 is None:
        pytest.skip("needs example-robot-data's UR5 (the test extra)")
    path = tmp_path / "ur5.yaml"
    path.write_text(yaml.safe_dump({"description": str(ur5.path), "initial_positions": READY, "safety": SAFETY}))
    return path


# ------------------------------------------------------------------ the keys
def test_key_mapping() -> None:
    assert key_action("i", 6) == JogAction("cartesian", 0, 1.0)
    assert key_action("K", 6) == JogAction("cartesian", 0, -1.0)  # Caps Lock or Shift: the same axis
    assert key_action("j", 6) == JogAction("cartesian", 1, 1.0)
    assert key_action("o", 6) == JogAction("cartesian", 2, -1.0)
    assert key_action("3", 6) == JogAction("joint", 2, 1.0)
    assert key_action("3", 6, shift=True) == JogAction("joint", 2, -1.0)
    assert key_action("#", 6) == JogAction("joint", 2, -1.0)  # Shift+3 in a terminal
    for other in ("7", "&", "0", "w", " ", "\x1b", "ii", ""):
        assert key_action(other, 6) is None, other  # no 7th joint; not a jog key
    assert JogAction("joint", 1, -1.0).describe(["a", "b"]) == "b -"


def test_terminal_input_is_split_into_key_presses() -> None:
    from agentsdk.keyjog import split_keys

    # arrows and function keys are escape sequences, not Esc (quit) plus letters; keys read together stay apart
    assert split_keys("\x1b[Au") == ["u"]
    assert split_keys("ii\x1b[1;5C\x1bOPk") == ["i", "i", "k"]
    assert split_keys("\x1b") == ["\x1b"] and split_keys("a\x1b") == ["a", "\x1b"]


async def test_jogger_steps_one_at_a_time_and_release_holds() -> None:
    async with agentsdk.connect("mock", robot="arm3", safety=SAFETY) as robot:
        jogger = Jogger(robot)
        with pytest.raises(InvalidValueError, match="positive"):
            Jogger(robot, step=0.0)
        first = jogger.submit(lambda: jogger.joint(1, JOINT_STEP))
        assert first is not None and jogger.busy
        assert jogger.submit(lambda: jogger.joint(1, JOINT_STEP)) is None  # dropped, not queued
        result = await first
        assert result.ok and abs(robot.desired_state()[0][1] - JOINT_STEP) < 1e-9
        # a long step released half way: the robot decelerates and holds short of the target
        long = jogger.submit(lambda: jogger.joint(1, 1.0))
        assert long is not None
        await robot.clock.sleep(0.2)
        jogger.release()
        await jogger.wait()
        await robot.clock.sleep(0.5)
        q = robot.latest_state()
        assert JOINT_STEP < q.position[1] < JOINT_STEP + 0.9 and float(np.max(np.abs(q.velocity))) < 1e-3
        # beyond the joint limit: clipped into it
        upper = robot.joints[0].upper
        assert (await jogger.joint(0, 100.0)).ok and abs(robot.desired_state()[0][0] - upper) < 1e-9


# ------------------------------------------------------------------ the terminal, through a pty
def _read_until(fd: int, pattern: str, buf: list[str], timeout: float = 240.0) -> re.Match[str]:
    rx = re.compile(pattern)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        m = rx.search("".join(buf))
        if m:
            return m
        import select

        ready, _, _ = select.select([fd], [], [], 0.2)
        if ready:
            try:
                buf.append(os.read(fd, 4096).decode(errors="replace"))
            except OSError:  # the child closed the terminal
                break
    raise AssertionError(f"{pattern!r} not seen; the terminal shows:\n{''.join(buf)}")


def _where(text: str) -> list[np.ndarray]:
    rx = r"at x=([+-][\d.]+) y=([+-][\d.]+) z=([+-][\d.]+) m"
    return [np.array([float(v) for v in m]) for m in re.findall(rx, text)]


@pytest.mark.timeout(300)
def test_terminal_keys_through_a_pty(tmp_path: Path) -> None:
    import pty

    robot = _ur5_yaml(tmp_path)
    master, slave = pty.openpty()
    before = termios.tcgetattr(slave)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "agentsdk", "teleop", "--keys", "--robot", str(robot),
                             "--backend", "mujoco"], stdin=slave, stdout=slave, stderr=slave, cwd=ROOT, env=env)
    buf: list[str] = []
    try:
        _read_until(master, r"q quits", buf)
        _read_until(master, r"at x=\S+ y=\S+ z=\S+ m", buf)
        assert not termios.tcgetattr(slave)[3] & termios.ICANON  # key-at-a-time while it runs
        os.write(master, b"i")  # +x
        _read_until(master, r"(at x=\S+ y=\S+ z=\S+ m[\s\S]*){2}", buf)
        start, moved = _where("".join(buf))[:2]
        d = moved - start
        assert abs(d[0] - JOG_STEP) < 1e-3 and np.linalg.norm(d[1:]) < 1e-3, d
        os.write(master, b"\x1b[Au")  # an arrow key (ignored, not a quit) read together with U (+z)
        _read_until(master, r"(at x=\S+ y=\S+ z=\S+ m[\s\S]*){3}", buf)
        up = _where("".join(buf))[2] - moved
        assert abs(up[2] - JOG_STEP) < 1e-3 and np.linalg.norm(up[:2]) < 1e-3, up
        os.write(master, b"q")
        assert proc.wait(timeout=120) == 0, "".join(buf)
        _read_until(master, r"jog ended after 2 steps", buf, timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        after = termios.tcgetattr(slave)
        os.close(slave)
        os.close(master)
    assert after == before  # the terminal is as it was
    assert "Traceback" not in "".join(buf)


def test_keys_without_a_terminal_says_what_to_do() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-m", "agentsdk", "teleop", "--keys", "--backend", "mock"],
                         stdin=subprocess.DEVNULL, capture_output=True, text=True, cwd=ROOT, env=env, timeout=120,
                         check=False)
    assert out.returncode != 0 and "Traceback" not in out.stderr
    assert "stdin is not one" in out.stderr and "ssh -t" in out.stderr, out.stderr


def test_teleop_without_a_mode_says_what_to_do() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-m", "agentsdk", "teleop"], capture_output=True, text=True, cwd=ROOT,
                         env=env, timeout=120, check=False)
    assert out.returncode != 0 and "Traceback" not in out.stderr
    assert "--leader" in out.stderr and "--keys" in out.stderr, out.stderr


# ------------------------------------------------------------------ the gamepad
def test_joystick_events_are_parsed() -> None:
    data = (encode_event("button", 4, 1, time_ms=10, initial=True) + encode_event("axis", 1, -1.0, time_ms=20)
            + encode_event("axis", 0, 0.5) + encode_event("button", 4, 0))
    assert len(data) == 4 * EVENT_SIZE == 32
    events, rest = parse_events(data[:-3])  # a partial trailing event is kept for the next read
    assert len(events) == 3 and len(rest) == EVENT_SIZE - 3
    assert (events[0].kind, events[0].number, events[0].value, events[0].initial) == ("button", 4, 1.0, True)
    assert (events[1].kind, events[1].number, events[1].value, events[1].time_ms) == ("axis", 1, -1.0, 20)
    assert abs(events[2].value - 0.5) < 1e-4 and not events[2].initial
    more, rest = parse_events(rest + data[-3:])
    assert rest == b"" and more[0].kind == "button" and more[0].value == 0.0
    # the kernel's own bytes: time 1000 ms, value -32767, type axis|init, number 3
    (ev,), _ = parse_events(bytes([0xE8, 0x03, 0, 0, 0x01, 0x80, 0x82, 3]))
    assert (ev.time_ms, ev.kind, ev.number, ev.value, ev.initial) == (1000, "axis", 3, -1.0, True)
    # an unknown event type is skipped
    assert parse_events(bytes([0, 0, 0, 0, 1, 0, 0x04, 0]))[0] == []


def test_gamepad_mapping_needs_the_deadman_and_ignores_the_deadzone() -> None:
    m = GamepadMapping()
    s = GamepadState()
    for ev in parse_events(encode_event("axis", 1, -1.0) + encode_event("axis", 0, 0.1)
                           + encode_event("axis", 4, 0.6))[0]:
        s.update(ev)
    assert not m.direction(s).any()  # dead-man not held: nothing
    s.update(parse_events(encode_event("button", 4, 1))[0][0])
    d = m.direction(s)
    assert d[0] == pytest.approx(1.0) and d[1] == 0.0 and d[2] == pytest.approx(-0.5, abs=1e-3)  # up = +x, z down
    with pytest.raises(InvalidValueError, match="deadzone"):
        GamepadMapping(deadzone=1.0)


async def test_gamepad_jogs_while_the_deadman_is_held_and_holds_on_release(tmp_path: Path) -> None:
    async with agentsdk.connect("mujoco", robot=str(_ur5_yaml(tmp_path)), realtime=True) as robot:
        link = Jogger(robot).link

        def desired() -> np.ndarray:  # the commanded pose (MuJoCo's UR5 sags a few mm under gravity)
            return robot.kinematics.fk(link, robot.desired_state()[0]).position.copy()

        start = desired()
        rfd, wfd = os.pipe()
        out = io.StringIO()
        session = asyncio.create_task(jog_with_gamepad(robot, rfd, out=out))
        try:
            os.write(wfd, encode_event("button", 4, 1, initial=True) + encode_event("axis", 1, -1.0))  # LB, stick up
            async with asyncio.timeout(120):
                while robot.kinematics.fk(link).position[0] - start[0] < 0.015:  # noqa: ASYNC110
                    await asyncio.sleep(0.02)
            os.write(wfd, encode_event("button", 4, 0))  # LB released: stop, hold
            await robot.clock.sleep(0.6)
            held = robot.kinematics.fk(link).position.copy()
            await robot.clock.sleep(0.5)
            # holds (0.5 mm: the measured pose of a PD-held MuJoCo arm still settles a little; a step is 10 mm)
            assert np.linalg.norm(robot.kinematics.fk(link).position - held) < 5e-4, held
            moved = desired() - start
            # a release stops each joint within its limits: the last millimetres may leave the line
            assert moved[0] > 0.015 and np.linalg.norm(moved[1:]) < 6e-3, moved
            os.write(wfd, encode_event("axis", 1, 0.0) + encode_event("button", 4, 1))  # dead-man, stick centred
            await robot.clock.sleep(0.3)
            assert np.linalg.norm(robot.kinematics.fk(link).position - held) < 5e-4, held
        finally:
            os.close(wfd)  # the device goes away: the session ends, the robot holds
            steps = await asyncio.wait_for(session, 60)
        assert steps >= 1 and "went away" in out.getvalue()


def test_no_gamepad_is_one_line(tmp_path: Path) -> None:
    from agentsdk.gamepad import find_gamepad

    if find_gamepad() is not None:
        pytest.skip("this machine has a joystick device")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-m", "agentsdk", "teleop", "--gamepad", "--backend", "mock"],
                         capture_output=True, text=True, cwd=ROOT, env=env, timeout=120, check=False)
    assert out.returncode != 0
    assert out.stderr.strip().splitlines() == [
        "error: no gamepad found (no /dev/input/js*): plug one in, or jog with --keys"]
    missing = subprocess.run([sys.executable, "-m", "agentsdk", "teleop", "--gamepad", str(tmp_path / "js9"),
                              "--backend", "mock"], capture_output=True, text=True, cwd=ROOT, env=env, timeout=120,
                             check=False)
    assert missing.returncode != 0 and "Traceback" not in missing.stderr
    assert "ls /dev/input/js*" in missing.stderr, missing.stderr
