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
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import pybullet as p
from pydantic import BaseModel, ConfigDict, Field

from agentsdk.backend import Backend, Capabilities, JointReading, SetpointView, substeps
from agentsdk.config import MAX_GAIN
from agentsdk.description import RobotDescription
from agentsdk.description.collision import SelfCollision, for_robot, from_mjcf
from agentsdk.description.mjcf import mjcf_unsupported_by_pybullet
from agentsdk.description.simurdf import collapsible_links, simulator_urdf
from agentsdk.errors import AgentSDKError, BackendFault, BackendStartError, ConfigurationError, SimulationDiverged
from agentsdk.threads import run_blocking
from agentsdk.types import MODES

__all__ = ["MAX_SPEED", "SPEED_CAP", "PybulletController", "PybulletOptions"]

log = logging.getLogger("agentsdk.backends.pybullet")

#: joint speed above which the simulation is declared diverged (rad/s or m/s)
MAX_SPEED = 1e4
#: PyBullet clamps joint speeds to ``maxJointVelocity`` (default 100): the backend lifts it to this, above MAX_SPEED
SPEED_CAP = 10.0 * MAX_SPEED
_MAX_SPEED_SQ = MAX_SPEED * MAX_SPEED

_MOVABLE = {p.JOINT_REVOLUTE: "revolute", p.JOINT_PRISMATIC: "prismatic"}
#: PyBullet's state queries (getBasePositionAndOrientation, getJointStates) fail beyond this many links
_MAX_LINKS = 127
#: force limit of the gear constraints that make mimic joints follow their leader (N or N·m)
_GEAR_FORCE = 1e5
#: smallest accepted physics timestep (s)
MIN_TIMESTEP = 1e-6
#: a gravity component (m/s²): finite, within ±1000 (about 100 g)
GravityComponent = Annotated[float, Field(ge=-1000.0, le=1000.0)]


