"""Jogging from a gamepad through the Linux joystick API: ``agentsdk teleop --gamepad [/dev/input/js0]``.

The kernel's joystick interface (``/dev/input/jsN``, any USB or Bluetooth pad the kernel drives; no
extra library) delivers 8-byte events: ``u32`` time (ms), ``s16`` value, ``u8`` type (1 button,
2 axis, | 0x80 for the initial state sent on open), ``u8`` number. :func:`parse_events` decodes them,
:class:`GamepadState` keeps the latest value of every axis and button, and :class:`GamepadMapping`
turns a state into an end-effector jog direction:

* **dead-man**: nothing moves unless the dead-man button (default 4: LB on an Xbox-style pad) is
  held; releasing it (or centring the sticks) cancels the running step: the robot decelerates to rest
  and holds (release = hold);
* **sticks**: left stick up/down: ±x, left/right: ±y; right stick up/down: ±z (root frame); values
  inside ``deadzone`` count as zero and the rest scales the step (full deflection: one
  :data:`agentsdk.jog.JOG_STEP` per step).

:func:`jog_with_gamepad` runs a session: every ``period`` it starts a step in the current direction
unless one runs (no queue), and ends when the device goes away (unplugged: the robot holds).
"""

from __future__ import annotations

import asyncio
import glob
import os
import struct
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import numpy as np

from .errors import ConfigurationError, InvalidValueError
from .jog import JOG_STEP, Jogger, StepReport

if TYPE_CHECKING:
    from .robot import Robot

__all__ = ["EVENT_SIZE", "GamepadMapping", "GamepadState", "JsEvent", "encode_event", "find_gamepad",
           "jog_with_gamepad", "parse_events"]

_EVENT = struct.Struct("<IhBB")
#: bytes per joystick event
EVENT_SIZE = _EVENT.size
_BUTTON, _AXIS, _INIT = 0x01, 0x02, 0x80
_AXIS_MAX = 32767.0


@dataclass(frozen=True)
class JsEvent:
    """One joystick event: ``kind`` "button" or "axis", its ``number``, ``value`` (axes in [-1, 1])."""

    time_ms: int
    kind: str
    number: int
    value: float
    initial: bool


def parse_events(data: bytes) -> tuple[list[JsEvent], bytes]:
    """Decode whole events from ``data``; returns them and the bytes of an incomplete trailing event."""
    n = len(data) // EVENT_SIZE
    events = []
    for k in range(n):
        t, value, kind, number = _EVENT.unpack_from(data, k * EVENT_SIZE)
        base = kind & ~_INIT
        if base == _BUTTON:
            events.append(JsEvent(t, "button", number, float(value != 0), bool(kind & _INIT)))
        elif base == _AXIS:
            events.append(JsEvent(t, "axis", number, max(-1.0, value / _AXIS_MAX), bool(kind & _INIT)))
    return events, data[n * EVENT_SIZE:]


def encode_event(kind: str, number: int, value: float, time_ms: int = 0, initial: bool = False) -> bytes:
    """The bytes the kernel sends for an event (for tests and fake devices)."""
    code = (_BUTTON if kind == "button" else _AXIS) | (_INIT if initial else 0)
    raw = int(value != 0) if kind == "button" else round(max(-1.0, min(1.0, value)) * _AXIS_MAX)
    return _EVENT.pack(time_ms & 0xFFFFFFFF, raw, code, number)


@dataclass
class GamepadState:
    """The latest value of every axis and button seen."""

    axes: dict[int, float] = field(default_factory=dict)
    buttons: dict[int, bool] = field(default_factory=dict)

    def update(self, event: JsEvent) -> None:
        """Apply one event."""
        if event.kind == "axis":
            self.axes[event.number] = event.value
        else:
            self.buttons[event.number] = event.value != 0


