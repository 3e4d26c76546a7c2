"""URDF and xacro loading: parse like ROS (urdfdom's rules), repair visibly what simulators cannot take.

What is required and what defaults follow ``urdfdom`` (``urdf_parser/src/
joint.cpp``, ``link.cpp``, ``model.cpp``, ``pose.cpp``):

* ``<robot name>``, ``<link name>``, ``<joint name type>`` and each joint's
  ``<parent link>``/``<child link>`` are required; names are unique; the
  links form one tree (one root, no loops, one parent per link).
* revolute and prismatic joints need a ``<limit>``; a ``<limit>`` needs
  ``effort`` and ``velocity``; ``lower``/``upper`` default to 0; a continuous
  joint needs no ``<limit>``; ``<axis>`` defaults to ``1 0 0``; ``<origin>``
  to identity; ``<mimic>`` needs ``joint`` (``multiplier`` 1, ``offset`` 0);
  ``<dynamics>`` damping and friction default to 0.
* geometry is one of box, cylinder, sphere, mesh (``capsule``, a common
  extension that both simulators read, is accepted too); sizes are not
  checked by urdfdom.
* attributes in other XML namespaces (``drake:acceleration``) are ignored,
  even when their prefix is not declared (urdfdom's tinyxml2 does not
  process namespaces).

Repairs (each listed once in a warning, refused with ``strict=True``):
degenerate inertias and massless moving links (see :mod:`.inertia`),
``effort``/``velocity`` limits of 0 (the SolidWorks exporter writes
``<limit lower="0" upper="0" effort="0" velocity="0"/>`` when nothing was
entered: that placeholder means "no limits"), negative ``effort``/``velocity``
limits (repairs only tighten: the magnitude is kept, the velocity capped at the
default), ``lower > upper`` (no valid range: the joint is held fixed),
zero-size shapes and unreadable or missing meshes (dropped), mimic joints
that name a missing or fixed joint (the mimic is ignored), floating and
planar joints (held fixed: the SDK commands revolute, continuous and
prismatic joints). Values a legal file leaves out (a continuous joint
without ``<limit>``) get defaults, listed in ``defaults``.

Genuinely broken files raise :class:`DescriptionError` with the file, the
line (plain URDF) and the element: malformed XML, a missing link, a loop, a
missing required attribute, a number that is not a number.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, cast

from lxml import etree

from ..errors import DescriptionError
from ..types import JointInfo
from .inertia import repair_inertials
from .model import (
    ACTUATED_TYPES,
    DEFAULT_VELOCITY,
    Geometry,
    Inertial,
    JointRecord,
    LinkRecord,
    Repair,
    RobotDescription,
)
from .packages import Resolver
from .xacro_expand import TRUST_HINT, run_xacro

__all__ = ["find_srdf", "load_urdf"]

log = logging.getLogger("agentsdk.description")

_JOINT_TYPES = (*ACTUATED_TYPES, "fixed", "floating", "planar")
_GEOMETRIES = ("box", "cylinder", "sphere", "mesh", "capsule")
#: mesh formats the simulators read directly or after conversion to STL (trimesh)
MESH_SUFFIXES = (".stl", ".obj", ".dae", ".ply", ".off", ".glb", ".gltf", ".3mf")

Vec3 = tuple[float, float, float]


def xml_parser() -> etree.XMLParser:
    """The lxml parser for descriptions: no entities, no network, comments and blank text dropped."""
    return etree.XMLParser(
        resolve_entities=False, no_network=True, huge_tree=False, remove_comments=True, remove_blank_text=True
    )


class Where:
    """Builds DescriptionErrors that say where the problem is (file, line, element)."""

    def __init__(self, path: Path, expanded: bool) -> None:
        self.path = path
        self.expanded = expanded

    def line(self, elem: Any) -> int | None:
        """The element's line in the file (None after xacro expansion)."""
        if self.expanded or elem is None:
            return None
        return cast(int | None, getattr(elem, "sourceline", None))

    def __call__(self, elem: Any, msg: str) -> DescriptionError:
        if self.expanded:
            return DescriptionError(f"{self.path} (after xacro expansion): {msg}")
        line = self.line(elem)
        if line:
            return DescriptionError(f"{self.path}, line {line}: {msg}")
        return DescriptionError(f"{self.path}: {msg}")


