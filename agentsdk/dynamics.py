"""Rigid-body dynamics of a robot, computed host-side: gravity torques, joint-space inertia, model-based gains.

The servo law every backend evaluates is (see :mod:`agentsdk.backend`)::

    effort = kp * (q_des - q) + kd * (v_des - v) + effort_ff + tau_model

where ``tau_model`` is the gravity torque ``g(q)`` of the model at the measured
position (``M(q) qdd + c(q, qd) + g(q) = tau``), so a robot holds its pose without a
steady-state error and its gains only have to reject disturbances. The simulators
compute ``g(q)`` from their own model (the MuJoCo backend with its compiled model,
PyBullet with ``calculateInverseDynamics``); a backend without a simulator (CAN)
computes it from the description with a :class:`DynamicsModel`.

Why MuJoCo for the host-side model, not pinocchio (the field's standard rigid-body
library): the SDK already depends on MuJoCo (simulator, kinematics), and
:class:`DynamicsModel` is built with :func:`agentsdk.description.mjspec.build_spec`,
body by body from the repaired description -- exactly the model the MuJoCo backend
and the CAN emulator's MuJoCo plant simulate. The host's ``g(q)`` therefore
matches the simulated robot to rounding (a second library would bring its own
URDF parser, its own inertia repairs and a second source of truth). MuJoCo's
recursive Newton-Euler (``mj_rne``) runs allocation-free on preallocated buffers,
a few microseconds per call for an arm.

The model is the robot's one :class:`~agentsdk.hostmodel.HostModel` (``host=``), the same compiled
model as its :class:`~agentsdk.kinematics.Kinematics`; a :class:`DynamicsModel` computes in its own
``MjData``. Model-based gains (:func:`model_gains`) are documented there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from .config import Gains
from .description.model import quat_from_rpy
from .errors import DescriptionError
from .hostmodel import GravityTerm, HostModel, coupling_matrix
from .pose import Pose
from .types import FloatArray, JointInfo

if TYPE_CHECKING:
    from .description import RobotDescription

__all__ = ["DynamicsModel", "GainReport", "GravityTerm", "coupling_matrix", "declared_gains", "model_gains"]


#: error at which a model-based servo commands the full effort limit (rad, or m for prismatic joints)
EFFORT_ERROR = 0.02
#: largest static error Coulomb friction may leave at the goal (rad or m)
FRICTION_ERROR = 0.005
#: fraction of the discrete-time stability limit the gains may use (see :func:`model_gains`)
STABILITY_FRACTION = 0.25
#: smallest joint inertia considered (kg·m² or kg): a massless chain is not divided by zero
MIN_INERTIA = 1e-9


class DynamicsModel:
    """The description's rigid-body model (MuJoCo, see the module docstring): ``g(q)`` and ``M(q)``.

    ``joints`` are the commanded joints (default: the description's); positions are
    arrays in that order. Mimic joints follow their leader (their inertia and gravity
    torque are carried by it). ``floating_base`` frees the root body (for ``g(q)`` of a
    legged robot at a given base attitude, see :meth:`gravity`).
    """

    def __init__(
        self,
        description: RobotDescription,
        joints: Sequence[JointInfo] | None = None,
        *,
        gravity: Sequence[float] = (0.0, 0.0, -9.81),
        floating_base: bool = False,
        host: HostModel | None = None,
    ) -> None:
        self.description = description
        if host is None:
            host = HostModel.compile(description, joints, gravity=gravity, floating_base=floating_base)
        elif joints is not None and tuple(j.name for j in joints) != host.names:
            raise DescriptionError(f"joints {[j.name for j in joints]} are not the host model's {list(host.names)}")
        #: the robot's one compiled host model (shared with its Kinematics; this object has its own MjData)
        self.host = host
        self.joints: tuple[JointInfo, ...] = host.joints
        self.names = host.names
        self.model = m = host.model
        self._free = host.free_body
        self._data = host.new_data()
        self._qadr = host.qadr
        self._s = host.coupling
        self._gravity = host.gravity_term()
        # joint equalities q_f = c0 + c1 q_l: followers placed from their leader (the host's couplings)
        self._followers = [(c.qadr, c.leader, c.multiplier, c.offset) for c in host.couplings]
        self._qpos = m.qpos0.copy()
        self._free_qadr = int(m.jnt_qposadr[m.body_jntadr[m.body(self._free).id]]) if self._free else 0
        self._mfull = np.zeros((m.nv, m.nv))
        # a floating base: the base link (description.base_link) in the frame of the body that floats
        self._base_in_free = Pose()
        if self._free and description.base_link != self._free:
            joint = description.parent_joint(description.base_link)
            if joint is not None:
                w, x, y, z = quat_from_rpy(joint.rpy)
                self._base_in_free = Pose(joint.xyz, (x, y, z, w))

    def qpos(self, positions: np.ndarray, base: Pose | None = None) -> np.ndarray:
        """The model's full ``qpos`` (a view of an internal buffer) for joint ``positions``.

        ``base``: a floating base link's pose in the world (ignored for a fixed base).
        """
        qpos: np.ndarray = self._qpos
        qpos[self._qadr] = positions
        for adr, leader, mult, offset in self._followers:
            qpos[adr] = offset + mult * positions[leader]
        if base is not None and self._free:
            free = base @ self._base_in_free.inverse()
            x, y, z, w = free.orientation
            adr = self._free_qadr
            qpos[adr : adr + 3] = free.position
            qpos[adr + 3 : adr + 7] = (w, x, y, z)
        return qpos

    def gravity(self, positions: np.ndarray, out: np.ndarray | None = None, base: Pose | None = None) -> FloatArray:
        """Joint torques ``g(q)`` (n,) that hold the robot still at ``positions``, into ``out``.

        Allocation-free with ``out`` and a fixed base. ``base``: a floating base link's pose
        in the world (its attitude sets the direction of gravity in the robot).
        """
        if out is None:
            out = np.zeros(len(self.names))
        return self._gravity.compute(self.qpos(positions, base), out)

    def dofs(self, joints: Sequence[str]) -> np.ndarray:
        """The model's dof index of each named joint (any movable joint, mimic followers included)."""
        m = self.model
        out = np.empty(len(joints), dtype=np.intp)
        for k, name in enumerate(joints):
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
            if jid < 0:
                raise DescriptionError(
                    f"joint {name!r} is missing from the dynamics model of {self.description.name!r}"
                )
            out[k] = m.jnt_dofadr[jid]
        return out

    def terms(self, qpos: np.ndarray, qvel: np.ndarray, mass: np.ndarray, bias: np.ndarray) -> None:
        """``M(q)`` (nv, nv) and ``c(q, v) + g(q)`` (nv,) of the whole model at ``qpos, qvel``, allocation-free.

        Unconstrained (mimic couplings are not applied): what a simulator's own mass matrix and
        bias forces are, in the model's dof order (see :meth:`dofs`).
        """
        m, d = self.model, self._data
        d.qpos[...] = qpos  # (np.copyto's Python wrapper costs more than these copies; per physics substep)
        d.qvel[...] = qvel
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_crb(m, d)
        mujoco.mj_comVel(m, d)
        mujoco.mj_rne(m, d, 0, bias)
        mujoco.mj_fullM(m, d, mass)

    def mass_matrix(self, positions: np.ndarray) -> FloatArray:
        """Joint-space inertia ``S.T M(q) S`` (n, n) of the commanded joints at ``positions``."""
        m, d = self.model, self._data
        np.copyto(d.qpos, self.qpos(positions))
        d.qvel[:] = 0.0
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_crb(m, d)
        mujoco.mj_fullM(m, d, self._mfull)
        return self._s.T @ self._mfull @ self._s

    def gains(
        self,
        positions: np.ndarray,
        *,
        bandwidth: float = 10.0,
        damping_ratio: float = 1.0,
        timestep: float | None = 0.001,
        floating_base: bool = False,
    ) -> GainReport:
        """Model-based servo gains at ``positions`` (see :func:`model_gains`).

        ``floating_base``: the robot stands on its limbs, so each joint also carries the rest of
        the robot (:meth:`carried_inertia`).
        """
        damping = np.zeros(len(self.names))
        friction = np.zeros(len(self.names))
        if self.description.format == "urdf":
            for k, name in enumerate(self.names):
                rec = self.description.joint_record(name)
                damping[k], friction[k] = rec.damping, rec.friction
        else:
            m = self.model
            for k, name in enumerate(self.names):
                jid = m.joint(name).id
                damping[k] = float(m.dof_damping[m.jnt_dofadr[jid]])
                friction[k] = float(m.dof_frictionloss[m.jnt_dofadr[jid]])
        return model_gains(
            self.mass_matrix(positions),
            np.array([j.max_effort for j in self.joints]),
            damping,
            friction,
            bandwidth=bandwidth,
            damping_ratio=damping_ratio,
            timestep=timestep,
            carried=self.carried_inertia(positions) if floating_base else None,
        )

    def carried_inertia(self, positions: np.ndarray) -> FloatArray:
        """Per joint, the inertia of the part of the robot on the base side of the joint, shared by the limbs.

        A robot standing on its limbs moves its body with its joints: joint ``j`` carries the
        mass ``m_r`` of everything not below it (the base and the other limbs) at the distance
        ``r`` of that mass's centre from the joint axis, shared among the ``n`` limbs (chains of
        movable joints leaving the base): ``m_r r**2 / n`` (``m_r / n`` for a prismatic joint).
        """
        m, d = self.model, self._data
        np.copyto(d.qpos, self.qpos(positions))
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        total = float(m.body_subtreemass[0])
        com_total = d.subtree_com[0]
        limbs = self._limbs()
        out = np.zeros(len(self.names))
        for k, name in enumerate(self.names):
            jid = m.joint(name).id
            body = int(m.jnt_bodyid[jid])
            rest = total - float(m.body_subtreemass[body])
            if rest <= 0.0:
                continue
            com = (total * com_total - float(m.body_subtreemass[body]) * d.subtree_com[body]) / rest
            if int(m.jnt_type[jid]) == int(mujoco.mjtJoint.mjJNT_SLIDE):
                out[k] = rest / limbs
                continue
            arm = com - d.xanchor[jid]
            axis = d.xaxis[jid]
            perp = arm - float(arm @ axis) * axis
            out[k] = rest * float(perp @ perp) / limbs
        return out

    def _limbs(self) -> int:
        """How many chains of movable joints leave the base body (at least 1)."""
        m = self.model
        jntnum = m.body_jntnum.copy()
        if self.host.added_free:  # a free joint added for a floating base is not one of the robot's joints
            jntnum[m.body(self._free).id] -= 1
        tops = [b for b in range(1, m.nbody) if m.body_parentid[b] == 0]
        base = tops[0] if len(tops) == 1 else 0
        # descend through bodies without joints (fixed links) to the body the limbs hang from
        while True:
            children = [b for b in range(1, m.nbody) if m.body_parentid[b] == base and b != base]
            if len(children) == 1 and jntnum[children[0]] == 0 and jntnum[base] == 0 and base != 0:
                base = children[0]
                continue
            break

        def moves(b: int) -> bool:
            children = (c for c in range(1, m.nbody) if m.body_parentid[c] == b and c != b)
            return bool(jntnum[b]) or any(moves(c) for c in children)

        return max(1, sum(1 for c in range(1, m.nbody) if m.body_parentid[c] == base and c != base and moves(c)))


@dataclass(frozen=True)
class GainReport:
    """Gains from :func:`model_gains` and what shaped them, per joint (arrays in joint order).

    ``inertia``: the joint-space inertia ``M_jj`` (others held); ``inertia_free``:
    ``1 / (M^-1)_jj`` (others free, what stability is checked against); ``bound``: which
    rule set ``kp`` last -- ``"bandwidth"``, ``"friction"``, ``"damping"``, ``"effort"``
    or ``"timestep"``.
    """

    kp: FloatArray
    kd: FloatArray
    inertia: FloatArray
    inertia_free: FloatArray
    bound: tuple[str, ...]

    def as_gains(self) -> list[Gains]:
        """One :class:`~agentsdk.config.Gains` per joint."""
        return [Gains(p=float(p), d=float(d)) for p, d in zip(self.kp, self.kd, strict=True)]


def model_gains(
    mass_matrix: np.ndarray,
    max_effort: np.ndarray,
    damping: np.ndarray | None = None,
    friction: np.ndarray | None = None,
    *,
    bandwidth: float = 10.0,
    damping_ratio: float = 1.0,
    timestep: float | None = 0.001,
    carried: np.ndarray | None = None,
) -> GainReport:
    """Per-joint servo gains from the joint-space inertia ``M`` (n, n) at the start pose.

    ``carried``: for a robot standing on its limbs (floating base), the inertia each joint
    carries besides its own chain (:meth:`DynamicsModel.carried_inertia`); ``I`` below is the
    larger of the two.

    With ``w = 2*pi*bandwidth``, ``z = damping_ratio``, ``I = M_jj`` (the inertia joint
    ``j`` moves when the other joints are held, at least :data:`MIN_INERTIA`), ``b`` and
    ``f`` the joint's viscous damping and Coulomb friction, ``tau_max`` its effort limit::

        kp = max(I w**2,                  # a position loop of the stated bandwidth
                 f / FRICTION_ERROR,      # friction leaves at most FRICTION_ERROR at the goal
                 b w / 2)                 # heavy damping still settles within ~2/w
        kp = min(kp, tau_max / EFFORT_ERROR)   # full effort at an error of EFFORT_ERROR
        kd = 2 z sqrt(kp I)

    Then the discrete-time bound: the simulators integrate the position term explicitly
    and the damping implicitly (MuJoCo ``implicitfast``, the PyBullet backend's implicit
    step), for which a joint of inertia ``I_f`` with total damping ``c = kd + b`` is
    stable while ``kp h**2 < 4 I_f + 2 h c`` (``h``: the physics ``timestep``). The worst
    case for a joint is when every other joint is free, ``I_f = 1 / (M^-1)_jj``; ``kp``
    is reduced until ``kp h**2 <= STABILITY_FRACTION (4 I_f + 2 h c)`` (``kd`` following
    ``kd = 2 z sqrt(kp I)``). ``timestep=None`` (firmware servos) skips this bound.
    The gravity torque is fed forward separately, so the gains do not need to hold the
    robot's weight.
    """
    m = np.asarray(mass_matrix, dtype=float)
    n = m.shape[0]
    damping = np.zeros(n) if damping is None else np.asarray(damping, dtype=float)
    friction = np.zeros(n) if friction is None else np.asarray(friction, dtype=float)
    effort = np.asarray(max_effort, dtype=float)
    inertia = np.maximum(np.diag(m).copy(), MIN_INERTIA)
    if carried is not None:
        inertia = np.maximum(inertia, np.asarray(carried, dtype=float))
    try:
        inv_diag = np.diag(np.linalg.inv(m + MIN_INERTIA * np.eye(n))) if n else np.zeros(0)
        free = np.minimum(np.maximum(1.0 / np.maximum(inv_diag, 1e-300), MIN_INERTIA), inertia)
    except np.linalg.LinAlgError:
        free = np.full(n, MIN_INERTIA)
    w = 2.0 * math.pi * bandwidth
    z = damping_ratio
    kp = np.empty(n)
    kd = np.empty(n)
    bound: list[str] = []
    for j in range(n):
        candidates = {"bandwidth": inertia[j] * w * w, "friction": friction[j] / FRICTION_ERROR,
                      "damping": damping[j] * w / 2.0}
        why = max(candidates, key=lambda k: candidates[k])
        p = candidates[why]
        if math.isfinite(effort[j]) and p > effort[j] / EFFORT_ERROR:
            p, why = effort[j] / EFFORT_ERROR, "effort"
        if timestep is not None:
            h = timestep
            # largest kp with kp h^2 = s (4 I_f + 2 h (b + 2 z sqrt(kp I))): a quadratic in sqrt(kp)
            s = STABILITY_FRACTION
            a_, b_ = h * h, -4.0 * s * h * z * math.sqrt(inertia[j])
            c_ = -s * (4.0 * free[j] + 2.0 * h * damping[j])
            disc = b_ * b_ - 4.0 * a_ * c_
            root = max(0.0, (-b_ + math.sqrt(disc)) / (2.0 * a_)) if disc >= 0.0 else 0.0
            limit = root * root
            if p > limit:
                p, why = limit, "timestep"
        kp[j] = p
        kd[j] = 2.0 * z * math.sqrt(p * inertia[j])
        bound.append(why)
    return GainReport(kp, kd, inertia, free, tuple(bound))


def declared_gains(
    declared: Sequence[tuple[float, float] | None],
    report: GainReport,
    damping: np.ndarray,
    timestep: float | None,
    damping_ratio: float = 1.0,
) -> list[Gains | None]:
    """The description's own servo gains (``(kp, kd)`` per joint, None where it declares none), as used.

    They are used as declared, with two exceptions:

    * a servo declared without damping (``kd = 0``: MJCF ``<position>``'s default ``kv``, i.e. none
      given) on a joint whose own damping ``b`` leaves it below ``damping_ratio`` gets
      ``kd = 2 z sqrt(kp I) - b`` (``I`` from ``report``, as :func:`model_gains` sizes ``kd``):
      an undamped servo rings for ever on a rigid model;
    * ``kp`` is lowered to the discrete-time bound of :func:`model_gains`,
      ``kp h**2 <= STABILITY_FRACTION (4 I_f + 2 h (kd + b))`` with ``I_f`` from ``report`` (the
      inertia the joint moves with every other joint free), where the simulator's ``timestep``
      could not integrate them (a model written for a smaller step, or a second simulator).
    """
    out: list[Gains | None] = []
    for j, pair in enumerate(declared):
        if pair is None:
            out.append(None)
            continue
        kp, kd = pair
        b = float(damping[j])
        if kd == 0.0:
            kd = max(0.0, 2.0 * damping_ratio * math.sqrt(kp * float(report.inertia[j])) - b)
        if timestep is not None:
            h = timestep
            kp = min(kp, STABILITY_FRACTION * (4.0 * float(report.inertia_free[j]) + 2.0 * h * (kd + b)) / (h * h))
        out.append(Gains(p=kp, d=kd))
    return out
