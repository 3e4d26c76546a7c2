"""Record runs to MCAP, read them back, and replay their commands into a fresh connection.

    agentsdk run behaviors/wave.py --record run.mcap        # record
    agentsdk replay run.mcap --backend mujoco               # replay + divergence report

Channels (all ``jsonschema`` schemas, ``json`` message encoding)
----------------------------------------------------------------

=========================  ==============================  ==================================================
topic                      schema name                     content
=========================  ==============================  ==================================================
``/joint_states``          ``sensor_msgs/msg/JointState``  measured state after every control tick (or
                                                           decimated to ``record_rate`` Hz): ``header.stamp``
                                                           {sec, nanosec}, ``name[]``, ``position[]``,
                                                           ``velocity[]``, ``effort[]``
``/joint_commands``        ``agentsdk/msg/JointCommand``   the servo setpoint actually written to the backend
                                                           (after the safety layer): the JointState fields
                                                           (desired position/velocity/effort) plus ``mode[]``
                                                           ("position"/"velocity"/"effort"), ``enabled[]``
                                                           ``kp[]``, ``kd[]`` and ``target[]`` (the last
                                                           commanded value before ramping)
``/safety/events``         ``agentsdk/msg/SafetyEvent``    ``kind``, ``joint`` (or null), ``detail``
``/behavior/transitions``  ``agentsdk/msg/Transition``     state-machine history records: ``machine``,
                                                           ``source``, ``target``, ``event``, ``note``
=========================  ==============================  ==================================================

A metadata record named ``agentsdk`` holds what replay needs: the robot (name,
or absolute path of its robot.yaml/URDF), the backend and its options, the
control period, the joint names, the validated robot.yaml content and the
behavior script.

Why JSON and not ROS 2 CDR: Foxglove decodes ``json`` channels natively from
their JSON schema (plots of ``/joint_states.position[0]`` and
``/joint_commands.position[0]`` work out of the box, with the same field paths
as a ROS bag, since the messages are shaped like ``sensor_msgs/JointState``),
``mcap cat --json`` prints them, every channel uses one code path, and the SDK
needs no extra dependency.  The price: ``ros2 bag play`` cannot republish JSON
channels; a ROS user who needs that can convert ``/joint_states`` to CDR with
``mcap-ros2-support`` offline.  The command channel has no ROS message type
anyway (``mode[]``, gains).

Timing
------
Log time (and ``header.stamp``) is robot clock time in nanoseconds: simulated
time in lockstep, time since connect in real time.  A ``/joint_states``
message stamped ``t`` is the state measured at the end of the tick that
started at ``t - period``; the ``/joint_commands`` message applied during that
tick is stamped ``t - period`` (when it was written).

``/joint_commands`` is change-based: a message is written at every tick whose
setpoint differs from the previous tick's, at the tick just before each change
(so a line plot shows holds as flat segments) and at the first and last tick
of every buffer block; sample-and-hold reconstructs the setpoint of every tick
exactly.  ``record_rate`` decimates ``/joint_states`` only: commands are never
decimated, so a decimated recording still replays exactly.

Cost on the control loop
------------------------
The recorder's tick hook copies a few numpy rows into preallocated blocks of
``BLOCK_TICKS`` ticks (about 3 µs per tick for a 3-joint arm); no logging and
no encoding per tick.  When a block is full the rows to keep are selected
(vectorized, well under a millisecond) and queued; :meth:`Recorder.finish`
encodes and writes them after the run.  Only a long run whose queue exceeds
``DRAIN_AFTER_TICKS`` ticks (about 2 minutes at 500 Hz) has the tick hook
write a few queued messages per tick, which bounds memory at a steady cost of
tens of microseconds per tick.  Writing whole blocks at once in the loop (or
in a thread: the GIL hand-offs stalled the loop for up to a second under load)
would pause the control loop long enough to trip the safety layer's stall
watchdog.  Call :meth:`Recorder.finish` after the robot is closed, as the CLI
does, so that the final write cannot stall a running control loop.

State-machine transitions
-------------------------
:mod:`agentsdk.statemachine` has no public transition hook yet; the recorder
listens by wrapping ``StateMachine._sm_record`` (the single place every
history record is made) while at least one recorder is attached, and keeps the
records of machines whose ``robot`` is the recorded robot.

Replay
------
:func:`replay` connects a fresh robot (lockstep for simulators), and an
updater writes the recorded setpoint (position, velocity, effort, kp, kd,
enabled, mode) into the robot's setpoint (a COMMAND-phase tick hook) at the same tick it was
applied in the recording.  The safety layer filters it again, which leaves it
unchanged (the recorded setpoint is already limited and ramped); the command
watchdog is turned off because no commands are sent.  Lockstep MuJoCo is
deterministic, so a MuJoCo recording replays into MuJoCo bit for bit.
"""

from __future__ import annotations

import asyncio
import datetime as _dt
import heapq
import json
import logging
import math
import os
import re
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
from mcap.records import Channel, Chunk, Footer, Message, Metadata
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from .backend import ModeCode, SetpointView
from .errors import ConfigurationError
from .loop import Phase, Setpoint, StateView
from .mcap_formats import FRAME_TRANSFORMS_SCHEMA, ROS2_MSGDEFS, STRING_SCHEMA, Cdr, TfLayout, tf_batch
from .statemachine import StateMachine
from .types import MODES

if TYPE_CHECKING:

    from .robot import Robot

__all__ = [
    "BLOCK_TICKS",
    "FORMAT",
    "RECORD_FORMATS",
    "TF_RATE",
    "TOPICS",
    "Recorder",
    "ReplayResult",
    "RunData",
    "read_recording",
    "replay",
    "robot_spec_for_metadata",
]

log = logging.getLogger("agentsdk.recording")

#: OBSERVE-phase order of the recorder: before every other observer (it sees the setpoint as written)
RECORDER_ORDER = -1000

FORMAT = "agentsdk-recording/1"
METADATA_NAME = "agentsdk"
BLOCK_TICKS = 4096
#: unwritten ticks kept in memory before the tick hook starts writing a few messages per tick
DRAIN_AFTER_TICKS = 16 * BLOCK_TICKS
#: messages written per tick while draining (more than a tick produces, so the backlog shrinks)
_DRAIN_PER_TICK = 4
#: MCAP chunk size: small enough that compressing one chunk is a short pause
_CHUNK_BYTES = 256 * 1024
#: wall-clock seconds between writes to the file: a killed run loses at most about this much
FLUSH_INTERVAL = 0.5
#: longest the writer task encodes before yielding to the event loop (s)
_SLICE_S = 0.001
#: default rate of /tf (Hz of robot time): smooth in Foxglove, cheap for a 30-link robot
TF_RATE = 50.0
#: ``--record-format`` choices
RECORD_FORMATS = ("mcap", "ros2")

