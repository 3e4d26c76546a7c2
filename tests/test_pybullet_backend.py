"""PyBullet backend: torque control really is torque control, isolation, determinism, MuJoCo agreement."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pybullet as p
import pytest

import agentsdk
from agentsdk import ConfigurationError, JointCommand, SafetyFault, SimulationDiverged
from agentsdk.backends.pybullet import PybulletController
from agentsdk.description import apply_overrides, resolve_robot
from agentsdk.loop import Setpoint

pytestmark = pytest.mark.asyncio


def _mujoco_dynamics(urdf_xml: str, positions: dict[str, float]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Full mass matrix and bias forces (gravity at rest) of the same URDF, computed by MuJoCo."""
    model = mujoco.MjSpec.from_string(urdf_xml).compile()
    data = mujoco.MjData(model)
    names = [model.joint(i).name for i in range(model.njnt)]
    for name, q in positions.items():
        data.qpos[model.jnt_qposadr[model.joint(name).id]] = q
    mujoco.mj_forward(model, data)
    mass = np.zeros((model.nv, model.nv))
    if hasattr(data, "qM"):  # MuJoCo 3.x
        mujoco.mj_fullM(model, mass, data.qM)
    else:  # MuJoCo 4: mj_fullM(m, d, dst)
        mujoco.mj_fullM(model, data, mass)
    return mass, data.qfrc_bias.copy(), names


async def _hold(robot: agentsdk.Robot, pose: dict[str, float], settle: float = 1.0) -> agentsdk.JointState:
    await robot.command(JointCommand("position", pose))
    await robot.clock.sleep(settle)
    return await robot.read()


# --------------------------------------------------------------------------- effort mode


@pytest.mark.parametrize("effort", ["small", "against_gravity"])
async def test_effort_mode_accelerates_as_physics_predicts(effort: str) -> None:
    """Default PyBullet velocity motors are off: a joint in effort mode obeys (tau + g_comp - tau_g) / I.

    Gravity compensation (on by default) adds g(q) to the commanded effort, so the net
    acceleration is tau / I and the reported effort is tau + g(q), as on a Franka or a Kinova.
    """
    async with agentsdk.connect("pybullet", robot="arm3") as robot:
        st0 = await _hold(robot, {"joint1": 0.0, "joint2": 0.5, "joint3": 0.0})
        j2 = st0.index("joint2")
        assert abs(st0.position[j2] - 0.5) < 0.01
        assert abs(st0.velocity[j2]) < 1e-6

        # reference dynamics from MuJoCo at the same pose (joint-space inertia and gravity torque)
        mass, bias, names = _mujoco_dynamics(robot.backend.description.urdf_xml, st0.positions())
        k = names.index("joint2")
        inertia, tau_gravity = mass[k, k], -bias[k]  # generalized gravity force at rest
        assert tau_gravity > 0.5  # tipped towards +x: gravity pulls joint2 further positive
        assert robot.gravity_compensation["joint2"]
        tau = -1.0 if effort == "small" else -(tau_gravity + 3.0)
        expected = tau / inertia  # the servo law's g(q) cancels gravity

        applied = await robot.command(JointCommand("effort", {"joint2": tau}))
        assert applied.values["joint2"] == pytest.approx(tau)
        dt = 0.01
        await robot.clock.sleep(dt)
        st1 = await robot.read()
        measured = (st1.velocity[j2] - st0.velocity[j2]) / dt

        assert math.copysign(1.0, measured) == math.copysign(1.0, expected)
        assert measured == pytest.approx(expected, rel=0.1)  # observed: within ~1%
        # the effort reported is the commanded torque plus the gravity compensation; the other joints still hold
        assert st1.effort[j2] == pytest.approx(tau - tau_gravity, rel=0.02)
        others = [i for i in range(len(st1.names)) if i != j2]
        assert np.abs(st1.position[others] - st0.position[others]).max() < 1e-3


async def test_effort_mode_constant_torque_drives_the_joint() -> None:
    """A torque larger than gravity, held for a while, moves the joint the way it pushes."""
    async with agentsdk.connect("pybullet", robot="arm3") as robot:
        st0 = await _hold(robot, {"joint2": 0.5})
        j2 = st0.index("joint2")
        for _ in range(4):  # keep feeding the effort watchdog
            await robot.command(JointCommand("effort", {"joint2": -4.0}))
            await robot.clock.sleep(0.05)
        st1 = await robot.read()
        assert st1.position[j2] < st0.position[j2] - 0.2
        assert st1.velocity[j2] < -1.0


# --------------------------------------------------------------------------- isolation, determinism


