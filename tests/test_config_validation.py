"""Every numeric configuration value is validated: robot.yaml, SafetyConfig, backend options (issue 10, items 3, 14).

A value is either rejected with one line per problem (file, key path, what was
expected, what was given, "did you mean") or the robot runs with every setpoint
finite and inside its limits. Regression tests for what fault injection found:
a negative ``max_position_step`` drove the robot by itself, a NaN ``min_position``
removed the URDF limit, ``update_rate: .inf`` hung the mock, infinite gains and
timeouts were accepted, MuJoCo zeroed a NaN control silently (``mjWARN_BADCTRL``).
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import agentsdk
from agentsdk import ConfigurationError, JointCommand
from agentsdk.config import format_value, load_robot_config
from agentsdk.loop import Phase
from agentsdk.safety import SafetyConfig

ROOT = Path(__file__).resolve().parents[1]
ARM3 = ROOT / "robots" / "arm3"
NAN, INF = math.nan, math.inf


def robot_yaml(tmp_path: Path, **fields: Any) -> Path:
    """arm3's robot.yaml with ``fields`` replaced (None deletes a key), written to ``tmp_path``."""
    cfg = yaml.safe_load((ARM3 / "robot.yaml").read_text())
    cfg["description"] = str(ARM3 / cfg["description"])
    for key, value in fields.items():
        if value is None:
            cfg.pop(key, None)
        else:
            cfg[key] = value
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def one_line_per_problem(message: str, n: int | None = None) -> list[str]:
    """The error's lines; none of them a pydantic dump."""
    lines = message.splitlines()
    assert lines, message
    for line in lines:
        assert "validation error" not in line and "errors.pydantic.dev" not in line and "[type=" not in line, message
        assert "np.float64" not in line, message
    if n is not None:
        assert len(lines) == n, message
    return lines


# ------------------------------------------------------------------ robot.yaml
@pytest.mark.parametrize(
    ("fields", "key", "expected"),
    [
        ({"update_rate": INF}, "update_rate", "finite"),
        ({"update_rate": NAN}, "update_rate", "finite"),
        ({"update_rate": 0}, "update_rate", ">= 1"),
        ({"update_rate": 1e9}, "update_rate", "<= 10000"),
        ({"gains": {"default": {"p": INF, "d": 1.0}}}, "gains.default.p", "finite"),
        ({"gains": {"joint1": {"p": 10.0, "d": -1.0}}}, "gains.joint1.d", ">= 0"),
        ({"gains": {"joint1": {"p": 10.0, "d": 1.0, "v": NAN}}}, "gains.joint1.v", "finite"),
        ({"joint_limits": {"joint1": {"min_position": NAN}}}, "joint_limits.joint1.min_position", "finite"),
        ({"joint_limits": {"joint1": {"max_position": -INF}}}, "joint_limits.joint1.max_position", "finite"),
        ({"joint_limits": {"default": {"max_acceleration": INF}}}, "joint_limits.default.max_acceleration", "finite"),
        ({"joint_limits": {"joint2": {"max_jerk": 0.0}}}, "joint_limits.joint2.max_jerk", ">= 0.001"),
        ({"joint_limits": {"joint2": {"max_acceleration": 5e-324}}}, "joint_limits.joint2.max_acceleration",
         ">= 0.001"),
        ({"initial_positions": {"joint1": INF}}, "initial_positions.joint1", "finite"),
    ],
)
def test_robot_yaml_numbers_are_finite_and_in_range(tmp_path: Path, fields: dict[str, Any], key: str,
                                                     expected: str) -> None:
    path = robot_yaml(tmp_path, **fields)
    with pytest.raises(ConfigurationError) as info:
        load_robot_config(path)
    (line,) = one_line_per_problem(str(info.value), 1)
    assert line.startswith(f"{path}: {key}: expected"), line
    assert expected in line, line


def test_robot_yaml_lists_every_problem_with_did_you_mean(tmp_path: Path) -> None:
    path = robot_yaml(tmp_path, update_rate=INF, gainz={}, joint_limits={"joint1": {"max_velocty": 1.0}})
    with pytest.raises(ConfigurationError) as info:
        load_robot_config(path)
    lines = one_line_per_problem(str(info.value), 3)
    text = "\n".join(lines)
    assert f"{path}: gainz: unknown key; did you mean 'gains'?" in text
    assert f"{path}: joint_limits.joint1.max_velocty: unknown key; did you mean 'max_velocity'?" in text
    assert f"{path}: update_rate: expected a finite number >= 1 and <= 10000, got inf" in text


