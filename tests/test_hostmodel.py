"""Issue 21 item 4: one host-side g(q).

``Kinematics.gravity`` and ``DynamicsModel.gravity`` (the model-based gravity compensation of the
CAN and PyBullet backends) compute through the same :class:`agentsdk.hostmodel.GravityTerm`, so
they agree, a mimic joint's torque carried by its leader in both.
"""

from __future__ import annotations

import importlib.metadata
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agentsdk.description import load_description, resolve_robot
from agentsdk.dynamics import DynamicsModel
from agentsdk.hostmodel import GravityTerm
from agentsdk.kinematics import Kinematics


def _describe(robot: str) -> Any:
    if robot != "panda":
        return resolve_robot(robot)[1]
    # a URDF with a mimic joint (the second finger), from the example-robot-data corpus
    prefix = importlib.metadata.distribution("example-robot-data").locate_file("cmeel.prefix")
    return load_description(Path(str(prefix)) / "share/example-robot-data/robots/panda_description/urdf/panda.urdf")


@pytest.mark.parametrize("robot", ["arm3", "panda"])
def test_kinematics_and_dynamics_share_one_gravity(robot: str, monkeypatch: pytest.MonkeyPatch) -> None:
    desc = _describe(robot)
    kin = Kinematics(desc)
    dyn = DynamicsModel(desc, kin.joints)
    callers: list[str] = []
    original = GravityTerm.compute

    def spy(self: GravityTerm, qpos: np.ndarray, out: np.ndarray) -> np.ndarray:
        callers.append(sys._getframe(1).f_globals["__name__"])
        result: np.ndarray = original(self, qpos, out)
        return result

    monkeypatch.setattr(GravityTerm, "compute", spy)
    rng = np.random.default_rng(3)
    lo = np.where(np.isfinite(kin.lower), kin.lower, -np.pi)
    hi = np.where(np.isfinite(kin.upper), kin.upper, np.pi)
    for _ in range(5):
        q = rng.uniform(lo, hi)
        np.testing.assert_allclose(kin.gravity(q), dyn.gravity(q), rtol=0, atol=1e-12)
    assert set(callers) == {"agentsdk.kinematics", "agentsdk.dynamics"}, callers


def test_kinematics_gravity_follows_the_gravity_vector() -> None:
    """The ``gravity`` argument is applied for one call and restored (the cached g(q) is not reused)."""
    kin = Kinematics(resolve_robot("arm3")[1])
    q = np.clip(np.full(len(kin.joints), 0.4), kin.lower, kin.upper)
    g = kin.gravity(q)
    assert np.abs(g).max() > 0
    np.testing.assert_allclose(kin.gravity(q, gravity=(0.0, 0.0, -2 * 9.81)), 2 * g, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(kin.gravity(q, gravity=(0.0, 0.0, 0.0)), 0.0, atol=0)
    np.testing.assert_array_equal(kin.gravity(q), g)
