"""The self-collision model, decided once from the description and used by every simulator.

Which pairs of links may collide is a property of the robot, not of the
simulator: MuJoCo by default collides every pair except parent/child bodies
(and never bodies welded together or to the world), PyBullet collides none
(or, with its flags, everything but parents). Here the pairs are decided once,
with the rules MoveIt's setup assistant applies (``compute_default_collisions``):

* only links with collision geometry take part;
* **adjacent** links never collide: connected by a joint, or through links
  that have no collision geometry (MoveIt connects the neighbours of a
  geometry-less link to each other), or rigidly attached to links so
  connected (a camera fixed to a tilting head and the pan link the head
  turns on: MoveIt connects a fixed child to its parent's neighbours, and
  MuJoCo's parent filter works on bodies welded together);
* **rigidly attached** links never collide: connected by fixed joints only
  (they cannot move relative to each other; MuJoCo cannot collide them at all);
* links **touching at the start pose** (within :data:`TOUCH_DISTANCE`, on the
  convex hulls both simulators use) do not collide - they would be stuck
  together from the first step. ``self_collision: true`` keeps these pairs;
* an SRDF's ``<disable_collisions>`` (and ``<disable_default_collisions>``,
  ``<enable_collisions>``) are honoured.

``self_collision: false`` turns every pair off. The touching test compiles
the robot in MuJoCo (collision shapes only); collision meshes MuJoCo cannot
read are dropped here - for both simulators - and reported as repairs.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import math
import re
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from lxml import etree

from ..errors import DescriptionError
from .meshes import MeshError, simulator_mesh
from .model import Geometry, Repair, RobotDescription

__all__ = [
    "TOUCH_DISTANCE",
    "SelfCollision",
    "SrdfRules",
    "for_robot",
    "from_mjcf",
    "lowest_point",
    "read_srdf",
    "self_collision",
    "standing_height",
]

log = logging.getLogger("agentsdk.description")

#: links closer than this at the start pose (m) count as touching
TOUCH_DISTANCE = 0.002

Pair = tuple[str, str]
Mode = Literal["auto", "true", "false"]


def _pair(a: str, b: str) -> Pair:
    return (a, b) if a <= b else (b, a)


@dataclass(frozen=True)
class SrdfRules:
    """The collision part of an SRDF: pairs disabled, links disabled entirely, pairs re-enabled."""

    path: Path
    disabled: Mapping[Pair, str] = field(default_factory=dict)
    disabled_links: frozenset[str] = frozenset()
    enabled: frozenset[Pair] = frozenset()
    unknown_links: frozenset[str] = frozenset()


def read_srdf(path: Path, links: frozenset[str] | set[str]) -> SrdfRules:
    """Read the ``<disable_collisions>``-family elements of an SRDF; links not in ``links`` are ignored."""
    try:
        root = etree.parse(str(path), etree.XMLParser(resolve_entities=False, no_network=True)).getroot()
    except (OSError, etree.XMLSyntaxError) as exc:
        raise DescriptionError(f"{path}: cannot read the SRDF: {exc}") from exc
    disabled: dict[Pair, str] = {}
    enabled: set[Pair] = set()
    disabled_links: set[str] = set()
    unknown: set[str] = set()
    for elem in root.iter("disable_collisions", "enable_collisions"):
        a, b = elem.get("link1"), elem.get("link2")
        if not a or not b:
            continue
        missing = {x for x in (a, b) if x not in links}
        if missing:
            unknown |= missing
            continue
        if elem.tag == "disable_collisions":
            disabled[_pair(a, b)] = elem.get("reason") or "Disabled"
        else:
            enabled.add(_pair(a, b))
    for elem in root.iter("disable_default_collisions"):
        name = elem.get("link")
        if name in links:
            disabled_links.add(name)
        elif name:
            unknown.add(name)
    return SrdfRules(path, disabled, frozenset(disabled_links), frozenset(enabled), frozenset(unknown))


@dataclass(frozen=True)
class SelfCollision:
    """Which links collide with which, for every simulator.

    ``shapes`` maps each link to the ``(index, shape)`` collision shapes the
    simulators build (meshes no simulator can read are left out, see
    ``repairs``); ``pairs`` are the link pairs that collide (sorted names);
    ``excluded`` maps every other pair of links with geometry to the reason.
    """

    mode: Mode
    shapes: Mapping[str, tuple[tuple[int, Geometry], ...]]
    pairs: frozenset[Pair]
    excluded: Mapping[Pair, str]
    repairs: tuple[Repair, ...] = ()
    srdf: Path | None = None
    start: Mapping[str, float] = field(default_factory=dict)
    #: ``(link, index)`` of meshes MuJoCo must treat as shells (open or flat meshes: no volume)
    shell: frozenset[tuple[str, int]] = frozenset()

    def reasons(self) -> dict[str, int]:
        """How many pairs each rule left out."""
        out: dict[str, int] = {}
        for reason in self.excluded.values():
            key = reason.split(":")[0]
            out[key] = out.get(key, 0) + 1
        return out


_CACHE: dict[tuple[object, ...], SelfCollision] = {}
_CACHE_LOCK = threading.Lock()


def self_collision(
    description: RobotDescription,
    *,
    mode: Mode | bool = "auto",
    start: Mapping[str, float] | None = None,
    srdf: Path | None = None,
) -> SelfCollision:
    """Decide the self-collision pairs (see the module docstring); cached per description, mode, pose, SRDF.

    ``start`` gives commanded-joint positions (others 0; mimic joints follow);
    ``srdf`` defaults to the one found beside the description.
    """
    if description.format != "urdf":
        raise ValueError("the self-collision model is decided from URDF descriptions; an MJCF model keeps its own")
    mode = "true" if mode is True else "false" if mode is False else mode
    if mode not in ("auto", "true", "false"):
        raise ValueError(f"self_collision must be auto, true or false, got {mode!r}")
    start = dict(start or {})
    srdf = srdf if srdf is not None else description.srdf
    key = (
        str(description.source),
        hashlib.sha1(description.urdf_xml.encode()).hexdigest(),
        mode,
        tuple(sorted(start.items())),
        str(srdf),
    )
    with _CACHE_LOCK:
        cached = _CACHE.get(key)
    if cached is not None:
        return cached
    result = _compute(description, mode, start, srdf)
    with _CACHE_LOCK:
        _CACHE[key] = result
    return result


def _compute(description: RobotDescription, mode: Mode, start: dict[str, float], srdf: Path | None) -> SelfCollision:
    repairs: list[Repair] = []
    shapes: dict[str, list[tuple[int, Geometry]]] = {}
    for rec in description.link_records:
        kept: list[tuple[int, Geometry]] = []
        for i, geom in enumerate(rec.collisions):
            if geom.kind == "mesh":
                assert geom.filename is not None
                try:
                    simulator_mesh(geom.filename)
                except MeshError as exc:
                    repairs.append(Repair(f"link '{rec.name}' <collision> {i}", f"{exc}: dropped"))
                    continue
            kept.append((i, geom))
        shapes[rec.name] = kept

    shell: set[tuple[str, int]] = set()
    model, data = _compile(description, shapes, repairs, shell, margin=TOUCH_DISTANCE if mode == "auto" else 0.0)
    geometric = sorted(n for n, s in shapes.items() if s)
    candidates = [_pair(a, b) for a, b in itertools.combinations(geometric, 2)]
    excluded: dict[Pair, str] = {}
    if mode == "false":
        excluded = {p: "self_collision: false" for p in candidates}
    else:
        group = _rigid_groups(description)
        adjacent = _adjacent_pairs(description, set(geometric))
        rules = read_srdf(srdf, set(description.links)) if srdf is not None else None
        touching = _touching(description, model, data, start) if mode == "auto" and model is not None else set()
        for p in candidates:
            a, b = p
            if group[a] == group[b]:
                excluded[p] = "rigidly attached"
            elif p in adjacent:
                excluded[p] = "adjacent"
            elif rules is not None and p not in rules.enabled and (
                p in rules.disabled or a in rules.disabled_links or b in rules.disabled_links
            ):
                excluded[p] = f"srdf: {rules.disabled.get(p, 'disable_default_collisions')}"
            elif p in touching:
                excluded[p] = "touching at the start pose"
    pairs = frozenset(p for p in candidates if p not in excluded)
    return SelfCollision(
        mode=mode,
        shapes={n: tuple(s) for n, s in shapes.items()},
        pairs=pairs,
        excluded=excluded,
        repairs=tuple(repairs),
        srdf=srdf if mode != "false" else None,
        start=dict(start),
        shell=frozenset(shell),
    )


_MESH_IN_ERROR = re.compile(r"(?:Element name|mesh) '(mesh\d+)'")


def _compile(
    description: RobotDescription,
    shapes: dict[str, list[tuple[int, Geometry]]],
    repairs: list[Repair],
    shelled: set[tuple[str, int]],
    margin: float,
) -> tuple[object, object]:
    """Compile the collision model; meshes MuJoCo refuses get shell inertia, then are dropped (a repair)."""
    import mujoco

    from .mjspec import build_spec

    for _ in range(2 * sum(len(s) for s in shapes.values()) + 2):
        build = build_spec(description, shapes, margin=margin, shell=frozenset(shelled))
        try:
            model = build.spec.compile()
        except Exception as exc:
            text = str(exc)
            match = _MESH_IN_ERROR.search(text)
            owner = build.meshes.get(match.group(1)) if match else None
            if owner is None:
                raise DescriptionError(
                    f"{description.source}: MuJoCo cannot build robot '{description.name}': {' '.join(text.split())}"
                ) from exc
            if owner not in shelled and "volume" in text:
                shelled.add(owner)  # MuJoCo's own advice for open or flat meshes
                continue
            link, index = owner
            shapes[link] = [(i, g) for i, g in shapes[link] if i != index]
            first = text.strip().splitlines()[0] if text.strip() else text
            repairs.append(
                Repair(f"link '{link}' <collision> {index}", f"MuJoCo cannot use the mesh ({first}): dropped")
            )
            continue
        return model, mujoco.MjData(model)
    raise DescriptionError(f"{description.source}: MuJoCo cannot build robot '{description.name}'")


def _rigid_groups(description: RobotDescription) -> dict[str, str]:
    """Each link -> the first link of its group of links connected by fixed joints only."""
    group = {name: name for name in description.links}

    def find(x: str) -> str:
        while group[x] != x:
            group[x] = group[group[x]]
            x = group[x]
        return x

    for j in description.all_joints:
        if not j.movable:
            ra, rb = find(j.parent), find(j.child)
            if ra != rb:
                group[rb] = ra
    return {name: find(name) for name in description.links}


def _adjacent_pairs(description: RobotDescription, geometric: set[str]) -> set[Pair]:
    """Pairs of geometric links joined directly, or through links without collision geometry.

    Also the links of two rigid groups (links joined by fixed joints) joined that way: a link
    fixed to a moving link is adjacent to the links its joint turns against.
    """
    out = _adjacent_links(description, geometric)
    group = _rigid_groups(description)
    members: dict[str, list[str]] = {}
    for name in sorted(geometric):
        members.setdefault(group[name], []).append(name)
    neighbours: dict[str, set[str]] = {g: set() for g in set(group.values())}
    for j in description.all_joints:
        a, b = group[j.parent], group[j.child]
        if a != b:
            neighbours[a].add(b)
            neighbours[b].add(a)
    for start in members:
        seen = {start}
        stack = list(neighbours[start])
        while stack:
            other = stack.pop()
            if other in seen:
                continue
            seen.add(other)
            if other in members:
                out.update(_pair(a, b) for a in members[start] for b in members[other])
            else:
                stack.extend(neighbours[other])
    return out


def _adjacent_links(description: RobotDescription, geometric: set[str]) -> set[Pair]:
    """Pairs of geometric links joined directly, or through links without collision geometry."""
    neighbours: dict[str, set[str]] = {name: set() for name in description.links}
    for j in description.all_joints:
        neighbours[j.parent].add(j.child)
        neighbours[j.child].add(j.parent)
    out: set[Pair] = set()
    for link in geometric:
        seen = {link}
        stack = list(neighbours[link])
        while stack:
            other = stack.pop()
            if other in seen:
                continue
            seen.add(other)
            if other in geometric:
                out.add(_pair(link, other))
            else:
                stack.extend(neighbours[other])
    return out


def _touching(description: RobotDescription, model: object, data: object, start: Mapping[str, float]) -> set[Pair]:
    """Link pairs in contact (within the geoms' margin) at the start pose, as MuJoCo sees the convex hulls."""
    import mujoco

    assert isinstance(model, mujoco.MjModel) and isinstance(data, mujoco.MjData)
    q = {name: float(start.get(name, 0.0)) for name in description.joint_names}
    for m in description.mimics:
        q[m.joint] = m.multiplier * q.get(m.leader, 0.0) + m.offset
    for name, value in q.items():
        if not math.isfinite(value):
            continue
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid >= 0:
            data.qpos[model.jnt_qposadr[jid]] = value
    mujoco.mj_kinematics(model, data)
    mujoco.mj_collision(model, data)
    out: set[Pair] = set()
    for c in data.contact[: data.ncon]:
        b1 = model.geom_bodyid[c.geom1]
        b2 = model.geom_bodyid[c.geom2]
        n1 = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b1)
        n2 = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b2)
        if n1 and n2 and n1 != n2:
            out.add(_pair(n1, n2))
    return out


