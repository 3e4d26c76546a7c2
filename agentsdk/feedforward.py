"""The inverse-dynamics feed-forward of the servo law: the torque the desired motion needs.

The servo law (:mod:`agentsdk.backend`) is ``effort = kp (q_des - q) + kd (v_des - v) + effort_ff +
tau_model``. With gravity compensation alone, ``tau_model = g(q)``: a robot holds its pose, but
while it moves the gains have to produce the torque that accelerates the links and carries
their Coriolis and centrifugal forces, so the joints lag the reference by about
``M q̈ / kp``; on an arm moving at its limits that is millimetres at the hand. A robot
controller feeds the desired motion's inverse dynamics forward instead
(computed-torque feed-forward)::

    tau_model = M(q) a_des + C(q, v_des) v_des + b v_des + friction(v_des, a_des) + g(q)

with ``v_des`` and ``a_des`` the reference's velocity and acceleration (the setpoint's
``velocity`` and ``acceleration``: the trajectory executor writes both every tick), ``q`` the
desired position (every backend passes the setpoint's ``position``, so that the term is a
function of the setpoint stream alone; ``g(q)`` stays at the measured one), and the joints' damping ``b`` and dry
friction, which the motion meets as well (on corpus arms with URDF ``<dynamics damping
friction>`` they, not the inertia, dominate the lag). :class:`InverseDynamicsTerm` computes the
motion part (``g(q)`` stays the gravity term, so robot.yaml ``gravity_compensation`` keeps its
meaning per joint) with MuJoCo's inverse dynamics (``mj_inverse``) on a private copy of the
model the backend simulates (the MuJoCo backend's compiled model: armature and soft
``frictionloss`` as it simulates them) or of the description's host model
(:class:`agentsdk.dynamics.DynamicsModel`: PyBullet, whose ``calculateInverseDynamics`` is wrong
with URDF fixed joints, and CAN; dry Coulomb friction). At rest (``v_des = a_des = 0``) the term
is exactly 0 and is not computed, so holds are unchanged.

Switched per robot by robot.yaml ``inverse_dynamics`` (default true) or the backend option of
the same name (``connect("mujoco", robot, inverse_dynamics=False)``).
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from typing import Literal

import mujoco
import numpy as np

from .backend import ModeCode
from .dynamics import coupling_matrix

__all__ = ["ACCELERATION_DTYPE", "FRICTION_VELOCITY", "InverseDynamicsTerm"]

_EFFORT = int(ModeCode.EFFORT)

#: desired speed (rad/s or m/s) from which a joint's full Coulomb friction is fed forward (linear below)
FRICTION_VELOCITY = 0.01
#: precision of the desired acceleration the term uses (rounded to it: relative 6e-8, far below any model's
#: accuracy), so that a recording carries it exactly in 4 bytes a joint and a replay feeds the same torque
ACCELERATION_DTYPE = np.float32


class InverseDynamicsTerm:
    """``M(q) a + C(q, v) v + b v + friction`` of the commanded joints from a MuJoCo model, allocation-free per call.

    ``b`` is the joints' viscous damping (``dof_damping``: URDF ``<dynamics damping>``, plus
    ``extra_damping`` on the commanded joints: a simulator option the model does not hold),
    ``M`` includes the rotor inertia (``dof_armature``). The joints' Coulomb friction
    (``dof_frictionloss``: URDF ``<dynamics friction>``) is fed forward as the backend's plant
    produces it: ``friction="coulomb"`` (PyBullet's and a motor's dry friction: ``F`` against the
    desired velocity, in full from :data:`FRICTION_VELOCITY` on and linearly below, so a
    reference at rest gets none) or ``friction="mujoco"`` (MuJoCo's soft ``frictionloss``
    constraint, through MuJoCo's own inverse dynamics).

    Computed with ``mj_inverse`` on a private copy of ``model`` without gravity (``g(q)`` is
    the gravity term's), springs, contacts, joint limits and equality constraints (mimic
    followers move with their leader: the desired velocity and acceleration are spread to
    them, their torque is carried by the leader, as in :func:`~agentsdk.dynamics.coupling_matrix`).
    A floating base's own velocity and acceleration are taken as zero (its pose, in ``qpos``,
    is used). Not thread-safe (one caller, the control tick).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        joints: Sequence[str],
        *,
        extra_damping: float = 0.0,
        friction: Literal["coulomb", "mujoco"] = "coulomb",
    ) -> None:
        s = coupling_matrix(model, joints)
        m = self.model = copy.copy(model)
        off = mujoco.mjtDisableBit
        m.opt.disableflags |= int(off.mjDSBL_GRAVITY) | int(off.mjDSBL_SPRING)
        if friction == "mujoco" and (m.dof_frictionloss.any() or m.tendon_frictionloss.any()):
            m.opt.disableflags |= int(off.mjDSBL_CONTACT) | int(off.mjDSBL_LIMIT) | int(off.mjDSBL_EQUALITY)
        else:
            # no constraint can remain (without frictionloss, MuJoCo's friction mode keeps none either: no
            # constraint row, qfrc_constraint 0): the constraint stages are skipped, qfrc_inverse the same bits
            m.opt.disableflags |= int(off.mjDSBL_CONSTRAINT)
        m.dof_damping[np.flatnonzero(s.any(axis=1))] += extra_damping
        d = self._data = mujoco.MjData(m)
        # views made once (each MjData attribute access builds a new array object)
        self._qpos, self._qvel, self._qacc, self._qfrc = d.qpos, d.qvel, d.qacc, d.qfrc_inverse
        self._s = np.ascontiguousarray(s)
        self._st = np.ascontiguousarray(s.T)
        self._friction = np.array(m.dof_frictionloss, dtype=np.float64) if friction == "coulomb" else None
        if self._friction is not None and not self._friction.any():
            self._friction = None
        self._tmp = np.zeros(m.nv)
        self._sq = np.zeros(())
        self._effort = np.zeros(len(joints), dtype=bool)
        self._no_effort = self._effort.tobytes()
        #: the bytes of an all-zero (n,) row: a hold's velocity and acceleration, compared without a BLAS call
        self._zero = np.zeros(len(joints)).tobytes()
        self._acc = np.zeros(len(joints))
        self._acc_rounded = np.zeros(len(joints), dtype=ACCELERATION_DTYPE)
        #: the commanded joints' dofs where ``S`` only selects them (see :func:`_selection`): then
        #: compute_block gathers and scatters instead of a matrix product per reference
        self._dofs = _selection(s)
        #: compute_block's work arrays: the rounded accelerations (float64, float32)
        self._blk: tuple[np.ndarray, np.ndarray] | None = None
        #: compute_block's per-reference inputs and results: qpos (K, nq), qvel, qacc, qfrc_inverse (K, nv)
        self._rows: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    def moving(self, velocity: np.ndarray, acceleration: np.ndarray) -> bool:
        """True unless ``velocity`` and ``acceleration`` are all zero (then the term is 0). Allocation-free."""
        zero = self._zero
        if velocity.tobytes() == zero and acceleration.tobytes() == zero:  # a hold: the common case, cheapest
            return False
        sq = self._sq
        np.dot(velocity, velocity, out=sq)
        if sq.item() != 0.0:
            return True
        np.dot(acceleration, acceleration, out=sq)
        return sq.item() != 0.0

    def compute(
        self,
        qpos: np.ndarray,
        velocity: np.ndarray,
        acceleration: np.ndarray,
        out: np.ndarray,
        mode: np.ndarray | None = None,
        *,
        moving: bool | None = None,
    ) -> np.ndarray:
        """Write the term (n,) for the desired ``velocity`` and ``acceleration`` (n,) at ``qpos`` into ``out``.

        ``acceleration`` is used rounded to :data:`ACCELERATION_DTYPE`.

        ``qpos`` is the model's full position vector (a floating base's pose included). 0 when the
        desired velocity and acceleration are both 0 (nothing computed). ``mode`` (the setpoint's
        :class:`~agentsdk.backend.ModeCode` per joint): an effort-mode joint gets none of it (its
        torque is the one commanded, plus ``g(q)``), though its motion still counts for the others.
        ``moving``: what :meth:`moving` returned for these very arrays, when the caller already asked
        (the tick asks once); None asks here.
        """
        if moving is None:
            moving = self.moving(velocity, acceleration)
        if not moving:
            out.fill(0.0)
            return out
        qvel = self._qvel
        self._qpos[...] = qpos
        np.dot(self._s, velocity, out=qvel)
        acc = self._acc
        np.copyto(self._acc_rounded, acceleration, casting="same_kind")  # see ACCELERATION_DTYPE
        np.copyto(acc, self._acc_rounded)
        np.dot(self._s, acc, out=self._qacc)
        mujoco.mj_inverse(self.model, self._data)
        full = self._qfrc
        friction = self._friction
        if friction is not None:  # dry friction against the desired velocity, smoothed near 0
            tmp = self._tmp
            np.multiply(qvel, 1.0 / FRICTION_VELOCITY, out=tmp)
            np.minimum(tmp, 1.0, out=tmp)
            np.maximum(tmp, -1.0, out=tmp)
            tmp *= friction
            full += tmp
        np.dot(self._st, full, out=out)
        if mode is not None:
            effort = self._effort
            np.equal(mode, _EFFORT, out=effort)
            if effort.tobytes() != self._no_effort:  # (np.count_nonzero's Python wrapper costs more)
                out[effort] = 0.0
        return out

    def compute_block(
        self,
        qpos: np.ndarray,
        put: Callable[[np.ndarray, np.ndarray], None],
        positions: np.ndarray,
        velocity: np.ndarray,
        acceleration: np.ndarray,
        rows: np.ndarray,
        out: np.ndarray,
        mode: np.ndarray | None = None,
    ) -> np.ndarray:
        """:meth:`compute` for the references ``rows`` of a block at once, into ``out[rows]`` (bit for bit).

        ``positions``, ``velocity``, ``acceleration`` and ``out`` are (K, n); ``rows`` the indices
        (ascending) of the references to compute; ``qpos`` is the model's full position vector
        around the references (what stays put: a floating base's pose) and ``put(qpos_rows,
        positions_rows)`` writes the references' joints (and mimic followers) into rows of it, (R,
        nq) and (R, n), with the element operations the caller uses per tick before
        :meth:`compute`. Every element operation is the per-call one: the acceleration's rounding,
        the effort-mode mask and, where ``S`` only selects the joints' dofs (no mimic follower:
        arm3, the humanoid), its products (gathers, see :func:`_selection`) run on all rows at
        once; only the copies into MuJoCo's arrays and ``mj_inverse`` run per row (block lockstep,
        issue 28: the feed-forward of a pre-planned motion computed before its block). With mimic
        followers the matrix products run per row; with the Coulomb friction term each row runs
        :meth:`compute` itself. The other rows of ``out`` are left as they are.
        """
        R = len(rows)
        if not R:
            return out
        K = len(velocity)
        m, d = self.model, self._data
        nq, nv, n = m.nq, m.nv, len(self._acc)
        work = self._rows
        if work is None or len(work[0]) < K:
            # the dofs no joint drives stay 0 in the velocity and acceleration rows (as S v leaves them)
            work = self._rows = (np.empty((K, nq)), np.zeros((K, nv)), np.zeros((K, nv)), np.empty((K, nv)))
        qs = work[0][:R]
        qs[...] = qpos
        put(qs, positions[rows])
        if self._friction is not None:
            for j, q in zip(rows, qs, strict=True):
                self.compute(q, velocity[j], acceleration[j], out[j], mode, moving=True)
            return out
        blk = self._blk
        if blk is None or len(blk[0]) < K:
            blk = self._blk = (np.empty((K, n)), np.empty((K, n), dtype=ACCELERATION_DTYPE))
        acc, rounded = blk[0][:K], blk[1][:K]
        np.copyto(rounded, acceleration, casting="same_kind")  # see ACCELERATION_DTYPE
        np.copyto(acc, rounded)
        qpos_, qvel, qacc, full = self._qpos, self._qvel, self._qacc, self._qfrc
        inverse = mujoco.mj_inverse
        dofs = self._dofs
        if dofs is not None:
            vs, accs, fs = work[1][:R], work[2][:R], work[3][:R]
            vs[:, dofs] = velocity[rows] + 0.0  # S v (see _selection)
            accs[:, dofs] = acc[rows] + 0.0
            for q, v, a, f in zip(qs, vs, accs, fs, strict=True):
                qpos_[...] = q
                qvel[...] = v
                qacc[...] = a
                inverse(m, d)
                f[...] = full
            out[rows] = fs[:, dofs] + 0.0  # S.T qfrc_inverse
        else:
            s, st, dot = self._s, self._st, np.dot
            for j, q in zip(rows, qs, strict=True):
                qpos_[...] = q
                dot(s, velocity[j], out=qvel)
                dot(s, acc[j], out=qacc)
                inverse(m, d)
                dot(st, full, out=out[j])
        if mode is not None:
            effort = self._effort
            np.equal(mode, _EFFORT, out=effort)
            if effort.tobytes() != self._no_effort:
                for j in rows:
                    out[j][effort] = 0.0
        return out


def _selection(s: np.ndarray) -> np.ndarray | None:
    """Joint ``k``'s dof where the coupling ``S`` (nv, n) only selects the joints' dofs (else None).

    That is: every column holds one 1.0 and every row at most one nonzero (no mimic follower
    moves with a joint). Then ``S v`` is ``v + 0.0`` at the joints' dofs and 0.0 elsewhere, and
    ``S.T f`` is ``f[dofs] + 0.0``: the matrix-vector product adds, to its initial 0.0, one product
    ``1.0 x`` (exact) and zeros, which leave ``x`` as it is except a -0.0, which becomes 0.0
    (``tests/test_tracking.py`` checks it bit for bit against ``np.dot``).
    """
    if s.shape[1] == 0:  # no joints (a fixed robot with no movable joint): nothing to select
        return np.empty(0, dtype=np.intp)
    nonzero = s != 0.0
    if (nonzero.sum(axis=0) != 1).any() or (nonzero.sum(axis=1) > 1).any():
        return None
    dofs = nonzero.argmax(axis=0)
    if not (s[dofs, np.arange(s.shape[1])] == 1.0).all():
        return None
    return np.ascontiguousarray(dofs, dtype=np.intp)
