"""Repairs only tighten (issue 20 item 6): a bad limit in non-strict mode gets a conservative value, named."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import pytest

from agentsdk.description import load_description
from agentsdk.errors import DescriptionError


def _robot(tmp_path: Path, limit: str, jtype: str = "revolute") -> Path:
    path = tmp_path / "r.urdf"
    path.write_text(
        '<robot name="r"><link name="base"/>'
        '<link name="a"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01"/></inertial></link>'
        '<link name="b"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01"/></inertial></link>'
        f'<joint name="j" type="{jtype}"><parent link="base"/><child link="a"/>{limit}</joint>'
        '<joint name="k" type="revolute"><parent link="a"/><child link="b"/>'
        '<limit lower="-1" upper="1" effort="2" velocity="3"/></joint></robot>'
    )
    return path


def test_negative_effort_keeps_its_magnitude_never_unlimited(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = _robot(tmp_path, '<limit lower="-1" upper="1" effort="-5" velocity="2"/>')
    with caplog.at_level(logging.WARNING, logger="agentsdk.description"):
        desc = load_description(path)
    assert desc.joint("j").max_effort == 5.0
    assert "joint 'j'" in caplog.text and "effort limit -5 -> 5" in caplog.text
    with pytest.raises(DescriptionError, match="effort limit -5"):
        load_description(path, strict=True)


@pytest.mark.parametrize(
    ("jtype", "velocity", "expected"),
    [("revolute", "-5", 1.0), ("revolute", "-0.3", 0.3), ("prismatic", "-5", 0.25), ("prismatic", "-0.1", 0.1),
     ("revolute", "0", 1.0)],
)
def test_negative_velocity_gets_the_tighter_of_its_magnitude_and_the_default(
    tmp_path: Path, jtype: str, velocity: str, expected: float
) -> None:
    desc = load_description(_robot(tmp_path, f'<limit lower="-1" upper="1" effort="2" velocity="{velocity}"/>', jtype))
    assert desc.joint("j").max_velocity == pytest.approx(expected)
    assert any(f"velocity limit {float(velocity):g} -> {expected:g}" in str(r) for r in desc.repairs)


def test_lower_above_upper_holds_the_joint_fixed_never_swapped(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = _robot(tmp_path, '<limit lower="1" upper="-1" effort="2" velocity="2"/>')
    with caplog.at_level(logging.WARNING, logger="agentsdk.description"):
        desc = load_description(path)
    assert desc.joint_names == ("k",)  # j is no longer a commanded joint
    assert next(r for r in desc.all_joints if r.name == "j").type == "fixed"
    assert "joint 'j'" in caplog.text and "lower=1 > upper=-1 leaves no valid range: joint held fixed" in caplog.text
    with pytest.raises(DescriptionError, match="lower=1 > upper=-1"):
        load_description(path, strict=True)


def test_no_repair_widens_a_limit(tmp_path: Path) -> None:
    """Over the repairable limit values, a repaired limit is never looser than the magnitude in the file."""
    for effort in ("-5", "-0.5", "5"):
        for velocity in ("-5", "-0.5", "0.5"):
            desc = load_description(_robot(tmp_path, f'<limit lower="-1" upper="1" effort="{effort}" '
                                                      f'velocity="{velocity}"/>'))
            j = desc.joint("j")
            assert math.isfinite(j.max_effort) and j.max_effort <= abs(float(effort))
            assert j.max_velocity <= abs(float(velocity))
