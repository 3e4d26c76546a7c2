"""A ``control_msgs/action/FollowJointTrajectory`` client over DDS (the ``ros2`` backend's trajectory offload).

The action ``<namespace>/<controller>/follow_joint_trajectory`` is, on the wire (rmw_cyclonedds'
format, as :mod:`agentsdk.ros2.server` serves it):

* services ``_action/send_goal``, ``_action/get_result``, ``_action/cancel_goal``: request topics
  ``rq/...Request``, reply topics ``rr/...Reply``, every sample the client's request writer id
  and a sequence number (:class:`~agentsdk.ros2.msgs.RequestHeader`) then the message;
* topics ``_action/feedback`` (the goal id, then desired/actual/error) and ``_action/status``.

A goal's life: ``send_goal`` (a random 16-byte goal id); accepted -> ``get_result``, whose reply
carries the final status (SUCCEEDED, CANCELED, ABORTED) and FollowJointTrajectory's
``error_code``; rejected -> INVALID_GOAL. :meth:`GoalHandle.outcome` maps them to
:class:`agentsdk.ResultCode` values. Everything runs on the event loop (DDS callbacks arrive
there); the writes never block.

The client is used only against servers that speak rmw_cyclonedds' request format: their service
endpoints carry ``serviceid=`` user data (:meth:`FollowJointTrajectoryClient.available`).
rmw_fastrtps keeps the request identity in RTPS inline QoS instead, which this client cannot
write: against such a controller the backend streams setpoints, as without an action server.
"""

from __future__ import annotations

import logging
import math
import secrets
import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from cyclonedds.core import Policy

from ..motion import ResultCode
from .convert import GOAL_ABORTED, GOAL_CANCELED, GOAL_SUCCEEDED
from .dds import QOS_DEFAULT, QOS_SERVICE, DdsNode, service_wire_type, wrap
from .msgs import (
    UUID,
    CancelGoal_Request,
    CancelGoal_Response,
    Duration,
    FollowJointTrajectory_FeedbackMessage,
    FollowJointTrajectory_GetResult_Request,
    FollowJointTrajectory_GetResult_Response,
    FollowJointTrajectory_Goal,
    FollowJointTrajectory_SendGoal_Request,
    FollowJointTrajectory_SendGoal_Response,
    GoalInfo,
    Header,
    JointTolerance,
    JointTrajectory,
    JointTrajectoryPoint,
    RequestHeader,
    Time,
)

if TYPE_CHECKING:
    from cyclonedds.pub import DataWriter

    from ..offload import OffloadRequest

__all__ = ["FollowJointTrajectoryClient", "GoalHandle", "goal_message"]

log = logging.getLogger(__name__)


def goal_message(request: OffloadRequest) -> FollowJointTrajectory_Goal:
    """The ``FollowJointTrajectory`` goal of an offload request: every joint, tolerances as JTC reads them.

    The robot's other joints (``request.hold``) are added to every point at their held
    position, so a controller that takes only complete goals accepts it. A point at
    ``time_from_start`` 0 (the start state, as agentsdk measured it) is left out: the controller
    starts from its own current state, as JTC does. A tolerance that is
    not checked (``inf``) is -1 (JTC: "not checked"); ``goal_time`` 0 or ``inf`` is sent as 0
    (the controller's default).
    """
    traj = request.trajectory
    names = [*traj.joint_names, *request.hold]
    held = [float(x) for x in request.hold.values()]
    n = len(traj.joint_names)
    points = []
    for p in traj.points:
        if p.time_from_start <= 0.0:
            continue  # the start state as agentsdk sees it: the controller starts from its own (JTC's rule)
        vel = [*(float(x) for x in p.velocities), *[0.0] * len(held)] if p.velocities is not None else []
        acc = [*(float(x) for x in p.accelerations), *[0.0] * len(held)] if p.accelerations is not None else []
        points.append(JointTrajectoryPoint([*(float(x) for x in p.positions), *held], vel, acc, [],
                                           Duration.from_seconds(p.time_from_start)))

    def tolerances(values: np.ndarray) -> list[JointTolerance]:
        return [JointTolerance(name, -1.0 if not math.isfinite(x) else float(x))
                for name, x in zip(names[:n], values.tolist(), strict=True)]

    gt = request.goal_time
    return FollowJointTrajectory_Goal(
        trajectory=JointTrajectory(Header(), names, points),
        path_tolerance=tolerances(request.path_tolerance),
        goal_tolerance=tolerances(request.goal_tolerance),
        goal_time_tolerance=Duration.from_seconds(gt if math.isfinite(gt) and gt > 0 else 0.0),
    )


