"""The implicit step of a floating-base robot on PyBullet: joint damping and rotor inertia with contacts.

A fixed-base arm's implicit step (:mod:`backends.pybullet`) predicts the joint
accelerations from the rigid-body model alone. A robot standing on the ground
cannot: its legs carry the body through contact forces the model does not see, and
a prediction without them (the robot in free fall) would take most of the holding
torque away. This step therefore adds the generalized constraint force PyBullet
applied in the previous substep (contacts, joint limits, mimic couplings), measured
as what the model needs to explain the motion::

    F_ext = (M(q) - A) (v - v_prev) / h + c(q, v) + g(q) - f_prev

(``f_prev``: the joint forces applied then, zero on the base's six dofs; ``M - A``: PyBullet's
rigid bodies, without the rotors' inertia ``A`` it does not simulate), weighted by
:data:`EXT_FILTER` against the previous estimate,
and kept only on the base and on the joints that carry a link in contact (elsewhere
the measurement holds nothing but model error, which fed back on a light finger
would grow from substep to substep), and
solves the whole model - the free base included, from PyBullet's base state -
with the damping integrated implicitly and the rotors' inertia ``A`` (MJCF
``armature``) that PyBullet does not simulate::

    (M + A + h D) qacc = f - c - g + F_ext
    f_applied = (c + g + M qacc - F_ext) on the joints

so PyBullet's rigid bodies take ``qacc`` when the constraint forces stay what they
were. Standing still, ``qacc`` is ~0 and the applied torque is the servo's; in
the air the legs move with their own (and their rotors') inertia and stiff damping
on a light shin stays stable. A constraint force that changes from one substep to
the next is corrected within a few substeps (the error shrinks by ``(A + h D) /
(M + A + h D)`` per substep).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pybullet as p

from agentsdk.dynamics import DynamicsModel
from agentsdk.pose import Pose

from .friction import friction_torque

__all__ = ["EXT_FILTER", "FloatingStep", "free_body_name"]

#: weight of the newest measurement in the constraint force estimate (per substep; below 1 a low-pass). 1: the
#: estimate lags one substep already, and a filter's further lag rings on a light link with a heavy rotor (the
#: quadruped fixture with rotors 20 times its shins' inertia held its knees within 0.03 rad at 1, swung 0.02-0.1
#: rad at 0.3); a 10 cm drop, G1's fingers, Apollo and the corpus quadrupeds stand either way
EXT_FILTER = 1.0


def free_body_name(model: mujoco.MjModel) -> str | None:
    """The body of the model's (first) free joint, or None."""
    for j in range(model.njnt):
        if int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE):
            return str(model.body(int(model.jnt_bodyid[j])).name)
    return None