def _numbers(
    where: Where,
    elem: Any,
    attr: str,
    owner: str,
    count: int | tuple[int, ...],
    default: tuple[float, ...] | None = None,
) -> tuple[float, ...]:
    raw = elem.get(attr)
    if raw is None:
        if default is None:
            raise where(elem, f"{owner}: <{elem.tag}> is missing the '{attr}' attribute")
        return default
    parts = raw.replace(",", " ").split()
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise where(elem, f'{owner}: <{elem.tag} {attr}="{raw}">: not a number') from None
    counts = (count,) if isinstance(count, int) else count
    if len(values) not in counts:
        need = " or ".join(str(c) for c in counts)
        raise where(elem, f'{owner}: <{elem.tag} {attr}="{raw}"> needs {need} number(s), got {len(values)}')
    if not all(math.isfinite(v) for v in values):
        raise where(elem, f'{owner}: <{elem.tag} {attr}="{raw}"> must be finite')
    return values


def _number(where: Where, elem: Any, attr: str, owner: str, default: float | None = None) -> float:
    return _numbers(where, elem, attr, owner, 1, None if default is None else (default,))[0]


def _origin(where: Where, parent: Any, owner: str) -> tuple[Vec3, Vec3]:
    origin = parent.find("origin")
    if origin is None:
        return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    xyz = _numbers(where, origin, "xyz", owner, 3, (0.0, 0.0, 0.0))
    rpy = _numbers(where, origin, "rpy", owner, 3, (0.0, 0.0, 0.0))
    return cast(Vec3, xyz), cast(Vec3, rpy)


# --------------------------------------------------------------------------- XML


_UNDECLARED = re.compile(r"Namespace prefix (\S+) (?:for \S+ )?on \S+ is not defined")


_DECLARATION = re.compile(rb"<\?xml\b[^>]*\?>")


def _like_tinyxml(data: bytes) -> bytes:
    """Read the bytes the way urdfdom does: up to the first NUL (a C string), any ``<?xml ...?>`` ignored.

    tinyxml2 accepts ``<?xml version="0.0"?>`` and a declaration after blank
    lines, which libxml2 refuses; the declaration is blanked out with spaces
    (newlines kept) so that line numbers stay put. The text is read as UTF-8.
    """
    data = data.split(b"\0", 1)[0]
    return _DECLARATION.sub(lambda m: bytes(b if b in b"\r\n" else 32 for b in m.group(0)), data)


def _parse_xml(where: Where, data: bytes) -> Any:
    """Parse ``data``; attributes/elements in undeclared namespaces are tolerated like tinyxml2 does."""
    data = _like_tinyxml(data)
    declared: set[str] = set()
    for _ in range(32):
        try:
            return etree.fromstring(data, xml_parser())
        except etree.XMLSyntaxError as exc:
            prefixes = {m.group(1) for e in exc.error_log for m in [_UNDECLARED.search(e.message)] if m}
            prefixes -= declared | {"xml", "xmlns"}
            if not prefixes:
                detail = re.sub(r" \(<string>, line \d+\)$", "", str(exc))
                raise where(None, f"malformed XML: {detail}") from exc
            declared |= prefixes
            data = _declare_prefixes(data, prefixes)
    raise where(None, "malformed XML: too many undeclared namespace prefixes")


def _declare_prefixes(data: bytes, prefixes: set[str]) -> bytes:
    """Declare ``prefixes`` on the root element, on its own line so that line numbers stay put."""
    decl = "".join(f' xmlns:{p}="urn:agentsdk:undeclared:{p}"' for p in sorted(prefixes)).encode()
    m = re.search(rb"<robot\b", data)
    if m is None:
        return data
    return data[: m.end()] + decl + data[m.end():]


# --------------------------------------------------------------------------- links


class _OutsideRoots(Exception):
    """A mesh outside the package roots: refused (not dropped like a missing mesh)."""

    def __init__(self, error: DescriptionError) -> None:
        super().__init__(str(error))
        self.error = error