class PybulletOptions(BaseModel):
    """robot.yaml ``backends.pybullet`` / ``connect("pybullet", ...)`` options."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    #: physics timestep (s); the control period must be a whole multiple of it (at most MAX_SUBSTEPS)
    timestep: float = Field(default=0.001, ge=MIN_TIMESTEP, le=0.1)
    #: gravity vector (m/s²), each component within ±1000
    gravity: tuple[GravityComponent, GravityComponent, GravityComponent] = (0.0, 0.0, -9.81)
    #: joint damping added to every actuated joint (N·m·s/rad), on top of the URDF ``<dynamics damping>``
    joint_damping: float = Field(default=0.0, ge=0.0, le=MAX_GAIN)
    #: constraint solver iterations (joint limits, contacts)
    solver_iterations: int = Field(default=50, ge=1, le=10_000)
    #: keep a free-floating base instead of fixing the root link to the world
    floating_base: bool = False
    #: override robot.yaml ``self_collision`` (auto | true | false) for this backend
    self_collision: Literal["auto"] | bool | None = None
    #: open the PyBullet GUI (needs a display; one GUI per process)
    gui: bool = False


class PybulletController(Backend):
    """PyBullet simulation of the description (DIRECT mode, headless), servo law applied as joint torques."""

    name = "pybullet"
    capabilities = Capabilities(
        modes=frozenset(MODES), lockstep=True, realtime=True, deterministic=True
    )
    options_model = PybulletOptions
    #: the self-collision model in use (None for an MJCF model)
    collision: SelfCollision | None = None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        opts: PybulletOptions = self.options
        self._nsub = substeps(self.period, opts.timestep, "PyBullet", self.config.label)
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
        self._tmp = np.zeros(n)
        self._kdm = np.zeros(n)
        self._mask = np.zeros(n, dtype=bool)
        self._all_on = np.ones(n, dtype=bool).tobytes()
        self._q = np.zeros(n)
        self._v = np.zeros(n)
        # what _read returns (the substep scratch arrays above change inside _step)
        self._rq = np.zeros(n)
        self._rv = np.zeros(n)

    # ------------------------------------------------------------ open/close
    async def _open(self) -> None:
        if self.options.gui:
            self._build()  # the GUI client starts its own window thread: opened from the loop's thread
        else:
            # loading the robot takes up to seconds: off the event loop
            await run_blocking(self._build, name="agentsdk-pybullet-build")

    def _build(self) -> None:
        opts: PybulletOptions = self.options
        try:
            self._cid = p.connect(p.GUI if opts.gui else p.DIRECT)
        except p.error as exc:  # e.g. a second GUI in the same process
            raise BackendStartError(
                f"PyBullet could not open a physics client for robot {self.description.name!r}: {exc}"
            ) from exc
        if self._cid < 0:
            raise BackendStartError(f"PyBullet could not open a physics client for robot {self.description.name!r}")
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
        desc = self.description
        label = f"robot {desc.name!r} ({desc.source})"
        try:
            self._load_urdf(label)
            self._setup_dofs(label)
        except AgentSDKError:
            raise
        except Exception as exc:  # p.error and anything PyBullet's bindings raise
            raise BackendStartError(f"PyBullet could not load {label}: {' '.join(str(exc).split())}") from exc

    def _load_urdf(self, label: str) -> None:
        """Load the URDF written from the description: tree order, repaired inertials, one collision model.

        An MJCF model goes the same way, from the records MuJoCo compiled
        (:mod:`agentsdk.description.mjcf`), when a URDF can carry it.
        """
        opts: PybulletOptions = self.options
        cid = self._cid
        desc = self.description
        if desc.format == "mjcf":
            unsupported = mjcf_unsupported_by_pybullet(desc)
            if unsupported:
                raise BackendStartError(
                    f"PyBullet cannot load {label}: the MJCF model uses {'; '.join(unsupported)}, which a URDF "
                    "cannot carry (PyBullet's own loadMJCF reads even less: no <include>, default classes or "
                    "meshdir). Use the mujoco backend for this model"
                )
            collision = from_mjcf(desc)
        else:
            collision = for_robot(desc, self.config, opts.self_collision)
        self.collision = collision
        skip: frozenset[str] = frozenset()
        base_pose: tuple[list[float], list[float]] | None = None
        if opts.floating_base:
            skip, base_pose = _world_link(desc)
        # PyBullet's state queries fail beyond MAX_LINKS links: leave out links that carry nothing
        extra = len(desc.links) - 1 - len(skip) - _MAX_LINKS
        collapse = collapsible_links(desc, collision.shapes, extra) if extra > 0 else frozenset()
        if extra > len(collapse):
            raise BackendStartError(
                f"PyBullet cannot load {label}: it has {len(desc.links) - 1 - len(skip)} links besides the base, "
                f"PyBullet handles at most {_MAX_LINKS}, and only {len(collapse)} of them carry nothing "
                "(no mass, no collision shape) and can be left out"
            )
        urdf_xml = simulator_urdf(desc, collision.shapes, visuals=opts.gui, skip_links=skip, collapse=collapse)
        # links are written parent before child, so PyBullet keeps the file's order without crashing
        flags = p.URDF_USE_INERTIA_FROM_FILE | p.URDF_MAINTAIN_LINK_ORDER
        if collision.mode != "false":
            flags |= p.URDF_USE_SELF_COLLISION  # every pair; the excluded ones are filtered below
        fd, tmp = tempfile.mkstemp(suffix=".urdf", prefix=f"agentsdk-{_safe(desc.name)}-")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(urdf_xml)
            kw: dict[str, Any] = {}
            if base_pose is not None:
                kw = {"basePosition": base_pose[0], "baseOrientation": base_pose[1]}
            self._body = p.loadURDF(tmp, useFixedBase=not opts.floating_base, flags=flags, physicsClientId=cid, **kw)
        finally:
            Path(tmp).unlink(missing_ok=True)
        body = self._body
        self._links = {p.getBodyInfo(body, physicsClientId=cid)[0].decode("utf-8"): -1}
        for i in range(p.getNumJoints(body, physicsClientId=cid)):
            self._links[p.getJointInfo(body, i, physicsClientId=cid)[12].decode("utf-8")] = i
        self._filtered: set[tuple[str, str]] = set()
        if collision.mode != "false":
            for a, b in sorted(collision.excluded):
                if a in self._links and b in self._links:
                    p.setCollisionFilterPair(body, body, self._links[a], self._links[b], 0, physicsClientId=cid)
                    self._filtered.add((a, b))
        # mimic joints: a gear constraint q_follower - multiplier * q_leader = offset
        joint_link = {j.name: self._links.get(j.child) for j in desc.all_joints}
        for m in desc.mimics:
            follower, leader = joint_link.get(m.joint), joint_link.get(m.leader)
            if follower is None or leader is None or follower < 0 or leader < 0:
                raise BackendStartError(f"mimic joint {m.joint!r} of {label} has no PyBullet joint")
            c = p.createConstraint(
                body, follower, body, leader, p.JOINT_GEAR, [0, 0, 1], [0, 0, 0], [0, 0, 0], physicsClientId=cid
            )
            p.changeConstraint(
                c, gearRatio=-m.multiplier, relativePositionTarget=m.offset, erp=0.5, maxForce=_GEAR_FORCE,
                physicsClientId=cid,
            )
        self._mimic_pairs = [(m.joint, m.leader, m.multiplier, m.offset) for m in desc.mimics]

    def _setup_dofs(self, label: str) -> None:
        opts: PybulletOptions = self.options
        cid, body = self._cid, self._body
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
                    f"joint {name!r} of {label} has a type PyBullet loads as "
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
                raise BackendStartError(f"joint {j.name!r} is missing from the PyBullet model of {label}")
            sel.append(row[int(info[0])])
        self._sel = np.array(sel, dtype=np.intp)
        self._dof_row = {info[1].decode("utf-8"): k for k, info in enumerate(dofs)}
        followers = {m[0] for m in self._mimic_pairs}
        passive = [
            info[1].decode("utf-8")
            for k, info in enumerate(dofs)
            if k not in set(sel) and info[1].decode("utf-8") not in followers
        ]
        if passive:
            log.warning("%s: movable joints %s are not commanded; they stay passive", label, ", ".join(passive))

        # passive dynamics: our own damping (URDF + option), Coulomb friction through the motors
        self._damping = np.array([float(info[6]) for info in dofs]) + opts.joint_damping
        friction = [float(info[7]) for info in dofs]
        for link in range(-1, len(infos)):
            p.changeDynamics(body, link, linearDamping=0.0, angularDamping=0.0, physicsClientId=cid)
        for j in self._dofs:
            p.changeDynamics(body, j, jointDamping=0.0, maxJointVelocity=SPEED_CAP, physicsClientId=cid)
        # turn the default velocity motors off (they hold the joints otherwise); keep URDF friction
        if nd:
            p.setJointMotorControlArray(
                body, self._dofs, p.VELOCITY_CONTROL, targetVelocities=[0.0] * nd, forces=friction,
                physicsClientId=cid,
            )
        self._implicit = not opts.floating_base
        self._base_pose = p.getBasePositionAndOrientation(body, physicsClientId=cid)

        # preallocated work arrays
        self._q_all = np.zeros(nd)
        self._v_all = np.zeros(nd)
        self._ql: list[float] = [0.0] * nd
        self._vl: list[float] = [0.0] * nd
        self._f_all = np.zeros(nd)
        self._d_all = np.zeros(nd)
        self._hd = np.zeros(nd)
        self._rhs = np.zeros(nd)
        self._zeros = [0.0] * nd
        self._neg_damping = -self._damping
        #: every dof is a commanded joint, in command order (no gather/scatter per substep)
        self._sel_all = bool(np.array_equal(self._sel, np.arange(nd)))

    def simulator_report(self) -> dict[str, Any]:
        """What the loaded PyBullet body holds: commanded joints, link masses, colliding link pairs.

        Same layout as the MuJoCo backend's: ``joints`` ``[name, lower, upper,
        effort]`` in command order (PyBullet's ``lower > upper`` means
        unlimited, reported as ``±inf``; an effort of 1e30 or more as ``inf``);
        ``masses`` from ``getDynamicsInfo`` (the root link, fixed to the world,
        is left out: PyBullet reports 0 for a fixed base); ``pairs`` the link
        pairs with collision shapes that self-collision does not filter out.
        """
        cid, body = self._cid, self._body
        joints = []
        index = {p.getJointInfo(body, i, physicsClientId=cid)[1].decode("utf-8"): i for i in self._links.values()
                 if i >= 0}
        for j in self.joints:
            info = p.getJointInfo(body, index[j.name], physicsClientId=cid)
            lo, hi = float(info[8]), float(info[9])
            if lo > hi:
                lo, hi = -math.inf, math.inf
            effort = float(info[10])
            joints.append([j.name, lo, hi, math.inf if effort >= 1e29 else effort])
        masses = {
            name: float(p.getDynamicsInfo(body, i, physicsClientId=cid)[0]) for name, i in self._links.items() if i >= 0
        }
        geometric = sorted(
            name for name, i in self._links.items() if p.getCollisionShapeData(body, i, physicsClientId=cid)
        )
        pairs: list[tuple[str, str]] = []
        if self.collision is not None and self.collision.mode != "false":
            for k, a in enumerate(geometric):
                for b in geometric[k + 1 :]:
                    pair = (a, b) if a <= b else (b, a)
                    if pair not in self._filtered:
                        pairs.append(pair)
        return {"joints": joints, "masses": masses, "pairs": sorted(pairs)}

    def _reset_state(self) -> None:
        cid, body = self._cid, self._body
        q0 = np.zeros(len(self._dofs))
        q0[self._sel] = self.initial_positions
        for follower, leader, multiplier, offset in self._mimic_pairs:
            q0[self._dof_row[follower]] = multiplier * q0[self._dof_row[leader]] + offset
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
        # Allocation-free per substep: preallocated arrays, ufuncs with out= (ufunc dispatch is
        # the cost on arrays this small), joint states gathered from PyBullet's tuples once.
        cid, body, dofs = self._cid, self._body, self._dofs
        h = self.options.timestep
        q_all, v_all, f_all, d_all = self._q_all, self._v_all, self._f_all, self._d_all
        tau, raw, tmp, kdm, mask = self._tau, self._raw, self._tmp, self._kdm, self._mask
        qd, vd, ff, kp, kd = self._qd, self._vd, self._ff, self._kp, self._kd
        lim, neg_lim, neg_damping, damping = self.max_effort, self._neg_lim, self._neg_damping, self._damping
        sel, every = self._sel, self._sel_all
        q, v = (q_all, v_all) if every else (self._q, self._v)
        set_motors, step = p.setJointMotorControlArray, p.stepSimulation
        for _ in range(self._nsub):
            if not every:
                q_all.take(sel, out=q)
                v_all.take(sel, out=v)
            # the servo law, clamped; zero torque for disabled joints / torque off
            np.subtract(qd, q, out=raw)
            np.multiply(raw, kp, out=raw)
            np.subtract(vd, v, out=tmp)
            np.multiply(kd, tmp, out=tmp)
            np.add(raw, tmp, out=raw)
            np.add(raw, ff, out=raw)
            np.maximum(raw, neg_lim, out=tau)  # ufuncs: np.clip dispatch costs µs here
            np.minimum(tau, lim, out=tau)
            en = self._en  # cleared by _emergency_stop from any thread: takes effect at the next substep
            all_on = en.tobytes() == self._all_on
            if not all_on:
                tau[~en] = 0.0
            # generalized force on every dof: servo torque minus passive damping
            np.multiply(neg_damping, v_all, out=f_all)
            if every:
                np.add(f_all, tau, out=f_all)
            else:
                f_all[sel] += tau
            if self._implicit:
                # velocity derivative of the forces: damping, plus kd of the unsaturated enabled servos
                np.abs(raw, out=tmp)
                np.less(tmp, lim, out=mask)
                if not all_on:
                    mask &= en
                kdm.fill(0.0)
                np.copyto(kdm, kd, where=mask)
                if every:
                    np.add(damping, kdm, out=d_all)
                else:
                    np.copyto(d_all, damping)
                    d_all[sel] += kdm
                if np.count_nonzero(d_all):
                    ql, vl = self._ql, self._vl
                    mass = np.array(p.calculateMassMatrix(body, ql, physicsClientId=cid))
                    bias = p.calculateInverseDynamics(body, ql, vl, self._zeros, physicsClientId=cid)
                    hd = self._hd
                    np.multiply(d_all, h, out=hd)
                    diag = mass.reshape(-1)[:: len(dofs) + 1]  # a view of the diagonal
                    np.add(diag, hd, out=diag)
                    rhs = self._rhs
                    np.subtract(f_all, bias, out=rhs)
                    qacc = np.linalg.solve(mass, rhs)
                    np.multiply(hd, qacc, out=rhs)
                    np.subtract(f_all, rhs, out=f_all)
            set_motors(body, dofs, p.TORQUE_CONTROL, forces=f_all.tolist(), physicsClientId=cid)
            step(physicsClientId=cid)
            self._time += h
            self._sense()

    def _sense(self) -> None:
        if not self._dofs:
            return
        states = p.getJointStates(self._body, self._dofs, physicsClientId=self._cid)
        ql = self._ql = [s[0] for s in states]
        vl = self._vl = [s[1] for s in states]
        q, v = self._q_all, self._v_all
        q[:] = ql
        v[:] = vl
        # fast path: |v|^2 <= MAX_SPEED^2 bounds every |v_i|, and q.q is finite iff every q_i is
        # (NaN fails both comparisons); only a state that fails it gets the per-joint check
        if v.dot(v) <= _MAX_SPEED_SQ and math.isfinite(q.dot(q)):
            return
        if not (np.abs(v).max(initial=0.0) <= MAX_SPEED and np.isfinite(q).all()):
            bad = int(np.argmax(~np.isfinite(q) | ~np.isfinite(v) | (np.abs(v) > MAX_SPEED)))
            name = p.getJointInfo(self._body, self._dofs[bad], physicsClientId=self._cid)[1].decode()
            raise SimulationDiverged(
                f"PyBullet simulation of {self.description.name!r} diverged at t={self._time:.4f} s "
                f"(joint {name!r}: q={q[bad]:.4g}, v={v[bad]:.4g}); lower the gains or the timestep"
            )

    def _read(self) -> JointReading:
        if self._sel_all:  # the arrays change inside _step only, and the loop copies them at once
            return self._q_all, self._v_all, self._tau
        self._q_all.take(self._sel, out=self._rq)
        self._v_all.take(self._sel, out=self._rv)
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


def _world_link(desc: RobotDescription) -> tuple[frozenset[str], tuple[list[float], list[float]] | None]:
    """For a floating base: a massless root link fixed to the next one (the ROS ``world`` link) is left out.

    PyBullet treats a massless base as static, so ``world -(fixed)-> base_link``
    would stay bolted down; the child becomes the floating root, placed at the
    fixed joint's origin.
    """
    root = desc.link(desc.root_link)
    out = desc.child_joints(desc.root_link)
    if root.mass > 0 or len(out) != 1 or out[0].type != "fixed":
        return frozenset(), None
    return frozenset({desc.root_link}), (list(out[0].xyz), list(_quat_from_rpy(list(out[0].rpy))))


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)[:40]


def _quat_from_rpy(rpy: list[float]) -> tuple[float, float, float, float]:
    r, pi, y = (0.5 * a for a in rpy)
    cr, sr, cp, sp_, cy, sy = math.cos(r), math.sin(r), math.cos(pi), math.sin(pi), math.cos(y), math.sin(y)
    return (
        sr * cp * cy - cr * sp_ * sy,
        cr * sp_ * cy + sr * cp * sy,
        cr * cp * sy - sr * sp_ * cy,
        cr * cp * cy + sr * sp_ * sy,
    )
