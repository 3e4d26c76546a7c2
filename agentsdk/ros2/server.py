"""The ROS 2 face of a robot: :func:`expose` makes it a ROS 2 node on the DDS graph.

What a served robot offers, under its namespace (``/arm1/joint_states`` ...):

* ``joint_states`` (``sensor_msgs/JointState``): reliable, keep last 10 (best effort with
  ``sensor_qos=True``);
* ``tf`` (``tf2_msgs/TFMessage``, links on moving joints): reliable, keep last 10;
* ``tf_static`` (links on fixed joints) and ``robot_description`` (``std_msgs/String``, the URDF):
  reliable, transient local, so a late subscriber gets them;
* ``clock`` (``rosgraph_msgs/Clock``, lockstep robots only): best effort;
* ``diagnostics`` (``diagnostic_msgs/DiagnosticArray``): safety state and cause, ticks, missed
  deadlines, motor statistics where the backend has them;
* services ``estop``, ``reset``, ``enable`` (``std_srvs/Trigger``);
* ``joint_trajectory_controller/joint_trajectory`` (``trajectory_msgs/JointTrajectory``, in),
  ``joint_trajectory_controller/controller_state`` (``control_msgs/JointTrajectoryControllerState``)
  and the action ``joint_trajectory_controller/follow_joint_trajectory``
  (``control_msgs/action/FollowJointTrajectory``: goal, cancel, feedback, result, status).

Every trajectory (topic or action goal) goes through :meth:`Robot.follow`: the same
validation, limits, safety layer, preemption and cancel-decelerates as in a behavior.

``joint_states`` leave the control tick without work on it: an OBSERVE hook copies the state
into a preallocated ring every ``control_rate / rate`` ticks and wakes a publisher thread
(``eventfd``), which encodes and writes the newest sample. When the robot runs faster than
the wall clock (lockstep), the publisher writes at most ``rate`` samples per wall second (the
newest each time, like a keep-last history). Stamps: robot time for lockstep robots (and
``/clock`` carries it, for ``use_sim_time``), wall time (epoch) for realtime robots.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import math
import os
import re
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import AgentSDKError, CommandRejected, InvalidValueError, SafetyError
from ..loop import HookHandle, Phase
from ..motion import Motion, MotionResult, ResultCode, Tolerances
from ..safety import SafetyState
from ._fast import ClockEncoder, FixedLayout, JointStateEncoder, write_raw
from .convert import (
    GOAL_ACCEPTED,
    GOAL_CANCELING,
    GOAL_EXECUTING,
    GOAL_UNKNOWN,
    feedback_points,
    goal_status,
    point_msg,
    result_msg,
    tolerances_from_goal,
    trajectory_from_msg,
)
from .dds import QOS_DEFAULT, QOS_LATCHED, QOS_SENSOR, DdsNode, normalize_namespace, resolve_domain_id
from .lease import Deadman
from .msgs import (
    UUID,
    CancelGoal_Request,
    CancelGoal_Response,
    Clock,
    DiagnosticArray,
    DiagnosticStatus,
    FollowJointTrajectory_Feedback,
    FollowJointTrajectory_FeedbackMessage,
    FollowJointTrajectory_GetResult_Request,
    FollowJointTrajectory_GetResult_Response,
    FollowJointTrajectory_Result,
    FollowJointTrajectory_SendGoal_Request,
    FollowJointTrajectory_SendGoal_Response,
    GoalInfo,
    GoalStatus,
    GoalStatusArray,
    Header,
    JointState,
    JointTrajectory,
    JointTrajectoryControllerState,
    KeyValue,
    Quaternion,
    RequestHeader,
    String,
    TFMessage,
    Time,
    Transform,
    TransformStamped,
    Trigger_Request,
    Trigger_Response,
    Vector3,
)
from .stream import CommandStream

if TYPE_CHECKING:
    from ..pose import Pose
    from ..robot import Robot

__all__ = ["JTC", "RosFace", "expose"]

log = logging.getLogger(__name__)

#: the JointTrajectoryController's name (its topics, state and action live under it, as in ros2_control)
JTC = "joint_trajectory_controller"
_RING = 64
#: how many finished goals' results stay available to ``get_result``
_KEEP_RESULTS = 100
_CANCEL_NONE, _CANCEL_REJECTED, _CANCEL_UNKNOWN_GOAL, _CANCEL_TERMINATED = 0, 1, 2, 3


class _StatePublisher:
    """The joint_states (and clock) publisher thread, fed by an OBSERVE tick hook."""

    def __init__(self, robot: Robot, writer: Any, clock_writer: Any | None, rate: float,
                 stamp_offset: float) -> None:
        n = len(robot.joint_names)
        self._ticks_per_sample = max(1, round(1.0 / (rate * robot.control_period)))
        self._countdown = 1
        self._ring = np.zeros((_RING, 1 + 3 * n))
        self._stamps = self._ring[:, 0]
        self._blocks = [self._ring[i, 1:].reshape(3, n) for i in range(_RING)]
        self._seq = 0
        self._writer = writer
        self._clock_writer = clock_writer
        self._encoder = JointStateEncoder(robot.joint_names)
        self._clock = ClockEncoder()
        self._offset = stamp_offset
        self._min_interval = 1.0 / rate
        self._waiting = False
        self._stop = threading.Event()
        self._efd = os.eventfd(0, os.EFD_CLOEXEC)
        self._closed = False
        self.published = 0
        self._thread = threading.Thread(target=self._run, name="agentsdk-ros2-joint-states", daemon=True)
        self._thread.start()
        self._hook: HookHandle = robot.add_tick_hook(Phase.OBSERVE, self._observe, order=-100)

    def _observe(self, t: float, state: Any, _setpoint: Any) -> None:
        # the tick path: a countdown, one row copy, and an eventfd write only when the publisher sleeps
        self._countdown -= 1
        if self._countdown:
            return
        self._countdown = self._ticks_per_sample
        i = self._seq % _RING
        self._stamps[i] = t
        self._blocks[i][...] = state.block
        self._seq += 1
        if self._waiting:
            self._waiting = False
            os.eventfd_write(self._efd, 1)

    def _run(self) -> None:
        last = 0
        next_time = 0.0
        try:
            while not self._closed:
                seq = self._seq
                if seq == last:
                    self._waiting = True
                    if self._seq == last:  # checked again after announcing: no wake-up is lost
                        os.eventfd_read(self._efd)
                    self._waiting = False
                    continue
                wait = next_time - time.monotonic()
                if wait > 0:
                    # the robot runs faster than ``rate`` in wall time (lockstep): publish the newest
                    # sample at most ``rate`` times per wall second (in this thread, never the loop)
                    self._stop.wait(wait)
                    seq = self._seq
                last = seq
                i = (seq - 1) % _RING
                stamp = float(self._stamps[i]) + self._offset
                q, v, e = self._blocks[i]
                data = self._encoder.encode(stamp, q, v, e)
                if self._seq - seq >= _RING - 1:
                    continue  # overwritten while copying (the robot ran far ahead): take the next one
                write_raw(self._writer, data)
                if self._clock_writer is not None:
                    write_raw(self._clock_writer, self._clock.encode(stamp))
                self.published += 1
                next_time = time.monotonic() + self._min_interval
        except Exception:
            if not self._closed:
                log.exception("ROS 2 joint_states publisher stopped")

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._hook.remove()
        self._stop.set()
        os.eventfd_write(self._efd, 1)
        self._thread.join(timeout=5.0)  # wakes at once: both its waits were just released
        os.close(self._efd)


@dataclass
class _Goal:
    uuid: bytes
    stamp: Time
    motion: Motion | None
    status: int
    result: FollowJointTrajectory_Result | None = None
    waiting: list[Callable[[FollowJointTrajectory_GetResult_Response], None]] = field(default_factory=list)


class RosFace:
    """A robot served on the ROS 2 graph (what :func:`expose` returns); an async context manager.

    ``async with expose(robot, namespace="/arm1"):`` serves until the block ends;
    :meth:`aclose` stops serving (idempotent) and leaves the robot as it is (motions started
    by ROS clients keep their own semantics: closing the robot stops them).
    """

    def __init__(self, robot: Robot, *, namespace: str = "", domain_id: int | None = None,
                 rate: float | None = None, tf_rate: float = 50.0, sensor_qos: bool = False,
                 feedback_rate: float = 20.0, tolerances: Tolerances | None = None,
                 lease: float | None = 1.0, lease_category: int = 1, require_lease: bool = False,
                 read_only: bool = False, dds_config: str | None = None) -> None:
        self.robot = robot
        self.namespace = normalize_namespace(namespace)
        self.domain_id = resolve_domain_id(domain_id)
        control_rate = 1.0 / robot.control_period
        if rate is None:
            rate = min(control_rate, 100.0)
        for what, value in (("rate", rate), ("tf_rate", tf_rate), ("feedback_rate", feedback_rate)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InvalidValueError(f"{what} must be a positive number of Hz, got {value!r}")
        if rate > control_rate * (1 + 1e-9):
            raise InvalidValueError(f"rate {rate} Hz is above the control rate ({control_rate:g} Hz)")
        self.rate = float(rate)
        self.tf_rate = float(tf_rate)
        self.feedback_rate = float(feedback_rate)
        self.sensor_qos = sensor_qos
        self.tolerances = tolerances or Tolerances()
        #: added to robot time to make ROS stamps: 0 in lockstep (sim time), epoch offset in realtime
        self.stamp_offset = 0.0 if robot.clock.lockstep else time.time() - robot.clock.now()
        self._node: DdsNode | None = None
        self._publisher: _StatePublisher | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._goals: OrderedDict[bytes, _Goal] = OrderedDict()
        #: the ``ros2`` backend's sequenced command stream (:mod:`agentsdk.ros2.stream`)
        self.stream = CommandStream(self)
        self._topic_motions: set[Motion] = set()
        self._closed = False
        #: trajectories from the topic that were rejected (the topic has no reply: counted and logged)
        self.rejected_trajectories = 0
        #: trajectories from the topic that were started (each DDS sample once: RTPS sequence numbers)
        self.accepted_trajectories = 0
        self.last_rejection: str = ""
        self._static_links: set[str] = set()
        self._transition_handle: HookHandle | None = None
        #: the ROS node name ``ros2 node list`` shows (under :attr:`namespace`)
        self.node_name = "agentsdk_" + (re.sub(r"\W", "_", robot.name) or "robot")
        #: a read-only face (a viewer's, :mod:`agentsdk.ros2.security`): state out, no command
        #: topic, no services, no action server
        self.read_only = bool(read_only)
        #: the Cyclone DDS configuration of this face's domain (None: ``CYCLONEDDS_URI``, else loopback)
        self.dds_config = dds_config
        #: the dead-man between hosts (:mod:`agentsdk.ros2.lease`); None: ``lease=None``, no dead-man
        self.deadman: Deadman | None = None
        if lease is not None and not self.read_only:
            self.deadman = Deadman(robot, lease, lease_category, require_lease)
        elif require_lease:
            raise InvalidValueError("require_lease needs a lease (seconds), got lease=None")

    # ------------------------------------------------------------------ lifecycle
    async def __aenter__(self) -> RosFace:
        await self.start()
        return self

    async def __aexit__(self, et: type[BaseException] | None, e: BaseException | None,
                        tb: TracebackType | None) -> None:
        await self.aclose()

    async def start(self) -> None:
        """Create the participant, its topics and services, and start publishing."""
        robot = self.robot
        loop = asyncio.get_running_loop()
        # creating DDS entities compiles each type's serialiser and XTypes data (slow): off the loop
        try:
            self._node = await _in_thread(lambda: self._build(loop))
        except asyncio.CancelledError:
            self._closed = True
            raise
        try:
            self._node.start()
            urdf = robot.description.urdf_xml
            if urdf:
                self._description.write(String(urdf))
            self._publish_static()
            self._publish_status()
            self._publisher = _StatePublisher(robot, self._js, self._clock_w, self.rate, self.stamp_offset)
            from ..statemachine import StateMachine

            self._transition_handle = StateMachine.add_transition_listener(self._on_transition)
            self._spawn(self._periodic())
            if self.deadman is not None:
                self._spawn(self.deadman.watch())
            self.stream.start(self._spawn)
        except BaseException:
            await self.aclose()
            raise

    def _build(self, loop: asyncio.AbstractEventLoop) -> DdsNode:
        """The participant with every writer, reader and service (runs in a worker thread)."""
        _warm_up()
        self._prepare_tf()
        self._prepare_controller_state()
        node = DdsNode(self.domain_id, self.namespace, loop, self.dds_config)
        try:
            self._create_entities(node)
        except BaseException:
            node.close()
            raise
        return node

    def _create_entities(self, node: DdsNode) -> None:
        robot = self.robot
        state_qos = QOS_SENSOR if self.sensor_qos else QOS_DEFAULT
        self._js = node.writer("joint_states", JointState, state_qos)
        # /clock without a namespace; a namespaced robot publishes <ns>/clock (remap clock:=<ns>/clock)
        self._clock_w = node.writer("clock", Clock, QOS_SENSOR) if robot.clock.lockstep else None
        self._tf = node.writer("tf", TFMessage, QOS_DEFAULT)
        self._tf_static = node.writer("tf_static", TFMessage, QOS_LATCHED)
        self._description = node.writer("robot_description", String, QOS_LATCHED)
        self._diagnostics = node.writer("diagnostics", DiagnosticArray, QOS_DEFAULT)
        # the robot's state machines, live: one JSON object per history record (std_msgs/String)
        self._transitions = node.writer("behavior/transitions", String, QOS_DEFAULT)
        self._controller_state = node.writer(f"{JTC}/controller_state", JointTrajectoryControllerState, QOS_DEFAULT)
        action = f"{JTC}/follow_joint_trajectory/_action"
        self._feedback = node.writer(f"{action}/feedback", FollowJointTrajectory_FeedbackMessage, QOS_DEFAULT)
        self._status = node.writer(f"{action}/status", GoalStatusArray, QOS_LATCHED)
        if not self.read_only:
            self._create_command_entities(node, action)
        node.announce(self.node_name)

    def _create_command_entities(self, node: DdsNode, action: str) -> None:
        """What commands the robot: the JTC topic, the services, the action server, the dead-man."""
        robot = self.robot
        node.subscribe(f"{JTC}/joint_trajectory", JointTrajectory, self._on_trajectory)
        node.service("estop", Trigger_Request, Trigger_Response, self._trigger(self._estop))
        node.service("reset", Trigger_Request, Trigger_Response, self._trigger(robot.reset))
        node.service("enable", Trigger_Request, Trigger_Response, self._trigger(robot.enable))
        node.service(f"{action}/send_goal", FollowJointTrajectory_SendGoal_Request,
                     FollowJointTrajectory_SendGoal_Response, self._on_send_goal)
        node.service(f"{action}/get_result", FollowJointTrajectory_GetResult_Request,
                     FollowJointTrajectory_GetResult_Response, self._on_get_result)
        node.service(f"{action}/cancel_goal", CancelGoal_Request, CancelGoal_Response, self._on_cancel)
        if self.deadman is not None:
            self.deadman.attach(node)
        self.stream.create(node)

    async def aclose(self) -> None:
        """Stop serving: cancel the face's tasks, stop the publisher, delete the participant (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._transition_handle is not None:
            self._transition_handle.remove()
        try:
            for task in list(self._tasks):
                task.cancel()
            if self._tasks:
                await asyncio.gather(*self._tasks, return_exceptions=True)
        finally:
            try:
                if self._publisher is not None:
                    self._publisher.close()
            finally:
                if self._node is not None:
                    self._node.close()

    def _spawn(self, coro: Any) -> asyncio.Task[Any]:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("ROS 2 face task failed", exc_info=task.exception())

    @property
    def published(self) -> int:
        """joint_states samples written so far."""
        return 0 if self._publisher is None else self._publisher.published

    def stamp(self, t: float) -> Time:
        """The ROS stamp of robot time ``t``."""
        return Time.from_seconds(t + self.stamp_offset)

    def robot_time(self, stamp: Time) -> float:
        """Robot time of a ROS stamp."""
        return stamp.sec + stamp.nanosec * 1e-9 - self.stamp_offset

    # ------------------------------------------------------------------ tf, state, diagnostics
    def _publish_static(self) -> None:
        if not self._static_links:
            return
        poses = self.robot.kinematics.link_poses()  # fixed joints: the same at every configuration
        stamp = self.stamp(self.robot.clock.now())
        msgs = [_transform(stamp, parent, child, pose) for parent, child, pose in poses.transforms()
                if child in self._static_links]
        self._tf_static.write(TFMessage(msgs))

    def _publish_tf(self) -> None:
        if self._tf_layout is None:
            return
        state = self.robot.latest_state()
        values = self.robot.kinematics.relative_transforms(self._tf_pairs, state.position)
        write_raw(self._tf, self._tf_layout.encode(values.ravel(), state.stamp + self.stamp_offset))

    def _prepare_tf(self) -> None:
        """The moving transforms (parent, child) and their fixed-layout encoder (None: no kinematics)."""
        self._tf_pairs: list[tuple[str, str]] = []
        self._tf_layout: FixedLayout | None = None
        try:
            kin = self.robot.kinematics
        except AgentSDKError as exc:
            log.warning("no tf for %s: %s", self.robot.name, exc)
            return
        self._static_links = _static_links(self.robot, kin)
        self._tf_pairs = [(parent, child) for child, parent in kin.parents.items()
                          if child not in self._static_links]
        if not self._tf_pairs:
            return
        pairs = self._tf_pairs

        def build(values: np.ndarray, stamps: list[Time]) -> TFMessage:
            return TFMessage([
                TransformStamped(Header(stamps[0], parent), child, Transform(
                    Vector3(*map(float, values[7 * k:7 * k + 3])),
                    Quaternion(*map(float, values[7 * k + 3:7 * k + 7]))))
                for k, (parent, child) in enumerate(pairs)])

        self._tf_layout = FixedLayout(build, 7 * len(pairs), 1)

    def _prepare_controller_state(self) -> None:
        names = list(self.robot.joint_names)
        n = len(names)

        def build(values: np.ndarray, stamps: list[Time]) -> JointTrajectoryControllerState:
            pts = [point_msg(values[2 * k * n:(2 * k + 1) * n], values[(2 * k + 1) * n:(2 * k + 2) * n])
                   for k in range(6)]
            return JointTrajectoryControllerState(Header(stamps[0]), names, reference=pts[0], feedback=pts[1],
                                                  error=pts[2], output=pts[3], desired=pts[4], actual=pts[5])

        self._cs_values = np.zeros(12 * n)
        self._cs_layout = FixedLayout(build, 12 * n, 1)

    def _publish_controller_state(self) -> None:
        robot = self.robot
        state = robot.latest_state()
        q_des, v_des, _ = robot.desired_state()
        n = len(q_des)
        v = self._cs_values.reshape(12, n)
        # reference, feedback, error, output, desired (= reference), actual (= feedback): positions, velocities
        v[0], v[1] = q_des, v_des
        v[2], v[3] = state.position, state.velocity
        v[4], v[5] = q_des - state.position, v_des - state.velocity
        v[6], v[7] = q_des, v_des
        v[8], v[9] = q_des, v_des
        v[10], v[11] = state.position, state.velocity
        write_raw(self._controller_state, self._cs_layout.encode(self._cs_values, state.stamp + self.stamp_offset))

    def _publish_diagnostics(self) -> None:
        robot = self.robot
        safety = robot.safety
        st = safety.state
        level = 0 if st in (SafetyState.OK, SafetyState.HOLD) else 2 if st is SafetyState.FAULT else 1
        cause = safety.cause
        values = [
            KeyValue("safety_state", st.name),
            KeyValue("cause", "" if cause is None else f"{type(cause).__name__}: {cause}"),
            KeyValue("backend", robot.backend.name),
            KeyValue("time_model", "realtime" if robot.realtime else "lockstep"),
            KeyValue("control_rate_hz", f"{1.0 / robot.control_period:g}"),
            KeyValue("ticks", str(robot.ticks)),
            KeyValue("missed_deadlines", str(robot.missed_deadlines)),
            KeyValue("torque_enabled", str(robot.torque_enabled)),
            KeyValue("busy", str(robot.busy)),
            KeyValue("joint_states_published", str(self.published)),
            KeyValue("trajectories_rejected", str(self.rejected_trajectories)),
            KeyValue("trajectories_accepted", str(self.accepted_trajectories)),
            KeyValue("deadman", "off" if self.deadman is None else
                     f"lease {self.deadman.lease:g} s, category {self.deadman.category}, "
                     f"trips {self.deadman.trips}{': ' + self.deadman.last_trip if self.deadman.last_trip else ''}"),
            KeyValue("deadman_tripped_at", "" if self.deadman is None or not self.deadman.trips
                     else f"{self.deadman.tripped_at:.6f}"),
        ]
        message = st.name if cause is None else f"{st.name}: {cause}"
        statuses = [DiagnosticStatus(level=level, name=f"agentsdk: {robot.name}{self.namespace}",
                                     message=message, hardware_id=robot.backend.name, values=values)]
        # per-motor statistics where the backend keeps them (the CAN backend: commands, replies, missed, late...)
        stats = getattr(robot.backend, "stats", None)
        if isinstance(stats, list | tuple):
            for item in stats:
                if not dataclasses.is_dataclass(item) or isinstance(item, type):
                    continue
                fields = dataclasses.asdict(item)
                trouble = bool(fields.get("consecutive_missed") or fields.get("last_error"))
                who = fields.get("joint", "motor")
                statuses.append(DiagnosticStatus(
                    level=1 if trouble else 0, name=f"agentsdk: {robot.name}{self.namespace} motor {who}",
                    message=str(fields.get("last_error") or ("missing replies" if trouble else "OK")),
                    hardware_id=str(fields.get("motor_id", robot.backend.name)),
                    values=[KeyValue(k, str(v)) for k, v in fields.items()]))
        self._diagnostics.write(DiagnosticArray(Header(self.stamp(robot.clock.now())), statuses))

    def _on_transition(self, machine: Any, rec: Any) -> None:
        """Publish a state machine's history record (this robot's machines only) on ``behavior/transitions``."""
        if getattr(machine, "robot", None) is not self.robot or self._closed:
            return
        stamp = self.stamp(rec.time)
        self._transitions.write(String(json.dumps({
            "stamp": {"sec": stamp.sec, "nanosec": stamp.nanosec}, "machine": rec.machine, "source": rec.source,
            "target": rec.target, "event": rec.event, "note": rec.note,
            "duration": getattr(rec, "duration", None), "configuration": getattr(rec, "configuration", ""),
        })))

    async def _periodic(self) -> None:
        """tf, controller_state at ``tf_rate`` and diagnostics at 1 Hz, in wall time."""
        period = 1.0 / self.tf_rate
        next_diag = 0.0
        while True:
            if not self.robot.closed:
                self._publish_tf()
                self._publish_controller_state()
                now = time.monotonic()
                if now >= next_diag:
                    self._publish_diagnostics()
                    next_diag = now + 1.0
            await asyncio.sleep(period)

    # ------------------------------------------------------------------ services
    async def _estop(self) -> None:
        await self.robot.estop()

    def _trigger(self, action: Callable[[], Any]) -> Callable[[RequestHeader, Any, Callable[[Any], None]], None]:
        async def run(reply: Callable[[Any], None]) -> None:
            try:
                await action()
            except AgentSDKError as exc:
                reply(Trigger_Response(False, f"{type(exc).__name__}: {exc}"))
            else:
                reply(Trigger_Response(True, self.robot.safety.state.name))

        def handler(_header: RequestHeader, _req: Any, reply: Callable[[Any], None]) -> None:
            self._spawn(run(reply))

        return handler

    # ------------------------------------------------------------------ JTC topic
    def _start(self, msg: JointTrajectory, tolerances: Tolerances) -> Motion:
        traj = trajectory_from_msg(msg)
        stamp = msg.header.stamp
        start = None if stamp.sec == 0 and stamp.nanosec == 0 else self.robot_time(stamp)
        if self.deadman is not None:
            self.deadman.admit()
        motion = self.robot.follow(traj, tolerances, start_time=start)
        if self.deadman is not None:
            self.deadman.accepted()
        return motion

    def _on_trajectory(self, msg: JointTrajectory) -> None:
        if self.robot.closed:
            return
        if not msg.points:  # JTC's topic interface: an empty trajectory holds the current position
            self._cancel_all_motions()
            return
        try:
            motion = self._start(msg, self.tolerances)
        except (CommandRejected, SafetyError) as exc:
            self.rejected_trajectories += 1
            self.last_rejection = f"{type(exc).__name__}: {exc}"
            log.warning("rejected trajectory on %s/%s/joint_trajectory: %s", self.namespace, JTC, self.last_rejection)
            return
        self.accepted_trajectories += 1
        self._topic_motions.add(motion)
        self._spawn(self._await_quietly(motion))

    async def _await_quietly(self, motion: Motion) -> None:
        try:
            result = await motion
        finally:
            self._topic_motions.discard(motion)
        log.debug("topic trajectory ended: %s", result)

    def _cancel_all_motions(self) -> None:
        """Hold: cancel every running goal and topic trajectory (each decelerates, then holds)."""
        for motion in list(self._topic_motions):
            motion.cancel()
        for goal in self._goals.values():
            if goal.result is None and goal.motion is not None:
                goal.motion.cancel()

    # ------------------------------------------------------------------ action server
    def _publish_status(self) -> None:
        self._status.write(GoalStatusArray([
            GoalStatus(GoalInfo(UUID(g.uuid), g.stamp), g.status) for g in self._goals.values()
        ]))

    def _remember(self, goal: _Goal) -> None:
        self._goals[goal.uuid] = goal
        while len(self._goals) > _KEEP_RESULTS:
            old = next(iter(self._goals.values()))
            if old.result is None:
                break
            self._goals.popitem(last=False)

    def _on_send_goal(self, _header: RequestHeader, req: FollowJointTrajectory_SendGoal_Request,
                      reply: Callable[[Any], None]) -> None:
        uuid = bytes(req.goal_id.uuid)
        stamp = self.stamp(self.robot.clock.now())
        if uuid in self._goals or self.robot.closed:
            reply(FollowJointTrajectory_SendGoal_Response(False, stamp))
            return
        try:
            tolerances = tolerances_from_goal(req.goal, self.tolerances)
            motion = self._start(req.goal.trajectory, tolerances)
        except (CommandRejected, SafetyError) as exc:
            log.warning("rejected FollowJointTrajectory goal: %s: %s", type(exc).__name__, exc)
            reply(FollowJointTrajectory_SendGoal_Response(False, stamp))
            return
        goal = _Goal(uuid, stamp, motion, GOAL_ACCEPTED)
        self._remember(goal)
        reply(FollowJointTrajectory_SendGoal_Response(True, stamp))
        goal.status = GOAL_EXECUTING
        self._publish_status()
        self._spawn(self._execute(goal, motion, list(req.goal.trajectory.joint_names)))

    async def _execute(self, goal: _Goal, motion: Motion, names: list[str]) -> None:
        try:
            async for fb in motion.feedback(rate=self.feedback_rate):
                desired, actual, error = feedback_points(fb)
                self._feedback.write(FollowJointTrajectory_FeedbackMessage(
                    UUID(goal.uuid),
                    FollowJointTrajectory_Feedback(Header(self.stamp(fb.time)), list(fb.joint_names),
                                                   desired, actual, error)))
            result: MotionResult = await motion
        except asyncio.CancelledError:
            motion.cancel()
            raise
        except Exception as exc:  # the robot closed or faulted under the goal: the client still gets a result
            if not isinstance(exc, AgentSDKError):
                log.exception("FollowJointTrajectory goal failed")
            result = MotionResult(ResultCode.ABORTED, {}, f"{type(exc).__name__}: {exc}", self.robot.clock.now())
        self._finish(goal, result)

    def _finish(self, goal: _Goal, result: MotionResult) -> None:
        goal.result = result_msg(result)
        goal.status = goal_status(result.code)
        self._publish_status()
        for reply in goal.waiting:
            reply(FollowJointTrajectory_GetResult_Response(goal.status, goal.result))
        goal.waiting.clear()

    def _on_get_result(self, _header: RequestHeader, req: FollowJointTrajectory_GetResult_Request,
                       reply: Callable[[Any], None]) -> None:
        goal = self._goals.get(bytes(req.goal_id.uuid))
        if goal is None:
            reply(FollowJointTrajectory_GetResult_Response(GOAL_UNKNOWN, FollowJointTrajectory_Result()))
        elif goal.result is not None:
            reply(FollowJointTrajectory_GetResult_Response(goal.status, goal.result))
        else:
            goal.waiting.append(reply)

    def _on_cancel(self, _header: RequestHeader, req: CancelGoal_Request, reply: Callable[[Any], None]) -> None:
        info = req.goal_info
        uuid = bytes(info.goal_id.uuid)
        t = info.stamp.sec + info.stamp.nanosec * 1e-9
        running = [g for g in self._goals.values() if g.result is None]
        if any(uuid):
            targets = [g for g in running if g.uuid == uuid]
            if not targets:
                known = uuid in self._goals
                reply(CancelGoal_Response(_CANCEL_TERMINATED if known else _CANCEL_UNKNOWN_GOAL, []))
                return
        else:  # zero id: every goal accepted at or before the stamp (all of them for a zero stamp)
            targets = [g for g in running if t == 0 or g.stamp.sec + g.stamp.nanosec * 1e-9 <= t]
        for g in targets:
            g.status = GOAL_CANCELING
            if g.motion is not None:
                g.motion.cancel()
        if targets:
            self._publish_status()
        reply(CancelGoal_Response(_CANCEL_NONE if targets else _CANCEL_REJECTED,
                                  [GoalInfo(UUID(g.uuid), g.stamp) for g in targets]))