def _geometry(
    where: Where,
    elem: Any,
    kind: str,
    owner: str,
    resolver: Resolver,
    repairs: list[Repair],
    mesh_files: list[Path],
    dropped: list[Any],
) -> Geometry | None:
    """Parse one <visual>/<collision>; a malformed one is dropped (urdfdom skips it too), with a repair."""
    try:
        return _parse_geometry(where, elem, kind, owner, resolver, repairs, mesh_files, dropped)
    except _OutsideRoots as exc:
        raise exc.error from None
    except DescriptionError as exc:
        label = f"{owner} <{kind}>" + (f" '{elem.get('name')}'" if elem.get("name") else "")
        problem = str(exc).split(f"{owner}: ", 1)[-1]
        repairs.append(Repair(label, f"{problem}: dropped", where.line(elem)))
        dropped.append(elem)
        return None


def _parse_geometry(
    where: Where,
    elem: Any,
    kind: str,
    owner: str,
    resolver: Resolver,
    repairs: list[Repair],
    mesh_files: list[Path],
    dropped: list[Any],
) -> Geometry | None:
    """Parse one <visual>/<collision>; None (with a repair) for a shape no simulator can use."""
    xyz, rpy = _origin(where, elem, owner)
    geometry = elem.find("geometry")
    label = f"{owner} <{kind}>" + (f" '{elem.get('name')}'" if elem.get("name") else "")

    def drop(reason: str, at: Any) -> None:
        repairs.append(Repair(label, f"{reason}: dropped", where.line(at)))
        dropped.append(elem)

    if geometry is None:
        drop("has no <geometry>", elem)
        return None
    shapes = [c for c in geometry if isinstance(c.tag, str)]
    if not shapes:
        drop("<geometry> is empty", geometry)
        return None
    shape = shapes[0]  # urdfdom reads the first child element
    tag = etree.QName(shape).localname if "}" in shape.tag else shape.tag
    if tag not in _GEOMETRIES:
        drop(f"unknown geometry <{tag}> (URDF has box, cylinder, sphere, mesh)", shape)
        return None
    rgba = None
    material = elem.find("material")
    if material is not None and material.find("color") is not None:
        rgba = cast(
            tuple[float, float, float, float],
            _numbers(where, material.find("color"), "rgba", owner, 4, (1.0, 1.0, 1.0, 1.0)),
        )
    name = elem.get("name")
    if tag == "box":
        size = _numbers(where, shape, "size", owner, 3)
        if min(size) <= 0:
            drop(f"box size {' '.join(f'{s:g}' for s in size)} is not positive", shape)
            return None
        return Geometry("box", size, xyz, rpy, name=name, rgba=rgba)
    if tag in ("cylinder", "capsule"):
        radius = _number(where, shape, "radius", owner)
        length = _number(where, shape, "length", owner)
        if radius <= 0 or length < 0 or (tag == "cylinder" and length == 0):
            drop(f"{tag} radius {radius:g} length {length:g} is degenerate", shape)
            return None
        return Geometry(cast(Literal["cylinder", "capsule"], tag), (radius, length), xyz, rpy, name=name, rgba=rgba)
    if tag == "sphere":
        radius = _number(where, shape, "radius", owner)
        if radius <= 0:
            drop(f"sphere radius {radius:g} is not positive", shape)
            return None
        return Geometry("sphere", (radius,), xyz, rpy, name=name, rgba=rgba)
    uri = shape.get("filename")
    if not uri:
        drop("<mesh> has no filename", shape)
        return None
    scale: tuple[float, ...] = (1.0, 1.0, 1.0)
    if shape.get("scale") is not None:
        scale = _numbers(where, shape, "scale", owner, (1, 3))
        if len(scale) == 1:
            scale = (scale[0],) * 3
    if any(s == 0 for s in scale):
        drop(f"mesh scale {' '.join(f'{s:g}' for s in scale)} has a zero component", shape)
        return None
    resolved, problem = resolver.resolve(uri)
    if resolved is None:
        drop(f"cannot resolve mesh '{uri}': {problem}", shape)
        return None
    escape = resolver.escape(resolved)
    if escape:
        raise _OutsideRoots(where(shape, f"{label}: mesh '{uri}' refused: {escape} ({TRUST_HINT})"))
    if resolved.suffix.lower() not in MESH_SUFFIXES:
        drop(f"mesh '{uri}': format '{resolved.suffix}' is not readable (use {', '.join(MESH_SUFFIXES)})", shape)
        return None
    shape.set("filename", str(resolved))
    if resolved not in mesh_files:
        mesh_files.append(resolved)
    return Geometry("mesh", scale, xyz, rpy, filename=resolved, name=name, rgba=rgba)


