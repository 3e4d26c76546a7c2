"""Pre-laid CDR encoders for the high-rate streams (``joint_states``, ``clock``).

The generic ``cyclonedds`` serialiser builds a sample object per message (tens of
microseconds); these fill the few changing bytes of a template instead. The bytes are the
same as :class:`~agentsdk.ros2.msgs.JointState`'s serialisation (checked in the tests).
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from cyclonedds._clayer import ddspy_write  # type: ignore[import-not-found]
from cyclonedds.pub import DataWriter

from .msgs import Clock, Header, JointState, Time

__all__ = ["ClockEncoder", "FixedLayout", "JointStateEncoder", "RawDataWriter", "write_raw"]

_TIME = struct.Struct("<iI")


def _split(t: float) -> tuple[int, int]:
    ns = round(t * 1e9)
    return ns // 1_000_000_000, ns % 1_000_000_000


class RawDataWriter(DataWriter):  # type: ignore[type-arg]
    """A ``DataWriter`` that can also write pre-serialised CDR bytes (cyclonedds-python has no public call)."""

    def write_raw(self, data: bytes | bytearray) -> None:
        """Write ``data``: CDR with its 4-byte encapsulation header, padded to a multiple of 4."""
        ret = ddspy_write(self._ref, bytes(data))
        if ret < 0:
            raise OSError(f"DDS write failed ({ret})")


def write_raw(writer: Any, data: bytes | bytearray) -> None:
    """Write pre-serialised CDR bytes with a :class:`RawDataWriter`."""
    writer.write_raw(data)


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


class FixedLayout:
    """Bytes of a message whose shape never changes (names, lengths): only floats and stamps vary.

    ``build(floats, stamps)`` makes the message from a vector of float64 values and a list of
    ``Time``s. It is called once with unique sentinel values; their byte offsets in the
    serialisation are found, and :meth:`encode` then writes new values at those offsets. The
    result is byte for byte the message's own serialisation (the tests check it).
    """

    def __init__(self, build: Callable[[np.ndarray, list[Time]], Any], n_floats: int, n_stamps: int) -> None:
        rng = np.random.default_rng(0x5EED)
        floats = rng.uniform(1.0, 2.0, n_floats)
        stamps = [Time(int(s), int(ns)) for s, ns in zip(rng.integers(10**8, 2 * 10**9, n_stamps),
                                                           rng.integers(1, 10**9, n_stamps), strict=True)]
        data = build(floats, stamps).serialize()
        self.buffer = bytearray(data)
        self.buffer.extend(b"\0" * (-len(self.buffer) % 4))
        offsets = []
        for x in floats:
            off = _unique(data, struct.pack("<d", float(x)))
            if (off - 4) % 8:
                raise AssertionError("float64 field not 8-aligned")  # pragma: no cover - CDR aligns them
            offsets.append((off - 4) // 8)
        self._index = np.array(offsets, dtype=np.intp)
        self._doubles = np.frombuffer(self.buffer, dtype="<f8", offset=4, count=(len(self.buffer) - 4) // 8)
        self._stamps = [off for t in stamps for off in _all(data, _TIME.pack(t.sec, t.nanosec))]

    def encode(self, floats: np.ndarray, stamp: float) -> bytearray:
        """The bytes with these float values and every stamp set to ``stamp`` (buffer reused).

        ``build`` may use one stamp in several places (every transform of a TFMessage).
        """
        self._doubles[self._index] = floats
        sec, ns = _split(stamp)
        for off in self._stamps:
            _TIME.pack_into(self.buffer, off, sec, ns)
        return self.buffer


def _all(data: bytes, pattern: bytes) -> list[int]:
    out: list[int] = []
    off = data.find(pattern)
    while off >= 0:
        out.append(off)
        off = data.find(pattern, off + 1)
    return out


def _unique(data: bytes, pattern: bytes) -> int:
    off = data.find(pattern)
    if off < 0 or data.find(pattern, off + 1) >= 0:
        raise AssertionError("sentinel not found exactly once")  # pragma: no cover - 52 random bits each
    return off
