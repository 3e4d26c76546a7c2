"""MuJoCo backend: the URDF compiled through ``mujoco.MjSpec`` with one joint servo per joint.

Each actuated joint gets a MuJoCo *general* actuator with ``gain = 1`` and an
affine bias ``[0, -kp, -kd]``; writing ``ctrl = kp*q_des + kd*v_des + effort_ff``
yields exactly the SDK's servo law ``kp*(q_des - q) + kd*(v_des - v) + effort_ff``,
evaluated by MuJoCo at every physics step (with the damping term integrated
implicitly by ``implicitfast``), clamped to the URDF effort limit.

Gravity compensation (``tau_model`` of the servo law, :mod:`agentsdk.dynamics`): computed by
MuJoCo inside the step (:mod:`backends.mujoco.gravcomp`: ``body_gravcomp`` routed through the
joints' actuator forces, ``g(q)`` of the state MuJoCo integrates at every physics step, clamped
with the servo torque to the effort limit), so a tick adds no host work for it. Where MuJoCo's
mechanism cannot express the law exactly (a floating base, a joint below a ball joint, gravity
compensation switched off for some joints only) ``g(q)`` is computed on the host instead, once
per control period at the measured position, from this backend's own compiled model (``mj_rne``
at rest on a private ``MjData``, a floating base's attitude included) and added to ``ctrl``, so
the actuator's force limit clamps the whole law. :attr:`MujocoBackend.gravity_route` says which.
The joint effort read back (``state.effort``) is the joint's actuator torque, gravity
compensation included, either way.

The inverse-dynamics feed-forward (robot.yaml ``inverse_dynamics``) is evaluated at the desired
state, ``M(q_des) a_des + C(q_des, v_des) v_des`` plus the joints' damping and friction (the
commanded joints at the setpoint's ``position``, mimic followers placed from it, every other
coordinate at the start pose), so it is a function of the setpoint stream alone.

Floating base (robot.yaml ``floating_base: true``): the root body gets a free joint, a ground
plane is added (friction robot.yaml ``ground_friction``, the robot's geoms given the same
coefficient, MuJoCo taking the larger of two), and the robot starts standing on it at its
start pose (:func:`agentsdk.description.collision.standing_height`).

MJCF models keep their own contact settings, with the one rule of the URDF path: bodies of
the robot touching at the start pose do not collide (:mod:`agentsdk.description.mjcf_scene`;
robot.yaml ``self_collision: true`` keeps them). A free joint at the root (``<freejoint>``)
is the floating base whatever robot.yaml says; a model without a floor (a plane or height
field attached to the world) gets the ground plane above (the model's own geom frictions
kept; it meets every contype/conaffinity bit, and a robot with no colliding geom at all gets
explicit pairs of its collision shapes with it: :func:`agentsdk.description.mjcf_scene.ground_geoms`),
and the robot is raised or lowered to stand on it. The simulation starts from the
keyframe the start pose comes from (:attr:`agentsdk.description.start.StartPose.keyframe`).

Divergence: MuJoCo silently resets a diverged state (``mjWARN_BADQACC``) and
zeroes every control when one is NaN, inf or huge (``mjWARN_BADCTRL``); this
backend checks the warning counters and finiteness after every control period
and raises :class:`SimulationDiverged` instead, like dm_control's
``check_invalid_state``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from math import inf
from typing import TYPE_CHECKING, Annotated, Any, Literal

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from agentsdk.backend import Backend, Capabilities, JointReading, SetpointView, substeps
from agentsdk.config import MAX_GAIN
from agentsdk.description.collision import SelfCollision, for_robot, standing_height
from agentsdk.description.mjcf import colliding_body_pairs
from agentsdk.description.mjcf_scene import ground_geoms, has_ground, standing_offset, start_qpos, touching_at_start
from agentsdk.description.mjspec import build_spec, mjcf_spec_without_actuators
from agentsdk.description.model import quat_from_rpy
from agentsdk.dynamics import GravityTerm, coupling_matrix
from agentsdk.errors import AgentSDKError, BackendStartError, SimulationDiverged
from agentsdk.feedforward import InverseDynamicsTerm
from agentsdk.pose import BaseState, Pose
from agentsdk.sensors import SensorChannel
from agentsdk.threads import run_blocking
from agentsdk.types import MODES

from .gravcomp import StepGravity, drop_model_gravcomp, step_gravity_obstacle
from .sensors import SERVED, MujocoSensors

if TYPE_CHECKING:
    from .block import BlockStepper

__all__ = ["MujocoBackend", "MujocoController", "MujocoOptions"]

#: smallest accepted physics timestep (s)
MIN_TIMESTEP = 1e-6
#: a gravity component (m/s²): finite, within ±1000 (about 100 g)
GravityComponent = Annotated[float, Field(ge=-1000.0, le=1000.0)]

_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    # NaN, inf or |ctrl| > mjMAXVAL: MuJoCo zeroes every control and carries on, i.e. the
    # robot silently goes limp; it is a fault like a divergence
    mujoco.mjtWarning.mjWARN_BADCTRL,
)
_BADCTRL = mujoco.mjtWarning.mjWARN_BADCTRL
#: the colour of the ground plane a floating base stands on (light grey: the robot stands out in a video)
GROUND_RGBA = (0.75, 0.77, 0.8, 1.0)


log = logging.getLogger("agentsdk.backends.mujoco")


def _log_mujoco_warning(message: str) -> None:
    log.warning("MuJoCo: %s", message.strip())


def _route_warnings() -> None:
    """Send MuJoCo's warnings to logging instead of stdout and ``MUJOCO_LOG.TXT`` in the working directory.

    The hook is process-wide: it is installed only when nobody else installed one.
    The warnings that matter to a run (divergence, bad controls) become faults anyway.
    """
    if mujoco.get_mju_user_warning() is None:
        mujoco.set_mju_user_warning(_log_mujoco_warning)


class MujocoOptions(BaseModel):
    """robot.yaml ``backends.mujoco`` / ``connect("mujoco", ...)`` options."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    #: physics timestep (s); the control period must be a whole multiple of it (at most MAX_SUBSTEPS)
    timestep: float = Field(default=0.001, ge=MIN_TIMESTEP, le=0.1)
    integrator: Literal["implicitfast", "implicit", "euler", "rk4"] = "implicitfast"
    #: gravity vector (m/s²), each component within ±1000
    gravity: tuple[GravityComponent, GravityComponent, GravityComponent] = (0.0, 0.0, -9.81)
    #: joint damping added to every actuated joint (N·m·s/rad), models gearbox friction
    joint_damping: float = Field(default=0.0, ge=0.0, le=MAX_GAIN)
    #: reflected rotor inertia added to every actuated joint (kg·m²)
    armature: float = Field(default=0.0, ge=0.0, le=MAX_GAIN)
    #: a free-floating base on a ground plane instead of a root link fixed to the world
    #: (default: robot.yaml ``floating_base``; an MJCF free joint at the root always floats)
    floating_base: bool | None = None
    #: override robot.yaml ``self_collision`` (auto | true | false) for this backend
    self_collision: Literal["auto"] | bool | None = None
    #: override robot.yaml ``inverse_dynamics`` (the desired motion's inverse dynamics in the servo law)
    inverse_dynamics: bool | None = None