def _parse_link(
    where: Where,
    link: Any,
    name: str,
    resolver: Resolver,
    repairs: list[Repair],
    mesh_files: list[Path],
    dropped: list[Any],
) -> LinkRecord:
    owner = f"link '{name}'"
    inertial_rec: Inertial | None = None
    inertial = link.find("inertial")
    if inertial is not None:
        xyz, rpy = _origin(where, inertial, owner)
        mass_elem = inertial.find("mass")
        if mass_elem is None:
            raise where(inertial, f"{owner}: <inertial> has no <mass>")
        mass = _number(where, mass_elem, "value", owner)
        if mass < 0:
            raise where(mass_elem, f"{owner}: mass must be >= 0 (got {mass:g})")
        inertia = inertial.find("inertia")
        if inertia is None:
            raise where(inertial, f"{owner}: <inertial> has no <inertia>")
        attrs = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
        values = {attr: _number(where, inertia, attr, owner, 0.0) for attr in attrs}
        missing = [a for a in ("ixx", "iyy", "izz") if inertia.get(a) is None]
        if missing:
            raise where(inertia, f"{owner}: <inertia> is missing the {', '.join(repr(a) for a in missing)} attribute")
        inertial_rec = Inertial(
            mass, xyz, rpy, cast(tuple[float, float, float, float, float, float], tuple(values.values()))
        )
    visuals = tuple(
        g
        for e in link.findall("visual")
        if (g := _geometry(where, e, "visual", owner, resolver, repairs, mesh_files, dropped))
    )
    collisions = tuple(
        g
        for e in link.findall("collision")
        if (g := _geometry(where, e, "collision", owner, resolver, repairs, mesh_files, dropped))
    )
    return LinkRecord(name, inertial_rec, visuals, collisions)


# --------------------------------------------------------------------------- joints