JOINT_STATES = "/joint_states"
JOINT_COMMANDS = "/joint_commands"
SAFETY_EVENTS = "/safety/events"
TRANSITIONS = "/behavior/transitions"
TF = "/tf"
ROBOT_DESCRIPTION = "/robot_description"
TOPICS = (JOINT_STATES, JOINT_COMMANDS, SAFETY_EVENTS, TRANSITIONS, TF, ROBOT_DESCRIPTION)
_ROS2_TOPICS = {
    JOINT_STATES: "sensor_msgs/msg/JointState",
    JOINT_COMMANDS: "sensor_msgs/msg/JointState",
    TF: "tf2_msgs/msg/TFMessage",
    ROBOT_DESCRIPTION: "std_msgs/msg/String",
}


def _qos(durability: int) -> str:
    # rosbag2's offered_qos_profiles (a YAML list): reliable, keep-last; durability 1 = transient local
    return (
        "- history: 1\n  depth: 1\n  reliability: 1\n  durability: "
        f"{durability}\n  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n"
        "  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n  liveliness: 1\n"
        "  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n"
        "  avoid_ros_namespace_conventions: false"
    )


_QOS_DEFAULT = _qos(2)
_QOS_LATCHED = _qos(1)  # like robot_state_publisher's /robot_description

_NS = 1_000_000_000

# ------------------------------------------------------------------ schemas
_TIME = {
    "type": "object",
    "title": "builtin_interfaces/msg/Time",
    "properties": {
        "sec": {"type": "integer", "description": "seconds of robot time"},
        "nanosec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}
_HEADER = {
    "type": "object",
    "title": "std_msgs/msg/Header",
    "properties": {"stamp": _TIME, "frame_id": {"type": "string"}},
}
_NUMBERS = {"type": "array", "items": {"type": "number"}}
_STRINGS = {"type": "array", "items": {"type": "string"}}

JOINT_STATE_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "sensor_msgs/msg/JointState",
    "description": "Measured joint state (sensor_msgs/JointState layout); robot clock time.",
    "type": "object",
    "properties": {
        "header": _HEADER,
        "name": _STRINGS,
        "position": {**_NUMBERS, "description": "rad or m"},
        "velocity": {**_NUMBERS, "description": "rad/s or m/s"},
        "effort": {**_NUMBERS, "description": "N·m or N"},
    },
}
JOINT_COMMAND_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "agentsdk/msg/JointCommand",
    "description": (
        "Servo setpoint written to the backend (after safety filtering), sensor_msgs/JointState layout "
        "plus mode and gains: effort = kp*(position - q) + kd*(velocity - v) + effort, zero if not enabled."
    ),
    "type": "object",
    "properties": {
        "header": _HEADER,
        "name": _STRINGS,
        "position": {**_NUMBERS, "description": "desired position, rad or m"},
        "velocity": {**_NUMBERS, "description": "desired velocity / feed-forward, rad/s or m/s"},
        "effort": {**_NUMBERS, "description": "effort feed-forward, N·m or N"},
        "mode": {"type": "array", "items": {"type": "string", "enum": list(MODES)}},
        "enabled": {"type": "array", "items": {"type": "boolean"}},
        "kp": _NUMBERS,
        "kd": _NUMBERS,
        "target": {**_NUMBERS, "description": "last commanded value (per mode) before ramping"},
    },
}
SAFETY_EVENT_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "agentsdk/msg/SafetyEvent",
    "type": "object",
    "properties": {
        "header": _HEADER,
        "kind": {"type": "string", "description": "clamp, watchdog, estop, reset, enable, fault, stall, ..."},
        "joint": {"type": ["string", "null"]},
        "detail": {"type": "string"},
    },
}
TRANSITION_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "agentsdk/msg/Transition",
    "description": "A state-machine history record; target is null for events that caused no transition.",
    "type": "object",
    "properties": {
        "header": _HEADER,
        "machine": {"type": "string"},
        "source": {"type": ["string", "null"]},
        "target": {"type": ["string", "null"]},
        "event": {"type": ["string", "null"]},
        "note": {"type": "string"},
    },
}
_SCHEMAS = {
    JOINT_STATES: JOINT_STATE_SCHEMA,
    JOINT_COMMANDS: JOINT_COMMAND_SCHEMA,
    SAFETY_EVENTS: SAFETY_EVENT_SCHEMA,
    TRANSITIONS: TRANSITION_SCHEMA,
    TF: FRAME_TRANSFORMS_SCHEMA,
    ROBOT_DESCRIPTION: STRING_SCHEMA,
}


def _ns(t: float) -> int:
    return round(t * _NS)