def test_unknown_joint_names_suggest_the_closest_joint(tmp_path: Path) -> None:
    path = robot_yaml(tmp_path, joint_limits={"jiont2": {"max_velocity": 1.0}})
    with pytest.raises(ConfigurationError, match=r"jiont2: unknown joint 'jiont2'; did you mean 'joint2'"):
        agentsdk.description.resolve_robot(path)


async def test_nan_min_position_cannot_remove_the_urdf_limit(tmp_path: Path) -> None:
    """Before: a NaN min_position replaced the URDF limit and a -50 rad command was applied."""
    path = robot_yaml(tmp_path, joint_limits={"joint2": {"min_position": NAN}})
    with pytest.raises(ConfigurationError, match=r"joint_limits\.joint2\.min_position: expected a finite number"):
        async with agentsdk.connect("mock", robot=path):
            pass


async def test_overrides_only_narrow_the_urdf_limits(tmp_path: Path) -> None:
    path = robot_yaml(tmp_path, joint_limits={"joint2": {"min_position": -1.0, "max_position": 0.5}})
    async with agentsdk.connect("mock", robot=path) as robot:
        j2 = robot.joints[robot.joint_index["joint2"]]
        assert (j2.lower, j2.upper) == (-1.0, 0.5)
        applied = await robot.command(JointCommand("position", {"joint2": -50.0}))
        assert applied.values["joint2"] == -1.0
    wide = robot_yaml(tmp_path, joint_limits={"joint2": {"min_position": -50.0}})
    with pytest.raises(ConfigurationError, match=r"min_position=-50 is below the URDF lower limit"):
        async with agentsdk.connect("mock", robot=wide):
            pass


# ------------------------------------------------------------------ SafetyConfig
@pytest.mark.parametrize(
    ("override", "key"),
    [
        ({"max_position_step": -0.001}, "max_position_step"),
        ({"max_position_step": -1.0}, "max_position_step"),
        ({"max_position_step": NAN}, "max_position_step"),
        ({"max_position_step": INF}, "max_position_step"),
        ({"command_timeout": INF}, "command_timeout"),
        ({"command_timeout": NAN}, "command_timeout"),
        ({"stall_timeout": INF}, "stall_timeout"),
        ({"stall_timeout": 1e-9}, "stall_timeout"),
        ({"stop_damping": INF}, "stop_damping"),
        ({"stop_damping": -1.0}, "stop_damping"),
        ({"position_margin": NAN}, "position_margin"),
        ({"rest_velocity": -0.1}, "rest_velocity"),
        ({"rest_timeout": INF}, "rest_timeout"),
        ({"warn_interval": NAN}, "warn_interval"),
        ({"position_limit_tolerance": INF}, "position_limit_tolerance"),
        ({"stop_deceleration_scale": NAN}, "stop_deceleration_scale"),
    ],
)
async def test_safety_numbers_are_validated(override: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigurationError) as info:
        async with agentsdk.connect("mock", robot="arm3", safety=override):
            pass
    (line,) = one_line_per_problem(str(info.value), 1)
    assert line.startswith(f"connect(safety=...): {key}: expected"), line


def test_safety_errors_name_the_robot_yaml() -> None:
    with pytest.raises(ConfigurationError) as info:
        SafetyConfig.from_sources({"rest_timeout": NAN, "stal_timeout": 1.0}, None, source="my/robot.yaml")
    lines = one_line_per_problem(str(info.value), 2)
    assert "my/robot.yaml: safety.rest_timeout: expected a finite number >= 0, got nan" in lines
    assert "my/robot.yaml: safety.stal_timeout: unknown key; did you mean 'stall_timeout'?" in lines


async def test_negative_position_step_no_longer_drives_the_robot() -> None:
    """Before: max_position_step=-0.001 drifted every joint at 0.5 rad/s with no command at all."""
    with pytest.raises(ConfigurationError, match="max_position_step"):
        await agentsdk.connect("mock", robot="arm3", safety={"max_position_step": -0.001})
    async with agentsdk.connect("mock", robot="arm3", safety={"max_position_step": 0.001}) as robot:
        start = (await robot.read()).position.copy()
        await robot.clock.sleep(0.5)
        assert np.array_equal((await robot.read()).position, start)


