"""PyBullet backend: the URDF loaded into a private physics client, the servo law evaluated in Python.

Each controller owns its own physics client (``p.DIRECT`` unless ``gui=True``)
and passes ``physicsClientId`` to every call, so several robots in one process
never share a world.

Torque control, done right. PyBullet gives every joint a velocity motor that
holds it in place; the backend turns those motors off
(``VELOCITY_CONTROL`` with ``forces = URDF friction``, i.e. zero for
frictionless joints, which leaves exactly the URDF Coulomb friction like
MuJoCo's ``frictionloss``), removes PyBullet's default link damping, and
takes the URDF joint damping out of PyBullet's hands. Then, at every physics
substep, it reads ``q, v`` and applies in ``TORQUE_CONTROL``::

    tau = clip(kp*(q_des - q) + kd*(v_des - v) + effort_ff, -max_effort, max_effort)

(zero for disabled joints), the same law the MuJoCo backend evaluates at every
physics step. Like MuJoCo's ``implicitfast`` integrator, the velocity-dependent
terms (the servo ``kd`` of unsaturated actuators and the joint damping) are
integrated implicitly: with the joint-space mass matrix ``M`` and bias forces
``c`` (Coriolis + gravity), the applied torque is
``tau - b*v - dt*D*qacc`` with ``(M + dt*D) qacc = tau - b*v - c`` and
``D = kd + b``, so the explicit PyBullet step lands where an implicit-damping
step would. This keeps stiff damping on light links stable (explicit damping
diverges once ``kd*dt/I > 2``) and matches the MuJoCo backend closely. A
floating base uses the plain explicit law (PyBullet's floating-base dynamics
queries are not reliable enough to build the implicit step on).

``effort`` in the measured state is the servo torque (like MuJoCo's
``actuator_force``): the clamped law above, without passive damping.

Divergence: after every physics substep the joint state is checked; a
non-finite value or a speed above 1e4 rad/s (m/s) raises
:class:`SimulationDiverged`.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import pybullet as p
from pydantic import BaseModel, ConfigDict, Field

from agentsdk.backend import Backend, Capabilities, JointReading, SetpointView
from agentsdk.errors import BackendFault, BackendStartError, ConfigurationError, SimulationDiverged
from agentsdk.types import MODES

__all__ = ["PybulletController", "PybulletOptions"]

log = logging.getLogger("agentsdk.backends.pybullet")

#: joint speed above which the simulation is declared diverged (rad/s or m/s)
MAX_SPEED = 1e4
#: PyBullet clamps joint speeds to ``maxJointVelocity`` (default 100): lift it above MAX_SPEED
_SPEED_CAP = 10.0 * MAX_SPEED

_MOVABLE = {p.JOINT_REVOLUTE: "revolute", p.JOINT_PRISMATIC: "prismatic"}


class PybulletOptions(BaseModel):
    """robot.yaml ``backends.pybullet`` / ``connect("pybullet", ...)`` options."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: physics timestep (s); the control period must be a whole multiple of it
    timestep: float = Field(default=0.001, gt=0.0)
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    #: joint damping added to every actuated joint (N·m·s/rad), on top of the URDF ``<dynamics damping>``
    joint_damping: float = Field(default=0.0, ge=0.0)
    #: constraint solver iterations (joint limits, contacts)
    solver_iterations: int = Field(default=50, ge=1)
    #: keep a free-floating base instead of fixing the root link to the world
    floating_base: bool = False
    #: collide links of the robot with each other (parent/child pairs excluded); PyBullet's default is off
    self_collision: bool = False
    #: open the PyBullet GUI (needs a display; one GUI per process)
    gui: bool = False


