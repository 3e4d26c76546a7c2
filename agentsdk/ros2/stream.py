"""The serving side of the ``ros2`` backend's command stream: sequenced setpoints, lockstep steps, holds.

A served robot (:func:`agentsdk.ros2.expose`) reads, under its namespace:

* ``agentsdk/command`` (``sensor_msgs/JointState``, reliable): one direct position command
  per sample. ``header.frame_id`` is ``"<session>:<seq>"``: ``session`` names the client
  (16 hex digits, new on every connect), ``seq`` its command number (16 hex digits, strictly
  increasing). A sample whose ``seq`` is not above the last one applied for its session is
  dropped (counted in :attr:`CommandStream.dropped`): no command executes twice or out of
  order, whatever the network repeats or reorders. ``name``/``position`` are the setpoint,
  ``velocity`` and ``effort`` its optional feed-forward. No names: a *sync* (nothing is
  commanded; the reply carries the state). ``header.stamp`` non-zero (lockstep robots): after
  applying, the robot runs until that ROS stamp (robot time), so a client steps the remote
  robot exactly as a local simulator steps: write, step, read.

and answers a sync, a stepped command (non-zero stamp) and every refused command on
``agentsdk/state`` (``sensor_msgs/JointState`` of every joint, stamped with the robot time of the
state) with the same ``frame_id``, followed by ``" rejected: <reason>"`` when the robot refused the
command (e-stop latched, a limit...). An applied command with a zero stamp gets no answer (the
state is on ``joint_states``).

Commands are applied one at a time, in arrival order, by one task: ``robot.command``, the
same validation, limits and safety layer as in a behavior; the safety layer's command
watchdog holds the robot when the stream stops.

An empty ``joint_trajectory_controller/joint_trajectory`` (no points) means *hold*, as for
ros2_controllers' JTC: running trajectories and goals are cancelled (they decelerate and hold).
"""

from __future__ import annotations

import asyncio
import logging
import re
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Any, Protocol

from cyclonedds.core import Policy, Qos
from cyclonedds.util import duration

from ..errors import AgentSDKError
from ..types import JointCommand
from .dds import QOS_DEFAULT, DdsNode
from .msgs import Header, JointState

if TYPE_CHECKING:
    from ..robot import Robot
    from .lease import Deadman
    from .msgs import Time


class Face(Protocol):
    """What the command stream needs of the face that serves the robot (:class:`~agentsdk.ros2.server.RosFace`)."""

    robot: Robot
    deadman: Deadman | None

    def stamp(self, t: float) -> Time:
        """Robot time ``t`` as a message stamp."""
        ...

    def robot_time(self, stamp: Time) -> float:
        """A message stamp as robot time."""
        ...

__all__ = ["COMMAND_TOPIC", "QOS_STREAM", "STATE_TOPIC", "CommandStream", "Face", "parse_frame_id"]

log = logging.getLogger(__name__)

#: the command stream's topics, under the robot's namespace
COMMAND_TOPIC = "agentsdk/command"
STATE_TOPIC = "agentsdk/state"
#: reliable, volatile, keep last 100: a burst is queued, never silently thinned
QOS_STREAM = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.Durability.Volatile,
                 Policy.History.KeepLast(100))
_FRAME = re.compile(r"^([0-9a-f]{16}):([0-9a-f]{16})$")
_QUEUE = 1000


def parse_frame_id(frame_id: str) -> tuple[str, int] | None:
    """``(session, seq)`` of a command's ``frame_id``, or None when it is not one."""
    m = _FRAME.match(frame_id)
    if m is None:
        return None
    return m.group(1), int(m.group(2), 16)


class CommandStream:
    """The ``agentsdk/command`` reader and ``agentsdk/state`` writer of one served robot."""

    def __init__(self, face: Face) -> None:
        self.face = face
        self._last: dict[str, int] = {}
        self._queue: asyncio.Queue[tuple[str, JointState]] = asyncio.Queue(_QUEUE)
        self._reply: Any = None
        #: commands applied, and samples dropped (repeated, out of order, malformed, queue full)
        self.applied = 0
        self.dropped = 0

    def create(self, node: DdsNode) -> None:
        """Create the topics (in the face's setup thread)."""
        self._reply = node.writer(STATE_TOPIC, JointState, QOS_DEFAULT)
        node.subscribe(COMMAND_TOPIC, JointState, self._on_command, QOS_STREAM)

    def start(self, spawn: Callable[[Coroutine[Any, Any, None]], object]) -> None:
        """Start the task that applies the commands with ``spawn`` (the face's, which keeps and cancels it)."""
        spawn(self._work())

    def _on_command(self, msg: JointState) -> None:
        ident = parse_frame_id(msg.header.frame_id)
        if ident is None:
            self.dropped += 1
            log.warning("dropped an agentsdk/command sample with frame_id %r (expected '<session>:<seq>')",
                        msg.header.frame_id[:40])
            return
        session, seq = ident
        if seq <= self._last.get(session, -1):
            self.dropped += 1
            log.debug("dropped command %d of session %s: not after %d", seq, session, self._last[session])
            return
        try:
            self._queue.put_nowait((msg.header.frame_id, msg))
        except asyncio.QueueFull:
            self.dropped += 1
            log.warning("dropped command %d of session %s: %d commands queued", seq, session, _QUEUE)
            return
        self._last[session] = seq

    async def _work(self) -> None:
        while True:
            frame_id, msg = await self._queue.get()
            await self._apply(frame_id, msg)

    async def _apply(self, frame_id: str, msg: JointState) -> None:
        face, robot = self.face, self.face.robot
        if robot.closed:
            return
        error = ""
        stamp = msg.header.stamp
        try:
            if len(msg.name):
                names = list(msg.name)
                vel = list(msg.velocity) if len(msg.velocity) else None
                eff = list(msg.effort) if len(msg.effort) else None
                if face.deadman is not None:
                    face.deadman.admit()
                await robot.command(JointCommand(
                    "position", dict(zip(names, msg.position, strict=True)),
                    velocity=None if vel is None else dict(zip(names, vel, strict=True)),
                    effort=None if eff is None else dict(zip(names, eff, strict=True))))
                self.applied += 1
                if face.deadman is not None:
                    face.deadman.accepted()  # bound to the live leases: the client's silence stops the robot
            if (stamp.sec or stamp.nanosec) and robot.clock.lockstep:
                await robot.clock.sleep_until(face.robot_time(stamp))
        except (AgentSDKError, ValueError) as exc:  # ValueError: names and values of different lengths
            error = f" rejected: {type(exc).__name__}: {exc}"
        if robot.closed or (len(msg.name) and not (stamp.sec or stamp.nanosec) and not error):
            return  # a realtime command that was applied: the state goes out on joint_states
        st = robot.latest_state()
        self._reply.write(JointState(Header(face.stamp(st.stamp), frame_id + error), list(st.names),
                                     st.position.tolist(), st.velocity.tolist(), st.effort.tolist()))
