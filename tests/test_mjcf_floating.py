"""Issue 24: MJCF floating bases, keyframes by name, one collision rule, SRDF start states, legged robots.

Self-contained models in tests/fixtures: ``mjcf_quadruped`` (a free joint at the root, no floor,
keyframes ``crouch`` and ``stand``) and ``mjcf_welded`` (a base welded to the world overlapping its
shoulder at the start pose; keyframes ``up`` and ``ready``).
"""

from __future__ import annotations

import importlib.metadata
import shutil
from pathlib import Path

import mujoco
import numpy as np
import pytest

import agentsdk
from agentsdk.description import apply_overrides, load_description, resolve_robot
from agentsdk.description.collision import from_mjcf
from agentsdk.description.mobility import mobility, report_lines
from agentsdk.description.start import start_pose
from agentsdk.dynamics import DynamicsModel
from agentsdk.errors import ConfigurationError

FIXTURES = Path(__file__).parent / "fixtures"
QUADRUPED = FIXTURES / "mjcf_quadruped" / "quadruped.xml"
WELDED = FIXTURES / "mjcf_welded" / "arm.xml"


def corpus(path: str) -> Path:
    """A robot of example-robot-data (installed)."""
    dist = importlib.metadata.distribution("example-robot-data")
    return Path(str(dist.locate_file("cmeel.prefix/share/example-robot-data/robots"))) / path


def _yaml(tmp_path: Path, model: Path, extra: str = "") -> Path:
    path = tmp_path / "robot.yaml"
    path.write_text(f"description: {model}\n{extra}")
    return path


def _scene(tmp_path: Path) -> Path:
    """The quadruped in a scene with its own floor (Menagerie's scene.xml layout)."""
    shutil.copy(QUADRUPED, tmp_path / QUADRUPED.name)
    scene = tmp_path / "scene.xml"
    scene.write_text(
        f'<mujoco model="quadruped scene"><include file="{QUADRUPED.name}"/>'
        '<worldbody><geom name="floor" type="plane" size="0 0 0.05"/></worldbody></mujoco>'
    )
    return scene


# --------------------------------------------------------------------------- the description


def test_a_free_joint_at_the_root_is_the_floating_base() -> None:
    desc = load_description(QUADRUPED)
    assert desc.free_root == "trunk" and desc.base_link == "trunk"
    assert "root" not in desc.joint_names  # the free joint is not commanded
    assert desc.default_state == "stand"  # no "home": the next start name the model has
    assert set(desc.named_states) == {"crouch", "stand"}
    assert desc.default_positions["FL_knee"] == pytest.approx(-1.2)
    assert load_description(WELDED).free_root is None


def test_keyframes_by_name(tmp_path: Path) -> None:
    config, desc = resolve_robot(QUADRUPED)
    pose = start_pose(desc, config)
    assert pose.keyframe == "stand" and set(pose.sources.values()) == {"keyframe stand"}
    assert "8 joints from the model's stand keyframe" in pose.summary()

    config, desc = resolve_robot(_yaml(tmp_path, QUADRUPED, "initial_group_state: crouch\n"))
    pose = start_pose(desc, config)
    assert pose.keyframe == "crouch" and pose.positions["FL_knee"] == pytest.approx(-1.8)

    config, desc = resolve_robot(_yaml(tmp_path, QUADRUPED, "initial_group_state: sitting\n"))
    with pytest.raises(ConfigurationError, match=r"'sitting' names no keyframe .*keyframes: crouch, stand"):
        start_pose(desc, config)

    config, desc = resolve_robot(WELDED)  # "ready" when there is neither "home" nor "stand"
    pose = start_pose(desc, config)
    assert pose.keyframe == "ready" and pose.positions["joint_3"] == pytest.approx(0.8)


def test_describe_and_check_say_a_floating_mjcf_base_floats() -> None:
    config, desc = resolve_robot(QUADRUPED)
    lines = "\n".join(report_lines(desc, config, start_pose(desc, config)))
    assert "floating base: 'trunk' (a free joint at the root)" in lines
    assert "a ground plane the simulators add (the model has no floor)" in lines
    assert "looks legged: base link 'trunk' with 4 feet" in lines and "the base floats" in lines
    config, desc = resolve_robot(WELDED)
    assert report_lines(desc, config, start_pose(desc, config)) == []


# --------------------------------------------------------------------------- MuJoCo: standing