_WARNED: set[int] = set()


def for_robot(description: RobotDescription, config: object, mode: Mode | bool | None = None) -> SelfCollision:
    """The self-collision model for a connected robot: robot.yaml ``self_collision``/``srdf``/``initial_positions``.

    ``mode`` overrides robot.yaml ``self_collision`` (a backend option).
    Geometry repairs found here are logged once, or raise ``DescriptionError``
    under robot.yaml/connect ``strict``.
    """
    from ..config import RobotConfig

    assert isinstance(config, RobotConfig)
    chosen = config.self_collision if mode is None else mode
    from .robot_yaml import apply_overrides
    from .start import start_pose

    start = dict(start_pose(description, config, apply_overrides(description, config)).positions)
    srdf = config.srdf_path or description.srdf
    if srdf is not None and not srdf.is_file():
        raise DescriptionError(f"robot '{description.name}': srdf {srdf} not found")
    result = self_collision(description, mode=chosen, start=start, srdf=srdf)
    if result.repairs:
        lines = "\n".join(f"  - {r}" for r in result.repairs)
        if config.strict:
            raise DescriptionError(
                f"{description.source}: strict mode refuses the repairs the simulators need:\n{lines}"
            )
        if id(result) not in _WARNED:
            _WARNED.add(id(result))
            log.warning("robot '%s' (%s): collision shapes no simulator can use:\n%s",
                        description.name, description.source, lines)
    return result


