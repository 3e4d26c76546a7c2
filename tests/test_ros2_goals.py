"""Issue 23 item 1: ``follow()``/``move_to`` on ``connect("ros2")`` are sent as FollowJointTrajectory goals.

Against an agentsdk robot served in-process (``expose``, realtime: our own JTC face, the same as
``agentsdk serve``) and against a ros2_control-like controller played in-process on DDS with
rmw_cyclonedds' service format (a nested namespace, another controller name, joint_states in
another order with an extra joint), whose results are chosen per test: every FollowJointTrajectory
result code is mapped back to the motion's result. All traffic on 127.0.0.1, a random domain.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import AsyncIterator, Callable
from typing import Any

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from ros_domains import random_domain

import agentsdk
from agentsdk import ResultCode, Tolerances, Trajectory, TrajectoryPoint
from agentsdk.backends.ros2.msgs import Float64MultiArray
from agentsdk.offload import OffloadRequest
from agentsdk.ros2 import expose
from agentsdk.ros2.convert import GOAL_ABORTED, GOAL_CANCELED, GOAL_SUCCEEDED
from agentsdk.ros2.dds import DdsNode
from agentsdk.ros2.goals import goal_message, map_result
from agentsdk.ros2.msgs import (
    UUID,
    CancelGoal_Request,
    CancelGoal_Response,
    Clock,
    FollowJointTrajectory_Feedback,
    FollowJointTrajectory_FeedbackMessage,
    FollowJointTrajectory_GetResult_Request,
    FollowJointTrajectory_GetResult_Response,
    FollowJointTrajectory_Result,
    FollowJointTrajectory_SendGoal_Request,
    FollowJointTrajectory_SendGoal_Response,
    Header,
    JointState,
    JointTrajectory,
    JointTrajectoryPoint,
    Time,
)

pytestmark = [pytest.mark.timeout(120)]

SAFETY = {"stall_timeout": 5.0}


def _domain() -> int:
    return random_domain()


async def _until(predicate: Callable[[], bool]) -> None:
    async with asyncio.timeout(10.0):
        while not predicate():  # noqa: ASYNC110 -- DDS callbacks and the control loops change it
            await asyncio.sleep(0.01)


# ------------------------------------------------------------------ pure rules
def test_goal_message_pads_held_joints_drops_the_start_state_and_maps_tolerances() -> None:
    traj = Trajectory(["joint2"], [TrajectoryPoint(0.0, [0.1], [0.0]), TrajectoryPoint(1.5, [0.4], [0.0])])
    goal = goal_message(OffloadRequest(traj, np.array([math.inf]), np.array([0.01]), 0.5,
                                       {"joint1": -0.2, "joint3": 0.3}))
    assert list(goal.trajectory.joint_names) == ["joint2", "joint1", "joint3"]
    assert len(goal.trajectory.points) == 1  # the point at time 0 (the start state) is the controller's own
    p = goal.trajectory.points[0]
    assert list(p.positions) == [0.4, -0.2, 0.3] and list(p.velocities) == [0.0, 0.0, 0.0]
    assert p.time_from_start.sec == 1 and p.time_from_start.nanosec == 500_000_000
    assert [(t.name, t.position) for t in goal.path_tolerance] == [("joint2", -1.0)]  # inf: not checked
    assert [(t.name, t.position) for t in goal.goal_tolerance] == [("joint2", 0.01)]
    assert goal.goal_time_tolerance.nanosec == 500_000_000
    inf_time = goal_message(OffloadRequest(traj, np.array([0.1]), np.array([0.1]), math.inf, {}))
    assert (inf_time.goal_time_tolerance.sec, inf_time.goal_time_tolerance.nanosec) == (0, 0)


@pytest.mark.parametrize(("status", "code", "expected"), [
    (GOAL_SUCCEEDED, 0, ResultCode.SUCCESSFUL),
    (GOAL_ABORTED, -1, ResultCode.INVALID_GOAL),
    (GOAL_ABORTED, -2, ResultCode.INVALID_JOINTS),
    (GOAL_ABORTED, -3, ResultCode.OLD_HEADER_TIMESTAMP),
    (GOAL_ABORTED, -4, ResultCode.PATH_TOLERANCE_VIOLATED),
    (GOAL_ABORTED, -5, ResultCode.GOAL_TOLERANCE_VIOLATED),
    (GOAL_ABORTED, 0, ResultCode.ABORTED),  # aborted without a reason
    (GOAL_CANCELED, 0, ResultCode.CANCELED),  # JTC cancels with SUCCESSFUL in error_code
    (0, 0, ResultCode.ABORTED),  # STATUS_UNKNOWN: the controller lost the goal
])
def test_controller_results_map_to_result_codes(status: int, code: int, expected: ResultCode) -> None:
    mapped, message = map_result(status, code, "")
    assert ResultCode(mapped) is expected
    assert message or expected is ResultCode.SUCCESSFUL  # a failure always says something


# ------------------------------------------------------------------ against our own JTC face
@contextlib.asynccontextmanager
async def _served(**served_options: Any) -> AsyncIterator[tuple[agentsdk.Robot, Any, agentsdk.Robot]]:
    did = _domain()
    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety=SAFETY, **served_options) as served, \
            expose(served, "/arm1", domain_id=did) as face, \
            agentsdk.connect("ros2", robot="arm3", namespace="/arm1", domain_id=did, safety=SAFETY) as robot:
        yield served, face, robot


@pytest.mark.asyncio
async def test_follow_is_one_goal_with_feedback_and_result_on_a_served_robot() -> None:
    async with _served() as (served, face, robot):
        backend: Any = robot.backend
        assert backend.interface == "agentsdk" and backend.goals_available
        sent = backend.sent
        motion = robot.follow(Trajectory(["joint1", "joint2"], [TrajectoryPoint(0.6, [0.3, -0.2]),
                                                                 TrajectoryPoint(1.2, [0.5, 0.1])]))
        seen, counts = [], []
        async for fb in motion.feedback(rate=20):
            seen.append(fb)
            counts.append(backend.sent)
        result = await motion
        assert result.ok, result
        assert backend.goals_sent == 1 and len(face._goals) == 1  # one goal reached the served robot
        goal = next(iter(face._goals.values()))
        assert goal.result is not None and goal.result.error_code == 0
        # a sync before the goal, nothing while it ran (streamed: one command per tick, ~600)
        assert counts[-2] - sent <= 2, (sent, counts)
        assert served.latest_state().position[:2].tolist() == pytest.approx([0.5, 0.1], abs=0.02)
        # feedback: the controller's desired state, moving towards the goal
        assert len(seen) > 5 and seen[-1].progress == pytest.approx(1.0)
        assert any(0.05 < fb.desired_positions[0] < 0.45 for fb in seen)
        # afterwards the robot is streamed again, holding where the goal ended (nothing jumps)
        await robot.clock.sleep(0.2)
        assert backend.sent > sent + 10
        assert served.latest_state().position[:2].tolist() == pytest.approx([0.5, 0.1], abs=0.02)


@pytest.mark.asyncio
async def test_cancel_and_estop_cancel_the_goal_and_a_remote_rejection_is_invalid_goal() -> None:
    async with _served() as (served, face, robot):
        motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(2.0, [-0.6])]))
        await _until(lambda: bool(face._goals) and served.latest_state().position[0] < -0.05)
        motion.cancel()
        result = await motion
        assert result.code is ResultCode.CANCELED, result
        goal = next(iter(face._goals.values()))
        assert goal.status == GOAL_CANCELED  # the served robot's goal was cancelled, not finished
        q = served.latest_state().position[0]
        assert -0.6 + 0.05 < q < -0.05
        await robot.clock.sleep(0.3)
        assert served.latest_state().position[0] == pytest.approx(q, abs=1e-3)  # at rest, holding
        assert (await robot.move_to({"joint1": 0.0}, duration=1.0)).ok  # the next goal runs

        # e-stop while a goal runs: the goal is cancelled on the controller, the motion ABORTED
        motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(2.0, [0.6])]))
        await _until(lambda: len(face._goals) == 3 and served.latest_state().position[0] > 0.05)
        await robot.estop(1)
        result = await motion
        assert result.code is ResultCode.ABORTED, result
        goal = list(face._goals.values())[-1]
        await _until(lambda: goal.result is not None)
        assert goal.status == GOAL_CANCELED
        q = served.latest_state().position[0]
        await asyncio.sleep(0.3)
        assert served.latest_state().position[0] == pytest.approx(q, abs=1e-3)  # stopped, short of 0.6
        assert q < 0.55
        await robot.reset()
        await robot.enable()

        # a trajectory beyond this client's own limits is refused here, whole, before anything is sent
        backend: Any = robot.backend
        sent = backend.goals_sent
        q0 = float(served.latest_state().position[0])
        ok = Trajectory(["joint1"], [TrajectoryPoint(1.0, [q0 + 0.1]), TrajectoryPoint(1.05, [q0 + 0.6])])
        with pytest.raises(agentsdk.LimitViolation, match=r"point|segment"):
            robot.follow(ok)
        assert backend.goals_sent == sent


@pytest.mark.asyncio
@pytest.mark.parametrize("category", [1, 2])
@pytest.mark.parametrize("latency", [0.0, 0.08])
async def test_an_estop_during_a_goal_never_moves_the_served_robot_back(category: int, latency: float) -> None:
    """Fault injection: the client sees joint_states ``latency`` s late (a slow link, a loaded host).

    The controller that runs the goal stops it from its own state; the client stops nothing on
    its own view, which lags by velocity x latency: once the goal has drained, the robot must not be
    pulled back to where the client thought it was. It comes to rest moving forward only, and stays.
    """
    async with _served() as (served, face, robot):
        backend: Any = robot.backend
        if latency:
            take, aloop = backend._take_state, asyncio.get_running_loop()
            backend._take_state = lambda msg: aloop.call_later(latency, take, msg)
        motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(2.0, [0.6])]))
        await _until(lambda: bool(face._goals) and served.latest_state().position[0] > 0.1)
        trace = [float(served.latest_state().position[0])]
        await robot.estop(category)
        assert (await motion).code is ResultCode.ABORTED
        goal = list(face._goals.values())[-1]
        await _until(lambda: goal.result is not None)
        assert goal.status == GOAL_CANCELED
        for _ in range(40):  # 0.4 s after the goal's result
            trace.append(float(served.latest_state().position[0]))
            await asyncio.sleep(0.01)
        steps = np.diff(trace)
        assert steps.min() > -1e-4, f"moved back {-steps.min():.4f} rad after the e-stop: {trace}"
        assert trace[-1] == pytest.approx(trace[-10], abs=1e-4)  # at rest, and staying there
        assert trace[-1] < 0.6 - 0.02  # stopped short of the goal
        state = robot.safety.state
        assert state.name == "ESTOP", state
        await robot.reset()
        await robot.enable()
        assert (await robot.move_to({"joint1": 0.0}, duration=1.0)).ok  # usable again


@pytest.mark.asyncio
async def test_remote_limits_tighter_than_the_clients_give_invalid_goal() -> None:
    """No ``robot=``: the client knows the URDF limits only; the served robot's robot.yaml is tighter."""
    did = _domain()
    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety=SAFETY) as served, \
            expose(served, "/arm1", domain_id=did), \
            agentsdk.connect("ros2", namespace="/arm1", domain_id=did, safety=SAFETY, realtime=True) as robot:
        amax_client = robot.joints[0].max_acceleration
        amax_served = served.joints[0].max_acceleration
        assert amax_served < amax_client
        result = await robot.move_to({"joint1": 0.4}, duration=None)  # planned at the client's own limits
        assert result.code is ResultCode.INVALID_GOAL, result
        assert served.latest_state().position[0] == pytest.approx(0.0, abs=1e-6)  # nothing moved
        assert (await robot.read()).position[0] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.asyncio
