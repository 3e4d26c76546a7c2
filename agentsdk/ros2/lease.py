"""A dead-man between hosts: a served robot stops when the client commanding it disappears.

A client that commands a served robot over the network holds a **lease**: it publishes a
heartbeat (``std_msgs/Header``, ``frame_id`` = its client id, ``stamp`` = its wall time) on
``<namespace>/agentsdk/heartbeat`` at least every ``lease / 4`` seconds, with DDS liveliness
``AUTOMATIC`` and a lease duration no longer than the server's (:func:`heartbeat_qos`), and
says goodbye on ``<namespace>/agentsdk/release`` (``std_msgs/String``, its client id) when it
leaves on purpose. :class:`Heartbeat` does all of that.

The serving side (:class:`Deadman`, created by :func:`agentsdk.ros2.expose`):

* binds a command (a trajectory on the JTC topic, a FollowJointTrajectory goal, or a direct
  command of the ``ros2`` backend's ``agentsdk/command`` stream) to every
  client whose lease is alive when the command is accepted;
* when a bound client's lease lapses -- no heartbeat received within ``lease`` seconds of wall
  time, or DDS reports its heartbeat writer not alive (its participant's lease expired or the
  writer vanished without a release) -- it latches an e-stop of ``category`` (1 by default:
  a controlled stop to rest, then torque off) and records a ``deadman`` safety event. The
  robot accepts commands again only after a deliberate reset (the ``reset`` service, then
  ``enable``; or :meth:`Robot.reset` locally);
* a client that released its lease is unbound: leaving on purpose never stops the robot;
* with ``require_lease=True`` a command while no client holds a live lease is refused with
  :class:`LeaseRequired` (plain ROS tools that send no heartbeat cannot command then).

The lease runs in wall time (``time.monotonic`` on the serving host), also for a lockstep
robot: it measures the network and the client, not the simulation.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import time
import uuid
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from cyclonedds.core import Policy, Qos
from cyclonedds.util import duration

from ..errors import AgentSDKError, CommandRejected, InvalidValueError
from .dds import QOS_DEFAULT, DdsNode
from .msgs import Header, String, Time

if TYPE_CHECKING:
    from ..robot import Robot

__all__ = [
    "HEARTBEAT_TOPIC", "RELEASE_TOPIC", "Deadman", "Heartbeat", "LeaseRequired", "LeaseTable", "heartbeat_qos",
]

log = logging.getLogger(__name__)

#: the heartbeat topic, relative to the robot's namespace (``/arm1/agentsdk/heartbeat``)
HEARTBEAT_TOPIC = "agentsdk/heartbeat"
#: the release topic, relative to the robot's namespace: a client leaving on purpose
RELEASE_TOPIC = "agentsdk/release"


class LeaseRequired(CommandRejected):
    """A command reached a served robot that requires a lease, and no client held a live one."""


def check_lease(lease: float) -> float:
    """``lease`` as a float, or :class:`InvalidValueError` unless it is a positive finite number of seconds."""
    if isinstance(lease, bool) or not isinstance(lease, (int, float)) or not math.isfinite(lease) or lease <= 0:
        raise InvalidValueError(f"lease must be a positive number of seconds, got {lease!r}")
    return float(lease)


def heartbeat_qos(lease: float) -> Qos:
    """The heartbeat writer's QoS: best effort, keep last 1, liveliness AUTOMATIC with ``lease``.

    A client passes the server's lease (or a shorter one): DDS then reports the writer not
    alive as soon as its participant is silent for ``lease``.
    """
    ns = int(check_lease(lease) * 1e9)
    return Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(1),
               Policy.Liveliness.Automatic(lease_duration=ns))


#: the server's heartbeat reader: best effort, any offered liveliness lease matches
_READER_QOS = Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(1),
                  Policy.Liveliness.Automatic(lease_duration=duration(infinite=True)))


class LeaseTable:
    """Which clients hold a live lease and which of them the running commands are bound to.

    Pure bookkeeping with explicit times (seconds, any monotonic clock): :class:`Deadman`
    feeds it wall time, tests feed it simulated time.
    """

    def __init__(self, lease: float) -> None:
        self.lease = check_lease(lease)
        self._last: dict[str, float] = {}
        self._bound: set[str] = set()

    def beat(self, client: str, now: float) -> None:
        """A heartbeat of ``client`` arrived at ``now``."""
        self._last[client] = now

    def release(self, client: str) -> None:
        """``client`` left on purpose: forget it and unbind it."""
        self._last.pop(client, None)
        self._bound.discard(client)

    def live(self, now: float) -> set[str]:
        """Clients whose last heartbeat is at most ``lease`` old."""
        return {c for c, t in self._last.items() if now - t <= self.lease}

    def bind(self, now: float) -> set[str]:
        """A command was accepted at ``now``: bind it to every live client; returns them."""
        live = self.live(now)
        self._bound |= live
        return live

    @property
    def bound(self) -> frozenset[str]:
        """The clients whose disappearance stops the robot."""
        return frozenset(self._bound)

    def lapsed(self, now: float) -> list[str]:
        """Bound clients without a heartbeat for longer than ``lease`` (sorted)."""
        return sorted(c for c in self._bound if now - self._last.get(c, -math.inf) > self.lease)

    def lost(self, client: str) -> None:
        """DDS reports ``client``'s writer not alive: its lease has lapsed whatever its last beat."""
        if client in self._last:
            self._last[client] = -math.inf

    def clear(self) -> None:
        """Unbind every client (after the stop they triggered)."""
        self._bound.clear()