async def _in_thread(fn: Callable[[], Any]) -> Any:
    """Run ``fn`` in a new thread that ends with it (no pooled thread outlives the call).

    Cancelling the caller waits for ``fn`` to finish first, so nothing it creates is orphaned
    (``cleanup`` style: the result is returned through the future even then).
    """
    loop = asyncio.get_running_loop()
    fut: asyncio.Future[Any] = loop.create_future()

    def settle(value: Any, exc: BaseException | None) -> None:
        if not fut.done():
            if exc is not None:
                fut.set_exception(exc)
            else:
                fut.set_result(value)

    def run() -> None:
        try:
            value = fn()
        except BaseException as exc:  # handed to the awaiting task
            loop.call_soon_threadsafe(settle, None, exc)
        else:
            loop.call_soon_threadsafe(settle, value, None)

    thread = threading.Thread(target=run, name="agentsdk-ros2-setup", daemon=True)
    thread.start()
    try:
        return await asyncio.shield(fut)
    finally:
        while thread.is_alive():  # noqa: ASYNC110 -- it ends right after handing over its result
            await asyncio.sleep(0.001)


def _warm_up() -> None:
    """Compile every message type's serialiser (the first use is slow): call off the event loop."""
    t: type[Any]
    for t in (JointState, Clock, TFMessage, String, DiagnosticArray, JointTrajectoryControllerState,
              FollowJointTrajectory_FeedbackMessage, GoalStatusArray, JointTrajectory):
        t.deserialize(t().serialize())
    from .dds import service_wire_type, wrap

    for t in (Trigger_Request, Trigger_Response, FollowJointTrajectory_SendGoal_Request,
              FollowJointTrajectory_SendGoal_Response, FollowJointTrajectory_GetResult_Request,
              FollowJointTrajectory_GetResult_Response, CancelGoal_Request, CancelGoal_Response):
        w = service_wire_type(t)
        w.deserialize(wrap(t, RequestHeader(), t()).serialize())