async def test_served_path_tolerance_violation_comes_back() -> None:
    """The served robot lags its setpoint (mock ``lag``): a tight path tolerance is violated there."""
    async with _served(lag=0.05) as (_served_robot, _face, robot):
        result = await robot.follow(Trajectory(["joint1"], [TrajectoryPoint(1.0, [0.5])]), Tolerances(path=1e-3))
        assert result.code is ResultCode.PATH_TOLERANCE_VIOLATED, result


@pytest.mark.asyncio
async def test_follow_goals_false_streams() -> None:
    did = _domain()
    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety=SAFETY) as served, \
            expose(served, "/arm1", domain_id=did) as face, \
            agentsdk.connect("ros2", robot="arm3", namespace="/arm1", domain_id=did, safety=SAFETY,
                             follow_goals=False) as robot:
        assert (await robot.move_to({"joint1": 0.3}, duration=1.0)).ok
        backend: Any = robot.backend
        assert backend.goals_sent == 0 and not face._goals


# ------------------------------------------------------------------ a ros2_control-like controller
class FakeController:
    """A JTC played on DDS: joint_states (its own joint order, an extra joint), the FollowJointTrajectory action.

    ``outcome``: ``(status, error_code)`` every goal ends with (after its duration), or None to reject goals.
    """

    def __init__(self, domain_id: int, namespace: str, controller: str, loop: asyncio.AbstractEventLoop,
                 outcome: tuple[int, int] | None = (GOAL_SUCCEEDED, 0), *, action: bool = True,
                 forward_joints: tuple[str, ...] = (), clock: bool = False) -> None:
        self.names = ["gripper", "joint3", "joint2", "joint1"]  # not the robot's order, one joint it does not know
        self.q = np.array([0.02, -0.1, 0.2, 0.1])
        self.outcome = outcome
        self.goals: list[FollowJointTrajectory_SendGoal_Request] = []
        self.cancels: list[CancelGoal_Request] = []
        self.streamed: list[JointTrajectory] = []
        self.results: dict[bytes, FollowJointTrajectory_GetResult_Response] = {}
        self._waiting: dict[bytes, list[Any]] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        #: a forward_command_controller's joints, in its order (its ``commands`` topic)
        self.forward_joints = forward_joints
        self.forwarded: list[Float64MultiArray] = []
        node = self.node = DdsNode(domain_id, namespace, loop)
        prefix = f"{controller}/follow_joint_trajectory/_action"
        if action:
            node.service(f"{prefix}/send_goal", FollowJointTrajectory_SendGoal_Request,
                         FollowJointTrajectory_SendGoal_Response, self._on_goal)
            node.service(f"{prefix}/get_result", FollowJointTrajectory_GetResult_Request,
                         FollowJointTrajectory_GetResult_Response, self._on_get_result)
            node.service(f"{prefix}/cancel_goal", CancelGoal_Request, CancelGoal_Response, self._on_cancel)
        if forward_joints:
            node.subscribe(f"{controller}/commands", Float64MultiArray, self._on_forward)
        else:
            node.subscribe(f"{controller}/joint_trajectory", JointTrajectory, self._on_trajectory)
        self._feedback = node.writer(f"{prefix}/feedback", FollowJointTrajectory_FeedbackMessage)
        self._js = node.writer("joint_states", JointState)
        self._clock = node.writer("clock", Clock) if clock else None
        self._sim_time = 0.0
        node.start()
        self._spawn(self._publish())

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def now(self) -> float:
        """The controller's time: its simulated time when it publishes a clock, else the wall clock."""
        return self._sim_time if self._clock is not None else asyncio.get_running_loop().time()

    async def _publish(self) -> None:
        while True:
            # a simulator publishes its clock (2 ms steps of simulated time) and stamps joint_states with it
            if self._clock is not None:
                self._sim_time += 0.002
            stamp = Time.from_seconds(self._sim_time) if self._clock is not None else Time()
            if self._clock is not None:
                self._clock.write(Clock(stamp))
            self._js.write(JointState(Header(stamp), self.names, self.q.tolist(), [0.0] * 4, [0.0] * 4))
            await asyncio.sleep(0.002 if self._clock is not None else 0.01)

    def _on_trajectory(self, msg: JointTrajectory) -> None:
        self.streamed.append(msg)
        if msg.points:
            for name, x in zip(msg.joint_names, msg.points[-1].positions, strict=True):
                self.q[self.names.index(name)] = x

    def _on_forward(self, msg: Float64MultiArray) -> None:
        self.forwarded.append(msg)
        for name, x in zip(self.forward_joints, msg.data, strict=True):
            self.q[self.names.index(name)] = x

    def _on_goal(self, _h: Any, req: FollowJointTrajectory_SendGoal_Request, reply: Any) -> None:
        self.goals.append(req)
        reply(FollowJointTrajectory_SendGoal_Response(self.outcome is not None, Time()))
        if self.outcome is not None:
            self._spawn(self._run(req))

    async def _run(self, req: FollowJointTrajectory_SendGoal_Request) -> None:
        traj = req.goal.trajectory
        uuid = bytes(req.goal_id.uuid)
        start = self.q.copy()
        last = traj.points[-1]
        end = last.time_from_start.sec + last.time_from_start.nanosec * 1e-9
        t0 = self.now()
        status, code = self.outcome or (GOAL_ABORTED, 0)
        while (s := (self.now() - t0) / end) < 1.0 and uuid not in self.results:
            for name, x in zip(traj.joint_names, last.positions, strict=True):  # linear, good enough
                i = self.names.index(name)
                self.q[i] = start[i] + (x - start[i]) * s
            desired = JointTrajectoryPoint(positions=[float(self.q[self.names.index(n)]) for n in traj.joint_names])
            self._feedback.write(FollowJointTrajectory_FeedbackMessage(UUID(uuid), FollowJointTrajectory_Feedback(
                Header(), list(traj.joint_names), desired, desired, JointTrajectoryPoint())))
            await asyncio.sleep(0.002 if self._clock is not None else 0.02)
            if status != GOAL_SUCCEEDED and s > 0.3:
                break  # a failure reported mid-way: the controller holds where it is
        if uuid in self.results:
            return  # cancelled: holding
        if status == GOAL_SUCCEEDED:
            for name, x in zip(traj.joint_names, last.positions, strict=True):
                self.q[self.names.index(name)] = x
        self._finish(uuid, FollowJointTrajectory_GetResult_Response(status, FollowJointTrajectory_Result(code, "")))

    def _finish(self, uuid: bytes, resp: FollowJointTrajectory_GetResult_Response) -> None:
        self.results[uuid] = resp
        for reply in self._waiting.pop(uuid, []):
            reply(resp)

    def _on_get_result(self, _h: Any, req: FollowJointTrajectory_GetResult_Request, reply: Any) -> None:
        uuid = bytes(req.goal_id.uuid)
        if uuid in self.results:
            reply(self.results[uuid])
        else:
            self._waiting.setdefault(uuid, []).append(reply)

    def _on_cancel(self, _h: Any, req: CancelGoal_Request, reply: Any) -> None:
        self.cancels.append(req)
        uuid = bytes(req.goal_info.goal_id.uuid)
        targets = [bytes(g.goal_id.uuid) for g in self.goals if not any(uuid) or bytes(g.goal_id.uuid) == uuid]
        for u in targets:
            if u not in self.results:  # JTC: a cancelled goal ends CANCELED with error_code SUCCESSFUL
                self._finish(u, FollowJointTrajectory_GetResult_Response(GOAL_CANCELED, FollowJointTrajectory_Result()))
        reply(CancelGoal_Response())

    async def aclose(self) -> None:
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self.node.close()


