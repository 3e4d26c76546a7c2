"""Bring your own robot: the description's repairs, self-collision model, mimic joints and MJCF on every backend."""

from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pybullet as p
import pytest

import agentsdk
from agentsdk import JointCommand
from agentsdk.description import load_description, resolve_robot
from agentsdk.description.collision import self_collision
from agentsdk.errors import BackendStartError, DescriptionError

FIXTURES = Path(__file__).parent / "fixtures"
MJCF_SCENE = FIXTURES / "mjcf_arm" / "scene.xml"
SIMS = ("mujoco", "pybullet")


def _inertial(mass: float = 1.0, i: float = 0.01, extra: str = "") -> str:
    return (
        f'<inertial><mass value="{mass}"/>{extra}'
        f'<inertia ixx="{i}" iyy="{i}" izz="{i}" ixy="0" ixz="0" iyz="0"/></inertial>'
    )


def _box(size: str, xyz: str = "0 0 0") -> str:
    return f'<collision><origin xyz="{xyz}"/><geometry><box size="{size}"/></geometry></collision>'


def _write(tmp_path: Path, text: str, name: str = "robot.urdf") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


async def _settle(robot: agentsdk.Robot, seconds: float) -> np.ndarray:
    await robot.clock.sleep(seconds)
    return (await robot.read()).position


def _sim_joint_position(robot: agentsdk.Robot, joint: str) -> float:
    """A joint's position as the simulator holds it (also for joints that are not commanded)."""
    ctl: Any = robot.backend
    if robot.backend.name == "mujoco":
        return float(ctl.data.qpos[ctl.model.joint(joint).qposadr[0]])
    index = next(i for i in range(p.getNumJoints(ctl._body, physicsClientId=ctl._cid))
                 if p.getJointInfo(ctl._body, i, physicsClientId=ctl._cid)[1].decode() == joint)
    return float(p.getJointState(ctl._body, index, physicsClientId=ctl._cid)[0])


# --------------------------------------------------------------------------- a root link touching its child

TOUCHING_ROOT = f"""<?xml version="1.0"?>
<robot name="touching_root">
  <link name="base">{_inertial(2.0)}{_box("0.3 0.3 0.2")}</link>
  <link name="arm">{_inertial(0.5, 0.005)}{_box("0.1 0.1 0.3", "0 0 0.1")}</link>
  <joint name="joint1" type="revolute">
    <parent link="base"/><child link="arm"/><origin xyz="0 0 0.05"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="20" velocity="2"/>
  </joint>
</robot>
"""


@pytest.mark.parametrize("backend", SIMS)
async def test_a_root_link_touching_its_first_child_does_not_block_the_joint(tmp_path: Path, backend: str) -> None:
    """The common URDF without a world link: the root overlaps its child; the joint must still move."""
    path = _write(tmp_path, TOUCHING_ROOT)
    async with agentsdk.connect(backend, robot=path) as robot:
        await robot.command(JointCommand("position", {"joint1": 0.3}))
        q = await _settle(robot, 1.5)
        assert q[0] == pytest.approx(0.3, abs=0.01), f"{backend}: joint1 at {q[0]:.4g}"
        assert robot.safety.state.name == "OK"
        report = robot.backend.simulator_report()  # type: ignore[attr-defined]
        assert report["pairs"] == []  # the only pair is adjacent


# --------------------------------------------------------------------------- mimic joints

MIMIC = f"""<?xml version="1.0"?>
<robot name="gripper">
  <link name="world"/>
  <link name="palm">{_inertial(1.0)}</link>
  <link name="finger_a">{_inertial(0.1, 1e-4)}</link>
  <link name="finger_b">{_inertial(0.1, 1e-4)}</link>
  <link name="finger_c">{_inertial(0.1, 1e-4)}</link>
  <joint name="mount" type="fixed"><parent link="world"/><child link="palm"/></joint>
  <joint name="finger" type="revolute">
    <parent link="palm"/><child link="finger_a"/><origin xyz="0.05 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="5" velocity="2"/>
  </joint>
  <joint name="finger_mirror" type="revolute">
    <parent link="palm"/><child link="finger_b"/><origin xyz="-0.05 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="5" velocity="2"/>
    <mimic joint="finger" multiplier="-0.5" offset="0.1"/>
  </joint>
  <joint name="finger_chain" type="revolute">
    <parent link="finger_b"/><child link="finger_c"/><origin xyz="0 0.05 0"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="5" velocity="2"/>
    <mimic joint="finger_mirror" multiplier="2" offset="0"/>
  </joint>
</robot>
"""