def _header(ns: int) -> dict[str, Any]:
    sec, nsec = divmod(ns, _NS)
    return {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": ""}


def _rows(a: np.ndarray) -> list[list[Any]]:
    """Rows as lists; non-finite floats become null (JSON has no NaN/inf)."""
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        return [[x if math.isfinite(x) else None for x in row] for row in a.tolist()]
    return a.tolist()


def robot_spec_for_metadata(spec: str | os.PathLike[str]) -> str:
    """A robot spec that still resolves from another directory: names stay, paths become absolute."""
    text = os.fspath(spec)
    is_path = "/" in text or os.sep in text or text.lower().endswith((".urdf", ".xacro", ".yaml", ".yml"))
    return str(Path(text).expanduser().resolve()) if is_path else text


# ------------------------------------------------------------------ data
@dataclass
class RunData:
    """A recorded run as arrays (joint columns in ``names`` order; times in ns of robot time)."""

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
    #: True when the file was cut short (the recording process was killed): read up to its last complete chunk
    truncated: bool = False

    @property
    def duration(self) -> float:
        """Robot time of the last joint state (s)."""
        return float(self.state_time[-1]) / _NS if len(self.state_time) else 0.0

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
        side = "left" if applied_before else "right"
        return np.searchsorted(self.cmd_time, t_ns, side=side) - 1

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


# ------------------------------------------------------------------ recorder
class _Block:
    """Preallocated per-tick rows (one control tick per row)."""

    __slots__ = ("e", "en", "kd", "kp", "mode", "q", "sp_e", "sp_q", "sp_v", "t", "target", "tc", "v")

    def __init__(self, cap: int, n: int) -> None:
        self.t = np.empty(cap)
        self.tc = np.empty(cap)
        self.q = np.empty((cap, n))
        self.v = np.empty((cap, n))
        self.e = np.empty((cap, n))
        self.sp_q = np.empty((cap, n))
        self.sp_v = np.empty((cap, n))
        self.sp_e = np.empty((cap, n))
        self.kp = np.empty((cap, n))
        self.kd = np.empty((cap, n))
        self.target = np.empty((cap, n))
        self.en = np.empty((cap, n), dtype=bool)
        self.mode = np.empty((cap, n), dtype=np.int8)


_CMD_FIELDS = ("sp_q", "sp_v", "sp_e", "kp", "kd", "en", "mode", "target")


@dataclass
class _Chunk:
    """Rows selected from one block for output."""

    st_ns: np.ndarray
    q: np.ndarray
    v: np.ndarray
    e: np.ndarray
    cmd_ns: np.ndarray
    cmd: dict[str, np.ndarray]
    tf_ns: np.ndarray
    tf_q: np.ndarray


class _Sink:
    """One MCAP output: the agentsdk JSON format (Foxglove-ready) or a rosbag2-compatible CDR file."""

    def __init__(self, path: Path, *, ros2: bool, names: tuple[str, ...], metadata: Mapping[str, str]) -> None:
        from . import __version__

        self.path, self.ros2 = path, ros2
        self.names = list(names)
        try:
            self.stream: IO[bytes] = open(path, "wb")  # closed in close()
        except OSError as exc:
            raise ConfigurationError(f"cannot write recording {path}: {exc.strerror or exc}") from exc
        self.writer = w = Writer(self.stream, chunk_size=_CHUNK_BYTES, compression=CompressionType.ZSTD)
        w.start(profile="ros2" if ros2 else "", library=f"agentsdk {__version__}")
        self.channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        if ros2:
            sids = {t: w.register_schema(t, "ros2msg", d.encode()) for t, d in ROS2_MSGDEFS.items()}
            for topic, msg_type in _ROS2_TOPICS.items():
                qos = _QOS_LATCHED if topic == ROBOT_DESCRIPTION else _QOS_DEFAULT
                self.channels[topic] = w.register_channel(topic, "cdr", sids[msg_type], {"offered_qos_profiles": qos})
                self.counts[topic] = 0
            self.types = dict(_ROS2_TOPICS)
        else:
            for topic, schema in _SCHEMAS.items():
                sid = w.register_schema(schema["title"], "jsonschema", json.dumps(schema).encode())
                self.channels[topic] = w.register_channel(topic, "json", sid)
                self.counts[topic] = 0
        w.add_metadata(METADATA_NAME, dict(metadata))
        self.start_ns: int | None = None
        self.end_ns = 0

    def _add(self, topic: str, ns: int, data: bytes) -> None:
        seq = self.counts[topic]
        self.writer.add_message(self.channels[topic], log_time=ns, data=data, publish_time=ns, sequence=seq)
        self.counts[topic] = seq + 1
        if self.start_ns is None or ns < self.start_ns:
            self.start_ns = ns
        self.end_ns = max(self.end_ns, ns)

    def description(self, ns: int, urdf: str) -> None:
        """The robot description, once, at the start (``/robot_description``)."""
        if self.ros2:
            data = Cdr.string_message(urdf)
        else:
            data = json.dumps({"data": urdf}).encode()
        self._add(ROBOT_DESCRIPTION, ns, data)

    def write_chunk(self, c: _Chunk, tf: _Tf | None) -> Iterator[None]:
        """Write a chunk's messages in log-time order, yielding after each one."""
        names = self.names
        ros2 = self.ros2
        d = c.cmd
        if ros2:
            q, v, e = c.q, c.v, c.e
            cq, cv, ce = d["sp_q"], d["sp_v"], d["sp_e"]
        else:
            q, v, e = _rows(c.q), _rows(c.v), _rows(c.e)
            cq, cv, ce, kp, kd, tg = (_rows(d[f]) for f in ("sp_q", "sp_v", "sp_e", "kp", "kd", "target"))
            en = d["en"].tolist()
            modes = [[MODES[x] for x in row] for row in d["mode"].tolist()]
        st_ns, cmd_ns = c.st_ns.tolist(), c.cmd_ns.tolist()
        tf_ns = tf.ns.tolist() if tf is not None else []
        dumps = json.dumps
        # merge the streams in log-time order (a command stamped t precedes the state stamped t)
        streams = heapq.merge(
            ((ns, 0, j) for j, ns in enumerate(cmd_ns)),
            ((ns, 1, i) for i, ns in enumerate(st_ns)),
            ((ns, 2, k) for k, ns in enumerate(tf_ns)),
        )
        for ns, kind, i in streams:
            if kind == 0:
                if ros2:
                    data = Cdr.joint_state(ns, names, cq[i], cv[i], ce[i])
                else:
                    msg = {
                        "header": _header(ns),
                        "name": names,
                        "position": cq[i],
                        "velocity": cv[i],
                        "effort": ce[i],
                        "mode": modes[i],
                        "enabled": en[i],
                        "kp": kp[i],
                        "kd": kd[i],
                        "target": tg[i],
                    }
                    data = dumps(msg).encode()
                self._add(JOINT_COMMANDS, ns, data)
            elif kind == 1:
                if ros2:
                    data = Cdr.joint_state(ns, names, q[i], v[i], e[i])
                else:
                    msg = {"header": _header(ns), "name": names, "position": q[i], "velocity": v[i], "effort": e[i]}
                    data = dumps(msg).encode()
                self._add(JOINT_STATES, ns, data)
            else:
                assert tf is not None
                if ros2:
                    data = Cdr.tf_message(ns, tf.parents, tf.children, tf.trans[i], tf.rot[i])
                else:
                    data = dumps({"transforms": _fox_transforms(ns, tf, i)}).encode()
                self._add(TF, ns, data)
            yield

    def write_side(self, side: list[tuple[int, str, dict[str, Any]]]) -> None:
        """Safety events and transitions (JSON format only: ROS has no message for them)."""
        if self.ros2:
            return
        for ns, topic, msg in sorted(side, key=lambda x: x[0]):
            self._add(topic, ns, json.dumps({"header": _header(ns), **msg}).encode())

    def flush(self) -> None:
        """Close the open MCAP chunk and push it to the OS: a killed process keeps everything written so far."""
        self.writer.flush()

    def close(self, ok: bool = True) -> None:
        """Write the summary (and the rosbag2 metadata) and close the file."""
        try:
            if ok:
                if self.ros2:
                    self.writer.add_metadata("rosbag2", {"serialized_metadata": self._rosbag2_metadata()})
                self.writer.finish()
        finally:
            self.stream.close()

    def _rosbag2_metadata(self) -> str:
        import yaml

        start = self.start_ns or 0
        info = {
            "rosbag2_bagfile_information": {
                "version": 8,
                "storage_identifier": "mcap",
                "relative_file_paths": [self.path.name],
                "duration": {"nanoseconds": max(0, self.end_ns - start)},
                "starting_time": {"nanoseconds_since_epoch": start},
                "message_count": sum(self.counts.values()),
                "topics_with_message_count": [
                    {
                        "topic_metadata": {
                            "name": topic,
                            "type": self.types[topic],
                            "serialization_format": "cdr",
                            "offered_qos_profiles": _QOS_LATCHED if topic == ROBOT_DESCRIPTION else _QOS_DEFAULT,
                            "type_description_hash": "",
                        },
                        "message_count": count,
                    }
                    for topic, count in self.counts.items()
                ],
                "compression_format": "",
                "compression_mode": "",
                "custom_data": {},
                "ros_distro": "",
                "files": [
                    {
                        "path": self.path.name,
                        "starting_time": {"nanoseconds_since_epoch": start},
                        "duration": {"nanoseconds": max(0, self.end_ns - start)},
                        "message_count": sum(self.counts.values()),
                    }
                ],
            }
        }
        return str(yaml.safe_dump(info, sort_keys=False))


def _fox_transforms(ns: int, tf: _Tf, i: int) -> list[dict[str, Any]]:
    sec, nsec = divmod(ns, _NS)
    stamp = {"sec": sec, "nsec": nsec}
    trans, rot = tf.trans[i].tolist(), tf.rot[i].tolist()
    return [
        {
            "timestamp": stamp,
            "parent_frame_id": parent,
            "child_frame_id": child,
            "translation": {"x": t[0], "y": t[1], "z": t[2]},
            "rotation": {"x": r[0], "y": r[1], "z": r[2], "w": r[3]},
        }
        for parent, child, t, r in zip(tf.parents, tf.children, trans, rot, strict=True)
    ]


@dataclass
class _Tf:
    """Link transforms of the TF samples of one chunk."""

    ns: np.ndarray
    parents: list[str]
    children: list[str]
    trans: np.ndarray  # (S, L, 3)
    rot: np.ndarray  # (S, L, 4) x, y, z, w


def _foxglove_urdf(urdf: str) -> str:
    """Mesh paths as ``file://`` URLs (what Foxglove's URDF loader resolves); ``package://`` stays."""
    return re.sub(r'filename="(/[^"]*)"', lambda m: f'filename="file://{m.group(1)}"', urdf)


class Recorder:
    """Records one robot's joint states, applied setpoints, link transforms, safety events and transitions.

    Create with :meth:`attach` (it registers a tick hook), call :meth:`finish`
    once the run is over (writes the MCAP summary).  Data reaches the file while
    the robot runs (see "Crash safety" in the module docs).  With ``keep=True``
    :meth:`data` returns the run as arrays; it is read back from the file (a
    temporary one without ``path``), so memory does not grow with the run.

    ``format`` is ``"mcap"`` (the agentsdk format: JSON channels, Foxglove
    transforms and description) or ``"ros2"`` (a rosbag2 MCAP: CDR
    ``sensor_msgs/msg/JointState`` and ``tf2_msgs/msg/TFMessage``).
    ``tf_rate`` (Hz of robot time) decimates ``/tf``; ``None`` or 0 records no
    transforms.
    """

    def __init__(
        self,
        robot: Robot,
        path: str | os.PathLike[str] | None = None,
        *,
        rate: float | None = None,
        keep: bool = False,
        metadata: Mapping[str, str] | None = None,
        block_ticks: int = BLOCK_TICKS,
        format: str = "mcap",
        tf_rate: float | None = TF_RATE,
    ) -> None:
        if rate is not None and not (math.isfinite(rate) and rate > 0):
            raise ConfigurationError(f"record rate must be a positive number of Hz, got {rate!r}")
        if tf_rate is not None and not (math.isfinite(tf_rate) and tf_rate >= 0):
            raise ConfigurationError(f"tf rate must be a positive number of Hz (0 for none), got {tf_rate!r}")
        if format not in RECORD_FORMATS:
            raise ConfigurationError(f"unknown recording format {format!r}; choose one of {', '.join(RECORD_FORMATS)}")
        if path is None and not keep:
            raise ConfigurationError("Recorder needs a path or keep=True")
        self._robot = robot
        self.names: tuple[str, ...] = tuple(robot.joint_names)
        self.period = float(robot.control_period)
        self.rate = rate
        self.tf_rate = tf_rate or None
        self.keep = keep
        self.format = format
        self.path = Path(path) if path is not None else None
        n = len(self.names)
        self._cap = int(block_ticks)
        self._block = _Block(self._cap, n)
        self._k = 0
        self._prev_t = float(robot.clock.now())
        self.ticks = 0
        # selection state carried across blocks
        self._last_sample = math.floor(self._prev_t * rate + 1e-6) if rate else 0
        self._last_tf = math.floor(self._prev_t * self.tf_rate + 1e-6) - 1 if self.tf_rate else 0
        self._last_cmd: tuple[np.ndarray, ...] | None = None
        self._held: tuple[int, tuple[np.ndarray, ...]] | None = None
        self._event_cursor = robot.safety.event_count
        self._pending_side: list[tuple[int, str, dict[str, Any]]] = []
        self._finished = False
        self._data: RunData | None = None
        self.truncated = False
        self.metadata = self._metadata(metadata or {})
        # the kinematics (a MuJoCo model compile, ~0.2 s with its imports) is built in a thread:
        # done in the event loop it would stall a running control loop
        self._layout: TfLayout | None = None
        self._layout_thread: threading.Thread | None = None
        self._layout_ready = asyncio.Event()
        try:
            self._loop: asyncio.AbstractEventLoop | None = asyncio.get_running_loop()
        except RuntimeError:
            self._loop = None
        self._sinks: list[_Sink] = []
        self._json_path: Path | None = None
        self._temp: Path | None = None
        self._backlog: deque[tuple[_Chunk | None, list[tuple[int, str, dict[str, Any]]]]] = deque()
        self._backlog_ticks = 0
        self._drain: Iterator[None] | None = None
        self._task: asyncio.Task[None] | None = None
        self._rotated_at = time.perf_counter()
        try:
            if self.path is not None:
                self._sinks.append(_Sink(self.path, ros2=format == "ros2", names=self.names, metadata=self.metadata))
                if format == "mcap":
                    self._json_path = self.path
            if keep and self._json_path is None:
                fd, tmp = tempfile.mkstemp(prefix="agentsdk-rec-", suffix=".mcap")
                os.close(fd)
                self._temp = self._json_path = Path(tmp)
                self._sinks.append(_Sink(self._temp, ros2=False, names=self.names, metadata=self.metadata))
            self._write_description()
        except BaseException:
            self._close_sinks(ok=False)
            raise
        if self.tf_rate:  # started last: its imports must not hold the import lock the code above needs
            self._layout_thread = threading.Thread(
                target=self._build_layout, name="agentsdk-recorder-kinematics", daemon=True
            )
            self._layout_thread.start()
        # first observer: sees the setpoint exactly as written, before a watchdog changes it
        self._tick_handle = robot.add_tick_hook(Phase.OBSERVE, self._on_tick, order=RECORDER_ORDER)
        self._transition_handle = StateMachine.add_transition_listener(self._on_transition)

    @classmethod
    def attach(
        cls,
        robot: Robot,
        path: str | os.PathLike[str] | None = None,
        *,
        rate: float | None = None,
        keep: bool = False,
        metadata: Mapping[str, str] | None = None,
        format: str = "mcap",
        tf_rate: float | None = TF_RATE,
    ) -> Recorder:
        """Start recording ``robot`` (call right after connect, before any tick)."""
        return cls(robot, path, rate=rate, keep=keep, metadata=metadata, format=format, tf_rate=tf_rate)

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic (of ``path``'s file, or of the temporary file)."""
        return dict(self._sinks[0].counts) if self._sinks else {}

    # -------------------------------------------------------------- setup
    def _metadata(self, extra: Mapping[str, str]) -> dict[str, str]:
        from . import __version__

        backend = self._robot.controller
        try:
            config = json.dumps(backend.config.model_dump(mode="json"), sort_keys=True)
        except Exception:  # pragma: no cover - a config that does not serialize
            config = ""
        opts = backend.options.model_dump(mode="json") if hasattr(backend.options, "model_dump") else {}
        md = {
            "format": FORMAT,
            "robot": self._robot.name,
            "robot_name": self._robot.name,
            "backend": self._robot.backend,
            "backend_options": json.dumps(opts, sort_keys=True),
            "realtime": "true" if self._robot.realtime else "false",
            "control_period": repr(self.period),
            "joints": json.dumps(list(self.names)),
            "record_rate": "" if self.rate is None else repr(float(self.rate)),
            "tf_rate": "" if not self.tf_rate else repr(float(self.tf_rate)),
            "robot_config": config,
            "agentsdk_version": __version__,
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        }
        md.update({k: str(v) for k, v in extra.items()})
        return md

    def _build_layout(self) -> None:
        try:
            kin = self._robot.kinematics
            if tuple(kin.joint_names) != self.names:
                raise ConfigurationError("kinematics joint order differs from the robot's")
            self._layout = TfLayout(kin)
        except Exception as exc:  # a robot whose model the kinematics cannot build still records joints
            log.warning("recording without /tf: no kinematics for %s (%s)", self._robot.name, exc)
        finally:
            loop = self._loop
            if loop is not None:
                try:
                    loop.call_soon_threadsafe(self._layout_ready.set)
                except RuntimeError:  # the event loop is closed: nobody waits
                    pass

    def _layout_pending(self) -> bool:
        return self._layout_thread is not None and self._layout_thread.is_alive()

    def _join_layout(self) -> None:
        if self._layout_thread is not None:
            self._layout_thread.join()

    def _write_description(self) -> None:
        desc = getattr(self._robot, "description", None)
        urdf = getattr(desc, "urdf_xml", "") or ""
        ns = _ns(self._prev_t)
        for s in self._sinks:
            if urdf:
                s.description(ns, urdf if s.ros2 else _foxglove_urdf(urdf))
            s.flush()  # the header, schemas and metadata reach the disk at once

    # ----------------------------------------------------------- per tick
    def _on_tick(self, t: float, st: StateView, sp: SetpointView) -> None:
        k = self._k
        if k == self._cap:
            self._rotate()
            k = 0
        b = self._block
        b.t[k] = t
        b.tc[k] = self._prev_t
        self._prev_t = t
        b.q[k] = st.position
        b.v[k] = st.velocity
        b.e[k] = st.effort
        b.sp_q[k] = sp.position
        b.sp_v[k] = sp.velocity
        b.sp_e[k] = sp.effort
        b.kp[k] = sp.kp
        b.kd[k] = sp.kd
        b.en[k] = sp.enabled
        b.mode[k] = sp.mode
        b.target[k] = sp.target
        self._k = k + 1
        self.ticks += 1
        if self._robot.safety.event_count != self._event_cursor:
            self._take_events()
        if not (k & 15) and time.perf_counter() - self._rotated_at > FLUSH_INTERVAL:
            self._rotate()
        if self._backlog_ticks > DRAIN_AFTER_TICKS:
            self._write_some(_DRAIN_PER_TICK)

    def _take_events(self) -> None:
        safety = self._robot.safety
        new = safety.events_since(self._event_cursor)
        self._event_cursor = safety.event_count
        for ev in new:
            msg = {"kind": ev.kind, "joint": ev.joint, "detail": ev.detail}
            self._pending_side.append((_ns(ev.time), SAFETY_EVENTS, msg))

    def _on_transition(self, machine: Any, rec: Any) -> None:
        if getattr(machine, "robot", None) is not self._robot or self._finished:
            return
        msg = {"machine": rec.machine, "source": rec.source, "target": rec.target, "event": rec.event, "note": rec.note}
        self._pending_side.append((_ns(rec.time), TRANSITIONS, msg))

    # ----------------------------------------------------------- blocks
    def _rotate(self, final: bool = False) -> None:
        self._rotated_at = time.perf_counter()
        m = self._k
        self._k = 0
        if m == 0:
            chunk = None
            if final and self._held is not None:  # the run's last tick, held back by the previous block
                ns, row = self._held
                self._held = None
                chunk = _Chunk(
                    st_ns=np.zeros(0, np.int64), q=self._block.q[:0].copy(), v=self._block.v[:0].copy(),
                    e=self._block.e[:0].copy(), cmd_ns=np.array([ns], np.int64),
                    cmd={f: r[None] for f, r in zip(_CMD_FIELDS, row, strict=True)},
                    tf_ns=np.zeros(0, np.int64), tf_q=self._block.q[:0].copy(),
                )
            if self._pending_side or chunk is not None:
                side, self._pending_side = self._pending_side, []
                self._backlog.append((chunk, side))
                self._kick()
            return
        chunk = self._select(self._block, m, final)
        side, self._pending_side = self._pending_side, []
        self._backlog.append((chunk, side))
        self._backlog_ticks += len(chunk.st_ns)
        self._kick()

    def _select(self, b: _Block, m: int, final: bool = False) -> _Chunk:
        t = b.t[:m]
        if self.rate is None:
            st_rows = np.arange(m)
        else:
            s = np.floor(t * self.rate + 1e-6).astype(np.int64)
            prev = np.concatenate(([self._last_sample], s[:-1]))
            st_rows = np.flatnonzero(s != prev)
            self._last_sample = int(s[-1])
        if self.tf_rate:
            s = np.floor(t * self.tf_rate + 1e-6).astype(np.int64)
            prev = np.concatenate(([self._last_tf], s[:-1]))
            tf_rows = np.flatnonzero(s != prev)
            self._last_tf = int(s[-1])
        else:
            tf_rows = np.zeros(0, np.intp)
        arrays = [getattr(b, f)[:m] for f in _CMD_FIELDS]
        changed = np.zeros(m, dtype=bool)
        last = self._last_cmd
        if last is None:
            changed[0] = True
        for a, lrow in zip(arrays, last or [None] * len(arrays), strict=True):
            if m > 1:
                changed[1:] |= (a[1:] != a[:-1]).any(axis=1)
            if lrow is not None:
                changed[0] |= bool((a[0] != lrow).any())
        keep = changed.copy()
        keep[:-1] |= changed[1:]  # the last tick of a hold, so line plots stay flat
        if final:
            keep[-1] = True
        self._last_cmd = tuple(a[m - 1].copy() for a in arrays)
        cmd_rows = np.flatnonzero(keep)
        ns = np.rint(t * _NS).astype(np.int64)
        cns = np.rint(b.tc[:m] * _NS).astype(np.int64)
        # Block boundaries follow the wall clock, so they must not add messages: the last row of a
        # block is held back and written only if the next block starts with a change (or at the end)
        held, self._held = self._held, None
        if not keep[-1]:
            self._held = (int(cns[m - 1]), self._last_cmd)
        cmd = {f: a[cmd_rows] for f, a in zip(_CMD_FIELDS, arrays, strict=True)}
        cmd_ns = cns[cmd_rows]
        if held is not None and changed[0]:
            h_ns, h_row = held
            cmd = {f: np.concatenate((r[None], cmd[f])) for f, r in zip(_CMD_FIELDS, h_row, strict=True)}
            cmd_ns = np.concatenate(([h_ns], cmd_ns))
        return _Chunk(
            st_ns=ns[st_rows],
            q=b.q[st_rows],
            v=b.v[st_rows],
            e=b.e[st_rows],
            cmd_ns=cmd_ns,
            cmd=cmd,
            tf_ns=ns[tf_rows],
            tf_q=b.q[tf_rows],
        )

    # ----------------------------------------------------------- writing (off the tick)
    def _kick(self) -> None:
        """Make sure the writer task runs (it writes the backlog between ticks, then exits)."""
        if self._finished or not self._sinks or (self._task is not None and not self._task.done()):
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # not inside an event loop: finish() writes everything
            return
        self._task = loop.create_task(self._write_task(), name="agentsdk-recorder-writer")

    async def _write_task(self) -> None:
        """Write the backlog in slices of at most ``_SLICE_S`` s, yielding to the loop in between; flush at the end."""
        try:
            if self._layout_pending():
                await self._layout_ready.wait()
            while not self._finished:
                if self._write_for(_SLICE_S):
                    for s in self._sinks:
                        s.flush()
                    return
                await asyncio.sleep(0)
        except OSError as exc:
            log.error("writing the recording failed: %s", exc.strerror or exc)

    def _write_for(self, budget: float) -> bool:
        """Write backlog messages for about ``budget`` seconds; True once the backlog is empty."""
        end = time.perf_counter() + budget
        while True:
            if self._write_some(16):
                return True
            if time.perf_counter() >= end:
                return False

    def _write_some(self, n: int) -> bool:
        """Write up to ``n`` messages of the backlog (resumable); True once it is empty."""
        for _ in range(n):
            if self._drain is None:
                if not self._backlog:
                    return True
                self._drain = self._write_backlog()
            try:
                next(self._drain)
            except StopIteration:
                self._drain = None
                return not self._backlog
        return False

    def _write_backlog(self) -> Iterator[None]:
        while self._layout_pending():
            yield
        while self._backlog:
            chunk, side = self._backlog[0]
            if chunk is not None:
                tf = None
                if self._layout is not None and len(chunk.tf_ns):
                    trans = np.empty((len(chunk.tf_ns), len(self._layout.children), 3))
                    rot = np.empty((len(chunk.tf_ns), len(self._layout.children), 4))
                    for i, q in enumerate(chunk.tf_q):
                        trans[i], rot[i] = tf_batch(self._layout, q)
                        yield
                    tf = _Tf(chunk.tf_ns, self._layout.parents, self._layout.children, trans, rot)
                for s in self._sinks:
                    yield from s.write_chunk(chunk, tf)
                self._backlog_ticks -= len(chunk.st_ns)
            for s in self._sinks:
                s.write_side(side)
            self._backlog.popleft()
            yield

    # ----------------------------------------------------------- finish
    def _close_sinks(self, ok: bool) -> None:
        sinks, self._sinks = self._sinks, []
        error: BaseException | None = None
        for s in sinks:
            try:
                s.close(ok)
            except OSError as exc:
                error = error or exc
        if error is not None:
            raise error

    def finish(self) -> None:
        """Write everything left, the MCAP summary, and close the file. Idempotent."""
        if self._finished:
            return
        self._finished = True
        self._tick_handle.remove()
        self._transition_handle.remove()
        if self._task is not None and not self._task.done():
            self._task.cancel()
        if self._robot.safety.event_count != self._event_cursor:
            self._take_events()
        self._rotate(final=True)
        self._join_layout()
        path = self.path or self._json_path
        try:
            while not self._write_some(1 << 30):
                pass
            self._close_sinks(ok=True)
        except OSError as exc:
            self._close_sinks(ok=False)
            raise ConfigurationError(f"writing recording {path} failed: {exc.strerror or exc}") from exc
        finally:
            if self._temp is not None:
                try:
                    self._data = read_recording(self._temp)
                finally:
                    self._temp.unlink(missing_ok=True)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()

    def data(self) -> RunData:
        """The recorded run (needs ``keep=True``), read back from the file; complete after :meth:`finish`."""
        if not self.keep:
            raise ConfigurationError("Recorder.data() needs keep=True")
        if self._data is not None:
            return self._data
        assert self._json_path is not None
        if not self._finished:
            self._rotate()
            self._join_layout()
            while not self._write_some(1 << 30):
                pass
            for s in self._sinks:
                s.flush()
        return read_recording(self._json_path)


# ------------------------------------------------------------------ reading
def _scan_mcap(p: Path) -> tuple[dict[str, str], list[tuple[str, int, bytes]], bool, str]:
    """Every metadata record and message of an MCAP file, read front to back.

    A file whose writer was killed has no summary and may end inside a record:
    what precedes the last complete chunk is returned, with ``truncated=True``
    and the reason (the ``mcap recover`` idea).  Chunk CRCs are checked, so a
    damaged chunk ends the read instead of returning garbage.
    """
    md: dict[str, str] = {}
    topics: dict[int, str] = {}
    out: list[tuple[str, int, bytes]] = []
    complete = False
    reason = ""

    def take(rec: Any) -> None:
        if isinstance(rec, Channel):
            topics[rec.id] = rec.topic
        elif isinstance(rec, Message):
            topic = topics.get(rec.channel_id)
            if topic is not None:
                out.append((topic, rec.log_time, rec.data))
        elif isinstance(rec, Metadata) and rec.name == METADATA_NAME:
            md.update(rec.metadata)

    with open(p, "rb") as f:
        records = StreamReader(f, emit_chunks=True, record_size_limit=1 << 31).records
        while True:
            try:
                rec = next(records)
                inner = breakup_chunk(rec, validate_crc=True) if isinstance(rec, Chunk) else [rec]
            except StopIteration:
                break
            except Exception as exc:  # any failure here is a damaged or cut tail: keep what came before
                reason = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                break
            for r in inner:
                take(r)
            if isinstance(rec, Footer):
                complete = True
    return md, out, not complete, reason


def read_recording(path: str | os.PathLike[str]) -> RunData:
    """Read an agentsdk MCAP recording; raises ConfigurationError for a missing or foreign file.

    A recording cut short (the process was killed) is read up to its last
    complete chunk; ``RunData.truncated`` is then True.
    """
    p = Path(path)
    if not p.is_file():
        raise ConfigurationError(f"recording not found: {p}")
    try:
        md, messages, truncated, reason = _scan_mcap(p)
    except OSError as exc:
        raise ConfigurationError(f"cannot read recording {p}: {exc.strerror or exc}") from exc
    if md.get("format") != FORMAT:
        if truncated and not messages and not md:
            raise ConfigurationError(f"cannot read recording {p}: {reason or 'no MCAP data'}")
        raise ConfigurationError(
            f"{p} is not an agentsdk recording (no '{METADATA_NAME}' metadata; a --record-format ros2 "
            "file is read with ROS 2 tools or the rosbags library)"
        )
    try:
        names = tuple(json.loads(md["joints"]))
        period = float(md["control_period"])
        st_t: list[int] = []
        st: list[tuple[list[float], list[float], list[float]]] = []
        cm_t: list[int] = []
        cm: list[dict[str, Any]] = []
        events: list[dict[str, Any]] = []
        transitions: list[dict[str, Any]] = []
        for topic, log_time, data in messages:
            if topic in (TF, ROBOT_DESCRIPTION):
                continue
            msg = json.loads(data)
            if topic == JOINT_STATES:
                st_t.append(log_time)
                st.append((msg["position"], msg["velocity"], msg["effort"]))
            elif topic == JOINT_COMMANDS:
                cm_t.append(log_time)
                cm.append(msg)
            else:
                msg.pop("header", None)
                item = {"time": log_time / _NS, **msg}
                (events if topic == SAFETY_EVENTS else transitions).append(item)
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigurationError(f"cannot read recording {p}: {exc}") from exc
    if truncated:
        log.warning("recording %s was not finished (%s); read up to its last complete chunk", p, reason or "no summary")
    n = len(names)
    out = _empty(names, period, md)
    out.truncated = truncated
    out.events, out.transitions = events, transitions
    if st:
        arr = np.array(st, dtype=float).reshape(len(st), 3, n)
        out.state_time = np.array(st_t, dtype=np.int64)
        out.position, out.velocity, out.effort = arr[:, 0], arr[:, 1], arr[:, 2]
    if cm:

        def col(key: str, dtype: Any = float) -> np.ndarray:
            return np.array([m[key] for m in cm], dtype=dtype).reshape(len(cm), n)

        out.cmd_time = np.array(cm_t, dtype=np.int64)
        out.cmd_position, out.cmd_velocity, out.cmd_effort = col("position"), col("velocity"), col("effort")
        out.cmd_kp, out.cmd_kd, out.cmd_target = col("kp"), col("kd"), col("target")
        out.cmd_enabled = col("enabled", bool)
        out.cmd_mode = np.array([[ModeCode.of(x) for x in m["mode"]] for m in cm], dtype=np.int8).reshape(len(cm), n)
    return out


# ------------------------------------------------------------------ replay
@dataclass
class ReplayResult:
    """Divergence of the replayed joint positions from the recorded ones (per joint, rad or m)."""

    names: tuple[str, ...]
    max_abs: dict[str, float]
    rms: dict[str, float]
    samples: int
    ticks: int
    replayed: RunData
    config_changed: bool = False
    #: True for a real-time recording: its stamps are off the tick grid, the replay is interpolated
    interpolated: bool = False

    @property
    def worst(self) -> float:
        """The largest absolute divergence over all joints."""
        return max(self.max_abs.values(), default=0.0)

    def lines(self) -> list[str]:
        """A table of the divergence per joint, one line per row."""
        width = max([len("joint"), *(len(n) for n in self.names)])
        out = [
            f"divergence of joint positions (replayed - recorded) over {self.samples} samples"
            + (" (real-time recording: replay interpolated, approximate):" if self.interpolated else ":"),
            f"  {'joint':{width}s}  {'max |err|':>11s}  {'RMS':>11s}",
        ]
        for n in self.names:
            out.append(f"  {n:{width}s}  {self.max_abs[n]:11.3e}  {self.rms[n]:11.3e}")
        return out


async def replay(
    data: RunData,
    *,
    backend: str | None = None,
    robot: str | None = None,
    options: Mapping[str, Any] | None = None,
    record: str | os.PathLike[str] | None = None,
    on_robot: Callable[[Robot], Any] | None = None,
) -> ReplayResult:
    """Feed the recorded setpoints, tick by tick, into a fresh connection and compare joint states."""
    from .robot import connect

    if not len(data.state_time):
        raise ConfigurationError("the recording has no joint states to replay")
    backend = backend or data.backend or "mujoco"
    robot = robot or data.robot
    if not robot:
        raise ConfigurationError("the recording does not name its robot; pass --robot")
    opts: dict[str, Any] = {}
    if backend == data.backend and data.metadata.get("backend_options"):
        opts.update(json.loads(data.metadata["backend_options"]))
        opts.pop("gui", None)  # a recording made with --view replays headless
    opts.update(options or {})
    end_ns = int(data.state_time[-1])
    async with connect(backend, robot=robot, safety={"watchdog_modes": ()}, **opts) as bot:
        index = bot.joint_index
        if abs(bot.control_period - data.period) > 1e-12:
            raise ConfigurationError(
                f"control period of {bot.name} on {backend} is {bot.control_period:g} s, "
                f"the recording's is {data.period:g} s; replay needs the same period"
            )
        missing = [n for n in data.names if n not in index]
        if missing:
            raise ConfigurationError(
                f"robot {bot.name!r} has no joint(s) {', '.join(missing)} from the recording "
                f"(its joints: {', '.join(bot.joint_names)})"
            )
        config_changed = False
        recorded_config = data.metadata.get("robot_config")
        if recorded_config:
            config_changed = json.loads(recorded_config) != bot.controller.config.model_dump(mode="json")
            if config_changed:
                log.warning("robot.yaml of %s differs from the recorded one; replay may diverge", bot.name)
        cols = np.array([index[n] for n in data.names], dtype=np.intp)
        rec = Recorder(
            bot,
            record,
            keep=True,
            metadata={
                "robot": robot_spec_for_metadata(robot),
                "backend_options": json.dumps(opts, sort_keys=True, default=str),
                "behavior": data.metadata.get("behavior", ""),
                "replay_of": data.metadata.get("created", ""),
            },
        )
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        half = _ns(bot.control_period) // 2
        cmd_ns = data.cmd_time
        pos, vel, eff = data.cmd_position, data.cmd_velocity, data.cmd_effort
        kp, kd, en, mode, tgt = data.cmd_kp, data.cmd_kd, data.cmd_enabled, data.cmd_mode, data.cmd_target

        def update(t: float, st: StateView, sp: Setpoint) -> bool:
            ns = _ns(t)
            if ns >= end_ns - half:
                return False
            i = int(np.searchsorted(cmd_ns, ns, side="right")) - 1
            if i >= 0:
                sp.position[cols] = pos[i]
                sp.velocity[cols] = vel[i]
                sp.effort[cols] = eff[i]
                sp.kp[cols] = kp[i]
                sp.kd[cols] = kd[i]
                sp.enabled[cols] = en[i]
                sp.mode[cols] = mode[i]
                sp.target[cols] = tgt[i]
            return True

        def watch(t: float, st: StateView, sp: SetpointView) -> None:
            if _ns(t) >= end_ns - half and not done.done():
                feeding.remove()
                done.set_result(None)

        def fault(exc: BaseException) -> None:
            if not done.done():
                done.set_exception(exc)

        bot.add_tick_hook(Phase.OBSERVE, watch)
        bot.add_fault_listener(fault)
        if on_robot is not None:
            on_robot(bot)
        feeding = bot.add_tick_hook(Phase.COMMAND, update)
        try:
            await done
        except BaseException:
            feeding.remove()
            await bot.close()
            rec.finish()
            raise
        ticks = bot.ticks
    rec.finish()  # after close: joining the writer must not stall the control loop
    return _compare(data, rec.data(), ticks, config_changed)


def _compare(data: RunData, replayed: RunData, ticks: int, config_changed: bool) -> ReplayResult:
    cols = [replayed.names.index(n) for n in data.names]
    rt = replayed.state_time
    if not len(rt):
        raise ConfigurationError("the replay produced no joint states")
    rows = np.minimum(np.searchsorted(rt, data.state_time), len(rt) - 1)
    if np.array_equal(rt[rows], data.state_time):
        actual = replayed.position[rows][:, cols]
        interpolated = False
    elif data.metadata.get("realtime") == "true":
        # real-time stamps are off the tick grid: compare against the replay interpolated in time
        actual = np.column_stack([np.interp(data.state_time, rt, replayed.position[:, c]) for c in cols])
        interpolated = True
    else:
        first = int(data.state_time[np.argmax(rt[rows] != data.state_time)]) / _NS
        raise ConfigurationError(f"the replay has no joint state at t={first:.6f} s")
    diff = actual - data.position
    max_abs = {n: float(np.max(np.abs(diff[:, j]))) for j, n in enumerate(data.names)}
    rms = {n: float(np.sqrt(np.mean(diff[:, j] ** 2))) for j, n in enumerate(data.names)}
    return ReplayResult(data.names, max_abs, rms, len(data.state_time), ticks, replayed, config_changed, interpolated)