def _parse_joint(
    where: Where, joint: Any, name: str, links: set[str], repairs: list[Repair], defaults: list[Repair]
) -> JointRecord:
    owner = f"joint '{name}'"
    jtype = joint.get("type")
    if jtype is None:
        raise where(joint, f"{owner} has no 'type' attribute")
    if jtype not in _JOINT_TYPES:
        raise where(joint, f"{owner}: unknown joint type '{jtype}' (URDF has {', '.join(_JOINT_TYPES)})")
    ends: dict[str, str] = {}
    for end in ("parent", "child"):
        elem = joint.find(end)
        if elem is None or not elem.get("link"):
            raise where(joint if elem is None else elem, f'{owner} has no <{end} link="..."/>')
        if elem.get("link") not in links:
            raise where(elem, f"{owner}: {end} link '{elem.get('link')}' is not defined")
        ends[end] = elem.get("link")
    if ends["parent"] == ends["child"]:
        raise where(joint, f"{owner} connects link '{ends['parent']}' to itself")
    xyz, rpy = _origin(where, joint, owner)
    line = where.line(joint)
    if jtype in ("floating", "planar"):
        repairs.append(
            Repair(owner, f"{jtype} joint held fixed (the SDK commands revolute, continuous, prismatic joints)", line)
        )
        jtype = "fixed"

    axis_elem = joint.find("axis")
    axis: tuple[float, ...] = (1.0, 0.0, 0.0)
    if axis_elem is not None:
        axis = _numbers(where, axis_elem, "xyz", owner, 3, (1.0, 0.0, 0.0))
    norm = math.sqrt(sum(a * a for a in axis))
    if jtype != "fixed" and norm < 1e-12:
        raise where(axis_elem, f"{owner}: <axis xyz> is zero; a {jtype} joint needs a direction")
    if norm >= 1e-12:
        axis = tuple(a / norm for a in axis)

    mimic_elem = joint.find("mimic")
    mimic = None
    multiplier, offset = 1.0, 0.0
    if mimic_elem is not None and jtype != "fixed":
        mimic = mimic_elem.get("joint")
        if not mimic:
            raise where(mimic_elem, f"{owner}: <mimic> has no 'joint' attribute")
        multiplier = _number(where, mimic_elem, "multiplier", owner, 1.0)
        offset = _number(where, mimic_elem, "offset", owner, 0.0)

    limit = joint.find("limit")
    lower = upper = velocity = effort = None
    if jtype in ACTUATED_TYPES:
        if limit is None:
            if jtype != "continuous":
                raise where(joint, f"{owner}: a {jtype} joint needs a <limit lower upper velocity effort/> (URDF spec)")
            velocity, effort = DEFAULT_VELOCITY[jtype], math.inf
            defaults.append(
                Repair(owner, f"continuous joint without <limit>: velocity {velocity:g}, effort unlimited", line)
            )
            lower, upper = -math.inf, math.inf
        else:
            for attr in ("velocity", "effort"):
                if limit.get(attr) is None:
                    raise where(limit, f"{owner}: <limit> is missing the '{attr}' attribute")
            velocity = _number(where, limit, "velocity", owner)
            effort = _number(where, limit, "effort", owner)
            lower = _number(where, limit, "lower", owner, 0.0)
            upper = _number(where, limit, "upper", owner, 0.0)
            placeholder = velocity == 0 and effort == 0 and lower == 0 and upper == 0 and limit.get("lower") is not None
            no_range = limit.get("lower") is None and limit.get("upper") is None
            notes: list[str] = []
            if jtype == "continuous":
                lower, upper = -math.inf, math.inf
            elif no_range:
                lower, upper = -math.inf, math.inf
                notes.append("<limit> gives neither lower nor upper (urdfdom reads [0, 0], a locked joint): "
                             "no position limits")
            elif placeholder:
                lower, upper = -math.inf, math.inf
                notes.append('<limit lower="0" upper="0" effort="0" velocity="0"/> is an exporter placeholder: '
                             "no position limits")
            elif lower > upper:
                # no valid range: which end was meant is unknown, so the joint does not move at all
                repairs.append(
                    Repair(owner, f"lower={lower:g} > upper={upper:g} leaves no valid range: joint held fixed",
                           where.line(limit))
                )
                jtype, mimic = "fixed", None
                lower = upper = velocity = effort = None
            if velocity is not None and velocity <= 0:
                # a negative limit keeps its magnitude where that is tighter than the default
                fallback = DEFAULT_VELOCITY[jtype] if velocity == 0 else min(-velocity, DEFAULT_VELOCITY[jtype])
                notes.append(f"velocity limit {velocity:g} -> {fallback:g}")
                velocity = fallback
            if effort is not None and effort < 0:
                notes.append(f"effort limit {effort:g} -> {-effort:g} (the sign dropped, the clamp kept)")
                effort = -effort
            elif effort == 0:
                notes.append("effort limit 0 -> unlimited")  # an exporter's 'not entered'
                effort = math.inf
            if notes:
                repairs.append(Repair(owner, "; ".join(notes), where.line(limit)))
    dynamics = joint.find("dynamics")
    damping = friction = 0.0
    if dynamics is not None:
        damping = _number(where, dynamics, "damping", owner, 0.0)
        friction = _number(where, dynamics, "friction", owner, 0.0)
        if damping < 0 or friction < 0:
            repairs.append(
                Repair(owner, f"negative <dynamics> damping {damping:g} / friction {friction:g} set to 0", line)
            )
            damping, friction = max(damping, 0.0), max(friction, 0.0)
    return JointRecord(
        name=name,
        type=jtype,
        parent=ends["parent"],
        child=ends["child"],
        xyz=xyz,
        rpy=rpy,
        axis=cast(Vec3, axis),
        lower=lower,
        upper=upper,
        velocity=velocity,
        effort=effort,
        damping=damping,
        friction=friction,
        mimic=mimic,
        mimic_multiplier=multiplier,
        mimic_offset=offset,
    )


