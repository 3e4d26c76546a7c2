"""Issue 28 item 2: the servo law's model terms computed inside MuJoCo's step.

Gravity compensation is MuJoCo's own on the MuJoCo backend (``body_gravcomp`` routed through the
joints' actuator forces, :mod:`backends.mujoco.gravcomp`): the same ``g(q)`` as the host term
(:class:`agentsdk.dynamics.GravityTerm`) to rounding, clamped with the servo torque to the effort
limit, off with the joint's torque; the host term where MuJoCo cannot express the law (a floating
base, a partial ``gravity_compensation``). The inverse-dynamics feed-forward is evaluated at the
desired state, so it depends on the setpoint alone. Everything runs in lockstep.
"""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import mujoco
import numpy as np
import pytest

import agentsdk
from agentsdk import Robot
from agentsdk.backend import ModeCode, SetpointView
from agentsdk.dynamics import GravityTerm, coupling_matrix

CORPUS = Path(
    str(importlib.metadata.distribution("example-robot-data").locate_file("cmeel.prefix/share/example-robot-data/robots"))
)
FIXTURES = Path(__file__).parent / "fixtures"
#: fixed-base robots MuJoCo compensates itself: shipped, corpus URDFs (Panda: mimic fingers), an MJCF arm
SIMULATOR_ROUTED = {
    "arm3": "arm3",
    "humanoid": "humanoid",
    "panda": str(CORPUS / "panda_description/urdf/panda.urdf"),
    "ur5": str(CORPUS / "ur_description/urdf/ur5_robot.urdf"),
    "talos_left_arm": str(CORPUS / "talos_data/robots/talos_left_arm.urdf"),
    "mjcf_arm": str(FIXTURES / "mjcf_arm" / "scene.xml"),
}
SAFETY = {"stall_timeout": 5.0}


def _random_poses(robot: Robot, count: int, seed: int) -> list[np.ndarray]:
    b = robot.backend
    rng = np.random.default_rng(seed)
    lo = np.where(np.isfinite(b.lower), b.lower, -np.pi)
    hi = np.where(np.isfinite(b.upper), b.upper, np.pi)
    return [rng.uniform(lo, hi) for _ in range(count)]


def _place(robot: Robot, q: np.ndarray) -> mujoco.MjData:
    """A copy of the backend's data at joint positions ``q`` (mimic followers placed), forward computed."""
    b = robot.backend
    m = b.model
    d = mujoco.MjData(m)
    d.qpos[:] = b.data.qpos
    d.qpos[b._qadr] = q
    for adr, leader, c1, c0 in b._qdes_followers:
        d.qpos[adr] = c0 + c1 * q[leader]
    mujoco.mj_forward(m, d)
    return d


@pytest.mark.parametrize("name", sorted(SIMULATOR_ROUTED))
async def test_mujoco_gravity_compensation_is_the_host_g_of_q(name: str) -> None:
    """``S.T @ qfrc_gravcomp`` equals the host term's ``g(q)`` at random poses, to rounding."""
    async with agentsdk.connect("mujoco", robot=SIMULATOR_ROUTED[name], safety=SAFETY) as robot:
        b = robot.backend
        assert b.gravity_route == "simulator", b.gravity_route_reason
        m = b.model
        host, s_t = GravityTerm(m, b.names), coupling_matrix(m, b.names).T
        g = np.zeros(len(b.names))
        for q in _random_poses(robot, 25, seed=3):
            d = _place(robot, q)
            host.compute(d.qpos, g)
            scale = max(1.0, float(np.abs(g).max()))
            np.testing.assert_allclose(s_t @ d.qfrc_gravcomp, g, rtol=0, atol=1e-12 * scale)
            # the joints no commanded joint moves get none (their actuator force is clamped to 0)
            carried = np.flatnonzero(s_t.any(axis=0))
            rest = np.setdiff1d(np.arange(m.nv), carried)
            assert not d.qfrc_actuator[rest].any()


def _setpoint(n: int, **values: np.ndarray) -> SetpointView:
    arrays: dict[str, np.ndarray] = {
        name: np.zeros(n) for name in ("position", "velocity", "effort", "kp", "kd", "target", "acceleration")
    }
    arrays["enabled"] = np.ones(n, dtype=bool)
    arrays["mode"] = np.full(n, int(ModeCode.POSITION), dtype=np.int8)
    arrays.update(values)
    return SetpointView(**arrays)


