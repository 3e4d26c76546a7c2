"""The host-side model of a robot: its description compiled by MuJoCo, without geometry.

The model :class:`~agentsdk.kinematics.Kinematics` computes with: an MJCF file as written, or
the description built by :func:`agentsdk.description.mjspec.build_spec` (how the MuJoCo backend
builds the robot), and the couplings of its mimic joints.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import mujoco
import numpy as np
import numpy.typing as npt

from .errors import DescriptionError
from .types import FloatArray, JointState

Positions = Mapping[str, float] | Sequence[float] | npt.NDArray[np.floating] | JointState
"""Joint positions: ``{joint: value}``, a full-length sequence in joint order, or a JointState."""

#: MuJoCo's joint and equality types as plain ints
HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)
FREE = int(mujoco.mjtJoint.mjJNT_FREE)
BALL = int(mujoco.mjtJoint.mjJNT_BALL)
EQ_JOINT = int(mujoco.mjtEq.mjEQ_JOINT)


def wxyz_to_xyzw(q: FloatArray) -> FloatArray:
    """A quaternion in MuJoCo's (w, x, y, z) order as (x, y, z, w), the order of :class:`~agentsdk.pose.Pose`."""
    return np.array([q[1], q[2], q[3], q[0]])


@dataclass(frozen=True)
class Coupling:
    """A mimic joint: ``q[follower] = multiplier * q[leader] + offset``."""

    qadr: int
    dadr: int
    leader: int  # index into the actuated joints
    multiplier: float
    offset: float


def mjcf_source(description: Any) -> Path | None:
    """The MJCF file behind a description, or None for a URDF description."""
    for attr in ("mjcf_path", "mjcf_file"):
        path = getattr(description, attr, None)
        if path:
            return Path(path)
    fmt = getattr(description, "format", None) or getattr(description, "kind", None)
    source = getattr(description, "source", None)
    if fmt == "mjcf" and source is not None:
        return Path(source)
    if source is not None and Path(source).suffix.lower() == ".xml" and not getattr(description, "urdf_xml", ""):
        return Path(source)
    return None


def compile_model(description: Any) -> tuple[mujoco.MjModel, list[str]]:
    """The kinematic/dynamic model: an MJCF file as written, or the description built by ``build_spec``.

    ``build_spec`` is how the MuJoCo backend builds the robot (one body per link, fixed
    links kept, the description's repaired inertials, mimic joints as equality
    constraints), so link frames and g(q) are the simulators' own. No collision geometry.
    """
    mjcf = mjcf_source(description)
    try:
        if mjcf is not None:
            spec = mujoco.MjSpec.from_file(str(mjcf))
            spec.compiler.fusestatic = False
        else:
            from .description.mjspec import build_spec

            spec = build_spec(description, {}).spec
        model = spec.compile()
    except Exception as exc:
        raise DescriptionError(f"MuJoCo could not build the kinematics of {description.name!r}: {exc}") from exc
    return model, [f"{r}" for r in getattr(description, "repairs", ()) if "inertia" in str(r) or "mass" in str(r)]


@dataclass(frozen=True)
class MjcfDescription:
    """The minimum of a RobotDescription that :class:`Kinematics` needs, for a bare MJCF file."""

    name: str
    source: Path
    format: Literal["mjcf"] = "mjcf"
    urdf_xml: str = ""
    links: tuple[str, ...] = ()
    all_joints: tuple[Any, ...] = ()
    root_link: str = "world"


def find_couplings(model: mujoco.MjModel, description: Any, index: Mapping[str, int]) -> list[Coupling]:
    """The mimic joints of ``model`` coupled to the actuated joints ``index`` ({name: position}).

    From the description's mimic records (URDF), else from the model's joint equalities (MJCF).
    """
    m = model
    out: list[Coupling] = []
    records = getattr(description, "all_joints", ())
    for rec in records:
        if getattr(rec, "mimic", None) and rec.mimic in index and rec.name not in index:
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, rec.name)
            if jid >= 0:
                out.append(
                    Coupling(int(m.jnt_qposadr[jid]), int(m.jnt_dofadr[jid]), index[rec.mimic],
                              float(rec.mimic_multiplier), float(rec.mimic_offset))
                )
    if out:
        return out
    # MJCF: joint equality constraints q1 = poly(q2); the linear part couples the follower
    for e in range(m.neq):
        if int(m.eq_type[e]) != EQ_JOINT or not m.eq_active0[e]:
            continue
        j1, j2 = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])
        if j2 < 0:
            continue
        n1, n2 = m.joint(j1).name, m.joint(j2).name
        if n2 in index and n1 not in index:
            coef = m.eq_data[e]
            out.append(Coupling(int(m.jnt_qposadr[j1]), int(m.jnt_dofadr[j1]), index[n2],
                                 float(coef[1]), float(coef[0])))
    return out


def link_tree(model: mujoco.MjModel, description: Any) -> tuple[dict[str, int], dict[str, str], str]:
    """``({link: body id} in tree order, {link: parent link}, root link)``.

    From the description's links and joints when every link is a body of the model (URDF;
    MJCF descriptions whose bodies carry at most one joint), else from the model's bodies
    (MJCF: every body, unnamed ones as ``body<id>``, under ``world``).
    """
    m = model
    names = list(getattr(description, "links", ()) or ())
    links: dict[str, int] = {}
    parents: dict[str, str] = {}
    found = True
    for name in names:
        bid = 0 if name == "world" else mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid < 0:
            found = False
            break
        links[name] = bid
    if names and found:
        root = description.root_link
        children: dict[str, list[str]] = {}
        for rec in getattr(description, "all_joints", ()):
            children.setdefault(rec.parent, []).append(rec.child)
        # tree order (breadth first from the root), so a parent always precedes its children
        ordered = {root: links[root]}
        queue = [root]
        while queue:
            parent = queue.pop(0)
            for child in children.get(parent, ()):
                if child not in ordered:
                    ordered[child] = links[child]
                    parents[child] = parent
                    queue.append(child)
        return ordered, parents, root
    if names and mjcf_source(description) is None:
        missing = next(n for n in names if n not in links)
        raise DescriptionError(f"link {missing!r} of {description.name!r} is missing from the kinematic model")

    def body_name(b: int) -> str:
        return "world" if b == 0 else (m.body(b).name or f"body{b}")

    links = {"world": 0}
    for bid in range(1, m.nbody):
        links[body_name(bid)] = bid
        parents[body_name(bid)] = body_name(int(m.body_parentid[bid]))
    return links, parents, "world"
