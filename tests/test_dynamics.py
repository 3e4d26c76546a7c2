"""Issue 13: gravity compensation in the servo law, model-based gains, the start pose, the floating base.

Fast, deterministic (lockstep) checks on single robots; the corpus sweeps are in
tests/test_corpus_dynamics.py.
"""

from __future__ import annotations

import importlib.metadata
import logging
import math
from pathlib import Path

import numpy as np
import pytest

import agentsdk
from agentsdk import ConfigurationError
from agentsdk.description import apply_overrides, resolve_robot
from agentsdk.description.start import read_group_states, start_pose
from agentsdk.dynamics import DynamicsModel, model_gains


def corpus(path: str) -> Path:
    dist = importlib.metadata.distribution("example-robot-data")
    return Path(str(dist.locate_file("cmeel.prefix/share/example-robot-data/robots"))) / path


PANDA = corpus("panda_description/urdf/panda.urdf")
PENDULUM = corpus("double_pendulum_description/urdf/double_pendulum.urdf")
UR5 = corpus("ur_description/urdf/ur5_robot.urdf")


def robot_yaml(tmp_path: Path, urdf: Path, body: str = "") -> Path:
    path = tmp_path / "robot.yaml"
    path.write_text(f"description: {urdf}\n{body}", encoding="utf-8")
    return path


# --------------------------------------------------------------------------- model-based gains


def test_model_gains_formula() -> None:
    """kp = I w^2 (bandwidth), kd = 2 z sqrt(kp I); effort and timestep bounds apply in that order."""
    m = np.diag([0.5, 0.002])
    w = 2 * math.pi * 10.0
    r = model_gains(m, np.array([1000.0, 1000.0]), bandwidth=10.0, damping_ratio=1.0, timestep=None)
    assert r.kp == pytest.approx([0.5 * w * w, 0.002 * w * w])
    assert r.kd == pytest.approx(2 * np.sqrt(r.kp * np.diag(m)))
    assert r.bound == ("bandwidth", "bandwidth")
    # a weak motor: full effort at EFFORT_ERROR
    r = model_gains(m, np.array([0.5, 1000.0]), timestep=None)
    assert r.bound[0] == "effort" and r.kp[0] == pytest.approx(0.5 / 0.02)
    # a light joint with friction: the friction rule wants a stiff servo, the timestep bounds it
    r = model_gains(np.diag([1e-6]), np.array([100.0]), friction=np.array([1.0]), timestep=0.001)
    assert r.bound == ("timestep",)
    assert model_gains(np.diag([1e-6]), np.array([100.0]), friction=np.array([1.0]), timestep=None).bound == (
        "friction",
    )
    h, inertia, c = 0.001, 1e-6, r.kd[0]
    assert r.kp[0] * h * h <= 0.25 * (4 * inertia + 2 * h * c) * (1 + 1e-9)


def test_gravity_torque_matches_mujocos_own_urdf_import() -> None:
    """g(q) of the description's model equals mj_inverse at rest of a model MuJoCo compiles from the URDF itself."""
    import mujoco

    config, desc = resolve_robot(PENDULUM)
    model = DynamicsModel(desc, apply_overrides(desc, config))
    q = np.array([0.3, -0.2])
    tau = model.gravity(q)
    m = mujoco.MjSpec.from_string(desc.urdf_xml).compile()
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_inverse(m, d)
    assert tau == pytest.approx(d.qfrc_inverse, abs=1e-6)
    assert np.abs(tau).max() > 0.01  # the pendulum does weigh something


# --------------------------------------------------------------------------- start pose


def test_start_pose_clips_zero_into_the_limits_with_one_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    srdf = tmp_path / "no_states.srdf"  # an SRDF without group states: the joints start at 0, clipped
    srdf.write_text('<robot name="panda"/>')
    config, desc = resolve_robot(robot_yaml(tmp_path, PANDA, f"srdf: {srdf}\n"))
    start = start_pose(desc, config, apply_overrides(desc, config))
    assert start.clipped.keys() == {"panda_joint4"}  # 0 is outside [-3.0718, -0.0698]
    assert start.positions["panda_joint4"] == pytest.approx(-0.0698)
    assert start.sources["panda_joint1"] == "zero"
    with caplog.at_level(logging.WARNING, logger="agentsdk"):
        backend_warning = start.warning("panda")
    assert backend_warning is not None and "panda_joint4 0 -> -0.0698" in backend_warning


def test_start_pose_from_an_srdf_group_state(tmp_path: Path) -> None:
    states = read_group_states(PANDA.parent.parent / "srdf" / "panda.srdf")
    assert "default" in states
    config, desc = resolve_robot(robot_yaml(tmp_path, PANDA, "initial_group_state: default\n"
                                            "initial_positions: {panda_joint1: 0.3}\n"))
    start = start_pose(desc, config, apply_overrides(desc, config))
    assert start.positions["panda_joint1"] == 0.3 and start.sources["panda_joint1"] == "robot.yaml"
    assert start.positions["panda_joint2"] == pytest.approx(states["default"]["panda_joint2"])
    assert start.sources["panda_joint2"] == "srdf default"
    assert not start.clipped


