"""Kinematics: Pose algebra, FK against raw MuJoCo and raw PyBullet, Jacobians, IK, MJCF models.

The references are independent of agentsdk's kinematic model: MuJoCo's own URDF import
(``MjSpec.from_string`` of the resolved URDF, as a user would load it) and PyBullet's
``loadURDF`` + ``getLinkState`` (the URDF link frame, indices 4/5), at random joint
configurations within the limits.
"""

from __future__ import annotations

import importlib.metadata
import math
from pathlib import Path

import mujoco
import numpy as np
import pybullet as p
import pytest

from agentsdk import InvalidValueError, Pose, UnknownJointError, UnknownLinkError, UnreachablePoseError
from agentsdk.description import RobotDescription, load_description, resolve_robot
from agentsdk.kinematics import IKResult, Kinematics
from agentsdk.pose import quat_to_matrix

CORPUS = Path(
    str(
        importlib.metadata.distribution("example-robot-data").locate_file(
            "cmeel.prefix/share/example-robot-data/robots"
        )
    )
)
CORPUS_ROBOTS = {
    "ur5": "ur_description/urdf/ur5_robot.urdf",
    "panda": "panda_description/urdf/panda.urdf",
    "kinova": "kinova_description/robots/kinova.urdf",
    "z1": "z1_description/urdf/z1.urdf",
    "xarm7": "xarm_description/urdf/xarm7.urdf",
    "so100": "so_arm_description/urdf/so100.urdf",
    "talos_left_arm": "talos_data/robots/talos_left_arm.urdf",
    "baxter": "baxter_description/urdf/baxter.urdf",
    "solo12": "solo_description/robots/solo12.urdf",
}
TOL_M = 1e-6
TOL_RAD = 1e-6
_CACHE: dict[str, RobotDescription] = {}


def describe(name: str) -> RobotDescription:
    if name not in _CACHE:
        if name in CORPUS_ROBOTS:
            _CACHE[name] = load_description(CORPUS / CORPUS_ROBOTS[name])
        else:
            _CACHE[name] = resolve_robot(name)[1]
    return _CACHE[name]


def random_positions(kin: Kinematics, rng: np.random.Generator) -> np.ndarray:
    lo = np.where(np.isfinite(kin.lower), kin.lower, -math.pi)
    hi = np.where(np.isfinite(kin.upper), kin.upper, math.pi)
    return rng.uniform(lo, hi)


def all_positions(desc: RobotDescription, q: np.ndarray) -> dict[str, float]:
    """Actuated and mimic joint values, as a simulator user sets them."""
    out = dict(zip(desc.joint_names, q.tolist(), strict=True))
    for rec in desc.all_joints:
        if rec.mimic is not None:
            out[rec.name] = rec.mimic_multiplier * out[rec.mimic] + rec.mimic_offset
    return out


def angle_between(r1: np.ndarray, r2: np.ndarray) -> float:
    c = (np.trace(r1.T @ r2) - 1.0) / 2.0
    # acos loses precision near 0: use the skew part for small angles
    s = np.linalg.norm(np.array([r1.T @ r2 - (r1.T @ r2).T])[0][[2, 0, 1], [1, 2, 0]]) / 2.0
    return float(math.atan2(s, min(1.0, max(-1.0, c))))


# --------------------------------------------------------------------------- Pose


