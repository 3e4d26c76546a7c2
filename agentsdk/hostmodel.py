"""The host-side model of a robot: its description compiled by MuJoCo, without geometry.

One :class:`HostModel` per robot: an MJCF file as written (actuators dropped), or the description
built by :func:`agentsdk.description.mjspec.build_spec` (how the MuJoCo backend builds the robot),
compiled once (:func:`compile_spec`), with the couplings of its mimic joints read once. It is
shared by :class:`~agentsdk.kinematics.Kinematics` (FK, Jacobians, IK) and
:class:`~agentsdk.dynamics.DynamicsModel` (``g(q)``, ``M(q)``, model-based gains); a connected
robot builds it once (:attr:`agentsdk.backendspec.BackendSpec.host`).

The ``MjModel`` is read-only once built; every user takes its own ``MjData``
(:meth:`HostModel.new_data`, :meth:`HostModel.gravity_term`), so IK in a worker thread and
the control tick's gravity term never share scratch state.
"""

from __future__ import annotations

import copy
import math
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import mujoco
import numpy as np
import numpy.typing as npt

from .errors import DescriptionError
from .types import FloatArray, JointInfo, JointState

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


def compile_spec(spec: mujoco.MjSpec) -> mujoco.MjModel:
    """Compile a host-side model: the one place :class:`HostModel` is compiled (tests count the calls)."""
    return spec.compile()


def host_spec(description: Any) -> mujoco.MjSpec:
    """The description as MuJoCo builds it host-side, without geometry or actuators.

    An MJCF file as written (includes, defaults, equalities) with its actuators removed and
    every body kept (``fusestatic`` off: links attached by fixed joints stay frames), or
    :func:`~agentsdk.description.mjspec.build_spec`'s model of a URDF (one body per link, the
    description's repaired inertials, mimic joints as joint equalities).
    """
    from .description.mjspec import build_spec, mjcf_spec_without_actuators

    mjcf = mjcf_source(description)
    if mjcf is not None:
        spec = mjcf_spec_without_actuators(str(mjcf))
        spec.compiler.fusestatic = False
        return spec
    return build_spec(description, {}).spec


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

    def __init__(self, model: mujoco.MjModel, joints: Sequence[str], coupling: FloatArray | None = None) -> None:
        self.model = model
        self._data = mujoco.MjData(model)  # qvel stays 0: mj_rne gives the bias at rest, g(q)
        self._qpos = self._data.qpos  # a view made once (each MjData attribute access builds a new array)
        s = coupling_matrix(model, joints) if coupling is None else coupling  # a HostModel passes its own
        self._st = np.ascontiguousarray(s.T)
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