class MujocoBackend(Backend):
    """MuJoCo simulation of the description, servo law applied as joint torques.

    The model is built from the URDF/MJCF records with ``build_spec``.
    """

    name = "mujoco"
    step_never_suspends = True  # its _step computes the step and returns
    capabilities = Capabilities(
        modes=frozenset(MODES), lockstep=True, realtime=True, deterministic=True
    )
    options_model = MujocoOptions
    sensor_kinds = SERVED

    model: mujoco.MjModel
    data: mujoco.MjData
    #: the self-collision model in use (None for an MJCF model, which keeps its own contact settings)
    collision: SelfCollision | None = None
    _free_body = ""  # the body given a free joint (floating base)
    _ground_height = 0.0  # the root frame's height when standing on the ground plane
    #: MJCF body pairs touching at the start pose, excluded from contact (empty for URDF models)
    mjcf_touching: frozenset[tuple[str, str]] = frozenset()

    @property
    def servo_timestep(self) -> float:
        """MuJoCo's physics timestep: the servo law is evaluated (and integrated) at every step."""
        return float(self.options.timestep)

    @property
    def floating_base(self) -> bool:
        """True when the base floats (an MJCF free joint at the root, else option ``floating_base``, robot.yaml)."""
        opt = self.options.floating_base
        return self.description.free_root is not None or bool(self.config.floating_base if opt is None else opt)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._nsub = substeps(self.period, self.options.timestep, "MuJoCo", self.config.label)

    async def _open(self) -> None:
        # building and compiling a model takes up to seconds: off the event loop
        await run_blocking(self._build, name="agentsdk-mujoco-build")

    def _build(self) -> None:
        opts: MujocoOptions = self.options
        _route_warnings()
        desc = self.description
        label = f"robot {desc.name!r} ({desc.source})"
        try:
            spec = self._mjcf_spec() if desc.format == "mjcf" else self._urdf_spec()
        except AgentSDKError:
            raise
        except Exception as exc:
            raise BackendStartError(f"MuJoCo could not build {label}: {_one_line(exc)}") from exc
        self._sensors = MujocoSensors(self.sensors, label)
        self._sensors.add_to(spec)
        spec.option.timestep = opts.timestep
        spec.option.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{opts.integrator.upper()}")
        spec.option.gravity = list(opts.gravity)
        for j in self.joints:
            sj = spec.joint(j.name)
            if sj is None:
                raise BackendStartError(f"joint {j.name!r} is missing from the MuJoCo model of {label}")
            damping = np.array(sj.damping, dtype=float)
            damping[0] += opts.joint_damping
            sj.damping = damping.tolist()
            sj.armature = sj.armature + opts.armature
            act = spec.add_actuator()
            act.name = f"{j.name}_servo"
            act.target = j.name
            act.trntype = mujoco.mjtTrn.mjTRN_JOINT
            act.gaintype = mujoco.mjtGain.mjGAIN_FIXED
            act.biastype = mujoco.mjtBias.mjBIAS_AFFINE
            act.gainprm[0] = 1.0
            if np.isfinite(j.max_effort):
                act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
                act.forcerange = [-j.max_effort, j.max_effort]
            else:
                act.forcelimited = mujoco.mjtLimited.mjLIMITED_FALSE
        self._step_gravity = self._plan_gravity(spec)
        if self._step_gravity is not None:
            self._step_gravity.configure(spec)
        # in lockstep, one effort sensor per joint, last in the model, reading what read() returns as the
        # effort (the servo's force, or the joint's actuation with MuJoCo's gravity compensation): a block
        # of ticks run as one mujoco.rollout gets each step's effort from them (backends.mujoco.block);
        # a realtime robot runs no blocks and does not pay for them (~3 % of arm3's step)
        #: the effort sensors are in the model (a lockstep robot with joints)
        self._effort_sensors = not self.realtime and bool(self.joints)
        for j in self.joints if self._effort_sensors else ():
            sensor = spec.add_sensor()
            if self._step_gravity is not None:
                sensor.type, sensor.objtype = mujoco.mjtSensor.mjSENS_JOINTACTFRC, mujoco.mjtObj.mjOBJ_JOINT
                sensor.objname = j.name
            else:
                sensor.type, sensor.objtype = mujoco.mjtSensor.mjSENS_ACTUATORFRC, mujoco.mjtObj.mjOBJ_ACTUATOR
                sensor.objname = f"{j.name}_servo"
        try:
            self.model = spec.compile()
        except Exception as exc:
            raise BackendStartError(f"MuJoCo could not compile {label}: {_one_line(exc)}") from exc
        self.data = mujoco.MjData(self.model)
        self._sensors.bind(self.model, self.data)
        m = self.model
        n = len(self.joints)
        #: where the effort sensors' values start in ``sensordata`` (one value each, in joint order)
        self._effort_sensor_adr = int(m.sensor_adr[m.nsensor - n]) if self._effort_sensors else 0
        if self._step_gravity is not None:
            self._step_gravity.bind(m)
        jids = [m.joint(j.name).id for j in self.joints]
        self._qadr = np.array([m.jnt_qposadr[i] for i in jids], dtype=np.intp)
        self._dadr = np.array([m.jnt_dofadr[i] for i in jids], dtype=np.intp)
        self._mimic = [
            (int(m.jnt_qposadr[m.joint(mm.joint).id]), int(m.jnt_qposadr[m.joint(mm.leader).id]),
             mm.multiplier, mm.offset)
            for mm in (desc.mimics if desc.format == "urdf" else ())
        ]
        key = self.start_pose.keyframe if desc.format == "mjcf" else None
        self._home_key = int(mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, key)) if key else -1
        d = self.data
        # views into the model and data, made once (each attribute access builds a new array object)
        self._ctrl = d.ctrl
        self._tmp = np.zeros(n)
        self._setup_gravity_compensation()
        self._setup_base()
        self._bias = m.actuator_biasprm  # view: (nu, 10)
        self._bias_kp = self._bias[:, 1]
        self._bias_kd = self._bias[:, 2]
        self._force = d.actuator_force
        #: effort read back as S.T @ qfrc_actuator (MuJoCo's gravity compensation: the joint's actuator
        #: force, a mimic follower's share carried by its leader); None: the servo actuators' force
        self._effort_map: np.ndarray | None = None
        if self._step_gravity is not None:
            s_t = np.ascontiguousarray(coupling_matrix(m, self.names).T)
            view = _gather_view(d.qfrc_actuator, self._dadr)
            if view is not None and np.count_nonzero(s_t) == n:
                self._force = view  # one dof per joint, consecutive, no follower: a view, nothing per tick
            else:
                self._effort_map = s_t
                self._qfrc_actuator = d.qfrc_actuator
                self._effort = np.zeros(n)
        # the desired state the inverse-dynamics term is evaluated at: the start pose, the commanded
        # joints and their mimic followers written from the setpoint (followers: (qadr, leader, c1, c0))
        self._qdes = np.zeros(m.nq)
        self._qdes_followers = _followers_of(m, self.names)
        self._qacc = d.qacc
        q, v = _gather_view(d.qpos, self._qadr), _gather_view(d.qvel, self._dadr)
        self._gather = q is None or v is None
        self._q = np.zeros(n) if q is None or v is None else q
        self._v = np.zeros(n) if q is None or v is None else v
        self._qpos, self._qvel = d.qpos, d.qvel
        self._n = n
        # the divergence warnings' counters, a view (a slice when their codes are consecutive)
        # sorted: the codes are consecutive (3, 4, 5), so the view is a slice, not a fancy-index copy per step
        codes = np.array(sorted(int(w) for w in _WARNINGS), dtype=np.intp)
        self._warn_view = _gather_view(d.warning.number, codes)
        self._warn_codes = codes
        self._warn = np.zeros(len(_WARNINGS), dtype=d.warning.number.dtype)  # same dtype: no casting buffer
        #: the warning counters' bytes at the last check (compared per step: no array per step)
        self._warn_bytes = b""
        self._all_enabled = np.ones(n, dtype=bool).tobytes()
        #: the bytes of an all-(+0.0) row (a setpoint without feed-forward), and of the last kd row found finite
        self._zeros = np.zeros(n)
        self._zeros.flags.writeable = False
        self._zero_row = self._zeros.tobytes()
        self._kd_finite_bytes = b""
        #: what the last servo-law write read and left (see _write): the position row, the other rows, ctrl
        self._servo_pos = b""
        self._servo_memo: tuple[bytes, bytes, bytes, bytes] | None = None
        self._servo_ctrl = b""
        #: kp and kd bytes the bias terms were last set from (empty: set them at the next write)
        self._gains: tuple[bytes, bytes] = (b"", b"")
        #: per-step scratch: |qacc|^2 (np.dot into a 0-d array: no numpy scalar per step)
        self._acc2 = np.zeros(())
        self._reset_state()

    def _urdf_spec(self) -> mujoco.MjSpec:
        """The URDF description built body by body, with the robot's one self-collision model."""
        opts: MujocoOptions = self.options
        desc = self.description
        collision = for_robot(desc, self.config, opts.self_collision)
        self.collision = collision
        spec = build_spec(desc, collision.shapes, shell=collision.shell).spec
        if collision.mode == "false":
            # robot geoms never touch each other (contype 2 & conaffinity 1 = 0) but still touch a world with 1/1
            for geom in spec.geoms:
                geom.contype, geom.conaffinity = 2, 1
        else:
            for a, b in sorted(collision.excluded):
                spec.add_exclude(bodyname1=a, bodyname2=b)
        if self.floating_base:
            tops = list(spec.worldbody.bodies)
            if len(tops) != 1:
                raise BackendStartError(
                    f"floating_base: robot {desc.name!r} has {len(tops)} bodies attached to the world, expected one"
                )
            tops[0].add_freejoint()
            self._free_body = tops[0].name
            mu = self.config.ground_friction
            for geom in spec.geoms:
                geom.friction = [mu, *list(geom.friction)[1:]]
            ground = spec.worldbody.add_geom()
            ground.name = "agentsdk/ground"
            ground.type = mujoco.mjtGeom.mjGEOM_PLANE
            ground.size = [0.0, 0.0, 1.0]  # infinite
            ground.friction = [mu, 0.005, 0.0001]
            ground.rgba = list(GROUND_RGBA)
            self._ground_height = standing_height(desc, collision)
        return spec

    def _mjcf_spec(self) -> mujoco.MjSpec:
        """The MJCF model as written (includes, assets, defaults, contacts), its actuators replaced by servos.

        Pairs touching at the start pose are excluded, a floating base gets its free joint and,
        without a floor in the model, a ground plane to stand on (see the module docstring).
        """
        desc = self.description
        spec = mjcf_spec_without_actuators(str(desc.source))
        free = desc.free_root
        if free is None and self.floating_base:
            free = _add_free_joint(spec, desc.name)
        probe = spec.compile()
        pdata = mujoco.MjData(probe)
        mimics = [(m.joint, m.leader, m.multiplier, m.offset) for m in desc.mimics]
        start_qpos(probe, pdata, dict(self.start_pose.positions), self.start_pose.keyframe, mimics)
        opt = self.options.self_collision
        mode = self.config.self_collision if opt is None else opt
        self.mjcf_touching = frozenset(touching_at_start(probe, pdata)) if mode == "auto" else frozenset()
        for a, b in sorted(self.mjcf_touching):
            spec.add_exclude(bodyname1=a, bodyname2=b)
        if free is not None:
            self._free_body = free
            if not has_ground(probe):
                mu = self.config.ground_friction
                ground = spec.worldbody.add_geom()
                ground.name = "agentsdk/ground"
                ground.type = mujoco.mjtGeom.mjGEOM_PLANE
                ground.size = [0.0, 0.0, 1.0]  # infinite
                ground.friction = [mu, 0.005, 0.0001]
                ground.rgba = list(GROUND_RGBA)
                ground.contype = ground.conaffinity = _ALL_BITS  # touches every geom that takes part in contacts
                root = int(probe.body_rootid[probe.body(free).id])
                geoms, paired = ground_geoms(probe, root)
                if paired:  # no geom of the robot collides: its collision shapes are paired with the ground
                    _pair_with_ground(spec, probe, geoms, ground.name, mu)
                self._ground_height = standing_offset(probe, pdata, probe.body(free).id)
        return spec

    def simulator_report(self) -> dict[str, Any]:
        """What the compiled MuJoCo model holds: commanded joints, link masses, colliding link pairs.

        ``joints``: ``[name, lower, upper, effort]`` per commanded joint in
        command order (range ``±inf`` when unlimited, effort ``inf`` when the
        servo is not force-limited); ``masses``: body mass per link;
        ``pairs``: sorted link pairs whose geoms can collide (contype/
        conaffinity, excludes, weld and parent filters as MuJoCo applies them).
        The root link (fixed to the world) is left out of ``masses``.
        """
        m = self.model
        joints = []
        for k, j in enumerate(self.joints):
            jid = m.joint(j.name).id
            lo, hi = (float(m.jnt_range[jid, 0]), float(m.jnt_range[jid, 1])) if m.jnt_limited[jid] else (-inf, inf)
            if self._step_gravity is not None:  # the limit is the joint's (servo and gravity torque together)
                effort = self._step_gravity.effort_limit(k)
            else:
                effort = float(m.actuator_forcerange[k, 1]) if m.actuator_forcelimited[k] else inf
            joints.append([j.name, lo, hi, effort])
        names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or f"body{b}" for b in range(m.nbody)]
        names[0] = "world"
        root = self.description.root_link
        masses = {names[b]: float(m.body_mass[b]) for b in range(1, m.nbody) if names[b] != root}
        pairs = colliding_body_pairs(m, world=self.description.format != "mjcf")
        return {"joints": joints, "masses": masses, "pairs": sorted(pairs)}

    # ------------------------------------------------------------ gravity compensation
    #: how ``g(q)`` enters the servo law: ``"simulator"`` (MuJoCo, inside the step), ``"host"`` (computed
    #: per control period and added to the control) or ``"off"`` (no joint compensated, or no gravity)
    gravity_route: Literal["simulator", "host", "off"] = "off"
    #: why the host computes ``g(q)`` (``gravity_route == "host"``), else ""
    gravity_route_reason = ""

    def _plan_gravity(self, spec: mujoco.MjSpec) -> StepGravity | None:
        """MuJoCo's own gravity compensation when it expresses the law exactly, else None (host or off)."""
        mask = self.gravity_compensation
        if not mask.any() or not any(self.options.gravity):
            self.gravity_route = "off"
            return None
        followers = {
            str(e.name1): str(e.name2) for e in spec.equalities
            if e.type == mujoco.mjtEq.mjEQ_JOINT and e.active and e.name2 in self.index and e.name1 not in self.index
        }
        reason = "" if mask.all() else "gravity compensation is off for some joints only"
        reason = reason or step_gravity_obstacle(spec, [*self.names, *followers]) or ""
        if reason:
            self.gravity_route, self.gravity_route_reason = "host", reason
            log.debug("%s: g(q) computed on the host: %s", self.config.label, reason)
            compensated = [n for n, on in zip(self.names, mask, strict=True) if on]
            compensated += [f for f, leader in followers.items() if mask[self.index[leader]]]
            cleared = drop_model_gravcomp(spec, compensated)
            if cleared:  # the host's g(q) carries their weight: the model's own gravcomp would carry it twice
                log.info("%s: the model's own gravcomp of %s is replaced by the servo law's g(q)",
                         self.config.label, ", ".join(repr(b) for b in cleared))
            return None
        self.gravity_route = "simulator"
        return StepGravity(self.names, followers, np.array([j.max_effort for j in self.joints], dtype=float))

    def _setup_gravity_compensation(self) -> None:
        """``tau_model = g(q)`` on the host for the joints with gravity compensation (None: MuJoCo's or off)."""
        m = self.model
        mask = self.gravity_compensation.astype(float)
        self._tau_model = np.zeros(len(self.joints))
        self._gc_mask = mask
        #: every joint compensated: the mask multiplies by 1.0 everywhere (no bit changes), so it is skipped
        self._gc_all = bool(mask.all())
        self._gravity = GravityTerm(m, self.names) if self.gravity_route == "host" else None
        # + M(q) a_des + C(q, v_des) v_des (robot.yaml inverse_dynamics), from this model, armature included
        self._inverse = InverseDynamicsTerm(m, self.names, friction="mujoco") if self.inverse_dynamics else None
        self._tau_motion = np.zeros(len(self.joints))

    # ------------------------------------------------------------ floating base
    def _setup_base(self) -> None:
        m = self.model
        self._free_qadr = -1
        if not self._free_body:
            return
        body = m.body(self._free_body)
        jnt = int(m.body_jntadr[body.id])
        self._free_qadr, self._free_dadr = int(m.jnt_qposadr[jnt]), int(m.jnt_dofadr[jnt])
        # the base link (description.base_link) in the free body's frame
        desc = self.description
        self._base_offset = Pose()
        if desc.base_link != self._free_body:
            joint = desc.parent_joint(desc.base_link)
            assert joint is not None
            w, x, y, z = quat_from_rpy(joint.rpy)
            self._base_offset = Pose(joint.xyz, (x, y, z, w))

    def base_state(self) -> BaseState:
        """The floating base link's pose and velocity (world frame) from the free joint's state."""
        if self._free_qadr < 0:
            return BaseState(Pose())
        d, a, v = self.data, self._free_qadr, self._free_dadr
        w, x, y, z = d.qpos[a + 3 : a + 7]
        body = Pose(d.qpos[a : a + 3], (x, y, z, w))
        rot = body.rotation
        omega = rot @ d.qvel[v + 3 : v + 6]  # MuJoCo: angular velocity of a free joint in the body frame
        base = body @ self._base_offset
        lin = d.qvel[v : v + 3] + np.cross(omega, base.position - body.position)
        return BaseState(base, lin, omega)

    def _reset_state(self) -> None:
        m, d = self.model, self.data
        if self._home_key >= 0:
            mujoco.mj_resetDataKeyframe(m, d, self._home_key)
        else:
            mujoco.mj_resetData(m, d)
        if self._free_qadr >= 0:
            d.qpos[self._free_qadr + 2] += self._ground_height  # standing on the ground plane
        d.qpos[self._qadr] = self.initial_positions
        for follower, leader, multiplier, offset in self._mimic:
            d.qpos[follower] = multiplier * d.qpos[leader] + offset
        mujoco.mj_forward(m, d)
        self._qdes[:] = d.qpos  # the desired state's coordinates that no setpoint moves: the start pose
        self._warn[:] = [d.warning[int(c)].number for c in self._warn_codes]
        self._warn_bytes = self._warnings().tobytes()

    async def _close(self) -> None:
        # nothing to release: the model and data are freed with the object
        if hasattr(self, "data"):
            self.data.ctrl[:] = 0.0
        if hasattr(self, "_sensors") and self._sensors.rendering:
            # freeing a GL context and the model's uploaded meshes takes up to a second: off the event loop
            await run_blocking(self._sensors.close, name="agentsdk-mujoco-gl-free")

    def _write(self, sp: SetpointView) -> None:
        ctrl, tmp = self._ctrl, self._tmp
        en = sp.enabled
        enabled = en.tobytes()
        # the rows' bytes asked more than once below, taken once
        zero, velocity, kd = self._zero_row, sp.velocity.tobytes(), sp.kd.tobytes()
        inverse = self._inverse
        # (zero velocity and acceleration, a hold or a pose stream: not moving, moving()'s own first test)
        moving = (inverse is not None and not (velocity == zero and sp.acceleration.tobytes() == zero)
                  and inverse.moving(sp.velocity, sp.acceleration))
        # A hold writes the same setpoint every tick: when ctrl is a function of the setpoint alone (no
        # host gravity term, no inverse dynamics, torque on everywhere) and the setpoint and ctrl hold the
        # bytes of last tick's write, ctrl already holds what the servo law would compute (bit for bit).
        # The position row is compared first (a moving setpoint differs there): one bytes compare per tick.
        pos = sp.position.tobytes()
        memo: tuple[bytes, bytes, bytes, bytes] | None = None
        held = False
        if pos == self._servo_pos and self._gravity is None and not moving and enabled == self._all_enabled:
            memo = (velocity, sp.effort.tobytes(), sp.kp.tobytes(), kd)
            held = memo == self._servo_memo and ctrl.tobytes() == self._servo_ctrl
        if not held:
            # ctrl = kp*q_des + kd*v_des + ff, computed in place in MuJoCo's ctrl (no temporaries)
            np.multiply(sp.kp, sp.position, out=ctrl)
            if (velocity == zero and sp.effort.tobytes() == zero
                    and (kd == self._kd_finite_bytes or self._kd_finite(sp.kd))):
                # no feed-forward (a pose stream): kd*(+0) is a zero for a finite kd, and (x + a zero) + (+0)
                # is x + (+0) for every x (only a -0 changes: to +0), bit for bit; one ufunc instead of three
                np.add(ctrl, self._zeros, out=ctrl)  # (an array: a Python float operand costs a conversion)
            else:
                np.multiply(sp.kd, sp.velocity, out=tmp)
                ctrl += tmp
                ctrl += sp.effort
            if memo is not None:
                self._servo_ctrl = ctrl.tobytes()
        self._servo_pos = pos
        self._servo_memo = memo
        if self._gravity is not None:  # tau_model: g(q) at the measured position, allocation-free
            tau = self._gravity.compute(self._qpos, self._tau_model)  # (views made once: no array per tick)
            if not self._gc_all:
                tau *= self._gc_mask
            ctrl += tau
        if moving:  # the motion's inverse dynamics
            assert inverse is not None
            qdes = self._qdes  # at the desired state: a function of the setpoint stream alone
            np.put(qdes, self._qadr, sp.position)
            for adr, leader, c1, c0 in self._qdes_followers:
                qdes[adr] = c0 + c1 * sp.position[leader]
            ctrl += inverse.compute(qdes, sp.velocity, sp.acceleration, self._tau_motion, sp.mode, moving=True)
        step_gravity = self._step_gravity
        if step_gravity is not None:  # MuJoCo's g(q): off with the joint's torque (bytes compare when unchanged)
            step_gravity.set_enabled(en, enabled)
        if enabled != self._all_enabled:  # bytes compare: ~5x cheaper than np.count_nonzero
            ctrl[~en] = 0.0
            self._bias_kp[:] = np.where(en, -sp.kp, 0.0)
            self._bias_kd[:] = np.where(en, -sp.kd, 0.0)
            self._gains = (b"", b"")
            return
        gains = self._gains
        if sp.kp.tobytes() != gains[0] or kd != gains[1]:  # the bias terms change with the gains only
            np.negative(sp.kp, out=self._bias_kp)
            np.negative(sp.kd, out=self._bias_kd)
            self._gains = (sp.kp.tobytes(), kd)

    def _kd_finite(self, kd: np.ndarray) -> bool:
        """Every damping gain in ``kd`` is finite; if so, its bytes are kept (the next write compares them)."""
        finite = math.isfinite(sum(kd.tolist())) or bool(np.isfinite(kd).all())
        if finite:
            self._kd_finite_bytes = kd.tobytes()
        return finite

    async def _step(self, dt: float) -> None:
        d = self.data
        t0 = d.time
        mujoco.mj_step(self.model, d, nstep=self._nsub)
        view = self._warn_view
        if view is None or view.tobytes() != self._warn_bytes:
            self._check_warnings(t0)
        # a float sum is NaN or inf as soon as one element is (no ufunc, no BLAS call); a non-finite
        # sum of finite values (an overflow) asks the elements
        qacc = self._qacc
        if not math.isfinite(sum(qacc.tolist())) and not np.isfinite(qacc).all():
            raise SimulationDiverged(f"MuJoCo state became non-finite at t={d.time:.4f} s")

    def block_stepper(self, capacity: int) -> BlockStepper:
        """A :class:`~.block.BlockStepper` of this backend: up to ``capacity`` ticks per call (block lockstep)."""
        from .block import BlockStepper

        return BlockStepper(self, capacity)

    def _warnings(self) -> np.ndarray:
        """The counters of the divergence warnings (in code order, ``_warn_codes``)."""
        view = self._warn_view
        return view if view is not None else self.data.warning.number[self._warn_codes]

    def _check_warnings(self, t0: float) -> None:
        w = self.data.warning
        where = {int(c): k for k, c in enumerate(self._warn_codes)}
        for code in _WARNINGS:  # reported in _WARNINGS order (bad qacc first)
            k = where[int(code)]
            n = w[code].number
            if n != self._warn[k]:
                self._warn[k] = n
                if code == _BADCTRL:
                    act = w[code].lastinfo
                    joint = self.names[act] if 0 <= act < len(self.names) else f"actuator {act}"
                    raise SimulationDiverged(
                        f"MuJoCo rejected the control of joint {joint!r} of {self.description.name!r} in the step "
                        f"after t={t0:.4f} s (NaN, inf or above {mujoco.mjMAXVAL:g}: {mujoco.mjtWarning(code).name}); "
                        "MuJoCo zeroed every control, so the servos were off"
                    )
                # MuJoCo has already reset the state: report the time before this step
                # and the dof it flagged (lastinfo), not the reset values
                raise SimulationDiverged(
                    f"MuJoCo simulation of {self.description.name!r} diverged in the step after "
                    f"t={t0:.4f} s ({mujoco.mjtWarning(code).name} at dof {w[code].lastinfo}); "
                    "lower the gains or the timestep"
                )
        self._warn[:] = self._warnings()
        self._warn_bytes = self._warnings().tobytes()

    def _read(self) -> JointReading:
        if self._gather:  # joints not consecutive in qpos / qvel (else _q, _v are views)
            self._qpos.take(self._qadr, out=self._q)
            self._qvel.take(self._dadr, out=self._v)
        if self._effort_map is not None:  # MuJoCo's gravity compensation with mimic followers or scattered dofs
            return self._q, self._v, np.dot(self._effort_map, self._qfrc_actuator, out=self._effort)
        return self._q, self._v, self._force

    def _read_sensors(self, channels: Sequence[SensorChannel]) -> None:
        self._sensors.read(channels)

    def _emergency_stop(self, category: int) -> None:
        # thread-safe enough: plain stores into arrays the loop thread reads at its next step
        self._gains = (b"", b"")  # the next write sets the bias terms again
        self._ctrl[:] = 0.0
        self._bias_kp[:] = 0.0
        self._bias_kd[:] = 0.0
        if self._step_gravity is not None:  # MuJoCo's gravity compensation off with the servos
            self._step_gravity.torque_off()

    async def _recover(self) -> None:
        self._reset_state()