def test_mimic_chains_resolve_to_the_commanded_joint(tmp_path: Path) -> None:
    desc = load_description(_write(tmp_path, MIMIC))
    assert desc.joint_names == ("finger",)
    chain = desc.joint_record("finger_chain")
    # q_chain = 2 * q_mirror = 2 * (-0.5 q + 0.1) = -q + 0.2
    assert (chain.mimic, chain.mimic_multiplier, chain.mimic_offset) == ("finger", -1.0, pytest.approx(0.2))


@pytest.mark.parametrize("backend", SIMS)
async def test_mimic_joints_follow_their_leader_and_are_not_commanded(tmp_path: Path, backend: str) -> None:
    path = _write(tmp_path, MIMIC)
    async with agentsdk.connect(backend, robot=path) as robot:
        assert robot.joint_names == ("finger",)
        assert _sim_joint_position(robot, "finger_mirror") == pytest.approx(0.1, abs=1e-6)  # offset at the start
        await robot.command(JointCommand("position", {"finger": 0.4}))
        q = await _settle(robot, 1.0)
        assert q[0] == pytest.approx(0.4, abs=0.01)
        assert _sim_joint_position(robot, "finger_mirror") == pytest.approx(-0.5 * 0.4 + 0.1, abs=0.01)
        assert _sim_joint_position(robot, "finger_chain") == pytest.approx(-0.4 + 0.2, abs=0.01)


# --------------------------------------------------------------------------- degenerate masses (issue 10, item 8)

DEGENERATE = f"""<?xml version="1.0"?>
<robot name="degenerate">
  <link name="world"/>
  <link name="base">{_inertial(1.0)}</link>
  <link name="massless"/>
  <link name="negative">
    <inertial><mass value="0.2"/><inertia ixx="-0.001" iyy="0.002" izz="0.002" ixy="0" ixz="0" iyz="0"/></inertial>
  </link>
  <link name="zero">{_inertial(0.0, 0.0)}</link>
  <joint name="mount" type="fixed"><parent link="world"/><child link="base"/></joint>
  <joint name="j1" type="revolute"><parent link="base"/><child link="massless"/><axis xyz="0 0 1"/>
    <limit lower="-2" upper="2" effort="10" velocity="2"/></joint>
  <joint name="j2" type="revolute"><parent link="massless"/><child link="negative"/><axis xyz="1 0 0"/>
    <limit lower="-2" upper="2" effort="10" velocity="2"/></joint>
  <joint name="j3" type="continuous"><parent link="negative"/><child link="zero"/><axis xyz="0 1 0"/>
    <limit effort="10" velocity="2"/></joint>
</robot>
"""


def test_degenerate_masses_are_repaired_once_with_one_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = _write(tmp_path, DEGENERATE)
    with caplog.at_level("WARNING", logger="agentsdk.description"):
        desc = load_description(path)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1
    text = warnings[0]
    assert "link 'massless' (line 5): moving link (joint 'j1') has no <inertial>: raised to mass 1e-05 kg" in text
    assert "link 'negative'" in text and "negative principal moment -0.001 clamped to 0" in text
    assert "link 'zero'" in text and "boundmass" in text
    # the repaired values are kept in the description, the file's beside them
    negative = desc.link("negative")
    assert negative.inertial_as_written is not None and negative.inertial_as_written.inertia[0] == -0.001
    assert min(negative.inertial.principal()[0]) >= 0  # type: ignore[union-attr]
    with pytest.raises(DescriptionError, match="strict mode refuses the 3 repairs"):
        load_description(path, strict=True)


@pytest.mark.parametrize("backend", SIMS)
async def test_degenerate_masses_give_the_same_robot_that_moves_on_both_simulators(
    tmp_path: Path, backend: str
) -> None:
    """PyBullet used to accept zero mass / negative inertia and never move the joint; MuJoCo refused the file."""
    path = _write(tmp_path, DEGENERATE)
    desc = load_description(path, warn=False)
    async with agentsdk.connect(backend, robot=path) as robot:
        masses = robot.backend.simulator_report()["masses"]  # type: ignore[attr-defined]
        for rec in desc.link_records:
            if rec.name in masses:
                assert masses[rec.name] == pytest.approx(rec.mass, rel=1e-12), rec.name
        assert masses["massless"] == pytest.approx(1e-5)
        await robot.command(JointCommand("position", {"j1": 0.5, "j2": 0.3, "j3": -0.4}))
        q = await _settle(robot, 2.0)
        np.testing.assert_allclose(q, [0.5, 0.3, -0.4], atol=0.02)


