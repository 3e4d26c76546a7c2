"""Issue 24.2 and 24.6: PyBullet loads what MuJoCo loads, and a camera fixed to a tilting head does not stop it.

Fixtures (``tests/fixtures/mjcf_pybullet``): an arm whose light flange turns on a motor with a large
rotor inertia (MJCF ``armature``, as Menagerie's UR10e wrist), a small quadruped floating on a root
``<freejoint>`` without a floor, and models a URDF cannot carry (a tendon, two free bodies);
``tests/fixtures/head_camera``: a pan-tilt head with a camera fixed in front of the tilt axis.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import agentsdk
from agentsdk import JointCommand, ResultCode, SafetyState, UnsupportedModelError
from agentsdk.description.mjcf import load_mjcf
from agentsdk.description.mjcf_pybullet import mjcf_pybullet_fit

FIXTURES = Path(__file__).parent / "fixtures"
MJCF = FIXTURES / "mjcf_pybullet"
SIMULATORS = ("mujoco", "pybullet")


async def _hold_and_move(robot: agentsdk.Robot, hold: float = 2.0, delta: float = 0.25) -> tuple[float, float]:
    """Hold ``hold`` s, then ``move_to`` +``delta`` on every joint (inside the limits): (drift, goal error)."""
    q0 = np.array((await robot.read()).position)
    await robot.clock.sleep(hold)
    drift = float(np.abs(np.array((await robot.read()).position) - q0).max())
    lower = np.array([j.lower for j in robot.joints])
    upper = np.array([j.upper for j in robot.joints])
    goal = np.clip(q0 + delta, lower + 0.01, upper - 0.01)
    result = await robot.move_to(dict(zip((j.name for j in robot.joints), goal.tolist(), strict=True)))
    assert result.code is ResultCode.SUCCESSFUL, result
    error = float(np.abs(np.array((await robot.read()).position) - goal).max())
    return drift, error


@pytest.mark.parametrize("backend", SIMULATORS)
async def test_an_arm_with_armature_holds_and_moves(backend: str) -> None:
    """The flange's gains are sized with its rotor inertia (500 times its own): PyBullet simulates it too."""
    async with agentsdk.connect(backend, robot=MJCF / "armature_wrist.xml") as robot:
        drift, error = await _hold_and_move(robot)
        assert drift < 0.005 and error < 0.02
        assert robot.safety.state is SafetyState.OK


async def test_pybullet_accelerates_a_joint_with_its_rotor_inertia() -> None:
    """A torque step on the flange: on both simulators it turns as ``(I + armature) qdd = tau`` says, not 500
    times faster (PyBullet's rigid bodies alone would)."""
    moved: dict[str, float] = {}
    for backend in SIMULATORS:
        async with agentsdk.connect(backend, robot=MJCF / "armature_wrist.xml") as robot:
            q0 = (await robot.read()).position[2]
            for _ in range(50):  # 0.1 s at 500 Hz; gravity compensation holds the other joints
                await robot.command(JointCommand("effort", {"shoulder": 0.0, "elbow": 0.0, "wrist": 0.05}))
                await robot.clock.sleep(robot.control_period)
            moved[backend] = (await robot.read()).position[2] - q0
    expected = 0.5 * 0.05 / (0.0002 + 0.1) * 0.1**2  # 2.5 mrad (damping takes a little)
    for backend, angle in moved.items():
        assert 0.8 * expected < angle <= 1.05 * expected, (backend, angle, expected)
    assert moved["pybullet"] == pytest.approx(moved["mujoco"], rel=0.05)


async def test_a_free_joint_root_floats_on_pybullet_and_stands() -> None:
    """A root ``<freejoint>`` is the floating base: PyBullet floats the body on a ground plane (none in the
    file), starts it standing at the keyframe pose, and ``base_state()`` reports it."""
    async with agentsdk.connect("pybullet", robot=MJCF / "free_quad.xml") as robot:
        assert robot.backend.floating_base
        start = robot.base_state()
        z0 = float(start.pose.position[2])
        assert 0.2 < z0 < 0.3  # feet on the ground with the knees bent (keyframe "home")
        heights = []
        for _ in range(10):
            await robot.clock.sleep(0.3)
            heights.append(float(robot.base_state().pose.position[2]))
        assert max(abs(h - z0) for h in heights) < 0.2 * z0, heights
        assert robot.safety.state is SafetyState.OK
        state = robot.base_state()
        assert np.linalg.norm(state.linear_velocity) < 0.05
        # upright: the torso's z axis still points up
        assert state.pose.rotation[2, 2] > 0.99