@contextlib.asynccontextmanager
async def _controller(outcome: tuple[int, int] | None = (GOAL_SUCCEEDED, 0), *, action: bool = True,
                      forward_joints: tuple[str, ...] = (), name: str = "scaled_arm_controller", **options: Any
                      ) -> AsyncIterator[tuple[FakeController, agentsdk.Robot]]:
    did = _domain()
    ns = "/lab/cell_2/arm"  # a nested namespace, another controller name
    fake = FakeController(did, ns, name, asyncio.get_running_loop(), outcome, action=action,
                          forward_joints=forward_joints)
    try:
        async with agentsdk.connect("ros2", robot="arm3", namespace=ns, controller=name, domain_id=did,
                                    realtime=True, safety=SAFETY, **options) as robot:
            yield fake, robot
    finally:
        await fake.aclose()


@pytest.mark.asyncio
async def test_a_controller_elsewhere_runs_the_goal_with_its_joint_order_and_extra_joints() -> None:
    async with _controller() as (fake, robot):
        backend: Any = robot.backend
        assert backend.interface == "joint_trajectory" and backend.goals_available
        # joint_states in another order with an extra joint: read by name
        assert (await robot.read()).position.tolist() == pytest.approx([0.1, 0.2, -0.1])
        streamed = len(fake.streamed)
        motion = robot.follow(Trajectory(["joint2"], [TrajectoryPoint(0.8, [0.5])]))
        feedback = [fb async for fb in motion.feedback(rate=25)]
        result = await motion
        assert result.ok, result
        assert len(fake.goals) == 1
        goal = fake.goals[0].goal.trajectory
        # every joint of the robot: the others held where they were
        assert list(goal.joint_names) == ["joint2", "joint1", "joint3"]
        assert list(goal.points[-1].positions) == pytest.approx([0.5, 0.1, -0.1])
        assert any(0.25 < fb.desired_positions[0] < 0.45 for fb in feedback)  # the controller's desired state
        # nothing streamed while the goal ran: no streamed setpoint on the way to the goal
        moving = [t for t in fake.streamed[streamed:] if 0.22 < t.points[-1].positions[1] < 0.48]
        assert not moving, moving[:2]
        await robot.clock.sleep(0.1)
        assert fake.q[fake.names.index("joint2")] == pytest.approx(0.5, abs=1e-6)  # streaming resumed in place
        assert fake.q[fake.names.index("gripper")] == 0.02  # the joint the robot does not know is left alone


