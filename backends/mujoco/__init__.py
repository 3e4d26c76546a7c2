"""MuJoCo backend: the URDF compiled through ``mujoco.MjSpec`` with one joint servo per joint.

Each actuated joint gets a MuJoCo *general* actuator with ``gain = 1`` and an
affine bias ``[0, -kp, -kd]``; writing ``ctrl = kp*q_des + kd*v_des + effort_ff``
yields exactly the SDK's servo law ``kp*(q_des - q) + kd*(v_des - v) + effort_ff``,
evaluated by MuJoCo at every physics step (with the damping term integrated
implicitly by ``implicitfast``), clamped to the URDF effort limit.

Divergence: MuJoCo silently resets a diverged state (``mjWARN_BADQACC``); this
backend checks the warning counters and finiteness after every control period
and raises :class:`SimulationDiverged` instead, like dm_control's
``check_invalid_state``.
"""

from __future__ import annotations

import hashlib
import tempfile
from pathlib import Path
from typing import Literal

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from agentsdk.backend import Backend, Capabilities, JointReading, SetpointView
from agentsdk.errors import BackendStartError, ConfigurationError, SimulationDiverged
from agentsdk.types import MODES

__all__ = ["MujocoController", "MujocoOptions"]

_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
)
_NATIVE_MESH = {".stl", ".obj", ".msh"}


