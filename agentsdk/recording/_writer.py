"""The recorder's writer thread: selects rows from filled blocks, encodes them as CDR, writes MCAP chunks.

The control loop only copies each tick's arrays into a preallocated
:class:`Block` and hands full blocks (or, every :data:`FLUSH_INTERVAL` of wall
time, partial ones) to :class:`WriterThread` through a queue whose length is
bounded by the block pool.  Everything else happens on the thread: choosing
the rows to keep (decimated joint states and ``/tf`` samples, change-based
commands), forward kinematics for ``/tf``, encoding whole blocks of messages at
once (:mod:`._cdr`), and writing each block as one zstd-compressed MCAP chunk
(:mod:`._mcap`: the chunk's records are laid out with numpy too).  The thread
holds the GIL only for a few array operations per block; compression and file
writes release it.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import re
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING

import numpy as np

from ..errors import ConfigurationError
from ._cdr import (
    COMMAND_TYPE,
    EVENT_TYPE,
    MSGDEFS,
    TRANSITION_TYPE,
    FixedLayout,
    command_layout,
    joint_state_layout,
    strings_message,
    tf_layout,
)
from ._channels import (
    JOINT_COMMANDS,
    JOINT_STATES,
    METADATA_NAME,
    NS_PER_S,
    QOS_DEFAULT,
    QOS_LATCHED,
    ROBOT_DESCRIPTION,
    ROS2_FORMAT,
    SAFETY_EVENTS,
    TF,
    TRANSITIONS,
)
from ._images import IMAGE_TYPE, Frame, ImageTap
from ._mcap import McapFile, Part
from ._sensors import SensorTrack

if TYPE_CHECKING:
    from ..kinematics import Kinematics

log = logging.getLogger("agentsdk.recording")

#: seconds between hand-offs (and chunk flushes), of wall time (realtime) or robot time (lockstep): a killed run
#: loses at most about this much
FLUSH_INTERVAL = 0.5

#: message type of every channel, per output kind ("agentsdk": replayable; "ros2": standard types only)
CHANNEL_TYPES: dict[str, dict[str, str]] = {
    "agentsdk": {
        JOINT_STATES: "sensor_msgs/msg/JointState",
        JOINT_COMMANDS: COMMAND_TYPE,
        SAFETY_EVENTS: EVENT_TYPE,
        TRANSITIONS: TRANSITION_TYPE,
        TF: "tf2_msgs/msg/TFMessage",
        ROBOT_DESCRIPTION: "std_msgs/msg/String",
    },
    "ros2": {
        JOINT_STATES: "sensor_msgs/msg/JointState",
        JOINT_COMMANDS: "sensor_msgs/msg/JointState",
        TF: "tf2_msgs/msg/TFMessage",
        ROBOT_DESCRIPTION: "std_msgs/msg/String",
    },
}

CMD_FIELDS = ("sp_q", "sp_v", "sp_a", "sp_e", "kp", "kd", "en", "mode", "target")


# ------------------------------------------------------------------ blocks
class Block:
    """Preallocated per-tick rows (one control tick per row), reused for the whole run."""

    __slots__ = ("e", "en", "kd", "kp", "mode", "q", "sp_a", "sp_e", "sp_q", "sp_v", "ss", "sv", "t", "target", "tc",
                 "v")

    def __init__(self, cap: int, n: int, width: int = 0, sensors: int = 0) -> None:
        #: sensor values (the recorded sensors' values side by side) and their stamps (robot time, s)
        self.sv = np.empty((cap, width))
        self.ss = np.empty((cap, sensors))
        self.t = np.empty(cap)
        self.tc = np.empty(cap)
        self.q = np.empty((cap, n))
        self.v = np.empty((cap, n))
        self.e = np.empty((cap, n))
        self.sp_q = np.empty((cap, n))
        self.sp_v = np.empty((cap, n))
        self.sp_a = np.empty((cap, n))
        self.sp_e = np.empty((cap, n))
        self.kp = np.empty((cap, n))
        self.kd = np.empty((cap, n))
        self.target = np.empty((cap, n))
        self.en = np.empty((cap, n), dtype=bool)
        self.mode = np.empty((cap, n), dtype=np.int8)

    @staticmethod
    def row_bytes(n: int, width: int = 0, sensors: int = 0) -> int:
        """Bytes per row."""
        return 16 + n * (10 * 8 + 2) + 8 * (width + sensors)


@dataclass
class Job:
    """A filled block handed to the writer: ``rows`` ticks, side messages, whether ticks were dropped before it."""

    block: Block | None
    rows: int
    side: list[tuple[int, str, tuple[str | float, ...]]]
    final: bool = False
    gap: bool = False
    #: camera frames copied into the image pool since the last job
    images: list[Frame] = field(default_factory=list)


@dataclass
class Rows:
    """What one block contributes to the file (copies: the block goes back to the pool)."""

    st_ns: np.ndarray
    q: np.ndarray
    v: np.ndarray
    e: np.ndarray
    cmd_ns: np.ndarray
    cmd: dict[str, np.ndarray]
    tf_ns: np.ndarray
    tf_q: np.ndarray
    sn_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    sv: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    ss: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))


# ------------------------------------------------------------------ row selection
class Selector:
    """Chooses the rows to write, block after block (its state carries across blocks).

    Joint states: every tick, or the first tick of every ``1/rate`` interval of
    robot time.  ``/tf``: likewise at ``tf_rate``.  Commands: every tick whose
    setpoint differs from the previous tick's, plus the tick before each change
    (flat holds in a line plot) and the run's last tick; block boundaries add
    nothing (the last row of a block is held back until the next block shows
    whether it precedes a change).
    """

    def __init__(
        self, t0: float, rate: float | None, tf_rate: float | None, *, sensor_rate: float | None = None,
        sensor_width: int = 0, sensor_count: int = 0,
    ) -> None:
        self.rate, self.tf_rate = rate, tf_rate
        # sensor rows: sampled like the states at sensor_rate (none without recorded sensors)
        self.sensor_rate, self.sensor_width, self.sensor_count = sensor_rate, sensor_width, sensor_count
        self._last_sn = math.floor(t0 * sensor_rate + 1e-6) if sensor_rate else 0
        self._last_sample = math.floor(t0 * rate + 1e-6) if rate else 0
        self._last_tf = math.floor(t0 * tf_rate + 1e-6) if tf_rate else 0  # sampled like the states
        self._last_cmd: tuple[np.ndarray, ...] | None = None
        self._held: tuple[int, tuple[np.ndarray, ...]] | None = None
        # the last tick's state and /tf rows, held back with a held command so the file stays in time order
        self._carry: tuple[np.ndarray, ...] | None = None

    def _sampled(self, t: np.ndarray, rate: float, last: int) -> tuple[np.ndarray, int]:
        s = np.floor(t * rate + 1e-6).astype(np.int64)
        prev = np.concatenate(([last], s[:-1]))
        return np.flatnonzero(s != prev), int(s[-1])

    def select(self, b: Block | None, m: int, final: bool, gap: bool) -> Rows | None:
        rows = self._select(b, m, final, gap)
        carry, self._carry = self._carry, None
        if carry is not None:
            if rows is None:
                self._carry = carry
            else:
                rows = self._prepend(rows, carry)
        if rows is not None and self._held is not None and not final:
            rows = self._hold_tail(rows, self._held[0])
        return rows

    def _prepend(self, r: Rows, carry: tuple[np.ndarray, ...]) -> Rows:
        st_ns, q, v, e, tf_ns, tf_q, sn_ns, sv, ss = carry
        return Rows(
            np.concatenate((st_ns, r.st_ns)), np.concatenate((q, r.q)), np.concatenate((v, r.v)),
            np.concatenate((e, r.e)), r.cmd_ns, r.cmd, np.concatenate((tf_ns, r.tf_ns)), np.concatenate((tf_q, r.tf_q)),
            np.concatenate((sn_ns, r.sn_ns)), np.concatenate((sv, r.sv)), np.concatenate((ss, r.ss)),
        )

    def _hold_tail(self, r: Rows, held_ns: int) -> Rows:
        """Keep the rows stamped after the held command for the next block."""
        s = int(np.searchsorted(r.st_ns, held_ns, side="right"))
        t = int(np.searchsorted(r.tf_ns, held_ns, side="right"))
        u = int(np.searchsorted(r.sn_ns, held_ns, side="right"))
        self._carry = (r.st_ns[s:], r.q[s:], r.v[s:], r.e[s:], r.tf_ns[t:], r.tf_q[t:], r.sn_ns[u:], r.sv[u:], r.ss[u:])
        return Rows(r.st_ns[:s], r.q[:s], r.v[:s], r.e[:s], r.cmd_ns, r.cmd, r.tf_ns[:t], r.tf_q[:t],
                    r.sn_ns[:u], r.sv[:u], r.ss[:u])

    def _select(self, b: Block | None, m: int, final: bool, gap: bool) -> Rows | None:
        if b is None or m == 0:
            if final and (self._held is not None or self._carry is not None):
                n = len(self._held[1][0]) if self._held is not None else self._carry[1].shape[1]  # type: ignore[index]
                z = np.zeros((0, n))
                cmd_ns = np.zeros(0, np.int64)
                kinds = {"en": bool, "mode": np.int8}
                cmd = {f: np.zeros((0, n), dtype=kinds.get(f, float)) for f in CMD_FIELDS}
                if self._held is not None:  # the run's last tick, held back by the previous block
                    last_ns, row = self._held
                    cmd_ns = np.array([last_ns], np.int64)
                    cmd = {f: r[None] for f, r in zip(CMD_FIELDS, row, strict=True)}
                self._held = None
                none = np.zeros(0, np.int64)
                return Rows(none, z, z, z, cmd_ns, cmd, none, z, none, *self._no_sensors())
            return None
        t = b.t[:m]
        if self.rate is None:
            st_rows = np.arange(m)
        else:
            st_rows, self._last_sample = self._sampled(t, self.rate, self._last_sample)
            if final and (not len(st_rows) or st_rows[-1] != m - 1):
                st_rows = np.append(st_rows, m - 1)  # the run's last state: the recording ends where the run did
        if self.tf_rate:
            tf_rows, self._last_tf = self._sampled(t, self.tf_rate, self._last_tf)
        else:
            tf_rows = np.zeros(0, np.intp)
        if not self.sensor_count:
            sn_rows = np.zeros(0, np.intp)
        elif self.sensor_rate is None:
            sn_rows = np.arange(m)
        else:
            sn_rows, self._last_sn = self._sampled(t, self.sensor_rate, self._last_sn)
        arrays = [getattr(b, f)[:m] for f in CMD_FIELDS]
        changed = np.zeros(m, dtype=bool)
        last = self._last_cmd
        changed[0] = last is None or gap
        for k, a in enumerate(arrays):
            if m > 1:
                changed[1:] |= (a[1:] != a[:-1]).any(axis=1)
            if last is not None:
                changed[0] |= bool((a[0] != last[k]).any())
        keep = changed.copy()
        keep[:-1] |= changed[1:]  # the last tick of a hold, so line plots stay flat
        if final:
            keep[-1] = True
        self._last_cmd = tuple(a[m - 1].copy() for a in arrays)
        cmd_rows = np.flatnonzero(keep)
        ns = np.rint(t * NS_PER_S).astype(np.int64)
        cns = np.rint(b.tc[:m] * NS_PER_S).astype(np.int64)
        held, self._held = self._held, None
        if not keep[-1]:
            self._held = (int(cns[m - 1]), self._last_cmd)
        cmd = {f: a[cmd_rows] for f, a in zip(CMD_FIELDS, arrays, strict=True)}
        cmd_ns = cns[cmd_rows]
        if held is not None and (changed[0] or gap):
            h_ns, h_row = held
            cmd = {f: np.concatenate((r[None], cmd[f])) for f, r in zip(CMD_FIELDS, h_row, strict=True)}
            cmd_ns = np.concatenate(([h_ns], cmd_ns))
        if self.sensor_count:
            sv, ss = b.sv[sn_rows], b.ss[sn_rows]
        else:
            sv, ss = self._no_sensors()
        return Rows(ns[st_rows], b.q[st_rows], b.v[st_rows], b.e[st_rows], cmd_ns, cmd, ns[tf_rows], b.q[tf_rows],
                    ns[sn_rows], sv, ss)

    def _no_sensors(self) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros((0, self.sensor_width)), np.zeros((0, self.sensor_count))


# ------------------------------------------------------------------ /tf from FK
class TfTree:
    """Parent -> child transforms of every non-root link, for many joint states at once."""

    def __init__(self, kin: Kinematics) -> None:
        self.kin = kin
        parents = dict(kin.parents)
        links = list(kin.link_names)
        index = {name: i for i, name in enumerate(links)}
        self.children: list[str] = list(parents)
        self.parents: list[str] = [parents[c] for c in self.children]
        self._ci = np.array([index[c] for c in self.children], dtype=np.intp)
        self._pi = np.array([index[p] for p in self.parents], dtype=np.intp)

    def transforms(self, qs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(translation (S, L, 3), rotation (S, L, 4) x y z w)`` for ``S`` joint states."""
        frames = [self.kin.link_frames(q) for q in qs]
        p = np.array([f[0] for f in frames]).reshape(len(qs), -1, 3)
        r = np.array([f[1] for f in frames]).reshape(len(qs), -1, 4)
        pp, pr = p[:, self._pi], r[:, self._pi]
        inv = pr * np.array([-1.0, -1.0, -1.0, 1.0])
        trans = _qrot(inv, p[:, self._ci] - pp)
        rot = _qmul(inv, r[:, self._ci])
        rot /= np.linalg.norm(rot, axis=-1, keepdims=True)
        return trans, rot


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) quaternions in (x, y, z, w) order."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def _qrot(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate (..., 3) vectors by (..., 4) unit quaternions (x, y, z, w)."""
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return np.asarray(v + w * t + np.cross(u, t))


