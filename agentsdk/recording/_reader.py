"""Reading a recording back: :class:`RunData` and :func:`read_recording`, including files cut short."""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from ..backend import ModeCode
from ..errors import ConfigurationError
from ._cdr import CdrReader, FixedLayout, command_layout, joint_state_layout
from ._channels import (
    CDR2_FORMAT,
    FORMAT,
    JOINT_COMMANDS,
    JOINT_STATES,
    JSON_FORMAT,
    METADATA_NAME,
    NS_PER_S,
    ROS2_FORMAT,
    SAFETY_EVENTS,
    TRANSITIONS,
)
from ._images import ImageSeries
from ._sensors import SensorSeries, SensorTrack, tracks_from_metadata

log = logging.getLogger("agentsdk.recording")


# ------------------------------------------------------------------ data
@dataclass
class RunData:
    """A recorded run as arrays (joint columns in ``names`` order; times in ns of robot time).

    .. attribute:: truncated
       :type: bool

       True when the file was cut short (the recording process was killed): read up to its last
       complete chunk.

    .. attribute:: sensors
       :type: dict[str, SensorSeries]

       The recorded sensors by name (``/sensors/<name>`` topics): header stamps and values in the
       layout of ``robot.sensors.values(name)``; empty for a robot without sensors.

    .. attribute:: images
       :type: dict[str, ImageSeries]

       The recorded camera frames by camera name: header stamps and the compressed bytes
       (``ImageSeries.frame(i)`` decodes one).

    .. attribute:: cmd_acceleration
       :type: numpy.ndarray | None

       The setpoint's desired acceleration of every command row (what the servo law's
       inverse-dynamics term fed forward; 0 where nothing did); ``None`` for recordings
       written before the commands carried it (formats ``agentsdk-recording/1`` and ``/2``).
    """

    names: tuple[str, ...]
    period: float
    metadata: dict[str, str]
    state_time: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    cmd_time: np.ndarray
    cmd_position: np.ndarray
    cmd_velocity: np.ndarray
    cmd_effort: np.ndarray
    cmd_kp: np.ndarray
    cmd_kd: np.ndarray
    cmd_enabled: np.ndarray
    cmd_mode: np.ndarray
    cmd_target: np.ndarray
    events: list[dict[str, Any]] = field(default_factory=list)
    transitions: list[dict[str, Any]] = field(default_factory=list)
    # documented in the class docstring (Sphinx reads field comments only from the package __init__)
    truncated: bool = False
    sensors: dict[str, SensorSeries] = field(default_factory=dict)
    images: dict[str, ImageSeries] = field(default_factory=dict)
    cmd_acceleration: np.ndarray | None = None

    @property
    def duration(self) -> float:
        """Robot time of the last joint state (s)."""
        return float(self.state_time[-1]) / NS_PER_S if len(self.state_time) else 0.0

    @property
    def robot(self) -> str:
        """The robot name stored in the recording's metadata."""
        return self.metadata.get("robot", "")

    @property
    def backend(self) -> str:
        """The backend name stored in the recording's metadata."""
        return self.metadata.get("backend", "")

    def command_index(self, t_ns: np.ndarray, *, applied_before: bool = True) -> np.ndarray:
        """Index of the setpoint in effect: the latest command stamped before ``t_ns``
        (``applied_before=True``: the setpoint that produced a state stamped ``t_ns``) or at/before it.
        """
        side: Literal["left", "right"] = "left" if applied_before else "right"
        return np.asarray(np.searchsorted(self.cmd_time, t_ns, side=side) - 1)

    def desired_position(self) -> np.ndarray:
        """Position setpoint behind every joint state (NaN where the joint was not position-servoed)."""
        out = np.full_like(self.position, np.nan)
        if not len(self.cmd_time):
            return out
        idx = self.command_index(self.state_time)
        ok = idx >= 0
        rows = idx[ok]
        des = self.cmd_position[rows]
        servo = (self.cmd_mode[rows] == ModeCode.POSITION) & self.cmd_enabled[rows]
        out[ok] = np.where(servo, des, np.nan)
        return out


