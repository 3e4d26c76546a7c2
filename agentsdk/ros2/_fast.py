"""Pre-laid CDR encoders for the high-rate streams (``joint_states``, ``clock``).

The generic ``cyclonedds`` serialiser builds a sample object per message (tens of
microseconds); these fill the few changing bytes of a template instead. The bytes are the
same as :class:`~agentsdk.ros2.msgs.JointState`'s serialisation (checked in the tests).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

import numpy as np
from cyclonedds._clayer import ddspy_write  # type: ignore[import-not-found]

from .msgs import Clock, Header, JointState, Time

__all__ = ["ClockEncoder", "JointStateEncoder", "write_raw"]

_TIME = struct.Struct("<iI")


def _split(t: float) -> tuple[int, int]:
    ns = round(t * 1e9)
    return ns // 1_000_000_000, ns % 1_000_000_000


def write_raw(writer: object, data: bytes | bytearray) -> None:
    """Write pre-serialised CDR bytes (encapsulation header included) to a ``DataWriter``."""
    ret = ddspy_write(writer._ref, bytes(data))  # type: ignore[attr-defined]
    if ret < 0:
        raise OSError(f"DDS write failed ({ret})")


class JointStateEncoder:
    """``sensor_msgs/JointState`` bytes for fixed joint names: :meth:`encode` fills stamp and arrays."""

    def __init__(self, names: Sequence[str], frame_id: str = "") -> None:
        n = len(names)
        template = JointState(Header(Time(), frame_id), list(names), [0.0] * n, [0.0] * n, [0.0] * n).serialize()
        # offsets (from the payload start, after the 4-byte encapsulation header) follow CDR alignment
        off = 8
        off += 4 + len(frame_id.encode()) + 1
        off = (off + 3) & ~3
        off += 4
        for name in names:
            off = (off + 3) & ~3
            off += 4 + len(name.encode()) + 1
        self._arrays: list[np.ndarray] = []
        self.buffer = bytearray(template)
        self.buffer.extend(b"\0" * (-len(self.buffer) % 4))
        for _ in range(3):
            off = (off + 3) & ~3
            off += 4
            if n:
                off = (off + 7) & ~7
            self._arrays.append(np.frombuffer(self.buffer, dtype="<f8", count=n, offset=4 + off))
            off += 8 * n
        if 4 + off != len(template):
            raise AssertionError("JointState layout mismatch")  # pragma: no cover - guarded by the tests

    def encode(self, stamp: float, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray) -> bytearray:
        """The message bytes for these values (the returned buffer is reused by the next call)."""
        _TIME.pack_into(self.buffer, 4, *_split(stamp))
        p, v, e = self._arrays
        p[...] = position
        v[...] = velocity
        e[...] = effort
        return self.buffer


class ClockEncoder:
    """``rosgraph_msgs/Clock`` bytes."""

    def __init__(self) -> None:
        self.buffer = bytearray(Clock(Time()).serialize())

    def encode(self, stamp: float) -> bytearray:
        """The message bytes for ``stamp`` (the buffer is reused by the next call)."""
        _TIME.pack_into(self.buffer, 4, *_split(stamp))
        return self.buffer
