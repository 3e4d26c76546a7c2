"""A MuJoCo model (``MjSpec``) built from a :class:`RobotDescription`, one MuJoCo body per URDF link.

Why not MuJoCo's own URDF importer: it fuses links rigidly attached by fixed
joints (so link masses and link-level collision pairs are lost), keeps only
mesh base names (two ``base.stl`` from different packages collide), and
applies its own inertia rules. Building the spec from the description's
records gives MuJoCo exactly what PyBullet gets (the same links, repaired
inertials, limits, collision shapes and converted mesh files), and lets the
self-collision model be expressed per link (``<exclude>`` per body pair, with
MuJoCo's parent filter turned off).

The root link is welded to the world (a root named ``world`` *is* MuJoCo's
world body). A link's body sits at its parent joint's origin; the joint's
axis is expressed in that frame, as in URDF. Mimic joints become joint
equality constraints (``q = offset + multiplier * q_leader``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np

from .meshes import simulator_mesh
from .model import Geometry, RobotDescription, quat_from_rpy

__all__ = ["MjBuild", "build_spec", "quat_from_matrix"]


@dataclass
class MjBuild:
    """A spec under construction and what its generated names stand for."""

    spec: mujoco.MjSpec
    #: geom name -> (link, index into the link's collision shapes)
    geoms: dict[str, tuple[str, int]] = field(default_factory=dict)
    #: mesh asset name -> (link, index into the link's collision shapes)
    meshes: dict[str, tuple[str, int]] = field(default_factory=dict)


def quat_from_matrix(rot: np.ndarray) -> list[float]:
    """Rotation matrix to a MuJoCo quaternion ``(w, x, y, z)``."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rot, dtype=float).reshape(9))
    return quat.tolist()


def _add_geom(
    build: MjBuild, body: mujoco.MjsBody, link: str, index: int, geom: Geometry, margin: float, shell: bool
) -> None:
    g = body.add_geom()
    g.name = f"{link}/collision{index}"
    g.pos = list(geom.xyz)
    g.quat = list(quat_from_rpy(geom.rpy))
    g.margin = margin
    if geom.kind == "box":
        g.type = mujoco.mjtGeom.mjGEOM_BOX
        g.size = [0.5 * s for s in geom.size]
    elif geom.kind == "sphere":
        g.type = mujoco.mjtGeom.mjGEOM_SPHERE
        g.size = [geom.size[0], 0.0, 0.0]
    elif geom.kind in ("cylinder", "capsule"):
        g.type = mujoco.mjtGeom.mjGEOM_CYLINDER if geom.kind == "cylinder" else mujoco.mjtGeom.mjGEOM_CAPSULE
        g.size = [geom.size[0], 0.5 * geom.size[1], 0.0]
    else:
        assert geom.filename is not None
        mesh = build.spec.add_mesh()
        mesh.name = f"mesh{len(build.meshes)}"
        mesh.file = str(simulator_mesh(geom.filename))
        mesh.scale = list(geom.size)
        if shell:
            mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
        build.meshes[mesh.name] = (link, index)
        g.type = mujoco.mjtGeom.mjGEOM_MESH
        g.meshname = mesh.name
    if geom.rgba is not None:
        g.rgba = list(geom.rgba)
    build.geoms[g.name] = (link, index)


def build_spec(
    description: RobotDescription,
    collisions: Mapping[str, Sequence[tuple[int, Geometry]]] | None = None,
    *,
    margin: float = 0.0,
    shell: frozenset[tuple[str, int]] = frozenset(),
) -> MjBuild:
    """The robot as an ``MjSpec`` (not compiled).

    ``collisions`` maps each link to the ``(index, shape)`` pairs to build
    (default: every collision shape of the description); ``margin`` is the
    contact margin of every geom (used to find links touching at the start
    pose); ``shell`` lists ``(link, index)`` meshes whose volume MuJoCo must
    compute as a shell (open or flat meshes). Visual shapes are not built.
    """
    spec = mujoco.MjSpec()
    spec.modelname = description.name
    c = spec.compiler
    c.degree = False
    c.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
    c.fusestatic = False
    c.balanceinertia = False
    c.discardvisual = False
    c.autolimits = False
    # the self-collision model decides adjacent pairs explicitly (see agentsdk.description.collision)
    spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_FILTERPARENT
    build = MjBuild(spec)
    if collisions is None:
        collisions = {rec.name: list(enumerate(rec.collisions)) for rec in description.link_records}
    records = {rec.name: rec for rec in description.link_records}
    parent_joint = {j.child: j for j in description.all_joints}
    bodies: dict[str, mujoco.MjsBody] = {}
    for name in description.tree_order():
        joint = parent_joint.get(name)
        if joint is None:
            if name == "world":
                body = spec.worldbody
            else:
                body = spec.worldbody.add_body()
                body.name = name
        else:
            body = bodies[joint.parent].add_body()
            body.name = name
            body.pos = list(joint.xyz)
            body.quat = list(quat_from_rpy(joint.rpy))
            if joint.movable:
                j = body.add_joint()
                j.name = joint.name
                j.type = mujoco.mjtJoint.mjJNT_SLIDE if joint.type == "prismatic" else mujoco.mjtJoint.mjJNT_HINGE
                j.axis = list(joint.axis)
                if joint.limited:
                    assert joint.lower is not None and joint.upper is not None
                    j.limited = mujoco.mjtLimited.mjLIMITED_TRUE
                    # MuJoCo needs lower < upper; a zero-width range (a locked joint) gets a nanometre
                    lo, hi = joint.lower, joint.upper
                    j.range = [lo, hi] if hi > lo else [lo - 1e-9, hi + 1e-9]
                else:
                    j.limited = mujoco.mjtLimited.mjLIMITED_FALSE
                j.damping = [joint.damping, 0.0, 0.0]
                j.frictionloss = joint.friction
        bodies[name] = body
        rec = records[name]
        if body is not spec.worldbody:
            inertial = rec.inertial
            if inertial is None:
                body.mass = 0.0
                body.inertia = [0.0, 0.0, 0.0]
            else:
                moments, rot = inertial.principal()
                body.mass = inertial.mass
                body.ipos = list(inertial.xyz)
                body.iquat = quat_from_matrix(rot)
                body.inertia = [max(m, 0.0) for m in moments]
            body.explicitinertial = True
        for index, geom in collisions.get(name, ()):
            _add_geom(build, body, name, index, geom, margin, (name, index) in shell)
    for mimic in description.mimics:
        eq = spec.add_equality()
        eq.name = f"mimic:{mimic.joint}"
        eq.type = mujoco.mjtEq.mjEQ_JOINT
        eq.objtype = mujoco.mjtObj.mjOBJ_JOINT
        eq.name1 = mimic.joint
        eq.name2 = mimic.leader
        data = np.zeros(len(eq.data))
        data[0], data[1] = mimic.offset, mimic.multiplier
        eq.data = data.tolist()
    return build


def mjcf_spec_without_actuators(path: str) -> mujoco.MjSpec:
    """An MJCF model as written (includes, assets, defaults, contacts) with its actuators removed.

    The simulators drive the joints with the SDK's own servo law, and the dynamics model needs
    none: actuator sensors and keyframe controls go with the actuators.
    """
    spec = mujoco.MjSpec.from_file(path)
    for sensor in list(spec.sensors):
        if sensor.objtype == mujoco.mjtObj.mjOBJ_ACTUATOR:
            spec.delete(sensor)
    for act in list(spec.actuators):
        spec.delete(act)
    for key in spec.keys:
        key.ctrl = []
        key.act = []
    return spec