def map_result(status: int, error_code: int, error_string: str) -> tuple[int, str]:
    """``(ResultCode value, message)`` of a goal's final status and FollowJointTrajectory result."""
    if status == GOAL_SUCCEEDED:
        return error_code, error_string
    if status == GOAL_CANCELED:
        return int(ResultCode.CANCELED), error_string or "canceled by the controller"
    if status == GOAL_ABORTED:
        # a JTC reports why in error_code (PATH_/GOAL_TOLERANCE_VIOLATED...); 0 with ABORTED: no reason given
        return (error_code if error_code != 0 else int(ResultCode.ABORTED)), error_string or "aborted by the controller"
    return int(ResultCode.ABORTED), f"the controller has no result for the goal (status {status})"


class GoalHandle:
    """One goal sent to the controller (:class:`agentsdk.offload.OffloadedGoal`)."""

    def __init__(self, client: FollowJointTrajectoryClient, uuid: bytes, names: Sequence[str],
                 deadline: float) -> None:
        self._client = client
        self.uuid = uuid
        self.names = tuple(names)
        self._index = {name: k for k, name in enumerate(self.names)}
        #: robot seconds from the first :meth:`outcome` call until the controller must have answered
        self._deadline = deadline
        self._expires: float | None = None
        self.accepted: bool | None = None
        self.result: tuple[int, str] | None = None
        self._cancel_wanted = False
        self._cancel_sent = False
        self.released = False
        #: seconds a released, unfinished goal is waited for before streaming again (0: not waited for)
        self.drain = 0.0
        #: set when something else commanded the robot: the cancel's outcome is PREEMPTED with this reason
        self.preempted: str | None = None
        #: the goal while its sending is deferred (:meth:`FollowJointTrajectoryClient.dispatch`)
        self._message: FollowJointTrajectory_Goal | None = None
        self._fb_q: np.ndarray | None = None
        self._fb_v: np.ndarray | None = None

    # OffloadedGoal -------------------------------------------------------------
    def outcome(self, now: float) -> tuple[int, str] | None:
        """The goal's ``(ResultCode value, message)`` once it has ended, else None."""
        if self.result is not None:
            return self.result
        if self._expires is None:
            self._expires = now + self._deadline
        elif now > self._expires:
            self._client.cancel(self)
            what = "accept the goal" if self.accepted is None else "send the goal's result"
            self.result = (int(ResultCode.ABORTED), f"the controller did not {what} within {self._deadline:.3g} s "
                           "(robot time) of the trajectory's end plus its goal time and the backend's timeout")
        return self.result

    def started(self) -> bool:
        """True once the controller accepted the goal (or the goal has ended)."""
        return self.accepted is True or self.result is not None

    def desired_into(self, position: np.ndarray, velocity: np.ndarray) -> bool:
        """The controller's latest desired state (trajectory joint order); False before its first feedback."""
        q, v = self._fb_q, self._fb_v
        if q is None or v is None:
            return False
        n = len(position)
        position[...] = q[:n]
        velocity[...] = v[:n]
        return True

    def cancel(self) -> None:
        """Cancel the goal (after its acceptance: a cancel may not overtake the goal it cancels)."""
        if self._message is not None and self.result is None:  # not sent yet: it never will be
            self._message = None
            self.result = (int(ResultCode.CANCELED), "canceled before it was sent")
            return
        self._cancel_wanted = True
        if self.result is None and self.accepted:
            self._client.cancel(self)

    def release(self) -> None:
        """The motion has ended: cancel the goal if it runs; the backend streams setpoints again."""
        if self.result is None:
            self.cancel()
        self.released = True
        self._client.released(self, self.drain)

    def preempt(self, reason: str) -> None:
        """Something else commands the robot: cancel; the outcome is PREEMPTED, ``reason`` its message."""
        if self.preempted is None and self.result is None:
            self.preempted = reason
            self.cancel()

    # the client's side ----------------------------------------------------------
    def _on_accepted(self, accepted: bool) -> None:
        if self.accepted is not None:
            return
        self.accepted = accepted
        if not accepted:
            if self.result is None:
                self.result = (int(ResultCode.INVALID_GOAL), "the controller rejected the goal")
            return
        self._client.request_result(self)
        if self._cancel_wanted:
            self._client.cancel(self)

    def _on_result(self, status: int, error_code: int, error_string: str) -> None:
        if self.result is not None:
            return
        code, msg = map_result(status, error_code, error_string)
        if self.preempted is not None and code == ResultCode.CANCELED:
            code, msg = int(ResultCode.PREEMPTED), self.preempted
        self.result = (code, msg)

    def _on_feedback(self, names: Sequence[str], desired: JointTrajectoryPoint) -> None:
        n = len(self.names)
        q = np.full(n, np.nan) if self._fb_q is None else self._fb_q.copy()
        v = np.zeros(n) if self._fb_v is None else self._fb_v.copy()
        nv = len(desired.velocities)
        for k, name in enumerate(names):
            i = self._index.get(name)
            if i is None or k >= len(desired.positions):
                continue
            q[i] = desired.positions[k]
            v[i] = desired.velocities[k] if k < nv else 0.0
        if np.isfinite(q).all():
            self._fb_q, self._fb_v = q, v


