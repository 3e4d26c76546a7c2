"""CAN motor-bus backend: MIT mini-cheetah protocol motors over python-can.

One bus cycle per control period: one command frame per motor, then the
replies are gathered until a deadline (``reply_deadline`` of the period). The
receive side is python-can's :class:`can.Notifier` on the running event loop
(``loop.add_reader`` on socketcan's file descriptor; a reader thread on buses
without one, e.g. ``virtual``); only the latest reply per motor is kept (no
unbounded queue). Missing or late replies are counted per motor
(:attr:`CanController.stats`); ``max_missed_replies`` consecutive misses, a
motor error code (over-temperature...) or replies from a motor we never
addressed persisting end in a :class:`BackendFault` naming the motor, which the
safety layer turns into FAULT with every motor disabled.

Open enables each motor and checks its reply; a silent motor fails the open
with an error naming its id and joint, and the motors already enabled are
disabled again. Close disables every motor, even when cancelled. Zeroing is
never automatic (``await robot.controller.set_zero(joint)`` is explicit).

The emergency-stop hook (called by the safety layer's stall watchdog *thread*)
sends the disable frames itself, on a second bus handle, without the event loop.

Joint <-> motor mapping (robot.yaml ``backends.can.motors``)::

    q_motor = direction * gear_ratio * q_joint + zero_offset
    tau_motor = direction * tau_joint / gear_ratio,   kp_motor = kp / gear_ratio**2
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np
from pydantic import Field, PositiveFloat, PositiveInt

from agentsdk.controller import Capabilities, Controller, Setpoint, StateBuffer
from agentsdk.errors import BackendFault, BackendStartError, ConfigurationError
from agentsdk.types import MODES

from .config import CanBusConfig
from .mit import DISABLE, ENABLE, ZERO, decode_reply, encode_command

__all__ = ["CanController", "CanOptions", "MotorStats"]

log = logging.getLogger("agentsdk.can")


class CanOptions(CanBusConfig):
    """robot.yaml ``backends.can`` plus runtime options (all overridable in ``connect``)."""

    #: fraction of the control period to wait for replies each cycle
    reply_deadline: float = Field(default=0.8, gt=0.0, le=1.0)
    #: consecutive cycles without a reply before a motor is declared lost (-> FAULT)
    max_missed_replies: PositiveInt = 5
    #: seconds to wait for each motor's reply to the enable frame at open
    open_timeout: PositiveFloat = 0.2
    #: extra keyword arguments for ``can.Bus`` (e.g. ``receive_own_messages``)
    bus_kwargs: dict[str, Any] = Field(default_factory=dict)


@dataclass
class MotorStats:
    """Per-motor bus statistics (exposed as ``robot.controller.stats``)."""

    joint: str
    motor_id: int
    commands: int = 0
    replies: int = 0
    missed: int = 0
    consecutive_missed: int = 0
    late: int = 0
    last_error: str | None = None
    temperature: float | None = None
    last_reply_time: float = field(default=0.0)


class CanController(Controller):
    name = "can"
    capabilities = Capabilities(modes=frozenset(MODES), lockstep=False, realtime=True, torque_off=True)
    options_model = CanOptions

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        opts: CanOptions = self.options
        missing = [j.name for j in self.joints if j.name not in opts.motors]
        unknown = [n for n in opts.motors if n not in self.index]
        if missing or unknown:
            raise ConfigurationError(
                f"backends.can.motors must map every joint: missing {missing}, unknown {unknown}"
            )
        self._motors = [opts.motors[j.name] for j in self.joints]
        self._ranges = [m.motor_ranges for m in self._motors]
        self._profile = opts.vendor_profile
        self._dir = np.array([m.direction for m in self._motors], dtype=float)
        self._gear = np.array([m.gear_ratio for m in self._motors])
        self._zero = np.array([m.zero_offset for m in self._motors])
        mask = self._profile.id_mask
        self._by_reply_id = {m.id & mask: k for k, m in enumerate(self._motors)}
        self.stats = [MotorStats(j.name, m.id) for j, m in zip(self.joints, self._motors, strict=True)]
        self.unexpected_replies = 0
        n = len(self.joints)
        self._reply: list[Any] = [None] * n
        self._got = np.zeros(n, dtype=bool)
        self._all_in: asyncio.Event | None = None
        self._bus: can.BusABC | None = None
        self._estop_bus: can.BusABC | None = None
        self._estop_lock = threading.Lock()
        self._notifier: can.Notifier | None = None
        self._msgs = [
            can.Message(arbitration_id=m.id, data=bytes(8), is_extended_id=False) for m in self._motors
        ]
        self._loop: asyncio.AbstractEventLoop | None = None
        self._fault_msg: str | None = None

    # ------------------------------------------------------------ open/close
    def _make_bus(self) -> can.BusABC:
        opts: CanOptions = self.options
        kwargs: dict[str, Any] = {"interface": opts.interface, "channel": opts.channel, **opts.bus_kwargs}
        if opts.interface not in ("virtual", "socketcan"):
            kwargs.setdefault("bitrate", opts.bitrate)
        return can.Bus(**kwargs)

    async def _open(self) -> None:
        opts: CanOptions = self.options
        try:
            self._bus = self._make_bus()
            self._estop_bus = self._make_bus()
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BackendStartError(
                f"cannot open CAN bus interface={opts.interface!r} channel={opts.channel!r}: {exc}"
            ) from exc
        self._bus.set_filters([{"can_id": opts.master_id, "can_mask": 0x7FF, "extended": False}])
        self._estop_bus.set_filters([{"can_id": 0x7FF, "can_mask": 0x7FF, "extended": False}])
        self._loop = asyncio.get_running_loop()
        self._all_in = asyncio.Event()
        self._any_reply = asyncio.Event()
        self._notifier = can.Notifier(self._bus, [self._on_frame], loop=self._loop)
        enabled: list[int] = []
        try:
            for k, m in enumerate(self._motors):
                if not await self._special_and_wait(k, ENABLE, opts.open_timeout):
                    raise BackendStartError(
                        f"motor id {m.id} (joint {self.names[k]!r}) did not answer the enable frame within "
                        f"{opts.open_timeout:g} s on {opts.interface}:{opts.channel}; "
                        "check power, wiring, CAN id and bit rate"
                    )
                enabled.append(k)
                rep = self._reply[k]
                if rep is not None and rep.error_code:
                    raise BackendStartError(f"motor id {m.id} (joint {self.names[k]!r}) reports error {rep.error}")
        except BaseException:
            self._disable_all()
            raise
        self._fill_state(self.state)

    async def _special_and_wait(self, k: int, frame: bytes, wait: float) -> bool:
        assert self._bus is not None
        self._got[k] = False
        self._any_reply.clear()
        self._bus.send(can.Message(arbitration_id=self._motors[k].id, data=frame, is_extended_id=False))
        try:
            async with asyncio.timeout(wait):
                while not self._got[k]:
                    await self._any_reply.wait()
                    self._any_reply.clear()
        except TimeoutError:
            return False
        return True

    def _disable_all(self) -> None:
        """Send DISABLE to every motor on the emergency bus handle (any thread, no event loop)."""
        bus = self._estop_bus or self._bus
        if bus is None:
            return
        with self._estop_lock:
            for m in self._motors:
                try:
                    bus.send(can.Message(arbitration_id=m.id, data=DISABLE, is_extended_id=False), timeout=0.01)
                except (can.CanError, OSError) as exc:
                    log.error("could not send DISABLE to motor %d: %s", m.id, exc)

    async def _close(self) -> None:
        self._disable_all()
        if self._notifier is not None:
            self._notifier.stop(timeout=1.0)
            self._notifier = None
        for bus in (self._bus, self._estop_bus):
            if bus is not None:
                bus.shutdown()
        self._bus = self._estop_bus = None

    async def _enable(self) -> None:
        """Enter motor mode again after an e-stop (explicit robot.enable())."""
        opts: CanOptions = self.options
        for k, m in enumerate(self._motors):
            if not await self._special_and_wait(k, ENABLE, opts.open_timeout):
                raise BackendFault(f"motor id {m.id} (joint {self.names[k]!r}) did not answer the enable frame")
        self._fill_state(self.state)

    async def _recover(self) -> None:
        """After a fault: clear counters and re-enable (the safety layer keeps torque off until enable())."""
        for s in self.stats:
            s.consecutive_missed = 0
            s.last_error = None
        self._fault_msg = None
        await self._enable()

    async def set_zero(self, joint: str) -> None:
        """Explicitly set the motor's current position as its zero (never automatic)."""
        k = self.index[joint]
        if not await self._special_and_wait(k, ZERO, 1.5):
            raise BackendFault(f"motor of joint {joint!r} did not acknowledge the zero frame")

    # ----------------------------------------------------------- receiving
    def _on_frame(self, msg: can.Message) -> None:
        """Notifier callback; python-can calls it on the event loop (add_reader, or
        call_soon_threadsafe from its reader thread on buses without a file descriptor)."""
        if msg.is_error_frame or msg.is_remote_frame or msg.dlc < 6:
            return
        data = msg.data
        mask = self._profile.id_mask
        k = self._by_reply_id.get(data[0] & mask)
        if k is None:
            self.unexpected_replies += 1
            return
        try:
            rep = decode_reply(data, self._ranges[k], self._profile)
        except Exception as exc:  # malformed frame: count it, never crash the loop
            self.unexpected_replies += 1
            log.debug("undecodable reply %s: %s", msg, exc)
            return
        self._reply[k] = rep
        self._got[k] = True
        self._any_reply.set()
        st = self.stats[k]
        st.replies += 1
        st.last_reply_time = time.monotonic()
        st.temperature = rep.temperature
        if rep.error_code:
            st.last_error = rep.error
        if self._all_in is not None and self._got.all():
            self._all_in.set()

    def _fill_state(self, out: StateBuffer) -> None:
        for k, rep in enumerate(self._reply):
            if rep is None:
                continue
            d, g = self._dir[k], self._gear[k]
            out.position[k] = d * (rep.position - self._zero[k]) / g
            out.velocity[k] = d * rep.velocity / g
            out.effort[k] = d * rep.torque * g

    # ------------------------------------------------------------- the cycle
    def _write(self, sp: Setpoint) -> None:
        d, g, z = self._dir, self._gear, self._zero
        pos = d * g * sp.position + z
        vel = d * g * sp.velocity
        tau = d * sp.effort / g
        kp = sp.kp / (g * g)
        kd = sp.kd / (g * g)
        en = sp.enabled
        for k, msg in enumerate(self._msgs):
            if en[k]:
                msg.data = bytearray(
                    encode_command(pos[k], vel[k], kp[k], kd[k], tau[k], self._ranges[k], policy="clamp")
                )
            else:  # limp: zero gains and torque (motor stays in motor mode, still replies)
                r = self._ranges[k]
                p = min(max(pos[k], r.p_min), r.p_max)
                msg.data = bytearray(encode_command(p, 0.0, 0.0, 0.0, 0.0, r, policy="clamp"))

    async def _step(self, dt: float) -> None:
        bus, ev = self._bus, self._all_in
        assert bus is not None and ev is not None
        if self._fault_msg is not None:
            raise BackendFault(self._fault_msg)
        self._got[:] = False
        ev.clear()
        for k, msg in enumerate(self._msgs):
            try:
                bus.send(msg, timeout=0.0)
            except can.CanOperationError as exc:  # TX buffer full: the bus is saturated
                raise BackendFault(f"CAN transmit failed for motor id {self._motors[k].id}: {exc}") from exc
            self.stats[k].commands += 1
        try:
            async with asyncio.timeout(dt * self.options.reply_deadline):
                await ev.wait()
        except TimeoutError:
            pass
        for k in np.flatnonzero(~self._got).tolist():
            s = self.stats[k]
            s.missed += 1
            s.consecutive_missed += 1
            if s.consecutive_missed >= self.options.max_missed_replies:
                raise BackendFault(
                    f"motor id {s.motor_id} (joint {s.joint!r}) lost: no reply for {s.consecutive_missed} "
                    f"consecutive cycles ({s.missed} missed of {s.commands})"
                )
        for k in np.flatnonzero(self._got).tolist():
            s = self.stats[k]
            s.consecutive_missed = 0
            rep = self._reply[k]
            if rep is not None and rep.error_code:
                raise BackendFault(f"motor id {s.motor_id} (joint {s.joint!r}) reports error: {rep.error}")

    def _read(self, out: StateBuffer) -> None:
        self._fill_state(out)

    @property
    def stale(self) -> np.ndarray:
        """Joints whose state did not refresh in the last cycle."""
        return ~self._got

    def _emergency_stop(self, category: int) -> None:
        self._disable_all()
