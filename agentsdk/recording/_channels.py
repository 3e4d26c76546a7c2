"""The recording's layout: format and metadata names, topics, their JSON schemas and ROS 2 types, stamps."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..types import MODES
from ._formats import FRAME_TRANSFORMS_SCHEMA, STRING_SCHEMA

FORMAT = "agentsdk-recording/1"
METADATA_NAME = "agentsdk"

JOINT_STATES = "/joint_states"
JOINT_COMMANDS = "/joint_commands"
SAFETY_EVENTS = "/safety/events"
TRANSITIONS = "/behavior/transitions"
TF = "/tf"
ROBOT_DESCRIPTION = "/robot_description"
TOPICS = (JOINT_STATES, JOINT_COMMANDS, SAFETY_EVENTS, TRANSITIONS, TF, ROBOT_DESCRIPTION)
ROS2_TOPICS = {
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


QOS_DEFAULT = _qos(2)
QOS_LATCHED = _qos(1)  # like robot_state_publisher's /robot_description

NS_PER_S = 1_000_000_000

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
        "duration": {"type": ["number", "null"], "description": "seconds spent in source (transitions)"},
        "configuration": {"type": "string", "description": "the root machine's active configuration after it"},
    },
}
JSON_SCHEMAS = {
    JOINT_STATES: JOINT_STATE_SCHEMA,
    JOINT_COMMANDS: JOINT_COMMAND_SCHEMA,
    SAFETY_EVENTS: SAFETY_EVENT_SCHEMA,
    TRANSITIONS: TRANSITION_SCHEMA,
    TF: FRAME_TRANSFORMS_SCHEMA,
    ROBOT_DESCRIPTION: STRING_SCHEMA,
}


def stamp_ns(t: float) -> int:
    """Robot time ``t`` (s) as integer nanoseconds, the recording's log time."""
    return round(t * NS_PER_S)


def json_header(ns: int) -> dict[str, Any]:
    """A ``std_msgs/Header`` for the JSON channels, stamped ``ns``."""
    sec, nsec = divmod(ns, NS_PER_S)
    return {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": ""}


def json_rows(a: np.ndarray) -> list[list[Any]]:
    """Rows as lists; non-finite floats become null (JSON has no NaN/inf)."""
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        return [[x if math.isfinite(x) else None for x in row] for row in a.tolist()]
    rows: list[list[Any]] = a.tolist()
    return rows


def robot_spec_for_metadata(spec: str | os.PathLike[str]) -> str:
    """A robot spec that still resolves from another directory: names stay, paths become absolute."""
    text = os.fspath(spec)
    is_path = "/" in text or os.sep in text or text.lower().endswith((".urdf", ".xacro", ".yaml", ".yml"))
    return str(Path(text).expanduser().resolve()) if is_path else text