def from_mjcf(description: RobotDescription, config: object | None = None) -> SelfCollision:
    """An MJCF model's own contact settings (contype/conaffinity, excludes, MuJoCo's filters) as link pairs.

    With robot.yaml ``config`` (``self_collision: auto``, the default), bodies touching at the
    start pose are left out as the MuJoCo backend leaves them out
    (:mod:`agentsdk.description.mjcf_scene`).
    """
    import mujoco

    from ..config import RobotConfig
    from .mjcf import colliding_body_pairs
    from .mjcf_scene import start_qpos, touching_at_start
    from .mjspec import mjcf_spec_without_actuators

    if description.format != "mjcf":
        raise ValueError("from_mjcf needs an MJCF description")
    model = mjcf_spec_without_actuators(str(description.source)).compile()
    pairs = colliding_body_pairs(model, world=False)
    shapes = {rec.name: tuple(enumerate(rec.collisions)) for rec in description.link_records}
    geometric = sorted(n for n, s in shapes.items() if s)
    candidates = [_pair(a, b) for a, b in itertools.combinations(geometric, 2)]
    excluded = {p: "mjcf contact settings" for p in candidates if p not in pairs}
    start: dict[str, float] = {}
    if isinstance(config, RobotConfig) and config.self_collision == "auto":
        from .robot_yaml import apply_overrides
        from .start import start_pose

        pose = start_pose(description, config, apply_overrides(description, config))
        start = dict(pose.positions)
        data = mujoco.MjData(model)
        mimics = [(m.joint, m.leader, m.multiplier, m.offset) for m in description.mimics]
        start_qpos(model, data, start, pose.keyframe, mimics)
        for p in touching_at_start(model, data):
            if p in pairs:
                excluded[p] = "touching at the start pose"
    return SelfCollision(
        mode="auto",
        shapes=shapes,
        pairs=frozenset(p for p in candidates if p in pairs and p not in excluded),
        excluded=excluded,
        start=start,
    )


