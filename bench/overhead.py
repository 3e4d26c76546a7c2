"""SDK overhead per control cycle and lockstep real-time factor, against raw simulator loops.

Overhead. The SDK loop is a behavior that, every control period, does::

    state = await robot.read()
    await robot.command(JointCommand("position", q_des))
    await robot.clock.sleep(period)

in lockstep (one control tick per cycle: updaters -> safety filter -> ``_write`` ->
``_step`` -> ``_read`` -> tick hooks). The raw loops do the same control without the
SDK, on the same model built the same way:

* raw MuJoCo: the backend's own compiled model (built from the description with
  ``build_spec``, the robot's self-collision model, the same options and general
  actuators: gain 1, affine bias ``[0, -kp, -kd]``, force-limited); per cycle:
  read ``qpos/qvel/actuator_force``, write ``ctrl = kp*q_des + kd*v_des + ff``,
  ``mj_step(nstep)``.
* raw PyBullet: the URDF loaded with the same flags, motors off, damping removed;
  per physics substep the same torque PD with the same implicit-damping correction
  (mass matrix + inverse dynamics + solve) as the backend, ``TORQUE_CONTROL``,
  ``stepSimulation``. An extra raw row without the implicit correction (plain
  explicit PD) shows what that correction costs.

Both loops see the same setpoint sequence ``q_des(k) = q0 + A sin(2 pi f k period)``,
so their final states agree (bit-identical on MuJoCo); the table shows the
difference as a check that the same control was timed.

Real-time factor: ~10 s of simulated time (sim time / wall time) holding a pose and
tracking a planned trajectory through random waypoints, SDK (lockstep) vs the raw
loop with the same setpoints; the MuJoCo hold row also gives the physics-only
ceiling (one ``mj_step`` call for all steps).
"""

from __future__ import annotations

import asyncio
import cProfile
import math
import os
import pstats
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import agentsdk
import agentsdk.backends
from agentsdk.bench.common import Comparison, Section, Table, fmt, median, progress, spread

ROBOTS = ("arm3", "humanoid")
BACKENDS = ("mujoco", "pybullet")
#: overhead target per control cycle (µs)
OVERHEAD_TARGET_US = 50.0
#: setpoint wave: small enough to stay inside every joint's limits (no clamping by the safety layer)
AMP = 0.04
FREQ = 0.5
W = 2.0 * math.pi * FREQ

_REPO = Path(__file__).resolve().parent.parent
#: where SDK code lives (a checkout keeps backends/ beside agentsdk/; an install nests it)
_SDK_DIRS = tuple(
    {str(Path(m.__file__).resolve().parent) + os.sep for m in (agentsdk, agentsdk.backends)}
)


def _wave(q0: np.ndarray, k: int, period: float) -> np.ndarray:
    return q0 + AMP * math.sin(W * k * period)


# =========================================================================== raw loops


@dataclass
class _Robot:
    config: Any
    description: Any
    joints: tuple[Any, ...]
    kp: np.ndarray
    kd: np.ndarray
    period: float


def _backend_model(rb: _Robot) -> tuple[Any, Any, int]:
    """(model, data at the initial state, substeps per control period) built by the MuJoCo backend itself."""
    from agentsdk.registry import load_backend

    ctl = load_backend("mujoco").create(rb.config, rb.description, rb.joints, realtime=False)

    async def build() -> tuple[Any, Any, int]:
        import mujoco

        await ctl.open()
        try:
            m = ctl.model
            if m.nsensor == len(rb.joints):
                # the backend's only sensors are its per-joint effort sensors (what a block's rollout reads
                # efforts from): a raw loop would not have them, so it does not compute them (no change
                # to the physics)
                m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_SENSOR)
            return m, ctl.data, round(rb.period / ctl.options.timestep)
        finally:
            await ctl.close()  # releases nothing MuJoCo owns: the model and data stay valid

    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return asyncio.run(build())
    with ThreadPoolExecutor(1) as pool:  # called from a coroutine: build on a loop of its own
        return pool.submit(asyncio.run, build()).result()


def load_robot(name: str) -> _Robot:
    from agentsdk.description import apply_overrides, resolve_robot

    config, description = resolve_robot(name)
    joints = apply_overrides(description, config)
    gains = [config.gains_for(j.name) for j in joints]
    return _Robot(
        config,
        description,
        joints,
        np.array([g.p for g in gains]),
        np.array([g.d for g in gains]),
        config.control_period,
    )


