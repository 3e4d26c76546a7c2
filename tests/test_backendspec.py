"""Issue 21 item 4: a backend is built from one ready value, :class:`agentsdk.backendspec.BackendSpec`.

The spec is derived by one function (no backend needed), is what the Backend base class adopts,
and is immutable.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import agentsdk
from agentsdk.backendspec import BackendSpec


async def test_backend_attributes_are_its_spec() -> None:
    async with agentsdk.connect("mock", "arm3") as robot:
        backend = robot.controller
        spec = backend.spec
        assert spec.names == backend.names == robot.joint_names
        assert spec.period == backend.period
        for name in ("lower", "upper", "max_velocity", "max_effort", "initial_positions", "gravity_compensation"):
            assert getattr(backend, name) is getattr(spec, name), name
        assert backend.start_pose is spec.start_pose
        assert backend.options is spec.options
        assert backend.inverse_dynamics is spec.inverse_dynamics
        assert spec.realtime is backend.realtime is False


async def test_spec_is_derived_without_a_backend_and_is_immutable() -> None:
    async with agentsdk.connect("mock", "arm3") as robot:
        backend = robot.controller
        again = BackendSpec.build(backend.config, backend.description, backend.joints, backend.options, realtime=False)
    assert again.names == backend.names
    np.testing.assert_array_equal(again.initial_positions, backend.initial_positions)
    np.testing.assert_array_equal(again.lower, [j.lower for j in backend.joints])
    np.testing.assert_array_equal(again.gravity_compensation, backend.gravity_compensation)
    with pytest.raises(dataclasses.FrozenInstanceError):
        again.period = 1.0  # type: ignore[misc]
    for name in ("lower", "upper", "max_velocity", "max_effort", "initial_positions", "gravity_compensation"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(again, name)[0] = 0.0


async def test_a_backend_option_overrides_the_gravity_flags() -> None:
    """``gravity_compensation`` / ``inverse_dynamics`` backend options switch the robot.yaml values."""
    async with agentsdk.connect("mock", "arm3") as robot:
        backend = robot.controller
        config, desc, joints = backend.config, backend.description, backend.joints

    class Options:
        gravity_compensation = False
        inverse_dynamics = True

    spec = BackendSpec.build(config, desc, joints, Options(), realtime=True)
    assert not spec.gravity_compensation.any()
    assert spec.inverse_dynamics is True
    assert spec.realtime is True
    Options.gravity_compensation = True
    Options.inverse_dynamics = False
    spec = BackendSpec.build(config, desc, joints, Options(), realtime=True)
    assert spec.gravity_compensation.all()
    assert spec.inverse_dynamics is False