@dataclass(frozen=True)
class GamepadMapping:
    """Which axes and button jog (defaults: an Xbox-style pad on the Linux xpad driver)."""

    deadman_button: int = 4
    #: (axis number, sign) for x, y, z: pushing a stick up reads negative on Linux
    x_axis: tuple[int, float] = (1, -1.0)
    y_axis: tuple[int, float] = (0, -1.0)
    z_axis: tuple[int, float] = (4, -1.0)
    deadzone: float = 0.2

    def __post_init__(self) -> None:
        if not 0.0 <= self.deadzone < 1.0:
            raise InvalidValueError(f"deadzone must be in [0, 1), got {self.deadzone!r}")

    def direction(self, state: GamepadState) -> np.ndarray:
        """The jog direction (3,), each component in [-1, 1]; zero unless the dead-man button is held."""
        out = np.zeros(3)
        if not state.buttons.get(self.deadman_button, False):
            return out
        for k, (axis, sign) in enumerate((self.x_axis, self.y_axis, self.z_axis)):
            v = sign * state.axes.get(axis, 0.0)
            if abs(v) > self.deadzone:  # rescale so motion starts from 0 at the deadzone's edge
                out[k] = np.sign(v) * (abs(v) - self.deadzone) / (1.0 - self.deadzone)
        return out


def find_gamepad() -> Path | None:
    """The first joystick device (``/dev/input/js*``), or None."""
    found = sorted(glob.glob("/dev/input/js*"))
    return Path(found[0]) if found else None


def _open(device: str | Path) -> int:
    try:
        return os.open(device, os.O_RDONLY | os.O_NONBLOCK)
    except PermissionError as exc:
        raise ConfigurationError(f"cannot read the gamepad {device}: permission denied; add yourself to the "
                                 "'input' group (sudo usermod -aG input $USER, then log in again)") from exc
    except OSError as exc:
        raise ConfigurationError(f"cannot open the gamepad {device}: {exc.strerror or exc}; check that it is "
                                 "plugged in (ls /dev/input/js*)") from exc


async def jog_with_gamepad(
    robot: Robot,
    device: str | Path | int,
    *,
    mapping: GamepadMapping | None = None,
    period: float = 0.05,
    out: TextIO | None = None,
) -> int:
    """Jog ``robot`` from a joystick device (a path, or an open file descriptor that is then closed).

    Runs until the device goes away or the task is cancelled; the robot holds afterwards. Returns the
    steps completed.
    """
    mapping = mapping or GamepadMapping()
    out = sys.stdout if out is None else out
    if not period > 0:
        raise InvalidValueError(f"period must be > 0 s, got {period!r}")
    fd = device if isinstance(device, int) else _open(device)
    jogger = Jogger(robot)
    state = GamepadState()
    loop = asyncio.get_running_loop()
    gone = asyncio.Event()
    changed = asyncio.Event()
    pending = b""

    def _readable() -> None:
        nonlocal pending
        try:
            data = os.read(fd, EVENT_SIZE * 64)
        except BlockingIOError:
            return
        except OSError:  # ENODEV: unplugged
            data = b""
        if not data:
            loop.remove_reader(fd)
            gone.set()
            return
        events, pending = parse_events(pending + data)
        for event in events:
            state.update(event)
        changed.set()

    report = StepReport(out)

    loop.add_reader(fd, _readable)
    try:
        while not gone.is_set():
            direction = mapping.direction(state)
            if not direction.any():
                jogger.release()  # dead-man released or sticks centred: hold
            elif not jogger.busy:
                jogger.submit(lambda d=direction: jogger.cartesian(JOG_STEP * d), report)  # type: ignore[misc]
            changed.clear()
            try:  # the next event, or the next period (a held stick keeps stepping)
                async with asyncio.timeout(period):
                    await changed.wait()
            except TimeoutError:
                pass
        print("the gamepad went away; the robot holds", file=out, flush=True)
    finally:
        loop.remove_reader(fd)
        os.close(fd)
        await jogger.aclose()
    return report.steps