class RawMujoco:
    """The MuJoCo backend's model and servo law, without the SDK.

    The model is the backend's own compiled ``MjModel`` (built by the backend from the
    description with ``agentsdk.description.mjspec.build_spec``, the robot's
    self-collision model, the same options and servo actuators) and its ``MjData`` at
    the initial state: the backend is opened once to build them and closed again,
    then this loop steps that very model with ``mj_step`` (the final states of the
    raw and the SDK loop agree bit for bit). Where the backend's per-joint effort
    sensors are the model's only sensors, this loop does not compute sensors: they
    are the SDK's, not part of a raw loop.
    """

    def __init__(self, rb: _Robot) -> None:
        import mujoco

        self.mj = mujoco
        m, d, nsub = _backend_model(rb)
        self.model, self.data = m, d
        self.nsub = nsub
        self.period = rb.period
        jids = [m.joint(j.name).id for j in rb.joints]
        self.qadr = np.array([m.jnt_qposadr[i] for i in jids])
        self.dadr = np.array([m.jnt_dofadr[i] for i in jids])
        self.kp, self.kd = rb.kp, rb.kd
        m.actuator_biasprm[:, 1] = -rb.kp
        m.actuator_biasprm[:, 2] = -rb.kd
        mujoco.mj_forward(m, d)
        self.ctrl = np.zeros(m.nu)
        self.zero = np.zeros(m.nu)

    def positions(self) -> np.ndarray:
        return self.data.qpos[self.qadr].copy()

    def run_wave(self, q0: np.ndarray, k0: int, n: int) -> float:
        """n control cycles of the wave setpoint; returns wall seconds."""
        mj, m, d = self.mj, self.model, self.data
        qadr, dadr, nsub, period = self.qadr, self.dadr, self.nsub, self.period
        kp, kd, ctrl, zero = self.kp, self.kd, self.ctrl, self.zero
        t0 = time.perf_counter()
        for k in range(k0, k0 + n):
            q = d.qpos[qadr]  # read (copies, like a state snapshot)
            v = d.qvel[dadr]
            e = d.actuator_force.copy()
            del q, v, e
            qd = q0 + AMP * math.sin(W * k * period)  # command
            np.multiply(kp, qd, out=ctrl)
            ctrl += kd * zero
            ctrl += zero
            d.ctrl[:] = ctrl
            mj.mj_step(m, d, nstep=nsub)  # step
        return time.perf_counter() - t0

    def run_setpoints(self, qd: np.ndarray, vd: np.ndarray) -> float:
        """One control cycle per row of (qd, vd); returns wall seconds."""
        mj, m, d = self.mj, self.model, self.data
        qadr, dadr, nsub = self.qadr, self.dadr, self.nsub
        kp, kd, ctrl, zero = self.kp, self.kd, self.ctrl, self.zero
        t0 = time.perf_counter()
        for k in range(len(qd)):
            q = d.qpos[qadr]
            v = d.qvel[dadr]
            del q, v
            np.multiply(kp, qd[k], out=ctrl)
            ctrl += kd * vd[k]
            ctrl += zero
            d.ctrl[:] = ctrl
            mj.mj_step(m, d, nstep=nsub)
        return time.perf_counter() - t0

    def run_physics_only(self, cycles: int) -> float:
        """All physics steps in one ``mj_step`` call with a constant ctrl (the ceiling)."""
        t0 = time.perf_counter()
        self.mj.mj_step(self.model, self.data, nstep=cycles * self.nsub)
        return time.perf_counter() - t0

    def close(self) -> None:
        pass