def _check_tree(where: Where, root: Any, links: list[str], joints: list[JointRecord], elems: dict[str, Any]) -> str:
    parent_of: dict[str, JointRecord] = {}
    for j in joints:
        if j.child in parent_of:
            raise where(
                elems[j.name],
                f"link '{j.child}' has two parent joints ('{parent_of[j.child].name}' and '{j.name}'); "
                "a URDF must be a tree",
            )
        parent_of[j.child] = j
    roots = [name for name in links if name not in parent_of]
    if not roots:
        raise where(root, "the joints form a loop: every link has a parent joint, so there is no root link")
    if len(roots) > 1:
        raise where(
            root,
            f"more than one root link ({', '.join(repr(r) for r in roots)}); every link but one needs a parent joint",
        )
    children: dict[str, list[str]] = {}
    for j in joints:
        children.setdefault(j.parent, []).append(j.child)
    reached = {roots[0]}
    stack = [roots[0]]
    while stack:
        for child in children.get(stack.pop(), []):
            if child not in reached:
                reached.add(child)
                stack.append(child)
    unreached = [name for name in links if name not in reached]
    if unreached:
        raise where(root, f"links {', '.join(repr(n) for n in unreached)} are in a kinematic loop, not in the tree")
    return roots[0]


def _resolve_mimics(
    where: Where, records: list[JointRecord], elems: Mapping[str, Any], repairs: list[Repair]
) -> list[JointRecord]:
    """Point every mimic at a commanded joint (following chains); drop mimics of missing/fixed joints."""
    by_name = {r.name: r for r in records}
    out: list[JointRecord] = []
    for rec in records:
        if rec.mimic is None:
            out.append(rec)
            continue
        mult, off = rec.mimic_multiplier, rec.mimic_offset
        chain = [rec.name]
        target = by_name.get(rec.mimic)
        broken = ""
        while True:
            if target is None:
                missing = rec.mimic if len(chain) == 1 else by_name[chain[-1]].mimic
                broken = f"mimics '{rec.mimic}'" + ("" if len(chain) == 1 else f" (through {', '.join(chain[1:])})")
                broken += f", but '{missing}' is not a joint of this robot"
                break
            if target.type not in ACTUATED_TYPES:
                broken = f"mimics '{target.name}', a {target.type} joint"
                break
            if target.name in chain:
                raise where(
                    elems[rec.name],
                    f"joint '{rec.name}': mimic joints form a cycle ({' -> '.join([*chain, target.name])})",
                )
            if target.mimic is None:
                break
            chain.append(target.name)
            mult, off = mult * target.mimic_multiplier, mult * target.mimic_offset + off
            target = by_name.get(target.mimic)
        if broken:
            repairs.append(
                Repair(
                    f"joint '{rec.name}'",
                    f"{broken}: <mimic> ignored, the joint is commanded on its own",
                    where.line(elems[rec.name]),
                )
            )
            out.append(JointRecord(**{**_asdict(rec), "mimic": None, "mimic_multiplier": 1.0, "mimic_offset": 0.0}))
            continue
        assert target is not None
        out.append(JointRecord(**{**_asdict(rec), "mimic": target.name, "mimic_multiplier": mult, "mimic_offset": off}))
    return out


def _asdict(rec: JointRecord) -> dict[str, Any]:
    return {k: getattr(rec, k) for k in JointRecord.__slots__}


# --------------------------------------------------------------------------- output


def _write_back(
    root: Any,
    records: Sequence[JointRecord],
    links: Mapping[str, LinkRecord],
    order: Sequence[str],
    link_elems: Mapping[str, Any],
    joint_elems: Mapping[str, Any],
    dropped: Sequence[Any],
) -> str:
    """The repaired URDF text: links and joints parent-before-child, repaired values written back."""
    for elem in dropped:
        parent = elem.getparent()
        if parent is not None:
            parent.remove(elem)
    by_child = {r.child: r for r in records}
    for name in order:
        link = link_elems[name]
        root.remove(link)
        root.append(link)
        rec = links[name]
        old = link.find("inertial")
        if old is not None:
            link.remove(old)
        inertial = rec.inertial
        if inertial is not None:
            link.insert(0, _inertial_elem(inertial))
        joint = by_child.get(name)
        if joint is not None:
            elem = joint_elems[joint.name]
            root.remove(elem)
            root.append(elem)
            _joint_back(elem, joint)
    text: str = etree.tostring(root, encoding="unicode", pretty_print=True)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + text