async def _trajectory(robot: agentsdk.Robot, pose: dict[str, float], mode: str = "position") -> np.ndarray:
    out = []
    await robot.command(JointCommand(mode, pose))  # type: ignore[arg-type]
    for _ in range(25):
        await robot.clock.sleep(0.02)
        out.append((await robot.read()).position.copy())
    return np.array(out)


def _controller() -> PybulletController:
    config, description = resolve_robot("arm3")
    return PybulletController.create(config, description, apply_overrides(description, config))


async def _drive(ctls: list[PybulletController], poses: list[dict[str, float]], ticks: int = 250) -> list[np.ndarray]:
    """Run the backends' own hooks (write -> step -> read) by hand, interleaving the backends."""
    setpoints = []
    for ctl, pose in zip(ctls, poses, strict=True):
        await ctl._open()
        sp = Setpoint(len(ctl.joints))
        sp.position[:] = ctl._read()[0]
        for name, q in pose.items():
            sp.position[ctl.index[name]] = q
        sp.kp[:] = [ctl.config.gains_for(j.name).p for j in ctl.joints]
        sp.kd[:] = [ctl.config.gains_for(j.name).d for j in ctl.joints]
        setpoints.append(sp)
    assert len({ctl._cid for ctl in ctls}) == len(ctls)  # one physics client each
    out: list[list[np.ndarray]] = [[] for _ in ctls]
    try:
        for _ in range(ticks):
            for k, ctl in enumerate(ctls):
                ctl._write(setpoints[k].view)
                await ctl._step(ctl.period)
                out[k].append(ctl._read()[0].copy())
    finally:
        for ctl in ctls:
            await ctl._close()
    return [np.array(o) for o in out]


async def test_two_robots_in_one_process_do_not_interfere() -> None:
    """Each controller owns its physics client: interleaved stepping gives the solo results bit for bit."""
    pose_a = {"joint1": 0.7, "joint2": 0.6, "joint3": -1.0}
    pose_b = {"joint1": -0.9, "joint2": -0.4, "joint3": 1.2}
    (solo_a,) = await _drive([_controller()], [pose_a])
    (solo_b,) = await _drive([_controller()], [pose_b])
    a, b = _controller(), _controller()
    both_a, both_b = await _drive([a, b], [pose_a, pose_b])

    np.testing.assert_array_equal(both_a, solo_a)
    np.testing.assert_array_equal(both_b, solo_b)
    assert np.abs(both_a[-1] - list(pose_a.values())).max() < 0.01
    assert np.abs(both_b[-1] - list(pose_b.values())).max() < 0.01


async def test_two_connected_robots_keep_their_own_state() -> None:
    """The same through connect(): two arms in one event loop, opposite commands."""
    async with agentsdk.connect("pybullet", robot="arm3") as a, agentsdk.connect("pybullet", robot="arm3") as b:
        await a.command(JointCommand("position", {"joint1": 0.5}))
        await b.command(JointCommand("position", {"joint1": -0.5}))
        await a.clock.sleep(0.05)
        await b.clock.sleep(0.05)
        sa, sb = await a.read(), await b.read()
    assert sa.position[0] > 0.01
    assert sb.position[0] < -0.01
    np.testing.assert_allclose(sa.position, -sb.position, atol=1e-9)


async def _scripted_run() -> np.ndarray:
    async with agentsdk.connect("pybullet", robot="arm3") as robot:
        out = [await _trajectory(robot, {"joint1": 0.5, "joint2": 0.8})]
        out.append(await _trajectory(robot, {"joint3": 2.0}, mode="velocity"))
        out.append(await _trajectory(robot, {"joint2": -1.0}, mode="effort"))
        await robot.move_to({"joint1": -0.3, "joint2": 0.2, "joint3": 0.0}, duration=None)
        out.append((await robot.read()).position.reshape(1, -1))
        return np.concatenate(out)


async def test_lockstep_is_deterministic() -> None:
    assert PybulletController.capabilities.deterministic
    first = await _scripted_run()
    second = await _scripted_run()
    assert first.tobytes() == second.tobytes()


# --------------------------------------------------------------------------- configuration


async def test_period_not_a_multiple_of_the_timestep_is_a_configuration_error() -> None:
    with pytest.raises(ConfigurationError, match=r"0\.002.*0\.0015"):
        async with agentsdk.connect("pybullet", robot="arm3", timestep=0.0015):
            pass


async def test_options_are_validated(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ConfigurationError, match="no_such_option"):
        async with agentsdk.connect("pybullet", robot="arm3", no_such_option=1):
            pass
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(ConfigurationError, match="display"):
        async with agentsdk.connect("pybullet", robot="arm3", gui=True):
            pass