class PybulletController(Backend):
    name = "pybullet"
    capabilities = Capabilities(
        modes=frozenset(MODES), lockstep=True, realtime=True, deterministic=True
    )
    options_model = PybulletOptions

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        opts: PybulletOptions = self.options
        nsub = round(self.period / opts.timestep)
        if nsub < 1 or abs(nsub * opts.timestep - self.period) > 1e-9:
            raise ConfigurationError(
                f"control period {self.period:g} s (update_rate {1.0 / self.period:g} Hz) is not a whole multiple "
                f"of the PyBullet timestep {opts.timestep:g} s; change backends.pybullet.timestep or update_rate"
            )
        self._nsub = nsub
        if opts.gui and not _has_display():
            raise ConfigurationError(
                "pybullet gui=True needs a display, but neither DISPLAY nor WAYLAND_DISPLAY is set; "
                "use gui=False (headless p.DIRECT) or run under a display / xvfb-run"
            )
        self._cid = -1
        self._body = -1
        self._time = 0.0
        n = len(self.joints)
        # setpoint copy (written by _write, read by the substeps; _emergency_stop may clear _en from any thread)
        self._qd = np.zeros(n)
        self._vd = np.zeros(n)
        self._ff = np.zeros(n)
        self._kp = np.zeros(n)
        self._kd = np.zeros(n)
        self._en = np.zeros(n, dtype=bool)
        # servo torque of the last substep (what _read reports as effort)
        self._tau = np.zeros(n)
        self._raw = np.zeros(n)
        self._neg_lim = -self.max_effort
        self._q = np.zeros(n)
        self._v = np.zeros(n)
        # what _read returns (the substep scratch arrays above change inside _step)
        self._rq = np.zeros(n)
        self._rv = np.zeros(n)

    # ------------------------------------------------------------ open/close
    async def _open(self) -> None:
        opts: PybulletOptions = self.options
        try:
            self._cid = p.connect(p.GUI if opts.gui else p.DIRECT)
        except p.error as exc:  # e.g. a second GUI in the same process
            raise BackendStartError(f"PyBullet could not open a physics client: {exc}") from exc
        if self._cid < 0:
            raise BackendStartError("PyBullet could not open a physics client")
        cid = self._cid
        if opts.gui:
            p.configureDebugVisualizer(p.COV_ENABLE_GUI, 0, physicsClientId=cid)
        p.setTimeStep(opts.timestep, physicsClientId=cid)
        p.setGravity(*opts.gravity, physicsClientId=cid)
        p.setPhysicsEngineParameter(
            numSolverIterations=opts.solver_iterations,
            numSubSteps=0,
            deterministicOverlappingPairs=1,
            physicsClientId=cid,
        )
        self._load_body()
        self._reset_state()

    def _load_body(self) -> None:
        opts: PybulletOptions = self.options
        cid = self._cid
        # PyBullet's URDF parser (tinyxml2) rejects some valid files written on one very long line
        # (XML_ERROR_PARSING_ATTRIBUTE on the humanoid's 12 kB line): put every element on its own line
        urdf_xml = self.description.urdf_xml.replace("><", ">\n<")
        base_pose: tuple[list[float], list[float]] | None = None
        if opts.floating_base:
            urdf_xml, base_pose = _strip_world_link(urdf_xml)
        flags = p.URDF_USE_INERTIA_FROM_FILE | p.URDF_MAINTAIN_LINK_ORDER
        if opts.self_collision:
            flags |= p.URDF_USE_SELF_COLLISION | p.URDF_USE_SELF_COLLISION_EXCLUDE_PARENT
        fd, tmp = tempfile.mkstemp(suffix=".urdf", prefix=f"agentsdk-{self.description.name}-")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(urdf_xml)
            kw: dict[str, Any] = {}
            if base_pose is not None:
                kw = {"basePosition": base_pose[0], "baseOrientation": base_pose[1]}
            self._body = p.loadURDF(tmp, useFixedBase=not opts.floating_base, flags=flags, physicsClientId=cid, **kw)
        except p.error as exc:
            raise BackendStartError(f"PyBullet could not load the URDF of {self.description.name!r}: {exc}") from exc
        finally:
            Path(tmp).unlink(missing_ok=True)
        body = self._body

        # every movable joint of the multibody (actuated or not), in dof order
        infos = [p.getJointInfo(body, i, physicsClientId=cid) for i in range(p.getNumJoints(body, physicsClientId=cid))]
        by_name: dict[str, tuple[Any, ...]] = {}
        dofs: list[tuple[Any, ...]] = []
        for info in infos:
            name = info[1].decode("utf-8")
            by_name[name] = info
            if info[2] == p.JOINT_FIXED:
                continue
            if info[2] not in _MOVABLE:
                raise BackendStartError(
                    f"joint {name!r} of {self.description.name!r} has a type PyBullet loads as "
                    f"{info[2]} (spherical/planar); only revolute, continuous and prismatic joints are supported"
                )
            dofs.append(info)
        dofs.sort(key=lambda info: info[4])  # uIndex: the row in the mass matrix
        self._dofs = [int(info[0]) for info in dofs]
        nd = len(self._dofs)
        row = {int(info[0]): k for k, info in enumerate(dofs)}
        sel: list[int] = []
        for j in self.joints:
            info = by_name.get(j.name)
            if info is None or info[2] == p.JOINT_FIXED:
                raise BackendStartError(
                    f"joint {j.name!r} is missing from the PyBullet model of {self.description.name!r}"
                )
            sel.append(row[int(info[0])])
        self._sel = np.array(sel, dtype=np.intp)
        passive = [info[1].decode("utf-8") for k, info in enumerate(dofs) if k not in set(sel)]
        if passive:
            log.warning(
                "%s: movable joints %s are not actuated (mimic joints?); they stay passive in PyBullet",
                self.description.name,
                ", ".join(passive),
            )

        # passive dynamics: our own damping (URDF + option), Coulomb friction through the motors
        self._damping = np.array([float(info[6]) for info in dofs]) + opts.joint_damping
        friction = [float(info[7]) for info in dofs]
        for link in range(-1, len(infos)):
            p.changeDynamics(body, link, linearDamping=0.0, angularDamping=0.0, physicsClientId=cid)
        for j in self._dofs:
            p.changeDynamics(body, j, jointDamping=0.0, maxJointVelocity=_SPEED_CAP, physicsClientId=cid)
        # turn the default velocity motors off (they hold the joints otherwise); keep URDF friction
        p.setJointMotorControlArray(
            body, self._dofs, p.VELOCITY_CONTROL, targetVelocities=[0.0] * nd, forces=friction, physicsClientId=cid
        )
        self._implicit = not opts.floating_base
        self._base_pose = p.getBasePositionAndOrientation(body, physicsClientId=cid)

        # preallocated work arrays
        self._q_all = np.zeros(nd)
        self._v_all = np.zeros(nd)
        self._f_all = np.zeros(nd)
        self._d_all = np.zeros(nd)
        self._zeros = [0.0] * nd
        self._diag = np.diag_indices(nd)

    def _reset_state(self) -> None:
        cid, body = self._cid, self._body
        q0 = np.zeros(len(self._dofs))
        q0[self._sel] = self.initial_positions
        for k, j in enumerate(self._dofs):
            p.resetJointState(body, j, float(q0[k]), 0.0, physicsClientId=cid)
        if self.options.floating_base:
            p.resetBasePositionAndOrientation(body, *self._base_pose, physicsClientId=cid)
            p.resetBaseVelocity(body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], physicsClientId=cid)
        self._tau[:] = 0.0
        self._time = 0.0
        self._sense()

    async def _close(self) -> None:
        cid, self._cid = self._cid, -1
        if cid >= 0:
            try:
                p.disconnect(physicsClientId=cid)
            except p.error:  # already gone
                pass

    # ------------------------------------------------------------ servo
    def _write(self, sp: SetpointView) -> None:
        np.copyto(self._qd, sp.position)
        np.copyto(self._vd, sp.velocity)
        np.copyto(self._ff, sp.effort)
        np.copyto(self._kp, sp.kp)
        np.copyto(self._kd, sp.kd)
        np.copyto(self._en, sp.enabled)

    async def _step(self, dt: float) -> None:
        cid, body, dofs = self._cid, self._body, self._dofs
        h = self.options.timestep
        sel = self._sel
        tau, raw = self._tau, self._raw
        f_all, d_all = self._f_all, self._d_all
        lim = self.max_effort
        for _ in range(self._nsub):
            q = np.take(self._q_all, sel, out=self._q)
            v = np.take(self._v_all, sel, out=self._v)
            # the servo law, clamped; zero torque for disabled joints / torque off
            np.subtract(self._qd, q, out=raw)
            raw *= self._kp
            raw += self._kd * (self._vd - v)
            raw += self._ff
            np.maximum(raw, self._neg_lim, out=tau)  # ufuncs: np.clip dispatch costs µs here
            np.minimum(tau, lim, out=tau)
            en = self._en  # cleared by _emergency_stop from any thread: takes effect at the next substep
            if not en.all():
                tau[~en] = 0.0
            # generalized force on every dof: servo torque minus passive damping
            np.multiply(self._damping, self._v_all, out=f_all)
            np.negative(f_all, out=f_all)
            f_all[sel] += tau
            if self._implicit:
                # velocity derivative of the forces: damping, plus kd of the unsaturated enabled servos
                np.copyto(d_all, self._damping)
                d_all[sel] += np.where(en & (np.abs(raw) < lim), self._kd, 0.0)
                if d_all.any():
                    q_list = self._q_all.tolist()
                    mass = np.array(p.calculateMassMatrix(body, q_list, physicsClientId=cid))
                    bias = p.calculateInverseDynamics(
                        body, q_list, self._v_all.tolist(), self._zeros, physicsClientId=cid
                    )
                    mass[self._diag] += h * d_all
                    qacc = np.linalg.solve(mass, f_all - bias)
                    f_all -= h * d_all * qacc
            p.setJointMotorControlArray(body, dofs, p.TORQUE_CONTROL, forces=f_all.tolist(), physicsClientId=cid)
            p.stepSimulation(physicsClientId=cid)
            self._time += h
            self._sense()

    def _sense(self) -> None:
        states = p.getJointStates(self._body, self._dofs, physicsClientId=self._cid)
        q, v = self._q_all, self._v_all
        for k, s in enumerate(states):
            q[k] = s[0]
            v[k] = s[1]
        # NaN in v makes the comparison False, so one max covers finiteness of v too
        if not (np.abs(v).max(initial=0.0) <= MAX_SPEED and np.isfinite(q).all()):
            bad = int(np.argmax(~np.isfinite(q) | ~np.isfinite(v) | (np.abs(v) > MAX_SPEED)))
            name = p.getJointInfo(self._body, self._dofs[bad], physicsClientId=self._cid)[1].decode()
            raise SimulationDiverged(
                f"PyBullet simulation of {self.description.name!r} diverged at t={self._time:.4f} s "
                f"(joint {name!r}: q={q[bad]:.4g}, v={v[bad]:.4g}); lower the gains or the timestep"
            )

    def _read(self) -> JointReading:
        np.take(self._q_all, self._sel, out=self._rq)
        np.take(self._v_all, self._sel, out=self._rv)
        return self._rq, self._rv, self._tau

    def _emergency_stop(self, category: int) -> None:
        # plain stores into arrays the loop thread reads at its next substep; no PyBullet call here
        self._en[:] = False

    async def _recover(self) -> None:
        if self._cid < 0:
            raise BackendFault("the PyBullet client is closed; reconnect")
        self._en[:] = False
        self._reset_state()


