"""Joint Coulomb friction in PyBullet's implicit step (``backends.pybullet.friction``)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pybullet")

from backends.pybullet.friction import friction_torque

H = 0.001


def _step(a: np.ndarray, rhs: np.ndarray, v: np.ndarray, friction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    force = friction_torque(a, rhs, v, H, friction)
    assert (np.abs(force) <= friction + 1e-12).all()
    return force, v + H * np.linalg.solve(a, rhs + force)


def test_one_joint_sticks_below_its_friction_and_slides_above() -> None:
    a, f = np.array([[2.0]]), np.array([1.0])
    force, v = _step(a, np.array([0.5]), np.zeros(1), f)
    assert force[0] == pytest.approx(-0.5) and v[0] == pytest.approx(0.0)
    force, v = _step(a, np.array([3.0]), np.zeros(1), f)
    assert force[0] == pytest.approx(-1.0) and v[0] == pytest.approx(H * 2.0 / 2.0)


def test_joints_moving_a_light_link_together_stop_without_overshoot() -> None:
    """Two aligned axes (xArm7's joint1 and joint3 at home): heavy each, light when turned opposite ways.
    Holding, the velocity of the light mode goes to zero in one step and stays there (a per-joint estimate
    reversed it, larger each step)."""
    heavy, light = 1.0, 0.001
    u = np.array([1.0, 1.0]) / np.sqrt(2)
    w = np.array([1.0, -1.0]) / np.sqrt(2)
    a = heavy * np.outer(u, u) + light * np.outer(w, w)
    f = np.array([1.0, 1.0])
    v = 1e-4 * w
    for _ in range(50):
        _, v = _step(a, np.zeros(2), v, f)
        assert np.abs(v).max() < 1e-12


def test_a_sliding_joint_and_a_sticking_joint_together() -> None:
    """One joint driven past its friction slides; a coupled one whose holding torque stays within its
    friction is held at rest; friction never drives a joint."""
    a = np.array([[1.0, 0.3], [0.3, 0.5]])
    f = np.array([0.2, 5.0])
    force, v = _step(a, np.array([2.0, 0.0]), np.zeros(2), f)
    assert v[0] > 0 and v[1] == pytest.approx(0.0, abs=1e-12)
    assert force[0] == pytest.approx(-0.2)
    rng = np.random.default_rng(0)
    for _ in range(200):
        m = rng.normal(size=(4, 4))
        a = m @ m.T + 0.01 * np.eye(4)
        f = rng.uniform(0.0, 1.0, 4)
        v0 = rng.normal(size=4) * 0.01
        force, v = _step(a, rng.normal(size=4), v0, f)
        sliding = np.abs(v) > 1e-9
        # a sliding joint feels its full friction against its new velocity
        assert np.allclose(force[sliding & (f > 0)], -f[sliding & (f > 0)] * np.sign(v[sliding & (f > 0)]))