@pytest.mark.parametrize("name", ["arm3", "panda", "humanoid"])
async def test_the_effort_is_the_servo_plus_g_of_q_clamped_to_the_limit(name: str) -> None:
    """The actuator torque read back is ``clamp(kp e + kd ė + ff + g(q), ±max_effort)``, g(q) included."""
    async with agentsdk.connect("mujoco", robot=SIMULATOR_ROUTED[name], safety=SAFETY) as robot:
        b = robot.backend
        n = len(b.names)
        m, d = b.model, b.data
        host, g = GravityTerm(m, b.names), np.zeros(n)
        rng = np.random.default_rng(5)
        limit = np.array([j.max_effort for j in b.joints])
        for scale in (0.1, 3.0):  # within the limits, then far beyond them (saturated)
            ff = rng.uniform(-1.0, 1.0, n) * np.where(np.isfinite(limit), limit, 10.0) * scale
            b.write(_setpoint(n, effort=ff, mode=np.full(n, int(ModeCode.EFFORT), dtype=np.int8)))
            mujoco.mj_forward(m, d)
            host.compute(d.qpos, g)
            expected = np.clip(ff + g, -limit, limit)
            _, _, effort = b.read()
            np.testing.assert_allclose(effort, expected, rtol=0, atol=1e-9 * max(1.0, float(np.abs(g).max())))
            if scale > 1.0:
                assert np.any(np.abs(expected) == limit)


async def test_disabled_joints_and_the_emergency_stop_get_no_gravity_compensation() -> None:
    """Torque off is all of it off: a disabled joint's servo and gravity torque, every joint's after an e-stop."""
    async with agentsdk.connect("mujoco", robot=SIMULATOR_ROUTED["panda"], safety=SAFETY) as robot:
        b = robot.backend
        n = len(b.names)
        m, d = b.model, b.data
        enabled = np.ones(n, dtype=bool)
        enabled[1] = enabled[-1] = False  # panda_joint2 (carries the arm) and the finger (its follower too)
        b.write(_setpoint(n, enabled=enabled))
        mujoco.mj_forward(m, d)
        _, _, effort = b.read()
        assert effort[1] == 0.0 and effort[-1] == 0.0
        assert np.abs(effort[enabled]).max() > 0.1  # the others still hold their links
        assert not d.qfrc_actuator[np.flatnonzero(coupling_matrix(m, b.names)[:, [1, n - 1]].any(axis=1))].any()
        b.write(_setpoint(n))  # enabled again: g(q) back
        mujoco.mj_forward(m, d)
        assert abs(b.read()[2][1]) > 1.0
        b.emergency_stop(0)
        mujoco.mj_forward(m, d)
        assert not d.qfrc_actuator.any()


async def test_an_emergency_stop_lets_the_arm_fall() -> None:
    async with agentsdk.connect("mujoco", robot=SIMULATOR_ROUTED["ur5"], safety=SAFETY) as robot:
        q0 = (await robot.read()).position
        await robot.estop(0)
        await robot.clock.sleep(0.3)
        st = await robot.read()
        assert not np.any(st.effort)
        assert np.abs(st.position - q0).max() > 0.05


@pytest.mark.parametrize(
    ("robot", "extra", "route", "reason"),
    [
        ("leveler", "", "host", "free joint"),  # a floating base: its weight must not be held up
        ("ur5", "gravity_compensation: {default: true, elbow_joint: false}\n", "host", "some joints only"),
        ("ur5", "gravity_compensation: false\n", "off", ""),
        ("ur5", "", "simulator", ""),
    ],
)
async def test_where_gravity_compensation_is_computed(tmp_path: Path, robot: str, extra: str, route: str,
                                                      reason: str) -> None:
    if robot == "ur5":
        yaml = tmp_path / "robot.yaml"
        yaml.write_text(f"description: {SIMULATOR_ROUTED['ur5']}\n{extra}", encoding="utf-8")
        robot = str(yaml)
    async with agentsdk.connect("mujoco", robot=robot, safety=SAFETY) as r:
        b = r.backend
        assert b.gravity_route == route
        assert reason in b.gravity_route_reason
        assert (route == "simulator") == bool(b.model.body_gravcomp.any())
        assert (route == "host") == (b._gravity is not None)


async def test_a_floating_base_robot_is_not_held_up_by_its_compensation() -> None:
    async with agentsdk.connect("mujoco", robot="leveler", safety=SAFETY) as robot:
        z0 = robot.base_state().pose.position[2]
        await robot.clock.sleep(0.3)
        assert robot.base_state().pose.position[2] <= z0 + 1e-3


