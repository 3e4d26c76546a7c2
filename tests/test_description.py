"""Robot descriptions: URDF/xacro loading, package:// resolution, robot.yaml overrides, shipped robots."""

from __future__ import annotations

import dataclasses
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from agentsdk.config import Gains, JointLimitsOverride, RobotConfig, load_robot_config
from agentsdk.description import (
    RobotDescription,
    apply_overrides,
    check_config,
    find_package,
    list_robots,
    load_description,
    resolve_robot,
)
from agentsdk.errors import ConfigurationError, DescriptionError, UnknownJointError
from agentsdk.robots import ROBOTS_DIR

FIXTURES = Path(__file__).parent / "fixtures"
MESH_PKG = FIXTURES / "mesh_pkg"
MESH_ARM = MESH_PKG / "urdf" / "mesh_arm.urdf"
PKG_NAME = "agentsdk_test_meshes"

ARM3_JOINTS = ("joint1", "joint2", "joint3")
HUMANOID_JOINTS = (
    "left_hip_pitch",
    "left_hip_roll",
    "left_knee",
    "left_ankle_pitch",
    "right_hip_pitch",
    "right_hip_roll",
    "right_knee",
    "right_ankle_pitch",
    "left_shoulder_pitch",
    "left_shoulder_roll",
    "left_elbow",
    "right_shoulder_pitch",
    "right_shoulder_roll",
    "right_elbow",
    "head_yaw",
)
MIT_LEG_JOINTS = ("hip_abduction", "hip_pitch", "knee")
EXPECTED = {"arm3": ARM3_JOINTS, "humanoid": HUMANOID_JOINTS, "mit_leg": MIT_LEG_JOINTS}