class RawPybullet:
    """The PyBullet backend's model loading and per-substep torque PD, without the SDK."""

    def __init__(self, rb: _Robot, implicit: bool = True) -> None:
        from agentsdk.backends.pybullet import SPEED_CAP, PybulletOptions
        from agentsdk.backends.pybullet.quiet import filtered_native_output

        with filtered_native_output():  # no "pybullet build time: ..." on the user's terminal
            import pybullet as p
        from agentsdk.description.collision import for_robot
        from agentsdk.description.simurdf import simulator_urdf

        self.p = p
        opts = PybulletOptions(**rb.config.backend_options("pybullet"))
        if opts.floating_base:
            raise NotImplementedError("the raw PyBullet loop covers fixed-base robots only")
        self.h = opts.timestep
        self.nsub = round(rb.period / opts.timestep)
        self.period = rb.period
        cid = self.cid = p.connect(p.DIRECT)
        p.setTimeStep(opts.timestep, physicsClientId=cid)
        p.setGravity(*opts.gravity, physicsClientId=cid)
        p.setPhysicsEngineParameter(
            numSolverIterations=opts.solver_iterations,
            numSubSteps=0,
            deterministicOverlappingPairs=1,
            physicsClientId=cid,
        )
        # the URDF the backend writes from the description, with the robot's one self-collision model
        collision = for_robot(rb.description, rb.config, opts.self_collision)
        urdf_xml = simulator_urdf(rb.description, collision.shapes, visuals=False)
        flags = p.URDF_USE_INERTIA_FROM_FILE | p.URDF_MAINTAIN_LINK_ORDER
        if collision.mode != "false":
            flags |= p.URDF_USE_SELF_COLLISION
        fd, tmp = tempfile.mkstemp(suffix=".urdf", prefix="bench-raw-")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(urdf_xml)
            body = self.body = p.loadURDF(tmp, useFixedBase=True, flags=flags, physicsClientId=cid)
        finally:
            Path(tmp).unlink(missing_ok=True)
        infos = [p.getJointInfo(body, i, physicsClientId=cid) for i in range(p.getNumJoints(body, physicsClientId=cid))]
        if collision.mode != "false":
            links = {p.getBodyInfo(body, physicsClientId=cid)[0].decode(): -1}
            links.update({i[12].decode(): int(i[0]) for i in infos})
            for a, b in sorted(collision.excluded):
                if a in links and b in links:
                    p.setCollisionFilterPair(body, body, links[a], links[b], 0, physicsClientId=cid)
        dofs = sorted((i for i in infos if i[2] != p.JOINT_FIXED), key=lambda i: i[4])
        self.dofs = [int(i[0]) for i in dofs]
        row = {int(i[0]): k for k, i in enumerate(dofs)}
        by_name = {i[1].decode(): i for i in infos}
        self.sel = np.array([row[int(by_name[j.name][0])] for j in rb.joints], dtype=np.intp)
        nd = len(self.dofs)
        self.damping = np.array([float(i[6]) for i in dofs]) + opts.joint_damping
        friction = [float(i[7]) for i in dofs]
        for link in range(-1, len(infos)):
            p.changeDynamics(body, link, linearDamping=0.0, angularDamping=0.0, physicsClientId=cid)
        for j in self.dofs:
            p.changeDynamics(body, j, jointDamping=0.0, maxJointVelocity=SPEED_CAP, physicsClientId=cid)
        p.setJointMotorControlArray(
            body, self.dofs, p.VELOCITY_CONTROL, targetVelocities=[0.0] * nd, forces=friction, physicsClientId=cid
        )
        q0 = np.zeros(nd)
        names = [j.name for j in rb.joints]
        for name, q in {**rb.description.default_positions, **rb.config.initial_positions}.items():
            if name in names:
                q0[self.sel[names.index(name)]] = q
        for k, j in enumerate(self.dofs):
            p.resetJointState(body, j, float(q0[k]), 0.0, physicsClientId=cid)
        self.implicit = implicit
        self.kp, self.kd = rb.kp, rb.kd
        self.lim = np.array([j.max_effort for j in rb.joints])
        self.neg_lim = -self.lim
        self.neg_damping = -self.damping
        n = len(rb.joints)
        self.q_all, self.v_all = np.zeros(nd), np.zeros(nd)
        self.f_all, self.d_all = np.zeros(nd), np.zeros(nd)
        self.hd, self.rhs = np.zeros(nd), np.zeros(nd)
        self.q, self.v = np.zeros(n), np.zeros(n)
        self.raw, self.tau, self.tmp, self.kdm = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
        self.mask = np.zeros(n, dtype=bool)
        self.zeros = [0.0] * nd
        self._sense()

    def _sense(self) -> None:
        states = self.p.getJointStates(self.body, self.dofs, physicsClientId=self.cid)
        self.ql = [s[0] for s in states]
        self.vl = [s[1] for s in states]
        self.q_all[:] = self.ql
        self.v_all[:] = self.vl

    def positions(self) -> np.ndarray:
        return self.q_all[self.sel].copy()

    def _cycle(self, qd: np.ndarray, vd: np.ndarray, ff: np.ndarray) -> None:
        """One control period: the servo law at every physics substep, as the backend evaluates it.

        The same arithmetic with the same numpy primitives (preallocated arrays, ufuncs with
        ``out=``), so that the difference to the SDK loop is the SDK, not the way the law is coded.
        """
        p, cid, body, dofs = self.p, self.cid, self.body, self.dofs
        sel, kp, kd, lim, neg_lim, h = self.sel, self.kp, self.kd, self.lim, self.neg_lim, self.h
        raw, tau, tmp, kdm, mask = self.raw, self.tau, self.tmp, self.kdm, self.mask
        q_all, v_all, f_all, d_all = self.q_all, self.v_all, self.f_all, self.d_all
        q, v = self.q, self.v
        for _ in range(self.nsub):
            q_all.take(sel, out=q)
            v_all.take(sel, out=v)
            np.subtract(qd, q, out=raw)
            np.multiply(raw, kp, out=raw)
            np.subtract(vd, v, out=tmp)
            np.multiply(kd, tmp, out=tmp)
            np.add(raw, tmp, out=raw)
            np.add(raw, ff, out=raw)
            np.maximum(raw, neg_lim, out=tau)
            np.minimum(tau, lim, out=tau)
            np.multiply(self.neg_damping, v_all, out=f_all)
            f_all[sel] += tau
            if self.implicit:
                np.abs(raw, out=tmp)
                np.less(tmp, lim, out=mask)
                kdm.fill(0.0)
                np.copyto(kdm, kd, where=mask)
                np.copyto(d_all, self.damping)
                d_all[sel] += kdm
                mass = np.array(p.calculateMassMatrix(body, self.ql, physicsClientId=cid))
                bias = p.calculateInverseDynamics(body, self.ql, self.vl, self.zeros, physicsClientId=cid)
                hd = self.hd
                np.multiply(d_all, h, out=hd)
                diag = mass.reshape(-1)[:: len(dofs) + 1]
                np.add(diag, hd, out=diag)
                rhs = self.rhs
                np.subtract(f_all, bias, out=rhs)
                qacc = np.linalg.solve(mass, rhs)
                np.multiply(hd, qacc, out=rhs)
                np.subtract(f_all, rhs, out=f_all)
            p.setJointMotorControlArray(body, dofs, p.TORQUE_CONTROL, forces=f_all.tolist(), physicsClientId=cid)
            p.stepSimulation(physicsClientId=cid)
            self._sense()

    def run_wave(self, q0: np.ndarray, k0: int, n: int) -> float:
        period, sel = self.period, self.sel
        zero = np.zeros(len(sel))
        t0 = time.perf_counter()
        for k in range(k0, k0 + n):
            q = self.q_all[sel]  # read
            v = self.v_all[sel]
            e = self.tau.copy()
            del q, v, e
            qd = q0 + AMP * math.sin(W * k * period)  # command
            self._cycle(qd, zero, zero)  # step
        return time.perf_counter() - t0

    def run_setpoints(self, qd: np.ndarray, vd: np.ndarray) -> float:
        zero = np.zeros(len(self.sel))
        t0 = time.perf_counter()
        for k in range(len(qd)):
            self._cycle(qd[k], vd[k], zero)
        return time.perf_counter() - t0

    def close(self) -> None:
        if self.cid >= 0:
            self.p.disconnect(physicsClientId=self.cid)
            self.cid = -1


