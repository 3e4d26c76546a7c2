"""Link poses in the motion feedback stream and the feedback-loop pattern (issue 15 item 3).

Lockstep, deterministic: every pose is checked against ``robot.kinematics.fk`` at the
measured state of the same stamp, captured independently by an OBSERVE tick hook.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest
from mcap.reader import make_reader

import agentsdk
from agentsdk import (
    FeedbackState,
    InvalidValueError,
    JointCommand,
    JointState,
    Trajectory,
    TrajectoryPoint,
    UnknownLinkError,
)
from agentsdk.feedback import FeedbackAgent, run_feedback
from agentsdk.kinematics import Kinematics
from agentsdk.loop import Phase
from agentsdk.pose import Pose
from agentsdk.recording import Recorder

pytestmark = pytest.mark.timeout(120)

SAFETY = {"stall_timeout": 5.0}
BACKENDS = ["mock", "mujoco"]
LINKS = ("ee_link", "link2")


@pytest.fixture(params=BACKENDS)
async def arm(request: pytest.FixtureRequest) -> AsyncIterator[agentsdk.Robot]:
    async with agentsdk.connect(request.param, robot="arm3", safety=SAFETY) as robot:
        yield robot


def _measured(robot: agentsdk.Robot) -> dict[float, np.ndarray]:
    """``{stamp: measured positions}`` of every tick from now on (an independent record)."""
    states: dict[float, np.ndarray] = {robot.latest_state().stamp: robot.latest_state().position.copy()}

    def observe(t: float, st: object, sp: object) -> None:
        states[t] = st.position.copy()  # type: ignore[attr-defined]

    robot.add_tick_hook(Phase.OBSERVE, observe)
    return states


def _assert_pose(got: Pose, want: Pose, atol: float = 1e-9) -> None:
    np.testing.assert_allclose(got.position, want.position, rtol=0, atol=atol)
    # q and -q are the same rotation
    dot = abs(float(np.dot(got.orientation, want.orientation)))
    assert dot == pytest.approx(1.0, abs=atol)
    np.testing.assert_allclose(got.matrix, want.matrix, rtol=0, atol=atol)


def _wave() -> Trajectory:
    return Trajectory(
        joint_names=["joint1", "joint2", "joint3"],
        points=[
            TrajectoryPoint(time_from_start=1.0, positions=[0.6, 0.5, -0.6], velocities=[0.0, 0.0, 0.0]),
            TrajectoryPoint(time_from_start=2.0, positions=[-0.3, 0.9, 0.3], velocities=[0.0, 0.0, 0.0]),
        ],
    )


def _check_feedback(fb: agentsdk.Feedback, motion: agentsdk.Motion, q: np.ndarray, kin: Kinematics) -> None:
    np.testing.assert_array_equal(fb.actual_positions, q[motion.idx])
    qd = q.copy()
    qd[motion.idx] = fb.desired_positions
    assert tuple(fb.poses) == LINKS and tuple(fb.desired_poses) == LINKS
    for link in LINKS:
        _assert_pose(fb.poses[link], kin.fk(link, q))
        _assert_pose(fb.desired_poses[link], kin.fk(link, qd))


async def test_motion_feedback_carries_link_poses_at_the_measured_state(arm: agentsdk.Robot) -> None:
    states = _measured(arm)
    kin = arm.kinematics
    motion = arm.follow(_wave())
    msgs = [fb async for fb in motion.feedback(rate=50.0, links=LINKS)]
    result = await motion
    assert result.ok, result
    assert len(msgs) >= 95  # 2 s at 50 Hz, the last message included
    assert msgs[-1].progress == 1.0
    for fb in msgs:
        _check_feedback(fb, motion, states[fb.time], kin)
    # the end effector moves along the trajectory: its reported pose changes
    ee = np.array([fb.poses["ee_link"].position for fb in msgs])
    steps = np.linalg.norm(np.diff(ee, axis=0), axis=1)
    assert np.count_nonzero(steps > 1e-5) >= 0.9 * len(steps)  # moving in nearly every period (rests at the points)
    assert np.linalg.norm(ee[-1] - ee[0]) > 0.05
    assert float(np.linalg.norm(ee[len(ee) // 2] - ee[0])) > 0.05
    # ...and its end pose is the FK of the goal
    _assert_pose(msgs[-1].desired_poses["ee_link"], kin.fk("ee_link", {"joint1": -0.3, "joint2": 0.9, "joint3": 0.3}),
                 atol=1e-6)


async def test_poses_use_every_joints_measured_state_not_only_the_motions(arm: agentsdk.Robot) -> None:
    """joint1 is not in the motion but turns meanwhile: the poses still use its value at ``fb.time``."""
    states = _measured(arm)
    kin = arm.kinematics
    await arm.command(JointCommand("velocity", {"joint1": 0.4}))
    traj = Trajectory(
        joint_names=["joint2", "joint3"],
        points=[TrajectoryPoint(time_from_start=1.0, positions=[0.7, -0.5], velocities=[0.0, 0.0])],
    )
    motion = arm.follow(traj)
    msgs = []
    async for fb in motion.feedback(rate=50.0, links=LINKS):
        msgs.append(fb)
        await arm.command(JointCommand("velocity", {"joint1": 0.4}))  # feed the command watchdog
    assert (await motion).ok
    await arm.command(JointCommand("velocity", {"joint1": 0.0}))
    q1 = [states[fb.time][0] for fb in msgs]
    assert q1[-1] - q1[0] > 0.2  # joint1 did turn during the motion
    for fb in msgs:
        q = states[fb.time]
        qd = q.copy()
        qd[motion.idx] = fb.desired_positions
        for link in LINKS:
            _assert_pose(fb.poses[link], kin.fk(link, q))
            _assert_pose(fb.desired_poses[link], kin.fk(link, qd))


async def test_a_pose_stream_started_mid_motion_is_exact_from_its_first_message(arm: agentsdk.Robot) -> None:
    states = _measured(arm)
    motion = arm.follow(_wave())
    plain = motion.feedback(rate=100.0)  # a stream without poses alongside
    first = await anext(plain)
    assert first.poses == {} and first.desired_poses == {}
    await arm.clock.sleep(0.3)
    msgs = []
    async for fb in motion.feedback(rate=25.0, links=LINKS):
        msgs.append(fb)
        if len(msgs) == 5:
            break
    await plain.aclose()
    assert msgs[0].time >= 0.3
    for fb in msgs:
        _check_feedback(fb, motion, states[fb.time], arm.kinematics)
    assert (await motion).ok


async def test_a_single_link_name_is_accepted(arm: agentsdk.Robot) -> None:
    motion = arm.follow(_wave())
    async for fb in motion.feedback(rate=10.0, links="ee_link"):
        assert tuple(fb.poses) == ("ee_link",)
    assert (await motion).ok


async def test_unknown_link_fails_at_the_call_and_the_robot_stays_usable(arm: agentsdk.Robot) -> None:
    motion = arm.follow(_wave())
    with pytest.raises(UnknownLinkError) as exc:
        motion.feedback(rate=20.0, links=("ee_link", "gripper_tcp"))  # raised here, not when iterated
    msg = str(exc.value)
    assert "'gripper_tcp'" in msg
    for link in arm.link_names:
        assert link in msg
    with pytest.raises(InvalidValueError):
        motion.feedback(links=(3,))  # type: ignore[arg-type]
    with pytest.raises(InvalidValueError):
        motion.feedback(rate=0.0, links=LINKS)
    assert (await motion).ok

    calls: list[str] = []

    class Agent(FeedbackAgent):
        rate = 50.0
        links = ("nope",)

        async def setup(self, robot: agentsdk.Robot) -> None:
            calls.append("setup")

        async def update(self, state: JointState) -> None:
            calls.append("update")

    with pytest.raises(UnknownLinkError, match="'nope'"):
        await run_feedback(arm, Agent(), duration=0.1)
    with pytest.raises(UnknownLinkError, match="'nope'"):
        await run_feedback(arm, lambda s: None, 50.0, duration=0.1, links=["ee_link", "nope"])
    assert calls == []  # rejected before setup
    assert (await arm.move_to({"joint1": 0.2})).ok


class PoseLogger(FeedbackAgent):
    """Swings joint2 and joint3 and logs the poses it was handed."""

    rate = 100.0
    links: ClassVar[tuple[str, ...]] = LINKS

    def __init__(self) -> None:
        self.seen: list[FeedbackState] = []

    async def update(self, state: JointState) -> JointCommand:
        assert isinstance(state, FeedbackState)
        self.seen.append(state)
        s = state.stamp
        return JointCommand("position", {"joint2": 0.8 * np.sin(3.0 * s), "joint3": -0.6 * np.sin(2.0 * s)})


async def test_feedback_loop_state_carries_link_poses(arm: agentsdk.Robot) -> None:
    states = _measured(arm)
    kin = arm.kinematics
    agent = PoseLogger()
    stats = await agent.run(arm, duration=1.0)
    assert stats.count == 100 == len(agent.seen)
    for st in agent.seen:
        assert tuple(st.poses) == LINKS
        np.testing.assert_array_equal(st.position, states[st.stamp])
        for link in LINKS:
            _assert_pose(st.poses[link], kin.fk(link, st.position))
        # still the JointState it extends
        assert st.positions() == dict(zip(arm.joint_names, st.position.tolist(), strict=True))
    ee = np.array([st.poses["ee_link"].position for st in agent.seen])
    assert np.ptp(ee, axis=0).max() > 0.05  # the end effector moved, and the poses followed


async def test_feedback_loop_links_argument_and_plain_state_without_links(arm: agentsdk.Robot) -> None:
    seen: list[JointState] = []

    async def update(state: JointState) -> None:
        seen.append(state)

    await run_feedback(arm, update, 50.0, duration=0.1, links="ee_link")
    assert all(isinstance(s, FeedbackState) and tuple(s.poses) == ("ee_link",) for s in seen)
    seen.clear()
    await run_feedback(arm, update, 50.0, duration=0.1)
    assert seen and all(type(s) is JointState for s in seen)

    class Types(FeedbackAgent):
        rate = 50.0
        links = LINKS

        def __init__(self) -> None:
            self.types: set[type] = set()

        async def update(self, state: JointState) -> None:
            self.types.add(type(state))

    agent = Types()
    await agent.run(arm, duration=0.1)
    assert agent.types == {FeedbackState}
    agent = Types()
    await agent.run(arm, duration=0.1, links=())  # the call's links override the class's
    assert agent.types == {JointState}


def _read_tf(path: Path) -> dict[int, Any]:
    """``{log time: tf2_msgs/TFMessage}`` decoded by rosbags (an independent CDR implementation)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    with open(path, "rb") as f:
        messages = make_reader(f).iter_messages(topics=["/tf"])
        return {m.log_time: store.deserialize_cdr(m.data, s.name) for s, _c, m in messages}