# ------------------------------------------------------------------ backend options
@pytest.mark.parametrize(
    ("backend", "options", "key"),
    [
        ("mock", {"lag": NAN}, "lag"),
        ("mock", {"inertia": 0.0}, "inertia"),
        ("mock", {"coast_damping": INF}, "coast_damping"),
        ("mujoco", {"timestep": INF}, "timestep"),
        ("mujoco", {"timestep": 1e-12}, "timestep"),
        ("mujoco", {"gravity": [0.0, 0.0, NAN]}, "gravity.2"),
        ("mujoco", {"gravity": [0.0, 0.0, -1e300]}, "gravity.2"),
        ("mujoco", {"joint_damping": INF}, "joint_damping"),
        ("mujoco", {"armature": -1.0}, "armature"),
        ("pybullet", {"timestep": NAN}, "timestep"),
        ("pybullet", {"gravity": [INF, 0.0, 0.0]}, "gravity.0"),
        ("pybullet", {"joint_damping": NAN}, "joint_damping"),
        ("pybullet", {"solver_iterations": 0}, "solver_iterations"),
    ],
)
async def test_simulator_options_are_validated(backend: str, options: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigurationError) as info:
        async with agentsdk.connect(backend, robot="arm3", **options):
            pass
    (line,) = one_line_per_problem(str(info.value), 1)
    assert line.startswith(f"backend {backend!r} option {key}: expected"), line


async def test_update_rate_infinite_is_rejected_not_hung(tmp_path: Path) -> None:
    """Before: update_rate .inf hung the mock and raised a raw ZeroDivisionError on PyBullet."""
    path = robot_yaml(tmp_path, update_rate=INF)
    for backend in ("mock", "pybullet", "mujoco"):
        with pytest.raises(ConfigurationError, match=r"update_rate: expected a finite number"):
            await agentsdk.connect(backend, robot=path)


async def test_substeps_are_bounded(tmp_path: Path) -> None:
    path = robot_yaml(tmp_path, update_rate=1)
    with pytest.raises(ConfigurationError, match=r"needs 100000 physics steps per control period"):
        await agentsdk.connect("mujoco", robot=path, timestep=1e-5)


@pytest.mark.parametrize(
    ("options", "key"),
    [
        ({"reply_deadline": NAN}, "reply_deadline"),
        ({"open_timeout": INF}, "open_timeout"),
        ({"max_missed_replies": 0}, "max_missed_replies"),
        ({"timeout": INF}, "timeout"),
        ({"bitrate": -1}, "bitrate"),
    ],
)
async def test_can_options_are_validated(options: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigurationError) as info:
        await agentsdk.connect("can", robot="mit_leg", interface="virtual", channel="unused", **options)
    (line,) = one_line_per_problem(str(info.value), 1)
    assert line.startswith(f"backend 'can' option {key}: expected"), line


@pytest.mark.parametrize(
    ("motor", "key"),
    [
        ({"gear_ratio": INF}, "gear_ratio"),
        ({"gear_ratio": 1e-300}, "gear_ratio"),
        ({"zero_offset": NAN}, "zero_offset"),
        ({"timeout": INF}, "timeout"),
        ({"ranges": {"t_max": INF}}, "ranges.t_max"),
    ],
)
async def test_can_motor_numbers_in_robot_yaml_are_validated(tmp_path: Path, motor: dict[str, Any],
                                                             key: str) -> None:
    src = ROOT / "robots" / "mit_leg" / "robot.yaml"
    cfg = yaml.safe_load(src.read_text())
    cfg["description"] = str(src.parent / cfg["description"])
    cfg["backends"]["can"]["motors"]["knee"].update(motor)
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    with pytest.raises(ConfigurationError) as info:
        await agentsdk.connect("can", robot=path, interface="virtual", channel="unused")
    (line,) = one_line_per_problem(str(info.value), 1)
    assert line.startswith(f"{path}: backends.can.motors.knee.{key}: expected"), line


async def test_can_backend_on_a_robot_without_a_can_section() -> None:
    with pytest.raises(ConfigurationError) as info:
        await agentsdk.connect("can", robot="arm3")
    (line,) = one_line_per_problem(str(info.value), 1)
    assert "has no backends.can section" in line and "mit_leg" in line and "joint1" in line