class FollowJointTrajectoryClient:
    """The action client of ``<namespace>/<controller>/follow_joint_trajectory`` on a :class:`DdsNode`."""

    def __init__(self, node: DdsNode, controller: str) -> None:
        action = f"{controller}/follow_joint_trajectory/_action"
        self._lock = threading.Lock()
        self._seq = 0
        self._goals: dict[bytes, GoalHandle] = {}
        self._requests: dict[tuple[int, int], GoalHandle] = {}
        #: goals the motion layer has not released yet (the backend streams nothing meanwhile)
        self.active: list[GoalHandle] = []
        #: released goals without a result yet, and the monotonic time until which they are waited for
        self._draining: dict[GoalHandle, float] = {}
        self._send_w: DataWriter[Any] = node.writer(
            f"{action}/send_goalRequest", service_wire_type(FollowJointTrajectory_SendGoal_Request), QOS_SERVICE,
            prefix="rq/")
        self._result_w: DataWriter[Any] = node.writer(
            f"{action}/get_resultRequest", service_wire_type(FollowJointTrajectory_GetResult_Request), QOS_SERVICE,
            prefix="rq/")
        self._cancel_w: DataWriter[Any] = node.writer(
            f"{action}/cancel_goalRequest", service_wire_type(CancelGoal_Request), QOS_SERVICE, prefix="rq/")
        self._send_r = node.subscribe(f"{action}/send_goalReply",
                                      service_wire_type(FollowJointTrajectory_SendGoal_Response),
                                      self._on_send_reply, QOS_SERVICE, prefix="rr/")
        self._result_r = node.subscribe(f"{action}/get_resultReply",
                                        service_wire_type(FollowJointTrajectory_GetResult_Response),
                                        self._on_result_reply, QOS_SERVICE, prefix="rr/")
        node.subscribe(f"{action}/cancel_goalReply", service_wire_type(CancelGoal_Response), self._on_cancel_reply,
                       QOS_SERVICE, prefix="rr/")
        node.subscribe(f"{action}/feedback", FollowJointTrajectory_FeedbackMessage, self._on_feedback, QOS_DEFAULT)
        self._send_id = int.from_bytes(self._send_w.guid.bytes[:8], "little")
        self._result_id = int.from_bytes(self._result_w.guid.bytes[:8], "little")
        #: cancel_goal requests sent (every goal, the hold's "cancel all" included)
        self.cancels = 0

    # discovery -----------------------------------------------------------------------
    def available(self) -> bool:
        """True when an action server in rmw_cyclonedds' request format answers send_goal and get_result."""
        for writer in (self._send_w, self._result_w, self._cancel_w):
            handles = writer.get_matched_subscriptions()
            if not handles or not any(_is_cyclone_service(writer, h) for h in handles):
                return False
        return bool(self._send_r.get_matched_publications()) and bool(self._result_r.get_matched_publications())

    # requests ---------------------------------------------------------------------------
    def send(self, request: OffloadRequest, deadline: float, *, defer: bool = False) -> GoalHandle:
        """Send ``request`` as a new goal; ``deadline``: robot seconds after the first poll to wait for its result.

        ``defer``: made now, sent by :meth:`dispatch` (after what was sent before it has been applied).
        """
        uuid = secrets.token_bytes(16)
        goal = goal_message(request)
        handle = GoalHandle(self, uuid, goal.trajectory.joint_names, deadline)
        self._goals[uuid] = handle
        self.active.append(handle)
        handle._message = goal
        if not defer:
            self.dispatch(handle)
        return handle

    def dispatch(self, handle: GoalHandle) -> None:
        """Write the goal's ``send_goal`` request (once)."""
        goal, handle._message = handle._message, None
        if goal is None or handle.result is not None:
            return
        uuid = handle.uuid
        with self._lock:
            self._seq += 1
            self._requests[(self._send_id, self._seq)] = handle
            self._send_w.write(wrap(FollowJointTrajectory_SendGoal_Request, RequestHeader(self._send_id, self._seq),
                                    FollowJointTrajectory_SendGoal_Request(UUID(uuid), goal)))

    def request_result(self, handle: GoalHandle) -> None:
        """Ask for the goal's result (the reply comes when it ends)."""
        with self._lock:
            self._seq += 1
            self._requests[(self._result_id, self._seq)] = handle
            self._result_w.write(wrap(FollowJointTrajectory_GetResult_Request,
                                      RequestHeader(self._result_id, self._seq),
                                      FollowJointTrajectory_GetResult_Request(UUID(handle.uuid))))

    def cancel(self, handle: GoalHandle | None) -> None:
        """Cancel one goal (its id), or every goal of the controller (None: a zero id and stamp). Thread-safe."""
        info = GoalInfo() if handle is None else GoalInfo(UUID(handle.uuid), Time())
        with self._lock:
            if handle is not None:
                if handle._cancel_sent:
                    return
                handle._cancel_sent = True
            self._seq += 1
            cancel_id = int.from_bytes(self._cancel_w.guid.bytes[:8], "little")
            self._cancel_w.write(wrap(CancelGoal_Request, RequestHeader(cancel_id, self._seq),
                                      CancelGoal_Request(info)))
            self.cancels += 1

    def released(self, handle: GoalHandle, drain: float = 0.0) -> None:
        """The motion layer let go of ``handle``; without a result yet it drains for ``drain`` s (:meth:`draining`)."""
        if handle in self.active:
            self.active.remove(handle)
        if handle.result is not None:
            self._goals.pop(handle.uuid, None)
        elif drain > 0.0 and handle.accepted is not False and handle._message is None:
            self._draining[handle] = time.monotonic() + drain

    def draining(self) -> bool:
        """True while a released goal may still run on the controller (cancelled, its result not back yet)."""
        if not self._draining:
            return False
        now = time.monotonic()
        for handle, until in list(self._draining.items()):
            if handle.result is not None or now > until:
                del self._draining[handle]
        return bool(self._draining)

    # replies (event loop) ----------------------------------------------------------------
    def _take_request(self, header: RequestHeader) -> GoalHandle | None:
        with self._lock:
            return self._requests.pop((header.guid, header.seq), None)

    def _on_send_reply(self, sample: Any) -> None:
        handle = self._take_request(sample.request_header)
        if handle is not None:
            handle._on_accepted(bool(sample.accepted))

    def _on_result_reply(self, sample: Any) -> None:
        handle = self._take_request(sample.request_header)
        if handle is None:
            return
        handle._on_result(int(sample.status), int(sample.result.error_code), str(sample.result.error_string))
        self._draining.pop(handle, None)
        if handle.released:
            self._goals.pop(handle.uuid, None)

    def _on_cancel_reply(self, sample: Any) -> None:
        log.debug("ros2: cancel_goal answered %d", sample.return_code)

    def _on_feedback(self, msg: FollowJointTrajectory_FeedbackMessage) -> None:
        handle = self._goals.get(bytes(msg.goal_id.uuid))
        if handle is not None and handle.result is None:
            fb = msg.feedback
            handle._on_feedback(list(fb.joint_names), fb.desired)


def _is_cyclone_service(writer: Any, handle: Any) -> bool:
    """The matched reader is a service endpoint in rmw_cyclonedds' format (``serviceid=`` user data)."""
    try:
        data = writer.get_matched_subscription_data(handle)
    except Exception:  # the reader went away meanwhile
        return False
    if data is None:
        return False
    for policy in data.qos:
        if isinstance(policy, Policy.Userdata) and bytes(policy.data).startswith(b"serviceid="):
            return True
    return False
