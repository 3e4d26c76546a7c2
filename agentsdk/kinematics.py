"""Kinematics from the robot description, computed host-side: FK, Jacobians, TF trees, IK.

Built on MuJoCo (``mj_kinematics``, ``mj_jacBody``) and `mink <https://github.com/kevinzakka/mink>`_
(differential inverse kinematics as a QP, solved by DAQP), so a CAN or mock robot gets
exactly the kinematics of a simulated one, from URDF and MJCF models alike. Why this
library and not pinocchio (+pink) or placo is measured and written down in the README
("Why MuJoCo + mink for kinematics").

The kinematic model is the description compiled by MuJoCo with

* every link kept as a body (``fusestatic`` off), so links attached by fixed joints
  (``tool0``, ``ee_link``, ``*_hand_tcp``) are frames like any other;
* for URDF, the robot exactly as the MuJoCo backend builds it
  (:func:`agentsdk.description.mjspec.build_spec`: one body per link, the
  description's repaired inertials, mimic joints as constraints) without geometry,
  so :meth:`Kinematics.gravity` is the simulators' rigid-body gravity torque and
  meshes are never loaded. The description's inertial repairs are listed in
  :attr:`Kinematics.repaired_inertias`;
* for MJCF, the model as written (MuJoCo is its reference implementation).

Conventions (as ROS / KDL / MoveIt):

* poses are :class:`~agentsdk.pose.Pose` in the root link's frame unless a
  ``reference`` link is given;
* :meth:`Kinematics.jacobian` is the geometric Jacobian of the link origin, rows
  ``(vx, vy, vz, wx, wy, wz)`` in the root frame, columns in ``joints`` order (the
  actuated joints; a mimic joint adds ``multiplier x`` its column to its leader's);
* ``positions`` is a mapping ``{joint: value}`` (the other joints keep their default),
  a full-length sequence in ``joints`` order, or a :class:`JointState`; ``None`` is
  the default: the robot's latest measured state when attached to a robot, else
  the neutral configuration (0 clipped into each joint's limits).
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import Callable, Generator, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import mujoco
import numpy as np
import numpy.typing as npt

from .errors import (
    DescriptionError,
    InvalidValueError,
    UnknownJointError,
    UnknownLinkError,
    UnreachablePoseError,
)
from .pose import Pose, quat_multiply, rotation_vector
from .types import FloatArray, JointInfo, JointState

if TYPE_CHECKING:
    from .description import RobotDescription

__all__ = ["IKResult", "Kinematics", "LinkPoses", "Positions", "run_async", "run_sync"]

log = logging.getLogger(__name__)

Positions = Mapping[str, float] | Sequence[float] | npt.NDArray[np.floating] | JointState
"""Joint positions: ``{joint: value}``, a full-length sequence in joint order, or a JointState."""

_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)
_FREE = int(mujoco.mjtJoint.mjJNT_FREE)
_BALL = int(mujoco.mjtJoint.mjJNT_BALL)
_EQ_JOINT = int(mujoco.mjtEq.mjEQ_JOINT)

#: IK defaults: convergence tolerances (10x tighter than what users usually ask for)
IK_POSITION_TOLERANCE = 1e-4
IK_ORIENTATION_TOLERANCE = 1e-3


#: wall time a coroutine computes IK before yielding to the event loop (s)
_SLICE = 0.002


def run_sync(gen: Generator[None, None, Any]) -> Any:
    """Run a cooperative computation (a generator that yields between steps) to completion."""
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return stop.value


async def run_async(gen: Generator[None, None, Any], slice_s: float = _SLICE) -> Any:
    """Run a cooperative computation, yielding to the event loop every ``slice_s`` seconds of wall time.

    In lockstep, simulated time stays frozen meanwhile (this task stays ready), so the result and
    the robot's motion do not depend on the machine's speed; in realtime the control loop and the
    watchdogs keep running.
    """
    t0 = time.perf_counter()
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return stop.value
        now = time.perf_counter()
        if now - t0 >= slice_s:
            await asyncio.sleep(0)
            t0 = time.perf_counter()


def _wxyz_to_xyzw(q: FloatArray) -> FloatArray:
    return np.array([q[1], q[2], q[3], q[0]])


# --------------------------------------------------------------------------- results


class IKResult(dict[str, float]):
    """Joint positions found by :meth:`Kinematics.ik`: a ``{joint: position}`` dict, plus diagnostics.

    ``ok`` is True for a solution within the tolerances; :meth:`Kinematics.ik` raises
    :class:`UnreachablePoseError` (carrying the best attempt, ``ok == False``) otherwise,
    so a returned result is always a solution. ``position_error`` (m) and
    ``orientation_error`` (rad, 0 for position-only) are the residual at the solution.
    """

    ok: bool
    position_error: float
    orientation_error: float
    iterations: int
    attempts: int
    message: str

    def __init__(
        self,
        positions: Mapping[str, float],
        *,
        ok: bool,
        position_error: float,
        orientation_error: float,
        iterations: int,
        attempts: int,
        message: str = "",
    ) -> None:
        super().__init__(positions)
        self.ok = ok
        self.position_error = position_error
        self.orientation_error = orientation_error
        self.iterations = iterations
        self.attempts = attempts
        self.message = message

    def __repr__(self) -> str:
        vals = ", ".join(f"{k!r}: {v:.6g}" for k, v in self.items())
        return (
            f"IKResult({{{vals}}}, ok={self.ok}, position_error={self.position_error:.3g}, "
            f"orientation_error={self.orientation_error:.3g}, iterations={self.iterations}, attempts={self.attempts})"
        )


@dataclass(frozen=True)
class LinkPoses(Mapping[str, Pose]):
    """Every link's pose at one joint configuration: a TF tree snapshot, like robot_state_publisher's.

    A mapping ``{link: Pose in the root frame}``; ``stamp`` is the JointState's stamp
    (robot time) or None; ``parents`` maps each link to its parent link (the root has
    none). :meth:`relative` gives any link in any other link's frame;
    :meth:`transforms` lists the parent -> child transforms (what ``/tf`` carries).
    """

    root: str
    poses: Mapping[str, Pose] = field(repr=False)
    parents: Mapping[str, str] = field(repr=False)
    stamp: float | None = None

    def __getitem__(self, link: str) -> Pose:
        try:
            return self.poses[link]
        except KeyError:
            raise UnknownLinkError(f"unknown link {link!r}; links: {', '.join(self.poses)}") from None

    def __iter__(self) -> Iterator[str]:
        return iter(self.poses)

    def __len__(self) -> int:
        return len(self.poses)

    def relative(self, link: str, reference: str) -> Pose:
        """Pose of ``link`` in the frame of ``reference`` (tf2's ``lookupTransform(reference, link)``)."""
        return self[reference].inverse() @ self[link]

    def transforms(self) -> list[tuple[str, str, Pose]]:
        """``(parent, child, pose of child in parent)`` for every link but the root, in tree order."""
        return [(parent, child, self.relative(child, parent)) for child, parent in self.parents.items()]


# --------------------------------------------------------------------------- model building


@dataclass(frozen=True)
class _Coupling:
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


def _compile(description: Any) -> tuple[mujoco.MjModel, list[str]]:
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


# --------------------------------------------------------------------------- kinematics


class Kinematics:
    """Forward/inverse kinematics and Jacobians of one robot description (thread-safe).

    ``Kinematics(description)`` uses the description's actuated joints; ``joints`` may
    pass the robot's joints with robot.yaml limit overrides applied (IK keeps within
    those). ``state`` is a callable returning the latest :class:`JointState`; it is the
    default for every ``positions`` argument (``robot.kinematics`` passes the robot's
    measured state). :meth:`from_mjcf` builds one from an MJCF file directly.
    """

    def __init__(
        self,
        description: RobotDescription,
        joints: Sequence[JointInfo] | None = None,
        *,
        state: Callable[[], JointState] | None = None,
    ) -> None:
        self.description = description
        self.name: str = description.name
        self.joints: tuple[JointInfo, ...] = tuple(joints if joints is not None else description.joints)
        self._state = state
        self.model, repaired = _compile(description)
        #: bodies whose inertia MuJoCo rejected and that were repaired (see the module docstring)
        self.repaired_inertias: tuple[str, ...] = tuple(repaired)
        m = self.model
        self._data = mujoco.MjData(m)
        self._lock = threading.RLock()
        self.joint_names: tuple[str, ...] = tuple(j.name for j in self.joints)
        self._index = {n: i for i, n in enumerate(self.joint_names)}
        n = len(self.joints)

        qadr, dadr = np.zeros(n, dtype=np.intp), np.zeros(n, dtype=np.intp)
        for k, j in enumerate(self.joints):
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j.name)
            if jid < 0:
                raise DescriptionError(f"joint {j.name!r} of {self.name!r} is missing from the kinematic model")
            if int(m.jnt_type[jid]) not in (_HINGE, _SLIDE):
                raise DescriptionError(f"joint {j.name!r} of {self.name!r} is not a revolute or prismatic joint")
            qadr[k], dadr[k] = m.jnt_qposadr[jid], m.jnt_dofadr[jid]
            # IK keeps within the robot's limits (robot.yaml may tighten the URDF ones)
            if math.isfinite(j.lower) and math.isfinite(j.upper):
                m.jnt_limited[jid] = 1
                m.jnt_range[jid] = (j.lower, j.upper)
            else:
                m.jnt_limited[jid] = 0
        self._qadr, self._dadr = qadr, dadr
        self.lower = np.array([j.lower for j in self.joints])
        self.upper = np.array([j.upper for j in self.joints])
        self._couplings = self._find_couplings()
        coupled = {c.dadr for c in self._couplings}
        actuated = set(dadr.tolist())
        #: dofs IK must not move: free/ball joints and joints that are neither actuated nor mimic
        self._frozen_dofs = [d for d in range(m.nv) if d not in actuated and d not in coupled]
        self._neutral = np.clip(np.zeros(n), self.lower, self.upper)

        self._links, self._parents, self.root_link = self._link_tree()
        self._body = {name: bid for name, bid in self._links.items()}
        self._ik: IKSolver | None = None

    @classmethod
    def for_robot(cls, robot: Any) -> Kinematics:
        """The kinematics of a connected :class:`~agentsdk.Robot`, defaulting to its latest measured state."""
        return cls(robot.description, robot.joints, state=robot.latest_state)

    @classmethod
    def from_mjcf(
        cls,
        path: str | Path,
        joints: Sequence[str] | None = None,
        *,
        state: Callable[[], JointState] | None = None,
    ) -> Kinematics:
        """Kinematics of an MJCF model (e.g. from MuJoCo Menagerie).

        The actuated joints are ``joints`` (names) or every hinge and slide joint that
        is not the follower of a joint equality constraint, in model order; their
        limits are the MJCF ranges (unlimited joints are continuous).
        """
        path = Path(path).expanduser().resolve()
        if not path.is_file():
            raise DescriptionError(f"MJCF model not found: {path}")
        try:
            model = mujoco.MjModel.from_xml_path(str(path))
        except Exception as exc:
            raise DescriptionError(f"{path}: MuJoCo could not load the MJCF model: {exc}") from exc
        followers = {
            int(model.eq_obj1id[e]) for e in range(model.neq) if int(model.eq_type[e]) == _EQ_JOINT
        }
        infos: list[JointInfo] = []
        names_in_model = []
        for jid in range(model.njnt):
            typ = int(model.jnt_type[jid])
            if typ not in (_HINGE, _SLIDE):
                continue
            name = model.joint(jid).name
            names_in_model.append(name)
            if joints is None and jid in followers:
                continue
            limited = bool(model.jnt_limited[jid])
            lo, hi = (float(v) for v in model.jnt_range[jid]) if limited else (-math.inf, math.inf)
            infos.append(
                JointInfo(
                    name=name,
                    type=("revolute" if limited else "continuous") if typ == _HINGE else "prismatic",
                    lower=lo,
                    upper=hi,
                    max_velocity=math.inf,
                    max_effort=math.inf,
                    axis=tuple(float(a) for a in model.jnt_axis[jid]),  # type: ignore[arg-type]
                )
            )
        if joints is not None:
            by_name = {j.name: j for j in infos}
            unknown = [j for j in joints if j not in by_name]
            if unknown:
                raise UnknownJointError(
                    f"{path.name}: no hinge or slide joint {unknown[0]!r}; joints: {', '.join(names_in_model)}"
                )
            infos = [by_name[j] for j in joints]
        desc = _MjcfDescription(name=model.names.split(b"\0")[0].decode() or path.stem, source=path)
        return cls(desc, infos, state=state)  # type: ignore[arg-type]

    # ------------------------------------------------------------ structure
    def _find_couplings(self) -> list[_Coupling]:
        m = self.model
        out: list[_Coupling] = []
        records = getattr(self.description, "all_joints", ())
        for rec in records:
            if getattr(rec, "mimic", None) and rec.mimic in self._index and rec.name not in self._index:
                jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, rec.name)
                if jid >= 0:
                    out.append(
                        _Coupling(int(m.jnt_qposadr[jid]), int(m.jnt_dofadr[jid]), self._index[rec.mimic],
                                  float(rec.mimic_multiplier), float(rec.mimic_offset))
                    )
        if out:
            return out
        # MJCF: joint equality constraints q1 = poly(q2); the linear part couples the follower
        for e in range(m.neq):
            if int(m.eq_type[e]) != _EQ_JOINT or not m.eq_active0[e]:
                continue
            j1, j2 = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])
            if j2 < 0:
                continue
            n1, n2 = m.joint(j1).name, m.joint(j2).name
            if n2 in self._index and n1 not in self._index:
                coef = m.eq_data[e]
                out.append(_Coupling(int(m.jnt_qposadr[j1]), int(m.jnt_dofadr[j1]), self._index[n2],
                                     float(coef[1]), float(coef[0])))
        return out

    def _link_tree(self) -> tuple[dict[str, int], dict[str, str], str]:
        """``({link: body id} in tree order, {link: parent link}, root link)``.

        From the description's links and joints when every link is a body of the model (URDF;
        MJCF descriptions whose bodies carry at most one joint), else from the model's bodies
        (MJCF: every body, unnamed ones as ``body<id>``, under ``world``).
        """
        m = self.model
        names = list(getattr(self.description, "links", ()) or ())
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
            root = self.description.root_link
            children: dict[str, list[str]] = {}
            for rec in getattr(self.description, "all_joints", ()):
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
        if names and mjcf_source(self.description) is None:
            missing = next(n for n in names if n not in links)
            raise DescriptionError(f"link {missing!r} of {self.name!r} is missing from the kinematic model")

        def body_name(b: int) -> str:
            return "world" if b == 0 else (m.body(b).name or f"body{b}")

        links = {"world": 0}
        for bid in range(1, m.nbody):
            links[body_name(bid)] = bid
            parents[body_name(bid)] = body_name(int(m.body_parentid[bid]))
        return links, parents, "world"

    @property
    def link_names(self) -> tuple[str, ...]:
        """Every link (frame) of the robot, the root first: fixed-joint links included."""
        return tuple(self._links)

    @property
    def parents(self) -> Mapping[str, str]:
        """``{link: parent link}`` for every link but the root."""
        return dict(self._parents)

    def body_id(self, link: str) -> int:
        """The model's body id of ``link``; raises :class:`UnknownLinkError` naming the known links."""
        if not isinstance(link, str):
            raise InvalidValueError(f"link must be a link name (str), got {link!r}")
        bid = self._body.get(link)
        if bid is None:
            raise UnknownLinkError(
                f"robot {self.name!r} has no link {link!r}; links: {', '.join(self._links)}"
            )
        return bid

    # ------------------------------------------------------------ positions
    def _default(self) -> FloatArray:
        if self._state is not None:
            st = self._state()
            if st.names == self.joint_names:
                return np.array(st.position, dtype=float)
            return self._from_mapping(st.positions(), self._neutral.copy(), "state")
        return self._neutral.copy()

    def _from_mapping(self, values: Mapping[str, Any], base: FloatArray, what: str) -> FloatArray:
        for name, v in values.items():
            k = self._index.get(name) if isinstance(name, str) else None
            if k is None:
                raise UnknownJointError(
                    f"{what}: robot {self.name!r} has no actuated joint {name!r}; joints: {', '.join(self.joint_names)}"
                )
            try:
                base[k] = float(v)
            except (TypeError, ValueError) as exc:
                raise InvalidValueError(f"{what}[{name!r}]: {v!r} is not a number") from exc
        return base

    def resolve(self, positions: Positions | None = None, what: str = "positions") -> FloatArray:
        """Joint positions as an array in ``joints`` order (see the module docstring for the forms)."""
        if positions is None:
            q = self._default()
        elif isinstance(positions, JointState):
            if positions.names == self.joint_names:
                q = np.array(positions.position, dtype=float)
            else:
                q = self._from_mapping(positions.positions(), self._default(), what)
        elif isinstance(positions, Mapping):
            q = self._from_mapping(positions, self._default(), what)
        else:
            if isinstance(positions, str | bytes):
                raise InvalidValueError(f"{what}: expected a mapping or a sequence of numbers, got {positions!r}")
            try:
                q = np.array(positions, dtype=float).reshape(-1)
            except (TypeError, ValueError) as exc:
                raise InvalidValueError(f"{what}: expected numbers, got {positions!r}") from exc
            if q.shape != (len(self.joints),):
                raise InvalidValueError(
                    f"{what}: {q.size} values for {len(self.joints)} joints {list(self.joint_names)}"
                )
        if not np.isfinite(q).all():
            k = int(np.flatnonzero(~np.isfinite(q))[0])
            raise InvalidValueError(f"{what}: joint {self.joint_names[k]!r} is {q[k]}")
        return q

    def _qpos(self, q: FloatArray, out: FloatArray) -> None:
        out[:] = self.model.qpos0
        out[self._qadr] = q
        for c in self._couplings:
            out[c.qadr] = c.multiplier * q[c.leader] + c.offset

    def _set(self, q: FloatArray) -> mujoco.MjData:
        d = self._data
        self._qpos(q, d.qpos)
        mujoco.mj_kinematics(self.model, d)
        return d

    # ------------------------------------------------------------ forward kinematics
    def _pose(self, d: mujoco.MjData, bid: int) -> Pose:
        return Pose.from_trusted_arrays(d.xpos[bid].copy(), _wxyz_to_xyzw(d.xquat[bid]))

    def fk(self, link: str, positions: Positions | None = None, reference: str | None = None) -> Pose:
        """Pose of ``link`` in the root frame (or in ``reference``'s frame) at ``positions``."""
        bid = self.body_id(link)
        rid = self.body_id(reference) if reference is not None else None
        q = self.resolve(positions)
        with self._lock:
            d = self._set(q)
            pose = self._pose(d, bid)
            if rid is not None:
                pose = self._pose(d, rid).inverse() @ pose
        return pose

    def link_poses(self, positions: Positions | None = None) -> LinkPoses:
        """Every link's pose in the root frame, from one FK pass (a TF tree snapshot).

        With a :class:`JointState`, the result carries its ``stamp``; with ``None``,
        the latest measured state's.
        """
        stamp: float | None = None
        if isinstance(positions, JointState):
            stamp = positions.stamp
        elif positions is None and self._state is not None:
            positions = self._state()
            stamp = positions.stamp
        q = self.resolve(positions)
        with self._lock:
            d = self._set(q)
            poses = {name: self._pose(d, bid) for name, bid in self._links.items()}
        return LinkPoses(self.root_link, poses, dict(self._parents), stamp)

    def relative_transforms(self, pairs: Sequence[tuple[str, str]], positions: Positions | None = None) -> FloatArray:
        """Each ``(parent, child)`` pair's pose of ``child`` in ``parent``, from one FK pass.

        A ``(len(pairs), 7)`` array of ``(x, y, z, qx, qy, qz, qw)`` rows: what ``/tf`` carries,
        without building a :class:`Pose` per link (vectorised; used by the ROS 2 tf publisher).
        """
        pid = np.array([self.body_id(p) for p, _ in pairs], dtype=np.intp)
        cid = np.array([self.body_id(c) for _, c in pairs], dtype=np.intp)
        q = self.resolve(positions)
        with self._lock:
            d = self._set(q)
            xp, xc = d.xpos[pid], d.xpos[cid]
            rp = d.xmat[pid].reshape(-1, 3, 3)
            qp, qc = d.xquat[pid], d.xquat[cid]
        out = np.empty((len(pairs), 7))
        out[:, :3] = np.einsum("kji,kj->ki", rp, xc - xp)  # R_parent^T (x_child - x_parent)
        # conj(q_parent) * q_child, MuJoCo's (w, x, y, z) in, (x, y, z, w) out
        aw, av = qp[:, 0], -qp[:, 1:]
        bw, bv = qc[:, 0], qc[:, 1:]
        ax, ay, az = av[:, 0], av[:, 1], av[:, 2]
        bx, by, bz = bv[:, 0], bv[:, 1], bv[:, 2]
        out[:, 3] = aw * bx + bw * ax + ay * bz - az * by
        out[:, 4] = aw * by + bw * ay + az * bx - ax * bz
        out[:, 5] = aw * bz + bw * az + ax * by - ay * bx
        out[:, 6] = aw * bw - ax * bx - ay * by - az * bz
        return out

    def link_frames(self, q: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Every link's position ``(L, 3)`` and orientation ``(L, 4)`` (x, y, z, w) in the root frame.

        Rows in :attr:`link_names` order, ``q`` in joint order; the arrays-only form of
        :meth:`link_poses` for callers that transform many states (the recorder's ``/tf``).
        """
        ids = np.fromiter(self._links.values(), dtype=np.intp, count=len(self._links))
        qa = np.asarray(q, dtype=float)
        with self._lock:
            d = self._set(qa)
            pos = d.xpos[ids].copy()
            quat = d.xquat[ids][:, [1, 2, 3, 0]]
        return pos, quat

    def jacobian(self, link: str, positions: Positions | None = None) -> FloatArray:
        """Geometric Jacobian (6, n) of ``link``'s origin in the root frame: rows (v; w), columns in joint order."""
        bid = self.body_id(link)
        q = self.resolve(positions)
        m = self.model
        jacp = np.zeros((3, m.nv))
        jacr = np.zeros((3, m.nv))
        with self._lock:
            d = self._set(q)
            mujoco.mj_comPos(m, d)
            mujoco.mj_jacBody(m, d, jacp, jacr, bid)
        full = np.vstack((jacp, jacr))
        jac = full[:, self._dadr].copy()
        for c in self._couplings:
            jac[:, c.leader] += c.multiplier * full[:, c.dadr]
        return jac

    def gravity(self, positions: Positions | None = None, gravity: Sequence[float] = (0.0, 0.0, -9.81)) -> FloatArray:
        """Joint torques (n,) that hold the robot still against ``gravity`` (root frame), in joint order.

        ``g(q)`` of ``M(q) qdd + c(q, qd) + g(q) = tau``: MuJoCo's bias force at zero velocity
        (its recursive Newton-Euler), from the description's inertial data. A mimic joint's
        torque is carried by its leader (``multiplier x``).
        """
        q = self.resolve(positions)
        g = np.asarray(gravity, dtype=float)
        if g.shape != (3,) or not np.isfinite(g).all():
            raise InvalidValueError(f"gravity must be 3 finite numbers, got {gravity!r}")
        m = self.model
        with self._lock:
            saved = m.opt.gravity.copy()
            try:
                m.opt.gravity[:] = g
                d = self._data
                self._qpos(q, d.qpos)
                d.qvel[:] = 0.0
                mujoco.mj_fwdPosition(m, d)
                mujoco.mj_fwdVelocity(m, d)
                bias = d.qfrc_bias.copy()
            finally:
                m.opt.gravity[:] = saved
        tau: FloatArray = bias[self._dadr].copy()
        for c in self._couplings:
            tau[c.leader] += c.multiplier * bias[c.dadr]
        return tau

    # ------------------------------------------------------------ inverse kinematics
    def ik(
        self,
        link: str,
        pose: Pose | npt.ArrayLike,
        seed: Positions | None = None,
        *,
        position_only: bool = False,
        position_tolerance: float = IK_POSITION_TOLERANCE,
        orientation_tolerance: float = IK_ORIENTATION_TOLERANCE,
        max_iterations: int = 200,
        restarts: int = 20,
        random_seed: int = 0,
    ) -> IKResult:
        """Joint positions within the limits that put ``link`` at ``pose`` (root frame).

        ``pose`` is a :class:`Pose` (or a 4x4 matrix); a 3-vector is a position target
        and implies ``position_only``. Starts from ``seed`` (default: the current
        positions), then from up to ``restarts`` random configurations within the limits
        (reproducible: ``random_seed``). Converged when the position error is within
        ``position_tolerance`` (m) and, unless ``position_only``, the orientation error
        within ``orientation_tolerance`` (rad).

        Returns an :class:`IKResult` (a ``{joint: position}`` dict) on success. Raises
        :class:`UnreachablePoseError` naming the residual of the best attempt otherwise:
        never a silent best effort. Each step is mink's QP (DAQP) with the joint limits
        as constraints and mimic joints tied to their leaders.
        """
        gen = self._ik_gen(None, link, pose, seed, position_only, position_tolerance, orientation_tolerance,
                           max_iterations, restarts, random_seed)
        with self._lock:
            result: IKResult = run_sync(gen)
            return result

    async def ik_async(
        self,
        link: str,
        pose: Pose | npt.ArrayLike,
        seed: Positions | None = None,
        *,
        position_only: bool = False,
        position_tolerance: float = IK_POSITION_TOLERANCE,
        orientation_tolerance: float = IK_ORIENTATION_TOLERANCE,
        max_iterations: int = 200,
        restarts: int = 20,
        random_seed: int = 0,
    ) -> IKResult:
        """:meth:`ik` for coroutines: yields to the event loop every couple of milliseconds.

        An unreachable target can take a few hundred milliseconds of restarts; this keeps
        the control loop, the watchdogs and other tasks running meanwhile (in lockstep,
        simulated time does not advance while it computes).
        """
        gen = self._ik_gen(IKSolver(self), link, pose, seed, position_only, position_tolerance,
                           orientation_tolerance, max_iterations, restarts, random_seed)
        result: IKResult = await run_async(gen)
        return result

    def _ik_gen(
        self,
        solver: IKSolver | None,
        link: str,
        pose: Pose | npt.ArrayLike,
        seed: Positions | None,
        position_only: bool,
        position_tolerance: float,
        orientation_tolerance: float,
        max_iterations: int,
        restarts: int,
        random_seed: int,
    ) -> Generator[None, None, IKResult]:
        bid = self.body_id(link)
        if bid == 0 or link == self.root_link:
            raise InvalidValueError(f"ik: {link!r} is the root frame; it does not move")
        target, position_only = ik_target(pose, position_only)
        for what, tol in (("position_tolerance", position_tolerance), ("orientation_tolerance", orientation_tolerance)):
            if not (isinstance(tol, int | float) and tol > 0 and math.isfinite(tol)):
                raise InvalidValueError(f"ik: {what} must be a finite number > 0, got {tol!r}")
        if int(max_iterations) < 1 or int(restarts) < 0:
            raise InvalidValueError("ik: max_iterations must be >= 1 and restarts >= 0")
        q0 = np.clip(self.resolve(seed, "seed"), self.lower, self.upper)
        rng = np.random.default_rng(random_seed)
        best: tuple[float, FloatArray, float, float] | None = None
        total = 0
        if solver is None:
            solver = self._solver()
        for attempt in range(int(restarts) + 1):
            start = q0 if attempt == 0 else self._random_configuration(rng)
            q, perr, rerr, iters = yield from solver.solve(
                bid, link, target, start, position_only, position_tolerance, orientation_tolerance,
                int(max_iterations),
            )
            total += iters
            score = perr / position_tolerance + (0.0 if position_only else rerr / orientation_tolerance)
            if best is None or score < best[0]:
                best = (score, q, perr, rerr)
            if perr <= position_tolerance and (position_only or rerr <= orientation_tolerance):
                q = self._tidy(q, q0)
                return IKResult(dict(zip(self.joint_names, q.tolist(), strict=True)), ok=True,
                                position_error=perr, orientation_error=0.0 if position_only else rerr,
                                iterations=total, attempts=attempt + 1)
        assert best is not None
        _, q, perr, rerr = best
        what = "position" if position_only else "pose"
        rot = "" if position_only else f", {rerr:.4g} rad orientation (tolerance {orientation_tolerance:g} rad)"
        msg = (
            f"IK found no joint positions within the limits of {self.name!r} that put link {link!r} at the target "
            f"{what}: residual {perr:.4g} m position (tolerance {position_tolerance:g} m){rot} "
            f"after {int(restarts) + 1} attempts ({total} iterations); the target may be out of reach"
        )
        result = IKResult(dict(zip(self.joint_names, q.tolist(), strict=True)), ok=False, position_error=perr,
                          orientation_error=0.0 if position_only else rerr, iterations=total,
                          attempts=int(restarts) + 1, message=msg)
        raise UnreachablePoseError(msg, result)

    def chain(self, link: str) -> tuple[str, ...]:
        """The actuated joints that move ``link`` (its ancestors' joints; mimic joints count as their leader)."""
        bid = self.body_id(link)
        m = self.model
        dofs: set[int] = set()
        b = bid
        while b > 0:
            for jid in range(int(m.body_jntadr[b]), int(m.body_jntadr[b]) + int(m.body_jntnum[b])):
                dofs.add(int(m.jnt_dofadr[jid]))
            b = int(m.body_parentid[b])
        moving = {k for k, d in enumerate(self._dadr.tolist()) if d in dofs}
        moving |= {c.leader for c in self._couplings if c.dadr in dofs}
        return tuple(self.joint_names[k] for k in sorted(moving))

    def bind_state(self, source: Callable[[], JointState]) -> None:
        """Use ``source()`` (e.g. ``robot.latest_state``) as the default for every ``positions`` argument."""
        self._state = source

    def prepare_ik(self) -> None:
        """Build the IK solver now (imports mink); ``ik`` otherwise builds it on first use."""
        with self._lock:
            self._solver()

    def _solver(self) -> IKSolver:
        if self._ik is None:
            self._ik = IKSolver(self)
        return self._ik

    def _random_configuration(self, rng: np.random.Generator) -> FloatArray:
        lo = np.where(np.isfinite(self.lower), self.lower, -math.pi)
        hi = np.where(np.isfinite(self.upper), self.upper, math.pi)
        return rng.uniform(lo, hi)

    def _tidy(self, q: FloatArray, seed: FloatArray) -> FloatArray:
        """Clip into the limits (QP round-off) and bring continuous joints within pi of the seed."""
        q = np.clip(q, self.lower, self.upper)
        cont = ~(np.isfinite(self.lower) | np.isfinite(self.upper))
        for k in np.flatnonzero(cont).tolist():
            if self.joints[k].type != "prismatic":
                q[k] = seed[k] + (q[k] - seed[k] + math.pi) % (2 * math.pi) - math.pi
        return q

    def __repr__(self) -> str:
        return (
            f"<Kinematics {self.name!r}: {len(self.joints)} joints, {len(self._links)} links, "
            f"root {self.root_link!r}>"
        )


@dataclass(frozen=True)
class _MjcfDescription:
    """The minimum of a RobotDescription that :class:`Kinematics` needs, for a bare MJCF file."""

    name: str
    source: Path
    format: Literal["mjcf"] = "mjcf"
    urdf_xml: str = ""
    links: tuple[str, ...] = ()
    all_joints: tuple[Any, ...] = ()
    root_link: str = "world"


def ik_target(pose: Pose | npt.ArrayLike, position_only: bool) -> tuple[Pose, bool]:
    """An IK target as a :class:`Pose` (a bare 3-vector is a position-only target) and its mode."""
    if isinstance(pose, Pose):
        return pose, bool(position_only)
    try:
        arr = np.asarray(pose, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidValueError(f"ik: expected a Pose, a 4x4 matrix or a position (3,), got {pose!r}") from exc
    if arr.shape == (3,):
        return Pose(arr), True
    if arr.shape == (4, 4):
        return Pose.from_matrix(arr), bool(position_only)
    raise InvalidValueError(f"ik: expected a Pose, a 4x4 matrix or a position (3,), got shape {arr.shape}")


class IKSolver:
    """mink differential IK iterated to convergence (one per Kinematics, used under its lock)."""

    def __init__(self, kin: Kinematics) -> None:
        import mink

        self._mink = mink
        self.kin = kin
        m = kin.model
        self.conf = mink.Configuration(m)
        self.limits = [mink.ConfigurationLimit(m, gain=0.5)]
        constraints: list[Any] = []
        if kin._frozen_dofs:
            constraints.append(mink.DofFreezingTask(m, dof_indices=kin._frozen_dofs))
        if m.neq > 0 and any(m.eq_active0):
            constraints.append(mink.EqualityConstraintTask(m, cost=1.0))
        self.constraints = constraints
        self._tasks: dict[tuple[int, bool], Any] = {}
        self._qpos = np.zeros(m.nq)

    def _task(self, link: str, bid: int, position_only: bool) -> Any:
        key = (bid, position_only)
        task = self._tasks.get(key)
        if task is None:
            task = self._mink.FrameTask(
                frame_name=link, frame_type="body", position_cost=1.0,
                orientation_cost=0.0 if position_only else 1.0, lm_damping=1e-6,
            )
            self._tasks[key] = task
        return task

    def solve(
        self,
        bid: int,
        link: str,
        target: Pose,
        start: FloatArray,
        position_only: bool,
        ptol: float,
        rtol: float,
        max_iterations: int,
    ) -> Generator[None, None, tuple[FloatArray, float, float, int]]:
        """Iterate from ``start`` (yielding after each step); return ``(q, pos. error, orient. error, iterations)``."""
        mink = self._mink
        kin = self.kin
        conf = self.conf
        data = conf.data
        kin._qpos(start, self._qpos)
        conf.update(self._qpos)
        task = self._task(link, bid, position_only)
        wxyz = np.array([target.orientation[3], *target.orientation[:3]])
        task.set_target(mink.SE3(np.concatenate((wxyz, target.position))))
        tq = target.orientation
        best = (math.inf, start.copy(), math.inf, math.inf)
        stall = 0
        iters = 0
        for iters in range(1, max_iterations + 1):
            perr, rerr = _residual(data, bid, target.position, tq)
            score = perr / ptol + (0.0 if position_only else rerr / rtol)
            q_now = data.qpos[kin._qadr].copy()
            if score < best[0] * (1.0 - 1e-3):
                stall = 0
            else:
                stall += 1
            if score < best[0]:
                best = (score, q_now, perr, rerr)
            if perr <= ptol and (position_only or rerr <= rtol):
                return q_now, perr, rerr, iters - 1
            if stall >= 15:  # a local minimum (or the target is out of reach)
                break
            yield
            if position_only:
                # mink's frame error is the SE(3) log, whose translation part mixes in the rotation
                # error: aim at the current orientation so the error is the position error alone
                task.set_target(mink.SE3(np.concatenate((data.xquat[bid], target.position))))
            vel = mink.solve_ik(conf, [task], 1.0, "daqp", damping=1e-8, limits=self.limits,
                                constraints=self.constraints)
            conf.integrate_inplace(vel, 1.0)
            # the QP meets limits and couplings to solver precision: restore them exactly
            kin._qpos(np.clip(data.qpos[kin._qadr], kin.lower, kin.upper), self._qpos)
            conf.update(self._qpos)
        perr, rerr = _residual(data, bid, target.position, tq)
        score = perr / ptol + (0.0 if position_only else rerr / rtol)
        if score < best[0]:
            best = (score, data.qpos[kin._qadr].copy(), perr, rerr)
        return best[1], best[2], best[3], iters


def _residual(data: mujoco.MjData, bid: int, position: FloatArray, quat_xyzw: FloatArray) -> tuple[float, float]:
    perr = float(np.linalg.norm(data.xpos[bid] - position))
    cur = _wxyz_to_xyzw(data.xquat[bid])
    inv = np.array([-cur[0], -cur[1], -cur[2], cur[3]])
    rerr = float(np.linalg.norm(rotation_vector(quat_multiply(inv, quat_xyzw))))
    return perr, rerr