async def test_a_floating_mjcf_robot_without_a_floor_stands_on_an_added_ground() -> None:
    async with agentsdk.connect("mujoco", robot=QUADRUPED) as robot:
        ctl = robot.backend
        assert ctl.model.geom("agentsdk/ground").id >= 0
        base = robot.base_state()
        # placed on the ground: the lowest collision shape touches z = 0 at the start pose
        feet = [ctl.model.geom(g).id for g in range(ctl.model.ngeom)
                if ctl.model.geom_bodyid[g] and ctl.model.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE]
        lowest = min(float(ctl.data.geom_xpos[g][2] - ctl.model.geom_size[g][0]) for g in feet)
        assert lowest == pytest.approx(0.0, abs=1e-6)
        h0 = float(base.pose.position[2])
        assert 0.2 < h0 < 0.3
        heights = []
        for _ in range(10):
            await robot.clock.sleep(0.5)
            heights.append(float(robot.base_state().pose.position[2]))
        assert max(abs(h - h0) for h in heights) < 0.05 * h0  # stands 5 s (Menagerie accepts 20 %)
        end = robot.base_state()
        assert np.abs(end.linear_velocity).max() < 0.01 and np.abs(end.angular_velocity).max() < 0.05


@pytest.mark.parametrize("bits", ["0", "2"])
async def test_a_robot_whose_geoms_do_not_collide_by_default_still_stands_on_the_added_ground(
    tmp_path: Path, bits: str
) -> None:
    # like Menagerie's Apollo main file: every geom contype = conaffinity = 0, contacts only through explicit
    # <pair>s in a scene file ("0"); or collision bits the default plane (contype 1) would not meet ("2")
    xml = QUADRUPED.read_text().replace(
        "<default>\n", f'<default>\n    <geom contype="{bits}" conaffinity="{bits}"/>\n', 1
    ).replace(  # a visual shape (group 1, below the trunk's collision box): not a collision shape
        '<geom name="trunk_box"', '<geom name="trunk_visual" type="sphere" size="0.1" pos="0 0 -0.05" group="1" '
        'contype="0" conaffinity="0"/>\n      <geom name="trunk_box"', 1
    )
    path = tmp_path / "quadruped.xml"
    path.write_text(xml)
    async with agentsdk.connect("mujoco", robot=path) as robot:
        m = robot.backend.model
        ground = m.geom("agentsdk/ground").id
        paired = {int(g) for p in range(m.npair) for g in (m.pair_geom1[p], m.pair_geom2[p]) if g != ground}
        if bits == "0":  # the collision shapes (group 3) are paired with the ground, not the visual sphere
            assert paired == {g for g in range(m.ngeom) if m.geom_group[g] == 3}
        else:  # the ground meets every contype/conaffinity bit: no pair needed
            assert paired == set()
        h0 = float(robot.base_state().pose.position[2])
        assert 0.2 < h0 < 0.3  # stands on its feet (the visual sphere would put it higher)
        for _ in range(6):
            await robot.clock.sleep(0.5)
            h = float(robot.base_state().pose.position[2])
            assert abs(h - h0) < 0.05 * h0, f"base at {h:.3f} m, started at {h0:.3f} m"


async def test_base_state_follows_the_free_joint() -> None:
    async with agentsdk.connect("mujoco", robot=QUADRUPED) as robot:
        ctl = robot.backend
        adr = ctl.model.joint("root").qposadr[0]
        ctl.data.qpos[adr : adr + 3] += [0.3, -0.2, 0.0]
        mujoco.mj_forward(ctl.model, ctl.data)
        base = robot.base_state()
        np.testing.assert_allclose(base.pose.position, ctl.data.xpos[ctl.model.body("trunk").id], atol=1e-12)


async def test_default_gains_include_the_load_the_legs_carry() -> None:
    async with agentsdk.connect("mujoco", robot=QUADRUPED) as robot:
        ctl = robot.backend
        assert ctl.floating_base
        carried = ctl.model_gain_report.kp
        desc = ctl.description
        alone = DynamicsModel(desc, ctl.joints).gains(ctl.initial_positions, timestep=ctl.servo_timestep).kp
        assert np.all(carried > 1.5 * alone)  # each leg carries a quarter of the trunk


async def test_a_model_with_its_own_floor_keeps_it(tmp_path: Path) -> None:
    async with agentsdk.connect("mujoco", robot=_scene(tmp_path)) as robot:
        ctl = robot.backend
        assert mujoco.mj_name2id(ctl.model, mujoco.mjtObj.mjOBJ_GEOM, "agentsdk/ground") == -1
        h0 = float(robot.base_state().pose.position[2])
        assert h0 == pytest.approx(0.27)  # the keyframe's height, as written
        await robot.clock.sleep(2.0)
        assert abs(float(robot.base_state().pose.position[2]) - h0) < 0.05 * h0