class HostModel:
    """One robot's host-side model: the description compiled once, its couplings read once.

    ``joints`` are the commanded joints (with robot.yaml limit overrides: IK keeps within
    them); each must be a hinge or slide joint of the model. The ``MjModel`` is not changed
    after construction; a user takes its own ``MjData`` (:meth:`new_data`, :meth:`gravity_term`).
    Build one with :meth:`compile`; :class:`~agentsdk.kinematics.Kinematics` and
    :class:`~agentsdk.dynamics.DynamicsModel` take it as ``host=``.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        description: Any,
        joints: Sequence[JointInfo],
        *,
        repaired: Sequence[str] = (),
        free_body: str = "",
        added_free: bool = False,
    ) -> None:
        self.model = model
        self.description = description
        self.name: str = str(description.name)
        self.joints: tuple[JointInfo, ...] = tuple(joints)
        self.names: tuple[str, ...] = tuple(j.name for j in self.joints)
        self.index: dict[str, int] = {n: k for k, n in enumerate(self.names)}
        #: bodies whose inertia MuJoCo rejected and that were repaired
        self.repaired_inertias: tuple[str, ...] = tuple(repaired)
        #: the body whose free joint floats the base ("" for a fixed base)
        self.free_body = free_body
        #: True when the free joint was added for a floating base (not in the description)
        self.added_free = added_free
        m = model
        n = len(self.joints)
        qadr, dadr = np.zeros(n, dtype=np.intp), np.zeros(n, dtype=np.intp)
        for k, j in enumerate(self.joints):
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j.name)
            if jid < 0:
                raise DescriptionError(f"joint {j.name!r} of {self.name!r} is missing from the host model")
            if int(m.jnt_type[jid]) not in (HINGE, SLIDE):
                raise DescriptionError(f"joint {j.name!r} of {self.name!r} is not a revolute or prismatic joint")
            qadr[k], dadr[k] = m.jnt_qposadr[jid], m.jnt_dofadr[jid]
            # IK keeps within the robot's limits (robot.yaml may tighten the URDF ones)
            if math.isfinite(j.lower) and math.isfinite(j.upper):
                m.jnt_limited[jid] = 1
                m.jnt_range[jid] = (j.lower, j.upper)
            else:
                m.jnt_limited[jid] = 0
        #: qpos and dof address of each commanded joint
        self.qadr, self.dadr = qadr, dadr
        #: the mimic joints and their leaders, read once (description records, else joint equalities)
        self.couplings: tuple[Coupling, ...] = tuple(find_couplings(m, description, self.index))
        s = np.zeros((m.nv, n))
        s[dadr, np.arange(n)] = 1.0
        for c in self.couplings:
            s[c.dadr, c.leader] += c.multiplier
        s.flags.writeable = False
        #: ``S`` (nv, n): generalized velocities from the commanded joints' (see :func:`coupling_matrix`)
        self.coupling = s
        #: the copy of the model with another gravity vector (:meth:`gravity_term`), the last one asked for
        self._copy: tuple[bytes, mujoco.MjModel] | None = None
        self._copy_lock = threading.Lock()

    @classmethod
    def compile(
        cls,
        description: Any,
        joints: Sequence[JointInfo] | None = None,
        *,
        gravity: Sequence[float] = (0.0, 0.0, -9.81),
        floating_base: bool = False,
    ) -> HostModel:
        """Compile ``description`` (:func:`host_spec`) once: the model every host-side user shares.

        ``floating_base`` frees the root body (a free joint added to a single top body without
        joints; an MJCF free joint at the root is kept), for ``g(q)`` at a given base attitude.
        """
        joints = tuple(joints if joints is not None else description.joints)
        free, added = "", False
        try:
            spec = host_spec(description)
            spec.option.gravity = [float(v) for v in gravity]
            if floating_base:
                tops = list(spec.worldbody.bodies)
                if len(tops) == 1 and not tops[0].joints:
                    tops[0].add_freejoint()
                    free, added = tops[0].name, True
                elif getattr(description, "free_root", None) is not None:  # an MJCF free joint at the root
                    free = description.free_root
                elif len(tops) == 1 and [j.type for j in tops[0].joints] == [mujoco.mjtJoint.mjJNT_FREE]:
                    free = tops[0].name  # an MJCF <freejoint>: the base floats already
            model = compile_spec(spec)
        except Exception as exc:
            raise DescriptionError(f"MuJoCo could not build the host model of {description.name!r}: {exc}") from exc
        repaired = [f"{r}" for r in getattr(description, "repairs", ()) if "inertia" in str(r) or "mass" in str(r)]
        return cls(model, description, joints, repaired=repaired, free_body=free, added_free=added)

    def new_data(self) -> mujoco.MjData:
        """A fresh ``MjData`` of the shared model: each user (thread) computes in its own."""
        return mujoco.MjData(self.model)

    def gravity_term(self, gravity: Sequence[float] | FloatArray | None = None) -> GravityTerm:
        """A new ``g(q)`` of the commanded joints with its own ``MjData`` (one per user).

        ``gravity``: a gravity vector other than the model's; its term computes on a copy of
        the model with that vector (the shared model is never changed; a copy, not a recompile,
        kept for the last vector asked for).
        """
        model = self.model
        if gravity is not None:
            g = np.asarray(gravity, dtype=float)
            if not np.array_equal(g, model.opt.gravity):
                key = g.tobytes()
                with self._copy_lock:
                    if self._copy is None or self._copy[0] != key:
                        other = copy.copy(self.model)
                        other.opt.gravity[:] = g
                        self._copy = (key, other)
                    model = self._copy[1]
        return GravityTerm(model, self.names, self.coupling)

    def qpos(self, q: FloatArray, out: FloatArray) -> FloatArray:
        """The full ``qpos`` for commanded positions ``q`` into ``out``: defaults, then ``q`` and the mimic joints."""
        out[:] = self.model.qpos0
        out[self.qadr] = q
        for c in self.couplings:
            out[c.qadr] = c.multiplier * q[c.leader] + c.offset
        return out

    def __repr__(self) -> str:
        base = f", floating at {self.free_body!r}" if self.free_body else ""
        return f"<HostModel {self.name!r}: {len(self.joints)} joints, {self.model.nbody} bodies{base}>"
