"""Where a robot starts: robot.yaml, a named pose of the description, or 0 clipped into the limits.

The start pose is decided once, here, and every backend, the self-collision model,
``agentsdk check`` and the CAN emulator use it. Per joint, the first that applies:

1. robot.yaml ``initial_positions``;
2. the named pose robot.yaml ``initial_group_state`` names: an MJCF keyframe of that name,
   else an SRDF ``<group_state>`` (MoveIt's named robot states; the SRDF is robot.yaml
   ``srdf`` or the one found beside the URDF);
3. when robot.yaml names none, the description's own start pose: the first of
   :data:`~agentsdk.description.mjcf.START_STATE_NAMES` (``home``, ``stand``, ``standing``,
   ``ready``, ...) that the MJCF's keyframes, or the SRDF's group states, hold;
4. 0, clipped into the joint's limits (a joint whose range excludes 0 starts at its
   nearest limit; these joints are listed in one warning per connection).

Values from 2 and 3 outside a joint's limits are clipped too and listed the same way;
robot.yaml values outside the limits are a configuration error (:func:`check_config`).
An MJCF keyframe also places what is not a commanded joint (a floating base, passive
joints): :attr:`StartPose.keyframe` names the one a simulator starts from.
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

__all__ = ["StartPose", "default_group_state", "read_group_states", "start_pose"]

log = logging.getLogger("agentsdk.description")


@dataclass(frozen=True)
class StartPose:
    """The start position of every commanded joint and where each came from.

    ``positions``: ``{joint: position}`` for every joint, in joint order; ``sources``:
    ``{joint: "robot.yaml" | "srdf <state>" | "keyframe <name>" | "zero"}``; ``clipped``: joints whose
    value was moved into their limits (with the value before clipping).
    """

    positions: Mapping[str, float]
    sources: Mapping[str, str]
    clipped: Mapping[str, float] = field(default_factory=dict)
    #: the MJCF keyframe the simulator state starts from (base pose, passive joints), or None
    keyframe: str | None = None

    def summary(self) -> str:
        """Where the pose came from, with joint counts (``2 joints from robot.yaml initial_positions, 4 at 0``)."""
        labels = {"robot.yaml": "from robot.yaml initial_positions", "zero": "at 0"}
        counts: dict[str, int] = {}
        for src in self.sources.values():
            label = labels.get(src) or (
                f"from the model's {src.removeprefix('keyframe ')} keyframe"
                if src.startswith("keyframe ")
                else f"from SRDF group_state {src.removeprefix('srdf ')!r}"
            )
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
    keyframes = ", ".join(sorted(description.named_states))
    if srdf is None:
        if description.format == "mjcf":
            raise ConfigurationError(
                f"{label}: initial_group_state {state!r} names no keyframe of {description.source.name} "
                f"(its keyframes: {keyframes or '(none)'})"
            )
        raise ConfigurationError(
            f"{label}: initial_group_state {state!r} names an SRDF group state, but there is no SRDF "
            "(none beside the URDF; set srdf: in robot.yaml)"
        )
    if not srdf.is_file():
        raise ConfigurationError(f"{label}: srdf {srdf} not found")
    states = read_group_states(srdf)
    if state not in states:
        known = ", ".join(sorted(states)) or "(none)"
        also = f" (keyframes of {description.source.name}: {keyframes})" if keyframes else ""
        raise ConfigurationError(f"{label}: {srdf.name} has no group_state {state!r}; its group states: {known}{also}")
    return state, states[state]


def default_group_state(description: RobotDescription, config: RobotConfig) -> tuple[str, dict[str, float]] | None:
    """The SRDF group state a URDF robot starts in when robot.yaml names none, or None.

    The first of :data:`~agentsdk.description.mjcf.START_STATE_NAMES` the SRDF (robot.yaml
    ``srdf``, else the one beside the URDF) holds; an unreadable SRDF gives none here (the
    self-collision model reports it).
    """
    from .mjcf import START_STATE_NAMES

    srdf = config.srdf_path or description.srdf
    if description.format != "urdf" or srdf is None or not srdf.is_file():
        return None
    try:
        states = read_group_states(srdf)
    except DescriptionError:
        return None
    for name in START_STATE_NAMES:
        if name in states:
            return name, states[name]
    return None


def start_pose(
    description: RobotDescription, config: RobotConfig, joints: Sequence[JointInfo] | None = None
) -> StartPose:
    """The start pose of ``joints`` (default: the description's; pass them with robot.yaml limit overrides)."""
    joints = tuple(joints if joints is not None else description.joints)
    layers: list[tuple[str, Mapping[str, float]]] = [("robot.yaml", config.initial_positions)]
    keyframe = description.default_state if description.format == "mjcf" else None
    named = config.initial_group_state
    if named and named in description.named_states and config.srdf_path is None:
        layers.append((f"keyframe {named}", description.named_states[named]))
        keyframe = named
    elif named:
        name, values = _srdf_state(description, config)
        layers.append((f"srdf {name}", values))
    else:
        found = default_group_state(description, config)
        if found is not None:
            layers.append((f"srdf {found[0]}", found[1]))
    if description.default_state is not None and keyframe == description.default_state:
        layers.append((f"keyframe {description.default_state}", description.default_positions))
    elif description.default_positions and description.default_state is None:
        layers.append(("keyframe home", description.default_positions))
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
    return StartPose(positions, sources, clipped, keyframe)