async def test_a_free_joint_root_can_be_welded_to_the_world() -> None:
    """``floating_base=False`` welds the free body where the file puts it: a fixed-base robot."""
    async with agentsdk.connect("pybullet", robot=MJCF / "free_quad.xml", floating_base=False) as robot:
        assert not robot.backend.floating_base
        assert robot.base_state().pose.position.tolist() == [0.0, 0.0, 0.0]
        drift, error = await _hold_and_move(robot, hold=0.5, delta=0.1)
        assert drift < 0.005 and error < 0.02


@pytest.mark.parametrize(
    ("model", "named"),
    [
        ("tendon_arm.xml", "fixed tendon 'coupling' with a length range"),
        ("two_free_bodies.xml", "free joints other than one at the root (a, b)"),
    ],
)
async def test_what_a_urdf_cannot_carry_is_refused_by_name(model: str, named: str) -> None:
    with pytest.raises(UnsupportedModelError, match=r"PyBullet cannot load .*" + named.replace("(", r"\(")
                       .replace(")", r"\)")):
        async with agentsdk.connect("pybullet", robot=MJCF / model):
            pass
    async with agentsdk.connect("mujoco", robot=MJCF / model) as robot:  # MuJoCo simulates it
        await robot.clock.sleep(0.05)


@pytest.mark.parametrize("backend", SIMULATORS)
async def test_a_camera_fixed_to_a_tilting_head_does_not_stop_the_tilt(backend: str) -> None:
    """Issue 24.6 (Hello Robot Stretch's head): the camera is fixed to the tilt link, so it is adjacent to the
    pan link the tilt turns against (MoveIt and MuJoCo's parent filter see it so); tilting 0.25 rad used to
    stop at 0.14 where the camera's box met the pan plate's (GOAL_TOLERANCE_VIOLATED)."""
    async with agentsdk.connect(backend, robot=FIXTURES / "head_camera" / "head.urdf") as robot:
        collision = robot.backend.collision
        assert collision is not None
        assert collision.excluded[("camera", "pan")] == "adjacent"
        assert ("camera", "neck") in collision.pairs  # not adjacent: it still collides
        result = await robot.move_to({"joint_tilt": 0.25})
        assert result.code is ResultCode.SUCCESSFUL, result
        assert abs((await robot.read()).position[1] - 0.25) < 0.02