def _empty(names: tuple[str, ...], period: float, metadata: dict[str, str]) -> RunData:
    n = len(names)
    z = np.zeros((0, n))
    return RunData(
        names,
        period,
        metadata,
        np.zeros(0, np.int64),
        z,
        z.copy(),
        z.copy(),
        np.zeros(0, np.int64),
        z.copy(),
        z.copy(),
        z.copy(),
        z.copy(),
        z.copy(),
        np.zeros((0, n), bool),
        np.zeros((0, n), np.int8),
        z.copy(),
    )



# ------------------------------------------------------------------ reading
class _Columns:
    """Preallocated arrays filled message by message (sized from the file's counts; grown only if a count was short)."""

    def __init__(self, rows: int, n: int, fields: dict[str, Any]) -> None:
        self.n = n
        self.k = 0
        self.time = np.empty(rows, np.int64)
        self.arrays = {f: np.empty((rows, n), dtype=dt) for f, dt in fields.items()}

    def reserve(self, extra: int) -> int:
        """Room for ``extra`` more rows; returns the first row index."""
        need = self.k + extra
        if need > len(self.time):
            cap = max(need, len(self.time) * 3 // 2 + 16)
            self.time = np.resize(self.time, cap)
            self.arrays = {f: np.resize(a, (cap, self.n)) for f, a in self.arrays.items()}
        start = self.k
        self.k = need
        return start

    def trimmed(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        k = self.k
        if k == len(self.time):
            return self.time, self.arrays
        return self.time[:k].copy(), {f: a[:k].copy() for f, a in self.arrays.items()}


_STATE_FIELDS: dict[str, Any] = {"position": float, "velocity": float, "effort": float}
_COMMAND_FIELDS: dict[str, Any] = {
    "position": float, "velocity": float, "effort": float, "kp": float, "kd": float, "target": float,
    "enabled": bool, "mode": np.int8,
}
#: the command fields of the current format: also the setpoint's acceleration
_COMMAND_FIELDS_ACC: dict[str, Any] = {**_COMMAND_FIELDS, "acceleration": float}


class _File:
    """One pass over an MCAP file, chunk by chunk (one decompressed chunk in memory at a time).

    A file whose writer was killed has no summary and may end inside a record:
    the pass stops after the last complete chunk, with ``truncated`` and the
    reason (the ``mcap recover`` idea).  Chunk CRCs are checked, so a damaged
    chunk ends the read instead of returning garbage.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.metadata: dict[str, str] = {}
        self.channels: dict[int, tuple[str, str]] = {}  # id -> (topic, schema name)
        self.truncated = True
        self.reason = ""

    def batches(self) -> Iterator[list[Message]]:
        schemas: dict[int, str] = {}
        self.truncated, self.reason = True, ""
        with open(self.path, "rb") as f:
            records = StreamReader(f, emit_chunks=True, record_size_limit=1 << 31).records
            while True:
                try:
                    rec = next(records)
                    inner = breakup_chunk(rec, validate_crc=True) if isinstance(rec, Chunk) else [rec]
                except StopIteration:
                    break
                except Exception as exc:  # any failure here is a damaged or cut tail: keep what came before
                    self.reason = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                    break
                msgs: list[Message] = []
                for r in inner:
                    if isinstance(r, Message):
                        msgs.append(r)
                    elif isinstance(r, Schema):
                        schemas[r.id] = r.name
                    elif isinstance(r, Channel):
                        self.channels[r.id] = (r.topic, schemas.get(r.schema_id, ""))
                    elif isinstance(r, Metadata) and r.name == METADATA_NAME:
                        self.metadata.update(r.metadata)
                if msgs:
                    yield msgs
                if isinstance(rec, Footer):
                    self.truncated = False

    def summary_counts(self) -> dict[str, int] | None:
        """Messages per topic from the summary, if the file has one."""
        try:
            with open(self.path, "rb") as f:
                summary = SeekingReader(f, record_size_limit=1 << 31).get_summary()
        except Exception:  # no (valid) summary: a truncated file
            return None
        if summary is None or summary.statistics is None:
            return None
        counts: dict[str, int] = {}
        for cid, ch in summary.channels.items():
            counts[ch.topic] = counts.get(ch.topic, 0) + summary.statistics.channel_message_counts.get(cid, 0)
        return counts

    def count(self) -> dict[str, int]:
        """Messages per topic: from the summary, or by a pass over the chunks (a truncated file)."""
        counts = self.summary_counts()
        if counts is not None:
            return counts
        counts = {}
        for msgs in self.batches():
            for m in msgs:
                ch = self.channels.get(m.channel_id)
                if ch is not None:
                    counts[ch[0]] = counts.get(ch[0], 0) + 1
        return counts


def read_recording(path: str | os.PathLike[str]) -> RunData:
    """Read an agentsdk MCAP recording; raises ConfigurationError for a missing or foreign file.

    Streams the file chunk by chunk into arrays allocated once from the file's
    message counts, so memory stays close to the arrays returned.  Reads the
    current (CDR) format, the CDR format without the setpoint's acceleration and the
    JSON format of earlier versions (``RunData.cmd_acceleration`` is then ``None``).  A recording
    cut short (the process was killed) is read up to its last complete chunk;
    ``RunData.truncated`` is then True.
    """
    p = Path(path)
    if not p.is_file():
        raise ConfigurationError(f"recording not found: {p}")
    f = _File(p)
    try:
        counts = f.count()
        if not f.metadata:  # read from the summary: the metadata comes with the first pass
            for _ in f.batches():
                if f.metadata:
                    break
        return _decode(f, counts)
    except OSError as exc:
        raise ConfigurationError(f"cannot read recording {p}: {exc.strerror or exc}") from exc


def _decode(f: _File, counts: dict[str, int]) -> RunData:
    p, md = f.path, f.metadata
    fmt = md.get("format")
    if fmt == ROS2_FORMAT:
        raise ConfigurationError(
            f"{p} is a --record-format ros2 recording: its commands carry no modes or gains, so it cannot be "
            "replayed or read with read_recording; read it with ROS 2 tools or the rosbags library"
        )
    if fmt not in (FORMAT, CDR2_FORMAT, JSON_FORMAT):
        if f.truncated and not md and not counts:
            raise ConfigurationError(f"cannot read recording {p}: {f.reason or 'no MCAP data'}")
        raise ConfigurationError(f"{p} is not an agentsdk recording (no '{METADATA_NAME}' metadata)")
    try:
        names = tuple(json.loads(md["joints"]))
        period = float(md["control_period"])
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigurationError(f"cannot read recording {p}: bad metadata ({exc})") from exc
    n = len(names)
    states = _Columns(counts.get(JOINT_STATES, 0), n, _STATE_FIELDS)
    accelerations = fmt == FORMAT
    commands = _Columns(counts.get(JOINT_COMMANDS, 0), n, _COMMAND_FIELDS_ACC if accelerations else _COMMAND_FIELDS)
    events: list[dict[str, Any]] = []
    transitions: list[dict[str, Any]] = []
    try:
        tracks = tracks_from_metadata(md["sensors"]) if md.get("sensors") else ()
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigurationError(f"cannot read recording {p}: bad sensors metadata ({exc})") from exc
    sensors = {t.topic: _SensorColumns(t, counts.get(t.topic, 0)) for t in tracks}
    try:
        cams = json.loads(md["cameras"]) if md.get("cameras") else []
        images = {f"/sensors/{c['name']}": ImageSeries(str(c["name"]), str(c["frame_id"]), md.get("image_format", ""),
                                                       np.zeros(0, np.int64), []) for c in cams}
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigurationError(f"cannot read recording {p}: bad cameras metadata ({exc})") from exc
    image_stamps: dict[str, list[int]] = {topic: [] for topic in images}
    dec = _JsonDecoder(names) if fmt == JSON_FORMAT else _CdrDecoder(names, acceleration=accelerations)
    try:
        for msgs in f.batches():
            by_topic: dict[str, list[Message]] = {}
            for m in msgs:
                ch = f.channels.get(m.channel_id)
                if ch is not None:
                    by_topic.setdefault(ch[0], []).append(m)
            for topic, group in by_topic.items():
                if topic == JOINT_STATES:
                    dec.states(group, states)
                elif topic == JOINT_COMMANDS:
                    dec.commands(group, commands)
                elif topic == SAFETY_EVENTS:
                    events.extend(dec.event(m) for m in group)
                elif topic == TRANSITIONS:
                    transitions.extend(dec.transition(m) for m in group)
                elif topic in sensors:
                    sensors[topic].add(group)
                elif topic in images:
                    for m in group:
                        r = CdrReader(m.data)
                        image_stamps[topic].append(r.header())
                        r.string()
                        n = r.u32()
                        images[topic].data.append(bytes(r.data[r.pos : r.pos + n]))
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        raise ConfigurationError(f"cannot read recording {p}: {type(exc).__name__}: {exc}") from exc
    if f.truncated:
        reason = f.reason or "no summary"
        log.warning("recording %s was not finished (%s); read up to its last complete chunk", p, reason)
    out = _empty(names, period, md)
    out.truncated = f.truncated
    out.events, out.transitions = events, transitions
    st_t, st = states.trimmed()
    out.state_time, out.position, out.velocity, out.effort = st_t, st["position"], st["velocity"], st["effort"]
    cm_t, cm = commands.trimmed()
    out.cmd_time = cm_t
    out.cmd_position, out.cmd_velocity, out.cmd_effort = cm["position"], cm["velocity"], cm["effort"]
    out.cmd_kp, out.cmd_kd, out.cmd_target = cm["kp"], cm["kd"], cm["target"]
    out.cmd_enabled, out.cmd_mode = cm["enabled"], cm["mode"]
    out.cmd_acceleration = cm.get("acceleration")
    out.sensors = {c.track.name: c.series() for c in sensors.values()}
    for topic, series in images.items():
        series.time = np.array(image_stamps[topic], np.int64)
    out.images = {s.name: s for s in images.values()}
    return out


class _SensorColumns:
    """One sensor's stamps and values, preallocated from the file's message count."""

    def __init__(self, track: SensorTrack, rows: int) -> None:
        self.track = track
        self.layout = track.layout()
        self.time = np.empty(rows, np.int64)
        self.values = np.empty((rows, track.size))
        self.k = 0

    def add(self, group: list[Message]) -> None:
        lay = self.layout
        group = [m for m in group if len(m.data) == lay.size]
        if not group:
            return
        block = np.frombuffer(b"".join(m.data for m in group), dtype=np.uint8).reshape(len(group), lay.size)
        ok = lay.matches(block)
        block = block[ok]
        n = len(block)
        if self.k + n > len(self.time):  # a count was short (a truncated file's counting pass is exact)
            cap = max(self.k + n, len(self.time) * 3 // 2 + 16)
            self.time = np.resize(self.time, cap)
            self.values = np.resize(self.values, (cap, self.track.size))
        sl = slice(self.k, self.k + n)
        self.time[sl] = lay.column(block, "sec")[:, 0].astype(np.int64) * NS_PER_S + lay.column(block, "nanosec")[:, 0]
        self.values[sl] = self.track.values(lay, block)
        self.k += n

    def series(self) -> SensorSeries:
        t = self.track
        k = self.k
        if k == len(self.time):
            time, values = self.time, self.values
        else:
            time, values = self.time[:k].copy(), self.values[:k].copy()
        return SensorSeries(t.name, t.kind, t.msg_type, t.frame_id, t.joint, time, values)


class _CdrDecoder:
    """The CDR messages of the current format; whole chunks at once when they have the expected layout."""

    def __init__(self, names: tuple[str, ...], *, acceleration: bool = True) -> None:
        self.names = names
        self.index = {nm: i for i, nm in enumerate(names)}
        self.state = joint_state_layout(names)
        self.command = command_layout(names, acceleration=acceleration)
        self.command_fields = _COMMAND_FIELDS_ACC if acceleration else _COMMAND_FIELDS
        # the message's field order (the layout's float sequences, then mode and enabled)
        self.command_order = (*(f for f in self.command.fields if f not in ("sec", "nanosec", "mode", "enabled")),
                              "mode", "enabled")

    def _block(self, group: list[Message], lay: FixedLayout) -> np.ndarray | None:
        if any(len(m.data) != lay.size for m in group):
            return None
        block = np.frombuffer(b"".join(m.data for m in group), dtype=np.uint8).reshape(len(group), lay.size)
        return block if bool(lay.matches(block).all()) else None

    def states(self, group: list[Message], out: _Columns) -> None:
        block = self._block(group, self.state)
        if block is None:
            for m in group:
                self._one(m, out, ("position", "velocity", "effort"))
            return
        i = out.reserve(len(group))
        out.time[i : i + len(group)] = [m.log_time for m in group]
        for fld in _STATE_FIELDS:
            out.arrays[fld][i : i + len(group)] = self.state.column(block, fld)

    def commands(self, group: list[Message], out: _Columns) -> None:
        block = self._block(group, self.command)
        if block is None:
            for m in group:
                self._one(m, out, self.command_order)
            return
        i = out.reserve(len(group))
        out.time[i : i + len(group)] = [m.log_time for m in group]
        for fld in self.command_fields:
            col = self.command.column(block, fld)
            out.arrays[fld][i : i + len(group)] = col.view(bool) if fld == "enabled" else col

    def _one(self, m: Message, out: _Columns, fields: tuple[str, ...]) -> None:
        """A message whose names differ from the recording's (order, subset): decoded field by field."""
        r = CdrReader(m.data)
        r.header()
        names = [r.string() for _ in range(r.u32())]
        cols = np.array([self.index.get(nm, -1) for nm in names], dtype=np.intp)
        ok = cols >= 0
        i = out.reserve(1)
        out.time[i] = m.log_time
        layout = self.command.fields
        for fld in fields:
            count = r.u32()
            dt = np.dtype(layout[fld][2]) if fld in layout else np.dtype("<f8")
            if count:
                r.pos += -r.pos % dt.itemsize
            values = np.frombuffer(r.data, dtype=dt, count=count, offset=r.pos)
            r.pos += count * dt.itemsize
            row = out.arrays[fld][i]
            row[...] = 0 if fld in ("mode", "enabled") else np.nan
            if count == len(cols):
                row[cols[ok]] = values[ok]

    def event(self, m: Message) -> dict[str, Any]:
        r = CdrReader(m.data)
        r.header()
        kind, joint, detail = r.string(), r.string(), r.string()
        return {"time": m.log_time / NS_PER_S, "kind": kind, "joint": joint or None, "detail": detail}

    def transition(self, m: Message) -> dict[str, Any]:
        r = CdrReader(m.data)
        r.header()
        machine, source, target, event, note = (r.string() for _ in range(5))
        out: dict[str, Any] = {
            "time": m.log_time / NS_PER_S, "machine": machine, "source": source or None,
            "target": target or None, "event": event or None, "note": note,
        }
        if r.pos < len(r.data):  # since the state-machine introspection: configuration and duration
            out["configuration"] = r.string()
            duration = r.f64()
            out["duration"] = None if math.isnan(duration) else duration
        return out


class _JsonDecoder:
    """The JSON messages of recordings written by earlier versions (format ``agentsdk-recording/1``)."""

    def __init__(self, names: tuple[str, ...]) -> None:
        self.n = len(names)

    def states(self, group: list[Message], out: _Columns) -> None:
        for m in group:
            msg = json.loads(m.data)
            i = out.reserve(1)
            out.time[i] = m.log_time
            for fld in _STATE_FIELDS:
                out.arrays[fld][i] = np.array(msg[fld], dtype=float)  # JSON null (a NaN) -> nan

    def commands(self, group: list[Message], out: _Columns) -> None:
        for m in group:
            msg = json.loads(m.data)
            i = out.reserve(1)
            out.time[i] = m.log_time
            for fld in ("position", "velocity", "effort", "kp", "kd", "target"):
                out.arrays[fld][i] = np.array(msg[fld], dtype=float)
            out.arrays["enabled"][i] = msg["enabled"]
            out.arrays["mode"][i] = [ModeCode.of(x) for x in msg["mode"]]

    def _side(self, m: Message) -> dict[str, Any]:
        msg = json.loads(m.data)
        msg.pop("header", None)
        return {"time": m.log_time / NS_PER_S, **msg}

    event = transition = _side
