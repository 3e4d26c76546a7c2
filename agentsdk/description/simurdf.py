"""The URDF a simulator loads, written from the description's records.

Links come parent before child (PyBullet's ``URDF_MAINTAIN_LINK_ORDER`` reads
the file in order and crashes the process on a child written before its
parent), every link has an explicit ``<inertial>`` in its principal frame
(PyBullet gives a link *without* one 1 kg and unit inertia, and re-diagonalises
full tensors with its own tolerance), only the collision shapes of the
self-collision model are written, with meshes pointing at the converted files
both simulators share (:mod:`.meshes`), and a revolute joint without position
limits is written as continuous, and a floating joint as fixed (a simulator that floats the body
leaves the joint's parent out).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from xml.sax.saxutils import quoteattr

import numpy as np

from .meshes import simulator_mesh
from .model import Geometry, Inertial, JointRecord, RobotDescription, rotation_from_rpy, rpy_from_rotation

__all__ = ["collapsible_links", "simulator_urdf"]


def _v(values: Sequence[float]) -> str:
    return " ".join(repr(float(v)) for v in values)


def _geometry(tag: str, geom: Geometry, label: str = "") -> str:
    if geom.kind == "box":
        shape = f'<box size="{_v(geom.size)}"/>'
    elif geom.kind == "sphere":
        shape = f'<sphere radius="{geom.size[0]!r}"/>'
    elif geom.kind in ("cylinder", "capsule"):
        shape = f'<{geom.kind} radius="{geom.size[0]!r}" length="{geom.size[1]!r}"/>'
    else:
        assert geom.filename is not None
        shape = f'<mesh filename={quoteattr(str(simulator_mesh(geom.filename)))} scale="{_v(geom.size)}"/>'
    color = ""
    if tag == "visual" and geom.rgba is not None:
        color = f'<material name={quoteattr(label)}><color rgba="{_v(geom.rgba)}"/></material>'
    return f'<{tag}><origin xyz="{_v(geom.xyz)}" rpy="{_v(geom.rpy)}"/><geometry>{shape}</geometry>{color}</{tag}>'


def _inertial(inertial: Inertial | None) -> str:
    if inertial is None:
        return '<inertial><mass value="0"/><inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial>'
    moments, rot = inertial.principal()
    m = [max(x, 0.0) for x in moments]
    return (
        f'<inertial><origin xyz="{_v(inertial.xyz)}" rpy="{_v(rpy_from_rotation(rot))}"/>'
        f'<mass value="{inertial.mass!r}"/>'
        f'<inertia ixx="{m[0]!r}" ixy="0" ixz="0" iyy="{m[1]!r}" iyz="0" izz="{m[2]!r}"/></inertial>'
    )


def collapsible_links(
    description: RobotDescription, collisions: Mapping[str, Sequence[tuple[int, Geometry]]], needed: int
) -> frozenset[str]:
    """Up to ``needed`` links that carry nothing (massless, no collision shape, fixed joint), leaves first.

    Leaving them out of a simulator changes no dynamics and no contact; their
    children are re-attached to their parent with the composed transform.
    """
    records = {rec.name: rec for rec in description.link_records}
    parent = {j.child: j for j in description.all_joints}
    candidates = [
        name
        for name in reversed(description.tree_order())
        if name in parent
        and parent[name].type == "fixed"
        and records[name].mass == 0.0
        and not collisions.get(name)
        and not any(j.mimic == name for j in description.all_joints)
    ]
    return frozenset(candidates[: max(0, needed)])


def _compose(outer: JointRecord, inner: JointRecord) -> JointRecord:
    """``inner`` re-expressed from ``outer``'s parent (``outer`` is a fixed joint being removed)."""
    r1 = rotation_from_rpy(outer.rpy)
    xyz = np.asarray(outer.xyz) + r1 @ np.asarray(inner.xyz)
    rpy = rpy_from_rotation(r1 @ rotation_from_rpy(inner.rpy))
    return replace(inner, parent=outer.parent, xyz=(float(xyz[0]), float(xyz[1]), float(xyz[2])), rpy=rpy)


def simulator_urdf(
    description: RobotDescription,
    collisions: Mapping[str, Sequence[tuple[int, Geometry]]],
    *,
    visuals: bool = False,
    skip_links: frozenset[str] = frozenset(),
    collapse: frozenset[str] = frozenset(),
) -> str:
    """URDF text of ``description`` with the ``collisions`` shapes (see the module docstring).

    ``visuals`` adds the visual shapes (for a GUI); ``skip_links`` leaves out
    links (and their parent joints), e.g. a massless world link; ``collapse``
    leaves out empty fixed links (see :func:`collapsible_links`) and attaches
    their children to their parents.
    """
    records = {rec.name: rec for rec in description.link_records}
    parent = {j.child: j for j in description.all_joints}
    for name in description.tree_order():
        joint = parent.get(name)
        while joint is not None and joint.parent in collapse:
            joint = _compose(parent[joint.parent], joint)
            parent[name] = joint
    skip_links = skip_links | collapse
    out = [f'<?xml version="1.0"?>\n<robot name={quoteattr(description.name)}>']
    for name in description.tree_order():
        if name in skip_links:
            continue
        rec = records[name]
        parts = [f"<link name={quoteattr(name)}>", _inertial(rec.inertial)]
        if visuals:
            parts.extend(_geometry("visual", g, f"{name}/visual{k}") for k, g in enumerate(rec.visuals))
        parts.extend(_geometry("collision", g) for _, g in collisions.get(name, ()))
        parts.append("</link>")
        # one element per line: PyBullet's tinyxml2 rejects some valid files written on very long lines
        out.append("\n".join(parts))
        joint = parent.get(name)
        if joint is None or joint.parent in skip_links:
            continue
        jtype = joint.type
        if jtype == "floating":  # a simulator floats the body by leaving this joint out (skip_links)
            jtype = "fixed"
        elif jtype == "revolute" and not joint.limited:
            jtype = "continuous"
        elif jtype == "prismatic" and not joint.limited:
            jtype = "prismatic_unlimited"
        body = [
            f'<origin xyz="{_v(joint.xyz)}" rpy="{_v(joint.rpy)}"/>',
            f"<parent link={quoteattr(joint.parent)}/><child link={quoteattr(joint.child)}/>",
        ]
        if jtype != "fixed":
            body.append(f'<axis xyz="{_v(joint.axis)}"/>')
            effort = joint.effort if joint.effort is not None and math.isfinite(joint.effort) else 1e30
            velocity = joint.velocity if joint.velocity is not None else 1.0
            if jtype in ("revolute", "prismatic"):
                assert joint.lower is not None and joint.upper is not None
                body.append(
                    f'<limit lower="{joint.lower!r}" upper="{joint.upper!r}" effort="{effort!r}" '
                    f'velocity="{velocity!r}"/>'
                )
            elif jtype == "prismatic_unlimited":
                # PyBullet reads lower > upper as "no limit"
                body.append(f'<limit lower="1" upper="-1" effort="{effort!r}" velocity="{velocity!r}"/>')
            else:
                body.append(f'<limit effort="{effort!r}" velocity="{velocity!r}"/>')
            body.append(f'<dynamics damping="{joint.damping!r}" friction="{joint.friction!r}"/>')
        kind = "prismatic" if jtype == "prismatic_unlimited" else jtype
        out.append(f'<joint name={quoteattr(joint.name)} type="{kind}">\n' + "\n".join(body) + "\n</joint>")
    out.append("</robot>\n")
    return "\n".join(out)