@pytest.mark.parametrize(("status", "code", "expected"), [
    (GOAL_ABORTED, -4, ResultCode.PATH_TOLERANCE_VIOLATED),
    (GOAL_ABORTED, -5, ResultCode.GOAL_TOLERANCE_VIOLATED),
    (GOAL_ABORTED, -3, ResultCode.OLD_HEADER_TIMESTAMP),
    (GOAL_ABORTED, -2, ResultCode.INVALID_JOINTS),
    (GOAL_ABORTED, 0, ResultCode.ABORTED),
])
@pytest.mark.asyncio
async def test_controller_failures_end_the_motion_with_their_code_and_hold_where_it_stopped(
        status: int, code: int, expected: ResultCode) -> None:
    async with _controller((status, code)) as (fake, robot):
        result = await robot.follow(Trajectory(["joint1"], [TrajectoryPoint(1.0, [0.6])]))
        assert result.code is expected, result
        q = fake.q[fake.names.index("joint1")]
        assert 0.1 < q < 0.6  # the controller stopped mid-way
        await robot.clock.sleep(0.3)
        # the robot holds where the controller stopped it (the setpoint followed the measured state)
        assert fake.q[fake.names.index("joint1")] == pytest.approx(q, abs=1e-6)
        assert robot.safety.state.name == "OK"