def _transform(stamp: Time, parent: str, child: str, pose: Pose) -> TransformStamped:
    p = pose.position
    q = pose.orientation
    return TransformStamped(Header(stamp, parent), child, Transform(
        Vector3(float(p[0]), float(p[1]), float(p[2])),
        Quaternion(float(q[0]), float(q[1]), float(q[2]), float(q[3]))))


def _static_links(robot: Robot, kin: Any) -> set[str]:
    """Links attached to their parent by fixed joints (their transform never changes): ``tf_static``."""
    fixed = {rec.child for rec in getattr(robot.description, "all_joints", ()) if rec.type == "fixed"}
    links = set(kin.link_names)
    if fixed and fixed <= links:
        return fixed
    # MJCF bodies: static when the parent->child transform is the same at several configurations
    rng = np.random.default_rng(0)
    lows = np.array([j.lower if j.lower is not None and math.isfinite(j.lower) else -1.0 for j in robot.joints])
    highs = np.array([j.upper if j.upper is not None and math.isfinite(j.upper) else 1.0 for j in robot.joints])
    samples = [kin.link_poses(list(rng.uniform(lows, highs))) for _ in range(3)]
    static = set()
    for parent, child, pose in samples[0].transforms():
        if all(np.allclose(s.relative(child, parent).matrix, pose.matrix, atol=1e-9) for s in samples[1:]):
            static.add(child)
    return static