def _raw(backend: str, rb: _Robot, implicit: bool = True) -> RawMujoco | RawPybullet:
    return RawMujoco(rb) if backend == "mujoco" else RawPybullet(rb, implicit=implicit)


# =========================================================================== SDK loops


class _Stalled(RuntimeError):
    """The SDK's stall watchdog latched an e-stop during a timed run (an overloaded machine): redo the run."""


#: stall-watchdog e-stops seen during SDK runs (each run was redone)
STALLS: list[str] = []


def _check_stall(r: Any, what: str) -> None:
    st = r.safety
    if st.stall_detected_at is not None or st.state.name != "OK":
        raise _Stalled(f"{what}: safety state {st.state.name} (stall latency {st.stall_latency})")


def _run_sdk(what: str, fn: Any, *args: Any, tries: int = 3, **kwargs: Any) -> Any:
    """``asyncio.run(fn(...))``, redone if the stall watchdog tripped (up to ``tries`` times)."""
    for attempt in range(tries):
        try:
            return asyncio.run(fn(*args, **kwargs))
        except _Stalled as exc:
            STALLS.append(str(exc))
            progress(f"{what}: the stall watchdog latched an e-stop (machine overloaded?); redoing the run")
            if attempt == tries - 1:
                raise RuntimeError(f"{what}: the stall watchdog tripped on all {tries} attempts") from exc
    raise AssertionError("unreachable")


async def _sdk_wave(
    backend: str, robot: str, warmup: int, n: int, profiler: cProfile.Profile | None = None
) -> tuple[float, float, np.ndarray, int]:
    """(wall seconds, process CPU seconds of n timed cycles, final positions, control ticks in them)."""
    import agentsdk
    from agentsdk import JointCommand
    from agentsdk.errors import SafetyError

    async with agentsdk.connect(backend, robot) as r:
        clock = r.clock
        period = r.control_period
        q0 = (await r.read()).position.copy()

        async def cycles(k0: int, k1: int) -> None:
            for k in range(k0, k1):
                state = await r.read()
                del state
                qd = q0 + AMP * math.sin(W * k * period)
                await r.command(JointCommand("position", qd.tolist()))
                await clock.sleep(period)

        try:
            await cycles(0, warmup)
            ticks0 = r.ticks
            if profiler is not None:
                profiler.enable()
            t0 = time.perf_counter()
            c0 = time.process_time()
            await cycles(warmup, warmup + n)
            wall = time.perf_counter() - t0
            cpu = time.process_time() - c0
            if profiler is not None:
                profiler.disable()
        except SafetyError as exc:
            if profiler is not None:
                profiler.disable()
            raise _Stalled(f"{robot} {backend}: {exc}") from exc
        _check_stall(r, f"{robot} {backend}")
        ticks = r.ticks - ticks0
        final = (await r.read()).position.copy()
    return wall, cpu, final, ticks