async def test_strict_connect_refuses_repairs(tmp_path: Path) -> None:
    path = _write(tmp_path, DEGENERATE)
    with pytest.raises(DescriptionError, match=r"strict mode refuses .*\n  - link 'massless'"):
        await agentsdk.connect("mock", robot=path, strict=True)
    (tmp_path / "robot.yaml").write_text("description: robot.urdf\nstrict: true\n")
    with pytest.raises(DescriptionError, match="strict mode refuses"):
        await agentsdk.connect("mock", robot=tmp_path / "robot.yaml")
    async with agentsdk.connect("mock", robot=tmp_path / "robot.yaml", strict=False) as robot:
        assert robot.joint_names == ("j1", "j2", "j3")


# --------------------------------------------------------------------------- parse like ROS


def test_what_urdfdom_accepts_loads(tmp_path: Path) -> None:
    """Namespaced attributes, zero limits, a continuous joint without <limit>, a zero sphere, package:///."""
    (tmp_path / "pkg" / "meshes").mkdir(parents=True)
    shutil.copy(FIXTURES / "mesh_pkg" / "meshes" / "link.stl", tmp_path / "pkg" / "meshes" / "link.stl")
    (tmp_path / "pkg" / "package.xml").write_text("<package><name>pkg</name></package>")
    urdf = f"""<?xml version="1.0"?>
<robot name="lenient">
  <link name="base">{_inertial()}</link>
  <link name="a">{_inertial(0.5, 0.001)}
    <collision><geometry><sphere radius="0"/></geometry></collision>
    <visual><geometry><mesh filename="package:///pkg/meshes/link.stl"/></geometry></visual>
  </link>
  <link name="b">{_inertial(0.5, 0.001)}</link>
  <joint name="ja" type="revolute">
    <parent link="base"/><child link="a"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="0" velocity="0" drake:acceleration="20"/>
  </joint>
  <joint name="jb" type="continuous"><parent link="a"/><child link="b"/></joint>
</robot>
"""
    desc = load_description(_write(tmp_path / "pkg", urdf))
    a, b = desc.joint("ja"), desc.joint("jb")
    assert (a.lower, a.upper, a.max_velocity, a.max_effort) == (-1.0, 1.0, 1.0, math.inf)
    assert (b.type, b.lower, b.upper) == ("continuous", -math.inf, math.inf)
    assert (b.max_velocity, b.max_effort) == (1.0, math.inf)
    assert b.axis == (1.0, 0.0, 0.0)  # urdfdom's default axis
    assert [str(r) for r in desc.repairs] == [
        "link 'a' <collision> (line 5): sphere radius 0 is not positive: dropped",
        "joint 'ja' (line 11): velocity limit 0 -> 1; effort limit 0 -> unlimited",
    ]
    assert [str(r) for r in desc.defaults] == [
        "joint 'jb' (line 13): continuous joint without <limit>: velocity 1, effort unlimited"
    ]
    assert desc.link("a").visuals[0].filename == (tmp_path / "pkg" / "meshes" / "link.stl").resolve()


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ('<link name="base"/><link name="a"/><joint name="j" type="revolute"><parent link="base"/>'
         '<child link="nowhere"/><limit effort="1" velocity="1"/></joint>',
         r"line 2: joint 'j': child link 'nowhere' is not defined"),
        ('<link name="base"/><link name="a"/><joint name="j" type="fixed"><parent link="a"/><child link="base"/>'
         '</joint><joint name="k" type="fixed"><parent link="base"/><child link="a"/></joint>',
         r"line 1: the joints form a loop"),
        ('<link name="base"/><link name="a"/><joint name="j" type="revolute"><parent link="base"/>'
         '<child link="a"/></joint>', r"line 2: joint 'j': a revolute joint needs a <limit"),
        ('<link name="base"/><link name="a"/><joint name="j" type="prismatic"><parent link="base"/>'
         '<child link="a"/><limit lower="0" upper="1" velocity="1"/></joint>',
         r"line 2: joint 'j': <limit> is missing the 'effort' attribute"),
        ('<link name="base"><inertial><mass value="abc"/></inertial></link>', r"line 2: link 'base'.*not a number"),
        ('<link name="base"/><link name="a"/><joint name="j" type="revolute"><parent link="base"/>'
         '<child link="a"/><limit effort="1" velocity="1"/><mimic joint="k"/></joint>'
         '<link name="b"/><joint name="k" type="revolute"><parent link="a"/>'
         '<child link="b"/><limit effort="1" velocity="1"/><mimic joint="j"/></joint>',
         r"line 2: joint 'j': mimic joints form a cycle \(j -> k -> j\)"),
    ],
)
def test_broken_files_name_file_line_and_element(tmp_path: Path, body: str, message: str) -> None:
    path = _write(tmp_path, f'<robot name="r">\n{body}\n</robot>\n')
    with pytest.raises(DescriptionError, match=r"robot\.urdf, " + message):
        load_description(path)


