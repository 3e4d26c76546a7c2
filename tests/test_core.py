"""Issue 2 acceptance: core API, descriptions, MuJoCo backend end to end."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import numpy as np
import pytest

import agentsdk
from agentsdk import JointCommand
from agentsdk.cli import main as cli_main
from agentsdk.cli import run_behavior

BEHAVIORS = Path(__file__).resolve().parents[1] / "behaviors"
FIXTURES = Path(__file__).parent / "fixtures"


def _record_positions(robot: agentsdk.Robot, out: list[np.ndarray]) -> None:
    robot.add_tick_hook(agentsdk.Phase.OBSERVE, lambda t, st, sp: out.append(st.position.copy()))


async def test_wave_reaches_last_target_in_lockstep() -> None:
    from agentsdk.behaviors.wave import POSES
    from agentsdk.behaviors.wave import main as wave

    summary = await run_behavior(wave, backend="mujoco", robot="arm3")
    assert summary.sim_time == pytest.approx(1.5 * len(POSES))
    assert set(summary.errors) == {"joint1", "joint2", "joint3"}
    for name, err in summary.errors.items():
        assert abs(err) < 0.01, f"{name} ended {err:+.4f} rad from its last target"


async def test_lockstep_runs_are_bit_identical() -> None:
    from agentsdk.behaviors.wave import main as wave

    runs: list[list[np.ndarray]] = []
    for _ in range(2):
        rec: list[np.ndarray] = []
        await run_behavior(wave, backend="mujoco", robot="arm3", on_robot=lambda r, rec=rec: _record_positions(r, rec))
        runs.append(rec)
    assert len(runs[0]) == len(runs[1]) > 1000
    assert all(np.array_equal(a, b) for a, b in zip(*runs, strict=True))


def test_cli_run_prints_summary(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["run", str(BEHAVIORS / "wave.py")]) == 0
    out = capsys.readouterr().out
    assert "real-time factor" in out and "final joint errors" in out


async def test_package_mesh_robot_loads_and_simulates(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AGENTSDK_PACKAGE_PATH", str(FIXTURES))
    urdf = FIXTURES / "mesh_pkg" / "urdf" / "mesh_arm.urdf"
    async with agentsdk.connect("mujoco", robot=urdf) as robot:
        assert any(p.suffix == ".stl" for p in robot.backend.description.mesh_files)
        assert robot.backend.model.nmesh >= 1  # the mesh really is in the simulation
        first = robot.joints[0].name
        await robot.command(JointCommand("position", {first: 0.3}))
        await robot.clock.sleep(1.0)
        st = await robot.read()
        assert abs(st.position[0] - 0.3) < 0.02


async def test_a_read_state_is_read_only_and_keeps_what_it_read() -> None:
    """A state the user holds never changes under them: read-only arrays of its own, not the loop's."""
    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        held = await robot.read()
        copies = [held.position.copy(), held.velocity.copy(), held.effort.copy()]
        for arr in (held.position, held.velocity, held.effort):
            with pytest.raises(ValueError, match="read-only"):
                arr[0] = 1.0
            with pytest.raises(ValueError):
                arr.flags.writeable = True  # not even on purpose
        await robot.command(JointCommand("position", {robot.joints[0].name: 0.3}))
        await robot.clock.sleep(0.2)
        now = await robot.read()
        assert now.stamp > held.stamp and not np.array_equal(now.position, held.position)
        for arr, before in zip((held.position, held.velocity, held.effort), copies, strict=True):
            assert arr.tobytes() == before.tobytes()


@pytest.mark.parametrize("name", ["humanoid", "mit_leg"])
async def test_robot_holds_pose_in_mujoco(name: str) -> None:
    async with agentsdk.connect("mujoco", robot=name) as robot:
        start = (await robot.read()).position
        await robot.clock.sleep(2.0)
        st = await robot.read()
        assert np.abs(st.position - start).max() < 0.02, dict(zip(st.names, st.position - start, strict=True))
        assert np.abs(st.velocity).max() < 0.05


# ------------------------------------------------------------------ bad input
async def test_unknown_backend_lists_known_ones() -> None:
    with pytest.raises(agentsdk.BackendUnavailableError, match=r"unknown backend 'nope'.*mujoco"):
        async with agentsdk.connect("nope", robot="arm3"):
            pass


async def test_unknown_robot_lists_known_ones() -> None:
    with pytest.raises(agentsdk.ConfigurationError, match=r"arm3"):
        async with agentsdk.connect("mujoco", robot="no_such_robot"):
            pass


async def test_malformed_urdf(tmp_path: Path) -> None:
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'></robot>")
    with pytest.raises(agentsdk.DescriptionError, match=r"bad\.urdf"):
        async with agentsdk.connect("mujoco", robot=bad):
            pass


async def test_malformed_xacro(tmp_path: Path) -> None:
    bad = tmp_path / "bad.urdf.xacro"
    bad.write_text(
        '<robot name="x" xmlns:xacro="http://www.ros.org/wiki/xacro">'
        '<link name="a"><visual><geometry><box size="${undefined_size} 1 1"/></geometry></visual></link></robot>'
    )
    with pytest.raises(agentsdk.DescriptionError, match="undefined_size"):
        async with agentsdk.connect("mujoco", robot=bad):
            pass