_HEIGHTS: dict[int, tuple[SelfCollision, float]] = {}


def lowest_point(model: object, data: object, geoms: Iterable[int]) -> float:
    """The lowest world ``z`` of ``geoms`` at ``data``'s kinematics (inf when none has a shape).

    Mesh vertices (the convex hulls both simulators collide), exact for spheres, capsules,
    cylinders, boxes and ellipsoids; planes and height fields are left out.
    """
    import mujoco
    import numpy as np

    assert isinstance(model, mujoco.MjModel) and isinstance(data, mujoco.MjData)
    gt = mujoco.mjtGeom
    lowest = math.inf
    for g in geoms:
        pos, rot, size = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3), model.geom_size[g]
        kind = int(model.geom_type[g])
        axis_z = float(rot[2, 2])
        if kind == gt.mjGEOM_MESH:
            mid = int(model.geom_dataid[g])
            adr, num = int(model.mesh_vertadr[mid]), int(model.mesh_vertnum[mid])
            z = float((model.mesh_vert[adr:adr + num] @ rot[2]).min()) + float(pos[2])
        elif kind == gt.mjGEOM_SPHERE:
            z = float(pos[2]) - float(size[0])
        elif kind == gt.mjGEOM_CAPSULE:
            z = float(pos[2]) - abs(axis_z) * float(size[1]) - float(size[0])
        elif kind == gt.mjGEOM_CYLINDER:
            z = float(pos[2]) - abs(axis_z) * float(size[1]) - float(size[0]) * math.sqrt(max(0.0, 1 - axis_z**2))
        elif kind == gt.mjGEOM_BOX:
            z = float(pos[2]) - float(np.abs(rot[2]) @ size[:3])
        elif kind == gt.mjGEOM_ELLIPSOID:
            z = float(pos[2]) - float(np.linalg.norm(rot[2] * size[:3]))
        else:
            continue
        lowest = min(lowest, z)
    return lowest