def test_bad_xml_names_file_and_line(tmp_path: Path) -> None:
    path = _write(tmp_path, '<robot name="r">\n<link name="a">\n</robot>\n')
    with pytest.raises(DescriptionError, match=r"robot\.urdf: malformed XML: .*line 3"):
        load_description(path)


def test_links_written_child_first_load_on_pybullet(tmp_path: Path) -> None:
    """UR writes its world link last: with URDF_MAINTAIN_LINK_ORDER that used to kill the process."""
    urdf = f"""<robot name="unordered">
  <link name="tool">{_inertial(0.2, 1e-3)}</link>
  <joint name="j2" type="revolute"><parent link="arm"/><child link="tool"/><origin xyz="0 0 0.3"/>
    <axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="10" velocity="1"/></joint>
  <link name="arm">{_inertial(1.0, 1e-2)}</link>
  <joint name="j1" type="revolute"><parent link="world"/><child link="arm"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="10" velocity="1"/></joint>
  <link name="world"/>
</robot>"""
    desc = load_description(_write(tmp_path, urdf))
    assert desc.joint_names == ("j2", "j1")  # document order
    assert desc.tree_order() == ("world", "arm", "tool")
    from agentsdk.probe import probe_in_subprocess

    result = probe_in_subprocess(str(tmp_path / "robot.urdf"), "pybullet")
    assert result["loaded"] and result["ok"], result


# --------------------------------------------------------------------------- one self-collision model

SIBLINGS = f"""<?xml version="1.0"?>
<robot name="siblings">
  <link name="world"/>
  <link name="base">{_inertial(2.0)}{_box("0.1 0.1 0.1")}</link>
  <link name="left">{_inertial(0.2, 1e-3)}{_box("0.05 0.05 0.2", "0 0 0.1")}</link>
  <link name="right">{_inertial(0.2, 1e-3)}{_box("0.05 0.05 0.2", "0 0 0.1")}</link>
  <link name="far">{_inertial(0.2, 1e-3)}{_box("0.05 0.05 0.2", "0 0 0.1")}</link>
  <joint name="mount" type="fixed"><parent link="world"/><child link="base"/></joint>
  <joint name="jl" type="revolute"><parent link="base"/><child link="left"/><origin xyz="0.025 0 0.05"/>
    <axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="10" velocity="2"/></joint>
  <joint name="jr" type="revolute"><parent link="base"/><child link="right"/><origin xyz="-0.0249 0 0.05"/>
    <axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="10" velocity="2"/></joint>
  <joint name="jf" type="revolute"><parent link="base"/><child link="far"/><origin xyz="0.3 0 0.05"/>
    <axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="10" velocity="2"/></joint>
</robot>
"""


def test_self_collision_rules(tmp_path: Path) -> None:
    desc = load_description(_write(tmp_path, SIBLINGS))
    auto = self_collision(desc)
    assert auto.excluded == {
        ("base", "far"): "adjacent",
        ("base", "left"): "adjacent",
        ("base", "right"): "adjacent",
        ("left", "right"): "touching at the start pose",
    }
    assert auto.pairs == {("far", "left"), ("far", "right")}
    assert self_collision(desc, mode=True).pairs == {("far", "left"), ("far", "right"), ("left", "right")}
    assert self_collision(desc, mode=False).pairs == frozenset()
    # the touching test runs at the start pose: spread apart, left and right no longer touch
    assert ("left", "right") in self_collision(desc, start={"jl": 0.5, "jr": -0.5}).pairs


@pytest.mark.parametrize("backend", SIMS)
async def test_srdf_beside_the_urdf_or_named_in_robot_yaml_is_honoured(tmp_path: Path, backend: str) -> None:
    _write(tmp_path, SIBLINGS)
    srdf = '<robot name="siblings"><disable_collisions link1="far" link2="left" reason="Never"/></robot>'
    (tmp_path / "robot.srdf").write_text(srdf)
    async with agentsdk.connect(backend, robot=tmp_path / "robot.urdf") as robot:
        assert robot.backend.simulator_report()["pairs"] == [("far", "right")]  # type: ignore[attr-defined]
    (tmp_path / "robot.srdf").unlink()
    (tmp_path / "other.srdf").write_text(srdf.replace('link2="left"', 'link2="right"'))
    (tmp_path / "robot.yaml").write_text("description: robot.urdf\nsrdf: other.srdf\nself_collision: true\n")
    async with agentsdk.connect(backend, robot=tmp_path / "robot.yaml") as robot:
        pairs = robot.backend.simulator_report()["pairs"]  # type: ignore[attr-defined]
        assert pairs == [("far", "left"), ("left", "right")]
    async with agentsdk.connect(backend, robot=tmp_path / "robot.yaml", self_collision=False) as robot:
        assert robot.backend.simulator_report()["pairs"] == []  # type: ignore[attr-defined]