def _chain_pose(transforms: dict[str, tuple[str, Pose]], root: str, link: str) -> Pose:
    pose = Pose.identity()
    while link != root:
        parent, rel = transforms[link]
        pose = rel @ pose
        link = parent
    return pose


async def test_recording_tf_contains_the_chosen_links_matching_the_feedback(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
        rec = Recorder.attach(robot, path, tf_rate=1.0 / robot.control_period)  # every tick's TF
        motion = robot.follow(_wave())
        msgs = [fb async for fb in motion.feedback(rate=50.0, links=LINKS)]
        assert (await motion).ok
        root = robot.kinematics.root_link
    rec.finish()
    tfs = _read_tf(path)
    matched = 0
    for fb in msgs:
        msg = tfs.get(round(fb.time * 1e9))
        if msg is None:
            continue
        matched += 1
        transforms = {}
        for tr in msg.transforms:
            t, r = tr.transform.translation, tr.transform.rotation
            transforms[tr.child_frame_id] = (
                tr.header.frame_id,
                Pose(position=[t.x, t.y, t.z], orientation=[r.x, r.y, r.z, r.w]),
            )
        for link in LINKS:
            assert link in transforms  # /tf carries every link, so the chosen ones too
            _assert_pose(_chain_pose(transforms, root, link), fb.poses[link], atol=1e-9)
    assert matched == len(msgs)