#: contype/conaffinity of the ground plane a floating MJCF robot stands on: every bit
_ALL_BITS = 0x7FFFFFFF


def _pair_with_ground(spec: mujoco.MjSpec, model: mujoco.MjModel, geoms: Sequence[int], ground: str, mu: float) -> None:
    """Explicit contact pairs of the compiled ``model``'s ``geoms`` with the ground (friction ``mu``, condim 3).

    A geom without a name is given one (``agentsdk/geom<id>``): a pair names its geoms. The spec's
    bodies and their geoms are in the compiled model's order.
    """
    bodies = list(spec.bodies)
    for g in geoms:
        b = int(model.geom_bodyid[g])
        geom = list(bodies[b].geoms)[g - int(model.body_geomadr[b])]
        if not geom.name:
            geom.name = f"agentsdk/geom{g}"
        spec.add_pair(geomname1=geom.name, geomname2=ground, condim=3, friction=[mu, mu, 0.005, 0.0001, 0.0001])


def _add_free_joint(spec: mujoco.MjSpec, robot: str) -> str:
    """Free the one body attached to the world (robot.yaml ``floating_base`` on an MJCF without a free joint).

    The keyframes get the body's pose at the front of their ``qpos`` (the free joint is the first joint).
    """
    tops = list(spec.worldbody.bodies)
    movable = [b for b in tops if list(b.bodies) or list(b.joints)]
    if len(movable) != 1:
        raise BackendStartError(
            f"floating_base: robot {robot!r} has {len(movable)} bodies attached to the world, expected one"
        )
    body = movable[0]
    body.add_freejoint()
    for key in spec.keys:
        if len(key.qpos):
            key.qpos = [*body.pos, *body.quat, *key.qpos]
    return str(body.name)


