"""MJCF models (MuJoCo Menagerie style) read through MuJoCo itself.

MuJoCo parses and compiles the file - ``<include>``, ``meshdir``/``assetdir``,
assets, ``<default>`` classes, ``fromto``, ``autolimits`` - exactly as the
MuJoCo backend will, and the description is read from the compiled model:

* commanded joints: the named hinge and slide joints that do not follow
  another joint through a joint ``<equality>`` (those are mimic joints), in
  model order; position limits from ``range`` (unlimited hinge: continuous);
* effort limits from the joint's ``actuatorfrcrange``, else from the
  actuators driving the joint (``forcerange`` times ``gear``, or a motor's
  ``ctrlrange`` times its gain and gear), else unlimited; MJCF has no velocity
  limits, so the SDK default is used (listed in ``defaults``);
* start positions from a keyframe: the first of :data:`START_STATE_NAMES` the model has
  (``home``, ``stand``, ...); every named keyframe is a ``named_states`` entry (robot.yaml
  ``initial_group_state`` picks one);
* a free joint (``<freejoint>``) at the root makes that body the floating base
  (:attr:`RobotDescription.free_root`);
* links are bodies; their frames sit on the joint axis (a joint ``pos``
  shifts the link frame, as URDF requires), a body with several joints
  becomes a chain of massless links named ``body/joint``; geometry is the
  compiled geometry (collision meshes as MuJoCo processed them, written once
  to a cache as OBJ files so another simulator sees the same vertices; visual
  meshes are left out of the records).

The MuJoCo backend loads the file itself (``description.source``); other
backends use these records.
"""

from __future__ import annotations

import hashlib
import math
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np

from ..errors import DescriptionError
from ..types import JointInfo
from .meshes import mesh_cache_dir
from .model import (
    DEFAULT_VELOCITY,
    Geometry,
    Inertial,
    JointRecord,
    LinkRecord,
    Repair,
    RobotDescription,
    rpy_from_rotation,
)
from .packages import Resolver
from .xacro_expand import TRUST_HINT

__all__ = [
    "START_STATE_NAMES",
    "colliding_body_pairs",
    "empty_world_links",
    "free_root",
    "load_mjcf",
]

#: names of a start pose, in order of preference: the first an MJCF keyframe (or, beside a URDF,
#: an SRDF ``<group_state>``) has is the start pose when robot.yaml names none
START_STATE_NAMES = ("home", "stand", "standing", "ready", "half_sitting", "neutral", "default")

Vec3 = tuple[float, float, float]


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _compile(path: Path) -> tuple[Any, Any]:
    import mujoco

    try:
        spec = mujoco.MjSpec.from_file(str(path))
        model = spec.compile()
    except Exception as exc:
        raise DescriptionError(f"{path}: MuJoCo cannot load the MJCF model: {_one_line(str(exc))}") from exc
    return spec, model


def _quat_matrix(quat: Any) -> np.ndarray:
    import mujoco

    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, dtype=float))
    return mat.reshape(3, 3)


def _mesh_file(model: Any, mesh_id: int) -> Path:
    """The compiled mesh (vertices in the geom's frame) as an OBJ file in the cache."""
    va, vn = int(model.mesh_vertadr[mesh_id]), int(model.mesh_vertnum[mesh_id])
    fa, fn = int(model.mesh_faceadr[mesh_id]), int(model.mesh_facenum[mesh_id])
    verts = np.asarray(model.mesh_vert[va : va + vn], dtype=float)
    faces = np.asarray(model.mesh_face[fa : fa + fn], dtype=np.int64)
    digest = hashlib.sha1(verts.tobytes() + faces.tobytes()).hexdigest()[:16]
    out = mesh_cache_dir() / f"mjcf-mesh-{digest}.obj"
    if not out.exists():
        lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in verts.tolist()]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces.tolist()]
        # a name of its own: another process (or thread) may be writing the same mesh right now
        fd, name = tempfile.mkstemp(dir=out.parent, prefix=out.stem, suffix=".tmp")
        try:
            with os.fdopen(fd, "w") as f:
                f.write("\n".join(lines) + "\n")
            os.replace(name, out)
        except BaseException:
            Path(name).unlink(missing_ok=True)
            raise
    return out