def test_pose_basics_and_validation() -> None:
    a = Pose.from_xyz_rpy([0.1, -0.2, 0.3], [0.3, -0.5, 1.2])
    b = Pose([0.5, 0.0, -0.1], [0.0, 0.0, math.sin(0.4), math.cos(0.4)])
    assert np.allclose((a @ b).matrix, a.matrix @ b.matrix, atol=1e-12)
    assert np.allclose((a * b).matrix, (a @ b).matrix)
    assert (a @ a.inverse()).isclose(Pose(), atol=1e-12, angle_tol=1e-12)
    assert Pose.from_matrix(a.matrix).isclose(a, atol=1e-12, angle_tol=1e-12)
    assert np.allclose(a.rpy, [0.3, -0.5, 1.2])
    assert np.allclose(a.apply([[0, 0, 0], [1, 0, 0]])[1], a.matrix[:3, :3] @ [1, 0, 0] + a.position)
    assert a.orientation.shape == (4,) and abs(np.linalg.norm(a.orientation) - 1) < 1e-12
    with pytest.raises(AttributeError):
        a.position = np.zeros(3)  # type: ignore[misc]
    with pytest.raises(ValueError):
        a.position[0] = 1.0
    for bad in ([0, 0, 0, 0], [0, 0, 0, 2], [math.nan, 0, 0, 1], [0, 0, 1]):
        with pytest.raises(InvalidValueError):
            Pose([0, 0, 0], bad)
    with pytest.raises(InvalidValueError, match="position"):
        Pose([0, 0], [0, 0, 0, 1])
    with pytest.raises(InvalidValueError, match="rotation"):
        Pose.from_matrix(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(InvalidValueError):
        Pose.from_matrix(np.eye(3))


# --------------------------------------------------------------------------- FK vs simulators


def _mujoco_reference(desc: RobotDescription) -> mujoco.MjModel:
    spec = mujoco.MjSpec.from_string(desc.urdf_xml)
    spec.compiler.fusestatic = False  # keep fixed-joint links as bodies to compare them too
    for geom in list(spec.geoms):
        spec.delete(geom)
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    try:
        return spec.compile()
    except ValueError:  # invalid inertial data in some corpus URDFs: FK does not depend on it
        spec.compiler.balanceinertia = True
        spec.compiler.boundmass = 1e-9
        spec.compiler.boundinertia = 1e-12
        for body in spec.bodies:
            if np.isfinite(body.fullinertia).all():
                body.fullinertia = [math.nan] * 6
                body.inertia = [1e-3, 1e-3, 1e-3]
        return spec.compile()


FK_ROBOTS = ["arm3", "humanoid", *CORPUS_ROBOTS]


@pytest.mark.parametrize("name", FK_ROBOTS)
def test_fk_matches_raw_mujoco(name: str) -> None:
    desc = describe(name)
    kin = Kinematics(desc)
    model = _mujoco_reference(desc)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(7)
    compared = 0
    for _ in range(10):
        q = random_positions(kin, rng)
        for jname, v in all_positions(desc, q).items():
            data.qpos[model.jnt_qposadr[model.joint(jname).id]] = v
        mujoco.mj_kinematics(model, data)
        poses = kin.link_poses(q)
        for link in kin.link_names:
            if link == "world":
                continue
            body = model.body(link).id
            pose = kin.fk(link, q)
            assert poses[link].isclose(pose, atol=0, angle_tol=0) or poses[link].isclose(pose, 1e-12, 1e-12)
            assert np.linalg.norm(pose.position - data.xpos[body]) < TOL_M, link
            assert angle_between(pose.rotation, data.xmat[body].reshape(3, 3)) < TOL_RAD, link
            compared += 1
    assert compared >= 10 * (len(kin.link_names) - 1)


@pytest.mark.parametrize("name", FK_ROBOTS)
def test_fk_matches_raw_pybullet(name: str, tmp_path: Path) -> None:
    desc = describe(name)
    kin = Kinematics(desc)
    urdf = desc.write_urdf(tmp_path)
    cid = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(str(urdf), useFixedBase=True, physicsClientId=cid)
        links: dict[str, int] = {}
        joints: dict[str, int] = {}
        for i in range(p.getNumJoints(body, physicsClientId=cid)):
            info = p.getJointInfo(body, i, physicsClientId=cid)
            links[info[12].decode()] = i
            joints[info[1].decode()] = i
        assert set(links) <= set(kin.link_names)
        rng = np.random.default_rng(11)
        for _ in range(10):
            q = random_positions(kin, rng)
            for jname, v in all_positions(desc, q).items():
                p.resetJointState(body, joints[jname], v, physicsClientId=cid)
            tf = kin.link_poses(q)
            for link, i in links.items():
                state = p.getLinkState(body, i, computeForwardKinematics=True, physicsClientId=cid)
                pos, quat = np.array(state[4]), np.array(state[5])
                pose = tf.relative(link, kin.root_link)
                assert np.linalg.norm(pose.position - pos) < TOL_M, link
                assert angle_between(pose.rotation, quat_to_matrix(quat)) < TOL_RAD, link
    finally:
        p.disconnect(cid)


def test_fixed_joint_frames_and_reference() -> None:
    kin = Kinematics(describe("ur5"))
    assert {"tool0", "ee_link", "base_link", "world"} <= set(kin.link_names)
    assert kin.link_names[0] == kin.root_link
    q = [0.3, -1.1, 1.4, -0.2, 0.9, 0.4]
    tool = kin.fk("tool0", q)
    wrist = kin.fk("wrist_3_link", q)
    assert kin.fk("tool0", q, reference="wrist_3_link").isclose(wrist.inverse() @ tool, 1e-12, 1e-12)
    tf = kin.link_poses(q)
    assert tf.relative("tool0", "wrist_3_link").isclose(wrist.inverse() @ tool, 1e-12, 1e-12)
    # the parent -> child transforms chain up to every link's pose
    chained = {tf.root: Pose()}
    for parent, child, rel in tf.transforms():
        chained[child] = chained[parent] @ rel
    for link in kin.link_names:
        assert chained[link].isclose(tf[link], 1e-12, 1e-12)


def test_positions_forms_and_bad_input() -> None:
    desc = describe("arm3")
    kin = Kinematics(desc)
    assert kin.fk("ee_link", {"joint2": 0.5}).isclose(kin.fk("ee_link", [0.0, 0.5, 0.0]))
    with pytest.raises(UnknownLinkError, match="no link 'nope'"):
        kin.fk("nope")
    with pytest.raises(UnknownLinkError):
        kin.jacobian("nope")
    with pytest.raises(UnknownLinkError):
        kin.fk("ee_link", reference="nope")
    with pytest.raises(UnknownJointError, match="jointX"):
        kin.fk("ee_link", {"jointX": 0.1})
    with pytest.raises(InvalidValueError, match="3 joints"):
        kin.fk("ee_link", [0.1, 0.2])
    with pytest.raises(InvalidValueError, match="nan"):
        kin.fk("ee_link", [0.1, math.nan, 0.0])
    with pytest.raises(InvalidValueError):
        kin.fk("ee_link", {"joint1": "abc"})


# --------------------------------------------------------------------------- Jacobian


@pytest.mark.parametrize("name,link", [("arm3", "ee_link"), ("ur5", "tool0"), ("panda", "panda_hand_tcp"),
                                       ("panda", "panda_rightfinger"), ("humanoid", None)])
def test_jacobian_matches_finite_differences(name: str, link: str | None) -> None:
    kin = Kinematics(describe(name))
    link = link or kin.link_names[-1]
    rng = np.random.default_rng(3)
    eps = 1e-6
    for _ in range(5):
        q = random_positions(kin, rng) * 0.9
        jac = kin.jacobian(link, q)
        assert jac.shape == (6, len(kin.joints))
        base = kin.fk(link, q)
        for k in range(len(kin.joints)):
            dq = q.copy()
            dq[k] += eps
            moved = kin.fk(link, dq)
            v = (moved.position - base.position) / eps
            drot = moved.rotation @ base.rotation.T  # world-frame angular displacement
            w = np.array([drot[2, 1] - drot[1, 2], drot[0, 2] - drot[2, 0], drot[1, 0] - drot[0, 1]]) / (2 * eps)
            assert np.allclose(jac[:3, k], v, atol=1e-5), (k, jac[:3, k], v)
            assert np.allclose(jac[3:, k], w, atol=1e-5), (k, jac[3:, k], w)


def test_mimic_joint_follows_its_leader() -> None:
    desc = describe("panda")
    kin = Kinematics(desc)
    assert "panda_finger_joint2" not in kin.joint_names  # a mimic joint is not actuated
    k = kin.joint_names.index("panda_finger_joint1")
    q = np.zeros(len(kin.joints))
    q[k] = 0.03
    left = kin.fk("panda_leftfinger", q, reference="panda_hand")
    right = kin.fk("panda_rightfinger", q, reference="panda_hand")
    assert abs(left.position[1] - 0.03) < 1e-12 and abs(right.position[1] + 0.03) < 1e-12


# --------------------------------------------------------------------------- gravity


@pytest.mark.parametrize("name", ["arm3", "ur5", "panda", "kinova", "z1"])
def test_gravity_matches_mujoco_bias_at_rest(name: str) -> None:
    desc = describe(name)
    kin = Kinematics(desc)
    model = _mujoco_reference(desc)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(5)
    for _ in range(5):
        q = random_positions(kin, rng)
        for jname, v in all_positions(desc, q).items():
            data.qpos[model.jnt_qposadr[model.joint(jname).id]] = v
        mujoco.mj_forward(model, data)
        ref = np.array([data.qfrc_bias[model.jnt_dofadr[model.joint(j).id]] for j in kin.joint_names])
        mimics = [r for r in desc.all_joints if r.mimic]
        for r in mimics:
            ref[kin.joint_names.index(r.mimic)] += r.mimic_multiplier * data.qfrc_bias[
                model.jnt_dofadr[model.joint(r.name).id]]
        assert np.allclose(kin.gravity(q), ref, atol=1e-9)


# --------------------------------------------------------------------------- IK


@pytest.mark.parametrize("name,link", [("ur5", "tool0"), ("panda", "panda_hand_tcp")])
def test_ik_reaches_100_random_reachable_poses(name: str, link: str) -> None:
    kin = Kinematics(describe(name))
    rng = np.random.default_rng(2024)
    seed = np.clip(np.zeros(len(kin.joints)), kin.lower, kin.upper)
    for _ in range(100):
        goal = kin.fk(link, random_positions(kin, rng))
        sol = kin.ik(link, goal, seed=seed)
        assert isinstance(sol, IKResult) and sol.ok
        q = np.array([sol[j] for j in kin.joint_names])
        assert (q >= kin.lower).all() and (q <= kin.upper).all()
        reached = kin.fk(link, sol)
        dist, angle = reached.distance(goal)
        assert dist <= 1e-3 and angle <= 0.01
        assert abs(dist - sol.position_error) < 1e-9


def test_ik_position_only_on_a_3_joint_arm() -> None:
    kin = Kinematics(describe("arm3"))
    goal = kin.fk("ee_link", [0.4, 0.7, -1.0]).position
    sol = kin.ik("ee_link", goal, seed=[0.0, 0.3, 0.0])
    assert np.linalg.norm(kin.fk("ee_link", sol).position - goal) < 1e-4
    assert sol.orientation_error == 0.0


def test_ik_unreachable_pose_names_the_residual() -> None:
    kin = Kinematics(describe("ur5"))
    far = Pose([3.0, 0.0, 0.5])
    with pytest.raises(UnreachablePoseError, match=r"residual \d\.\d+ m position") as info:
        kin.ik("tool0", far, restarts=3)
    best = info.value.result
    assert isinstance(best, IKResult) and not best.ok
    assert best.position_error > 2.0  # UR5 reaches ~0.85 m
    assert "tool0" in str(info.value)
    with pytest.raises(UnknownLinkError):
        kin.ik("nope", far)
    with pytest.raises(InvalidValueError):
        kin.ik("tool0", [1.0, 2.0])


# --------------------------------------------------------------------------- MJCF

MJCF_ARM = """
<mujoco model="menagerie_style_arm">
  <compiler angle="radian" autolimits="true"/>
  <default>
    <default class="arm">
      <joint axis="0 0 1" damping="0.5" armature="0.1" range="-2.9 2.9"/>
      <geom type="capsule" size="0.04" density="1000"/>
      <default class="wrist"><joint range="-1.8 1.8"/></default>
    </default>
  </default>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <body name="base" pos="0.1 -0.2 0.05" quat="0 0 0 -1" childclass="arm">
      <inertial pos="0 0 0.05" mass="4" diaginertia="0.02 0.02 0.02"/>
      <geom type="cylinder" size="0.08 0.05"/>
      <body name="link1" pos="0 0 0.1">
        <joint name="joint1"/>
        <geom fromto="0 0 0 0 0 0.25"/>
        <body name="link2" pos="0 0 0.25" euler="1.5707963 0 0">
          <joint name="joint2"/>
          <geom fromto="0 0 0 0.3 0 0"/>
          <body name="link3" pos="0.3 0 0" axisangle="0 0 1 0.4">
            <joint name="joint3" range="-2.5 0.5"/>
            <geom fromto="0 0 0 0.28 0 0"/>
            <body name="link4" pos="0.28 0 0" xyaxes="0 1 0 0 0 1">
              <joint name="joint4" class="wrist"/>
              <geom fromto="0 0 0 0 0 0.1" size="0.03"/>
              <body name="link5" pos="0 0 0.1" zaxis="1 0 0">
                <joint name="joint5" class="wrist" axis="0 1 0"/>
                <geom fromto="0 0 0 0.08 0 0" size="0.03"/>
                <body name="link6" pos="0.08 0 0">
                  <joint name="joint6" axis="1 0 0"/>
                  <geom type="box" size="0.02 0.02 0.02"/>
                  <body name="finger_a" pos="0.03 0.01 0">
                    <joint name="finger_a" type="slide" axis="0 1 0" range="0 0.04"/>
                    <geom type="box" size="0.01 0.01 0.02"/>
                  </body>
                  <body name="finger_b" pos="0.03 -0.01 0">
                    <joint name="finger_b" type="slide" axis="0 1 0" range="-0.04 0"/>
                    <geom type="box" size="0.01 0.01 0.02"/>
                  </body>
                  <body name="attachment" pos="0.06 0 0" euler="0 1.5707963 0"/>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <equality>
    <joint joint1="finger_b" joint2="finger_a" polycoef="0 -1 0 0 0"/>
  </equality>
</mujoco>
"""


@pytest.fixture
def mjcf_arm(tmp_path: Path) -> Path:
    path = tmp_path / "arm.xml"
    path.write_text(MJCF_ARM)
    return path


def test_mjcf_fk_jacobian_ik(mjcf_arm: Path) -> None:
    kin = Kinematics.from_mjcf(mjcf_arm)
    assert kin.joint_names == ("joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "finger_a")
    assert "attachment" in kin.link_names and kin.root_link == "world"
    model = mujoco.MjModel.from_xml_path(str(mjcf_arm))
    data = mujoco.MjData(model)
    rng = np.random.default_rng(1)
    for _ in range(10):
        q = random_positions(kin, rng)
        for jname, v in zip(kin.joint_names, q, strict=True):
            data.qpos[model.jnt_qposadr[model.joint(jname).id]] = v
        data.qpos[model.jnt_qposadr[model.joint("finger_b").id]] = -q[-1]
        mujoco.mj_forward(model, data)
        tf = kin.link_poses(q)
        for b in range(1, model.nbody):
            pose = tf[model.body(b).name]
            assert np.linalg.norm(pose.position - data.xpos[b]) < TOL_M
            assert angle_between(pose.rotation, data.xmat[b].reshape(3, 3)) < TOL_RAD
    # the root body's placement counts (pinocchio 4.1's MJCF parser drops it)
    assert np.allclose(kin.fk("base").position, [0.1, -0.2, 0.05])
    # the mimic-like equality: finger_b follows finger_a
    jac = kin.jacobian("finger_b", q)
    assert jac.shape == (6, 7) and np.linalg.norm(jac[:3, 6]) > 0.9
    goal = kin.fk("attachment", random_positions(kin, rng))
    sol = kin.ik("attachment", goal)
    assert kin.fk("attachment", sol).isclose(goal, atol=1e-4, angle_tol=1e-3)


def test_ik_respects_tightened_limits() -> None:
    desc = describe("arm3")
    from dataclasses import replace

    joints = [replace(j, lower=-0.5, upper=0.5) if j.name == "joint1" else j for j in desc.joints]
    kin = Kinematics(desc, joints)
    reachable = kin.fk("ee_link", [0.4, 0.8, 0.0]).position
    sol = kin.ik("ee_link", reachable, seed=[0.0, 0.5, 0.0])
    assert -0.5 <= sol["joint1"] <= 0.5
    outside = Kinematics(desc).fk("ee_link", [2.0, 0.8, 0.0]).position  # needs joint1 = 2.0 (or a flip)
    with pytest.raises(UnreachablePoseError):
        kin.ik("ee_link", outside, restarts=5)