def _has_display() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _strip_world_link(urdf_xml: str) -> tuple[str, tuple[list[float], list[float]] | None]:
    """For a floating base: drop a massless root link fixed to the next one (the ROS ``world`` link).

    PyBullet treats a massless base as static, so ``world -(fixed)-> base_link``
    would stay bolted down; the child becomes the floating root, placed at the
    fixed joint's origin.
    """
    root = ET.fromstring(urdf_xml)
    links = {link.get("name"): link for link in root.findall("link")}
    joints = root.findall("joint")
    children = {j.find("child").get("link") for j in joints if j.find("child") is not None}  # type: ignore[union-attr]
    roots = [name for name in links if name not in children]
    if len(roots) != 1:
        return urdf_xml, None
    top = links[roots[0]]
    if top.find("inertial") is not None:
        return urdf_xml, None
    out = [j for j in joints if j.find("parent") is not None and j.find("parent").get("link") == roots[0]]  # type: ignore[union-attr]
    if len(out) != 1 or out[0].get("type") != "fixed":
        return urdf_xml, None
    origin = out[0].find("origin")
    xyz = [float(x) for x in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()]
    rpy = [float(x) for x in (origin.get("rpy", "0 0 0") if origin is not None else "0 0 0").split()]
    root.remove(top)
    root.remove(out[0])
    return ET.tostring(root, encoding="unicode"), (xyz, list(_quat_from_rpy(rpy)))


def _quat_from_rpy(rpy: list[float]) -> tuple[float, float, float, float]:
    r, pi, y = (0.5 * a for a in rpy)
    cr, sr, cp, sp_, cy, sy = math.cos(r), math.sin(r), math.cos(pi), math.sin(pi), math.cos(y), math.sin(y)
    return (
        sr * cp * cy - cr * sp_ * sy,
        cr * sp_ * cy + sr * cp * sy,
        cr * cp * sy - sr * sp_ * cy,
        cr * cp * cy + sr * sp_ * sy,
    )