@pytest.mark.asyncio
async def test_a_rejected_goal_is_invalid_goal_and_cancel_and_preemption_reach_the_controller() -> None:
    async with _controller(None) as (fake, robot):
        result = await robot.move_to({"joint1": 0.4}, duration=1.0)
        assert result.code is ResultCode.INVALID_GOAL, result
        assert fake.q[fake.names.index("joint1")] == pytest.approx(0.1)
    async with _controller() as (fake, robot):
        motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(2.0, [0.8])]))
        await _until(lambda: fake.q[fake.names.index("joint1")] > 0.2)
        motion.cancel()
        assert (await motion).code is ResultCode.CANCELED
        assert bytes(fake.cancels[-1].goal_info.goal_id.uuid) == bytes(fake.goals[-1].goal_id.uuid)
        # a direct command to a joint the goal holds preempts it (the controller runs one command source)
        motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(2.0, [0.0])]))
        await _until(lambda: len(fake.goals) == 2 and fake.q[fake.names.index("joint1")] < 0.25)
        await robot.command(agentsdk.JointCommand("position", {"joint3": -0.05}))
        result = await motion
        assert result.code is ResultCode.PREEMPTED, result
        assert "joint3" in result.message


@pytest.mark.asyncio
async def test_a_forward_command_controller_in_its_own_joint_order_is_streamed() -> None:
    """A forward_command_controller (no action): ``commands`` in ``command_joints`` order, follow() streamed."""
    order = ("joint3", "joint1", "joint2")
    async with _controller(action=False, forward_joints=order, name="forward_position_controller",
                           interface="forward_command", command_joints=order) as (fake, robot):
        backend: Any = robot.backend
        assert backend.interface == "forward_command" and not backend.goals_available
        result = await robot.move_to({"joint1": 0.4, "joint3": 0.2}, duration=1.0)
        assert result.ok, result
        await robot.clock.sleep(0.1)
        assert fake.q[[fake.names.index(n) for n in ("joint1", "joint2", "joint3")]].tolist() == pytest.approx(
            [0.4, 0.2, 0.2], abs=1e-6)
        assert len(fake.forwarded) > 100 and not fake.goals
        assert list(fake.forwarded[-1].data) == pytest.approx([0.2, 0.4, 0.2], abs=1e-6)  # its order


