"""One name for the backend concept: ``robot.backend`` is the Backend instance (issue 21 item 5).

``robot.controller`` (its former name) and comparing ``robot.backend`` with a string (its type in
0.1) still work, each with a ``DeprecationWarning``.
"""

from __future__ import annotations

import pytest

import agentsdk
from agentsdk import Backend, available_backends, connect


async def test_robot_backend_is_the_backend_instance_named_by_its_name() -> None:
    async with connect("mock", robot="arm3") as robot:
        assert isinstance(robot.backend, Backend)
        assert robot.backend.name == "mock" and str(robot.backend) == "mock"
        assert f"{robot.backend}" == "mock"
        assert robot.backend.name in available_backends()
        assert hash(robot.backend) == hash("mock")


async def test_the_former_names_still_work_and_warn() -> None:
    async with connect("mock", robot="arm3") as robot:
        with pytest.warns(DeprecationWarning, match=r"Robot\.backend"):
            assert robot.controller is robot.backend
        with pytest.warns(DeprecationWarning, match=r"robot\.backend\.name == 'mock'"):
            assert robot.backend == "mock"
        with pytest.warns(DeprecationWarning):
            assert robot.backend != "mujoco"
        with pytest.warns(DeprecationWarning):  # in sets and as dict keys too (the name's hash)
            assert robot.backend in {"mock", "mujoco"} and {"mock": 1}.get(robot.backend) == 1  # type: ignore[call-overload]
        assert agentsdk.Controller is Backend


async def test_backends_compare_by_identity() -> None:
    async with connect("mock", robot="arm3") as a, connect("mock", robot="arm3") as b:
        assert a.backend == a.backend and a.backend != b.backend
        assert len({a.backend, b.backend, a.backend}) == 2