# ------------------------------------------------------------------ one MCAP file
def foxglove_urdf(urdf: str) -> str:
    """Mesh paths as ``file://`` URLs (what Foxglove's URDF loader resolves); ``package://`` stays."""
    return re.sub(r'filename="(/[^"]*)"', lambda m: f'filename="file://{m.group(1)}"', urdf)


class Output:
    """One MCAP file: the agentsdk format (replayable) or ``ros2`` (standard message types only).

    Both are rosbag2 MCAP files (profile ``ros2``, ``ros2msg`` schemas, ``cdr``
    messages, the ``rosbag2`` metadata record), compressed with zstd chunks.
    """

    def __init__(
        self, path: Path, *, kind: str, names: Sequence[str], metadata: Mapping[str, str],
        sensors: Sequence[SensorTrack] = (),
        images: Sequence[str] = (),
    ) -> None:
        from .. import __version__

        self.path, self.kind = path, kind
        self.names = list(names)
        try:
            self.stream: IO[bytes] = open(path, "wb")  # closed in close()
        except OSError as exc:
            raise ConfigurationError(f"cannot write recording {path}: {exc.strerror or exc}") from exc
        try:
            # The agentsdk kind has no chunk or message index: message indexes cost 16 uncompressed bytes a
            # message (a third of the file), and readers that find chunk indexes (Foxglove, rosbags) look
            # messages up through them. Without them, readers stream the file (it is in log-time order).
            # The ros2 kind keeps both for ROS 2 tooling.
            self.file = f = McapFile(
                self.stream, profile="ros2", library=f"agentsdk {__version__}", message_index=kind == "ros2"
            )
            self.types = dict(CHANNEL_TYPES[kind])
            # sensors as their ROS messages (the ros2 kind: only the standard message types)
            self.sensors = tuple(
                t for t in sensors if kind == "agentsdk" or not t.msg_type.startswith("agentsdk_msgs/")
            )
            for track in self.sensors:
                self.types[track.topic] = track.msg_type
            for topic in images:
                self.types[topic] = IMAGE_TYPE
            sids = {t: f.schema(t, "ros2msg", MSGDEFS[t].encode()) for t in sorted(set(self.types.values()))}
            self.channels: dict[str, int] = {}
            for topic, msg_type in self.types.items():
                qos = QOS_LATCHED if topic == ROBOT_DESCRIPTION else QOS_DEFAULT
                self.channels[topic] = f.channel(topic, "cdr", sids[msg_type], {"offered_qos_profiles": qos})
            md = dict(metadata)
            if kind == "ros2":
                md["format"] = ROS2_FORMAT  # not replayable: the commands carry no modes or gains
            f.metadata(METADATA_NAME, md)
            self.state = joint_state_layout(self.names)
            self.command: FixedLayout = command_layout(self.names) if kind == "agentsdk" else self.state
            self.tf: FixedLayout | None = None
            self.sensor_layouts = [t.layout() for t in self.sensors]
            self._sensor_cols = np.array([sensors.index(t) for t in self.sensors], dtype=np.intp)
            #: per recorded sensor, the stamp of its last message (a sample is written once)
            self._sensor_last = np.full(len(self.sensors), -math.inf)
            self.flush()  # the header, schemas and metadata reach the disk at once
        except OSError as exc:
            with contextlib.suppress(OSError):  # closing flushes what the full disk refused again
                self.stream.close()
            raise ConfigurationError(f"cannot write recording {path}: {exc.strerror or exc}") from exc

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic."""
        per_id = self.file.stats.channel_message_counts
        return {topic: per_id[cid] for topic, cid in self.channels.items()}

    def description(self, ns: int, urdf: str) -> None:
        """The robot description, once, at the start."""
        data = strings_message(None, [urdf if self.kind == "ros2" else foxglove_urdf(urdf)])
        self.file.chunk([(self.channels[ROBOT_DESCRIPTION], np.array([ns], np.int64), [data])])

    def encode(self, rows: Rows, tf: tuple[TfTree, np.ndarray, np.ndarray] | None) -> list[Part]:
        """Every message of a block, one part per channel (commands first: they win ties of stamps)."""
        ch = self.channels
        state_cols = {"position": rows.q, "velocity": rows.v, "effort": rows.e}
        out: list[Part] = [
            (ch[JOINT_COMMANDS], rows.cmd_ns, self._commands(rows)),
            (ch[JOINT_STATES], rows.st_ns, self.state.encode(rows.st_ns, state_cols)),
        ]
        if tf is not None:
            tree, trans, rot = tf
            if self.tf is None:
                self.tf = tf_layout(tree.parents, tree.children)
            cols: dict[str, np.ndarray] = {}
            for i in range(len(tree.children)):
                cols[f"t{i}"], cols[f"r{i}"] = trans[:, i], rot[:, i]
            stamps = [f"{i}." for i in range(len(tree.children))]
            out.append((ch[TF], rows.tf_ns, self.tf.encode(rows.tf_ns, cols, stamps)))
        if self.sensors and len(rows.sn_ns):
            out.extend(self._sensor_parts(rows))
        return out

    def _sensor_parts(self, rows: Rows) -> list[Part]:
        """Each sensor's new samples among the sampled rows: logged at the tick, stamped when measured."""
        parts: list[Part] = []
        for i, (track, lay) in enumerate(zip(self.sensors, self.sensor_layouts, strict=True)):
            stamps = rows.ss[:, self._sensor_cols[i]]
            prev = np.concatenate(([self._sensor_last[i]], stamps[:-1]))
            keep = np.flatnonzero(np.isfinite(stamps) & (stamps != prev))
            self._sensor_last[i] = stamps[-1]
            if not len(keep):
                continue
            header_ns = np.rint(stamps[keep] * NS_PER_S).astype(np.int64)
            values = rows.sv[keep, track.offset : track.offset + track.size]
            parts.append((self.channels[track.topic], rows.sn_ns[keep], lay.encode(header_ns, track.columns(values))))
        return parts

    def _commands(self, rows: Rows) -> np.ndarray:
        c = rows.cmd
        cols = {"position": c["sp_q"], "velocity": c["sp_v"], "effort": c["sp_e"]}
        if self.kind == "agentsdk":
            cols.update(acceleration=c["sp_a"], kp=c["kp"], kd=c["kd"], target=c["target"],
                        mode=c["mode"].view(np.uint8), enabled=c["en"].view(np.uint8))
        return self.command.encode(rows.cmd_ns, cols)

    def side(self, side: list[tuple[int, str, tuple[str | float, ...]]]) -> list[Part]:
        """Safety events and transitions (only the agentsdk kind has their message types), one part per topic."""
        parts: list[Part] = []
        for topic in (SAFETY_EVENTS, TRANSITIONS):
            items = sorted((x for x in side if x[1] == topic and topic in self.channels), key=lambda x: x[0])
            if items:
                stamps = np.array([x[0] for x in items], dtype=np.int64)
                parts.append((self.channels[topic], stamps, [strings_message(x[0], x[2]) for x in items]))
        return parts

    def flush(self) -> None:
        """Push what is written to the OS: a killed process keeps every chunk written so far."""
        self.file.flush()

    def close(self, ok: bool = True) -> None:
        """Write the summary and the rosbag2 metadata, and close the file."""
        try:
            if ok:
                self.file.metadata("rosbag2", {"serialized_metadata": self._rosbag2_metadata()})
                self.file.finish()
        finally:
            self.stream.close()

    def _rosbag2_metadata(self) -> str:
        import yaml

        st = self.file.stats
        start = st.message_start_time
        total = st.message_count
        span = {"nanoseconds": max(0, st.message_end_time - start)}
        info = {
            "rosbag2_bagfile_information": {
                "version": 8,
                "storage_identifier": "mcap",
                "relative_file_paths": [self.path.name],
                "duration": span,
                "starting_time": {"nanoseconds_since_epoch": start},
                "message_count": total,
                "topics_with_message_count": [
                    {
                        "topic_metadata": {
                            "name": topic,
                            "type": self.types[topic],
                            "serialization_format": "cdr",
                            "offered_qos_profiles": QOS_LATCHED if topic == ROBOT_DESCRIPTION else QOS_DEFAULT,
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
                        "duration": span,
                        "message_count": total,
                    }
                ],
            }
        }
        return str(yaml.safe_dump(info, sort_keys=False))


# ------------------------------------------------------------------ the thread
class WriterThread:
    """Consumes :class:`Job` s from a queue on its own thread and returns each block to ``free`` when done."""

    def __init__(
        self,
        outputs: list[Output],
        selector: Selector,
        free: queue.SimpleQueue[Block],
        *,
        kinematics: Callable[[], Kinematics] | None,
        description: tuple[int, str] | None,
        names: tuple[str, ...],
        images: ImageTap | None = None,
    ) -> None:
        self.outputs = outputs
        self.images = images
        self.selector = selector
        self.free = free
        self.jobs: queue.SimpleQueue[Job | None] = queue.SimpleQueue()
        self.error: BaseException | None = None
        self._kinematics = kinematics
        self._description = description
        self._names = names
        self.tree: TfTree | None = None
        self.final_counts: dict[str, int] = {}
        self.pending = 0  # jobs queued and not yet written
        self.submitted = 0  # jobs queued so far
        self.done = 0  # jobs written (or dropped after an error) so far
        self._idle = threading.Condition()
        self.thread = threading.Thread(target=self._run, name="agentsdk-recorder-writer", daemon=True)
        self.thread.start()

    def submit(self, job: Job) -> None:
        with self._idle:
            self.pending += 1
            self.submitted += 1
        self.jobs.put(job)

    def wait_idle(self) -> None:
        """Block until every submitted job is written and flushed (not from a running control loop)."""
        with self._idle:
            self._idle.wait_for(lambda: self.pending == 0 or not self.thread.is_alive())

    def wait_written(self, upto: int) -> None:
        """Block until the first ``upto`` submitted jobs are written (later ones may still be queued)."""
        with self._idle:
            self._idle.wait_for(lambda: self.done >= upto or not self.thread.is_alive())

    def stop(self) -> None:
        """Write what is queued, then end the thread (joins it)."""
        self.jobs.put(None)
        self.thread.join()

    # -------------------------------------------------------------- thread body
    def _run(self) -> None:
        try:
            self._describe()
        except BaseException as exc:  # kept for finish() to raise
            self.error = exc
        try:
            self._setup_tf()
        except Exception as exc:  # the file is still written, without /tf
            log.warning("recording without /tf: %s", exc)
        while True:
            job = self.jobs.get()
            if job is None:
                return
            try:
                if self.error is None:
                    self._write(job)
            except BaseException as exc:  # kept for finish() to raise; later jobs are dropped
                self.error = exc
                log.error("writing the recording failed: %s", exc)
            finally:
                if job.images and self.images is not None:
                    self.images.release(job.images)  # encoded frames were already returned: emptied below
                if job.block is not None:
                    self.free.put(job.block)
                with self._idle:
                    self.pending -= 1
                    self.done += 1
                    self._idle.notify_all()

    def _describe(self) -> None:
        if self._description is not None:
            ns, urdf = self._description
            for o in self.outputs:
                o.description(ns, urdf)
                o.flush()

    def _setup_tf(self) -> None:
        if self._kinematics is not None:
            kin = self._kinematics()
            if tuple(kin.joint_names) != self._names:
                raise ConfigurationError("kinematics joint order differs from the robot's")
            self.tree = TfTree(kin)

    def _write(self, job: Job) -> None:
        rows = self.selector.select(job.block, job.rows, job.final, job.gap)
        if rows is not None:
            if job.block is not None:  # the rows are copies: the block can be refilled now
                self.free.put(job.block)
                job.block = None
        tf = None
        if rows is not None:
            if self.tree is not None and len(rows.tf_ns):
                trans, rot = self.tree.transforms(rows.tf_q)
                tf = (self.tree, trans, rot)
        frames, job.images = job.images, []
        encoded = self.images.encode(frames) if frames and self.images is not None else {}
        for o in self.outputs:
            parts = o.encode(rows, tf) if rows is not None else []
            parts += [(o.channels[topic], ns, msgs) for topic, (ns, msgs) in encoded.items() if topic in o.channels]
            o.file.chunk(parts + o.side(job.side))
            o.flush()

    def close_outputs(self, ok: bool) -> None:
        error: BaseException | None = None
        for o in self.outputs:
            try:
                o.close(ok)
            except OSError as exc:
                error = error or exc
        self.final_counts = dict(self.outputs[0].counts) if self.outputs else {}
        self.outputs = []
        if error is not None:
            raise error
