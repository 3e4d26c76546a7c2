"""Issue 21 item 4: a backend is built from one ready value, :class:`agentsdk.backendspec.BackendSpec`.

The spec is derived by one function (no backend needed), is what the Backend base class adopts,
and is immutable.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk.backendspec import BackendSpec


async def test_backend_attributes_are_its_spec() -> None:
    async with agentsdk.connect("mock", "arm3") as robot:
        backend = robot.backend
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
        backend = robot.backend
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
        backend = robot.backend
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


# ---------------------------------------------------------------- a backend is constructed from its spec


async def test_a_backend_is_constructed_from_its_spec() -> None:
    """``connect`` builds the spec (options, start pose, gains, the host model), then ``cls(spec)``."""
    from tiny_backend import TinyController

    from agentsdk.backendspec import takes_spec

    agentsdk.register_backend("tiny_spec", TinyController)
    try:
        async with agentsdk.connect("tiny_spec", "arm3") as robot:
            backend = robot.backend
            spec = backend.spec
            assert backend.servo_gains is spec.servo_gains
            assert len(spec.servo_gains) == len(spec.joints)
            assert spec.gain_report is None  # arm3's robot.yaml sets every joint's gains
            assert robot.kinematics.model is spec.host.get().model
            assert backend.dynamics.model is spec.host.get().model
    finally:
        agentsdk.unregister_backend("tiny_spec")
    assert takes_spec(TinyController, agentsdk.Backend)
    again = TinyController(TinyController.make_spec(spec.config, spec.description, spec.joints))
    assert again.spec.names == spec.names
    np.testing.assert_array_equal(again.initial_positions, spec.initial_positions)
    with pytest.raises(TypeError, match="BackendSpec alone"):
        TinyController(spec, spec.description)  # type: ignore[arg-type]


async def test_the_spec_carries_the_backends_timestep_and_floating_base() -> None:
    pytest.importorskip("mujoco")
    async with agentsdk.connect("mujoco", "arm3", timestep=0.0005) as robot:
        spec = robot.backend.spec
        assert spec.servo_timestep == 0.0005 == robot.backend.servo_timestep
        assert spec.floating_base is robot.backend.floating_base is False
        report = robot.backend.model_gain_report  # computed on demand with the spec's timestep
        stiffer = robot.backend.dynamics.gains(spec.initial_positions, timestep=0.002).kp
        assert (report.kp >= stiffer).all()


def test_model_gains_come_from_the_host_model() -> None:
    """A robot without robot.yaml gains (its bare xacro): the spec's gains are the host model's."""
    from pathlib import Path

    from agentsdk.description import resolve_robot

    config, desc = resolve_robot(Path(__file__).resolve().parents[1] / "robots" / "arm3" / "arm3.urdf.xacro")
    spec = agentsdk.load_backend("mock").make_spec(config, desc, desc.joints, realtime=False)
    assert spec.gain_report is not None and spec.host.built
    assert [g.p for g in spec.servo_gains] == spec.gain_report.kp.tolist()


async def test_a_backend_written_against_the_old_constructor_still_connects_and_warns() -> None:
    """Deprecation path: ``__init__(self, config, description, joints, **options)`` calling the base that way."""
    from tiny_backend import TinyController

    class OldStyle(TinyController):
        name = "old_style"

        def __init__(self, config: Any, description: Any, joints: Any, *, realtime: bool | None = None,
                     **options: Any) -> None:
            super().__init__(config, description, joints, realtime=realtime, **options)
            self.built_the_old_way = True

    agentsdk.register_backend("old_style", OldStyle)
    try:
        with pytest.warns(DeprecationWarning, match="OldStyle: constructing a backend from"):
            connection = agentsdk.connect("old_style", "arm3")
            robot = await connection
        try:
            backend = robot.backend
            assert isinstance(backend, OldStyle) and backend.built_the_old_way
            assert backend.spec.names == robot.joint_names
            assert robot.kinematics.model is backend.spec.host.get().model
            await robot.move_to({robot.joint_names[0]: 0.2})
        finally:
            await robot.close()
    finally:
        agentsdk.unregister_backend("old_style")
    # a built-in backend constructed the old way directly still works too, and warns
    config, desc, joints = backend.config, backend.description, backend.joints
    with pytest.warns(DeprecationWarning, match="MockBackend"):
        old = agentsdk.load_backend("mock")(config, desc, joints, realtime=False)  # type: ignore[arg-type]
    new = agentsdk.load_backend("mock").create(config, desc, joints, realtime=False)
    assert old.spec.names == new.spec.names
    np.testing.assert_array_equal(old.initial_positions, new.initial_positions)
    assert [(g.p, g.d) for g in old.servo_gains] == [(g.p, g.d) for g in new.servo_gains]
