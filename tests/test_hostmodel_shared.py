"""Issue 21 item 4: one compiled host-side model per robot, shared by its kinematics and dynamics.

A connect compiles the description host-side once (counted at :func:`agentsdk.hostmodel.compile_spec`,
the one place a :class:`~agentsdk.hostmodel.HostModel` is compiled); ``robot.kinematics`` and the
backend's ``dynamics`` (servo gains, gravity compensation) compute on that one ``MjModel``, each with
its own ``MjData``, so IK in a worker thread and the tick's gravity term do not disturb each other.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest
from conftest import lockstep_backends
from test_hostmodel import _describe

import agentsdk
from agentsdk import hostmodel
from agentsdk.description import resolve_robot
from agentsdk.dynamics import DynamicsModel
from agentsdk.hostmodel import HostModel
from agentsdk.kinematics import Kinematics


@pytest.fixture
def compiles(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The names of the descriptions compiled host-side while the test runs."""
    seen: list[str] = []
    original = hostmodel.compile_spec

    def counting(spec: Any) -> Any:
        model = original(spec)
        seen.append(model.names.split(b"\0")[0].decode())
        return model

    monkeypatch.setattr(hostmodel, "compile_spec", counting)
    return seen


@pytest.mark.parametrize("backend", lockstep_backends())
async def test_a_connect_compiles_the_host_model_once(backend: str, compiles: list[str]) -> None:
    async with agentsdk.connect(backend, "arm3") as robot:
        ctl = robot.backend
        kin = robot.kinematics
        dyn = ctl.dynamics
        gains = ctl.model_gain_report  # the model-based gains come from the same model
        assert len(gains.kp) == len(robot.joints)
        assert kin.model is dyn.model is ctl.spec.host.get().model
        assert kin.host is dyn.host
        # every user has its own scratch data on the shared model
        assert kin._data is not dyn._data
        q = np.asarray(ctl.initial_positions)
        np.testing.assert_allclose(kin.gravity(q), dyn.gravity(q), rtol=0, atol=1e-12)
        kin.ik("ee_link", kin.fk("ee_link", q))
    assert len(compiles) == 1, compiles


async def test_the_host_model_floats_and_carries_the_simulators_gravity(compiles: list[str]) -> None:
    """A backend's ``gravity`` option and floating base are the host model's: PyBullet's gravity
    compensation computes on the robot's one model, not on a second one of its own."""
    pytest.importorskip("pybullet")
    async with agentsdk.connect("pybullet", "arm3", gravity=(0.0, 0.0, -3.0)) as robot:
        ctl = robot.backend
        host = ctl.spec.host.get()
        np.testing.assert_array_equal(host.model.opt.gravity, (0.0, 0.0, -3.0))
        assert ctl._model.model is host.model is robot.kinematics.model
        q = np.asarray(ctl.initial_positions)
        # the kinematics' g(q) at standard gravity computes on a copy: the shared model is not changed
        np.testing.assert_allclose(robot.kinematics.gravity(q, (0.0, 0.0, -3.0)) * 9.81 / 3.0,
                                   robot.kinematics.gravity(q), rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(host.model.opt.gravity, (0.0, 0.0, -3.0))
    assert len(compiles) == 1, compiles


def test_a_kinematics_gravity_vector_leaves_the_shared_model_alone() -> None:
    desc = resolve_robot("arm3")[1]
    host = HostModel.compile(desc)
    kin = Kinematics(desc, host=host)
    dyn = DynamicsModel(desc, host=host)
    q = np.clip(np.full(len(host.joints), 0.3), kin.lower, kin.upper)
    before = dyn.gravity(q).copy()
    assert np.abs(before).max() > 0
    np.testing.assert_allclose(kin.gravity(q, gravity=(0.0, 0.0, -2 * 9.81)), 2 * before, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(host.model.opt.gravity, (0.0, 0.0, -9.81))
    np.testing.assert_array_equal(dyn.gravity(q + 1e-3 * 0), before)
    np.testing.assert_allclose(kin.gravity(q), before, rtol=0, atol=1e-12)


def test_ik_in_a_worker_thread_beside_the_gravity_term() -> None:
    """Kinematics (FK, Jacobians, IK) in a thread and ``g(q)`` in this one, on one MjModel: each its own MjData."""
    desc = resolve_robot("arm3")[1]
    host = HostModel.compile(desc)
    kin = Kinematics(desc, host=host)
    dyn = DynamicsModel(desc, host=host)
    rng = np.random.default_rng(7)
    lo = np.where(np.isfinite(kin.lower), kin.lower, -np.pi)
    hi = np.where(np.isfinite(kin.upper), kin.upper, np.pi)
    qs = rng.uniform(lo, hi, size=(200, len(host.joints)))
    expected = np.array([dyn.gravity(q).copy() for q in qs])
    targets = [kin.fk("ee_link", q) for q in qs[:20]]
    jacobians = [kin.jacobian("ee_link", q) for q in qs[:20]]
    stop = threading.Event()
    problems: list[str] = []

    def worker() -> None:
        try:
            while not stop.is_set():
                for k, (q, target) in enumerate(zip(qs[:20], targets, strict=True)):
                    if stop.is_set():
                        return
                    np.testing.assert_allclose(kin.jacobian("ee_link", q), jacobians[k], rtol=0, atol=1e-12)
                    result = kin.ik("ee_link", target, seed=q)
                    reached = kin.fk("ee_link", [result[n] for n in kin.joint_names])
                    assert np.linalg.norm(reached.position - target.position) < 1e-3
        except Exception as exc:  # reported by the main thread
            problems.append(repr(exc))

    thread = threading.Thread(target=worker, name="test-ik-worker")
    thread.start()
    try:
        out = np.zeros(len(host.joints))
        for _ in range(20):
            for q, want in zip(qs, expected, strict=True):
                np.testing.assert_array_equal(dyn.gravity(q, out), want)
    finally:
        stop.set()
        thread.join(timeout=60)
    assert not thread.is_alive()
    assert not problems, problems


def test_couplings_are_read_once_and_shared() -> None:
    """A mimic joint's coupling, read once by the host model, is what FK, Jacobians and g(q) use."""
    desc = _describe("panda")  # the second finger mimics the first
    host = HostModel.compile(desc)
    assert len(host.couplings) == 1
    kin = Kinematics(desc, host=host)
    dyn = DynamicsModel(desc, host=host)
    assert kin._couplings is host.couplings
    assert dyn._s is host.coupling
    np.testing.assert_array_equal(host.coupling, hostmodel.coupling_matrix(host.model, host.names))


def test_a_host_model_for_other_joints_is_refused() -> None:
    desc = resolve_robot("arm3")[1]
    host = HostModel.compile(desc)
    with pytest.raises(agentsdk.errors.AgentSDKError, match="host model"):
        Kinematics(desc, desc.joints[:1], host=host)
    with pytest.raises(agentsdk.errors.AgentSDKError, match="host model"):
        DynamicsModel(desc, desc.joints[:1], host=host)