async def test_a_named_keyframe_places_the_base_too(tmp_path: Path) -> None:
    robot_yaml = _yaml(tmp_path, _scene(tmp_path), "initial_group_state: crouch\n")
    async with agentsdk.connect("mujoco", robot=robot_yaml) as robot:
        assert float(robot.base_state().pose.position[2]) == pytest.approx(0.18)
        np.testing.assert_allclose((await robot.read()).position[1::2], -1.8)


async def test_floating_base_on_an_mjcf_without_a_free_joint(tmp_path: Path) -> None:
    """robot.yaml floating_base: true frees the one body attached to the world; keyframes keep working."""
    async with agentsdk.connect("mujoco", robot=_yaml(tmp_path, WELDED, "floating_base: true\n")) as robot:
        ctl = robot.backend
        assert ctl.model.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
        np.testing.assert_allclose((await robot.read()).position, [0.3, 0.4, 0.8], atol=1e-9)
        assert float(robot.base_state().pose.position[2]) == pytest.approx(0.0, abs=1e-9)  # the base on the ground


# --------------------------------------------------------------------------- one collision rule


def test_check_reports_the_world_welded_pair_touching_at_the_start_pose(tmp_path: Path) -> None:
    config, desc = resolve_robot(WELDED)
    collision = from_mjcf(desc, config)
    assert collision.excluded[("base_link", "shoulder_link")] == "touching at the start pose"
    assert ("base_link", "shoulder_link") not in collision.pairs
    assert ("base_link", "upper_arm") in collision.pairs  # a pair apart at the start pose still collides
    config, desc = resolve_robot(_yaml(tmp_path, WELDED, "self_collision: true\n"))
    assert ("base_link", "shoulder_link") in from_mjcf(desc, config).pairs


@pytest.mark.parametrize("self_collision", ["auto", "true"])
async def test_a_world_welded_contact_at_the_start_pose_does_not_drag_the_joint(
    tmp_path: Path, self_collision: str
) -> None:
    robot_yaml = _yaml(tmp_path, WELDED, f"self_collision: {self_collision}\n")
    async with agentsdk.connect("mujoco", robot=robot_yaml) as robot:
        ctl = robot.backend
        start = (await robot.read()).position.copy()
        await robot.clock.sleep(2.0)
        assert np.abs((await robot.read()).position - start).max() < 0.005
        result = await robot.move_to({"joint_1": 0.55, "joint_2": 0.65, "joint_3": 1.05})
        if self_collision == "auto":
            assert ctl.mjcf_touching == {("base_link", "shoulder_link")}
            assert result.ok, result
            assert max(abs(v) for v in result.error.values()) < 0.02
        else:  # the model's own contact: the base drags joint_1 (what the rule is for)
            assert ctl.mjcf_touching == frozenset()
            assert not result.ok and abs(result.error["joint_1"]) > 0.02


def test_a_robot_never_loses_its_contact_with_the_scene(tmp_path: Path) -> None:
    """Feet on a floor body at the start pose keep colliding with it: only pairs within one tree are excluded."""
    shutil.copy(QUADRUPED, tmp_path / QUADRUPED.name)
    scene = tmp_path / "scene.xml"
    scene.write_text(
        f'<mujoco model="box floor"><include file="{QUADRUPED.name}"/>'
        '<worldbody><body name="slab" pos="0 0 -0.05"><geom type="box" size="1 1 0.05"/></body></worldbody></mujoco>'
    )
    config, desc = resolve_robot(scene)
    collision = from_mjcf(desc, config)
    assert not any("slab" in p for p in collision.excluded if collision.excluded[p] == "touching at the start pose")
    assert ("FL_foot", "slab") in collision.pairs


# --------------------------------------------------------------------------- legged URDFs


def test_a_legged_urdf_says_what_to_set() -> None:
    config, desc = resolve_robot(corpus("go2_description/urdf/go2.urdf"))
    pose = start_pose(desc, config, apply_overrides(desc, config))
    assert pose.summary().endswith("from SRDF group_state 'standing'")  # the SRDF in ../srdf
    lines = "\n".join(report_lines(desc, config, pose))
    assert "looks legged: base link 'base' with 4 feet (FL_foot, FR_foot, RL_foot, RR_foot)" in lines
    assert "floating_base: true (it starts in 'standing')" in lines
    looks = mobility(desc, floating_base=True)
    assert looks is not None and looks.floating == "robot.yaml"
    config, desc = resolve_robot(corpus("panda_description/urdf/panda.urdf"))
    assert mobility(desc) is None