def expose(robot: Robot, namespace: str = "", *, domain_id: int | None = None, rate: float | None = None,
           tf_rate: float = 50.0, sensor_qos: bool = False, feedback_rate: float = 20.0,
           tolerances: Tolerances | None = None, lease: float | None = 1.0, lease_category: int = 1,
           require_lease: bool = False) -> RosFace:
    """Serve ``robot`` as a ROS 2 node until the ``async with`` block ends.

    ``namespace`` (``"/arm1"``) prefixes every name; ``domain_id`` defaults to ``ROS_DOMAIN_ID``
    (else 0). ``rate``: joint_states in Hz (default: the control rate, at most 100 Hz; up to the
    control rate); ``sensor_qos=True`` publishes them best effort (ROS's SensorDataQoS).
    ``tf_rate``: tf and controller_state in Hz of wall time; ``feedback_rate``: action feedback
    in Hz of robot time. ``tolerances`` are the defaults for goals that set none (JTC's
    constraints). Without ``CYCLONEDDS_URI`` in the environment the node talks on loopback
    only; set ``CYCLONEDDS_URI`` to a Cyclone DDS configuration to choose the network.

    The dead-man (:mod:`agentsdk.ros2.lease`): a client holding a lease (heartbeats) that
    commanded the robot and then goes silent for ``lease`` seconds of wall time stops it with
    an e-stop of ``lease_category`` (1: to rest, then torque off; 0: torque off at once), and
    commands are refused until a reset. ``require_lease=True`` refuses commands while no
    client holds a live lease; ``lease=None`` turns the dead-man off.
    """
    return RosFace(robot, namespace=namespace, domain_id=domain_id, rate=rate, tf_rate=tf_rate,
                   sensor_qos=sensor_qos, feedback_rate=feedback_rate, tolerances=tolerances,
                   lease=lease, lease_category=lease_category, require_lease=require_lease)