@pytest.mark.parametrize("backend", SIMULATORS)
async def test_a_tendon_driven_linkage_is_commanded_joint_by_joint(
    backend: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A fixed tendon that only transmits the model's actuator and a connect constraint that closes a
    parallelogram (Menagerie's xArm7 gripper): PyBullet drops both, naming each; both simulators command every
    joint on its own, hold the linkage and move it along a pose that keeps the loop closed."""
    async with agentsdk.connect(backend, robot=MJCF / "tendon_linkage.xml") as robot:
        assert [j.name for j in robot.joints] == ["j1", "j3", "j2"]
        q0 = np.array((await robot.read()).position)
        await robot.clock.sleep(1.0)
        assert float(np.abs(np.array((await robot.read()).position) - q0).max()) < 0.005
        result = await robot.move_to({"j1": 0.55, "j3": -0.55, "j2": 0.55})  # still a parallelogram
        assert result.code is ResultCode.SUCCESSFUL, result
        assert np.abs(np.array((await robot.read()).position) - [0.55, -0.55, 0.55]).max() < 0.02
        if backend == "pybullet":
            # the loop is open: a command that breaks the parallelogram moves that joint alone (MuJoCo's
            # constraint would hold the coupler on the second crank)
            result = await robot.move_to({"j1": 0.55, "j3": -0.3, "j2": 0.55})
            assert result.code is ResultCode.SUCCESSFUL, result
            assert abs((await robot.read()).position[1] + 0.3) < 0.02
        assert robot.safety.state is SafetyState.OK
    warned = [r.getMessage() for r in caplog.records if "PyBullet leaves out" in r.getMessage()]
    if backend == "mujoco":
        assert warned == []
    else:
        assert len(warned) == 2, warned
        assert "fixed tendon 'drive'" in warned[0]
        assert "connect 'close' constraint between bodies 'coupler' and 'crank2'" in warned[1]


@pytest.mark.parametrize(
    ("extra", "refused"),
    [
        ('<tendon><fixed name="t" damping="1"><joint joint="j1" coef="1"/></fixed></tendon>',
         "fixed tendon 't' with damping"),
        ('<tendon><fixed name="t" stiffness="2"><joint joint="j1" coef="1"/></fixed></tendon>',
         "fixed tendon 't' with stiffness"),
        ('<equality><weld name="w" body1="b"/></equality>',
         "equality constraints other than joint coupling or linkage closure (weld 'w')"),
        ('<equality><connect name="c" body1="b" body2="a" anchor="0 0 0"/></equality>', None),
    ],
)
def test_what_pybullet_drops_and_what_it_refuses(tmp_path: Path, extra: str, refused: str | None) -> None:
    """The rule, on elements nobody named: a tendon acting by itself or a weld to the world has no URDF form;
    a connect between two moving bodies closes a loop and is dropped."""
    path = tmp_path / "m.xml"
    path.write_text(
        '<mujoco><worldbody><body name="a"><joint name="j1" axis="0 1 0" range="-1 1"/>'
        '<geom type="sphere" size="0.05" mass="1"/><body name="b" pos="0.2 0 0"><joint name="j2" axis="0 1 0" '
        f'range="-1 1"/><geom type="sphere" size="0.05" mass="1"/></body></body></worldbody>{extra}</mujoco>'
    )
    dropped, unsupported = mjcf_pybullet_fit(load_mjcf(path))
    if refused is None:
        assert unsupported == [] and len(dropped) == 1
        assert "connect 'c' constraint between bodies 'b' and 'a'" in dropped[0]
    else:
        assert unsupported == [refused] and dropped == []


#: a wrist like Menagerie's Lite6: the flange (link3) folds back against link1 at the start pose (they overlap
#: by 5 mm; not parent and child, so MuJoCo's parent filter does not cover them)
FOLDED_WRIST = """<mujoco model="folded_wrist">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="0.002"/>
  <default><joint axis="0 1 0" range="-2.5 2.5" damping="0.5" armature="0.01"/></default>
  <worldbody>
    <body name="base"><geom type="cylinder" size="0.05 0.02" mass="2"/>
      <body name="link1" pos="0 0 0.05"><joint name="j1" axis="0 0 1"/>
        <geom type="box" size="0.03 0.03 0.06" pos="0 0 0.06" mass="1"/>
        <body name="link2" pos="0 0 0.15"><joint name="j2"/>
          <geom type="capsule" fromto="0 0 0 0.08 0 0" size="0.015" mass="0.4"/>
          <body name="link3" pos="0.08 0 0"><joint name="j3"/>
            <geom type="box" size="0.02 0.02 0.06" pos="-0.045 0 -0.06" mass="0.2"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("backend", SIMULATORS)
async def test_links_touching_at_the_start_pose_do_not_collide_on_either_simulator(
    tmp_path: Path, backend: str
) -> None:
    path = tmp_path / "folded_wrist.xml"
    path.write_text(FOLDED_WRIST)
    async with agentsdk.connect(backend, robot=path) as robot:
        if backend == "pybullet":
            assert robot.backend.collision.excluded.get(("link1", "link3")) == "touching at the start pose"
        q0 = np.array((await robot.read()).position)
        await robot.clock.sleep(1.0)
        drift = float(np.abs(np.array((await robot.read()).position) - q0).max())
        assert drift < 0.005, f"drift {drift:.4f} rad: the touching links push each other"


@pytest.mark.parametrize("simulator", SIMULATORS)
async def test_a_main_file_whose_contacts_are_scene_pairs_stands_beside_an_empty_world_body(
    tmp_path: Path, simulator: str
) -> None:
    """Like Menagerie's Apollo main file: no geom has a contact bit (the scene file's explicit pairs touch the
    floor) and an empty marker body is fixed to the world beside the floating base."""
    xml = (MJCF / "free_quad.xml").read_text()
    xml = xml.replace("<default>\n", '<default>\n    <geom contype="0" conaffinity="0"/>\n', 1)
    xml = xml.replace("<worldbody>\n", '<worldbody>\n    <body name="world_link"/>\n', 1)
    path = tmp_path / "free_quad.xml"
    path.write_text(xml)
    desc = load_mjcf(path)
    assert desc.free_root == "torso" and mjcf_pybullet_fit(desc)[1] == []
    async with agentsdk.connect(simulator, robot=path) as robot:
        z0 = float(robot.base_state().pose.position[2])
        assert 0.2 < z0 < 0.3  # on its feet
        for _ in range(6):
            await robot.clock.sleep(0.3)
            z = float(robot.base_state().pose.position[2])
            assert abs(z - z0) < 0.2 * z0, f"base at {z:.3f} m from {z0:.3f} m"
        assert robot.safety.state is SafetyState.OK