def test_a_free_object_in_the_scene_is_not_the_base(tmp_path: Path) -> None:
    """Only a free body carrying commanded joints is the floating base (not a ball beside a mounted arm)."""
    shutil.copy(WELDED, tmp_path / WELDED.name)
    scene = tmp_path / "scene.xml"
    scene.write_text(
        f'<mujoco model="arm and ball"><include file="{WELDED.name}"/><worldbody>'
        '<geom name="floor" type="plane" size="0 0 0.05"/>'
        '<body name="ball" pos="0.4 0 0.05"><freejoint/><geom type="sphere" size="0.04" mass="0.1"/></body>'
        "</worldbody></mujoco>"
    )
    desc = load_description(scene)
    assert desc.free_root is None and mobility(desc) is None
    shutil.copy(QUADRUPED, tmp_path / QUADRUPED.name)
    scene.write_text(
        f'<mujoco model="dog and ball"><include file="{QUADRUPED.name}"/><worldbody>'
        '<body name="ball" pos="0.6 0 0.05"><freejoint/><geom type="sphere" size="0.04" mass="0.1"/></body>'
        "</worldbody></mujoco>"
    )
    assert load_description(scene).free_root == "trunk"


def test_an_srdf_in_the_package_is_found_and_its_ready_state_starts_the_robot(tmp_path: Path) -> None:
    """A URDF deeper in its package (pkg/urdf/robots/) finds pkg/srdf/; `ready` is a start-pose name."""
    pkg = tmp_path / "two_link_description"
    (pkg / "urdf" / "robots").mkdir(parents=True)
    (pkg / "srdf").mkdir()
    (pkg / "package.xml").write_text("<package><name>two_link_description</name></package>")
    inertial = (
        '<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>'
    )
    joint = '<joint name="{n}" type="revolute"><parent link="{p}"/><child link="{c}"/><origin xyz="0 0 {z}"/>' \
        '<axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="50" velocity="2"/></joint>'
    (pkg / "urdf" / "robots" / "two_link.urdf").write_text(
        '<robot name="two_link"><link name="base"/>'
        f'<link name="a">{inertial}</link><link name="b">{inertial}</link>'
        + joint.format(n="j1", p="base", c="a", z=0.1) + joint.format(n="j2", p="a", c="b", z=0.3) + "</robot>"
    )
    (pkg / "srdf" / "two_link.srdf").write_text(
        '<robot name="two_link"><group_state name="folded" group="arm"><joint name="j1" value="1.0"/></group_state>'
        '<group_state name="ready" group="arm"><joint name="j1" value="0.4"/><joint name="j2" value="-0.7"/>'
        "</group_state></robot>"
    )
    config, desc = resolve_robot(pkg / "urdf" / "robots" / "two_link.urdf")
    assert desc.srdf == (pkg / "srdf" / "two_link.srdf").resolve()
    pose = start_pose(desc, config)
    assert pose.positions == {"j1": 0.4, "j2": -0.7} and set(pose.sources.values()) == {"srdf ready"}
    assert mobility(desc) is None  # an arm: no feet, no wheels


def _two_limbs(tmp_path: Path, name: str, down: bool) -> Path:
    """A free-standing body (root not 'world') with two 2-joint limbs, hanging down or held out sideways."""
    inertial = (
        '<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>'
    )
    links = [f'<link name="body">{inertial}</link>']
    joints = []
    for side, y in (("left", 0.1), ("right", -0.1)):
        step = "0 0 -0.2" if down else f"0 {y * 2} 0"
        for k, (parent, xyz) in enumerate((("body", f"0 {y} 0"), (f"{side}_upper", step))):
            child = f"{side}_upper" if k == 0 else f"{side}_lower"
            links.append(f'<link name="{child}">{inertial}</link>')
            joints.append(
                f'<joint name="{child}_joint" type="revolute"><parent link="{parent}"/><child link="{child}"/>'
                f'<origin xyz="{xyz}"/><axis xyz="0 1 0"/>'
                '<limit lower="-1" upper="1" effort="20" velocity="2"/></joint>'
            )
        links.append(f'<link name="{side}_end">{inertial}</link>')
        joints.append(f'<joint name="{side}_end_joint" type="fixed"><parent link="{side}_lower"/>'
                      f'<child link="{side}_end"/><origin xyz="{step}"/></joint>')
    path = tmp_path / f"{name}.urdf"
    path.write_text(f'<robot name="{name}">' + "".join(links + joints) + "</robot>")
    return path


def test_legs_without_foot_names_are_found_by_where_they_hang(tmp_path: Path) -> None:
    config, desc = resolve_robot(_two_limbs(tmp_path, "biped", down=True))
    looks = mobility(desc, positions=start_pose(desc, config).positions)
    assert looks is not None and looks.kind == "legged" and set(looks.contacts) == {"left_end", "right_end"}
    config, desc = resolve_robot(_two_limbs(tmp_path, "two_arms", down=False))
    assert mobility(desc, positions=start_pose(desc, config).positions) is None  # arms held out: not legs
