"""The inverse-dynamics feed-forward of the servo law: the torque the desired motion needs.

The servo law (:mod:`agentsdk.backend`) is ``effort = kp (q_des - q) + kd (v_des - v) + effort_ff +
tau_model``. With gravity compensation alone, ``tau_model = g(q)``: a robot holds its pose, but
while it moves the gains have to produce the torque that accelerates the links and carries
their Coriolis and centrifugal forces, so the joints lag the reference by about
``M q̈ / kp``; on an arm moving at its limits that is millimetres at the hand. A robot
controller feeds the desired motion's inverse dynamics forward instead
(computed-torque feed-forward)::

    tau_model = M(q) a_des + C(q, v_des) v_des + g(q)

with ``v_des`` and ``a_des`` the reference's velocity and acceleration (the setpoint's
``velocity`` and ``acceleration``: the trajectory executor writes both every tick) and ``q``
the measured position. :class:`InverseDynamicsTerm` computes the motion part,
``M(q) a_des + C(q, v_des) v_des`` (``g(q)`` stays the gravity term, so robot.yaml
``gravity_compensation`` keeps its meaning per joint), with MuJoCo's recursive Newton-Euler
on a private ``MjData`` of the model the backend simulates (the MuJoCo backend's compiled
model: its armature included) or the description's host model
(:class:`agentsdk.dynamics.DynamicsModel`: PyBullet, whose ``calculateInverseDynamics`` is
wrong with URDF fixed joints, and CAN). At rest (``v_des = a_des = 0``) the term is exactly 0
and is not computed, so holds are unchanged.

Switched per robot by robot.yaml ``inverse_dynamics`` (default true) or the backend option of
the same name (``connect("mujoco", robot, inverse_dynamics=False)``).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from .dynamics import coupling_matrix

__all__ = ["InverseDynamicsTerm"]


class InverseDynamicsTerm:
    """``M(q) a + C(q, v) v`` of the commanded joints from a compiled MuJoCo model, allocation-free per call.

    ``joints`` are the commanded joints (mimic followers move with their leader: the desired
    velocity and acceleration are spread to them, their torque is carried by the leader, as in
    :func:`~agentsdk.dynamics.coupling_matrix`). Holds a private ``MjData``: not thread-safe
    (one caller, the control tick). A floating base's own velocity and acceleration are taken
    as zero (its pose, in ``qpos``, is used).
    """

    def __init__(self, model: mujoco.MjModel, joints: Sequence[str]) -> None:
        self.model = model
        self._data = mujoco.MjData(model)
        self._s = np.ascontiguousarray(coupling_matrix(model, joints))
        self._st = np.ascontiguousarray(self._s.T)
        self._armature = np.array(model.dof_armature, dtype=np.float64)
        self._full = np.zeros(model.nv)
        self._rest = np.zeros(model.nv)
        self._tmp = np.zeros(model.nv)

    def compute(self, qpos: np.ndarray, velocity: np.ndarray, acceleration: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Write ``S.T (M(q) S a + C(q, S v) S v)`` (n,) into ``out`` and return it.

        ``qpos`` is the model's full position vector (a floating base's pose included);
        ``velocity`` and ``acceleration`` (n,) the desired ones of the commanded joints. 0 when
        both are 0 (nothing computed).
        """
        if not velocity.any() and not acceleration.any():
            out.fill(0.0)
            return out
        m, d = self.model, self._data
        d.qpos[:] = qpos
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        # the bias at rest (gravity only) at this q: subtracted below, g(q) is the gravity term's
        d.qvel[:] = 0.0
        mujoco.mj_comVel(m, d)
        mujoco.mj_rne(m, d, 0, self._rest)
        # the full inverse dynamics M qacc + c(q, qvel) + g(q), plus the rotor inertia (armature)
        np.dot(self._s, velocity, out=d.qvel)
        np.dot(self._s, acceleration, out=d.qacc)
        mujoco.mj_comVel(m, d)
        mujoco.mj_rne(m, d, 1, self._full)
        np.multiply(self._armature, d.qacc, out=self._tmp)
        self._full += self._tmp
        self._full -= self._rest
        np.dot(self._st, self._full, out=out)
        return out
