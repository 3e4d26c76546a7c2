"""Where a robot starts: robot.yaml, an SRDF group state, the model's own pose, or 0 clipped into the limits.

The start pose is decided once, here, and every backend, the self-collision model,
``agentsdk check`` and the CAN emulator use it. Per joint, the first that applies:

1. robot.yaml ``initial_positions``;
2. the SRDF ``<group_state>`` named by robot.yaml ``initial_group_state`` (MoveIt's
   named robot states; the SRDF is robot.yaml ``srdf`` or the one found beside the URDF);
3. the description's own start pose (an MJCF ``home`` keyframe);
4. 0, clipped into the joint's limits (a joint whose range excludes 0 starts at its
   nearest limit; these joints are listed in one warning per connection).

Values from 2 and 3 outside a joint's limits are clipped too and listed the same way;
robot.yaml values outside the limits are a configuration error (:func:`check_config`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from lxml import etree

from ..config import RobotConfig
from ..errors import ConfigurationError, DescriptionError
from ..types import JointInfo
from .model import RobotDescription

__all__ = ["StartPose", "read_group_states", "start_pose"]

log = logging.getLogger("agentsdk.description")


@dataclass(frozen=True)
class StartPose:
    """The start position of every commanded joint and where each came from.

    ``positions``: ``{joint: position}`` for every joint, in joint order; ``sources``:
    ``{joint: "robot.yaml" | "srdf <state>" | "model" | "zero"}``; ``clipped``: joints whose
    value was moved into their limits (with the value before clipping).
    """

    positions: Mapping[str, float]
    sources: Mapping[str, str]
    clipped: Mapping[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        """Where the pose came from, with joint counts (``2 joints from robot.yaml initial_positions, 4 at 0``)."""
        labels = {"robot.yaml": "from robot.yaml initial_positions", "model": "from the model's home keyframe",
                  "zero": "at 0"}
        counts: dict[str, int] = {}
        for src in self.sources.values():
            label = labels.get(src) or f"from SRDF group_state {src.removeprefix('srdf ')!r}"
            counts[label] = counts.get(label, 0) + 1
        parts = [f"{n} {'joint' if n == 1 else 'joints'} {label}" for label, n in counts.items()]
        return ", ".join(parts) or "no joints"

    def warning(self, robot: str) -> str | None:
        """The one warning listing the clipped joints, or None."""
        if not self.clipped:
            return None
        items = ", ".join(f"{name} {raw:g} -> {self.positions[name]:g}" for name, raw in self.clipped.items())
        return (
            f"robot '{robot}': the start pose is outside the limits of {len(self.clipped)} joint(s), clipped into "
            f"their range: {items} (set initial_positions or initial_group_state in robot.yaml)"
        )


def read_group_states(path: Path) -> dict[str, dict[str, float]]:
    """Every SRDF ``<group_state>``: ``{state name: {joint: value}}`` (states of one name merged).

    Multi-value joints (a floating ``root_joint``'s pose) are left out.
    """
    try:
        root = etree.parse(str(path), etree.XMLParser(resolve_entities=False, no_network=True)).getroot()
    except (OSError, etree.XMLSyntaxError) as exc:
        raise DescriptionError(f"{path}: cannot read the SRDF: {exc}") from exc
    states: dict[str, dict[str, float]] = {}
    for elem in root.iter("group_state"):
        name = elem.get("name")
        if not name:
            continue
        values = states.setdefault(name, {})
        for joint in elem.iter("joint"):
            jname, text = joint.get("name"), (joint.get("value") or "").split()
            if not jname or len(text) != 1:
                continue
            try:
                values[jname] = float(text[0])
            except ValueError as exc:
                raise DescriptionError(
                    f"{path}: group_state {name!r}, joint {jname!r}: {text[0]!r} is not a number"
                ) from exc
    return states


def _srdf_state(description: RobotDescription, config: RobotConfig) -> tuple[str, dict[str, float]]:
    state = config.initial_group_state
    assert state is not None
    srdf = config.srdf_path or description.srdf
    label = f"robot '{config.name or description.name}'"
    if srdf is None:
        raise ConfigurationError(
            f"{label}: initial_group_state {state!r} names an SRDF group state, but there is no SRDF "
            "(none beside the URDF; set srdf: in robot.yaml)"
        )
    if not srdf.is_file():
        raise ConfigurationError(f"{label}: srdf {srdf} not found")
    states = read_group_states(srdf)
    if state not in states:
        known = ", ".join(sorted(states)) or "(none)"
        raise ConfigurationError(f"{label}: {srdf.name} has no group_state {state!r}; its group states: {known}")
    return state, states[state]


def start_pose(
    description: RobotDescription, config: RobotConfig, joints: Sequence[JointInfo] | None = None
) -> StartPose:
    """The start pose of ``joints`` (default: the description's; pass them with robot.yaml limit overrides)."""
    joints = tuple(joints if joints is not None else description.joints)
    layers: list[tuple[str, Mapping[str, float]]] = [("robot.yaml", config.initial_positions)]
    if config.initial_group_state:
        name, values = _srdf_state(description, config)
        layers.append((f"srdf {name}", values))
    layers.append(("model", description.default_positions))
    positions: dict[str, float] = {}
    sources: dict[str, str] = {}
    clipped: dict[str, float] = {}
    for j in joints:
        value, source = 0.0, "zero"
        for src, layer in layers:
            if j.name in layer:
                value, source = float(layer[j.name]), src
                break
        lo, hi = j.lower, j.upper
        inside = min(max(value, lo), hi) if not (math.isnan(lo) or math.isnan(hi)) else value
        if inside != value:
            clipped[j.name] = value
        positions[j.name] = inside
        sources[j.name] = source
    return StartPose(positions, sources, clipped)
