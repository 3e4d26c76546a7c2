"""Issue 24: the servo gains an MJCF declares (its position actuators) are the default gains.

robot.yaml ``gains`` first, then the description's own position servos (``kp``/``kv``, or ``dampratio``,
times ``gear**2``), then gains from the model (:func:`agentsdk.dynamics.model_gains`) for the joints
the description gives none. Self-contained models written here; the Menagerie counterparts (Apollo
standing on its actuators' gains) are in test_menagerie.py and test_menagerie_pybullet.py.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

import agentsdk
from agentsdk.description import load_description
from agentsdk.description.actuators import declared_servo_gains
from agentsdk.dynamics import STABILITY_FRACTION

pytestmark = pytest.mark.timeout(120)

#: a four-joint arm: j1 a position servo (kp, kv), j2 a position servo with a gear of 2 and dampratio,
#: j3 a motor (torque actuator: no servo declared), j4 a position servo without damping (kv = 0)
ARM = """
<mujoco model="declared_gains_arm">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="0.001"/>
  <default>
    <joint axis="0 1 0" range="-2 2" damping="0.01"/>
    <geom type="capsule" size="0.02" contype="0" conaffinity="0"/>
  </default>
  <worldbody>
    <body name="base">
      <geom type="cylinder" size="0.05 0.02"/>
      <body name="l1" pos="0 0 0.05">
        <joint name="j1" axis="0 0 1"/>
        <inertial pos="0 0 0.05" mass="1" diaginertia="0.004 0.004 0.002"/>
        <geom fromto="0 0 0 0 0 0.1"/>
        <body name="l2" pos="0 0 0.1">
          <joint name="j2"/>
          <inertial pos="0 0 0.1" mass="0.6" diaginertia="0.002 0.002 0.0005"/>
          <geom fromto="0 0 0 0 0 0.2"/>
          <body name="l3" pos="0 0 0.2">
            <joint name="j3"/>
            <inertial pos="0 0 0.1" mass="0.4" diaginertia="0.001 0.001 0.0002"/>
            <geom fromto="0 0 0 0 0 0.2"/>
            <body name="l4" pos="0 0 0.2">
              <joint name="j4"/>
              <inertial pos="0 0 0.03" mass="0.1" diaginertia="0.0001 0.0001 0.00002"/>
              <geom fromto="0 0 0 0 0 0.06"/>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position name="a1" joint="j1" kp="300" kv="12" forcerange="-40 40"/>
    <position name="a2" joint="j2" kp="100" dampratio="1" gear="2" forcerange="-30 30"/>
    <motor name="a3" joint="j3" ctrlrange="-20 20"/>
    <position name="a4" joint="j4" kp="30" forcerange="-5 5"/>
  </actuator>
  <keyframe>
    <key name="home" qpos="0.2 0.5 -0.8 0.3"/>
  </keyframe>