async def _sdk_hold(backend: str, robot: str, sim_seconds: float) -> tuple[float, float]:
    """(sim seconds, wall seconds) of holding the initial pose for ``sim_seconds``."""
    import agentsdk
    from agentsdk import JointCommand

    async with agentsdk.connect(backend, robot) as r:
        clock = r.clock
        await r.command(JointCommand("position", (await r.read()).position.tolist()))
        s0 = clock.now()
        t0 = time.perf_counter()
        await clock.sleep(sim_seconds)
        wall = time.perf_counter() - t0
        _check_stall(r, f"{robot} {backend} hold")
        return clock.now() - s0, wall


async def _sdk_track(backend: str, robot: str, traj: Any, tail: float) -> tuple[float, float, str, np.ndarray]:
    """(sim s, wall s, motion result, final positions) of following ``traj`` (planned beforehand), plus ``tail``."""
    import agentsdk

    async with agentsdk.connect(backend, robot) as r:
        clock = r.clock
        s0 = clock.now()
        t0 = time.perf_counter()
        motion = r.follow(traj)
        await clock.sleep(traj.duration + tail)
        wall = time.perf_counter() - t0
        sim = clock.now() - s0
        _check_stall(r, f"{robot} {backend} track")
        res = motion.result().code.name if motion.done() else "RUNNING"
        return sim, wall, res, (await r.read()).position.copy()


#: the SDK runs and their stall check, for the other benchmarks that time them the same way (bench/anchors.py)
run_sdk, sdk_hold, sdk_track, check_stall = _run_sdk, _sdk_hold, _sdk_track, _check_stall


def waypoints(rb: _Robot, target_duration: float, seed: int = 1) -> tuple[np.ndarray, Any]:
    """Fixed-seed random waypoints in the middle of the joint ranges until the plan lasts ~target_duration."""
    from agentsdk.trajectory import plan

    rng = np.random.default_rng(seed)
    lo = np.array([j.lower if math.isfinite(j.lower) else -1.0 for j in rb.joints])
    hi = np.array([j.upper if math.isfinite(j.upper) else 1.0 for j in rb.joints])
    q0 = np.zeros(len(rb.joints))
    for name, q in rb.config.initial_positions.items():
        names = [j.name for j in rb.joints]
        if name in names:
            q0[names.index(name)] = q
    wps: list[np.ndarray] = []
    for _ in range(100):
        wps.append(lo + (hi - lo) * (0.3 + 0.4 * rng.random(len(lo))))
        wps_arr = np.array(wps)
        # 1 % below the limits: plan() at the full limits can exceed them by float noise (~1e-4 relative
        # in the interpolated acceleration), which follow()'s check (1e-6) rejects
        traj = plan(wps_arr, rb.joints, start=(q0, None, None), velocity_scale=0.99, acceleration_scale=0.99)
        if traj.duration >= target_duration:
            break
    return np.array(wps), traj


# =========================================================================== profile


def _profile_tables(prof: cProfile.Profile, cycles: int, label: str, top: int = 10) -> tuple[Table, Table, float]:
    st = pstats.Stats(prof)
    total = st.total_tt  # type: ignore[attr-defined]
    stats: dict[Any, Any] = st.stats  # type: ignore[attr-defined]
    sdk_rows, other_rows = [], []
    for (path, line, func), (_cc, nc, tt, ct, _callers) in stats.items():
        entry = (tt, nc, ct, path, line, func)
        if path.startswith(_SDK_DIRS):
            sdk_rows.append(entry)
        else:
            other_rows.append(entry)
    sdk_total = sum(e[0] for e in sdk_rows)

    def rows(entries: list[tuple[Any, ...]]) -> list[list[Any]]:
        out = []
        for tt, nc, ct, path, line, func in sorted(entries, key=lambda e: -e[0])[:top]:
            where = (
                f"{os.path.relpath(path, _REPO)}:{line}"
                if path.startswith(str(_REPO))
                else (path if path == "~" else os.path.basename(path) + f":{line}")
            )
            name = func if path != "~" else func.strip("<>")
            out.append(
                [
                    f"{name}  ({where})" if path != "~" else name,
                    fmt(tt / cycles * 1e6),
                    fmt(ct / cycles * 1e6),
                    fmt(nc / cycles),
                    f"{100 * tt / total:.1f}%",
                ]
            )
        return out

    headers = ("function (file:line)", "self µs/cycle", "cum µs/cycle", "calls/cycle", "% of total")
    t1 = Table(
        f"cProfile {label}: top {top} self-time functions in agentsdk/ and backends/ "
        f"({fmt(sdk_total / cycles * 1e6)} of {fmt(total / cycles * 1e6)} µs/cycle profiled)",
        headers,
        rows(sdk_rows),
    )
    t2 = Table(
        f"cProfile {label}: top {top} self-time outside agentsdk/backends (asyncio, numpy, simulator, ...)",
        headers,
        rows(other_rows),
    )
    return t1, t2, total / cycles * 1e6