def _followers_of(model: mujoco.MjModel, joints: Sequence[str]) -> list[tuple[int, int, float, float]]:
    """``(qpos address, leader index in joints, c1, c0)`` of every joint following a commanded one.

    A joint equality ``q_follower = c0 + c1 * q_leader`` (URDF mimic joints as built, MJCF joint
    equalities), as :func:`agentsdk.dynamics.coupling_matrix` reads it.
    """
    index = {name: k for k, name in enumerate(joints)}
    out: list[tuple[int, int, float, float]] = []
    for e in range(model.neq):
        if int(model.eq_type[e]) != int(mujoco.mjtEq.mjEQ_JOINT) or not model.eq_active0[e] or model.eq_obj2id[e] < 0:
            continue
        follower, leader = model.joint(int(model.eq_obj1id[e])).name, model.joint(int(model.eq_obj2id[e])).name
        if leader in index and follower not in index:
            out.append((int(model.jnt_qposadr[model.joint(follower).id]), index[leader],
                        float(model.eq_data[e, 1]), float(model.eq_data[e, 0])))
    return out


def _gather_view(arr: np.ndarray, idx: np.ndarray) -> np.ndarray | None:
    """A view of ``arr[idx]`` when ``idx`` is a run of consecutive indices (no copy per tick), else None."""
    if len(idx) == 0:
        return arr[0:0]
    start = int(idx[0])
    if np.array_equal(idx, np.arange(start, start + len(idx))):
        return arr[start : start + len(idx)]
    return None


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__

#: the former name of :class:`MujocoBackend` (deprecated: import MujocoBackend)
MujocoController = MujocoBackend
