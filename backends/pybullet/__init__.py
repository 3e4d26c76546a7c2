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
diverges once ``kd*dt/I > 2``) and matches the MuJoCo backend closely. ``M``
includes the rotor inertia ``A`` (MJCF ``armature``) PyBullet does not simulate:
the torque ``A qacc`` that accelerates the rotors is held back. A floating base
solves the whole model, its free base included, and adds the constraint forces
(ground contacts) PyBullet applied over the last substeps (:mod:`.floating`).

Gravity compensation (``tau_model`` of the servo law, :mod:`agentsdk.dynamics`): once per
control period ``g(q)`` at the measured position is added to the feed-forward of the law above
(so the clamp covers it). It comes from the description's rigid-body model
(:class:`agentsdk.dynamics.DynamicsModel`: the same links and inertials PyBullet loaded, a floating
base at PyBullet's measured attitude), not from PyBullet's ``calculateInverseDynamics``, which
mishandles URDF fixed joints (bullet3 #1379: on example-robot-data's double pendulum it gives
0.074 N·m where 0.266 N·m hold the link) and floating bases (bullet3 #3149, #3264).

Floating base (robot.yaml ``floating_base: true``, or an MJCF ``<freejoint>`` on the root body, which
is written as the URDF's root): a ground plane is added; PyBullet multiplies
the two friction coefficients of a contact, so the plane gets robot.yaml ``ground_friction`` and
the robot's links 1.0 (the same contact friction as on MuJoCo); the robot starts standing on it
(:func:`agentsdk.description.collision.standing_height`).

``effort`` in the measured state is the servo torque (like MuJoCo's
``actuator_force``): the clamped law above, without passive damping.

Divergence: after every physics substep the joint state is checked; a
non-finite value or a speed above 1e4 rad/s (m/s) raises
:class:`SimulationDiverged`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .quiet import filtered_native_output

with filtered_native_output():  # "pybullet build time: ..." goes to the log, not the user's terminal
    import pybullet as p

from agentsdk.backend import Backend, Capabilities, JointReading, SetpointView, substeps
from agentsdk.config import MAX_GAIN
from agentsdk.description import RobotDescription
from agentsdk.description.collision import SelfCollision, for_robot, from_mjcf, standing_height
from agentsdk.description.mjcf import empty_world_links, free_root
from agentsdk.description.mjcf_pybullet import mjcf_pybullet_fit
from agentsdk.description.model import quat_from_rpy
from agentsdk.description.simurdf import collapsible_links, simulator_urdf
from agentsdk.dynamics import DynamicsModel
from agentsdk.errors import (
    AgentSDKError,
    BackendFault,
    BackendStartError,
    ConfigurationError,
    SimulationDiverged,
    UnsupportedModelError,
)
from agentsdk.feedforward import InverseDynamicsTerm
from agentsdk.pose import BaseState, Pose
from agentsdk.sensors import SensorChannel
from agentsdk.threads import run_blocking
from agentsdk.types import MODES

from .floating import FloatingStep
from .friction import friction_torque
from .sensors import SERVED, PybulletSensors

if TYPE_CHECKING:
    from .block import BlockStepper

__all__ = ["MAX_SPEED", "SPEED_CAP", "PybulletBackend", "PybulletController", "PybulletOptions"]

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

#: ``count_nonzero(x) > 0`` as one ufunc reduction (NaN counts, as there); the numpy function has a Python wrapper
_any_nonzero = np.logical_or.reduce


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
    #: a free-floating base on a ground plane instead of a root link fixed to the world
    #: (default: robot.yaml ``floating_base``)
    floating_base: bool | None = None
    #: override robot.yaml ``self_collision`` (auto | true | false) for this backend
    self_collision: Literal["auto"] | bool | None = None
    #: override robot.yaml ``inverse_dynamics`` (the desired motion's inverse dynamics in the servo law)
    inverse_dynamics: bool | None = None
    #: open the PyBullet GUI (needs a display; one GUI per process)
    gui: bool = False


class PybulletBackend(Backend):
    """PyBullet simulation of the description (DIRECT mode, headless), servo law applied as joint torques."""

    name = "pybullet"
    step_never_suspends = True  # its _step computes the step and returns
    capabilities = Capabilities(
        modes=frozenset(MODES), lockstep=True, realtime=True, deterministic=True
    )
    options_model = PybulletOptions
    sensor_kinds = SERVED
    #: the self-collision model in use (None for an MJCF model)
    collision: SelfCollision | None = None
    #: :attr:`floating_base`, kept by the first write (the servo path asks every tick)
    _floating: bool | None = None

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
        # tau_model (gravity compensation) of this control period, masked per joint
        self._tau_model = np.zeros(n)
        self._gc_mask = self.gravity_compensation.astype(float)

    @property
    def servo_timestep(self) -> float:
        """PyBullet's physics timestep: the servo law is evaluated (and integrated) at every step."""
        return float(self.options.timestep)

    @property
    def floating_base(self) -> bool:
        """True when the base floats on a ground plane.

        Option ``floating_base``, else robot.yaml, else whether the model's root body has a free joint
        (an MJCF ``<freejoint>``; ``floating_base: false`` welds it to the world).
        """
        opt = self.options.floating_base
        if opt is not None:
            return bool(opt)
        return bool(self.config.floating_base) or free_root(self.description) is not None

    # ------------------------------------------------------------ open/close
    async def _open(self) -> None:
        if self.options.gui:
            self._build()  # the GUI client starts its own window thread: opened from the loop's thread
        else:
            # loading the robot takes up to seconds: off the event loop
            await run_blocking(self._build, name="agentsdk-pybullet-build")

    def _build(self) -> None:
        # PyBullet's b3Warning/b3Printf lines go to the log, not into the user's output
        with filtered_native_output():
            self._build_client()

    def _build_client(self) -> None:
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
        self._sensors = PybulletSensors(self.sensors, f"robot {self.description.name!r}")
        desc = self.description
        world = (desc.root_link,) if self.floating_base and _float_link(desc) != desc.root_link else ()
        self._sensors.bind(cid, self._body, self._links, opts.gravity,
                           getattr(self, "_base_inertial", None), world)
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
            dropped, unsupported = mjcf_pybullet_fit(desc)
            if unsupported:
                raise UnsupportedModelError(
                    f"PyBullet cannot load {label}: the MJCF model uses {'; '.join(unsupported)}, which a URDF "
                    "cannot carry (PyBullet's own loadMJCF reads even less: no <include>, default classes or "
                    "meshdir). Use the mujoco backend for this model"
                )
            for what in dropped:
                log.warning("%s: PyBullet leaves out the %s", label, what)
            # the one collision rule: bodies touching at the start pose do not collide (as on MuJoCo), unless
            # self_collision says to keep every pair
            mode = self.config.self_collision if opts.self_collision is None else opts.self_collision
            collision = from_mjcf(desc, self.config if mode == "auto" else None)
        else:
            collision = for_robot(desc, self.config, opts.self_collision)
        self.collision = collision
        skip: frozenset[str] = frozenset()
        base_pose: tuple[list[float], list[float]] | None = None
        if self.floating_base:
            # the base link floats (a massless root fixed to it is left out: PyBullet would hold a massless
            # base static); it starts where the root frame stands on the ground plane
            if _float_link(desc) != desc.root_link:
                skip = frozenset({desc.root_link})
                if desc.format == "mjcf":  # with the bodies fixed to the world that hold nothing
                    skip |= empty_world_links(desc)
            if desc.format == "urdf":
                height = standing_height(desc, collision)
            else:  # the MJCF body at its free joint's place, its lowest shape on the ground at the start pose
                start = dict(zip((j.name for j in self.joints), self.initial_positions.tolist(), strict=True))
                shapes = {k: v for k, v in collision.shapes.items() if k not in skip}
                height = standing_height(desc, replace(collision, shapes=shapes, start=start))
            pose = Pose((0.0, 0.0, height)) @ _base_offset(desc)
            base_pose = (pose.position.tolist(), pose.orientation.tolist())
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
            self._body = p.loadURDF(tmp, useFixedBase=not self.floating_base, flags=flags, physicsClientId=cid, **kw)
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

        # passive dynamics: our own damping (URDF + option); Coulomb friction in the implicit step
        # (a fixed base), else through the motors
        self._damping = np.array([float(info[6]) for info in dofs]) + opts.joint_damping
        friction = [float(info[7]) for info in dofs]
        self._implicit = True  # a floating base falls back to the explicit law if its step cannot be built
        self._friction = np.array(friction)
        self._friction_any = any(friction) and self._implicit
        for link in range(-1, len(infos)):
            p.changeDynamics(body, link, linearDamping=0.0, angularDamping=0.0, physicsClientId=cid)
        for dof in self._dofs:
            # two calls: given together with maxJointVelocity, PyBullet 3.2.7 ignores jointDamping (the URDF
            # damping then acts twice, explicitly in PyBullet and implicitly here: light damped links diverge)
            p.changeDynamics(body, dof, jointDamping=0.0, physicsClientId=cid)
            p.changeDynamics(body, dof, maxJointVelocity=SPEED_CAP, physicsClientId=cid)
        # turn the default velocity motors off (they hold the joints otherwise); keep URDF friction
        if nd:
            p.setJointMotorControlArray(
                body, self._dofs, p.VELOCITY_CONTROL, targetVelocities=[0.0] * nd,
                forces=[0.0] * nd if self._implicit else friction, physicsClientId=cid,
            )
        self._base_pose = p.getBasePositionAndOrientation(body, physicsClientId=cid)
        self._setup_dynamics()
        if self.floating_base:
            mu = self.config.ground_friction
            plane = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid)
            self._ground = p.createMultiBody(0.0, plane, physicsClientId=cid)
            p.changeDynamics(self._ground, -1, lateralFriction=mu, physicsClientId=cid)
            for link in range(-1, len(infos)):  # combined friction = product: mu * 1
                p.changeDynamics(body, link, lateralFriction=1.0, physicsClientId=cid)
            info = p.getDynamicsInfo(body, -1, physicsClientId=cid)
            # the base's inertial frame in its link frame (PyBullet reports the base by its inertial frame)
            self._base_inertial = Pose(info[3], info[4])
            self._setup_floating_step(label, friction)

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
        self._diag = np.diag_indices(nd)
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
        if self.floating_base:
            p.resetBasePositionAndOrientation(body, *self._base_pose, physicsClientId=cid)
            p.resetBaseVelocity(body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], physicsClientId=cid)
        self._tau[:] = 0.0
        self._time = 0.0
        if self._floating_step is not None:
            self._floating_step.reset()
        if hasattr(self, "_sensors"):
            self._sensors.reset()
        self._sense()

    async def _close(self) -> None:
        cid, self._cid = self._cid, -1
        if cid >= 0:
            # the GUI prints its threads' shutdown
            with filtered_native_output() if self.options.gui else contextlib.nullcontext():
                try:
                    p.disconnect(physicsClientId=cid)
                except p.error:  # already gone
                    pass

    # ------------------------------------------------------------ gravity compensation
    def _setup_dynamics(self) -> None:
        """The description's rigid-body model (see the module docstring) and the buffers of the implicit step."""
        # on the robot's one host model (compiled with this backend's gravity and floating base, see
        # BackendSpec.host), with scratch data of its own
        self._model = DynamicsModel(self.description, self.joints, host=self.spec.host.get())
        self._gc_on = bool(self._gc_mask.any()) and any(self.options.gravity)
        self._gc_q = np.zeros(len(self.joints))
        # + M(q) a_des + C(q, v_des) v_des (robot.yaml inverse_dynamics), from the same host model
        self._inverse = (InverseDynamicsTerm(self._model.model, self.names, extra_damping=self.options.joint_damping)
                         if self.inverse_dynamics else None)
        self._tau_motion = np.zeros(len(self.joints))
        model = self._model.model
        nd, nv = len(self._dofs), model.nv
        # PyBullet dof k is the model's dof _perm[k], its position the model's qpos[_qadr[k]]
        names = list(self._dof_row)
        self._perm = self._model.dofs(names)
        self._qadr = np.array([model.jnt_qposadr[model.joint(n).id] for n in names], dtype=np.intp)
        self._floating_step: FloatingStep | None = None
        self._mq = model.qpos0.copy()
        self._mv = np.zeros(nv)
        self._m_full = np.zeros((nv, nv))
        self._m_rows = np.zeros((nd, nv))
        self._m_bias = np.zeros(nv)
        self._mass = np.zeros((nd, nd))
        self._bias = np.zeros(nd)
        self._a = np.zeros((nd, nd))
        # rotor inertia (MJCF ``armature``) per PyBullet dof: PyBullet has no such term, the implicit step adds it
        arm = self._model.model.dof_armature
        self._armature = np.asarray(arm[self._perm], dtype=float)
        self._armature_any = bool(self._armature.any())
        # PyBullet's dofs in the model's own order (a fixed base of hinges and slides, as a rule): the
        # terms need no gathering, and the positions go in as one slice (the same values, fewer calls)
        self._same_order = nd == nv and bool(np.array_equal(self._perm, np.arange(nv)))
        qadr = self._qadr
        self._q_span = (slice(int(qadr[0]), int(qadr[0]) + nd)
                        if nd and np.array_equal(qadr, np.arange(qadr[0], qadr[0] + nd)) else None)
        #: the diagonal of the implicit step's matrix, as a view (a[i, i] += h d_i, no index arrays)
        self._a_diag = self._a.reshape(-1)[:: nd + 1]
        self._hd_sub = np.zeros(nd)
        self._rhs_sub = np.zeros(nd)
        self._rigid_mass = np.zeros((nd, nd))

    def _setup_floating_step(self, label: str, friction: list[float]) -> None:
        """The floating base's implicit step (:mod:`.floating`), else the explicit law with motor friction."""
        try:
            self._floating_step = FloatingStep(
                self._model, self._perm, self._qadr, base_link=_float_link(self.description),
                base_in_inertial=self._base_inertial.inverse(), timestep=self.options.timestep,
                friction=self._friction,
            )
            self._floating_step.bind(self._cid, self._body, self._dofs)
        except ValueError as exc:
            log.warning("%s: %s; the floating base runs the explicit servo law (no armature, no implicit damping)",
                        label, exc)
            self._implicit = False
            self._friction_any = False
            if self._dofs:
                p.setJointMotorControlArray(
                    self._body, self._dofs, p.VELOCITY_CONTROL, targetVelocities=[0.0] * len(self._dofs),
                    forces=friction, physicsClientId=self._cid,
                )

    def _gravity_torque(self, q: np.ndarray, base: Pose | None) -> np.ndarray:
        """g(q) at the latest sensed state ``q`` (base pose ``base``) into ``_tau_model`` (masked per joint)."""
        tau = self._model.gravity(q, self._tau_model, base)
        tau *= self._gc_mask
        return tau

    def _motion_torque(self, sp: SetpointView, base: Pose | None) -> np.ndarray:
        """``M(q_des) a_des + C(q_des, v_des) v_des`` at the desired position into ``_tau_motion``.

        As on every backend: a function of the setpoint stream alone (the joint-space terms do not
        depend on a floating base's pose, which is the measured one here).
        """
        assert self._inverse is not None
        # (called only when the write found the reference moving: not asked again)
        return self._inverse.compute(self._model.qpos(sp.position, base), sp.velocity, sp.acceleration,
                                     self._tau_motion, sp.mode, moving=True)

    def _implicit_terms(self) -> tuple[np.ndarray, np.ndarray]:
        """``M(q)`` and ``c(q, v) + g(q)`` in PyBullet's dof order, from the description's model.

        PyBullet's own ``calculateInverseDynamics`` is wrong with fixed joints (module docstring).
        """
        perm, span = self._perm, self._q_span
        if span is not None:
            self._mq[span] = self._q_all
        else:
            self._mq[self._qadr] = self._q_all
        if self._same_order:  # (the gathers below would be copies)
            self._mv[...] = self._v_all
            self._model.terms(self._mq, self._mv, self._m_full, self._m_bias)
            return self._m_full, self._m_bias
        self._mv[perm] = self._v_all
        self._model.terms(self._mq, self._mv, self._m_full, self._m_bias)
        # (ndarray.take: np.take's Python wrapper costs more than the gather of a few rows)
        self._m_full.take(perm, axis=0, out=self._m_rows)
        self._m_rows.take(perm, axis=1, out=self._mass)
        self._m_bias.take(perm, out=self._bias)
        return self._mass, self._bias

    def _implicit_step(self, f_all: np.ndarray, d_all: np.ndarray, h: float) -> np.ndarray:
        """The generalized force whose explicit PyBullet step lands where an implicit-damping step would.

        ``(M + h D) qacc = f - c(q, v) - g(q) + F`` with ``F`` the joints' Coulomb friction (the joints
        that can stop this step stop, the others slide: :func:`.friction.friction_torque`), then
        ``f = c + g + (M - A) qacc`` (PyBullet's motors carry no friction here). ``M`` includes the
        rotor inertia ``A`` (MJCF ``armature``, diagonal) that PyBullet does not simulate: the torque
        ``A qacc`` that accelerates the rotors is held back, so PyBullet's rigid bodies take ``qacc``.
        """
        mass, bias = self._implicit_terms()
        a = self._a
        a[...] = mass
        self._a_diag += np.multiply(d_all, h, out=self._hd_sub)
        rhs = np.subtract(f_all, bias, out=self._rhs_sub)
        qacc = np.linalg.solve(a, rhs)
        if self._friction_any:  # the joints that can stop this step stop, the others slide (coupled)
            rhs += friction_torque(a, rhs, self._v_all, h, self._friction)
            qacc = np.linalg.solve(a, rhs)
        if self._armature_any:
            rigid = self._rigid_mass
            rigid[...] = mass
            rigid[self._diag] -= self._armature
            mass = rigid
        np.matmul(mass, qacc, out=f_all)
        f_all += bias
        return f_all

    # ------------------------------------------------------------ floating base
    def base_state(self) -> BaseState:
        """The floating base link's pose and velocity (world frame) as PyBullet measures them."""
        if not self.floating_base:
            return BaseState(Pose())
        cid, body = self._cid, self._body
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
        lin, ang = p.getBaseVelocity(body, physicsClientId=cid)
        inertial = Pose(pos, orn)
        link = inertial @ self._base_inertial.inverse()
        omega = np.array(ang)
        # PyBullet's linear velocity is the inertial frame's (centre of mass): move it to the link origin
        v = np.array(lin) + np.cross(omega, link.position - inertial.position)
        return BaseState(link, v, omega)

    def block_stepper(self, capacity: int) -> BlockStepper:
        """A :class:`~.block.BlockStepper` of this backend: up to ``capacity`` ticks per call (block lockstep)."""
        from .block import BlockStepper

        return BlockStepper(self, capacity)

    # ------------------------------------------------------------ servo
    def _write(self, sp: SetpointView) -> None:
        # (a[...] = b: np.copyto's Python-level wrapper costs more than the copy of a few joints)
        self._qd[...] = sp.position
        self._vd[...] = sp.velocity
        self._ff[...] = sp.effort
        gc = self._gc_on
        moving = self._inverse is not None and self._inverse.moving(sp.velocity, sp.acceleration)
        if gc or moving:
            # the measured state, gathered once for both terms (the base pose is two PyBullet calls)
            q = np.take(self._q_all, self._sel, out=self._gc_q)
            floating = self._floating
            if floating is None:
                floating = self._floating = self.floating_base
            base = self.base_state().pose if floating else None
            if gc:  # tau_model: g(q) at the measured position, added to the feed-forward
                self._ff += self._gravity_torque(q, base)
            if moving:
                self._ff += self._motion_torque(sp, base)
        self._kp[...] = sp.kp
        self._kd[...] = sp.kd
        self._en[...] = sp.enabled

    async def _step(self, dt: float) -> None:
        self.substeps()

    def substeps(self) -> None:
        """One control period's physics substeps, each with the servo law of the last write (synchronous).

        What :meth:`_step` runs (it never awaits); block lockstep (:mod:`.block`) and the benchmarks'
        raw loop call it directly. Raises :class:`SimulationDiverged` after the substep that diverged.
        """
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
                np.positive(kd, out=kdm, where=mask)  # copyto(kdm, kd, where=mask) as a plain ufunc
                if every:
                    np.add(damping, kdm, out=d_all)
                else:
                    d_all[...] = damping
                    d_all[sel] += kdm
                if self._floating_step is not None:
                    f_all = self._floating_step(cid, body, q_all, v_all, f_all, d_all)
                elif self._armature_any or self._friction_any or _any_nonzero(d_all):
                    f_all = self._implicit_step(f_all, d_all, h)
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

    def _read_sensors(self, channels: Sequence[SensorChannel]) -> None:
        self._sensors.read(channels, self._time)

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


def _float_link(desc: RobotDescription) -> str:
    """The link PyBullet floats: the body of a root free joint (MJCF), else ``desc.base_link``."""
    return free_root(desc) or desc.base_link


def _base_offset(desc: RobotDescription) -> Pose:
    """The floating link (:func:`_float_link`) in the root link's frame (identity when it is the root)."""
    link = _float_link(desc)
    if link == desc.root_link:
        return Pose()
    joint = desc.parent_joint(link)
    assert joint is not None
    w, x, y, z = quat_from_rpy(joint.rpy)
    return Pose(joint.xyz, (x, y, z, w))


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)[:40]

#: the former name of :class:`PybulletBackend` (deprecated: import PybulletBackend)
PybulletController = PybulletBackend