async def test_mujoco_bad_control_is_a_fault_not_a_silent_zero() -> None:
    """A NaN reaching MuJoCo's ctrl (mjWARN_BADCTRL) used to zero every servo silently, state OK."""
    async with agentsdk.connect("mujoco", robot="arm3") as robot:

        def poison(t: float, state: Any, setpoint: Any) -> None:
            setpoint.position[1] = math.nan

        robot.add_tick_hook(Phase.COMMAND, poison)
        with pytest.raises(agentsdk.SimulationDiverged, match=r"joint 'joint2'.*mjWARN_BADCTRL"):
            await robot.clock.sleep(0.1)
        assert robot.safety.state is agentsdk.SafetyState.FAULT
        assert not robot.torque_enabled


def test_format_value_is_plain() -> None:
    assert format_value(np.float64("nan")) == "nan"
    assert format_value(np.float32(0.5)) == "0.5"
    assert format_value(-INF) == "-inf"
    assert format_value([1, 2.5, None]) == "[1, 2.5, null]"


# ------------------------------------------------------------------ CLI
def _cli(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "agentsdk", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=120)


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (("--backend", "can"), "has no backends.can section"),
        (("-o", "foo=1"), "error: backend 'mujoco' option foo: unknown option; expected one of: armature,"),
        (("-o", "timestpe=0.001"), "error: backend 'mujoco' option timestpe: unknown option; did you mean 'timestep'?"),
        (("--backend", "mock", "-o", "lag=.nan"), "error: backend 'mock' option lag: expected a finite number >= 0, "
                                                  "got nan"),
    ],
)
def test_cli_configuration_errors_are_one_line_each(args: tuple[str, ...], expected: str) -> None:
    proc = _cli("run", "behaviors/wave.py", "-q", *args)
    assert proc.returncode == 2, proc.stderr
    lines = one_line_per_problem(proc.stderr.strip(), 1)
    assert expected in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def test_cli_robot_yaml_typos_one_line_per_problem(tmp_path: Path) -> None:
    path = robot_yaml(tmp_path, upate_rate=100, gains={"default": {"p": 1.0, "d": 0.1, "i": 1.0}})
    proc = _cli("run", "behaviors/wave.py", "-q", "--backend", "mock", "--robot", str(path))
    assert proc.returncode == 2
    lines = one_line_per_problem(proc.stderr.strip(), 2)
    assert f"error: {path}: upate_rate: unknown key; did you mean 'update_rate'?" in lines
    assert f"error: {path}: gains.default.i: unknown key; expected one of: d, p, v" in lines


async def test_limits_narrowed_past_the_start_pose_are_refused(tmp_path: Path) -> None:
    """Found by the property test: min_position 1.0 with the robot starting at 0 made the safety
    layer drive the joint into its new range by itself. The start must be inside the limits."""
    narrowed = robot_yaml(tmp_path, joint_limits={"default": {"min_position": 1.0}})
    with pytest.raises(ConfigurationError) as info:
        async with agentsdk.connect("mock", robot=narrowed):
            pass
    (line,) = one_line_per_problem(str(info.value), 1)
    assert "joint 'joint1' starts at 0 rad, outside its joint_limits [1," in line, line
    assert "set initial_positions.joint1" in line
    ok = robot_yaml(tmp_path, joint_limits={"joint1": {"min_position": 1.0}}, initial_positions={"joint1": 1.5})
    async with agentsdk.connect("mock", robot=ok) as robot:
        assert robot.joints[0].lower == 1.0


@pytest.mark.parametrize("rate", [0.0, -5.0, math.nan, math.inf, 1e9])
async def test_connect_update_rate_is_validated_like_robot_yaml(rate: float) -> None:
    """``connect(update_rate=...)`` / ``agentsdk run --update-rate``: the robot.yaml range, named."""
    with pytest.raises(ConfigurationError, match="update_rate"):
        async with agentsdk.connect("mock", update_rate=rate):
            pytest.fail("connect must fail")


async def test_connect_update_rate_sets_the_control_period() -> None:
    async with agentsdk.connect("mock", update_rate=125) as robot:
        assert robot.control_period == pytest.approx(0.008)
        await robot.clock.sleep(0.1)


def test_cli_run_update_rate_reaches_the_robot(tmp_path: Path) -> None:
    behavior = tmp_path / "rate.py"
    behavior.write_text("async def main(robot):\n    print('PERIOD', robot.control_period)\n")
    proc = subprocess.run([sys.executable, "-m", "agentsdk", "run", str(behavior), "--backend", "mock",
                           "--update-rate", "250", "-q"], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert "PERIOD 0.004" in proc.stdout
