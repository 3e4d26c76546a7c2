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
* for MJCF, the model as written (MuJoCo is its reference implementation), its actuators dropped.

That model is a :class:`~agentsdk.hostmodel.HostModel`, compiled once per robot and shared with the
robot's :class:`~agentsdk.dynamics.DynamicsModel` (``host=``); this object computes in its own
``MjData`` under its own lock, so it may be used from any thread.

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

import logging
import math
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np
import numpy.typing as npt

from .errors import (
    DescriptionError,
    InvalidValueError,
    UnknownJointError,
    UnknownLinkError,
)
from .hostmodel import (
    EQ_JOINT,
    HINGE,
    SLIDE,
    GravityTerm,
    HostModel,
    MjcfDescription,
    Positions,
    compile_spec,
    host_spec,
    link_tree,
    wxyz_to_xyzw,
)

# mjcf_source and ik_target live in .hostmodel and .ik; still importable from here (re-exported)
from .hostmodel import mjcf_source as mjcf_source
from .ik import (
    IK_ORIENTATION_TOLERANCE,
    IK_POSITION_TOLERANCE,
    IKResult,
    IKSolver,
    run_async,
    run_sync,
    search,
)
from .ik import ik_target as ik_target
from .pose import Pose
from .types import FloatArray, JointInfo, JointState

if TYPE_CHECKING:
    from .description import RobotDescription

__all__ = ["IKResult", "Kinematics", "LinkPoses", "Positions", "run_async", "run_sync"]

log = logging.getLogger(__name__)



# --------------------------------------------------------------------------- results


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
        host: HostModel | None = None,
    ) -> None:
        self.description = description
        self.name: str = description.name
        if host is None:
            host = HostModel.compile(description, joints)
        elif joints is not None and tuple(j.name for j in joints) != host.names:
            raise InvalidValueError(f"joints {[j.name for j in joints]} are not the host model's {list(host.names)}")
        #: the robot's one compiled host model (shared with its DynamicsModel; this object has its own MjData)
        self.host = host
        self.joints: tuple[JointInfo, ...] = host.joints
        self._state = state
        self.model = host.model
        #: bodies whose inertia MuJoCo rejected and that were repaired (see the module docstring)
        self.repaired_inertias: tuple[str, ...] = host.repaired_inertias
        m = self.model
        self._data = host.new_data()
        self._lock = threading.RLock()
        self.joint_names: tuple[str, ...] = host.names
        self._index = dict(host.index)
        n = len(self.joints)
        self._qadr, self._dadr = host.qadr, host.dadr
        self.lower = np.array([j.lower for j in self.joints])
        self.upper = np.array([j.upper for j in self.joints])
        self._couplings = host.couplings
        coupled = {c.dadr for c in self._couplings}
        actuated = set(self._dadr.tolist())
        #: dofs IK must not move: free/ball joints and joints that are neither actuated nor mimic
        self._frozen_dofs = [d for d in range(m.nv) if d not in actuated and d not in coupled]
        self._neutral = np.clip(np.zeros(n), self.lower, self.upper)

        self._links, self._parents, self.root_link = link_tree(m, description)
        self._body = {name: bid for name, bid in self._links.items()}
        self._ik: IKSolver | None = None
        self._gravity: GravityTerm | None = None
        self._gravity_qpos = np.zeros(m.nq)

    @classmethod
    def for_robot(cls, robot: Any) -> Kinematics:
        """The kinematics of a connected :class:`~agentsdk.Robot`, defaulting to its latest measured state.

        On the robot's one host model (its own ``MjData``): nothing is compiled again.
        """
        return cls(robot.description, robot.joints, state=robot.latest_state, host=robot.backend.spec.host.get())

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
        desc = MjcfDescription(name=path.stem, source=path)
        try:
            model = compile_spec(host_spec(desc))
        except Exception as exc:
            raise DescriptionError(f"{path}: MuJoCo could not load the MJCF model: {exc}") from exc
        followers = {
            int(model.eq_obj1id[e]) for e in range(model.neq) if int(model.eq_type[e]) == EQ_JOINT
        }
        infos: list[JointInfo] = []
        names_in_model = []
        for jid in range(model.njnt):
            typ = int(model.jnt_type[jid])
            if typ not in (HINGE, SLIDE):
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
                    type=("revolute" if limited else "continuous") if typ == HINGE else "prismatic",
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
        desc = MjcfDescription(name=model.names.split(b"\0")[0].decode() or path.stem, source=path)
        # the model compiled above is the host model: an MJCF file is compiled once here too
        host = HostModel(model, desc, infos)
        return cls(desc, infos, state=state, host=host)  # type: ignore[arg-type]

    # ------------------------------------------------------------ structure
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
        self.host.qpos(q, out)

    def _set(self, q: FloatArray) -> mujoco.MjData:
        d = self._data
        self._qpos(q, d.qpos)
        mujoco.mj_kinematics(self.model, d)
        return d

    # ------------------------------------------------------------ forward kinematics
    def _pose(self, d: mujoco.MjData, bid: int) -> Pose:
        return Pose.from_trusted_arrays(d.xpos[bid].copy(), wxyz_to_xyzw(d.xquat[bid]))

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
        out = np.zeros(len(self.joints))
        with self._lock:
            term = self._gravity_term(g)
            self._qpos(q, self._gravity_qpos)
            term.compute(self._gravity_qpos, out)
        return out

    def _gravity_term(self, gravity: FloatArray) -> GravityTerm:
        """The host model's one g(q) (:class:`~agentsdk.hostmodel.GravityTerm`, this object's own ``MjData``).

        Made on first use, and again when ``gravity`` differs from the last call's (the shared
        model is never changed: another vector computes on a copy, :meth:`HostModel.gravity_term`).
        """
        term = self._gravity
        if term is None or not np.array_equal(term.model.opt.gravity, gravity):
            term = self._gravity = self.host.gravity_term(gravity)
        return term

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
        gen = search(self, None, link, pose, seed, position_only, position_tolerance, orientation_tolerance,
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
        gen = search(self, IKSolver(self), link, pose, seed, position_only, position_tolerance,
                           orientation_tolerance, max_iterations, restarts, random_seed)
        result: IKResult = await run_async(gen)
        return result


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


    def __repr__(self) -> str:
        return (
            f"<Kinematics {self.name!r}: {len(self.joints)} joints, {len(self._links)} links, "
            f"root {self.root_link!r}>"
        )


