"""Reading a recording back: :class:`RunData` and :func:`read_recording`, including files cut short."""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from mcap.records import Channel, Chunk, Footer, Message, Metadata
from mcap.stream_reader import StreamReader, breakup_chunk

from ..backend import ModeCode
from ..errors import ConfigurationError
from ._channels import (
    FORMAT,
    JOINT_COMMANDS,
    JOINT_STATES,
    METADATA_NAME,
    NS_PER_S,
    ROBOT_DESCRIPTION,
    SAFETY_EVENTS,
    TF,
)

log = logging.getLogger("agentsdk.recording")


# ------------------------------------------------------------------ data
@dataclass
class RunData:
    """A recorded run as arrays (joint columns in ``names`` order; times in ns of robot time).

    .. attribute:: truncated
       :type: bool

       True when the file was cut short (the recording process was killed): read up to its last
       complete chunk.
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
                item = {"time": log_time / NS_PER_S, **msg}
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
