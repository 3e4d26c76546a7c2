"""Property test over every numeric configuration value (issue 10, acceptance 3).

Random values (NaN, +-inf, negative, zero, subnormal, huge, ordinary) go into every
numeric field of robot.yaml (update rate, gains, joint limit overrides, initial
positions, the safety section), ``connect(safety=...)`` and the mock backend's
options. Each is either rejected with a :class:`ConfigurationError` of one line per
problem (no pydantic dump, no ``np.float64``), or the robot runs a move and a
velocity stream with every setpoint reaching the backend finite and inside the
joint limits, and the measured positions inside them too.

The fields are enumerated from the pydantic models, so a numeric field added later is
covered without editing this file. (Tolerances and trajectory numbers have their own
property test with the trajectory code.)
"""

from __future__ import annotations

import asyncio
import math
import types
import typing
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel

import agentsdk
from agentsdk import ConfigurationError, JointCommand
from agentsdk.backends.mock import MockOptions
from agentsdk.config import Gains, JointLimitsOverride, RobotConfig
from agentsdk.loop import Phase
from agentsdk.safety import SafetyConfig

ROOT = Path(__file__).resolve().parents[1]
ARM3 = ROOT / "robots" / "arm3"
BASE = yaml.safe_load((ARM3 / "robot.yaml").read_text())
BASE["description"] = str(ARM3 / BASE["description"])


def _numeric(annotation: Any) -> bool:
    """True when the annotation admits a float or an int (not a bool)."""
    if annotation in (float, int):
        return True
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _numeric(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return any(_numeric(a) for a in typing.get_args(annotation))
    return False


def numeric_fields(model: type[BaseModel]) -> list[str]:
    """Names of the model's numeric fields."""
    return sorted(name for name, f in model.model_fields.items() if _numeric(f.annotation))


def _paths() -> list[tuple[str, ...]]:
    paths: list[tuple[str, ...]] = [(name,) for name in numeric_fields(RobotConfig)]
    for who in ("default", "joint2"):
        paths += [("gains", who, name) for name in numeric_fields(Gains)]
        paths += [("joint_limits", who, name) for name in numeric_fields(JointLimitsOverride)]
    paths += [("initial_positions", "joint2")]
    paths += [("safety", name) for name in numeric_fields(SafetyConfig)]
    return paths


YAML_PATHS = _paths()
SAFETY_FIELDS = numeric_fields(SafetyConfig)
MOCK_FIELDS = numeric_fields(MockOptions)

NUMBERS = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0, -1.0, -1e-3, 1e-9, 5e-324, 1e300, -1e300, 1e6]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=-10.0, max_value=10.0),
    st.integers(min_value=-1000, max_value=10**6),
)
SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _set(cfg: dict[str, Any], path: tuple[str, ...], value: Any) -> None:
    node = cfg
    for key in path[:-1]:
        node = node.setdefault(key, {})
        if node is None:  # an empty section in the yaml
            raise AssertionError(path)
    node[path[-1]] = value


def _one_line_per_problem(exc: ConfigurationError) -> None:
    lines = str(exc).splitlines()
    assert lines, repr(exc)
    for line in lines:
        assert "validation error" not in line and "errors.pydantic.dev" not in line and "[type=" not in line, str(exc)
        assert "np.float64" not in line and "Traceback" not in line, str(exc)


async def _exercise(robot_arg: Any, **kwargs: Any) -> None:
    """Connect, run a move and a velocity stream, check what reaches the backend and what is measured."""
    try:
        robot = await agentsdk.connect("mock", robot=robot_arg, **kwargs)
    except ConfigurationError as exc:
        _one_line_per_problem(exc)
        return
    bad: list[str] = []
    lo = np.array([j.lower for j in robot.joints])
    hi = np.array([j.upper for j in robot.joints])
    tol = 1e-6

    def check(t: float, state: Any, sp: Any) -> None:
        on = np.asarray(sp.enabled, dtype=bool)
        for what in ("position", "velocity", "effort", "kp", "kd"):
            arr = np.asarray(getattr(sp, what))
            if not np.isfinite(arr[on]).all():
                bad.append(f"t={t:.3f}: non-finite {what} setpoint {arr.tolist()}")
        pos = np.asarray(sp.position)[on]
        if ((pos < lo[on] - tol) | (pos > hi[on] + tol)).any():
            bad.append(f"t={t:.3f}: position setpoint {pos.tolist()} outside {lo.tolist()}..{hi.tolist()}")
        q = np.asarray(state.position)
        if not np.isfinite(q).all():
            bad.append(f"t={t:.3f}: measured position {q.tolist()}")

    try:
        hook = robot.add_tick_hook(Phase.OBSERVE, check)
        try:
            lower, upper = robot.joints[1].lower, robot.joints[1].upper
            target = min(max(0.3, lower), upper)
            try:
                async with asyncio.timeout(5.0), robot.clock.timeout(0.4):
                    await robot.move_to({robot.joints[1].name: target})
            except TimeoutError:
                pass
            except agentsdk.AgentSDKError:
                pass  # refused or stopped (e.g. a command timeout or a stall): the robot stays safe
            for _ in range(20):
                try:
                    await robot.command(JointCommand("velocity", {robot.joints[0].name: 100.0}))
                except agentsdk.AgentSDKError:
                    break
                await robot.clock.sleep(0.01)
        finally:
            hook.remove()
    finally:
        await robot.close()
    assert not bad, bad[:3]


@SETTINGS
@given(path=st.sampled_from(YAML_PATHS), value=NUMBERS)
def test_every_numeric_robot_yaml_value_is_rejected_or_safe(tmp_path_factory: Any, path: tuple[str, ...],
                                                             value: float) -> None:
    cfg = yaml.safe_load(yaml.safe_dump(BASE))
    _set(cfg, path, value)
    robot_file = tmp_path_factory.mktemp("cfg") / "robot.yaml"
    robot_file.write_text(yaml.safe_dump(cfg))
    asyncio.run(_exercise(robot_file))


@SETTINGS
@given(field=st.sampled_from(SAFETY_FIELDS), value=NUMBERS)
def test_every_numeric_safety_value_is_rejected_or_safe(field: str, value: float) -> None:
    asyncio.run(_exercise("arm3", safety={field: value}))


@SETTINGS
@given(field=st.sampled_from(MOCK_FIELDS), value=NUMBERS)
def test_every_numeric_connect_option_is_rejected_or_safe(field: str, value: float) -> None:
    asyncio.run(_exercise("arm3", **{field: value}))


def test_the_property_covers_the_fields_that_matter() -> None:
    """The enumeration is not empty by accident (e.g. a changed annotation style)."""
    assert ("update_rate",) in YAML_PATHS and ("gains", "joint2", "p") in YAML_PATHS
    assert ("joint_limits", "joint2", "min_position") in YAML_PATHS
    assert {"max_position_step", "command_timeout", "stall_timeout", "stop_damping"} <= set(SAFETY_FIELDS)
    assert {"lag", "inertia", "coast_damping"} <= set(MOCK_FIELDS)