def _geometry(model: Any, g: int, shift: np.ndarray, collision: bool) -> Geometry | None:
    """Geom ``g`` in its link's frame (the body frame moved by ``shift``); None for types URDF cannot hold.

    Visual meshes are left out (only collision meshes are written to the cache).
    """
    import mujoco

    t = int(model.geom_type[g])
    size = model.geom_size[g]
    xyz = cast(Vec3, tuple(float(v) for v in np.asarray(model.geom_pos[g]) - shift))
    rpy = rpy_from_rotation(_quat_matrix(model.geom_quat[g]))
    rgba = cast(tuple[float, float, float, float], tuple(float(v) for v in model.geom_rgba[g]))
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or None
    if t == mujoco.mjtGeom.mjGEOM_SPHERE:
        return Geometry("sphere", (float(size[0]),), xyz, rpy, name=name, rgba=rgba)
    if t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return Geometry("capsule", (float(size[0]), 2 * float(size[1])), xyz, rpy, name=name, rgba=rgba)
    if t == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return Geometry("cylinder", (float(size[0]), 2 * float(size[1])), xyz, rpy, name=name, rgba=rgba)
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        return Geometry("box", tuple(2 * float(s) for s in size), xyz, rpy, name=name, rgba=rgba)
    if t == mujoco.mjtGeom.mjGEOM_MESH:
        if not collision:
            return None
        path = _mesh_file(model, int(model.geom_dataid[g]))
        return Geometry("mesh", (1.0, 1.0, 1.0), xyz, rpy, filename=path, name=name, rgba=rgba)
    return None


def _effort(model: Any, jid: int) -> float:
    """The joint's effort limit (see the module docstring); inf when the model gives none."""
    import mujoco

    if model.jnt_actfrclimited[jid]:
        return float(np.max(np.abs(model.jnt_actfrcrange[jid])))
    best = 0.0
    for a in range(model.nu):
        if model.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT or model.actuator_trnid[a, 0] != jid:
            continue
        gear = abs(float(model.actuator_gear[a, 0]))
        if model.actuator_forcelimited[a]:
            best = max(best, gear * float(np.max(np.abs(model.actuator_forcerange[a]))))
        elif (
            model.actuator_ctrllimited[a]
            and model.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED
            and model.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE
        ):
            ctrl = float(np.max(np.abs(model.actuator_ctrlrange[a])))
            best = max(best, gear * abs(float(model.actuator_gainprm[a, 0])) * ctrl)
    return best if best > 0 else math.inf


_ASSET_DIR = {"mesh": "meshdir", "skin": "meshdir", "texture": "texturedir", "hfield": "texturedir"}
_MAX_INCLUDES = 256


def _check_files(path: Path, roots: list[Path]) -> None:
    """Refuse an MJCF whose ``<include>`` or asset ``file`` leaves the package roots (before MuJoCo reads it)."""
    from lxml import etree

    from .packages import path_inside

    model_dir = path.parent
    parser = etree.XMLParser(resolve_entities=False, no_network=True, huge_tree=False)
    dirs: dict[str, str] = {}
    pending, seen = [path], set()
    while pending:
        current = pending.pop()
        if current in seen:
            raise DescriptionError(f"{current}: <include> cycle")
        seen.add(current)
        if len(seen) > _MAX_INCLUDES:
            raise DescriptionError(f"{path}: more than {_MAX_INCLUDES} included files")
        try:
            root = etree.parse(str(current), parser).getroot()
        except (OSError, etree.XMLSyntaxError):
            return  # MuJoCo reports the unreadable or malformed file itself
        for elem in root.iter("compiler"):
            for key in ("meshdir", "texturedir", "assetdir"):
                if elem.get(key) is not None:
                    dirs[key] = elem.get(key) or ""
        for elem in root.iter():
            if not isinstance(elem.tag, str) or elem.get("file") is None:
                continue
            name = elem.get("file") or ""
            if elem.tag == "include":
                target = model_dir / name
            else:
                sub = dirs.get(_ASSET_DIR.get(elem.tag, "assetdir"), dirs.get("assetdir", ""))
                target = model_dir / sub / name
            if not path_inside(target, roots):
                listed = ", ".join(str(r) for r in dict.fromkeys(roots))
                raise DescriptionError(
                    f"{current}, line {elem.sourceline}: <{elem.tag} file=\"{name}\"> refused: "
                    f"{os.path.realpath(target)} is outside the package roots ({listed}) ({TRUST_HINT})"
                )
            if elem.tag == "include":
                pending.append(Path(os.path.realpath(target)))