# =========================================================================== sections


def _note_stalls(sec: Section, since: int) -> None:
    new = STALLS[since:]
    sec.data["stall_watchdog_redone_runs"] = new
    if new:
        sec.notes.append(
            f"the SDK's stall watchdog (stall_timeout 0.25 s) latched an e-stop in {len(new)} SDK run(s) because "
            "the event loop's heartbeat was late by that much (most likely the overloaded machine: see the load "
            "average); "
            "those runs were discarded and redone."
        )


def run_overhead(quick: bool = False, profile: bool = True) -> Section:
    n_stalls = len(STALLS)
    cycles = 1000 if quick else 3000
    warmup = 100 if quick else 200
    repeats = 3 if quick else 5
    sec = Section(
        "overhead",
        f"SDK overhead per control cycle (read + command through the safety layer + lockstep tick), "
        f"median of {repeats} x {cycles} cycles",
    )
    detail: list[list[Any]] = []
    cpu_rows: list[Comparison] = []
    for robot in ROBOTS:
        rb = load_robot(robot)
        for backend in BACKENDS:
            progress(f"overhead: {robot} on {backend} ({repeats} x {cycles} cycles, raw and SDK)")
            raw_us: list[float] = []
            sdk_us: list[float] = []
            raw_cpu: list[float] = []
            sdk_cpu: list[float] = []
            expl_us: list[float] = []
            dq = math.nan
            ticks_per_cycle = math.nan
            for rep in range(repeats):
                order = ("raw", "sdk") if rep % 2 == 0 else ("sdk", "raw")
                for which in order:
                    if which == "raw":
                        sim = _raw(backend, rb)
                        try:
                            q0 = sim.positions()
                            sim.run_wave(q0, 0, warmup)
                            c0 = time.process_time()
                            raw_us.append(sim.run_wave(q0, warmup, cycles) / cycles * 1e6)
                            raw_cpu.append((time.process_time() - c0) / cycles * 1e6)
                            raw_final = sim.positions()
                        finally:
                            sim.close()
                    else:
                        wall, cpu, sdk_final, ticks = _run_sdk(
                            f"overhead {robot} {backend}", _sdk_wave, backend, robot, warmup, cycles
                        )
                        sdk_us.append(wall / cycles * 1e6)
                        sdk_cpu.append(cpu / cycles * 1e6)
                        ticks_per_cycle = ticks / cycles
                if rep == 0:
                    dq = float(np.max(np.abs(sdk_final - raw_final)))
                if backend == "pybullet":
                    sim = RawPybullet(rb, implicit=False)
                    try:
                        q0 = sim.positions()
                        sim.run_wave(q0, 0, warmup)
                        expl_us.append(sim.run_wave(q0, warmup, cycles) / cycles * 1e6)
                    finally:
                        sim.close()
            raw_m, sdk_m = median(raw_us), median(sdk_us)
            sec.comparisons.append(
                Comparison(
                    f"{robot} {backend}: time per control cycle",
                    "µs",
                    raw_m,
                    sdk_m,
                    baseline_label=f"raw {backend}",
                    diff_target=OVERHEAD_TARGET_US,
                    extra={"raw_us": spread(raw_us), "sdk_us": spread(sdk_us)},
                )
            )
            cpu_rows.append(
                Comparison(
                    f"{robot} {backend}: CPU time per control cycle",
                    "µs",
                    median(raw_cpu),
                    median(sdk_cpu),
                    baseline_label=f"raw {backend}",
                    diff_target=OVERHEAD_TARGET_US,
                    extra={"raw_cpu_us": spread(raw_cpu), "sdk_cpu_us": spread(sdk_cpu)},
                )
            )
            detail.append(
                [
                    f"{robot} {backend}",
                    len(rb.joints),
                    f"{fmt(min(raw_us))}-{fmt(max(raw_us))}",
                    f"{fmt(min(sdk_us))}-{fmt(max(sdk_us))}",
                    fmt(median(raw_cpu)),
                    fmt(median(sdk_cpu)),
                    fmt(median(sdk_cpu) - median(raw_cpu)),
                    fmt(ticks_per_cycle),
                    f"{dq:.2g}",
                ]
            )
            sec.data[f"{robot}/{backend}"] = {
                "joints": len(rb.joints),
                "control_period_s": rb.period,
                "cycles": cycles,
                "repeats": repeats,
                "raw_us": raw_us,
                "sdk_us": sdk_us,
                "raw_cpu_us": raw_cpu,
                "sdk_cpu_us": sdk_cpu,
                "overhead_cpu_us": median(sdk_cpu) - median(raw_cpu),
                "overhead_us": sdk_m - raw_m,
                "ticks_per_cycle": ticks_per_cycle,
                "final_position_max_abs_diff_rad": dq,
                **({"raw_explicit_pd_us": expl_us} if expl_us else {}),
            }
            if expl_us:
                sec.data[f"{robot}/{backend}"]["implicit_damping_cost_us"] = raw_m - median(expl_us)
    sec.tables.append(
        Table(
            "detail: wall-time spread over the repeats; process CPU time per cycle (less sensitive to other load "
            "on the machine; includes the SDK's watchdog thread); same-control check (final joint positions)",
            (
                "robot backend",
                "joints",
                "raw µs range",
                "SDK µs range",
                "raw CPU µs",
                "SDK CPU µs",
                "CPU overhead µs",
                "ticks/cycle",
                "max |Δq| rad",
            ),
            detail,
        )
    )
    expl_rows = [
        [
            k,
            fmt(median(v["raw_explicit_pd_us"])),
            fmt(median(v["raw_us"])),
            fmt(median(v["raw_us"]) - median(v["raw_explicit_pd_us"])),
        ]
        for k, v in sec.data.items()
        if "raw_explicit_pd_us" in v
    ]
    if expl_rows:
        sec.tables.append(
            Table(
                "raw PyBullet: explicit PD vs the backend's implicit-damping PD (physics-side cost, not SDK overhead)",
                ("robot backend", "explicit µs/cycle", "implicit µs/cycle", "implicit cost µs"),
                expl_rows,
            )
        )
    wall_rows = list(sec.comparisons)
    sec.comparisons += cpu_rows
    for what, rows in (("wall-clock", wall_rows), ("CPU-time", cpu_rows)):
        over = [c.diff for c in rows if c.diff is not None]
        met = [c for c in rows if c.target_met]
        if over:
            sec.notes.append(
                f"target overhead < {OVERHEAD_TARGET_US:g} µs per cycle ({what}): met on {len(met)} of {len(rows)} "
                f"configurations (overhead {fmt(min(over))} .. {fmt(max(over))} µs)."
            )
    sec.notes.append(
        "wall-clock rows are what a loop sees; CPU-time rows (process_time, all threads of the process) are the "
        "cost itself and barely move when other processes compete for the cores. Ratios hold either way; the "
        "wall-clock differences grow with the machine's load (see the load average on the machine line)."
    )
    sec.notes.append(
        "overhead = SDK - raw: everything the SDK adds per cycle (JointCommand validation, Robot.read/command, "
        "safety limit/filter/tick hook, the lockstep clock and loop hand-off through asyncio, the backends' "
        "divergence checks, the stall-watchdog thread). The raw loops read the same state, compute the same "
        "servo law and step the same model; max |Δq| shows both ran the same control (0 = bit-identical)."
    )
    sec.notes.append("SDK commands are passed as a full-length list (JointCommand('position', q.tolist())).")

    if profile:
        for backend in BACKENDS:
            robot = "arm3"
            progress(f"overhead: cProfile of the SDK cycle, {robot} on {backend}")
            n = 1000 if quick else 2000
            for _attempt in range(3):
                # thread CPU time: the profile does not count time the process spends descheduled
                prof = cProfile.Profile(time.thread_time)
                try:
                    asyncio.run(_sdk_wave(backend, robot, warmup, n, profiler=prof))
                    break
                except _Stalled as exc:
                    STALLS.append(str(exc))
            t1, t2, total = _profile_tables(prof, n, f"{robot} {backend}")
            sec.tables += [t1, t2]
            sec.data[f"profile/{robot}/{backend}"] = {
                "profiled_us_per_cycle": total,
                "sdk_top": t1.rows,
                "other_top": t2.rows,
            }
        sec.notes.append(
            "the profiles use the loop thread's CPU time (time.thread_time); cProfile inflates Python-call costs "
            "(profiled µs/cycle > unprofiled), so use them for ranking, not as absolute figures."
        )
    _note_stalls(sec, n_stalls)
    return sec