async def test_the_feed_forward_depends_on_the_setpoint_not_the_measured_state() -> None:
    """The inverse-dynamics term is evaluated at the desired state: the same setpoint, the same control."""
    async with agentsdk.connect("mujoco", robot=SIMULATOR_ROUTED["panda"], safety=SAFETY) as robot:
        b = robot.backend
        n = len(b.names)
        d = b.data
        rng = np.random.default_rng(11)
        sp = _setpoint(n, position=_random_poses(robot, 1, seed=2)[0], velocity=rng.uniform(-1, 1, n),
                       acceleration=rng.uniform(-3, 3, n), kp=np.full(n, 100.0), kd=np.full(n, 5.0))
        qpos0 = d.qpos.copy()
        b.write(sp)
        first = d.ctrl.copy()
        d.qpos[b._qadr] += rng.uniform(-0.3, 0.3, n)  # another measured state
        b.write(sp)
        np.testing.assert_array_equal(d.ctrl, first)
        # and the term is M(q*) a* + C(q*, v*) v* (+ damping, friction) at q* = the setpoint's position
        d.qpos[:] = qpos0
        at_rest = _setpoint(n, position=sp.position, kp=sp.kp, kd=sp.kd)
        b.write(at_rest)
        term = first - d.ctrl - sp.kd * sp.velocity
        s = coupling_matrix(b.model, b.names)
        m = b._inverse.model
        probe = mujoco.MjData(m)
        probe.qpos[:] = _place(robot, sp.position).qpos
        probe.qvel[:] = s @ sp.velocity
        probe.qacc[:] = s @ sp.acceleration.astype(np.float32).astype(float)
        mujoco.mj_inverse(m, probe)
        np.testing.assert_allclose(term, s.T @ probe.qfrc_inverse, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", ["arm3", "humanoid", "panda"])
async def test_a_planned_motion_runs_as_one_rollout_bit_for_bit(name: str) -> None:
    """No model term depends on the measured state: the controls of K ticks computed from their setpoints
    alone, run as one ``mujoco.rollout`` call, give tick-by-tick's states bit for bit (issue 28's block)."""
    from mujoco import rollout

    async with agentsdk.connect("mujoco", robot=SIMULATOR_ROUTED[name], safety=SAFETY) as robot:
        b = robot.backend
        m, d = b.model, b.data
        n, ticks, nsub = len(b.names), 150, b._nsub
        kp = np.array([g.p for g in robot.gains.values()])
        kd = np.array([g.d for g in robot.gains.values()])
        q0 = d.qpos[b._qadr].copy()
        goal = np.clip(q0 + np.random.default_rng(4).uniform(-0.3, 0.3, n), b.lower, b.upper)
        duration = ticks * b.period
        stream = []
        for k in range(ticks):  # a quintic from q0 to the goal: position, velocity and acceleration
            s = (k + 1) / ticks
            p, dp = 10 * s**3 - 15 * s**4 + 6 * s**5, (30 * s**2 - 60 * s**3 + 30 * s**4) / duration
            ddp = (60 * s - 180 * s**2 + 120 * s**3) / duration**2
            stream.append(_setpoint(n, position=q0 + p * (goal - q0), velocity=dp * (goal - q0),
                                    acceleration=ddp * (goal - q0), kp=kp, kd=kd, target=goal))
        full = mujoco.mjtState.mjSTATE_FULLPHYSICS
        start = np.empty(mujoco.mj_stateSize(m, full))
        mujoco.mj_getState(m, d, start, full)
        warmstart = d.qacc_warmstart.copy()
        expected = np.empty((ticks, start.size))
        for k, sp in enumerate(stream):  # tick by tick, as the loop runs them
            b.write(sp)
            await b.step(b.period)
            mujoco.mj_getState(m, d, expected[k], full)
        controls = np.empty((ticks * nsub, m.nu))
        for k, sp in enumerate(stream):  # the same setpoints from anywhere: the controls do not change
            d.qpos[b._qadr] = q0 - 0.1
            b.write(sp)
            controls[k * nsub : (k + 1) * nsub] = d.ctrl
        states, _ = rollout.rollout(m, mujoco.MjData(m), start, controls, initial_warmstart=warmstart)
        np.testing.assert_array_equal(states[0][nsub - 1 :: nsub], expected)
        assert np.abs(expected[-1, 1 : 1 + m.nq][b._qadr] - q0).max() > 0.05  # it moved


_MJCF = """<mujoco model="passive">
  <compiler angle="radian"/>
  <worldbody>
    <body name="l1" pos="0 0 0.5">
      <joint name="j1" axis="0 1 0" range="-2 2" actuatorfrcrange="-40 40"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="2"/>
      <body name="lp" pos="0.3 0 0">
        <joint axis="0 0 1" range="-1 1" damping="0.5"/>
        <geom type="capsule" fromto="0 0 0 0.1 0 0" size="0.03" mass="0.5"/>
        <body name="l2" pos="0.1 0 0">
          <joint name="j2" axis="0 1 0" range="-2 2" actuatorfrcrange="-20 20"/>
          <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
          {tip}
        </body>
      </body>
    </body>
  </worldbody>
  <keyframe><key name="home" qpos="0.3 0.2 -0.4{tip_q}"/></keyframe>
</mujoco>"""
_BALL_TIP = """<body name="bob" pos="0.3 0 0"><joint type="ball"/>
            <geom type="sphere" pos="0 0 -0.1" size="0.03" mass="0.3"/></body>"""


async def test_an_mjcf_passive_joint_gets_none_and_a_ball_joint_keeps_the_host_term(tmp_path: Path) -> None:
    """A passive (unnamed) hinge between commanded joints is left out, as the host term leaves it out;
    a ball joint below a commanded joint (its share cannot be clamped away) keeps the host term."""
    plain = tmp_path / "plain.xml"
    plain.write_text(_MJCF.format(tip="", tip_q=""), encoding="utf-8")
    async with agentsdk.connect("mujoco", robot=str(plain), safety=SAFETY) as robot:
        b = robot.backend
        assert list(b.names) == ["j1", "j2"]
        assert b.gravity_route == "simulator", b.gravity_route_reason
        m = b.model
        host, s_t, g = GravityTerm(m, b.names), coupling_matrix(m, b.names).T, np.zeros(2)
        for q in _random_poses(robot, 10, seed=8):
            d = _place(robot, q)
            d.qpos[1] = 0.7  # the passive joint anywhere
            mujoco.mj_forward(m, d)
            np.testing.assert_allclose(s_t @ d.qfrc_gravcomp, host.compute(d.qpos, g), rtol=0, atol=1e-12)
            assert d.qfrc_actuator[1] == 0.0  # the passive joint: no torque
        assert b.simulator_report()["joints"][1][3] == 20.0  # the effort limit is the joint's
    ball = tmp_path / "ball.xml"
    ball.write_text(_MJCF.format(tip=_BALL_TIP, tip_q=" 1 0 0 0"), encoding="utf-8")
    async with agentsdk.connect("mujoco", robot=str(ball), safety=SAFETY) as robot:
        assert robot.backend.gravity_route == "host"
        assert "ball joint" in robot.backend.gravity_route_reason


_OWN_GRAVCOMP = """<mujoco model="own_gravcomp">
  <compiler angle="radian"/>
  <worldbody>
    <body name="l1" pos="0 0 0.5"{gc}>
      <joint name="j1" axis="0 1 0" range="-2 2" actuatorfrcrange="-60 60"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="2"/>
      <body name="l2" pos="0.3 0 0"{gc}>
        <joint name="j2" axis="0 1 0" range="-2 2" actuatorfrcrange="-30 30"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
        <body name="tip" pos="0.3 0 0"{gc}>
          <joint name="j3" axis="0 1 0" range="-2 2" actuatorfrcrange="-10 10"/>
          <geom type="sphere" size="0.04" mass="0.5"/>
        </body>
      </body>
    </body>
  </worldbody>
  <keyframe><key name="home" qpos="0.4 -0.3 0.2"/></keyframe>
</mujoco>"""


async def test_an_mjcf_own_gravcomp_is_not_added_to_the_host_term(tmp_path: Path) -> None:
    """On the host route (compensation off for one joint), a model whose bodies carry their own
    ``gravcomp`` holds exactly as the same model without it: the host's g(q) holds each body once
    (before, MuJoCo's force held them a second time and the arm rose by 10 mrad)."""
    yaml_gc = "gravity_compensation: {default: true, j3: false}\n"
    finals = []
    for gc in ("", ' gravcomp="1"'):
        d = tmp_path / ("own" if gc else "plain")
        d.mkdir()
        (d / "arm.xml").write_text(_OWN_GRAVCOMP.format(gc=gc), encoding="utf-8")
        (d / "robot.yaml").write_text(f"description: arm.xml\n{yaml_gc}", encoding="utf-8")
        async with agentsdk.connect("mujoco", robot=str(d / "robot.yaml"), safety=SAFETY) as robot:
            b = robot.backend
            assert b.gravity_route == "host", b.gravity_route
            assert not b.model.body_gravcomp.any()  # the model's own gravcomp is the host term's now
            await robot.clock.sleep(1.0)
            finals.append((await robot.read()).position.copy())
    np.testing.assert_allclose(finals[1], finals[0], rtol=0, atol=1e-12)
