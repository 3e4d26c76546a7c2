"""The ``ros2`` backend: drive a robot through ROS 2 over DDS, without ROS (``pip install 'agentsdk[ros2]'``).

::

    async with agentsdk.connect("ros2", namespace="/arm1", controller="joint_trajectory_controller") as robot:
        ...   # the same behaviors as on any backend, agentsdk's safety layer in front

The robot on the other side is a ros2_control robot (a driver or a simulator with a
JointTrajectoryController) or an agentsdk robot served by ``agentsdk serve``, on this or
another host. What the backend uses, under ``namespace``:

* ``robot_description`` (transient local, as robot_state_publisher publishes it): the
  description, when ``connect`` is given no ``robot``;
* ``joint_states``: the measured state;
* the command interface (``interface``):

  - ``"agentsdk"`` (an agentsdk robot, chosen by ``"auto"`` when the remote reads
    ``agentsdk/command``): every tick's setpoint as one sequence-numbered direct command
    (:mod:`agentsdk.ros2.stream`); in lockstep the remote runs exactly one control period
    per tick (write, step, read, like a local simulator);
  - ``"joint_trajectory"`` (ros2_control's JTC topic interface ``<controller>/joint_trajectory``):
    every tick's setpoint as a one-point trajectory reached ``horizon`` seconds later;
  - ``"forward_command"`` (a ``forward_command_controller``'s ``<controller>/commands``,
    ``std_msgs/Float64MultiArray`` in ``command_joints`` order);

* ``<controller>/follow_joint_trajectory`` (``follow_goals``): a ``follow()``/``move_to`` trajectory,
  validated and limit-checked here, is sent as one ``FollowJointTrajectory`` goal when the action
  server speaks rmw_cyclonedds' request format (:mod:`agentsdk.ros2.goals`, the
  :class:`agentsdk.offload.TrajectoryOffload` capability): nothing is streamed while it runs, its
  feedback and result come back to the motion; else, and against a lockstep served robot, streamed;
* ``clock`` (``<namespace>/clock``: remap a simulator's ``/clock`` there): followed when the remote runs in
  simulated time (lockstep): a tick ends when the remote's time has advanced by one period.

Safety across the wire: trajectories, limits and the e-stop run here, in agentsdk's own
layers, before anything is sent. In realtime a ``joint_states`` stream older than
``stale_after`` seconds (in lockstep: no answer within ``timeout`` seconds of wall time)
latches a fault before the tick writes, so no command is ever sent on stale state. An
e-stop or fault sends the controller a hold (an empty trajectory: JTC holds its current
position) and cancels every FollowJointTrajectory goal of the controller.

Against a served agentsdk robot the backend holds a dead-man lease (``lease`` seconds,
:class:`agentsdk.ros2.lease.Heartbeat`) from open to close: if this process dies or stalls, the
served robot stops; closing releases the lease.

``realtime=None`` picks the remote's time model: lockstep when the robot's participant
publishes ``clock``, else realtime. Position mode only (what a JTC takes).
"""

from __future__ import annotations

import asyncio
import atexit
import logging
import math
import secrets
import shutil
import struct
import tempfile
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

# without cyclonedds this import fails: the registry names the missing package and the install hint
from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication
from cyclonedds.core import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from pydantic import BaseModel, ConfigDict, Field

from agentsdk.backend import Backend, Capabilities, JointReading, SetpointView
from agentsdk.errors import BackendFault, BackendStartError, ConfigurationError
from agentsdk.ros2._fast import FixedLayout, JointStateEncoder, write_raw
from agentsdk.ros2.dds import (
    QOS_DEFAULT,
    QOS_LATCHED,
    DdsNode,
    normalize_namespace,
    participant,
    resolve_domain_id,
)
from agentsdk.ros2.goals import FollowJointTrajectoryClient, GoalHandle
from agentsdk.ros2.lease import Heartbeat
from agentsdk.ros2.msgs import (
    CancelGoal_Request,
    Clock,
    Duration,
    FollowJointTrajectory_SendGoal_Request,
    Header,
    JointState,
    JointTrajectory,
    JointTrajectoryPoint,
    String,
    Time,
)
from agentsdk.ros2.stream import COMMAND_TOPIC, QOS_STREAM, STATE_TOPIC, parse_frame_id