def run_rtf(quick: bool = False) -> Section:
    n_stalls = len(STALLS)
    sim_s = 2.0 if quick else 10.0
    repeats = 1 if quick else 3
    tail = 0.5
    sec = Section(
        "rtf",
        f"lockstep real-time factor (sim time / wall time), ~{sim_s:g} s simulated, median of {repeats}",
    )
    detail: list[list[Any]] = []
    for robot in ROBOTS:
        rb = load_robot(robot)
        wps, traj = waypoints(rb, sim_s - tail)
        # the setpoints the SDK's trajectory executor writes, tick by tick (precomputed for the raw loop)
        from agentsdk.trajectory import TrajectorySampler

        q_init = _raw("mujoco", rb).positions()
        ticks_track = round((traj.duration + tail) / rb.period)
        sampler = TrajectorySampler(traj, 0.0, q_init, np.zeros(len(q_init)), np.zeros(len(q_init)))
        qd = np.empty((ticks_track, len(q_init)))
        vd = np.empty_like(qd)
        for k in range(ticks_track):
            q, v, _a = sampler.sample(k * rb.period)
            qd[k], vd[k] = q, v
        ticks_hold = round(sim_s / rb.period)
        hold_q = np.repeat(q_init[None, :], ticks_hold, axis=0)
        hold_v = np.zeros_like(hold_q)
        for backend in BACKENDS:
            progress(f"rtf: {robot} on {backend} (hold {sim_s:g} s, track {traj.duration + tail:.1f} s) x {repeats}")
            res: dict[str, list[float]] = {k: [] for k in ("raw_hold", "sdk_hold", "raw_track", "sdk_track", "phys")}
            results: list[str] = []
            dq = 0.0
            for _ in range(repeats):
                sim = _raw(backend, rb)
                try:
                    res["raw_hold"].append(ticks_hold * rb.period / sim.run_setpoints(hold_q, hold_v))
                finally:
                    sim.close()
                s, w = _run_sdk(f"rtf {robot} {backend} hold", _sdk_hold, backend, robot, sim_s)
                res["sdk_hold"].append(s / w)
                sim = _raw(backend, rb)
                try:
                    res["raw_track"].append(ticks_track * rb.period / sim.run_setpoints(qd, vd))
                    raw_final = sim.positions()
                finally:
                    sim.close()
                s, w, code, sdk_final = _run_sdk(f"rtf {robot} {backend} track", _sdk_track, backend, robot, traj, tail)
                dq = max(dq, float(np.max(np.abs(sdk_final - raw_final))))
                res["sdk_track"].append(s / w)
                results.append(code)
                if isinstance(sim, RawMujoco):
                    sim = RawMujoco(rb)
                    sim.data.ctrl[:] = sim.kp * sim.positions()
                    res["phys"].append(ticks_hold * rb.period / sim.run_physics_only(ticks_hold))
            for scen, what in (("hold", "holding a pose"), ("track", "tracking a trajectory")):
                sec.comparisons.append(
                    Comparison(
                        f"{robot} {backend}: real-time factor, {what}",
                        "x real time",
                        median(res[f"raw_{scen}"]),
                        median(res[f"sdk_{scen}"]),
                        baseline_label=f"raw {backend}",
                        lower_is_better=False,
                        extra={"raw": spread(res[f"raw_{scen}"]), "sdk": spread(res[f"sdk_{scen}"])},
                    )
                )
            detail.append(
                [
                    f"{robot} {backend}",
                    fmt(median(res["phys"])) if res["phys"] else "-",
                    f"{traj.duration:.2f}",
                    len(wps),
                    ",".join(sorted(set(results))),
                    f"{dq:.2g}",
                ]
            )
            sec.data[f"{robot}/{backend}"] = {
                "sim_seconds_hold": sim_s,
                "trajectory_seconds": traj.duration,
                "waypoints": len(wps),
                "track_results": results,
                "track_final_position_max_abs_diff_rad": dq,
                **{k: v for k, v in res.items() if v},
            }
    sec.tables.append(
        Table(
            "detail (physics-only = all MuJoCo steps in one mj_step call, constant ctrl: the simulator's ceiling; "
            "track max |Δq| = final joint positions SDK vs raw: same setpoints, same physics)",
            (
                "robot backend",
                "physics-only RTF",
                "trajectory s",
                "waypoints",
                "SDK motion result",
                "track max |Δq| rad",
            ),
            detail,
        )
    )
    sec.notes.append(
        "hold: SDK = one command then robot.clock.sleep(T) (only the control loop runs); raw = the same hold "
        "setpoint every cycle. track: SDK = robot.follow(plan(...)) then sleep until the end + "
        f"{tail:g} s; raw = the same per-tick setpoints (sampled beforehand, as the trajectory executor samples "
        "them) written every cycle."
    )
    sec.notes.append(
        "SDK rows run as a plain connect does: in lockstep with block lockstep on (the default on MuJoCo and "
        "PyBullet; uneventful ticks as blocks, bit for bit tick by tick); `--only block` compares blocks with "
        "tick by tick."
    )
    _note_stalls(sec, n_stalls)
    return sec


def run(quick: bool = False) -> list[Section]:
    return [run_overhead(quick), run_rtf(quick)]


if __name__ == "__main__":
    import sys

    for s in run("--quick" in sys.argv):
        print(s.render())
        print()