</mujoco>
"""


@pytest.fixture
def arm(tmp_path: Path) -> Path:
    path = tmp_path / "arm.xml"
    path.write_text(ARM)
    return path


def test_position_servos_are_read_as_joint_gains(arm: Path) -> None:
    m = mujoco.MjModel.from_xml_path(str(arm))
    by_name = {m.joint(j).name: g for j, g in declared_servo_gains(m).items()}
    assert set(by_name) == {"j1", "j2", "j4"}  # the motor declares no servo
    assert by_name["j1"] == pytest.approx((300.0, 12.0))
    kp2, kd2 = by_name["j2"]
    assert kp2 == pytest.approx(100.0 * 2**2)  # on the joint: kp gear^2
    assert kd2 > 0.0  # dampratio became kv at compile time
    assert by_name["j4"] == (30.0, 0.0)
    desc = load_description(arm)
    assert dict(desc.declared_gains) == by_name


@pytest.mark.parametrize(
    "actuator",
    [
        '<velocity joint="j" kv="5"/>',  # a velocity servo: no position gain
        '<intvelocity joint="j" kp="50" actrange="-1 1"/>',  # an integrator in front: not a position servo
        '<general joint="j" gainprm="50" biastype="affine" biasprm="0 -20 -1"/>',  # bias and gain disagree
        '<motor joint="j"/>',
    ],
)
def test_other_actuators_declare_no_servo(tmp_path: Path, actuator: str) -> None:
    path = tmp_path / "one.xml"
    path.write_text(
        '<mujoco><worldbody><body><joint name="j" axis="0 1 0"/><geom size="0.1"/></body></worldbody>'
        f"<actuator>{actuator}</actuator></mujoco>"
    )
    assert declared_servo_gains(mujoco.MjModel.from_xml_path(str(path))) == {}


def test_a_general_actuator_written_as_a_position_servo_counts_and_two_on_one_joint_add(tmp_path: Path) -> None:
    path = tmp_path / "two.xml"
    path.write_text(
        '<mujoco><worldbody><body><joint name="j" axis="0 1 0"/><geom size="0.1"/></body></worldbody><actuator>'
        '<general joint="j" gainprm="50" biastype="affine" biasprm="0 -50 -3"/>'
        '<position joint="j" kp="10" kv="1"/></actuator></mujoco>'
    )
    assert declared_servo_gains(mujoco.MjModel.from_xml_path(str(path))) == {0: pytest.approx((60.0, 4.0))}


@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
async def test_declared_gains_are_the_default_and_the_model_fills_in(arm: Path, backend: str) -> None:
    async with agentsdk.connect(backend, robot=arm) as robot:
        ctl = robot.backend
        assert ctl.gain_sources == ("description", "description", "model", "description")
        declared = ctl.description.declared_gains
        gains = robot.gains
        assert (gains["j1"].p, gains["j1"].d) == pytest.approx(declared["j1"])
        assert (gains["j2"].p, gains["j2"].d) == pytest.approx(declared["j2"])
        report = ctl.model_gain_report
        assert (gains["j3"].p, gains["j3"].d) == pytest.approx((report.kp[2], report.kd[2]))
        # kv = 0 declared no damping: critically damped with the joint's own damping (0.01) counted
        kd4 = 2.0 * np.sqrt(30.0 * report.inertia[3]) - 0.01
        assert gains["j4"].p == pytest.approx(30.0) and gains["j4"].d == pytest.approx(kd4)
        q0 = (await robot.read()).position.copy()
        np.testing.assert_allclose(q0, [0.2, 0.5, -0.8, 0.3], atol=1e-9)
        await robot.clock.sleep(1.0)
        assert np.abs((await robot.read()).position - q0).max() < 0.005  # gravity fed forward: the soft servo holds
        goal = {"j1": 0.45, "j2": 0.75, "j3": -0.55, "j4": 0.55}
        result = await robot.move_to(goal)
        assert result.ok, result
        assert max(abs(e) for e in result.error.values()) < 0.02


async def test_robot_yaml_gains_win(arm: Path, tmp_path: Path) -> None:
    yaml = tmp_path / "robot.yaml"
    yaml.write_text(f"description: {arm}\ngains:\n  j1: {{p: 77.0, d: 3.0}}\n")
    async with agentsdk.connect("mujoco", robot=yaml) as robot:
        assert robot.backend.gain_sources[0] == "robot.yaml"
        assert (robot.gains["j1"].p, robot.gains["j1"].d) == (77.0, 3.0)
        assert robot.backend.gain_sources[1] == "description"


async def test_declared_gains_too_stiff_for_the_timestep_are_lowered(tmp_path: Path) -> None:
    # a 10 g link on a 1e5 N·m/rad servo at the simulator's 1 ms step: kp h^2 is far beyond 4 I (as declared it
    # would diverge)
    path = tmp_path / "stiff.xml"
    path.write_text(
        '<mujoco><compiler angle="radian"/><worldbody><body><joint name="j" axis="0 1 0" range="-2 2"/>'
        '<inertial pos="0 0 0.05" mass="0.01" diaginertia="1e-5 1e-5 1e-6"/></body></worldbody>'
        '<actuator><position joint="j" kp="1e5" kv="1"/></actuator></mujoco>'
    )
    async with agentsdk.connect("mujoco", robot=path) as robot:
        ctl = robot.backend
        report = ctl.model_gain_report
        h = ctl.servo_timestep
        bound = STABILITY_FRACTION * (4.0 * report.inertia_free[0] + 2.0 * h * 1.0) / h**2
        assert robot.gains["j"].p == pytest.approx(bound) and robot.gains["j"].p < 1e5
        assert robot.gains["j"].d == 1.0
        result = await robot.move_to({"j": 0.3})
        assert result.ok, result


def test_check_says_where_the_gains_came_from(arm: Path, tmp_path: Path) -> None:
    from agentsdk.check import check_robot

    report = check_robot(arm, backends=["mujoco"])
    text = "\n".join(report.lines)
    assert "servo gains on mujoco (the description's position actuators (kp, kv; lowered only where a " \
           "simulator's timestep requires) for 3; from the model, agentsdk.dynamics.model_gains for 1;" in text
    assert "j1 p=300 d=12" in text
    yaml = tmp_path / "robot.yaml"
    yaml.write_text(f"description: {arm}\ngains:\n  default: {{p: 50.0, d: 2.0}}\n")
    text = "\n".join(check_robot(yaml, backends=["mujoco"]).lines)
    assert "servo gains on mujoco (robot.yaml; p N·m/rad" in text
