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


def coupling_matrix(model: mujoco.MjModel, joints: Sequence[str]) -> FloatArray:
    """``S`` (nv, n): generalized velocities of ``model`` from the commanded joints' velocities.

    Column ``k`` has 1 at joint ``k``'s dof and ``multiplier`` at the dof of every joint
    coupled to it by a joint equality ``q_follower = offset + multiplier * q_leader``
    (URDF mimic joints as built by :func:`~agentsdk.description.mjspec.build_spec`, MJCF
    joint equalities). ``S.T @ tau_all`` is the generalized force on the commanded
    joints (a follower's torque is carried by its leader), ``S.T @ M @ S`` their inertia.
    """
    index = {name: k for k, name in enumerate(joints)}
    s = np.zeros((model.nv, len(joints)))
    for k, name in enumerate(joints):
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            raise DescriptionError(f"joint {name!r} is missing from the MuJoCo model")
        s[model.jnt_dofadr[jid], k] = 1.0
    for e in range(model.neq):
        if int(model.eq_type[e]) != EQ_JOINT or not model.eq_active0[e]:
            continue
        follower, leader = int(model.eq_obj1id[e]), int(model.eq_obj2id[e])
        if leader < 0:
            continue
        col = index.get(model.joint(leader).name)
        if col is None or model.joint(follower).name in index:
            continue
        s[model.jnt_dofadr[follower], col] += float(model.eq_data[e, 1])
    return s


class GravityTerm:
    """``g(q)`` of the commanded joints from a compiled MuJoCo model, allocation-free per call.

    Holds a private ``MjData``; :meth:`compute` takes a full ``qpos`` (a floating
    base's pose included: gravity acts along the world's ``-z`` whatever the base's
    attitude) and writes ``S.T @ g_all`` into ``out``. Not thread-safe (one caller).
    """

    def __init__(self, model: mujoco.MjModel, joints: Sequence[str]) -> None:
        self.model = model
        self._data = mujoco.MjData(model)  # qvel stays 0: mj_rne gives the bias at rest, g(q)
        self._qpos = self._data.qpos  # a view made once (each MjData attribute access builds a new array)
        self._st = np.ascontiguousarray(coupling_matrix(model, joints).T)
        self._all = np.zeros(model.nv)
        #: the last result and the bytes of the ``qpos`` it is for: a robot at rest has the same
        #: ``qpos`` bit for bit tick after tick, and g(q) is a pure function of it (same result)
        self._g = np.zeros(len(joints))
        self._key = b""

    def compute(self, qpos: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Write the joint torques that hold the robot against gravity at ``qpos`` into ``out``.

        The result for the previous ``qpos`` is reused when ``qpos`` is bit for bit the same
        (the model is not meant to change between calls; :meth:`invalidate` after changing it).
        """
        key = qpos.tobytes()
        if key != self._key:
            m, d = self.model, self._data
            self._qpos[...] = qpos
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            mujoco.mj_rne(m, d, 0, self._all)
            np.dot(self._st, self._all, out=self._g)
            self._key = key
        out[:] = self._g
        return out

    def invalidate(self) -> None:
        """Forget the cached result (after changing the model's masses, inertias or gravity)."""
        self._key = b""