class MujocoOptions(BaseModel):
    """robot.yaml ``backends.mujoco`` / ``connect("mujoco", ...)`` options."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    timestep: float = Field(default=0.001, gt=0.0)
    integrator: Literal["implicitfast", "implicit", "euler", "rk4"] = "implicitfast"
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    #: joint damping added to every actuated joint (N·m·s/rad), models gearbox friction
    joint_damping: float = Field(default=0.0, ge=0.0)
    #: reflected rotor inertia added to every actuated joint (kg·m²)
    armature: float = Field(default=0.0, ge=0.0)
    #: keep a free-floating base instead of fixing the root link to the world
    floating_base: bool = False


class MujocoController(Backend):
    name = "mujoco"
    capabilities = Capabilities(
        modes=frozenset(MODES), lockstep=True, realtime=True, deterministic=True
    )
    options_model = MujocoOptions

    model: mujoco.MjModel
    data: mujoco.MjData

    async def _open(self) -> None:
        opts: MujocoOptions = self.options
        nsub = round(self.period / opts.timestep)
        if nsub < 1 or abs(nsub * opts.timestep - self.period) > 1e-9:
            raise ConfigurationError(
                f"control period {self.period:g} s is not a whole multiple of the MuJoCo timestep {opts.timestep:g} s"
            )
        self._nsub = nsub
        try:
            spec = mujoco.MjSpec.from_string(self.description.urdf_xml)
        except Exception as exc:
            raise BackendStartError(f"MuJoCo could not import the URDF of {self.description.name!r}: {exc}") from exc
        self._fix_meshes(spec)
        spec.option.timestep = opts.timestep
        spec.option.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{opts.integrator.upper()}")
        spec.option.gravity = list(opts.gravity)
        if opts.floating_base:
            root = spec.worldbody.first_body()
            if root is not None:
                root.add_freejoint()
        else:
            # MuJoCo fuses links fixed to the world into the world body, and its
            # parent/child contact filter does not apply to the world: restore the
            # URDF convention that adjacent links do not collide.
            for body in spec.worldbody.bodies:
                spec.add_exclude(bodyname1="world", bodyname2=body.name)
        for j in self.joints:
            sj = spec.joint(j.name)
            if sj is None:
                raise BackendStartError(f"joint {j.name!r} missing from the MuJoCo model")
            sj.damping = sj.damping + opts.joint_damping
            sj.armature = sj.armature + opts.armature
            act = spec.add_actuator()
            act.name = f"{j.name}_servo"
            act.target = j.name
            act.trntype = mujoco.mjtTrn.mjTRN_JOINT
            act.gaintype = mujoco.mjtGain.mjGAIN_FIXED
            act.biastype = mujoco.mjtBias.mjBIAS_AFFINE
            act.gainprm[0] = 1.0
            act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
            act.forcerange = [-j.max_effort, j.max_effort]
        try:
            self.model = spec.compile()
        except Exception as exc:
            raise BackendStartError(f"MuJoCo could not compile {self.description.name!r}: {exc}") from exc
        self.data = mujoco.MjData(self.model)
        m = self.model
        jids = [m.joint(j.name).id for j in self.joints]
        self._qadr = np.array([m.jnt_qposadr[i] for i in jids])
        self._dadr = np.array([m.jnt_dofadr[i] for i in jids])
        self._ctrl = np.zeros(m.nu)
        self._q = np.zeros(len(self.joints))
        self._v = np.zeros(len(self.joints))
        self._bias = m.actuator_biasprm  # view: (nu, 10)
        self._warn = np.zeros(len(_WARNINGS), dtype=np.int64)
        self._reset_state()

    def _fix_meshes(self, spec: mujoco.MjSpec) -> None:
        """MuJoCo's URDF importer keeps only mesh base names: point them back at real files."""
        files = {p.name: p for p in self.description.mesh_files}
        for mesh in spec.meshes:
            name = Path(mesh.file).name
            path = files.get(name)
            if path is None:
                continue
            if path.suffix.lower() not in _NATIVE_MESH:
                path = _convert_mesh(path)
            mesh.file = str(path)

    def _reset_state(self) -> None:
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[self._qadr] = self.initial_positions
        mujoco.mj_forward(m, d)
        self._warn[:] = [d.warning[w].number for w in _WARNINGS]

    async def _close(self) -> None:
        # nothing to release: the model and data are freed with the object
        if hasattr(self, "data"):
            self.data.ctrl[:] = 0.0

    def _write(self, sp: SetpointView) -> None:
        en = sp.enabled
        ctrl = self._ctrl
        np.multiply(sp.kp, sp.position, out=ctrl)
        ctrl += sp.kd * sp.velocity
        ctrl += sp.effort
        if not en.all():
            ctrl[~en] = 0.0
            self._bias[:, 1] = np.where(en, -sp.kp, 0.0)
            self._bias[:, 2] = np.where(en, -sp.kd, 0.0)
        else:
            np.negative(sp.kp, out=self._bias[:, 1])
            np.negative(sp.kd, out=self._bias[:, 2])
        self.data.ctrl[:] = ctrl

    async def _step(self, dt: float) -> None:
        m, d = self.model, self.data
        t0 = d.time
        mujoco.mj_step(m, d, nstep=self._nsub)
        w = d.warning
        for k, code in enumerate(_WARNINGS):
            n = w[code].number
            if n != self._warn[k]:
                self._warn[k] = n
                # MuJoCo has already reset the state: report the time before this step
                # and the dof it flagged (lastinfo), not the reset values
                raise SimulationDiverged(
                    f"MuJoCo simulation of {self.description.name!r} diverged in the step after "
                    f"t={t0:.4f} s ({mujoco.mjtWarning(code).name} at dof {w[code].lastinfo}); "
                    "lower the gains or the timestep"
                )
        if not np.isfinite(d.qacc).all():
            raise SimulationDiverged(f"MuJoCo state became non-finite at t={d.time:.4f} s")

    def _read(self) -> JointReading:
        d = self.data
        np.take(d.qpos, self._qadr, out=self._q)
        np.take(d.qvel, self._dadr, out=self._v)
        return self._q, self._v, d.actuator_force

    def _emergency_stop(self, category: int) -> None:
        # thread-safe enough: plain stores into arrays the loop thread reads at its next step
        self.data.ctrl[:] = 0.0
        self._bias[:, 1] = 0.0
        self._bias[:, 2] = 0.0

    async def _recover(self) -> None:
        self._reset_state()


def _convert_mesh(path: Path) -> Path:
    """Convert a mesh MuJoCo cannot read (e.g. COLLADA .dae) to STL in a cache dir."""
    import trimesh

    digest = hashlib.sha1(str(path.resolve()).encode()).hexdigest()[:12]
    out = Path(tempfile.gettempdir()) / "agentsdk-meshes" / f"{path.stem}-{digest}.stl"
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        mesh = trimesh.load(path, force="mesh")
        mesh.export(out)
    return out
