"""CAN motor-bus backend: MIT mini-cheetah protocol motors over python-can.

One bus cycle per control period: one command frame per motor, then the
replies are gathered until a deadline (``reply_deadline`` of the period). On socketcan the
event loop watches the bus socket itself (``loop.add_reader``) and drains every
queued frame with one ``recvmmsg`` per wake-up, and a cycle's commands go out
with one non-blocking ``sendmmsg`` (:mod:`.rawsock`: python-can's per-frame ``select``, interface
name lookup and clock reads were most of the host's CPU per cycle where system
calls are expensive, e.g. user-mode Linux); other interfaces use python-can's
:class:`can.Notifier` (a reader thread on buses without a file descriptor, e.g.
``virtual``). Only the latest reply per motor is kept (no unbounded queue).
Missing or late replies are counted per motor (:attr:`CanBackend.stats`); ``max_missed_replies`` consecutive misses or a
motor error code (over-temperature...) end in a :class:`BackendFault` naming the
motor, which the safety layer turns into FAULT with every motor disabled.
Replies naming a motor id we never addressed are counted
(:attr:`CanBackend.unexpected_replies`) and named in the fault of the motor
that went missing meanwhile (a wrong CAN id shows up that way).

MIT replies carry no sequence number, so a reply belongs to the current cycle
only if it reached the bus after this cycle's commands were sent (the frame's
receive timestamp, when the interface's timestamps are on the host's wall
clock as on socketcan and virtual; else its arrival time) and before the
cycle's deadline. Any other reply is counted ``late``: its data still updates
the state, but the motor counts as missed for that cycle. (A reply delayed by
more than a whole period cannot be told apart from a prompt one.)

Open enables each motor and checks its reply; a silent motor fails the open
with an error naming its id and joint, and the motors already enabled are
disabled again. Close disables every motor, even when cancelled (its blocking
part, joining python-can's reader thread and shutting the driver down, runs in a
worker thread). Zeroing is never automatic (``await robot.backend.set_zero(joint)``
is explicit) and needs the joint's torque off.

The emergency-stop hook (called by the safety layer's stall watchdog *thread*)
sends the disable frames itself, on a second bus handle, without the event loop.

Joint <-> motor mapping (robot.yaml ``backends.can.motors``)::

    q_motor = direction * gear_ratio * q_joint + zero_offset
    tau_motor = direction * tau_joint / gear_ratio,   kp_motor = kp / gear_ratio**2

Gravity compensation (``tau_model`` of the servo law, robot.yaml ``gravity_compensation``): the
motors run the PD law in firmware, so the host computes ``g(q)`` at the last measured position
from the description's rigid-body model (:class:`agentsdk.dynamics.DynamicsModel`, a MuJoCo model
compiled from the same description) once per cycle and adds it to the MIT torque feed-forward,
which the encoder clamps to the motor's torque range. ``CanBackend.gravity_torque`` is the
last value sent (joint side). Likewise the inverse dynamics of the desired motion (robot.yaml
``inverse_dynamics``, :mod:`agentsdk.feedforward`, from the same host model, the URDF friction
as dry Coulomb friction): ``CanBackend.motion_torque``, 0 at rest.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np
from pydantic import Field

from agentsdk.backend import Backend, Capabilities, JointReading, SetpointView
from agentsdk.errors import (
    BackendFault,
    BackendStartError,
    BusConflict,
    CommandRejected,
    ConfigurationError,
    UnknownJointError,
)
from agentsdk.feedforward import InverseDynamicsTerm
from agentsdk.sensors import SensorChannel, SensorSpec
from agentsdk.threads import run_blocking
from agentsdk.types import MODES

from .claims import Claim, claim
from .config import CanBusConfig
from .mit import DISABLE, ENABLE, ZERO, encode_command_into, is_special, reply_error_code, reply_state
from .rawsock import FrameReader, FrameWriter, frame_reader, frame_writer

__all__ = ["CanBackend", "CanController", "CanOptions", "MotorStats"]

log = logging.getLogger("agentsdk.can")

#: receive poll interval (s) of python-can's reader thread on buses without a file descriptor
_RX_POLL = 0.05
#: the enable frame is resent this often while a motor has not answered it (``open_timeout`` bounds the whole wait)
_ENABLE_RETRY = 0.2
#: SocketCAN's flag bits in a can_id: extended (29-bit) id, remote request, error frame
_EFF_FLAG, _RTR_FLAG, _ERR_FLAG = 0x80000000, 0x40000000, 0x20000000
#: how long a motor may take to answer after a zero frame (CubeMars pauses ~1 s)
_ZERO_TIMEOUT = 2.0
#: bus cycles with a reply a zero frame waits for before the state is taken to be in the new frame
_SETTLE_CYCLES = 3
#: a motor that answered this many more frames than were sent to it has a second responder
_SURPLUS_LIMIT = 3
#: the reply deficit (lost replies) is remembered down to -max(this, 2 x max_missed_replies), so that
#: losses cannot mask a second responder for long, while replies still in flight (late: a starved
#: motor side answers a backlog in a burst) stay within it (more than max_missed_replies consecutive
#: cycles without a reply is a lost motor anyway)
_SURPLUS_FLOOR = 20


def _deadline(fut: asyncio.Future[bool]) -> None:
    """The reply deadline of a cycle passed (an event loop timer).

    asyncio's timers are only ~1 ms precise on Linux (epoll rounds its timeout up to
    whole milliseconds), so a cycle with a missing reply may run up to ~1 ms past its
    deadline. Spinning on the loop for the last part (as RealtimeClock does) would
    make that precise, but it was measured to starve a motor emulator sharing the CPU
    (one-vCPU VM: 23 % of replies missed at 640 Hz with it, 0.1 % without).
    """
    if not fut.done():
        fut.set_result(False)


class CanOptions(CanBusConfig):
    """robot.yaml ``backends.can`` plus runtime options (all overridable in ``connect``)."""

    #: override robot.yaml ``gravity_compensation`` for every joint (None: robot.yaml); off for a plant
    #: without gravity (the free-motor emulator)
    gravity_compensation: bool | None = None
    #: override robot.yaml ``inverse_dynamics`` (the desired motion's inverse dynamics, from the host model)
    inverse_dynamics: bool | None = None
    #: fraction of the control period to wait for replies each cycle
    reply_deadline: float = Field(default=0.8, gt=0.0, le=1.0)
    #: consecutive cycles without a reply before a motor is declared lost (-> FAULT)
    max_missed_replies: int = Field(default=5, ge=1, le=1000)
    #: seconds to wait for each motor's reply to the enable frame at open, resent every 0.2 s (and to special frames)
    open_timeout: float = Field(default=0.2, gt=0.0, le=10.0)
    #: extra keyword arguments for ``can.Bus`` (e.g. ``receive_own_messages``)
    bus_kwargs: dict[str, Any] = Field(default_factory=dict)


def _robots_with_can() -> list[str]:
    """The shipped robots whose robot.yaml has a ``backends.can`` section."""
    from agentsdk.config import load_robot_config
    from agentsdk.description import list_robots
    from agentsdk.robots import ROBOTS_DIR

    out = []
    for name in list_robots(ROBOTS_DIR):
        try:
            if "can" in load_robot_config(ROBOTS_DIR / name / "robot.yaml").backends:
                out.append(name)
        except ConfigurationError:
            continue
    return out


@dataclass
class MotorStats:
    """Per-motor bus statistics (exposed as ``robot.backend.stats``)."""

    joint: str
    motor_id: int
    commands: int = 0
    replies: int = 0
    missed: int = 0
    consecutive_missed: int = 0
    #: replies that came after their cycle's deadline (or answered an earlier command)
    late: int = 0
    #: late replies during the current run of missed cycles
    consecutive_late: int = 0
    last_error: str | None = None
    temperature: float | None = None
    last_reply_time: float = field(default=0.0)
    #: frames addressed to this motor that this robot did not send (another controller on the bus)
    foreign_commands: int = 0
    #: replies beyond the frames sent to it (a second device answering with this id), net of lost ones
    surplus_replies: int = 0


class CanBackend(Backend):
    """Motors on a CAN bus speaking the MIT mini-cheetah protocol (python-can).

    One request and one reply per motor per control tick.
    """

    name = "can"
    capabilities = Capabilities(modes=frozenset(MODES), lockstep=False, realtime=True, standalone=False)
    options_model = CanOptions
    #: the motors' reported temperatures (when the vendor profile carries one); their torque estimate
    #: is every backend's ``joint_effort`` sensor
    sensor_kinds = frozenset({"temperature"})
    #: the desired motion's inverse dynamics (robot.yaml ``inverse_dynamics``), built at open
    _inverse: InverseDynamicsTerm | None = None

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        opts: CanOptions = self.options
        missing = [j.name for j in self.joints if j.name not in opts.motors]
        unknown = [n for n in opts.motors if n not in self.index]
        if missing or unknown:
            from agentsdk.config import did_you_mean

            label = self.config.label
            lines = [f"{label}: backends.can.motors: no motor for joint {n!r}" for n in missing]
            lines += [
                f"{label}: backends.can.motors.{n}: unknown joint{did_you_mean(n, self.names)}" for n in unknown
            ]
            raise ConfigurationError("\n".join(lines))
        self._motors = [opts.motors[j.name] for j in self.joints]
        self._ranges = [m.motor_ranges for m in self._motors]
        self._profile = opts.vendor_profile
        # joint <-> motor maps as Python floats: the cycle encodes and decodes a few motors one by one
        self._dir = [float(m.direction) for m in self._motors]
        self._gear = [float(m.gear_ratio) for m in self._motors]
        self._zero = [float(m.zero_offset) for m in self._motors]
        mask = self._profile.id_mask
        self._id_mask = mask
        self._by_reply_id = {m.id & mask: k for k, m in enumerate(self._motors)}
        self.stats = [MotorStats(j.name, m.id) for j, m in zip(self.joints, self._motors, strict=True)]
        self.unexpected_replies = 0
        n = len(self.joints)
        self._n = n
        # the newest reply per motor: python-can's own data bytearray (decoded when read), its fault code
        self._rx: list[bytes | bytearray | None] = [None] * n
        self._err: list[int] = [0] * n
        profile = self._profile
        self._accepted_dlcs = profile.accepted_dlcs
        self._temp_offset = None if profile.byte6 == "none" else profile.temperature_offset
        # the joint-frame state of the newest replies (what _read returns)
        self._q = np.zeros(n)
        self._v = np.zeros(n)
        self._tau = np.zeros(n)
        #: which motors answered this cycle's command (plain lists: touched per frame)
        self._got: list[bool] = [False] * n
        self._none_got: list[bool] = [False] * n
        self._n_got = 0
        #: resolved (True) when every motor answered this cycle's command, (False) at the reply deadline
        self._all_in: asyncio.Future[bool] | None = None
        #: socketcan: the bus's raw socket, read in batches (None: python-can's Notifier receives)
        self._reader: FrameReader | None = None
        self._writer: FrameWriter | None = None
        self._bus: can.BusABC | None = None
        self._estop_bus: can.BusABC | None = None
        self._estop_lock = threading.Lock()
        self._notifier: can.Notifier | None = None
        self._msgs = [
            can.Message(arbitration_id=m.id, data=bytes(8), is_extended_id=False) for m in self._motors
        ]
        self._loop: asyncio.AbstractEventLoop | None = None
        self._fault_msg: str | None = None
        #: the reply window of the current cycle: open from the first send to the deadline
        self._window_open = False
        self._window_start = 0.0  # time.time() just before the cycle's first send
        self._cycling = False  # the control loop has started its bus cycles
        #: when each motor's newest reply reached the bus (time.time())
        self._reply_stamp: list[float] = [0.0] * n
        #: when the reply whose data ``_rx`` holds reached the bus (time.time()), and its age at read
        self._rx_stamp: list[float] = [0.0] * n
        self._age = np.zeros(n)
        #: a special frame to this motor awaits its reply (not a late command reply)
        self._special_wait: list[bool] = [False] * n
        #: the replies' receive timestamps are on this host's wall clock (socketcan, virtual): used as
        #: they are, no clock read per frame; checked on the enable replies at open and every cycle
        self._host_stamps = False
        self._stamps_seen = 0
        self._stamps_bad = 0
        #: time.time() - time.monotonic(), for MotorStats.last_reply_time from a wall-clock stamp
        self._clock_offset = time.time() - time.monotonic()
        #: the same offset read at the start of the current bus cycle (None before the first): reading_age
        self._wall_minus_mono: float | None = None
        #: unknown ids seen in reply byte 0 since the last fault check (id -> count)
        self._unexpected_ids: dict[int, int] = {}
        #: the emergency bus handle has no file descriptor (virtual): drain its rx queue each cycle
        self._drain_estop = False
        #: the receive side runs in python-can's reader thread (buses without a file descriptor)
        self._threaded_rx = False
        #: torque on per joint, as the last setpoint written (set_zero needs it off)
        self._torque = np.zeros(n, dtype=bool)
        # ---- one controller per bus and per motor (claims.py in-process, the wire for the rest)
        self._claim: Claim | None = None
        self._master_id = opts.master_id
        self._by_motor_id = {m.id: k for k, m in enumerate(self._motors)}
        self._motor_ids = [m.id for m in self._motors]
        #: our own frames come back on the main handle (bus_kwargs receive_own_messages): count them
        self._own_echo = bool(opts.bus_kwargs.get("receive_own_messages"))
        self._echo_pending = [0] * n
        #: DISABLE frames sent on the emergency handle (any thread, under _estop_lock) and their
        #: echoes seen on the main handle (the loop): a DISABLE beyond those came from someone else
        self._estop_sent = [0] * n
        self._estop_seen = [0] * n
        #: special frames sent on the main handle (each one is answered, like a command)
        self._specials = [0] * n
        #: per motor: replies minus frames sent, since the last check (floored, see _check_surplus)
        self._replies_seen = [0] * n
        self._expected_seen = [0] * n
        self._surplus = [0] * n
        self._surplus_floor = -max(_SURPLUS_FLOOR, 2 * opts.max_missed_replies)
        #: a frame for one of our motors that we did not send was seen (raised by the next cycle)
        self._foreign_seen = False

    def joint_source(self, index: int) -> str | None:
        """The motor that measures joint ``index``: ``"motor id 2 on socketcan:vcan0"``."""
        opts: CanOptions = self.options
        return f"motor id {self._motors[index].id} on {opts.interface}:{opts.channel}"

    def _validate_options(self, options: dict[str, Any], given: frozenset[str] = frozenset()) -> Any:
        if "motors" not in options:
            # the usual mistake: a robot without a CAN section (e.g. `--backend can` with arm3)
            with_can = _robots_with_can()
            raise ConfigurationError(
                f"{self.config.label}: robot {self.description.name!r} has no backends.can section: the CAN backend "
                f"needs backends.can.motors, a motor (id, model) for each joint ({', '.join(self.names)})"
                + (f"; shipped robots with one: {', '.join(with_can)}" if with_can else "")
            )
        return super()._validate_options(options, given)

    # ------------------------------------------------------------ open/close
    def _make_bus(self) -> can.BusABC:
        opts: CanOptions = self.options
        kwargs: dict[str, Any] = {"interface": opts.interface, "channel": opts.channel, **opts.bus_kwargs}
        if opts.interface not in ("virtual", "socketcan"):
            kwargs.setdefault("bitrate", opts.bitrate)
        return can.Bus(**kwargs)

    async def _open(self) -> None:
        opts: CanOptions = self.options
        # one controller per motor within this process: refused before anything touches the bus
        self._claim = claim(
            opts.interface, opts.channel, [m.id for m in self._motors], owner=f"robot {self.description.name!r}"
        )
        # tau_model: g(q) from the description's model, for the joints with gravity compensation
        self._gc_mask = self.gravity_compensation.astype(float)
        self._gc_model = None
        self._inverse = None
        #: the desired motion's inverse dynamics (joint side, N·m) added to the last command's feed-forward
        self.motion_torque = np.zeros(len(self.joints))
        self._eff = np.zeros(len(self.joints))
        if self._gc_mask.any() or self.inverse_dynamics:  # compiling the model is blocking work: not on the loop
            model = await run_blocking(lambda: self.dynamics, name="agentsdk-can-dynamics")
            self._gc_model = model if self._gc_mask.any() else None
            if self.inverse_dynamics:  # + M(q) a_des + C(q, v_des) v_des from the host model
                self._inverse = InverseDynamicsTerm(model.model, self.names)
        #: the gravity torque (joint side, N·m) added to the last command's feed-forward
        self.gravity_torque = np.zeros(len(self.joints))
        try:
            self._bus = self._make_bus()
            self._estop_bus = self._make_bus()
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            from .hints import bus_open_hint

            hint = bus_open_hint(opts.interface, opts.channel, exc)
            raise BackendStartError(
                f"cannot open CAN bus interface={opts.interface!r} channel={opts.channel!r}: {exc}"
                + (f"; {hint}" if hint else "")
            ) from exc
        # the replies, and frames addressed to our motors: on SocketCAN a socket does not receive its
        # own frames (CAN_RAW_RECV_OWN_MSGS is off by default) while every other socket and node on the
        # bus does, so a frame for our motor ids here was sent by another controller (or is our
        # emergency handle's DISABLE, counted in _estop_sent); python-can's virtual bus behaves alike
        filters: list[can.typechecking.CanFilter] = [
            {"can_id": i, "can_mask": 0x7FF, "extended": False} for i in (opts.master_id, *self._motor_ids)
        ]
        self._bus.set_filters(filters)
        try:
            self._bus.fileno()
        except NotImplementedError:
            self._threaded_rx = True
        try:
            self._estop_bus.fileno()
        except NotImplementedError:
            # The emergency handle only sends. A kernel filter keeps a socket's rx buffer
            # empty, but a bus without a file descriptor (python-can's virtual) queues every
            # frame of the channel in an unbounded queue: drain it on every cycle instead.
            self._drain_estop = True
        else:
            self._estop_bus.set_filters([{"can_id": 0x7FF, "can_mask": 0x7FF, "extended": False}])
        self._loop = asyncio.get_running_loop()
        self._any_reply = asyncio.Event()
        reader = frame_reader(self._bus, self._on_raw) if opts.interface == "socketcan" else None
        if reader is not None:  # batched receive and sends on the bus's own socket (see rawsock)
            self._writer = frame_writer(self._bus, self._motor_ids)
            self._reader = reader
            self._loop.add_reader(reader.fd, self._on_readable)
        else:
            # a reader thread (buses without a file descriptor) polls at this interval: it ends that fast on close
            self._notifier = can.Notifier(self._bus, [self._on_frame], timeout=_RX_POLL, loop=self._loop)
        enabled: list[int] = []
        try:
            for k, m in enumerate(self._motors):
                if not await self._enable_motor(k, opts.open_timeout):
                    raise BackendStartError(
                        f"motor id {m.id} (joint {self.names[k]!r}) did not answer the enable frame within "
                        f"{opts.open_timeout:g} s on {opts.interface}:{opts.channel}; "
                        "check power, wiring, CAN id and bit rate"
                    )
                enabled.append(k)
                if self._rx[k] is not None and self._err[k]:
                    raise BackendStartError(
                        f"motor id {m.id} (joint {self.names[k]!r}) reports error "
                        f"{self._profile.error_name(self._err[k])}"
                    )
        except BaseException:
            self._disable_all()
            raise
        self._host_stamps = self._stamps_seen > 0 and self._stamps_bad == 0
        self._clock_offset = time.time() - time.monotonic()
        self._fill_state()
        if self._foreign_seen:
            self._disable_all()
            raise BusConflict(self._foreign_message())

    async def _enable_motor(self, k: int, wait: float) -> bool:
        """Send motor ``k`` the enable frame until it answers, for at most ``wait`` seconds.

        Resent every :data:`_ENABLE_RETRY` s: a frame sent before a motor (or its emulator) was
        listening is gone, so a longer ``open_timeout`` also covers a drive that powers up late.
        """
        deadline = time.monotonic() + wait
        while True:
            remaining = deadline - time.monotonic()
            if await self._special_and_wait(k, ENABLE, max(1e-3, min(_ENABLE_RETRY, remaining))):
                return True
            if remaining <= _ENABLE_RETRY:
                return False

    async def _special_and_wait(self, k: int, frame: bytes, wait: float, *, next_cycle: bool = False) -> bool:
        """Send a special frame to motor ``k`` and wait for a reply from it that left after it.

        Also used while the control loop runs (enable after an e-stop, set_zero): it leaves the
        cycle's reply window alone (with the loop's commands in flight, a reply from the motor
        after this frame is all the protocol can tell).
        """
        bus = self._bus
        assert bus is not None
        msg = can.Message(arbitration_id=self._motors[k].id, data=frame, is_extended_id=False)
        self._special_wait[k] = True
        try:
            async with asyncio.timeout(wait):
                while True:  # never block the event loop on a full transmit queue: retry
                    sent = time.time()  # before the send: the reply can be stamped before send() returns
                    self._any_reply.clear()
                    self._specials[k] += 1  # counted before the send: its reply may come first
                    self._echo_pending[k] += self._own_echo
                    try:
                        bus.send(msg, timeout=0.0)
                        break
                    except can.CanOperationError:
                        self._specials[k] -= 1
                        self._echo_pending[k] -= self._own_echo
                        await asyncio.sleep(self.period)
                while self._reply_stamp[k] < sent:
                    await self._any_reply.wait()
                    self._any_reply.clear()
                # The motor handles frames in order, so a reply to a command sent after this frame
                # reflects it; the first reply after it may answer an earlier command. Replies carry
                # no sequence number: wait for this motor's reply in several cycles started after it.
                cycles: set[float] = set()
                while next_cycle and len(cycles) < _SETTLE_CYCLES:
                    await self._any_reply.wait()
                    self._any_reply.clear()
                    if self._window_start > sent and self._got[k]:
                        cycles.add(self._window_start)
        except TimeoutError:
            return False
        finally:
            self._special_wait[k] = False
        return True

    def _disable_all(self) -> None:
        """Send DISABLE to every motor on the emergency bus handle (any thread, no event loop)."""
        bus = self._estop_bus or self._bus
        if bus is None:
            return
        # a frame on the emergency handle reaches the main handle like another node's: count it first
        echo = [1 if bus is self._estop_bus else int(self._own_echo)] * self._n
        with self._estop_lock:
            for k, m in enumerate(self._motors):
                self._estop_sent[k] += echo[k]
                try:
                    bus.send(can.Message(arbitration_id=m.id, data=DISABLE, is_extended_id=False), timeout=0.01)
                except (can.CanError, OSError) as exc:
                    self._estop_sent[k] -= echo[k]
                    log.error("could not send DISABLE to motor %d: %s", m.id, exc)

    async def _close(self) -> None:
        try:
            reader, self._reader = self._reader, None
            self._writer = None
            if reader is not None and self._loop is not None and not self._loop.is_closed():
                self._loop.remove_reader(reader.fd)
            notifier, self._notifier = self._notifier, None
            if notifier is not None and not self._threaded_rx:
                notifier.stop(timeout=0.0)  # removes the loop's fd reader; nothing to join (must run on the loop)
                notifier = None
            # disable frames, joining a reader thread, shutting drivers down: blocking, so off the event loop
            await run_blocking(self._release, notifier, name="agentsdk-can-close")
        finally:
            held, self._claim = self._claim, None
            if held is not None:
                held.release()

    def _release(self, notifier: can.Notifier | None) -> None:
        self._disable_all()
        if notifier is not None:
            notifier.stop(timeout=10 * _RX_POLL)  # joins the reader thread (it polls every _RX_POLL)
        for bus in (self._bus, self._estop_bus):
            if bus is not None:
                bus.shutdown()
        self._bus = self._estop_bus = None

    async def _enable(self) -> None:
        """Enter motor mode again after an e-stop (explicit robot.enable())."""
        opts: CanOptions = self.options
        for k, m in enumerate(self._motors):
            if not await self._enable_motor(k, opts.open_timeout):
                raise BackendFault(f"motor id {m.id} (joint {self.names[k]!r}) did not answer the enable frame")
        self._fill_state()

    async def _recover(self) -> None:
        """After a fault: clear counters and re-enable (the safety layer keeps torque off until enable())."""
        for s in self.stats:
            s.consecutive_missed = s.consecutive_late = 0
            s.last_error = None
        self._fault_msg = None
        self._unexpected_ids.clear()
        self._foreign_seen = False
        self._surplus[:] = [0] * self._n
        # the cycles stopped at the fault: its last cycle's replies (the error among them) are no longer
        # this cycle's, so the replies to the enable frames below replace them (a reply that arrives after
        # a cycle's own is kept out of that cycle's data, and the stale error code latched the fault again
        # at the next cycle whenever a motor's reply there came late)
        self._got[:] = self._none_got
        self._err[:] = [0] * self._n
        await self._enable()

    async def set_zero(self, joint: str) -> None:
        """Set the motor's current position as its zero: explicit, never automatic, and only with its torque off.

        Zeroing changes the frame the position setpoint is expressed in: a motor
        holding a position would jump to its old target in the new frame. So the
        joint's torque must be off (``await robot.estop(0)``; then ``reset()``,
        ``set_zero(...)``, ``enable()``, which holds the new position), else
        :class:`CommandRejected` is raised and nothing is sent. After the zero the
        joint reads ``-direction * zero_offset / gear_ratio`` (0 with the default mapping).
        """
        k = self.index.get(joint)
        if k is None:
            raise UnknownJointError(f"unknown joint {joint!r}; this robot's joints are: {', '.join(self.names)}")
        if self._torque[k]:
            raise CommandRejected(
                f"set_zero({joint!r}) refused: motor id {self._motors[k].id} has torque on, and zeroing would make it "
                "jump to its old target in the new frame; remove torque first (await robot.estop(0), "
                "await robot.reset()), zero, then await robot.enable()"
            )
        # (CubeMars motors ignore frames for ~1 s after a zero frame: those cycles are not counted as missed)
        with self.frame_change(k):  # the jump to the new zero is not a sensor fault
            if not await self._special_and_wait(k, ZERO, _ZERO_TIMEOUT, next_cycle=self._cycling):
                raise BackendFault(f"motor of joint {joint!r} did not acknowledge the zero frame")

    # ----------------------------------------------------------- receiving
    def _on_readable(self) -> None:
        """The bus socket is readable (event loop reader, socketcan): drain it, one system call per batch."""
        reader = self._reader
        if reader is None:
            return
        try:
            reader.drain()
        except OSError as exc:  # the interface went down...: stop watching, the next cycle faults
            if self._loop is not None:
                self._loop.remove_reader(reader.fd)
            self._reader = None
            opts: CanOptions = self.options
            self._fault_msg = f"CAN receive failed on {opts.interface}:{opts.channel}: {exc}"
            log.error("%s", self._fault_msg)

    def _on_frame(self, msg: can.Message) -> None:
        """Notifier callback; python-can calls it on the event loop (add_reader, or
        call_soon_threadsafe from its reader thread on buses without a file descriptor).
        """
        can_id = msg.arbitration_id
        if msg.is_extended_id:
            can_id |= _EFF_FLAG
        if msg.is_remote_frame:
            can_id |= _RTR_FLAG
        if msg.is_error_frame:
            can_id |= _ERR_FLAG
        self._on_raw(can_id, msg.data, msg.timestamp)

    def _on_raw(self, can_id: int, data: bytes | bytearray, stamp: float) -> None:
        """One received frame: ``can_id`` with its EFF/RTR/ERR flag bits, ``stamp`` its receive time
        (wall clock; 0.0 when the interface gave none).

        Per frame: no decoding (the newest data is kept and decoded once per cycle in
        ``read``), no Python objects beyond the data bytes, no clock read when the frame's
        receive timestamp is on this host's clock.
        """
        if can_id != self._master_id:  # (a flag bit set is never the master id)
            self._frame_for_a_motor(can_id, data)
            return
        if len(data) < 6:
            return
        k = self._by_reply_id.get(data[0] & self._id_mask)
        if k is None:
            self.unexpected_replies += 1
            ids = self._unexpected_ids
            if len(ids) < 16 or data[0] in ids:
                ids[data[0]] = ids.get(data[0], 0) + 1
            return
        if len(data) not in self._accepted_dlcs:  # malformed frame: count it, never crash the loop
            self.unexpected_replies += 1
            log.debug("reply with an unexpected DLC for profile %s: %s", self._profile.name, bytes(data).hex(" "))
            return
        st = self.stats[k]
        st.replies += 1
        if self._host_stamps:
            ts = stamp
            ws = self._window_start
            if not self._window_open or ws - 1.0 < ts < ws + 1.0:
                st.last_reply_time = ts - self._clock_offset
            else:  # the stamps left this host's clock: read the clock per frame from now on
                self._host_stamps = False
                ts = self._reply_time(stamp)
                st.last_reply_time = time.monotonic()
        else:
            ts = self._reply_time(stamp)
            st.last_reply_time = time.monotonic()
        temp = self._temp_offset
        if temp is not None and len(data) >= 7:
            st.temperature = data[6] + temp
        err = reply_error_code(data, self._profile)
        if err:
            st.last_error = self._profile.error_name(err)
        self._reply_stamp[k] = ts
        self._any_reply.set()
        got = self._got
        if not self._window_open or got[k] or ts < self._window_start:
            # after the deadline, a second reply in one cycle, or sent before this cycle's
            # command: it answers an earlier command. Newest data, but not this cycle's reply.
            if self._cycling and not self._special_wait[k]:
                st.late += 1
                st.consecutive_late += 1
            if not got[k]:
                self._rx[k] = data
                self._rx_stamp[k] = ts
                self._err[k] = err
            return
        self._rx[k] = data
        self._rx_stamp[k] = ts
        self._err[k] = err
        got[k] = True
        self._n_got += 1
        if self._n_got == self._n:
            fut = self._all_in
            if fut is not None and not fut.done():
                fut.set_result(True)

    def _frame_for_a_motor(self, can_id: int, data: bytes | bytearray) -> None:
        """A frame addressed to one of our motors reached our receive handle: ours, or a foreign commander's."""
        if can_id & (_EFF_FLAG | _ERR_FLAG):
            return
        k = self._by_motor_id.get(can_id & ~_RTR_FLAG)
        if k is None:
            return
        if data == DISABLE and self._estop_seen[k] < self._estop_sent[k]:
            self._estop_seen[k] += 1  # our emergency handle's
            return
        if self._echo_pending[k] > 0:
            self._echo_pending[k] -= 1  # our own frame (receive_own_messages)
            return
        self.stats[k].foreign_commands += 1
        if not self._foreign_seen:
            self._foreign_seen = True
            kind = is_special(bytes(data)) or "command"
            log.error("a %s frame for motor id %d that this robot did not send: %s", kind, can_id & ~_RTR_FLAG,
                      bytes(data).hex(" "))

    def _foreign_message(self) -> str:
        opts: CanOptions = self.options
        who = ", ".join(
            f"motor id {s.motor_id} (joint {s.joint!r}, {s.foreign_commands} frames)"
            for s in self.stats
            if s.foreign_commands
        )
        return (
            f"another controller commands {who} on {opts.interface}:{opts.channel}: frames this robot did not "
            "send; two controllers on one motor fight over it (stop the other one; motors disabled)"
        )

    def _check_surplus(self) -> None:
        """Once per cycle: a motor answering more frames than were sent to it has a second responder.

        One device answers each frame at most once, so per motor the replies never exceed the
        frames sent (commands, special frames, emergency DISABLEs), whatever their timing.
        Lost replies leave a deficit, remembered down to a floor (see :data:`_SURPLUS_FLOOR`)
        so that losses cannot hide a second responder for long.
        """
        floor = self._surplus_floor
        stats, surplus = self.stats, self._surplus
        specials, estop = self._specials, self._estop_sent
        r_seen, e_seen = self._replies_seen, self._expected_seen
        for k in range(self._n):
            s = stats[k]
            replies = s.replies
            expected = s.commands + specials[k] + estop[k]
            x = surplus[k] + (replies - r_seen[k]) - (expected - e_seen[k])
            r_seen[k] = replies
            e_seen[k] = expected
            if x < floor:
                x = floor
            surplus[k] = x
            if x >= _SURPLUS_LIMIT:
                s.surplus_replies = x
                opts: CanOptions = self.options
                raise BusConflict(
                    f"motor id {s.motor_id} (joint {s.joint!r}) on {opts.interface}:{opts.channel} answered {x} more "
                    f"frames than this robot sent it: a second device answers with id {s.motor_id} (a duplicate CAN "
                    "id), or another controller commands it (motors disabled)"
                )

    def _reply_time(self, ts: float) -> float:
        """When the reply reached the bus (wall clock): its timestamp ``ts`` if that is plausibly
        on our clock (socketcan, virtual), else now (interfaces with device timestamps).
        """
        now = time.time()
        if now - 1.0 < ts <= now + 0.001:
            self._stamps_seen += 1
            return ts
        self._stamps_bad += 1
        return now

    def _fill_state(self) -> None:
        rx, ranges = self._rx, self._ranges
        q, v, tau = self._q, self._v, self._tau
        for k in range(self._n):
            data = rx[k]
            if data is None:
                continue
            p, vel, t = reply_state(data, ranges[k])
            d, g = self._dir[k], self._gear[k]
            q[k] = d * (p - self._zero[k]) / g
            v[k] = d * vel / g
            tau[k] = d * t * g

    # ------------------------------------------------------------- the cycle
    def _write(self, sp: SetpointView) -> None:
        # encoded in place into the reused messages' data (no objects per frame)
        pos, vel = sp.position.tolist(), sp.velocity.tolist()
        ff = self._eff
        np.copyto(ff, sp.effort)
        if self._gc_model is not None:  # tau_model: g(q) at the last measured position (main's feedforward)
            gt = self._gc_model.gravity(self._q, self.gravity_torque)
            gt *= self._gc_mask
            ff += gt
        inverse = self._inverse
        if inverse is not None:  # + the desired motion's inverse dynamics at the desired position (host model)
            qpos = self.dynamics.qpos(sp.position)
            ff += inverse.compute(qpos, sp.velocity, sp.acceleration, self.motion_torque, sp.mode)
        eff = ff.tolist()
        kp, kd, en = sp.kp.tolist(), sp.kd.tolist(), sp.enabled.tolist()
        self._torque[...] = sp.enabled  # torque on per joint (set_zero needs it off)
        for k, msg in enumerate(self._msgs):
            d, g, r = self._dir[k], self._gear[k], self._ranges[k]
            p = d * g * pos[k] + self._zero[k]
            if en[k]:
                g2 = g * g
                encode_command_into(msg.data, p, d * g * vel[k], kp[k] / g2, kd[k] / g2, d * eff[k] / g, r,
                                    policy="clamp")
            else:  # limp: zero gains and torque (motor stays in motor mode, still replies)
                encode_command_into(msg.data, min(max(p, r.p_min), r.p_max), 0.0, 0.0, 0.0, 0.0, r, policy="clamp")

    async def _step(self, dt: float) -> None:
        bus, loop = self._bus, self._loop
        assert bus is not None and loop is not None
        if self._fault_msg is not None:
            raise BackendFault(self._fault_msg)
        if self._foreign_seen:
            raise BusConflict(self._foreign_message())
        if self._drain_estop:
            self._drain_estop_bus()
        self._cycling = True
        got = self._got
        got[:] = self._none_got
        self._n_got = 0
        stats = self.stats
        # the cycle's start on both clocks, back to back: the wall clock for the replies' receive
        # stamps, the monotonic clock (the event loop's: asyncio's loop.time()) for the reply deadline;
        # their difference converts the stamps to the tick's own clock read in reading_age (no read there)
        mono = time.monotonic()
        self._window_start = ws = time.time()
        self._wall_minus_mono = ws - mono
        self._window_open = True
        try:
            # the commands go out back to back, before any reply is handled (each counted before
            # its send: the reply may be handled first)
            own_echo = self._own_echo
            writer = self._writer
            for k, msg in enumerate(self._msgs):
                stats[k].commands += 1
                if own_echo:
                    self._echo_pending[k] += 1
                if writer is not None:
                    writer.set_data(k, msg.data)
                    continue
                try:
                    bus.send(msg, timeout=0.0)
                except can.CanOperationError as exc:  # TX buffer full: the bus is saturated
                    self._unsent(k)
                    raise BackendFault(f"CAN transmit failed for motor id {self._motors[k].id}: {exc}") from exc
            if writer is not None:  # socketcan: every command in one sendmmsg (see rawsock)
                sent, err = writer.send()
                if sent < self._n:
                    for k in range(sent, self._n):
                        self._unsent(k)
                    why = os.strerror(err) if err else "not queued"
                    raise BackendFault(f"CAN transmit failed for motor id {self._motors[sent].id}: {why}")
            # every reply or the deadline: a future and one timer handle (asyncio.timeout and an Event
            # cost a clock read and several running-loop look-ups, each a getpid() on Python 3.11)
            if self._n_got < self._n:
                fut: asyncio.Future[bool] = loop.create_future()
                self._all_in = fut
                timer = loop.call_at(mono + dt * self.options.reply_deadline, _deadline, fut)
                try:
                    if not await fut:
                        await asyncio.sleep(0)  # frames the loop already holds are still this cycle's
                finally:
                    timer.cancel()
                    self._all_in = None
        finally:
            self._window_open = False
        if self._foreign_seen:
            raise BusConflict(self._foreign_message())
        self._check_surplus()
        if self._n_got == self._n:
            for s in stats:
                s.consecutive_missed = s.consecutive_late = 0
            if self._unexpected_ids:
                self._unexpected_ids.clear()
        else:
            special = self._special_wait
            for k, s in enumerate(stats):
                if not got[k] and not special[k]:  # a special frame's pause is not a missed reply
                    s.missed += 1
                    s.consecutive_missed += 1
                    if s.consecutive_missed >= self.options.max_missed_replies:
                        raise BackendFault(self._missing_message(s, dt))
            for k, s in enumerate(stats):
                if got[k]:
                    s.consecutive_missed = s.consecutive_late = 0
        if any(self._err):  # this cycle's or a late reply: an error is an error
            for k, code in enumerate(self._err):
                if code and self._rx[k] is not None:
                    s = stats[k]
                    raise BackendFault(
                        f"motor id {s.motor_id} (joint {s.joint!r}) reports error: {self._profile.error_name(code)}"
                    )

    def _unsent(self, k: int) -> None:
        """Motor ``k``'s command was counted but not sent: take it back."""
        self.stats[k].commands -= 1
        if self._own_echo:
            self._echo_pending[k] -= 1

    def _missing_message(self, s: MotorStats, dt: float) -> str:
        where = f"motor id {s.motor_id} (joint {s.joint!r})"
        counts = f"({s.missed} missed, {s.late} late of {s.commands} commands)"
        if 2 * s.consecutive_late >= s.consecutive_missed:  # it mostly answers, but after the deadline
            window = dt * self.options.reply_deadline * 1e3
            return (
                f"{where} replies too late: none within the {window:.3g} ms reply deadline for "
                f"{s.consecutive_missed} consecutive cycles, {s.consecutive_late} came late {counts}"
            )
        hint = ""
        if self._unexpected_ids:
            ids = ", ".join(f"{i} ({n}x)" for i, n in sorted(self._unexpected_ids.items()))
            hint = f"; meanwhile replies named motor id(s) not in backends.can.motors: {ids} (wrong CAN id?)"
        return f"{where} lost: no reply for {s.consecutive_missed} consecutive cycles {counts}{hint}"

    def _drain_estop_bus(self) -> None:
        bus = self._estop_bus
        if bus is None:
            return
        try:
            for _ in range(4096):  # bounded: a flooding sender cannot keep the loop here
                if bus.recv(0.0) is None:
                    break
        except (can.CanError, OSError):
            pass

    def _read(self) -> JointReading:
        self._fill_state()
        return self._q, self._v, self._tau

    def _backend_sensors(self) -> tuple[SensorSpec, ...]:
        """``<joint>_temperature`` per motor when the vendor profile's replies carry a temperature byte."""
        if self._temp_offset is None or self._profile.reply_dlc < 7:
            return ()
        child = {j.name: j.child for j in self.description.all_joints}
        return tuple(
            SensorSpec(name=f"{j.name}_temperature", kind="temperature", link=child.get(j.name, j.name),
                       joint=j.name, source="backend")
            for j in self.joints
        )

    def _read_sensors(self, channels: Sequence[SensorChannel]) -> None:
        index, stats = self.index, self.stats
        for ch in channels:
            if ch.due and ch.spec.kind == "temperature":
                temp = stats[index[ch.spec.joint or ""]].temperature
                ch.values[0] = math.nan if temp is None else temp  # NaN until the motor first replied

    def reading_age(self, now: float | None = None) -> np.ndarray:
        """Seconds since each motor's newest reply (the data ``read`` returns) reached the bus.

        ``now`` (``time.monotonic()`` of the read, which the control tick has already read) is put
        on the replies' wall clock with this cycle's offset between the two clocks (both read at
        the cycle's start); None, or before the first cycle: the wall clock is read here.
        """
        offset = self._wall_minus_mono
        now = time.time() if now is None or offset is None else now + offset
        age = self._age
        for k, ts in enumerate(self._rx_stamp):
            a = now - ts
            age[k] = a if a > 0.0 else 0.0
        return age

    @property
    def stale(self) -> np.ndarray:
        """Joints whose state did not refresh in the last cycle."""
        return np.logical_not(self._got)

    def _emergency_stop(self, category: int) -> None:
        self._torque[:] = False
        self._disable_all()

#: the former name of :class:`CanBackend` (deprecated: import CanBackend)
CanController = CanBackend