@pytest.mark.asyncio
async def test_ros_domain_id_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """No ``domain_id``: ``ROS_DOMAIN_ID`` picks the domain (ROS 2's rule), here a non-zero one."""
    did = _domain()
    monkeypatch.setenv("ROS_DOMAIN_ID", str(did))
    fake = FakeController(did, "/env", "joint_trajectory_controller", asyncio.get_running_loop())
    try:
        async with agentsdk.connect("ros2", robot="arm3", namespace="/env", realtime=True, safety=SAFETY) as robot:
            backend: Any = robot.backend
            assert backend.domain_id == did != 0
            assert (await robot.move_to({"joint2": 0.0}, duration=1.0)).ok
            assert len(fake.goals) == 1
    finally:
        await fake.aclose()


@pytest.mark.asyncio
async def test_a_simulator_with_a_clock_runs_the_goal_in_lockstep() -> None:
    """A simulator's JTC that publishes ``<ns>/clock``: the robot follows its time, the goal runs there."""
    did = _domain()
    fake = FakeController(did, "/sim", "joint_trajectory_controller", asyncio.get_running_loop(), clock=True)
    try:
        async with agentsdk.connect("ros2", robot="arm3", namespace="/sim", domain_id=did, safety=SAFETY) as robot:
            backend: Any = robot.backend
            assert not robot.realtime and backend.goals_available
            result = await robot.move_to({"joint1": -0.3}, duration=0.8)
            assert result.ok, result
            assert len(fake.goals) == 1
            assert fake.q[fake.names.index("joint1")] == pytest.approx(-0.3, abs=1e-6)
            await robot.clock.sleep(0.05)  # the simulator's next joint_states
            assert (await robot.read()).position[0] == pytest.approx(-0.3, abs=1e-6)
    finally:
        await fake.aclose()


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.asyncio
async def test_pick_place_runs_as_goals_against_agentsdk_serve_in_another_process(
        capsys: pytest.CaptureFixture[str]) -> None:
    """``agentsdk serve --backend mujoco`` (realtime, its own process): every move_to/follow of the behavior
    is one goal, each SUCCESSFUL, and the arm ends where the same behavior ends on a local MuJoCo."""
    import test_ros2_backend as rb

    from agentsdk.cli import load_behavior

    did = _domain()
    # a loaded 2-core test machine runs both processes: the served robot's stall watchdog gets the client's slack,
    # and joint_states go out at 500 Hz (at 100 Hz a late sample of the fast transfer can jump more than the
    # client's sensor plausibility margin allows between two of its ticks)
    async with rb._serve("--backend", "mujoco", "--robot", "arm3", "--namespace", "/cell", "--rate", "500", "-o",
                         "safety={stall_timeout: 5.0}", domain_id=did):
        local = await rb._final_joints("pick_place", "mujoco")
        capsys.readouterr()
        module = load_behavior("pick_place")
        # joint_states from another process on a loaded 2-core machine arrive bunched (gaps of tens of ms while the
        # arm moves at up to 2.5 rad/s): the sensor plausibility check gets a 0.2 rad floor here
        async with agentsdk.connect("ros2", robot="arm3", namespace="/cell", domain_id=did, realtime=True,
                                    safety={**SAFETY, "sensor_jump_floor": 0.2}) as robot:
            backend: Any = robot.backend
            await module.main(robot)  # raises if a step does not end SUCCESSFUL
            await robot.clock.sleep(0.3)
            remote = np.array((await robot.read()).position)
            steps = capsys.readouterr().out.count("SUCCESSFUL")
            assert steps >= 5 and backend.goals_sent == steps, (steps, backend.goals_sent)
    # the served arm ends at the behavior's last goal, within its goal tolerance (0.02 rad)
    assert np.abs(remote - local).max() <= 0.02, (local, remote)