@pytest.fixture(autouse=True)
def _clean_package_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tests control the package search path themselves."""
    monkeypatch.delenv("AGENTSDK_PACKAGE_PATH", raising=False)
    monkeypatch.delenv("ROS_PACKAGE_PATH", raising=False)


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _urdf(joints: str, links: str = "", name: str = "t") -> str:
    inertial = (
        '<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>'
    )
    base = "".join(f'<link name="{n}">{inertial}</link>' for n in ("base", "a", "b"))
    return f'<?xml version="1.0"?>\n<robot name="{name}">\n{base}{links}\n{joints}\n</robot>\n'


REVOLUTE_A = (
    '<joint name="ja" type="revolute"><parent link="base"/><child link="a"/><axis xyz="0 0 1"/>'
    '<limit lower="-1" upper="1" velocity="2" effort="10"/></joint>'
)
FIXED_B = '<joint name="jb" type="fixed"><parent link="a"/><child link="b"/></joint>'


# --------------------------------------------------------------------------- shipped robots


def test_list_robots_finds_the_shipped_robots() -> None:
    assert {"arm3", "humanoid", "mit_leg"} <= set(list_robots())
    assert list_robots() == sorted(list_robots())
    assert "common" not in list_robots()  # shared macros, no robot.yaml


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_shipped_robot_loads_with_expected_joints(name: str) -> None:
    config, desc = resolve_robot(name)
    assert isinstance(desc, RobotDescription)
    assert desc.name == name
    assert config.name == name
    assert desc.joint_names == EXPECTED[name]
    assert desc.root_link == "world"
    assert desc.source == (ROBOTS_DIR / name / f"{name}.urdf.xacro").resolve()
    for j in desc.joints:
        assert j.type == "revolute"
        assert j.lower < 0.0 < j.upper, j  # the zero pose is inside the limits
        assert j.max_velocity > 0 and j.max_effort > 0
        assert math.isclose(np.linalg.norm(j.axis), 1.0)
        assert j.parent in desc.links and j.child in desc.links
    # robot.yaml: 500 Hz, gains for every joint, 1 ms physics
    assert config.update_rate == 500
    for j in desc.joints:
        assert j.name in config.gains, f"{name}: no gains for {j.name}"
        assert config.gains[j.name].p > 0 and config.gains[j.name].d > 0
    assert config.backend_options("mujoco")["timestep"] == 0.001
    assert config.backend_options("pybullet")["timestep"] == 0.001
    assert config.joint_limits["default"].max_acceleration is not None
    assert config.joint_limits["default"].max_jerk is not None


def test_arm3_limits() -> None:
    _, desc = resolve_robot("arm3")
    j1, j2, j3 = desc.joints
    assert (j1.lower, j1.upper, j1.axis) == (-3.14, 3.14, (0.0, 0.0, 1.0))
    assert (j2.lower, j2.upper, j2.axis) == (-2.0, 2.0, (0.0, 1.0, 0.0))
    assert (j3.lower, j3.upper, j3.axis) == (-3.14, 3.14, (0.0, 0.0, 1.0))
    assert all(2.0 <= j.max_velocity <= 3.0 for j in desc.joints)
    assert j3.child == "ee_link"
    joint1 = next(r for r in desc.all_joints if r.name == "joint1")
    assert joint1.xyz == (0.0, 0.0, 0.05)  # on top of the 5 cm base


def test_humanoid_limits_are_mirrored() -> None:
    _, desc = resolve_robot("humanoid")
    for joint in ("hip_roll", "shoulder_roll"):
        left, right = desc.joint(f"left_{joint}"), desc.joint(f"right_{joint}")
        assert (left.lower, left.upper) == (-right.upper, -right.lower)
        assert left.axis == right.axis
    for joint in ("hip_pitch", "knee", "ankle_pitch", "shoulder_pitch", "elbow"):
        left, right = desc.joint(f"left_{joint}"), desc.joint(f"right_{joint}")
        assert (left.lower, left.upper, left.axis) == (right.lower, right.upper, right.axis)
    assert len(desc.joints) >= 13


def test_mit_leg_matches_its_motors() -> None:
    config, desc = resolve_robot("mit_leg")
    can = config.backend_options("can")
    assert set(can["motors"]) == set(desc.joint_names)
    assert can["profile"] in ("cubemars", "damiao")
    limits = {"AK80-9": 18.0, "AK70-10": 25.0}
    for j in desc.joints:
        motor = can["motors"][j.name]
        assert j.max_effort <= limits[motor["model"]], j
        assert j.max_velocity <= 20.0
    assert desc.joint("hip_abduction").axis == (1.0, 0.0, 0.0)
    assert desc.joint("knee").axis == (0.0, 1.0, 0.0)
    # MIT protocol gain ranges: kp 0..500, kd 0..5
    for name in desc.joint_names:
        assert config.gains_for(name).p <= 500 and config.gains_for(name).d <= 5


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_shipped_robot_compiles_in_mujoco_with_a_fixed_base(name: str) -> None:
    mujoco = pytest.importorskip("mujoco")
    _, desc = resolve_robot(name)
    model = mujoco.MjModel.from_xml_string(desc.urdf_xml)
    assert model.njnt == len(desc.joints)  # no free joint: the base is welded to the world
    assert all(t == mujoco.mjtJoint.mjJNT_HINGE for t in model.jnt_type)
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, i) for i in range(model.njnt)]
    assert names == list(desc.joint_names)
    np.testing.assert_allclose(model.jnt_range, [[j.lower, j.upper] for j in desc.joints])
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert data.ncon == 0, "links collide in the zero pose"


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_shipped_robot_loads_in_pybullet(name: str) -> None:
    pybullet = pytest.importorskip("pybullet")
    _, desc = resolve_robot(name)
    client = pybullet.connect(pybullet.DIRECT)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            urdf = desc.write_urdf(tmp)
            body = pybullet.loadURDF(str(urdf), useFixedBase=True, physicsClientId=client)
        infos = [pybullet.getJointInfo(body, i, physicsClientId=client) for i in range(pybullet.getNumJoints(body))]
        revolute = [i[1].decode() for i in infos if i[2] == pybullet.JOINT_REVOLUTE]
        assert revolute == list(desc.joint_names)
    finally:
        pybullet.disconnect(client)


# (robot, pose) pairs where gravity loads the joints most
_WORST_POSES = {
    "arm3": {"joint2": math.pi / 2},
    "humanoid": {
        "left_hip_pitch": -math.pi / 2,
        "right_hip_pitch": -math.pi / 2,
        "left_shoulder_pitch": -math.pi / 2,
        "right_shoulder_pitch": -math.pi / 2,
        "left_knee": 1.0,
    },
    "mit_leg": {"hip_pitch": math.pi / 2, "hip_abduction": 0.6},
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_robot_yaml_gains_hold_the_worst_pose_against_gravity(name: str) -> None:
    """The PD servo (no gravity compensation, explicit at 1 ms) settles with < 0.005 rad sag."""
    mujoco = pytest.importorskip("mujoco")
    config, desc = resolve_robot(name)
    model = mujoco.MjModel.from_xml_string(desc.urdf_xml)
    model.opt.timestep = 0.001
    data = mujoco.MjData(model)
    joints = apply_overrides(desc, config)
    target = np.array([_WORST_POSES[name].get(j.name, 0.0) for j in joints])
    p = np.array([config.gains_for(j.name).p for j in joints])
    d = np.array([config.gains_for(j.name).d for j in joints])
    limit = np.array([j.max_effort for j in joints])
    data.qpos[:] = target
    mujoco.mj_forward(model, data)
    for _ in range(1500):
        effort = np.clip(p * (target - data.qpos) - d * data.qvel, -limit, limit)
        data.qfrc_applied[:] = effort
        mujoco.mj_step(model, data)
    assert np.all(np.isfinite(data.qpos))
    assert np.max(np.abs(data.qvel)) < 1e-3, "still moving after 1.5 s"
    assert np.max(np.abs(target - data.qpos)) < 0.005


# --------------------------------------------------------------------------- xacro


def test_xacro_args_change_a_link_length() -> None:
    path = ROBOTS_DIR / "arm3" / "arm3.urdf.xacro"
    default = load_description(path)
    longer = load_description(path, {"link1_length": "0.4"})

    def joint2_z(desc: RobotDescription) -> float:
        return next(r for r in desc.all_joints if r.name == "joint2").xyz[2]

    assert joint2_z(default) == pytest.approx(0.3)
    assert joint2_z(longer) == pytest.approx(0.4)
    assert 'size="0.08 0.08 0.4"' in longer.urdf_xml


def test_xacro_arg_not_declared_by_the_file_is_an_error() -> None:
    with pytest.raises(DescriptionError, match=r"'link1_lenght'.*declares:.*link1_length"):
        load_description(ROBOTS_DIR / "arm3" / "arm3.urdf.xacro", {"link1_lenght": "0.4"})


def test_xacro_undefined_property_names_file_and_property(tmp_path: Path) -> None:
    path = _write(
        tmp_path / "bad.urdf.xacro",
        '<robot name="bad" xmlns:xacro="http://www.ros.org/wiki/xacro">\n'
        '  <link name="base"><visual><geometry><box size="${undefined_len} 1 1"/></geometry></visual></link>\n'
        "</robot>\n",
    )
    with pytest.raises(DescriptionError) as info:
        load_description(path)
    assert str(path) in str(info.value)
    assert "undefined_len" in str(info.value)


def test_xacro_missing_arg_names_the_arg(tmp_path: Path) -> None:
    path = _write(
        tmp_path / "needs_arg.urdf.xacro",
        '<robot name="r" xmlns:xacro="http://www.ros.org/wiki/xacro">\n'
        '  <link name="base"><visual><geometry><box size="$(arg size) 1 1"/></geometry></visual></link>\n'
        "</robot>\n",
    )
    with pytest.raises(DescriptionError, match=r"needs_arg\.urdf\.xacro.*Undefined substitution argument size"):
        load_description(path)


def test_xacro_error_inside_a_macro_names_the_macro(tmp_path: Path) -> None:
    path = _write(
        tmp_path / "macro.urdf.xacro",
        '<robot name="r" xmlns:xacro="http://www.ros.org/wiki/xacro">\n'
        '  <xacro:macro name="limb" params="n"><link name="${n}_${missing}"/></xacro:macro>\n'
        '  <xacro:limb n="left"/>\n'
        "</robot>\n",
    )
    with pytest.raises(DescriptionError, match=r"in macro 'limb'.*missing"):
        load_description(path)


def test_malformed_xacro_xml(tmp_path: Path) -> None:
    path = _write(tmp_path / "broken.xacro", '<robot name="r" xmlns:xacro="http://www.ros.org/wiki/xacro">\n<link>\n')
    with pytest.raises(DescriptionError, match=r"broken\.xacro.*xacro failed"):
        load_description(path)


def test_xacro_find_uses_the_package_search_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AGENTSDK_PACKAGE_PATH", str(MESH_PKG))
    path = _write(
        tmp_path / "find.urdf.xacro",
        '<robot name="r" xmlns:xacro="http://www.ros.org/wiki/xacro">\n'
        f'  <link name="base"><visual><geometry><mesh filename="$(find {PKG_NAME})/meshes/link.stl"/>'
        "</geometry></visual></link>\n"
        '  <link name="a"/>\n'
        '  <joint name="j" type="continuous"><parent link="base"/><child link="a"/>'
        '<limit velocity="1" effort="1"/></joint>\n'
        "</robot>\n",
    )
    desc = load_description(path)
    assert desc.mesh_files == ((MESH_PKG / "meshes" / "link.stl").resolve(),)


def test_xacro_find_unknown_package(tmp_path: Path) -> None:
    path = _write(
        tmp_path / "find.urdf.xacro",
        '<robot name="r" xmlns:xacro="http://www.ros.org/wiki/xacro">\n'
        '  <link name="base"><visual><geometry><mesh filename="$(find no_such_pkg)/m.stl"/>'
        "</geometry></visual></link>\n"
        "</robot>\n",
    )
    with pytest.raises(DescriptionError, match=r"no_such_pkg.*not found.*search path"):
        load_description(path)


# --------------------------------------------------------------------------- URDF checks


def test_malformed_xml_names_file_and_problem(tmp_path: Path) -> None:
    path = _write(tmp_path / "broken.urdf", '<robot name="r">\n  <link name="base">\n</robot>\n')
    with pytest.raises(DescriptionError, match=r"broken\.urdf.*malformed XML.*line 3"):
        load_description(path)


def test_missing_file() -> None:
    with pytest.raises(DescriptionError, match=r"not found: .*nope\.urdf"):
        load_description("/nonexistent/nope.urdf")


def test_revolute_without_limit_is_an_error(tmp_path: Path) -> None:
    joint = '<joint name="ja" type="revolute"><parent link="base"/><child link="a"/><axis xyz="0 0 1"/></joint>'
    path = _write(tmp_path / "r.urdf", _urdf(joint))
    with pytest.raises(DescriptionError, match=r"r\.urdf, line \d+: joint 'ja': a revolute joint needs a <limit"):
        load_description(path)


@pytest.mark.parametrize("missing", ["velocity", "effort"])
def test_limit_without_velocity_or_effort_names_the_joint(tmp_path: Path, missing: str) -> None:
    attrs = {"lower": "-1", "upper": "1", "velocity": "2", "effort": "10"}
    del attrs[missing]
    limit = "<limit " + " ".join(f'{k}="{v}"' for k, v in attrs.items()) + "/>"
    joint = f'<joint name="elbow" type="revolute"><parent link="base"/><child link="a"/>{limit}</joint>'
    path = _write(tmp_path / "r.urdf", _urdf(joint))
    with pytest.raises(DescriptionError, match=rf"joint 'elbow': <limit> is missing the '{missing}' attribute"):
        load_description(path)


def test_bad_number_names_the_joint_and_line(tmp_path: Path) -> None:
    joint = REVOLUTE_A.replace('upper="1"', 'upper="${pi}"')
    path = _write(tmp_path / "r.urdf", _urdf(joint))
    with pytest.raises(DescriptionError, match=r"line 4: joint 'ja': <limit upper=\"\$\{pi\}\">: not a number"):
        load_description(path)


def test_continuous_joint_has_infinite_limits_and_fixed_and_mimic_are_skipped(tmp_path: Path) -> None:
    joints = (
        '<joint name="spin" type="continuous"><parent link="base"/><child link="a"/><axis xyz="0 0 2"/>'
        '<limit velocity="5" effort="3"/></joint>'
        '<joint name="follow" type="revolute"><parent link="a"/><child link="b"/>'
        '<limit lower="-1" upper="1" velocity="1" effort="1"/><mimic joint="spin" multiplier="2" offset="0.1"/></joint>'
        '<joint name="tool" type="fixed"><parent link="b"/><child link="c"/></joint>'
    )
    path = _write(tmp_path / "r.urdf", _urdf(joints, links='<link name="c"/>'))
    desc = load_description(path)
    assert desc.joint_names == ("spin",)
    spin = desc.joint("spin")
    assert (spin.type, spin.lower, spin.upper) == ("continuous", -math.inf, math.inf)
    assert spin.axis == (0.0, 0.0, 1.0)  # normalised
    assert (spin.max_velocity, spin.max_effort) == (5.0, 3.0)
    assert [r.name for r in desc.all_joints] == ["spin", "follow", "tool"]
    follow = desc.all_joints[1]
    assert (follow.mimic, follow.mimic_multiplier, follow.mimic_offset, follow.actuated) == ("spin", 2.0, 0.1, False)
    with pytest.raises(UnknownJointError, match="known joints: spin"):
        desc.joint("follow")


def test_no_actuated_joints(tmp_path: Path) -> None:
    joints = '<joint name="j" type="fixed"><parent link="base"/><child link="a"/></joint>' + FIXED_B
    path = _write(tmp_path / "r.urdf", _urdf(joints))
    desc = load_description(path)  # legal URDF (a sensor rig, a rigid object): no commanded joints
    assert desc.joints == () and len(desc.all_joints) == 2


def test_link_with_two_parents_is_not_a_tree(tmp_path: Path) -> None:
    second = '<joint name="jc" type="fixed"><parent link="base"/><child link="b"/></joint>'
    path = _write(tmp_path / "r.urdf", _urdf(REVOLUTE_A + FIXED_B + second))
    with pytest.raises(DescriptionError, match=r"link 'b' has two parent joints \('jb' and 'jc'\).*tree"):
        load_description(path)


def test_disconnected_links_are_reported(tmp_path: Path) -> None:
    path = _write(tmp_path / "r.urdf", _urdf(REVOLUTE_A))  # link 'b' is not connected
    with pytest.raises(DescriptionError, match=r"more than one root link \('base', 'b'\)"):
        load_description(path)


def test_kinematic_loop_is_reported(tmp_path: Path) -> None:
    loop = (
        '<joint name="jb" type="fixed"><parent link="c"/><child link="b"/></joint>'
        '<joint name="jc" type="fixed"><parent link="b"/><child link="c"/></joint>'
    )
    path = _write(tmp_path / "r.urdf", _urdf(REVOLUTE_A + loop, links='<link name="c"/>'))
    with pytest.raises(DescriptionError, match=r"'b', 'c'.*loop"):
        load_description(path)


def test_joint_referencing_unknown_link(tmp_path: Path) -> None:
    joint = REVOLUTE_A.replace('<child link="a"/>', '<child link="nowhere"/>')
    path = _write(tmp_path / "r.urdf", _urdf(joint + FIXED_B))
    with pytest.raises(DescriptionError, match=r"joint 'ja': child link 'nowhere' is not defined"):
        load_description(path)


def test_floating_and_planar_joints_are_held_fixed_as_a_repair(tmp_path: Path) -> None:
    joint = '<joint name="free" type="floating"><parent link="base"/><child link="a"/></joint>'
    path = _write(tmp_path / "r.urdf", _urdf(joint + FIXED_B))
    with pytest.raises(DescriptionError, match=r"joint 'free' \(line \d+\): floating joint held fixed"):
        load_description(path, strict=True)
    desc = load_description(path)
    assert desc.joint_record("free").type == "fixed"


def test_unknown_joint_type(tmp_path: Path) -> None:
    joint = '<joint name="j" type="hinge"><parent link="base"/><child link="a"/></joint>'
    path = _write(tmp_path / "r.urdf", _urdf(joint + FIXED_B))
    with pytest.raises(DescriptionError, match=r"r\.urdf, line \d+: joint 'j': unknown joint type 'hinge'"):
        load_description(path)


def test_plain_urdf_rejects_xacro_args(tmp_path: Path) -> None:
    path = _write(tmp_path / "r.urdf", _urdf(REVOLUTE_A + FIXED_B))
    with pytest.raises(DescriptionError, match="plain URDF"):
        load_description(path, {"x": "1"})


# --------------------------------------------------------------------------- meshes and packages


def _copy_mesh_arm(tmp_path: Path) -> Path:
    """The mesh arm URDF outside its package, so that only the search path can find the package."""
    target = tmp_path / "elsewhere" / "mesh_arm.urdf"
    target.parent.mkdir(parents=True)
    shutil.copy(MESH_ARM, target)
    return target


def _assert_meshes_resolved(desc: RobotDescription, package_dir: Path) -> None:
    link_stl = (package_dir / "meshes" / "link.stl").resolve()
    ee_obj = (package_dir / "meshes" / "ee.obj").resolve()
    assert desc.mesh_files == (link_stl, ee_obj)
    assert "package://" not in desc.urdf_xml
    assert desc.urdf_xml.count(f'filename="{link_stl}"') == 4  # visual + collision of two links
    assert all(p.is_file() and p.is_absolute() for p in desc.mesh_files)


def test_package_uri_resolved_in_place() -> None:
    """Next to its own package.xml, the URDF finds its package without any environment."""
    desc = load_description(MESH_ARM)
    assert desc.joint_names == ("joint_a", "joint_b")
    _assert_meshes_resolved(desc, MESH_PKG)


@pytest.mark.parametrize("variable", ["AGENTSDK_PACKAGE_PATH", "ROS_PACKAGE_PATH"])
@pytest.mark.parametrize("entry", ["package_dir", "parent_dir"])
def test_package_uri_resolved_via_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, variable: str, entry: str
) -> None:
    urdf = _copy_mesh_arm(tmp_path)
    # the package dir itself (its package.xml names it), or a parent to crawl (dir name != package name)
    directory = MESH_PKG if entry == "package_dir" else FIXTURES
    monkeypatch.setenv(variable, str(tmp_path / "empty") + ":" + str(directory))
    _assert_meshes_resolved(load_description(urdf), MESH_PKG)


def test_package_dir_named_like_the_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    shutil.copytree(MESH_PKG, tmp_path / "share" / PKG_NAME)
    (tmp_path / "share" / PKG_NAME / "package.xml").unlink()
    monkeypatch.setenv("ROS_PACKAGE_PATH", str(tmp_path / "share"))
    urdf = _copy_mesh_arm(tmp_path)
    _assert_meshes_resolved(load_description(urdf), tmp_path / "share" / PKG_NAME)
    assert find_package(PKG_NAME) == (tmp_path / "share" / PKG_NAME).resolve()


def test_explicit_package_path_wins(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    copy = tmp_path / "copy" / PKG_NAME
    shutil.copytree(MESH_PKG, copy)
    monkeypatch.setenv("AGENTSDK_PACKAGE_PATH", str(MESH_PKG))
    desc = load_description(_copy_mesh_arm(tmp_path), package_path=[copy.parent])
    _assert_meshes_resolved(desc, copy)


def test_missing_package_names_uri_and_search_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AGENTSDK_PACKAGE_PATH", str(tmp_path / "nothing_here"))
    urdf = _copy_mesh_arm(tmp_path)
    with pytest.raises(DescriptionError) as info:
        load_description(urdf, strict=True)
    message = str(info.value)
    assert str(urdf) in message
    assert f"package://{PKG_NAME}/meshes/link.stl" in message
    assert f"package '{PKG_NAME}' not found" in message
    assert "AGENTSDK_PACKAGE_PATH" in message and str(tmp_path / "nothing_here") in message
    assert "link 'link_a'" in message


def test_missing_file_inside_a_found_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AGENTSDK_PACKAGE_PATH", str(MESH_PKG))
    urdf = _write(tmp_path / "r.urdf", MESH_ARM.read_text().replace("meshes/ee.obj", "meshes/gone.obj"))
    with pytest.raises(DescriptionError, match=r"package://agentsdk_test_meshes/meshes/gone\.obj.*file not found"):
        load_description(urdf, strict=True)


def test_relative_and_file_uri_mesh_paths(tmp_path: Path) -> None:
    (tmp_path / "meshes").mkdir()
    (tmp_path / "package.xml").write_text("<package><name>r</name></package>")  # ../meshes stays in the package
    shutil.copy(MESH_PKG / "meshes" / "link.stl", tmp_path / "meshes" / "link.stl")
    shutil.copy(MESH_PKG / "meshes" / "ee.obj", tmp_path / "meshes" / "ee.obj")
    text = (
        MESH_ARM.read_text()
        .replace(f"package://{PKG_NAME}/meshes/link.stl", "../meshes/link.stl")
        .replace(f"package://{PKG_NAME}/meshes/ee.obj", (tmp_path / "meshes" / "ee.obj").as_uri())
    )
    desc = load_description(_write(tmp_path / "urdf" / "r.urdf", text))
    _assert_meshes_resolved(desc, tmp_path)


def test_missing_relative_mesh_is_dropped_with_one_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """urdfdom does not open meshes: a missing one is dropped (visibly), strict mode refuses it."""
    text = MESH_ARM.read_text().replace(f"package://{PKG_NAME}/meshes/link.stl", "meshes/missing.stl")
    urdf = _write(tmp_path / "r.urdf", text)
    pattern = (
        r"r\.urdf: strict mode refuses.*\n  - link 'link_a' <visual> \(line \d+\)"
        r": cannot resolve mesh 'meshes/missing\.stl': file not found"
    )
    with pytest.raises(DescriptionError, match=pattern):
        load_description(urdf, strict=True)
    with caplog.at_level("WARNING", logger="agentsdk.description"):
        desc = load_description(urdf, package_path=[MESH_PKG])
    warnings = [r for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1, "every repair in one warning"
    assert warnings[0].getMessage().count("cannot resolve mesh 'meshes/missing.stl'") == 4
    assert desc.link("link_a").collisions == () and desc.link("link_a").visuals == ()
    assert "missing.stl" not in desc.urdf_xml


def test_resolved_mesh_urdf_loads_in_mujoco_and_pybullet_from_a_temp_dir() -> None:
    mujoco = pytest.importorskip("mujoco")
    pybullet = pytest.importorskip("pybullet")
    desc = load_description(MESH_ARM)
    model = mujoco.MjModel.from_xml_string(desc.urdf_xml)
    assert model.njnt == 2 and model.nmesh >= 1
    client = pybullet.connect(pybullet.DIRECT)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            body = pybullet.loadURDF(str(desc.write_urdf(tmp)), useFixedBase=True, physicsClientId=client)
        assert pybullet.getNumJoints(body, physicsClientId=client) == 2
    finally:
        pybullet.disconnect(client)


# --------------------------------------------------------------------------- resolve_robot / robot.yaml


def test_unknown_robot_lists_the_known_ones() -> None:
    with pytest.raises(ConfigurationError, match=r"unknown robot 'robot9000'.*arm3, humanoid, (\w+, )*mit_leg"):
        resolve_robot("robot9000")


def test_resolve_bare_urdf_synthesises_a_config() -> None:
    config, desc = resolve_robot(MESH_ARM)
    assert desc.name == config.name == "mesh_arm"
    assert config.description_path == MESH_ARM.resolve()
    # no gains in a bare URDF: the backend computes them from the model (agentsdk.dynamics.model_gains)
    assert config.gains_for("joint_a") is None
    assert config.gravity_compensation is True


def test_resolve_robot_yaml_path_and_directory() -> None:
    by_file = resolve_robot(ROBOTS_DIR / "humanoid" / "robot.yaml")
    by_dir = resolve_robot(str(ROBOTS_DIR / "humanoid"))
    assert by_file[1].joint_names == by_dir[1].joint_names == HUMANOID_JOINTS


def test_resolve_robot_from_another_robots_dir(tmp_path: Path) -> None:
    shutil.copytree(ROBOTS_DIR / "arm3", tmp_path / "robots" / "myarm")
    shutil.copytree(ROBOTS_DIR / "common", tmp_path / "robots" / "common")
    config, desc = resolve_robot("myarm", robots_dir=tmp_path / "robots")
    assert config.name == "myarm" and desc.joint_names == ARM3_JOINTS
    assert list_robots(tmp_path / "robots") == ["myarm"]


def test_robot_yaml_xacro_args_are_used(tmp_path: Path) -> None:
    shutil.copytree(ROBOTS_DIR / "arm3", tmp_path / "arm3")
    shutil.copytree(ROBOTS_DIR / "common", tmp_path / "common")
    shutil.copy(ROBOTS_DIR / "package.xml", tmp_path)  # arm3 includes ../common: one package holds both
    yaml_path = tmp_path / "arm3" / "robot.yaml"
    yaml_path.write_text(yaml_path.read_text().replace("xacro_args: {}", "xacro_args: {link2_length: 0.5}"))
    _, desc = resolve_robot(yaml_path)
    assert next(r for r in desc.all_joints if r.name == "joint3").xyz[2] == pytest.approx(0.5)


def test_robot_yaml_with_unknown_gain_joint(tmp_path: Path) -> None:
    shutil.copytree(ROBOTS_DIR / "arm3", tmp_path / "arm3")
    shutil.copytree(ROBOTS_DIR / "common", tmp_path / "common")
    shutil.copy(ROBOTS_DIR / "package.xml", tmp_path)  # arm3 includes ../common: one package holds both
    yaml_path = tmp_path / "arm3" / "robot.yaml"
    yaml_path.write_text(yaml_path.read_text() + "\ninitial_positions: {joint4: 0.1}\n")
    with pytest.raises(
        ConfigurationError, match=r"initial_positions\.joint4: unknown joint 'joint4'; did you mean 'joint\d'\?; known"
    ):
        resolve_robot(yaml_path)


def _config(**kwargs: object) -> RobotConfig:
    return RobotConfig(name="arm3", description="arm3.urdf.xacro", base_dir=ROBOTS_DIR / "arm3", **kwargs)


def test_apply_overrides() -> None:
    _, desc = resolve_robot("arm3")
    config = _config(
        joint_limits={
            "default": JointLimitsOverride(max_acceleration=4.0, max_jerk=80.0, max_velocity=2.2),
            "joint1": JointLimitsOverride(min_position=-1.0, max_position=1.5, max_velocity=1.0, max_jerk=50.0),
            "joint3": JointLimitsOverride(max_effort=2.0),
        }
    )
    j1, j2, j3 = apply_overrides(desc, config)
    assert (j1.lower, j1.upper, j1.max_velocity, j1.max_acceleration, j1.max_jerk) == (-1.0, 1.5, 1.0, 4.0, 50.0)
    assert (j2.lower, j2.upper, j2.max_velocity, j2.max_acceleration, j2.max_jerk) == (-2.0, 2.0, 2.2, 4.0, 80.0)
    assert (j3.max_effort, j3.max_velocity) == (2.0, 2.2)  # default only tightens: URDF 3.0 -> 2.2
    assert desc.joint("joint1").lower == -3.14  # the description itself is unchanged
    # no overrides: URDF values and JointInfo defaults
    assert apply_overrides(desc, _config()) == desc.joints


def test_apply_overrides_unknown_joint_lists_known_joints() -> None:
    _, desc = resolve_robot("arm3")
    config = _config(joint_limits={"joint9": JointLimitsOverride(max_velocity=1.0)})
    with pytest.raises(
        ConfigurationError, match=r"'joint9'; did you mean 'joint\d'\?; known joints: joint1, joint2, joint3"
    ):
        apply_overrides(desc, config)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (JointLimitsOverride(max_velocity=10.0), r"joint_limits\.joint2\.max_velocity=10 is above the URDF"),
        (JointLimitsOverride(min_position=-2.5), r"joint_limits\.joint2\.min_position=-2\.5 is below the URDF"),
        (JointLimitsOverride(max_effort=100.0), r"joint_limits\.joint2\.max_effort=100 is above the URDF"),
        (JointLimitsOverride(min_position=1.0, max_position=0.5), r"joint 'joint2' an empty range"),
    ],
)
def test_apply_overrides_cannot_widen_urdf_limits(override: JointLimitsOverride, message: str) -> None:
    _, desc = resolve_robot("arm3")
    with pytest.raises(ConfigurationError, match=message):
        apply_overrides(desc, _config(joint_limits={"joint2": override}))


def test_check_config_initial_position_outside_limits() -> None:
    _, desc = resolve_robot("arm3")
    with pytest.raises(ConfigurationError, match=r"initial_positions\.joint2=2\.5 is outside the joint limits"):
        check_config(_config(initial_positions={"joint2": 2.5}), desc)
    with pytest.raises(ConfigurationError, match=r"gains\.wrist: unknown joint 'wrist'; known joints"):
        check_config(_config(gains={"wrist": Gains(p=1.0, d=0.1)}), desc)


def test_shipped_robot_yaml_files_validate() -> None:
    for name in EXPECTED:
        config = load_robot_config(ROBOTS_DIR / name / "robot.yaml")
        assert config.description_path.is_file()


# --------------------------------------------------------------------------- description object


def test_tree_lines_arm3() -> None:
    _, desc = resolve_robot("arm3")
    assert desc.tree_lines() == [
        "robot 'arm3': root link 'world', 5 links, 4 joints (3 actuated)",
        "world",
        "└─ world_to_base [fixed] → base_link",
        "   └─ joint1 [revolute] z  lower=-3.140 upper=3.140 vel=2.5 effort=20 → link1",
        "      └─ joint2 [revolute] y  lower=-2.000 upper=2.000 vel=2.5 effort=20 → link2",
        "         └─ joint3 [revolute] z  lower=-3.140 upper=3.140 vel=3 effort=5 → ee_link",
    ]


def test_tree_lines_branches() -> None:
    _, desc = resolve_robot("humanoid")
    lines = desc.tree_lines()
    assert lines[1] == "world"
    assert lines[2] == "└─ world_to_torso [fixed] → torso"
    assert "   ├─ left_hip_pitch [revolute] y  lower=-1.600 upper=0.800 vel=6 effort=100 → left_hip_link" in lines
    assert "   │  └─ left_hip_roll [revolute] x  lower=-0.200 upper=0.600 vel=6 effort=100 → left_thigh" in lines
    assert lines[-1].startswith("   └─ head_yaw [revolute] z ")
    assert len(lines) == 2 + len(desc.all_joints)


def test_tree_lines_continuous_and_mimic(tmp_path: Path) -> None:
    joints = (
        '<joint name="spin" type="continuous"><parent link="base"/><child link="a"/><axis xyz="1 1 0"/>'
        '<limit velocity="5" effort="3"/></joint>'
        '<joint name="follow" type="prismatic"><parent link="a"/><child link="b"/><axis xyz="0 0 -1"/>'
        '<limit lower="0" upper="0.04" velocity="0.1" effort="20"/><mimic joint="spin"/></joint>'
    )
    desc = load_description(_write(tmp_path / "r.urdf", _urdf(joints)))
    assert desc.tree_lines()[2:] == [
        "└─ spin [continuous] axis=(0.707 0.707 0)  vel=5 effort=3 → a",
        "   └─ follow [prismatic] -z  lower=0.000 upper=0.040 vel=0.1 effort=20 mimic=spin x1+0 → b",
    ]


def test_description_is_immutable_and_writes_its_urdf(tmp_path: Path) -> None:
    _, desc = resolve_robot("mit_leg")
    with pytest.raises(dataclasses.FrozenInstanceError):
        desc.name = "other"  # type: ignore[misc]
    written = desc.write_urdf(tmp_path)
    assert written == tmp_path / "mit_leg.urdf"
    assert load_description(written).joints == desc.joints
    assert "urdf_xml" not in repr(desc)
    assert "foot_fixed" in [r.name for r in desc.all_joints]
    assert desc.links[-1] == "foot"
