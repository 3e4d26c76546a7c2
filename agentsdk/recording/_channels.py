"""The recording's layout: format and metadata names, topics, QoS records, stamps."""

from __future__ import annotations

import os
from pathlib import Path

#: the format of the recordings written now (CDR, commands with the setpoint's acceleration); the older
#: :data:`CDR2_FORMAT` (commands without it) and :data:`JSON_FORMAT` files are still read
FORMAT = "agentsdk-recording/3"
#: CDR recordings written before the commands carried the setpoint's acceleration (replayed without it)
CDR2_FORMAT = "agentsdk-recording/2"
JSON_FORMAT = "agentsdk-recording/1"
#: ``--record-format ros2`` files: standard message types only, not replayable
ROS2_FORMAT = "agentsdk-recording/2+ros2"
METADATA_NAME = "agentsdk"

JOINT_STATES = "/joint_states"
JOINT_COMMANDS = "/joint_commands"
SAFETY_EVENTS = "/safety/events"
TRANSITIONS = "/behavior/transitions"
TF = "/tf"
ROBOT_DESCRIPTION = "/robot_description"
TOPICS = (JOINT_STATES, JOINT_COMMANDS, SAFETY_EVENTS, TRANSITIONS, TF, ROBOT_DESCRIPTION)


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

def stamp_ns(t: float) -> int:
    """Robot time ``t`` (s) as integer nanoseconds, the recording's log time."""
    return round(t * NS_PER_S)


def robot_spec_for_metadata(spec: str | os.PathLike[str]) -> str:
    """A robot spec that still resolves from another directory: names stay, paths become absolute."""
    text = os.fspath(spec)
    is_path = "/" in text or os.sep in text or text.lower().endswith((".urdf", ".xacro", ".yaml", ".yml"))
    return str(Path(text).expanduser().resolve()) if is_path else text