def test_start_pose_from_the_srdf_beside_the_urdf_without_robot_yaml() -> None:
    """No initial_group_state: the SRDF found beside the URDF gives its `default` group state (issue 24)."""
    states = read_group_states(PANDA.parent.parent / "srdf" / "panda.srdf")
    config, desc = resolve_robot(PANDA)
    start = start_pose(desc, config, apply_overrides(desc, config))
    assert set(start.sources.values()) == {"srdf default"}
    assert start.positions["panda_joint4"] == pytest.approx(states["default"]["panda_joint4"])
    assert not start.clipped and "from SRDF group_state 'default'" in start.summary()


def test_unknown_group_state_names_the_known_ones(tmp_path: Path) -> None:
    config, desc = resolve_robot(robot_yaml(tmp_path, PANDA, "initial_group_state: nowhere\n"))
    with pytest.raises(ConfigurationError, match=r"no group_state 'nowhere'; its group states: default"):
        start_pose(desc, config)


@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
async def test_simulators_start_exactly_at_the_start_pose_without_a_jump(backend: str) -> None:
    async with agentsdk.connect(backend, robot=str(PANDA)) as robot:
        q0 = (await robot.read()).position
        expected = np.array([robot.backend.initial_positions[k] for k in range(len(q0))])
        assert q0 == pytest.approx(expected, abs=1e-9)
        # the SRDF's `default` group state (found beside the URDF), not 0 clipped to -0.0698
        assert q0[robot.joint_names.index("panda_joint4")] == pytest.approx(-2.35619, abs=1e-4)
        await robot.clock.sleep(0.2)
        st = await robot.read()
        assert np.abs(st.position - q0).max() < 1e-3
        assert np.abs(st.velocity).max() < 1e-2


# --------------------------------------------------------------------------- gravity compensation


@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
async def test_gravity_compensation_removes_the_sag(backend: str, tmp_path: Path) -> None:
    """Same model-based gains: with g(q) the arm holds; without it, it sags by about g/kp."""
    drift = {}
    for on in (True, False):
        yaml = robot_yaml(tmp_path, UR5, f"gravity_compensation: {str(on).lower()}\n"
                                         "initial_positions: {shoulder_lift_joint: -1.2, elbow_joint: 0.8}\n")
        async with agentsdk.connect(backend, robot=str(yaml)) as robot:
            assert all(robot.gravity_compensation.values()) is on
            q0 = (await robot.read()).position
            await robot.clock.sleep(1.0)
            drift[on] = float(np.abs((await robot.read()).position - q0).max())
    assert drift[True] < 0.001
    assert drift[False] > 10 * max(drift[True], 1e-4)


async def test_gravity_compensation_per_joint(tmp_path: Path) -> None:
    yaml = robot_yaml(tmp_path, UR5, "gravity_compensation: {default: true, elbow_joint: false}\n"
                                     "initial_positions: {shoulder_lift_joint: -1.2, elbow_joint: 0.8}\n")
    async with agentsdk.connect("mujoco", robot=str(yaml)) as robot:
        flags = robot.gravity_compensation
        assert not flags["elbow_joint"] and flags["shoulder_lift_joint"]
        q0 = (await robot.read()).position
        await robot.clock.sleep(1.0)
        moved = np.abs((await robot.read()).position - q0)
        names = robot.joint_names
        assert moved[names.index("elbow_joint")] > 0.002  # sags: nothing holds its weight but the gains


def test_gravity_compensation_names_unknown_joints(tmp_path: Path) -> None:
    yaml = robot_yaml(tmp_path, UR5, "gravity_compensation: {elbow: false}\n")
    with pytest.raises(ConfigurationError, match=r"gravity_compensation.elbow: unknown joint 'elbow'; did you mean"):
        resolve_robot(yaml)  # which runs check_config


# --------------------------------------------------------------------------- gains on the Robot


async def test_robot_shows_model_gains_and_keeps_robot_yaml_gains() -> None:
    async with agentsdk.connect("mujoco", robot=str(UR5)) as robot:
        gains = robot.gains
        report = robot.backend.model_gain_report
        assert [g.p for g in gains.values()] == pytest.approx(report.kp)
        assert [g.d for g in gains.values()] == pytest.approx(report.kd)
        assert all(g.p > 0 and g.d > 0 for g in gains.values())
    async with agentsdk.connect("mujoco", robot="arm3") as robot:  # shipped: tuned gains kept
        assert robot.gains["joint2"].p == 800.0 and robot.gains["joint2"].d == 10.0


async def test_fixed_base_state_is_the_identity_at_rest() -> None:
    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        base = robot.base_state()
        assert base.position.tolist() == [0.0, 0.0, 0.0]
        assert base.linear_velocity.tolist() == [0.0, 0.0, 0.0]