# --------------------------------------------------------------------------- MJCF


def test_mjcf_description_comes_from_the_model() -> None:
    _, desc = resolve_robot(MJCF_SCENE)
    assert desc.format == "mjcf" and desc.source == MJCF_SCENE.resolve() and desc.urdf_xml == ""
    assert desc.joint_names == ("shoulder_yaw", "shoulder_pitch", "elbow")
    yaw, pitch, elbow = desc.joints
    assert (yaw.lower, yaw.upper, yaw.axis) == (-2.5, 2.5, (0.0, 0.0, 1.0))
    assert pitch.axis == (0.0, 1.0, 0.0)  # from the default class
    assert (yaw.max_effort, pitch.max_effort, elbow.max_effort) == (8.0, 12.0, 8.0)  # actuator forceranges
    assert dict(desc.default_positions) == {"shoulder_yaw": 0.0, "shoulder_pitch": 0.3, "elbow": -0.6}
    assert desc.link("upper_arm").collisions[0].kind == "mesh"
    assert desc.mesh_files == ((MJCF_SCENE.parent / "assets" / "upper_link.stl").resolve(),)
    assert desc.total_mass() == pytest.approx(1.9)


@pytest.mark.parametrize("backend", ["mujoco", "mock", "pybullet"])
async def test_mjcf_model_loads_holds_and_moves(backend: str) -> None:
    async with agentsdk.connect(backend, robot=MJCF_SCENE) as robot:
        assert robot.joint_names == ("shoulder_yaw", "shoulder_pitch", "elbow")
        start = (await robot.read()).position
        np.testing.assert_allclose(start, [0.0, 0.3, -0.6], atol=1e-9)  # the home keyframe
        held = await _settle(robot, 0.5)
        np.testing.assert_allclose(held, start, atol=0.03)
        result = await robot.move_to({"shoulder_yaw": 0.5, "elbow": 0.2})
        assert result.ok, result
        q = await _settle(robot, 0.5)
        np.testing.assert_allclose(q[[0, 2]], [0.5, 0.2], atol=0.03)


async def test_mjcf_from_robot_yaml(tmp_path: Path) -> None:
    shutil.copytree(MJCF_SCENE.parent, tmp_path / "arm")
    (tmp_path / "arm" / "robot.yaml").write_text(
        "description: scene.xml\ninitial_positions: {elbow: 0.1}\ngains: {default: {p: 60, d: 2}}\n"
    )
    async with agentsdk.connect("mujoco", robot=tmp_path / "arm" / "robot.yaml") as robot:
        q = (await robot.read()).position
        np.testing.assert_allclose(q, [0.0, 0.3, 0.1], atol=1e-9)  # keyframe, then robot.yaml on top


async def test_mjcf_pybullet_cannot_carry_says_what(tmp_path: Path) -> None:
    (tmp_path / "ball.xml").write_text(
        """<mujoco><worldbody><body name="a"><joint name="hinge" axis="0 0 1"/><geom size="0.05" mass="1"/>
        <body name="b" pos="0 0 0.2"><joint name="ball" type="ball"/><geom size="0.05" mass="1"/>
        </body></body></worldbody></mujoco>"""
    )
    with pytest.raises(BackendStartError, match=r"PyBullet cannot load robot .*ball\.xml.*ball joints"):
        await agentsdk.connect("pybullet", robot=tmp_path / "ball.xml")
    async with agentsdk.connect("mujoco", robot=tmp_path / "ball.xml") as robot:
        assert robot.joint_names == ("hinge",)


def test_broken_mjcf_is_a_description_error(tmp_path: Path) -> None:
    (tmp_path / "bad.xml").write_text("<mujoco><worldbody><body><joint type='hinge'/></body></worldbody>")
    with pytest.raises(DescriptionError, match=r"bad\.xml: MuJoCo cannot load the MJCF model"):
        load_description(tmp_path / "bad.xml")