@pytest.mark.asyncio
async def test_joint_states_split_over_messages_best_effort_without_velocities() -> None:
    """A robot whose joint_states come in parts (one message per hardware group), best effort (SensorDataQoS),
    positions only; a namespace written without its leading slash. Read by name; the JTC topic drives it."""
    from agentsdk.ros2.dds import QOS_SENSOR

    did = _domain()
    loop = asyncio.get_running_loop()
    q = {"joint1": 0.1, "joint2": -0.2, "joint3": 0.3}
    node = DdsNode(did, "/plant/arm", loop)

    def on_trajectory(msg: JointTrajectory) -> None:
        if msg.points:
            q.update(zip(msg.joint_names, msg.points[-1].positions, strict=True))

    node.subscribe("joint_trajectory_controller/joint_trajectory", JointTrajectory, on_trajectory)
    js = node.writer("joint_states", JointState, QOS_SENSOR)
    node.start()

    async def publish() -> None:
        while True:
            js.write(JointState(Header(), ["joint1"], [q["joint1"]]))
            js.write(JointState(Header(), ["joint3", "joint2"], [q["joint3"], q["joint2"]]))
            await asyncio.sleep(0.01)

    task = asyncio.create_task(publish())
    try:
        # the plant above is an asyncio task on this loaded event loop: its 100 Hz samples can come tens of ms apart
        async with agentsdk.connect("ros2", robot="arm3", namespace="plant/arm", domain_id=did, realtime=True,
                                    safety={**SAFETY, "sensor_jump_floor": 0.2}) as robot:
            backend: Any = robot.backend
            assert backend.namespace == "/plant/arm" and not backend.goals_available
            assert (await robot.read()).position.tolist() == pytest.approx([0.1, -0.2, 0.3])
            assert (await robot.move_to({"joint2": 0.25}, duration=1.0)).ok
            await robot.clock.sleep(0.1)
            assert q["joint2"] == pytest.approx(0.25, abs=1e-6)
            assert (await robot.read()).position.tolist() == pytest.approx([0.1, 0.25, 0.3], abs=1e-6)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        node.close()