@pytest.mark.parametrize(
    ("cmd", "exc", "match"),
    [
        (JointCommand("position", {"elbow": 0.1}), agentsdk.UnknownJointError, "elbow"),
        (JointCommand("position", {"joint1": math.nan}), agentsdk.InvalidValueError, "joint1"),
        (JointCommand("velocity", {"joint2": math.inf}), agentsdk.InvalidValueError, "joint2"),
        (JointCommand("position", [0.1, 0.2]), agentsdk.InvalidValueError, "expected 3 values"),
    ],
)
async def test_bad_command_rejected_state_unchanged(cmd: JointCommand, exc: type[Exception], match: str) -> None:
    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        await robot.command(JointCommand("position", {"joint1": 0.2}))
        await robot.clock.sleep(0.1)
        target = robot.command_targets()
        modes = robot.setpoint.mode.copy()
        with pytest.raises(exc, match=match):
            await robot.command(cmd)
        assert np.array_equal(robot.command_targets(), target)
        assert np.array_equal(robot.setpoint.mode, modes)
        # still usable
        await robot.command(JointCommand("position", {"joint1": 0.4}))
        await robot.clock.sleep(1.0)
        assert abs((await robot.read()).positions()["joint1"] - 0.4) < 0.01


async def test_unsupported_mode_rejected() -> None:
    with pytest.raises(agentsdk.UnsupportedModeError, match="torque"):
        JointCommand("torque", {"joint1": 1.0})  # type: ignore[arg-type]
    async with agentsdk.connect("mock", robot="arm3", modes=["position"]) as robot:
        with pytest.raises(agentsdk.UnsupportedModeError, match="velocity"):
            await robot.command(JointCommand("velocity", {"joint1": 0.1}))
        await robot.command(JointCommand("position", {"joint1": 0.1}))


async def test_unknown_backend_option_is_a_configuration_error() -> None:
    with pytest.raises(agentsdk.ConfigurationError, match="timestepp"):
        async with agentsdk.connect("mujoco", robot="arm3", timestepp=0.001):
            pass


async def test_period_must_be_multiple_of_timestep() -> None:
    with pytest.raises(agentsdk.ConfigurationError, match="multiple"):
        async with agentsdk.connect("mujoco", robot="arm3", timestep=0.0015):
            pass


PENDULUM = """<robot name="pendulum">
  <link name="base"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/>
  </inertial></link>
  <joint name="swing" type="revolute"><parent link="base"/><child link="bob"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" velocity="5" effort="1e12"/></joint>
  <link name="bob"><inertial><origin xyz="0 0 -0.3"/><mass value="0.1"/>
    <inertia ixx="1e-4" iyy="1e-4" izz="1e-4" ixy="0" ixz="0" iyz="0"/></inertial></link>
</robot>"""


async def test_simulation_divergence_is_a_clear_fault(tmp_path: Path) -> None:
    (tmp_path / "pendulum.urdf").write_text(PENDULUM)
    (tmp_path / "robot.yaml").write_text(
        "description: pendulum.urdf\nupdate_rate: 500\ngains: {default: {p: 1.0e9, d: 0.0}}\n"
        "safety: {max_position_step: null}\n"
    )
    async with agentsdk.connect("mujoco", robot=tmp_path / "robot.yaml") as robot:
        await robot.command(JointCommand("position", {"swing": 1.0}))
        with pytest.raises(agentsdk.SimulationDiverged, match="diverged"):
            await robot.clock.sleep(1.0)
        assert robot.safety.state is agentsdk.SafetyState.FAULT
        with pytest.raises(agentsdk.SafetyFault, match="diverged"):
            await robot.command(JointCommand("position", {"swing": 0.0}))


async def test_connect_can_be_awaited_and_closed_twice() -> None:
    robot = await agentsdk.connect("mock", robot="arm3")
    assert "arm3" in repr(robot)
    await robot.close()
    await robot.close()
    with pytest.raises(agentsdk.RobotClosedError):
        await robot.read()


async def test_clock_timeout_in_robot_time() -> None:
    async with agentsdk.connect("mock", robot="arm3") as robot:
        with pytest.raises(agentsdk.AgentTimeoutError):
            async with robot.clock.timeout(0.5):
                await robot.clock.sleep(2.0)
        assert robot.clock.now() == pytest.approx(0.5, abs=robot.control_period)
        assert isinstance(agentsdk.AgentTimeoutError("x"), TimeoutError)
        await asyncio.sleep(0)


def test_cli_user_errors_are_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["run", str(BEHAVIORS / "wave.py"), "--backend", "nope"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown backend 'nope'" in err[0]
    assert cli_main(["describe", "no_such_robot"]) == 2


def test_cli_describe_and_robots(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["describe", "arm3"]) == 0
    out = capsys.readouterr().out
    assert "joint1" in out and "revolute" in out
    assert cli_main(["robots"]) == 0
    out = capsys.readouterr().out
    for name in ("arm3", "humanoid", "mit_leg"):
        assert name in out