def standing_height(description: RobotDescription, collision: SelfCollision) -> float:
    """How high the root link's frame must be for the robot to stand on the ground plane ``z = 0``.

    The robot at its start pose (``collision.start``), root frame upright at the origin: the
    height is minus the lowest point of its collision shapes (mesh vertices - the convex hulls
    both simulators collide -, exact for spheres, capsules, cylinders and boxes), so the lowest
    shape touches the ground. The same number for every simulator (one floating-base placement).
    """
    cached = _HEIGHTS.get(id(collision))
    if cached is not None and cached[0] is collision:
        return cached[1]
    import mujoco

    from .mjspec import build_spec

    model = build_spec(description, collision.shapes, shell=collision.shell).spec.compile()
    data = mujoco.MjData(model)
    for name, q in collision.start.items():
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid >= 0:
            data.qpos[model.jnt_qposadr[jid]] = q
    for mimic in description.mimics:
        jf = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, mimic.joint)
        jl = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, mimic.leader)
        if jf >= 0 and jl >= 0:
            data.qpos[model.jnt_qposadr[jf]] = mimic.offset + mimic.multiplier * data.qpos[model.jnt_qposadr[jl]]
    mujoco.mj_kinematics(model, data)
    lowest = lowest_point(model, data, range(model.ngeom))
    height = 0.0 if not math.isfinite(lowest) else -lowest
    _HEIGHTS[id(collision)] = (collision, height)
    return height