def _inertial_elem(inertial: Inertial) -> Any:
    elem = etree.Element("inertial")
    etree.SubElement(
        elem, "origin", xyz=" ".join(repr(v) for v in inertial.xyz), rpy=" ".join(repr(v) for v in inertial.rpy)
    )
    etree.SubElement(elem, "mass", value=repr(inertial.mass))
    names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    etree.SubElement(elem, "inertia", **{n: repr(v) for n, v in zip(names, inertial.inertia, strict=True)})
    return elem


def _joint_back(elem: Any, rec: JointRecord) -> None:
    if elem.get("type") != rec.type:
        elem.set("type", rec.type)
        for tag in ("limit", "axis", "mimic"):
            for sub in elem.findall(tag):
                elem.remove(sub)
        return
    if rec.type == "fixed":
        return
    mimic = elem.find("mimic")
    if rec.mimic is None and mimic is not None:
        elem.remove(mimic)
    elif mimic is not None:
        mimic.set("joint", rec.mimic)
        mimic.set("multiplier", repr(rec.mimic_multiplier))
        mimic.set("offset", repr(rec.mimic_offset))
    limit = elem.find("limit")
    if rec.velocity is None or rec.effort is None:
        return
    if limit is None:
        limit = etree.SubElement(elem, "limit")
    if rec.type != "continuous" and not rec.limited:
        elem.set("type", "continuous")  # a revolute joint without position limits
    else:
        if rec.lower is not None and math.isfinite(rec.lower):
            limit.set("lower", repr(rec.lower))
        if rec.upper is not None and math.isfinite(rec.upper):
            limit.set("upper", repr(rec.upper))
    limit.set("velocity", repr(rec.velocity))
    # URDF has no "unlimited": a huge effort keeps every URDF reader happy
    limit.set("effort", repr(rec.effort) if math.isfinite(rec.effort) else "1e+30")
    dyn = elem.find("dynamics")
    if dyn is not None:
        dyn.set("damping", repr(rec.damping))
        dyn.set("friction", repr(rec.friction))


# --------------------------------------------------------------------------- SRDF


def find_srdf(urdf_path: Path, robot_name: str) -> Path | None:
    """An SRDF beside ``urdf_path``: same stem, or naming the same robot, in the same or a sibling srdf/config dir.

    Searched: the URDF's directory and ``../srdf``, ``../config`` (and the ``srdf``/``config``
    directories of the ROS package it is in, up to three levels up). A file with the
    URDF's stem wins; else the one file declaring ``<robot name="robot_name">``
    whose stem is the longest prefix of the URDF's stem; ambiguity means none.
    """
    stem = urdf_path.name
    for suffix in (".xacro", ".urdf"):
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
    dirs = [urdf_path.parent, urdf_path.parent.parent / "srdf", urdf_path.parent.parent / "config"]
    # the package's own srdf/ and config/ when the URDF sits deeper in it (pkg/urdf/robots/r.urdf)
    for up in list(urdf_path.parents)[1:4]:
        if (up / "package.xml").is_file():
            dirs += [d for d in (up / "srdf", up / "config") if d not in dirs]
            break
    candidates: list[Path] = []
    for d in dirs:
        if d.is_dir():
            candidates.extend(sorted(p for p in d.iterdir() if p.suffix.lower() == ".srdf" and p.is_file()))
    for c in candidates:
        if c.stem == stem:
            return c.resolve()
    named: list[Path] = []
    for c in candidates:
        try:
            root = etree.parse(str(c), xml_parser()).getroot()
        except (OSError, etree.XMLSyntaxError):
            continue
        if root.get("name") == robot_name:
            named.append(c)
    prefixes = [c for c in named if stem.startswith(c.stem)]
    if prefixes:
        best = max(len(c.stem) for c in prefixes)
        top = [c for c in prefixes if len(c.stem) == best]
        return top[0].resolve() if len(top) == 1 else None
    return named[0].resolve() if len(named) == 1 else None


# --------------------------------------------------------------------------- loading


def _is_xacro(path: Path, raw: bytes) -> bool:
    if path.suffix.lower() == ".xacro":
        return True
    return b"xmlns:xacro" in raw and (b"<xacro:" in raw or b"${" in raw or b"$(" in raw)


