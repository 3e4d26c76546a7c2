"""One MCAP output file (agentsdk JSON or rosbag2 CDR): chunks of rows encoded in log-time order."""

from __future__ import annotations

import heapq
import json
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.writer import CompressionType, Writer

from ..errors import ConfigurationError
from ..types import MODES
from ._channels import (
    JOINT_COMMANDS,
    JOINT_STATES,
    JSON_SCHEMAS,
    METADATA_NAME,
    NS_PER_S,
    QOS_DEFAULT,
    QOS_LATCHED,
    ROBOT_DESCRIPTION,
    ROS2_TOPICS,
    TF,
    json_header,
    json_rows,
)
from ._formats import ROS2_MSGDEFS, Cdr

#: MCAP chunk size: small enough that compressing one chunk is a short pause
_CHUNK_BYTES = 256 * 1024




@dataclass
class RowChunk:
    """Rows selected from one block for output."""

    st_ns: np.ndarray
    q: np.ndarray
    v: np.ndarray
    e: np.ndarray
    cmd_ns: np.ndarray
    cmd: dict[str, np.ndarray]
    tf_ns: np.ndarray
    tf_q: np.ndarray


class Sink:
    """One MCAP output: the agentsdk JSON format (Foxglove-ready) or a rosbag2-compatible CDR file."""

    def __init__(self, path: Path, *, ros2: bool, names: tuple[str, ...], metadata: Mapping[str, str]) -> None:
        from .. import __version__

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
            for topic, msg_type in ROS2_TOPICS.items():
                qos = QOS_LATCHED if topic == ROBOT_DESCRIPTION else QOS_DEFAULT
                self.channels[topic] = w.register_channel(topic, "cdr", sids[msg_type], {"offered_qos_profiles": qos})
                self.counts[topic] = 0
            self.types = dict(ROS2_TOPICS)
        else:
            for topic, schema in JSON_SCHEMAS.items():
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

    def write_chunk(self, c: RowChunk, tf: TfSamples | None) -> Iterator[None]:
        """Write a chunk's messages in log-time order, yielding after each one."""
        names = self.names
        ros2 = self.ros2
        d = c.cmd
        # numpy rows for CDR, JSON-ready lists for the agentsdk format
        q: Any
        v: Any
        e: Any
        cq: Any
        cv: Any
        ce: Any
        if ros2:
            q, v, e = c.q, c.v, c.e
            cq, cv, ce = d["sp_q"], d["sp_v"], d["sp_e"]
        else:
            q, v, e = json_rows(c.q), json_rows(c.v), json_rows(c.e)
            cq, cv, ce, kp, kd, tg = (json_rows(d[f]) for f in ("sp_q", "sp_v", "sp_e", "kp", "kd", "target"))
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
                        "header": json_header(ns),
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
                    msg = {"header": json_header(ns), "name": names, "position": q[i], "velocity": v[i], "effort": e[i]}
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
            self._add(topic, ns, json.dumps({"header": json_header(ns), **msg}).encode())

    def flush(self) -> None:
        """Close the open MCAP chunk and push it to the OS: a killed process keeps everything written so far."""
        self.writer.flush()  # type: ignore[no-untyped-call]  # mcap's Writer has no annotations here

    def close(self, ok: bool = True) -> None:
        """Write the summary (and the rosbag2 metadata) and close the file."""
        try:
            if ok:
                if self.ros2:
                    self.writer.add_metadata("rosbag2", {"serialized_metadata": self._rosbag2_metadata()})
                self.writer.finish()  # type: ignore[no-untyped-call]  # mcap's Writer has no annotations here
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
                        "duration": {"nanoseconds": max(0, self.end_ns - start)},
                        "message_count": sum(self.counts.values()),
                    }
                ],
            }
        }
        return str(yaml.safe_dump(info, sort_keys=False))


def _fox_transforms(ns: int, tf: TfSamples, i: int) -> list[dict[str, Any]]:
    sec, nsec = divmod(ns, NS_PER_S)
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
class TfSamples:
    """Link transforms of the TF samples of one chunk."""

    ns: np.ndarray
    parents: list[str]
    children: list[str]
    trans: np.ndarray  # (S, L, 3)
    rot: np.ndarray  # (S, L, 4) x, y, z, w


def foxglove_urdf(urdf: str) -> str:
    """Mesh paths as ``file://`` URLs (what Foxglove's URDF loader resolves); ``package://`` stays."""
    return re.sub(r'filename="(/[^"]*)"', lambda m: f'filename="file://{m.group(1)}"', urdf)