def _pose_in(model: mujoco.MjModel, body: str, frame: str) -> Pose:
    """``body``'s frame in ``frame``'s body frame at the model's reference configuration."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)

    def world(name: str) -> Pose:
        b = model.body(name).id
        w, x, y, z = data.xquat[b]
        return Pose(data.xpos[b], (x, y, z, w))

    return world(frame).inverse() @ world(body)


class FloatingStep:
    """The step of the module docstring for one PyBullet body (allocation-light: preallocated buffers).

    ``dofs``: per PyBullet joint dof, its dof index in ``model``; ``qadr`` its ``qpos`` index.
    ``base_in_inertial``: PyBullet's base link in the frame PyBullet reports the base by (its inertial
    frame); ``base_link``: that link's name in the model.
    """

    def __init__(
        self,
        model: DynamicsModel,
        dofs: np.ndarray,
        qadr: np.ndarray,
        *,
        base_link: str,
        base_in_inertial: Pose,
        timestep: float,
        friction: np.ndarray,
    ) -> None:
        self._model = model
        m = model.model
        free = free_body_name(m)
        if free is None or m.nv != 6 + len(dofs):
            raise ValueError("the floating step needs a model with one free joint and PyBullet's joints")
        jid = int(m.body_jntadr[m.body(free).id])
        fadr = int(m.jnt_dofadr[jid])
        self._base_dofs = np.arange(fadr, fadr + 6)
        self._fqadr = int(m.jnt_qposadr[jid])
        # the free body in PyBullet's base inertial frame: T_free = T_inertial @ x
        link_in_free = _pose_in(m, base_link, free) if base_link != free else Pose()
        x = base_in_inertial @ link_in_free.inverse()
        self._xp = np.array(x.position, dtype=float)
        xx, xy, xz, xw = x.orientation
        self._xq = np.array([xw, xx, xy, xz])
        self._dofs = np.asarray(dofs, dtype=np.intp)
        self._qadr = np.asarray(qadr, dtype=np.intp)
        self._h = float(timestep)
        self._friction = np.asarray(friction, dtype=float)
        self._friction_any = bool(self._friction.any())
        self._armature = np.asarray(m.dof_armature, dtype=float).copy()
        nv = m.nv
        self._friction_all = np.zeros(nv)  # the base's six dofs: none
        self._friction_all[self._dofs] = self._friction
        self._qpos = m.qpos0.copy()
        self._qvel = np.zeros(nv)
        self._qvel_prev = np.zeros(nv)
        self._have_prev = False
        self._mass = np.zeros((nv, nv))
        self._bias = np.zeros(nv)
        self._a = np.zeros((nv, nv))
        self._rhs = np.zeros(nv)
        self._ext = np.zeros(nv)
        self._meas = np.zeros(nv)
        self._applied = np.zeros(nv)
        self._out = np.zeros(nv)
        self._diag = np.diag_indices(nv)
        self._jdiag = (self._dofs, self._dofs)
        # base-state scratch (wxyz quaternions, 3-vectors)
        self._qin = np.zeros(4)
        self._qfree = np.zeros(4)
        self._qneg = np.zeros(4)
        self._vec = np.zeros(3)
        self._vec2 = np.zeros(3)
        self._omega = np.zeros(3)

    def _touching(self, cid: int, body: int) -> np.ndarray:
        """Per joint dof: whether a link at or below it is in contact (with the ground or itself)."""
        links = self._contact_links
        links.fill(False)
        for c in p.getContactPoints(bodyA=body, physicsClientId=cid):
            links[c[3] + 1] = True
            if c[2] == body:
                links[c[4] + 1] = True
        np.matmul(self._subtree, links, out=self._touch_count)
        return self._touch_count > 0

    def bind(self, cid: int, body: int, joints: list[int]) -> None:
        """PyBullet's link tree: which links move with each joint dof (``joints``: PyBullet joint index per dof)."""
        n = p.getNumJoints(body, physicsClientId=cid)
        parent = [int(p.getJointInfo(body, j, physicsClientId=cid)[16]) for j in range(n)]
        below = np.zeros((len(joints), n + 1), dtype=np.int64)  # column 0: the base (link -1)
        for k, j in enumerate(joints):
            for link in range(n):
                x = link
                while x >= 0 and x != j:
                    x = parent[x]
                if x == j:
                    below[k, link + 1] = 1
        self._subtree = below
        self._contact_links = np.zeros(n + 1, dtype=np.int64)
        self._touch_count = np.zeros(len(joints), dtype=np.int64)

    def reset(self) -> None:
        """Forget the previous substep (after the state was set from outside)."""
        self._have_prev = False

    def _base_state(self, cid: int, body: int) -> None:
        """The free joint's ``qpos``/``qvel`` (MuJoCo's convention) from PyBullet's base state."""
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
        lin, ang = p.getBaseVelocity(body, physicsClientId=cid)
        qin, qfree, vec, vec2, omega = self._qin, self._qfree, self._vec, self._vec2, self._omega
        qin[0], qin[1], qin[2], qin[3] = orn[3], orn[0], orn[1], orn[2]
        mujoco.mju_mulQuat(qfree, qin, self._xq)
        mujoco.mju_rotVecQuat(vec, self._xp, qin)  # free origin - inertial origin (world)
        a = self._fqadr
        qpos, qvel = self._qpos, self._qvel
        qpos[a] = pos[0] + vec[0]
        qpos[a + 1] = pos[1] + vec[1]
        qpos[a + 2] = pos[2] + vec[2]
        qpos[a + 3 : a + 7] = qfree
        omega[0], omega[1], omega[2] = ang
        # linear velocity of the free body's origin: PyBullet's is the centre of mass's
        mujoco.mju_cross(vec2, omega, vec)
        d = self._base_dofs
        qvel[d[0]] = lin[0] + vec2[0]
        qvel[d[1]] = lin[1] + vec2[1]
        qvel[d[2]] = lin[2] + vec2[2]
        # angular velocity in the free body's frame
        mujoco.mju_negQuat(self._qneg, qfree)
        mujoco.mju_rotVecQuat(vec2, omega, self._qneg)
        qvel[d[3]], qvel[d[4]], qvel[d[5]] = vec2

    def __call__(
        self, cid: int, body: int, q: np.ndarray, v: np.ndarray, force: np.ndarray, damping: np.ndarray
    ) -> np.ndarray:
        """The joint forces to apply (into ``force``, which holds the servo's and passive forces on entry).

        ``q, v``: PyBullet's joint state (its dof order); ``damping``: per dof, the velocity derivative
        of ``-force`` (servo ``kd`` where unsaturated, plus viscous damping).
        """
        self._base_state(cid, body)
        qpos, qvel, mass, bias = self._qpos, self._qvel, self._mass, self._bias
        dofs, h = self._dofs, self._h
        qpos[self._qadr] = q
        qvel[dofs] = v
        self._model.terms(qpos, qvel, mass, bias)
        ext = self._ext
        if self._have_prev:
            meas = self._meas
            np.subtract(qvel, self._qvel_prev, out=meas)
            meas /= h
            np.matmul(mass, meas, out=self._out)
            # PyBullet moved rigid bodies without rotors: their inertia explains the motion, not M + A (measured
            # with A, the rotors' A qacc came back as a constraint force with the gain -A/M_rigid: a light ankle
            # link on a heavy rotor diverged within a few substeps: A/M_rigid > 5.7 with a filter weight of 0.3)
            self._out -= self._armature * meas
            self._out += bias
            self._out -= self._applied
            # (a weight below 1 low-passes: a standing robot's weight passes, an impulse is spread over substeps)
            self._out -= ext
            self._out *= EXT_FILTER
            ext += self._out
            # contacts act only on the joints that carry a touching link: elsewhere the measurement holds
            # nothing but model error, which fed back on a light finger would grow from step to step
            touching = self._touching(cid, body)
            ext[dofs[~touching]] = 0.0
        else:
            ext.fill(0.0)
        a, rhs = self._a, self._rhs
        np.copyto(a, mass)
        a[self._jdiag] += h * damping
        np.subtract(ext, bias, out=rhs)
        rhs[dofs] += force
        qacc = np.linalg.solve(a, rhs)
        if self._friction_any:  # the joints that can stop this substep stop, the others slide (coupled)
            rhs += friction_torque(a, rhs, qvel, h, self._friction_all)
            qacc = np.linalg.solve(a, rhs)
        mass[self._diag] -= self._armature  # PyBullet's rigid bodies: the rotors take A qacc
        out = self._out
        np.matmul(mass, qacc, out=out)
        out += bias
        out -= ext
        np.take(out, dofs, out=force)
        self._applied.fill(0.0)
        self._applied[dofs] = force
        np.copyto(self._qvel_prev, qvel)
        self._have_prev = True
        return force