def load_urdf(
    path: Path,
    xacro_args: Mapping[str, str] | None = None,
    package_path: Sequence[Path] | None = None,
    *,
    trusted: bool = False,
    roots: Sequence[Path] = (),
) -> RobotDescription:
    """Load a ``.urdf`` or ``.xacro`` file (see the module docstring); ``path`` is absolute and exists.

    Unless ``trusted``, xacro runs sandboxed (:mod:`.xacro_sandbox`) and every file the
    description reaches must lie inside a package root (:meth:`.Resolver.roots`, plus ``roots``).
    """
    resolver = Resolver(path.parent, package_path, roots, trusted=trusted)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DescriptionError(f"{path}: cannot read: {exc}") from exc

    is_xacro = _is_xacro(path, raw)
    if is_xacro:
        data = run_xacro(path, xacro_args or {}, resolver, trusted=trusted).encode("utf-8")
    else:
        if xacro_args:
            raise DescriptionError(
                f"{path}: xacro_args {dict(xacro_args)} given, but the file is plain URDF (not .xacro)"
            )
        data = raw
    where = Where(path, expanded=is_xacro)

    root = _parse_xml(where, data)
    if etree.QName(root).localname != "robot":
        raise where(root, f"the top-level element is <{root.tag}>, expected <robot>")
    name = root.get("name")
    if not name:
        raise where(root, "<robot> has no 'name' attribute")

    repairs: list[Repair] = []
    defaults: list[Repair] = []
    mesh_files: list[Path] = []
    dropped: list[Any] = []
    link_elems: dict[str, Any] = {}
    link_recs: dict[str, LinkRecord] = {}
    for link in root.findall("link"):
        lname = link.get("name")
        if not lname:
            raise where(link, "a <link> has no 'name' attribute")
        if lname in link_elems:
            raise where(link, f"link '{lname}' is defined twice")
        link_elems[lname] = link
        link_recs[lname] = _parse_link(where, link, lname, resolver, repairs, mesh_files, dropped)
    if not link_elems:
        raise where(root, "the robot has no <link>")

    joint_elems: dict[str, Any] = {}
    records: list[JointRecord] = []
    for joint in root.findall("joint"):
        jname = joint.get("name")
        if not jname:
            raise where(joint, "a <joint> has no 'name' attribute")
        if jname in joint_elems:
            raise where(joint, f"joint '{jname}' is defined twice")
        joint_elems[jname] = joint
        records.append(_parse_joint(where, joint, jname, set(link_elems), repairs, defaults))
    records = _resolve_mimics(where, records, joint_elems, repairs)
    root_link = _check_tree(where, root, list(link_elems), records, joint_elems)

    parent_joint = {r.child: r for r in records}
    lines = {n: where.line(e) for n, e in link_elems.items()}
    link_recs, inertia_repairs = repair_inertials(link_recs, parent_joint, lines)
    repairs.extend(inertia_repairs)

    order = _tree_order(root_link, records)
    urdf_xml = _write_back(root, records, link_recs, order, link_elems, joint_elems, dropped)

    joints: list[JointInfo] = []
    for rec in records:
        if not rec.actuated:
            continue
        assert rec.velocity is not None and rec.effort is not None and rec.lower is not None and rec.upper is not None
        joints.append(
            JointInfo(
                name=rec.name,
                type=cast(Literal["revolute", "continuous", "prismatic"], rec.type),
                lower=rec.lower,
                upper=rec.upper,
                max_velocity=rec.velocity,
                max_effort=rec.effort,
                parent=rec.parent,
                child=rec.child,
                axis=rec.axis,
            )
        )
    return RobotDescription(
        name=name,
        source=path,
        urdf_xml=urdf_xml,
        joints=tuple(joints),
        all_joints=tuple(records),
        links=tuple(link_elems),
        root_link=root_link,
        mesh_files=tuple(mesh_files),
        format="urdf",
        link_records=tuple(link_recs[n] for n in link_elems),
        repairs=tuple(repairs),
        defaults=tuple(defaults),
        srdf=find_srdf(path, name),
    )


def _tree_order(root_link: str, records: Sequence[JointRecord]) -> list[str]:
    children: dict[str, list[str]] = {}
    for r in records:
        children.setdefault(r.parent, []).append(r.child)
    out: list[str] = []
    stack = [root_link]
    while stack:
        link = stack.pop()
        out.append(link)
        stack.extend(reversed(children.get(link, [])))
    return out