def load_mjcf(path: Path, *, trusted: bool = False, roots: Sequence[Path] = ()) -> RobotDescription:
    """Read an MJCF model into a :class:`RobotDescription` (see the module docstring).

    Unless ``trusted``, every included file and asset must lie inside the package roots
    (the package the model is in, the package search path, ``roots``).
    """
    try:
        if not trusted:
            _check_files(path, Resolver(path.parent, None, roots).roots())
        return _load_mjcf(path)
    except UnicodeDecodeError as exc:  # a name in the model (or an included file) that is not UTF-8
        raise DescriptionError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start} of a name)") from exc
    except OSError as exc:  # an asset path too long for the filesystem
        raise DescriptionError(f"{path}: cannot read a file of the model: {exc}") from exc


def _load_mjcf(path: Path) -> RobotDescription:
    import mujoco

    spec, m = _compile(path)
    obj = mujoco.mjtObj

    def body_name(b: int) -> str:
        return "world" if b == 0 else (mujoco.mj_id2name(m, obj.mjOBJ_BODY, b) or f"body{b}")

    # joint equalities: follower -> (leader, multiplier, offset)
    follows: dict[int, tuple[int, float, float]] = {}
    for e in range(m.neq):
        if m.eq_type[e] == mujoco.mjtEq.mjEQ_JOINT and m.eq_active0[e] and m.eq_obj2id[e] >= 0:
            coef = m.eq_data[e]
            if np.allclose(coef[2:5], 0.0):
                follows[int(m.eq_obj1id[e])] = (int(m.eq_obj2id[e]), float(coef[1]), float(coef[0]))

    defaults: list[Repair] = []
    records: list[JointRecord] = []
    links: list[LinkRecord] = [LinkRecord("world")]
    link_names = ["world"]
    joints: list[JointInfo] = []
    shift_of: dict[int, np.ndarray] = {0: np.zeros(3)}
    last_link: dict[int, str] = {0: "world"}
    unnamed: list[str] = []
    no_velocity: list[str] = []
    # a floating robot none of whose geoms collides (its contacts are a scene file's explicit pairs) stands on
    # the simulators' ground with its collision shapes (mjcf_scene.ground_geoms): collision shapes here too
    from .mjcf_scene import ground_geoms

    stands_on: set[int] = set()
    for jid in range(m.njnt):
        body = int(m.jnt_bodyid[jid])
        if int(m.jnt_type[jid]) == mujoco.mjtJoint.mjJNT_FREE and int(m.body_parentid[body]) == 0:
            geoms, paired = ground_geoms(m, int(m.body_rootid[body]))
            if paired:
                stands_on.update(geoms)
    for b in range(1, m.nbody):
        name = body_name(b)
        parent = int(m.body_parentid[b])
        rot = _quat_matrix(m.body_quat[b])
        origin = np.asarray(m.body_pos[b], dtype=float) - shift_of[parent]
        jids = list(range(int(m.body_jntadr[b]), int(m.body_jntadr[b]) + int(m.body_jntnum[b])))
        prev_link, prev_shift = last_link[parent], np.zeros(3)
        if not jids:
            xyz0 = cast(Vec3, tuple(float(v) for v in origin))
            records.append(JointRecord(f"{name}/fixed", "fixed", prev_link, name, xyz0, rpy_from_rotation(rot)))
        for k, jid in enumerate(jids):
            jname = mujoco.mj_id2name(m, obj.mjOBJ_JOINT, jid) or ""
            jtype = int(m.jnt_type[jid])
            p = np.asarray(m.jnt_pos[jid], dtype=float)
            child = name if k == len(jids) - 1 else f"{name}/{jname or jid}"
            if k == 0:
                xyz, rpy = origin + rot @ p, rpy_from_rotation(rot)
            else:
                xyz, rpy = p - prev_shift, (0.0, 0.0, 0.0)
            axis = cast(Vec3, tuple(float(v) for v in m.jnt_axis[jid]))
            if jtype == mujoco.mjtJoint.mjJNT_FREE:
                rec = JointRecord(jname or f"{name}/free", "floating", prev_link, child, tuple(xyz), rpy)
            elif jtype == mujoco.mjtJoint.mjJNT_BALL:
                rec = JointRecord(jname or f"{name}/ball", "ball", prev_link, child, tuple(xyz), rpy)
            else:
                kind = "prismatic" if jtype == mujoco.mjtJoint.mjJNT_SLIDE else "revolute"
                limited = bool(m.jnt_limited[jid])
                lower, upper = (-math.inf, math.inf)
                if limited:
                    lower, upper = float(m.jnt_range[jid, 0]), float(m.jnt_range[jid, 1])
                if kind == "revolute" and not limited:
                    kind = "continuous"
                dof = int(m.jnt_dofadr[jid])
                mimic = follows.get(jid)
                velocity = DEFAULT_VELOCITY[kind]
                effort = _effort(m, jid)
                rec = JointRecord(
                    name=jname or f"{name}/joint{jid}",
                    type=kind,
                    parent=prev_link,
                    child=child,
                    xyz=cast(Vec3, tuple(float(v) for v in xyz)),
                    rpy=rpy,
                    axis=axis,
                    lower=lower,
                    upper=upper,
                    velocity=velocity,
                    effort=effort,
                    damping=float(m.dof_damping[dof]),
                    friction=float(m.dof_frictionloss[dof]),
                    mimic=mujoco.mj_id2name(m, obj.mjOBJ_JOINT, mimic[0]) if mimic else None,
                    mimic_multiplier=mimic[1] if mimic else 1.0,
                    mimic_offset=mimic[2] if mimic else 0.0,
                )
                if not jname:
                    unnamed.append(rec.name)
                elif mimic is None:
                    no_velocity.append(jname)
                    joints.append(
                        JointInfo(
                            name=jname,
                            type=cast(Literal["revolute", "continuous", "prismatic"], kind),
                            lower=lower,
                            upper=upper,
                            max_velocity=velocity,
                            max_effort=effort,
                            parent=prev_link,
                            child=child,
                            axis=axis,
                        )
                    )
            records.append(rec)
            if child != name:
                links.append(LinkRecord(child))
                link_names.append(child)
            prev_link, prev_shift = child, p
        shift = prev_shift if jids else np.zeros(3)
        shift_of[b] = shift
        last_link[b] = name
        ipos = np.asarray(m.body_ipos[b], dtype=float) - shift
        inertial = Inertial(
            float(m.body_mass[b]),
            cast(Vec3, tuple(float(v) for v in ipos)),
            rpy_from_rotation(_quat_matrix(m.body_iquat[b])),
            (float(m.body_inertia[b, 0]), 0.0, 0.0, float(m.body_inertia[b, 1]), 0.0, float(m.body_inertia[b, 2])),
        )
        visuals: list[Geometry] = []
        collisions: list[Geometry] = []
        for g in range(int(m.body_geomadr[b]), int(m.body_geomadr[b]) + int(m.body_geomnum[b])):
            collides = bool(m.geom_contype[g] or m.geom_conaffinity[g]) or g in stands_on
            geom = _geometry(m, g, shift, collides)
            if geom is None:
                continue
            (collisions if collides else visuals).append(geom)
        links.append(LinkRecord(name, inertial, tuple(visuals), tuple(collisions)))
        link_names.append(name)
    if unnamed:
        defaults.append(Repair("joints", f"unnamed joints {', '.join(unnamed)} cannot be commanded: they stay passive"))
    if no_velocity:
        defaults.append(
            Repair(
                "velocity limits",
                f"MJCF has none: {DEFAULT_VELOCITY['revolute']:g} rad/s (prismatic "
                f"{DEFAULT_VELOCITY['prismatic']:g} m/s) for {len(no_velocity)} joints",
            )
        )
    states = _keyframes(m, {j.name for j in joints})
    default_state = next((k for k in START_STATE_NAMES if k in states), None)
    meshes: list[Path] = []
    for mesh in spec.meshes:
        if mesh.file:
            f = Path(mesh.file)
            if not f.is_absolute():
                f = path.parent / (spec.meshdir or "") / f
            meshes.append(f.resolve())
    return RobotDescription(
        name=spec.modelname or path.stem,
        source=path,
        urdf_xml="",
        joints=tuple(joints),
        all_joints=tuple(records),
        links=tuple(link_names),
        root_link="world",
        mesh_files=tuple(dict.fromkeys(meshes)),
        format="mjcf",
        link_records=tuple(links),
        repairs=(),
        defaults=tuple(defaults),
        srdf=None,
        default_positions=dict(states[default_state]) if default_state else {},
        named_states=states,
        default_state=default_state,
        declared_gains=_declared_gains(m, {j.name for j in joints}),
    )


