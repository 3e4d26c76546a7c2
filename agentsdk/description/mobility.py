"""Does a robot look legged or mobile? What ``agentsdk check`` and ``describe`` tell the user to set.

A robot looks **legged** when its root link has no fixed parent (a URDF root other than
``world``, or an MJCF free joint) and at least two of its limbs (chains leaving the base
link) end in feet: links named ``foot``, ``feet``, ``toe``, ``sole`` or ``ankle``, or, without
such names, limbs hanging down from the base at the start pose (see :func:`_legs_below`). It looks
**mobile** (wheeled) when two or more links below movable joints are named ``wheel`` or
``caster``. A robot that looks either way but is welded to the world (no ``floating_base``)
gets the robot.yaml settings that let it stand or roll on the ground.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

from .model import RobotDescription

__all__ = ["Mobility", "mobility"]

_FOOT = re.compile(r"foot|feet|toe|sole|ankle", re.IGNORECASE)
_WHEEL = re.compile(r"wheel|caster", re.IGNORECASE)


@dataclass(frozen=True)
class Mobility:
    """What the robot looks like: ``kind``, the base link, the links that touch the ground, whether it floats."""

    kind: Literal["legged", "mobile"]
    base: str
    contacts: tuple[str, ...]
    #: how the base floats now: ``"free joint"`` (MJCF), ``"robot.yaml"`` (floating_base), or None (welded)
    floating: str | None
    #: the SRDF group state or MJCF keyframe the robot starts in, if any
    start_state: str | None = None

    def lines(self) -> list[str]:
        """The report: what it looks like, and what to set when its base is welded to the world."""
        what = "legged" if self.kind == "legged" else "mobile (wheeled)"
        parts = "feet" if self.kind == "legged" else "wheels"
        shown = ", ".join(self.contacts[:6]) + (", ..." if len(self.contacts) > 6 else "")
        head = f"looks {what}: base link '{self.base}' with {len(self.contacts)} {parts} ({shown})"
        if self.floating is not None:
            how = "a free joint in the model" if self.floating == "free joint" else "robot.yaml floating_base: true"
            return [f"{head}; the base floats ({how}): base_state() reports its pose and twist"]
        state = (
            f"it starts in '{self.start_state}'"
            if self.start_state
            else "also set initial_group_state (a standing pose) or initial_positions"
        )
        return [
            f"{head}; its root has no fixed parent, but the simulators weld it to the world",
            f"  to {'stand' if self.kind == 'legged' else 'drive'} on the ground set in robot.yaml: "
            f"floating_base: true ({state})",
        ]


def _limb_of(description: RobotDescription, link: str, base: str) -> str | None:
    """The child of ``base`` that ``link`` hangs from (None when ``link`` is not below ``base``)."""
    parent = {j.child: j.parent for j in description.all_joints}
    current = link
    while current in parent:
        if parent[current] == base:
            return current
        current = parent[current]
    return None


def _below_movable(description: RobotDescription, link: str) -> bool:
    joints = {j.child: j for j in description.all_joints}
    current = link
    while current in joints:
        j = joints[current]
        if j.movable:
            return True
        current = j.parent
    return False


def mobility(
    description: RobotDescription,
    floating_base: bool = False,
    start_state: str | None = None,
    positions: Mapping[str, float] | None = None,
) -> Mobility | None:
    """How the robot looks (see the module docstring), or None for a robot that does neither.

    ``floating_base``: robot.yaml ``floating_base``; ``start_state``: the named pose it starts in;
    ``positions``: the start pose (for limbs hanging down without a foot name; default 0).
    """
    free = description.free_root
    if free is None and description.format == "mjcf" and not floating_base:
        return None  # an MJCF body without a free joint is welded to the world as written
    if free is None and description.format == "urdf" and description.root_link == "world" and not floating_base:
        root_out = description.child_joints("world")
        if all(not j.movable for j in root_out):
            return None  # welded to the world on purpose
    base = description.base_link
    while True:  # the link the limbs leave: below a root rigidly attached to a single child (base -> trunk)
        out = description.child_joints(base)
        if len(out) != 1 or out[0].movable:
            break
        base = out[0].child
    links = [rec.name for rec in description.link_records if rec.name != base]
    floating = "free joint" if free is not None else ("robot.yaml" if floating_base else None)
    feet = [n for n in links if _FOOT.search(n) and _below_movable(description, n)]
    limbs = {_limb_of(description, n, base) for n in feet} - {None}
    if len(limbs) >= 2:
        # one foot per limb: the lowest named link of each (the last in tree order)
        order = description.tree_order()
        per_limb: dict[str, str] = {}
        for n in sorted(feet, key=order.index):
            limb = _limb_of(description, n, base)
            if limb is not None:
                per_limb[limb] = n
        return Mobility("legged", base, tuple(per_limb.values()), floating, start_state)
    wheels = [n for n in links if _WHEEL.search(n) and _below_movable(description, n)]
    if len(wheels) >= 2:
        return Mobility("mobile", base, tuple(wheels), floating, start_state)
    legs = _legs_below(description, base, positions or {})
    if len(legs) >= 2:
        return Mobility("legged", base, tuple(legs), floating, start_state)
    return None


def _legs_below(description: RobotDescription, base_link: str, positions: Mapping[str, float]) -> list[str]:
    """The lowest link of each limb hanging down from the base at the start pose (feet without a foot name).

    A limb (a subtree of the base with a movable joint) is a leg when its lowest link is, within 20 %,
    as far below the base as the lowest of all, and that drop is at least a third of the robot's size
    (arms held out sideways or up are not legs). Link frames are compared (no geometry).
    """
    import mujoco
    import numpy as np

    from .mjspec import build_spec, mjcf_spec_without_actuators

    try:
        if description.format == "mjcf":
            model = mjcf_spec_without_actuators(str(description.source)).compile()
        else:
            model = build_spec(description, {}).spec.compile()
    except Exception:  # a model MuJoCo cannot compile: the loaders and simulators report it
        return []
    data = mujoco.MjData(model)
    for name, q in positions.items():
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid >= 0 and model.jnt_type[jid] in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            data.qpos[model.jnt_qposadr[jid]] = q
    mujoco.mj_kinematics(model, data)
    base = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, base_link)
    if base < 0:
        return []
    parent = model.body_parentid

    def subtree(b: int) -> list[int]:
        out = [b]
        for c in range(1, model.nbody):
            if parent[c] == b and c != b:
                out.extend(subtree(c))
        return out

    limbs: list[tuple[float, str]] = []
    z0 = float(data.xpos[base][2])
    size = 0.0
    for child in range(1, model.nbody):
        if parent[child] != base or child == base:
            continue
        bodies = subtree(child)
        size = max(size, max(float(np.linalg.norm(data.xpos[b] - data.xpos[base])) for b in bodies))
        if not any(model.body_jntnum[b] for b in bodies):
            continue
        low = min(bodies, key=lambda b: float(data.xpos[b][2]))
        limbs.append((z0 - float(data.xpos[low][2]), mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, low) or ""))
    if not limbs:
        return []
    deepest = max(drop for drop, _ in limbs)
    if deepest <= 0.0 or deepest < size / 3:
        return []
    return [name for drop, name in limbs if drop >= 0.8 * deepest and name]


def report_lines(description: RobotDescription, config: object, start: object | None = None) -> list[str]:
    """``check`` / ``describe`` lines on the base: floating or welded, legged or mobile, what to set (may be empty).

    ``config``: the robot.yaml :class:`~agentsdk.config.RobotConfig`; ``start``: the
    :class:`~agentsdk.description.start.StartPose` (names the pose it starts in).
    """
    from ..config import RobotConfig
    from .start import StartPose

    assert isinstance(config, RobotConfig)
    state = None
    if isinstance(start, StartPose):
        for src in start.sources.values():
            if src.startswith(("srdf ", "keyframe ")):
                state = src.split(" ", 1)[1]
                break
    out: list[str] = []
    positions = dict(start.positions) if isinstance(start, StartPose) else None
    looks = mobility(description, bool(config.floating_base), state, positions)
    free = description.free_root
    if free is not None:
        ground = "the model's own floor"
        try:
            from .mjcf_scene import has_ground
            from .mjspec import mjcf_spec_without_actuators

            if description.format == "mjcf" and not has_ground(
                mjcf_spec_without_actuators(str(description.source)).compile()
            ):
                ground = "a ground plane the simulators add (the model has no floor)"
        except Exception:  # the simulators report a model MuJoCo cannot compile
            ground = "unknown (MuJoCo cannot compile the model)"
        out.append(f"floating base: '{free}' (a free joint at the root), standing on {ground}")
    if looks is not None:
        out.extend(looks.lines())
    return [*out, ""] if out else []