async def test_timestep_from_robot_yaml_section() -> None:
    async with agentsdk.connect("pybullet", robot="arm3", timestep=0.0005) as robot:
        ctl = robot.backend
        assert ctl._nsub == 4  # type: ignore[attr-defined]
        assert p.getPhysicsEngineParameters(physicsClientId=ctl._cid)["fixedTimeStep"] == 0.0005  # type: ignore[attr-defined]


async def test_close_is_idempotent_and_safe_without_open() -> None:
    config, description = resolve_robot("arm3")
    ctl = PybulletController.create(config, description, apply_overrides(description, config))
    await ctl._close()  # never opened
    await ctl._open()
    cid = ctl._cid
    assert p.isConnected(physicsClientId=cid)
    await ctl._close()
    await ctl._close()
    assert not p.isConnected(physicsClientId=cid)


# --------------------------------------------------------------------------- robots, stops, faults


async def test_humanoid_holds_its_initial_pose() -> None:
    async with agentsdk.connect("pybullet", robot="humanoid") as robot:
        start = await robot.read()
        await robot.clock.sleep(2.0)
        st = await robot.read()
        assert st.stamp == pytest.approx(2.0)
        err = np.abs(st.position - start.position)
        assert err.max() < 0.02, dict(zip(st.names, err.round(4).tolist(), strict=True))


async def test_estop_category0_removes_torque_and_enable_restores_it() -> None:
    async with agentsdk.connect("pybullet", robot="arm3") as robot:
        st0 = await _hold(robot, {"joint2": 0.5})
        j2 = st0.index("joint2")
        robot.estop_threadsafe(0)
        await robot.clock.sleep(0.1)
        st1 = await robot.read()
        assert np.all(st1.effort == 0.0)
        assert st1.position[j2] > st0.position[j2] + 0.05  # falls under gravity
        await robot.reset()
        await robot.enable()
        held = (await robot.read()).position[j2]
        await robot.clock.sleep(0.5)
        st2 = await robot.read()
        assert abs(st2.position[j2] - held) < 0.05
        assert abs(st2.velocity[j2]) < 0.05


async def test_divergence_faults_and_recover_resets_the_world() -> None:
    async with agentsdk.connect("pybullet", robot="arm3") as robot:
        await _hold(robot, {"joint2": 0.5}, settle=0.2)
        ctl = robot.backend
        # corrupt the physics state the way an exploding simulation would
        p.resetJointState(ctl._body, ctl._dofs[1], 0.5, 1e6, physicsClientId=ctl._cid)  # type: ignore[attr-defined]
        with pytest.raises(SimulationDiverged, match="diverged"):
            await robot.clock.sleep(0.01)
        with pytest.raises(SafetyFault, match="diverged"):
            await robot.read()
        await robot.reset()
        st = await robot.read()
        np.testing.assert_allclose(st.position, 0.0, atol=1e-12)
        await robot.enable()
        await robot.clock.sleep(0.2)
        assert np.abs((await robot.read()).position).max() < 0.01


async def test_matches_mujoco_for_the_same_command() -> None:
    pose = {"joint1": 0.8, "joint2": 0.9, "joint3": 1.0}
    runs = {}
    for backend in ("mujoco", "pybullet"):
        async with agentsdk.connect(backend, robot="arm3") as robot:
            runs[backend] = await _trajectory(robot, pose)
    # transient within a few mrad, steady state identical to ~1e-6
    assert np.abs(runs["mujoco"] - runs["pybullet"]).max() < 0.01
    np.testing.assert_allclose(runs["mujoco"][-1], runs["pybullet"][-1], atol=1e-5)


async def test_stiff_damping_on_a_light_link_stays_stable_like_mujoco() -> None:
    """Damping is integrated implicitly (as MuJoCo's implicitfast does).

    joint3 carries only the 0.3 kg end-effector sphere (I ~ 2e-4 kg·m²): with 0.5 N·m·s/rad of
    joint damping an explicit step has damping*dt/I ~ 2.6 > 2 and would blow up within a few ms.
    """
    pose = {"joint2": 0.5, "joint3": 1.0}
    final = {}
    for backend in ("mujoco", "pybullet"):
        async with agentsdk.connect(backend, robot="arm3", joint_damping=0.5) as robot:
            await robot.command(JointCommand("position", pose))
            await robot.clock.sleep(1.0)
            final[backend] = (await robot.read()).position
    np.testing.assert_allclose(final["pybullet"], final["mujoco"], atol=1e-3)
    assert final["pybullet"][2] == pytest.approx(1.0, abs=1e-3)