def _declared_gains(m: Any, names: set[str]) -> dict[str, tuple[float, float]]:
    """The commanded joints' position-servo gains the model declares (:mod:`.actuators`)."""
    import mujoco

    from .actuators import declared_servo_gains

    by_id = declared_servo_gains(m)
    named = ((mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, jid), g) for jid, g in by_id.items())
    return {name: g for name, g in named if name in names}


def _keyframes(m: Any, names: set[str]) -> dict[str, dict[str, float]]:
    """Every named keyframe's positions of the joints in ``names`` (the first keyframe of a name wins)."""
    import mujoco

    out: dict[str, dict[str, float]] = {}
    for key in range(m.nkey):
        kname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_KEY, key)
        if not kname or kname in out:
            continue
        out[kname] = {
            jname: float(m.key_qpos[key, m.jnt_qposadr[jid]])
            for jid in range(m.njnt)
            if (jname := mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, jid)) in names
        }
    return out


def colliding_body_pairs(model: Any, *, world: bool = True) -> set[tuple[str, str]]:
    """Body-name pairs with at least one geom pair MuJoCo tests for contact (its filters applied).

    ``world=False`` leaves out the world body (an MJCF scene's floor is not part of the robot).
    """
    import mujoco

    m = model
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or f"body{b}" for b in range(m.nbody)]
    names[0] = "world"
    excluded = {int(x) for x in m.exclude_signature}
    filterparent = not (m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)
    out: set[tuple[str, str]] = set()
    geoms_of: dict[int, list[int]] = {}
    for g in range(m.ngeom):
        geoms_of.setdefault(int(m.geom_bodyid[g]), []).append(g)
    bodies = sorted(b for b in geoms_of if world or b != 0)
    for i, b1 in enumerate(bodies):
        for b2 in bodies[i + 1 :]:
            w1, w2 = int(m.body_weldid[b1]), int(m.body_weldid[b2])
            if w1 == w2 or ((b1 << 16) + b2) in excluded:
                continue
            if filterparent and w1 != 0 and w2 != 0 and (
                int(m.body_weldid[m.body_parentid[w1]]) == w2 or int(m.body_weldid[m.body_parentid[w2]]) == w1
            ):
                continue
            if any(
                (m.geom_contype[g1] & m.geom_conaffinity[g2]) or (m.geom_contype[g2] & m.geom_conaffinity[g1])
                for g1 in geoms_of[b1]
                for g2 in geoms_of[b2]
            ):
                a, b = names[b1], names[b2]
                out.add((a, b) if a <= b else (b, a))
    return out


def free_root(description: RobotDescription) -> str | None:
    """The body a root free joint floats (an MJCF ``<freejoint>`` on the one body attached to the world), or None.

    That body is the robot's floating base: a URDF's root link, which PyBullet floats unless the
    base is fixed.
    """
    out = [j for j in description.child_joints(description.root_link) if j.child not in empty_world_links(description)]
    if len(out) == 1 and out[0].type == "floating":
        return out[0].child
    return None


def empty_world_links(description: RobotDescription) -> frozenset[str]:
    """Bodies fixed to the world that hold nothing: no mass, no shape, no joint or body below (markers).

    Menagerie's Apollo has one (``world_link``) beside its floating base; it changes no physics, and a
    URDF rooted at the floating base has no place for it, so the floating step leaves it out.
    """
    records = {rec.name: rec for rec in description.link_records}
    out = []
    for j in description.child_joints(description.root_link):
        rec = records.get(j.child)
        if (
            j.type == "fixed" and rec is not None and not description.child_joints(j.child)
            and not rec.visuals and not rec.collisions and (rec.inertial is None or rec.inertial.mass <= 0.0)
        ):
            out.append(j.child)
    return frozenset(out)
