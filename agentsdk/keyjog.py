"""Jogging from the terminal's keyboard: ``agentsdk teleop --keys --robot ur5``.

The terminal is switched to non-canonical, no-echo input (each key press arrives at once, as over
``ssh -t``) for the session and restored on exit, however the session ends (``q``, Ctrl-D, Ctrl-C,
an error). Keys are read without blocking the event loop (``loop.add_reader``) and mapped by
:func:`agentsdk.jog.key_action` (I/K, J/L, U/O: ±x, ±y, ±z of the end effector in 1 cm steps;
1-9 and Shift+1-9: joints by ±0.05 rad). One press is one step; a press while a step runs is dropped
(a held key's auto-repeat never piles up steps); **space** stops the running step at once (release =
hold); after each step one line tells where the end effector is.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import sys
from collections.abc import Iterator
from typing import TYPE_CHECKING, TextIO

from .errors import ConfigurationError
from .jog import CARTESIAN_KEYS, JOG_STEP, JOINT_STEP, Jogger, StepReport, key_action

if TYPE_CHECKING:
    from .robot import Robot

__all__ = ["QUIT_KEYS", "jog_with_keys", "split_keys", "terminal_mode"]

#: keys that end the session: q, Esc, Ctrl-D
QUIT_KEYS = frozenset({"q", "Q", "\x1b", "\x04"})


_ESCAPE = re.compile(r"\x1b(\[[0-?]*[ -/]*[@-~]|O.)")


def split_keys(text: str) -> list[str]:
    """The key presses in what the terminal sent: escape sequences (arrows, function keys) dropped, a lone Esc kept."""
    return list(_ESCAPE.sub("", text))


@contextlib.contextmanager
def terminal_mode(fd: int) -> Iterator[None]:
    """Key-at-a-time input without echo on terminal ``fd`` (signals such as Ctrl-C still work), restored on exit."""
    import termios
    import tty

    if not os.isatty(fd):
        raise ConfigurationError("--keys reads the keyboard of a terminal, but stdin is not one; run it in a "
                                 "terminal (over ssh: ssh -t), or jog from the web page (agentsdk run --web)")
    saved = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd, termios.TCSANOW)
        yield
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


def _help(jogger: Jogger) -> str:
    keys = {(axis, sign): key.upper() for key, (axis, sign) in CARTESIAN_KEYS.items()}
    n = min(len(jogger.robot.joints), 9)
    return (f"jog {jogger.robot.name} ({jogger.link}): {keys[0, 1.0]}/{keys[0, -1.0]} x, {keys[1, 1.0]}/"
            f"{keys[1, -1.0]} y, {keys[2, 1.0]}/{keys[2, -1.0]} z ({JOG_STEP * 100:g} cm); 1-{n} joints "
            f"(+{JOINT_STEP:g} rad, Shift: back); space stops; q quits")


def _where(jogger: Jogger) -> str:
    p = jogger.robot.kinematics.fk(jogger.link).position
    return f"{jogger.link} at x={p[0]:+.4f} y={p[1]:+.4f} z={p[2]:+.4f} m"


async def jog_with_keys(robot: Robot, fd: int | None = None, out: TextIO | None = None) -> int:
    """Jog ``robot`` from the keys typed on terminal ``fd`` (default stdin) until ``q``; returns the steps done."""
    fd = sys.stdin.fileno() if fd is None else fd
    out = sys.stdout if out is None else out
    jogger = Jogger(robot)
    loop = asyncio.get_running_loop()
    keys: asyncio.Queue[str] = asyncio.Queue()

    def _readable() -> None:
        try:
            data = os.read(fd, 64)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:  # the terminal went away (ssh dropped): quit, the robot holds
            loop.remove_reader(fd)
            keys.put_nowait("\x04")
            return
        for key in split_keys(data.decode("utf-8", "replace")):
            keys.put_nowait(key)

    report = StepReport(out, lambda: _where(jogger))

    with terminal_mode(fd):
        print(_help(jogger), file=out, flush=True)
        print(_where(jogger), file=out, flush=True)
        loop.add_reader(fd, _readable)
        try:
            while True:
                key = await keys.get()
                if key in QUIT_KEYS:
                    break
                if key == " ":
                    jogger.release()
                    continue
                action = key_action(key, len(robot.joints))
                if action is None:
                    continue
                jogger.submit(lambda a=action: jogger.run(a), report)  # type: ignore[misc]
        finally:
            loop.remove_reader(fd)
            await jogger.aclose()  # release = hold
    return report.steps
