"""A MuJoCo simulation of the robot behind the emulated MIT motors (``emulate-can --plant mujoco``).

The free-rotor model of :class:`~agentsdk.backends.can.emulator.EmulatedMotor` has no gravity,
no coupling between joints and no contacts; this plant does. The robot is built from its
description exactly as the MuJoCo backend builds it (:func:`agentsdk.description.mjspec.build_spec`,
the same links, repaired inertials and collision model), with one servo actuator per motor.
Each motor's firmware law is mapped into its joint through the robot.yaml
mapping ``q_motor = direction * gear_ratio * q_joint + zero_offset``::

    tau_joint = direction * gear_ratio * tau_motor       kp_joint = gear_ratio**2 * kp_motor
    q_des_joint = (p_des_motor + zero - zero_offset) / (direction * gear_ratio)  (same for v, without offsets)

and evaluated by MuJoCo as an affine-bias actuator (implicit in the damping term, clamped to the
motor's torque range through the gearbox), so stiff gains on light links stay stable. After the
step, each motor's physical position and velocity are read back from its joint. A motor that is
disabled, faulted, pausing after a zero frame or timed out applies no torque: the joint falls.
The motors' own viscous damping and Coulomb friction become joint damping and friction loss.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from agentsdk.description import resolve_robot
from agentsdk.description.collision import for_robot
from agentsdk.description.mjspec import build_spec
from agentsdk.errors import ConfigurationError

from .config import CanBusConfig

if TYPE_CHECKING:
    from pathlib import Path

    from .emulator import EmulatedMotor

__all__ = ["MujocoPlant", "untimed_mujoco"]


def _no_time() -> float:
    return 0.0


def untimed_mujoco() -> None:
    """Turn MuJoCo's internal profiling timers off in this process (``mjcb_time`` returns 0).

    MuJoCo (4.x) times the stages of every ``mj_step`` with the process's monotonic clock,
    about 30 clock reads per step. On most machines a clock read costs tens of nanoseconds
    (the vDSO); in user-mode Linux, which has no vDSO, each is a system call that traps into
    the guest kernel (~60 µs measured), so one ``mj_step`` of mit_leg took ~1.8 ms instead of
    ~20 µs and a plant stepping every 2 ms needed the VM's whole CPU. With this callback
    ``MjData.timer`` stays at 0. Process-wide (``mjcb_time`` is a global of MuJoCo): the
    ``emulate-can`` process calls it, a library importing the plant does not.
    """
    mujoco.set_mjcb_time(_no_time)


class MujocoPlant:
    """The robot of a robot.yaml simulated in MuJoCo, driven by the emulated motors' torques."""

    def __init__(
        self,
        robot: str | Path,
        can_config: CanBusConfig,
        *,
        gravity: tuple[float, float, float] = (0.0, 0.0, -9.81),
        damping: float = 0.05,
        friction: float = 0.02,
    ) -> None:
        config, description = resolve_robot(robot)
        if description.format != "urdf":
            raise ConfigurationError("the MuJoCo plant builds URDF robots (MJCF robots are not mapped to motors)")
        collision = for_robot(description, config)
        build = build_spec(description, collision.shapes, shell=collision.shell)
        spec = build.spec
        for a, b in sorted(collision.excluded):
            spec.add_exclude(bodyname1=a, bodyname2=b)
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
        spec.option.gravity = list(gravity)
        self._motor_ids: list[int] = []
        self._dir: list[float] = []
        self._gear: list[float] = []
        self._z0: list[float] = []
        self._joints: list[str] = []
        for joint, mc in can_config.motors.items():
            sj = spec.joint(joint)
            if sj is None:
                raise ConfigurationError(f"backends.can.motors names joint {joint!r}, which the robot does not have")
            g = mc.gear_ratio
            d = np.array(sj.damping, dtype=float)
            d[0] += damping * g * g
            sj.damping = d.tolist()
            sj.frictionloss = sj.frictionloss + friction * g
            r = mc.motor_ranges
            lo, hi = sorted((mc.direction * g * r.t_min, mc.direction * g * r.t_max))
            act = spec.add_actuator()
            act.name = f"{joint}_motor"
            act.target = joint
            act.trntype = mujoco.mjtTrn.mjTRN_JOINT
            act.gaintype = mujoco.mjtGain.mjGAIN_FIXED
            act.biastype = mujoco.mjtBias.mjBIAS_AFFINE
            act.gainprm[0] = 1.0
            act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
            act.forcerange = [lo, hi]
            self._motor_ids.append(mc.id)
            self._dir.append(float(mc.direction))
            self._gear.append(float(g))
            self._z0.append(float(mc.zero_offset))
            self._joints.append(joint)
        self._spec = spec
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self._motors: list[EmulatedMotor] = []
        self._start = {**description.default_positions, **config.initial_positions}

    def attach(self, motors: Mapping[int, EmulatedMotor], substep: float) -> None:
        """Compile the model with ``substep`` as its timestep and start it where the motors are."""
        missing = [mid for mid in self._motor_ids if mid not in motors]
        if missing:
            raise ConfigurationError(f"the plant drives motor id(s) {missing}, which the emulator does not have")
        self._spec.option.timestep = substep
        self.model = self._spec.compile()
        self.data = mujoco.MjData(self.model)
        m, d = self.model, self.data
        self._motors = [motors[mid] for mid in self._motor_ids]
        jids = [m.joint(j).id for j in self._joints]
        self._qadr = np.array([m.jnt_qposadr[i] for i in jids], dtype=np.intp)
        self._dadr = np.array([m.jnt_dofadr[i] for i in jids], dtype=np.intp)
        self._dg = np.array(self._dir) * np.array(self._gear)
        self._g2 = np.array(self._gear) ** 2
        self._z = np.array(self._z0)
        # the rest of the robot (joints without a motor) starts at the robot's start pose
        for name, q in self._start.items():
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
            if jid >= 0:
                d.qpos[m.jnt_qposadr[jid]] = q
        raw = np.array([mot.raw_position for mot in self._motors])
        d.qpos[self._qadr] = (raw - self._z) / self._dg
        d.qvel[self._dadr] = np.array([mot.velocity for mot in self._motors]) / self._dg
        mujoco.mj_forward(m, d)
        # the same maps as Python floats: advance() uses them per motor, per batch
        self._dg_f: list[float] = self._dg.tolist()
        self._g2_f: list[float] = self._g2.tolist()
        self._z_f: list[float] = self._z.tolist()
        self._ctrl = np.zeros(m.nu)
        self._bias = m.actuator_biasprm

    def advance(self, h: float, t: float, n: int) -> None:
        """``n`` MuJoCo steps under the motors' firmware laws at ``t``, then the motors' state from their joints.

        The laws are constant over the batch (the emulator cuts batches where one changes), so the
        actuators are set once and MuJoCo steps ``n`` times in one call: the Python cost is per
        batch (per received frame or idle poll), not per substep.
        """
        m, d = self.model, self.data
        assert m is not None and d is not None
        ctrl, bias = self._ctrl, self._bias
        dg_, g2_, z_ = self._dg_f, self._g2_f, self._z_f
        for k, mot in enumerate(self._motors):
            if mot.active(t):
                dg = dg_[k]
                kp = g2_[k] * mot.kp
                kd = g2_[k] * mot.kd
                q_des = (mot.p_des + mot.zero_offset - z_[k]) / dg
                ctrl[k] = kp * q_des + kd * (mot.v_des / dg) + dg * mot.t_ff
                bias[k, 1] = -kp
                bias[k, 2] = -kd
            else:
                ctrl[k] = 0.0
                bias[k, 1] = 0.0
                bias[k, 2] = 0.0
        d.ctrl[:] = ctrl
        mujoco.mj_step(m, d, nstep=n)
        q = d.qpos[self._qadr].tolist()
        v = d.qvel[self._dadr].tolist()
        for k, mot in enumerate(self._motors):
            mot.raw_position = dg_[k] * q[k] + z_[k]
            mot.velocity = dg_[k] * v[k]