class Deadman:
    """The serving side of the lease (see the module documentation); owned by a ``RosFace``."""

    def __init__(self, robot: Robot, lease: float, category: int = 1, require_lease: bool = False,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if category not in (0, 1):
            raise InvalidValueError(f"dead-man stop category must be 0 or 1 (IEC 60204-1), got {category!r}")
        self.robot = robot
        self.table = LeaseTable(lease)
        self.lease = self.table.lease
        self.category = category
        self.require_lease = bool(require_lease)
        self._clock = clock
        self._reader: Any = None
        self._writers: dict[int, str] = {}
        #: how often a lapsed lease stopped the robot
        self.trips = 0
        #: the last trip's reason ("" before any)
        self.last_trip = ""
        #: wall time (epoch seconds) of the last trip (0.0 before any)
        self.tripped_at = 0.0

    def attach(self, node: DdsNode) -> None:
        """Subscribe the heartbeat and release topics on ``node`` (before it starts)."""
        self._reader = node.subscribe(HEARTBEAT_TOPIC, Header, self._on_beat, _READER_QOS)
        node.subscribe(RELEASE_TOPIC, String, self._on_release, QOS_DEFAULT)

    def _on_beat(self, msg: Header) -> None:
        client = msg.frame_id
        if not client:
            return
        info = getattr(msg, "sample_info", None)
        if info is not None:
            self._writers[int(info.publication_handle)] = client
        self.table.beat(client, self._clock())

    def _on_release(self, msg: String) -> None:
        if msg.data:
            self.table.release(msg.data)
            log.info("client %s released its lease", msg.data)

    def admit(self) -> None:
        """Before a command starts: :class:`LeaseRequired` when a lease is required and none is live."""
        if self.require_lease and not self.table.live(self._clock()):
            raise LeaseRequired(
                f"this robot requires a lease: publish heartbeats on {HEARTBEAT_TOPIC} at least every "
                f"{self.lease / 4:g} s (agentsdk.ros2.lease.Heartbeat) before commanding it")

    def accepted(self) -> None:
        """A command was accepted: bind it to the clients holding a live lease."""
        self.table.bind(self._clock())

    def _poll_liveliness(self) -> None:
        reader = self._reader
        if reader is None:
            return
        status = reader.get_liveliness_changed_status()
        if status.not_alive_count_change > 0 or status.alive_count_change < 0:
            # a writer we never heard a beat from holds no lease: the heartbeat timing covers the rest
            client = self._writers.pop(int(status.last_publication_handle), None)
            if client is not None:
                self.table.lost(client)

    def check(self) -> list[str]:
        """The bound clients whose lease lapsed now (and unbind them): the robot must stop."""
        self._poll_liveliness()
        lapsed = self.table.lapsed(self._clock())
        if lapsed:
            self.table.clear()
        return lapsed

    async def watch(self) -> None:
        """Check the leases every ``lease / 10`` s of wall time; stop the robot when one lapses."""
        period = self.lease / 10
        while True:
            await asyncio.sleep(period)
            if self.robot.closed:
                continue
            lapsed = self.check()
            if lapsed:
                await self._trip(lapsed)

    async def _trip(self, clients: list[str]) -> None:
        self.trips += 1
        self.tripped_at = time.time()
        self.last_trip = (f"lease of {', '.join(clients)} lapsed (no heartbeat within {self.lease:g} s): "
                          f"category {self.category} stop; reset to command again")
        log.warning("dead-man: %s", self.last_trip)
        self.robot.safety.record("deadman", self.last_trip)
        try:
            await self.robot.estop(self.category)
        except AgentSDKError as exc:  # the robot closed meanwhile: nothing left to stop; keep watching
            log.warning("dead-man: the stop failed: %s: %s", type(exc).__name__, exc)


class Heartbeat:
    """The client side of a lease: heartbeats on a :class:`DdsNode` until :meth:`aclose` releases it.

    ``async with Heartbeat(node, lease=1.0):`` -- ``lease`` is the served robot's lease (or
    shorter); heartbeats go out every ``lease / 5`` s from an asyncio task, so a client whose
    event loop stalls loses its lease just as one whose host or network goes away.
    """

    def __init__(self, node: DdsNode, lease: float, client_id: str | None = None) -> None:
        self.lease = check_lease(lease)
        self.client_id = client_id or f"{os.uname().nodename}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self._writer = node.writer(HEARTBEAT_TOPIC, Header, heartbeat_qos(self.lease))
        self._release = node.writer(RELEASE_TOPIC, String, QOS_DEFAULT)
        self._task: asyncio.Task[None] | None = None
        self._closed = False

    async def __aenter__(self) -> Heartbeat:
        self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    def beat(self) -> None:
        """Send one heartbeat now."""
        self._writer.write(Header(Time.from_seconds(time.time()), self.client_id))

    def start(self) -> None:
        """Start the heartbeat task (on the running event loop)."""
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run())

    async def _run(self) -> None:
        period = self.lease / 5
        while True:
            self.beat()
            await asyncio.sleep(period)

    async def aclose(self) -> None:
        """Stop the heartbeats and release the lease (idempotent): the server unbinds this client."""
        if self._closed:
            return
        self._closed = True
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            try:
                await task
            except asyncio.CancelledError:
                if (me := asyncio.current_task()) is not None and me.cancelling():
                    raise
        self._release.write(String(self.client_id))