from .msgs import Float64MultiArray

if TYPE_CHECKING:
    from agentsdk.backendspec import BackendSpec
    from agentsdk.config import RobotConfig
    from agentsdk.offload import OffloadRequest

__all__ = ["Ros2Backend", "Ros2Options"]

log = logging.getLogger(__name__)

Interface = Literal["auto", "agentsdk", "joint_trajectory", "forward_command"]
#: best effort reader: matches reliable and best-effort (SensorDataQoS) writers alike
_QOS_STATE = Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(10))
_QOS_CLOCK = Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(1))
#: how long ``"auto"`` waits, after the first joint_states, for an agentsdk command reader
_AUTO_GRACE = 0.5
#: how often a sync is repeated until the remote answers
_SYNC_RETRY = 0.2
_TIME = struct.Struct("<iI")


class Ros2Options(BaseModel):
    """``connect("ros2", ...)`` / robot.yaml ``backends.ros2`` options (every number finite)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    #: the robot's ROS namespace (``/arm1``); every topic is under it
    namespace: str = ""
    #: the controller's name: its topics and action are under ``<namespace>/<controller>/``
    controller: str = "joint_trajectory_controller"
    #: how setpoints are sent (see the module documentation); ``auto``: agentsdk if the remote reads it, else JTC
    interface: Interface = "auto"
    #: DDS domain (default: ``ROS_DOMAIN_ID``, else 0)
    domain_id: int | None = Field(default=None, ge=0, le=232)
    #: joint_states older than this (s) latch a fault: wall time for a realtime robot, the remote's time in lockstep
    stale_after: float = Field(default=0.5, gt=0.0)
    #: wall seconds to discover the robot, and (lockstep) for the remote to answer one step
    timeout: float = Field(default=10.0, gt=0.0)
    #: JTC streaming: time_from_start of each streamed point (s; default: one control period)
    horizon: float | None = Field(default=None, gt=0.0)
    #: forward_command_controller: its joints, in its order (default: the robot's joints)
    command_joints: tuple[str, ...] | None = None
    #: dead-man lease (s) held with an agentsdk server while connected (heartbeats; None: no lease)
    lease: float | None = Field(default=1.0, gt=0.0)
    #: send follow()/move_to trajectories as FollowJointTrajectory goals when the controller serves the action
    #: (in rmw_cyclonedds' request format); False: always stream setpoints
    follow_goals: bool = True


class Ros2Backend(Backend):
    """A robot on the ROS 2 graph: state from ``joint_states``, setpoints to its controller."""

    name = "ros2"
    capabilities = Capabilities(modes=frozenset({"position"}), lockstep=True, realtime=True, deterministic=False,
                                standalone=False)
    options_model = Ros2Options

    @classmethod
    def default_realtime(cls, config: RobotConfig, options: dict[str, Any]) -> bool:
        """The remote's time model: lockstep when it publishes ``/clock``."""
        return not remote_sim_time(options)

    def __init__(self, spec: BackendSpec) -> None:
        super().__init__(spec)
        opts: Ros2Options = self.options
        try:
            self.namespace = normalize_namespace(opts.namespace)
            self.controller = normalize_namespace(opts.controller).lstrip("/")
        except Exception as exc:
            raise ConfigurationError(f"ros2: {exc}") from None
        if not self.controller:
            raise ConfigurationError("ros2: controller must name the controller, e.g. 'joint_trajectory_controller'")
        self.domain_id = resolve_domain_id(opts.domain_id)
        self.horizon = opts.horizon if opts.horizon is not None else self.period
        self.stale_after = opts.stale_after
        self.timeout = opts.timeout
        command_joints = opts.command_joints if opts.command_joints is not None else self.names
        unknown = [j for j in command_joints if j not in self.index]
        if unknown:
            raise ConfigurationError(f"ros2: command_joints names unknown joint(s) {unknown}")
        self._command_index = np.array([self.index[j] for j in command_joints], dtype=np.intp)
        #: the command interface in use (``interface`` resolved when the robot is opened)
        self.interface: str = opts.interface
        n = len(self.names)
        self._q = np.array(self.initial_positions, dtype=float)
        self._v = np.zeros(n)
        self._e = np.zeros(n)
        self._seen = np.zeros(n, dtype=bool)
        self._session = secrets.token_hex(8)
        self._seq = 0
        self._lock = threading.Lock()
        self._node: DdsNode | None = None
        self._heartbeat: Heartbeat | None = None
        self._error: str | None = None
        self._last_rx = -math.inf  # monotonic time of the newest joint_states (or reply)
        self._state_stamp = -math.inf  # remote time of the newest state
        self._clock = -math.inf  # the remote's newest clock
        self._offset = 0.0  # remote time at local robot time 0 (lockstep)
        self._local_t = 0.0
        self._waiter: asyncio.Future[None] | None = None
        self._wait_seq = 0
        self._wait_time = math.inf
        self._enabled = False  # the latest write's: any joint enabled
        #: a goal to send once the served robot answers the sync of that sequence number
        self._deferred: tuple[int, GoalHandle] | None = None
        self._goals: FollowJointTrajectoryClient | None = None
        #: the robot's joints an offloaded goal holds (indices, positions), and the goal
        self._hold: tuple[np.ndarray, np.ndarray, GoalHandle] | None = None
        self._hold_dev = np.zeros(0)
        #: True once the controller's FollowJointTrajectory action server was found (follow_goals)
        self.goals_available = False
        #: FollowJointTrajectory goals sent
        self.goals_sent = 0
        self.last_write = -math.inf
        self.last_write_age = 0.0
        #: commands sent, replies received, and joint_states samples received
        self.sent = 0
        self.replies = 0
        self.states = 0

    # ------------------------------------------------------------------ description and time model
    @classmethod
    def remote_description(cls, options: Mapping[str, Any]) -> Path:
        """The URDF the robot publishes on ``robot_description`` (blocking: call from a worker thread).

        Written to a file in a temporary directory (removed at exit), which ``connect`` loads.
        """
        ns, domain_id, timeout = _probe_options(options)
        with participant(domain_id) as dp:
            reader: DataReader[Any] = DataReader(dp, Topic(dp, f"rt{ns}/robot_description", String), qos=QOS_LATCHED)
            deadline = time.monotonic() + timeout
            while True:
                samples = [s for s in reader.take(N=4) if isinstance(s, String)]
                if samples and samples[-1].data.strip():
                    urdf = samples[-1].data
                    break
                if time.monotonic() > deadline:
                    raise BackendStartError(
                        f"ros2: no robot_description on {ns or ''}/robot_description (domain {domain_id}) within "
                        f"{timeout:g} s; is the robot running (robot_state_publisher, agentsdk serve) on this "
                        "ROS_DOMAIN_ID? Or pass robot= a description")
                time.sleep(0.02)
        path = _description_dir() / f"robot_description{ns.replace('/', '_')}_{secrets.token_hex(4)}.urdf"
        path.write_text(urdf)
        return path

    # ------------------------------------------------------------------ hooks
    async def _open(self) -> None:
        loop = asyncio.get_running_loop()
        from agentsdk.threads import run_blocking

        self._node = await run_blocking(self._build, loop, name="agentsdk-ros2-connect")
        self._node.start()
        await self._discover()
        if self.interface == "agentsdk" and self.options.lease is not None:
            # the served robot's dead-man covers this client: it stops when the heartbeats stop
            self._heartbeat = Heartbeat(self._node, self.options.lease, f"agentsdk-ros2-{self._session}")
            self._heartbeat.beat()
            self._heartbeat.start()

    def _build(self, loop: asyncio.AbstractEventLoop) -> DdsNode:
        """The participant, its readers and writers, the pre-laid encoders (in a worker thread)."""
        names = list(self.names)
        n = len(names)
        frame = f"{self._session}:{0:016x}"
        self._cmd_enc = JointStateEncoder(names, frame_id=frame)
        self._sync_enc = JointStateEncoder([], frame_id=frame)
        self._seq_at = 4 + 8 + 4 + 17  # encapsulation, stamp, string length, "<session>:"
        horizon = Duration.from_seconds(self.horizon)

        def jtc(values: np.ndarray, _stamps: list[Time]) -> JointTrajectory:
            return JointTrajectory(Header(), names, [JointTrajectoryPoint(
                positions=[float(x) for x in values[:n]], velocities=[float(x) for x in values[n:]],
                time_from_start=horizon)])

        self._jtc_layout = FixedLayout(jtc, 2 * n, 0)
        self._jtc_values = np.zeros(2 * n)
        k = len(self._command_index)
        self._fwd_layout = FixedLayout(lambda values, _s: Float64MultiArray(data=[float(x) for x in values]), k, 0)
        self._fwd_values = np.zeros(k)
        self._hold_bytes = bytes(JointTrajectory(Header(), names, []).serialize())
        for t in (JointState, Clock, CancelGoal_Request, FollowJointTrajectory_SendGoal_Request):
            t.deserialize(t().serialize())  # compile the serialisers here, not on the event loop
        node = DdsNode(self.domain_id, self.namespace, loop)
        try:
            node.subscribe("joint_states", JointState, self._on_joint_states, _QOS_STATE)
            self._clock_reader = node.subscribe("clock", Clock, self._on_clock, _QOS_CLOCK)
            node.subscribe(STATE_TOPIC, JointState, self._on_reply, QOS_DEFAULT)
            self._cmd_w = node.writer(COMMAND_TOPIC, JointState, QOS_STREAM)
            self._jtc_w = node.writer(f"{self.controller}/joint_trajectory", JointTrajectory, QOS_DEFAULT)
            self._fwd_w = node.writer(f"{self.controller}/commands", Float64MultiArray, QOS_DEFAULT)
            self._goals = FollowJointTrajectoryClient(node, self.controller)
            node.announce(f"agentsdk_ros2_{self._session[:8]}")
        except BaseException:
            node.close()
            raise
        return node

    async def _discover(self) -> None:
        """Find the robot, pick the interface, take the first state (and the remote time in lockstep)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.timeout
        wanted = self.interface
        first_state: float | None = None
        while True:
            if wanted in ("auto", "agentsdk") and self._cmd_w.get_matched_subscriptions():
                self.interface = "agentsdk"
                break
            if wanted != "agentsdk" and self._seen.all():
                first_state = loop.time() if first_state is None else first_state
                if wanted != "auto" or loop.time() - first_state > _AUTO_GRACE:
                    self.interface = "joint_trajectory" if wanted == "auto" else wanted
                    break
            if loop.time() > deadline:
                raise BackendStartError(self._not_found())
            await asyncio.sleep(0.02)
        if not self.realtime and not self._clock_reader.get_matched_publications():
            raise BackendStartError(
                f"ros2: lockstep needs the remote's simulated time, but nothing publishes {self._ns('clock')}; "
                "connect with realtime=True (the remote runs in wall-clock time)")
        if self.options.follow_goals:
            # the action server's endpoints are discovered with the robot's participant: a short grace at most
            grace = loop.time() + _AUTO_GRACE
            while not self.goals_available and loop.time() < min(grace, deadline):
                self.goals_available = self._goals is not None and self._goals.available()
                if not self.goals_available:
                    await asyncio.sleep(0.02)
        if self.interface == "agentsdk":
            await self._sync(deadline)
        elif not self.realtime:
            while not math.isfinite(self._clock):
                if loop.time() > deadline:
                    raise BackendStartError(f"ros2: no {self._ns('clock')} sample within {self.timeout:g} s")
                await asyncio.sleep(0.02)
            self._offset = self._clock
        log.debug("ros2: %s on %s via %s (%s), trajectories %s", self.description.name, self.namespace or "/",
                  self.interface, "realtime" if self.realtime else "lockstep",
                  "as FollowJointTrajectory goals" if self.goals_available else "streamed")

    async def _sync(self, deadline: float, error: type[Exception] = BackendStartError) -> None:
        """Ask the agentsdk robot for its state until it answers (the first commands may precede matching)."""
        loop = asyncio.get_running_loop()
        while True:
            fut = self._expect(self._send_sync(0.0), math.inf)
            try:
                async with asyncio.timeout(_SYNC_RETRY):
                    await fut
                break
            except TimeoutError:
                if loop.time() > deadline:
                    raise error(
                        f"ros2: the agentsdk robot on {self._ns(COMMAND_TOPIC)} did not answer within "
                        f"{self.timeout:g} s") from None
            finally:
                self._waiter = None
        if self._error is not None:
            raise error(f"ros2: {self._error}")
        missing = [self.names[i] for i in np.flatnonzero(~self._seen)]
        if missing:
            raise error(f"ros2: the remote robot has no joint(s) {missing} (check robot= and namespace)")
        self._offset = self._state_stamp - self._local_t

    def _not_found(self) -> str:
        seen = np.flatnonzero(self._seen)
        if self.states and len(seen) < len(self.names):
            missing = [self.names[i] for i in np.flatnonzero(~self._seen)]
            return (f"ros2: {self._ns('joint_states')} has no joint(s) {missing}; the robot description does not "
                    "match the remote robot")
        if self.interface == "agentsdk":
            return f"ros2: nothing reads {self._ns(COMMAND_TOPIC)} (is agentsdk serve running there?)"
        return (f"ros2: no joint_states on {self._ns('joint_states')} (domain {self.domain_id}) within "
                f"{self.timeout:g} s; is the robot running on this ROS_DOMAIN_ID and namespace?")

    def _ns(self, name: str) -> str:
        return f"{self.namespace}/{name}"

    async def _close(self) -> None:
        node, self._node = self._node, None
        if node is None:
            return
        heartbeat, self._heartbeat = self._heartbeat, None
        try:
            self._send_hold()
            if heartbeat is not None:
                await heartbeat.aclose()  # released on purpose: leaving never stops the served robot
        finally:
            node.close()

    def _write(self, sp: SetpointView) -> None:
        if self._error is not None:
            raise BackendFault(f"ros2: {self._error}")
        if self.realtime:
            now = time.monotonic()
            age = now - self._last_rx
            if age > self.stale_after:
                raise BackendFault(
                    f"ros2: joint_states on {self._ns('joint_states')} are {age:.3f} s old (bound stale_after "
                    f"{self.stale_after:g} s); no command is sent on stale state")
            #: monotonic time of the latest realtime write, and the age of the state it was based on
            self.last_write, self.last_write_age = now, age
        elif self.interface != "agentsdk" and self._clock - self._state_stamp > self.stale_after:
            raise BackendFault(
                f"ros2: joint_states on {self._ns('joint_states')} are {self._clock - self._state_stamp:.3f} s "
                f"(robot time) old (bound stale_after {self.stale_after:g} s); no command is sent on stale state")
        self._enabled = bool(sp.enabled.any())
        goals = self._goals
        if goals is not None and goals.active:
            self._check_hold(sp, goals.active[-1])
            return  # the controller runs the goal: nothing is streamed meanwhile
        if goals is not None and self.interface == "agentsdk" and goals.draining():
            return  # a served robot still stops a cancelled goal (its stream would be refused): not yet
        if self.interface == "agentsdk":
            self._cmd_enc.encode(0.0, sp.position, sp.velocity, sp.effort)
            if self.realtime and self._enabled:
                self._send_command(0.0)
            return
        if not self._enabled:
            return  # torque off: the controller holds where the stop left it
        if self.interface == "joint_trajectory":
            n = len(self.names)
            self._jtc_values[:n] = sp.position
            self._jtc_values[n:] = sp.velocity
            write_raw(self._jtc_w, self._jtc_layout.encode(self._jtc_values, 0.0))
        else:
            self._fwd_values[:] = sp.position[self._command_index]
            write_raw(self._fwd_w, self._fwd_layout.encode(self._fwd_values, 0.0))
        self.sent += 1

    async def _step(self, dt: float) -> None:
        if self.realtime:
            return
        target = self._offset + self._local_t + dt
        self._local_t += dt
        if self.interface == "agentsdk":
            streaming = self._enabled and not (self._goals is not None and self._goals.active)
            seq = self._send_command(target) if streaming else self._send_sync(target)
            fut = self._expect(seq, math.inf)
        else:
            if self._clock >= target - 1e-9:
                return
            fut = self._expect(None, target)
        try:
            async with asyncio.timeout(self.timeout):
                await fut
        except TimeoutError:
            what = "answer" if self.interface == "agentsdk" else f"advance {self._ns('clock')} to {target:.6f} s"
            raise BackendFault(f"ros2: the remote robot did not {what} within {self.timeout:g} s "
                               "(wall time)") from None
        finally:
            self._waiter = None
        if self._error is not None:
            raise BackendFault(f"ros2: {self._error}")

    def _read(self) -> JointReading:
        return self._q, self._v, self._e

    async def _recover(self) -> None:
        """After a fault: usable again once the remote answers (agentsdk) or its joint_states are fresh."""
        self._error = None
        loop = asyncio.get_running_loop()
        if self.interface == "agentsdk":
            await self._sync(loop.time() + self.timeout, BackendFault)
            if self._error is not None:
                raise BackendFault(f"ros2: cannot recover: {self._error}")
            return
        if self.realtime:
            age = time.monotonic() - self._last_rx
            if age > self.stale_after:
                raise BackendFault(f"ros2: cannot recover: joint_states on {self._ns('joint_states')} are "
                                   f"{age:.3f} s old (bound stale_after {self.stale_after:g} s)")
        else:
            if self._clock - self._state_stamp > self.stale_after:
                raise BackendFault(f"ros2: cannot recover: joint_states on {self._ns('joint_states')} are stale")
            self._offset = self._clock - self._local_t

    def _emergency_stop(self, category: int) -> None:
        self._send_hold()

    # ------------------------------------------------------------------ sending
    def _next_seq(self, encoder: JointStateEncoder) -> int:
        self._seq += 1
        at = self._seq_at
        encoder.buffer[at:at + 16] = b"%016x" % self._seq
        return self._seq

    def _send_command(self, stamp: float) -> int:
        """Send the encoded setpoint with the next sequence number; ``stamp``: remote time to run to (0: none)."""
        return self._send(self._cmd_enc, stamp)

    def _send_sync(self, stamp: float) -> int:
        """Send a command without joints (the remote answers with its state, after running to ``stamp``)."""
        return self._send(self._sync_enc, stamp)

    def _send(self, enc: JointStateEncoder, stamp: float) -> int:
        with self._lock:
            seq = self._next_seq(enc)
            ns = round(stamp * 1e9)
            _TIME.pack_into(enc.buffer, 4, ns // 1_000_000_000, ns % 1_000_000_000)
            write_raw(self._cmd_w, enc.buffer)
        self.sent += 1
        return seq

    def _send_hold(self) -> None:
        """Hold (an empty trajectory: JTC keeps its current position) and cancel every goal (thread-safe)."""
        node, goals = self._node, self._goals
        if node is None or goals is None:
            return
        with self._lock:
            try:
                write_raw(self._jtc_w, self._hold_bytes)
                goals.cancel(None)
            except Exception as exc:  # the participant is closing: nothing left to tell
                log.debug("ros2: hold not sent: %s", exc)

    # ------------------------------------------------------------------ trajectory offload (agentsdk.offload)
    def offload_trajectory(self, request: OffloadRequest) -> GoalHandle | None:
        """Send a validated trajectory as one FollowJointTrajectory goal (None: it is streamed instead).

        Only when the controller's action server was found (``follow_goals``), the robot is
        enabled and not faulted. The goal holds the robot's other joints where they are; a
        setpoint of one of them that moves meanwhile (something else commands the robot)
        cancels the goal (PREEMPTED).
        """
        goals = self._goals
        if (goals is None or not self.goals_available or self._node is None or self._error is not None
                or not self._enabled or not goals.available()):
            return None
        if not any(p.time_from_start > 0.0 for p in request.trajectory.points):
            return None  # nothing after the start state: nothing for a controller to run
        if self.interface == "agentsdk" and not self.realtime:
            # a served lockstep robot runs a goal at its own pace (its time advances while a goal runs), not
            # one control period per step of this robot: streamed, its lockstep stays exact
            return None
        gt = request.goal_time if math.isfinite(request.goal_time) else 0.0
        deadline = request.trajectory.duration + gt + self.timeout
        # a served agentsdk robot applies its stream's commands in order, a goal on arrival: the goal is sent once
        # the robot has answered a sync sent now, after every command before it (none refused as "driven by a goal")
        defer = self.interface == "agentsdk"
        handle = goals.send(request, deadline, defer=defer)
        if defer:
            # released unfinished (e-stop, abort): the served robot decelerates the goal itself and refuses stream
            # commands on its joints until it has; nothing is streamed until its result (at most `timeout`)
            handle.drain = self.timeout
        if defer:
            self._deferred = (self._send_sync(0.0), handle)
        hold_idx = np.array([self.index[n] for n in request.hold], dtype=np.intp)
        self._hold = (hold_idx, np.array([float(x) for x in request.hold.values()]), handle)
        self._hold_dev = np.zeros(len(hold_idx))
        self.goals_sent += 1
        return handle

    def _check_hold(self, sp: SetpointView, handle: GoalHandle) -> None:
        """A setpoint of a joint the goal holds moved, or torque went off: the goal is preempted."""
        hold = self._hold
        if not sp.enabled.all():
            handle.preempt("preempted: the robot's torque went off")
        if hold is None or hold[2] is not handle or not len(hold[0]):
            return
        idx, q, _ = hold
        dev = self._hold_dev  # preallocated: the tick allocates nothing
        np.take(sp.position, idx, out=dev)
        np.subtract(dev, q, out=dev)
        np.abs(dev, out=dev)
        if float(dev.max()) > 1e-9:
            k = int(np.argmax(dev))
            handle.preempt(f"preempted: joint {self.names[int(idx[k])]!r} was commanded while the goal held it")

    def _expect(self, seq: int | None, remote_time: float) -> asyncio.Future[None]:
        """A future resolved by the answer to command ``seq`` or by the remote clock reaching ``remote_time``."""
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._waiter, self._wait_time = fut, remote_time
        self._wait_seq = 1 << 62 if seq is None else seq
        return fut

    # ------------------------------------------------------------------ receiving (event loop callbacks)
    def _take_state(self, msg: JointState) -> None:
        index = self.index
        q, v, e, seen = self._q, self._v, self._e, self._seen
        nv, ne = len(msg.velocity), len(msg.effort)
        for k, name in enumerate(msg.name):
            i = index.get(name)
            if i is None or k >= len(msg.position):
                continue
            q[i] = msg.position[k]
            v[i] = msg.velocity[k] if k < nv else 0.0
            e[i] = msg.effort[k] if k < ne else 0.0
            seen[i] = True
        self._state_stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        self._last_rx = time.monotonic()

    def _on_joint_states(self, msg: JointState) -> None:
        self.states += 1
        if self.interface == "agentsdk" and not self.realtime:
            return  # lockstep: the state of each step comes with its answer
        self._take_state(msg)

    def _on_reply(self, msg: JointState) -> None:
        text = msg.header.frame_id
        ident = parse_frame_id(text[:33])
        if ident is None or ident[0] != self._session:
            return
        self.replies += 1
        _, seq = ident
        if len(text) > 33:
            self._error = f"the remote robot refused command {seq}:{text[33:]}"
        if self.interface == "agentsdk" and not self.realtime:
            self._take_state(msg)
        elif not self._seen.all():  # the sync's answer: the first state
            self._take_state(msg)
        deferred = self._deferred
        if deferred is not None and seq >= deferred[0] and self._goals is not None:
            self._deferred = None
            self._goals.dispatch(deferred[1])
        fut = self._waiter
        if fut is not None and not fut.done() and seq >= self._wait_seq:
            fut.set_result(None)

    def _on_clock(self, msg: Clock) -> None:
        self._clock = msg.clock.sec + msg.clock.nanosec * 1e-9
        fut = self._waiter
        if fut is not None and not fut.done() and self._clock >= self._wait_time - 1e-9:
            fut.set_result(None)


# ---------------------------------------------------------------------- blocking helpers (worker threads)
def _probe_options(options: Mapping[str, Any]) -> tuple[str, int, float]:
    try:
        ns = normalize_namespace(options.get("namespace", ""))
    except Exception as exc:
        raise ConfigurationError(f"ros2: {exc}") from None
    domain_id = resolve_domain_id(options.get("domain_id"))
    timeout = options.get("timeout", 10.0)
    if not (isinstance(timeout, int | float) and math.isfinite(timeout) and timeout > 0):
        raise ConfigurationError(f"ros2: timeout must be a positive number of seconds, got {timeout!r}")
    return ns, domain_id, float(timeout)


def remote_sim_time(options: Mapping[str, Any]) -> bool:
    """True when the robot in ``namespace`` runs in simulated time (its participant publishes ``clock``).

    Waits (blocking, up to ``timeout``) until the robot's ``joint_states`` writer is discovered,
    then briefly for the rest of its writers. Raises :class:`BackendStartError` when no robot is
    found.
    """
    ns, domain_id, timeout = _probe_options(options)
    want_js, want_clock = f"rt{ns}/joint_states", f"rt{ns}/clock"
    with participant(domain_id) as dp:
        reader = BuiltinDataReader(dp, BuiltinTopicDcpsPublication)
        deadline = time.monotonic() + timeout
        found: float | None = None
        topics: set[str] = set()
        while True:
            for s in reader.take(N=256):
                name = getattr(s, "topic_name", None)
                if isinstance(name, str):
                    topics.add(name)
            if want_clock in topics:
                return True
            now = time.monotonic()
            if want_js in topics:
                found = now if found is None else found
                if now - found > _AUTO_GRACE:
                    return False
            elif now > deadline:
                raise BackendStartError(
                    f"ros2: no robot publishes {ns}/joint_states on domain {domain_id} (waited {timeout:g} s); is "
                    "it running on this ROS_DOMAIN_ID and namespace?")
            time.sleep(0.02)


_description_tmp: list[Path] = []
_description_lock = threading.Lock()


def _description_dir() -> Path:
    with _description_lock:
        if not _description_tmp:
            path = Path(tempfile.mkdtemp(prefix="agentsdk-ros2-description-"))
            atexit.register(shutil.rmtree, path, True)
            _description_tmp.append(path)
        return _description_tmp[0]
