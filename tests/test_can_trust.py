"""Issue 20.1/20.2 on python-can's virtual bus: spoofed replies, a second controller, a duplicate responder.

The motors are the in-process emulator (a thread); the intruders are extra virtual bus
handles on the same channel. The same scenarios on a real SocketCAN vcan0 with the
emulator in another process are in tests/test_can_vcan.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import threading
import time
from collections.abc import AsyncIterator, Iterator
from typing import Any

import can
import numpy as np
import pytest
from test_can_backend import MAX_MISSED, MOTORS, emulator, unique_channel, wait_until

import agentsdk
from agentsdk import BusClaimedError, BusConflict, JointCommand, Robot, SafetyState, SensorFault
from agentsdk.backends.can import claims
from agentsdk.backends.can.config import load_can_config
from agentsdk.backends.can.mit import DISABLE, encode_command, encode_reply, profile_for
from agentsdk.loop import Phase

#: the spoofed reading of the issue: 10.9 rad on hip_pitch (motor id 2)
SPOOF_POSITION = 10.9


@contextlib.asynccontextmanager
async def robot_on(channel: str, **options: Any) -> AsyncIterator[Robot]:
    options.setdefault("max_missed_replies", MAX_MISSED)
    # (a busy 2-CPU host stalls the loop now and then; the stall watchdog has its own tests)
    options.setdefault("safety", {"stall_timeout": 2.0})
    async with agentsdk.connect("can", robot="mit_leg", interface="virtual", channel=channel, **options) as bot:
        yield bot


@contextlib.contextmanager
def intruder(channel: str) -> Iterator[can.BusABC]:
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        yield bus
    finally:
        bus.shutdown()


def spoof_frame(motor_id: int, position: float, velocity: float = 0.0, torque: float = 0.0) -> can.Message:
    """A reply frame as motor ``motor_id`` would send it, with a nonsense position."""
    _, cfg = load_can_config("mit_leg")
    profile = profile_for(cfg.profile)
    joint = MOTORS[motor_id]
    ranges = cfg.motors[joint].motor_ranges
    data = encode_reply(motor_id, position, velocity, torque, ranges, profile, temperature=30.0)
    return can.Message(arbitration_id=cfg.master_id, data=data, is_extended_id=False)


@contextlib.contextmanager
def spoof_after_command(channel: str, motor_id: int, reply: can.Message, limit: int = 1) -> Iterator[threading.Event]:
    """Send ``reply`` right after the robot's next commands to ``motor_id`` (at most ``limit`` times) once
    the yielded event is set, so that it lands in the cycle's reply window."""
    go, done = threading.Event(), threading.Event()
    bus = can.Bus(interface="virtual", channel=channel)

    def run() -> None:
        sent = 0
        while not done.is_set() and sent < limit:
            msg = bus.recv(0.05)
            if msg is not None and go.is_set() and msg.arbitration_id == motor_id and msg.data[7] != 0xFC:
                bus.send(reply)
                sent += 1

    thread = threading.Thread(target=run, name="spoofer")
    thread.start()
    try:
        yield go
    finally:
        done.set()
        thread.join(5)
        bus.shutdown()


class SetpointLog:
    """Every tick's (robot time, measured position, setpoint position), from an OBSERVE hook."""

    def __init__(self, robot: Robot) -> None:
        self.rows: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.handle = robot.add_tick_hook(Phase.OBSERVE, self._observe)
        self.vmax = np.array([j.max_velocity for j in robot.joints])
        self.period = robot.control_period

    def _observe(self, t: float, st: Any, sp: Any) -> None:
        self.rows.append((t, st.position.copy(), sp.position.copy()))

    def worst_step_ratio(self) -> float:
        """The largest per-tick setpoint change as a fraction of what max_velocity allows in that time."""
        worst = 0.0
        for (t0, _, a), (t1, _, b) in zip(self.rows, self.rows[1:], strict=False):
            allowed = self.vmax * max(t1 - t0, self.period)
            worst = max(worst, float((np.abs(b - a) / allowed).max()))
        return worst


async def hold_still(robot: Robot) -> None:
    """Hold the start pose (a position command) and let the motors settle."""
    q0 = dict(zip(robot.joint_names, robot.backend.initial_positions.tolist(), strict=True))
    await robot.command(JointCommand("position", q0))
    await robot.clock.sleep(0.3)
    assert robot.safety.state is SafetyState.OK


# ----------------------------------------------------------------- plausibility (20.1)
async def test_one_spoofed_reply_is_a_sensor_fault_naming_the_motor_and_moves_nothing() -> None:
    channel = unique_channel()
    # hip_pitch runs with direction -1: a motor position of -10.9 rad reads as joint +10.9 rad
    spoof = spoof_frame(2, -SPOOF_POSITION)
    with emulator(channel) as emu, spoof_after_command(channel, 2, spoof) as go:
        async with robot_on(channel) as robot:
            await hold_still(robot)
            log = SetpointLog(robot)
            before = robot.setpoint.position.copy()
            # the real motor skips a reply (one missed cycle) so that the one spoof stands for it,
            # whenever the spoofer thread gets to send it
            emu.set_faults(2, silent=True)
            go.set()
            t0 = robot.clock.now()
            await wait_until(lambda: robot.safety.state is SafetyState.FAULT, "sensor fault")
            emu.set_faults(2, silent=False)
            assert robot.clock.now() - t0 < 0.5
            await robot.safety.wait_stopped()
            await robot.clock.sleep(0.3)
            log.handle.remove()
            cause = robot.safety.cause
            assert isinstance(cause, SensorFault), cause
            assert cause.joint == "hip_pitch" and "motor id 2" in str(cause) and cause.source is not None
            assert [e.joint for e in robot.safety.events if e.kind == "sensor"] == ["hip_pitch"]
            # the spoof never became the state, and the stop started from the reference: no step
            assert all(abs(q[1]) < 2.0 for _, q, _ in log.rows)
            assert log.worst_step_ratio() <= 1.0 + 1e-6
            np.testing.assert_allclose(robot.setpoint.position, before, atol=0.05)
            assert robot.torque_enabled  # category 2: holding where it stopped
            await robot.reset()
            await robot.enable()
            assert robot.safety.state is SafetyState.OK


async def test_a_flood_of_random_spoofed_replies_never_steps_a_setpoint() -> None:
    """200 random reply frames per second for our ids: a sensor fault, then a bus conflict; no step."""
    channel = unique_channel()
    stop = threading.Event()
    rng = random.Random(20)

    def flood(bus: can.BusABC) -> None:
        # well-formed replies (no error code: that alone would fault the motor) with random readings
        while not stop.wait(1 / 200):
            motor = rng.choice(list(MOTORS))
            bus.send(spoof_frame(motor, rng.uniform(-12.5, 12.5), rng.uniform(-50, 50), rng.uniform(-18, 18)))

    # the motors answer after 1 ms: half the spoofs land in a reply window ahead of the real reply
    with emulator(channel, reply_latency=0.001), intruder(channel) as bus:
        async with robot_on(channel) as robot:
            await hold_still(robot)
            log = SetpointLog(robot)
            thread = threading.Thread(target=flood, args=(bus,), name="spoof-flood")
            thread.start()
            try:
                await wait_until(lambda: robot.safety.state is SafetyState.FAULT, "fault")
                await robot.safety.wait_stopped()
                await asyncio.sleep(0.5)
            finally:
                stop.set()
                thread.join(5)
            log.handle.remove()
            kinds = {e.kind for e in robot.safety.events}
            assert "sensor" in kinds or "fault" in kinds
            assert any("motor id" in e.detail for e in robot.safety.events if e.kind in ("sensor", "fault"))
            # (a random spoof that happens to lie within reach of the last plausible reading is a
            # plausible reading: the state may take it; the setpoint never follows the measurement)
            assert log.worst_step_ratio() <= 1.0 + 1e-6


# ----------------------------------------------------------------- one controller (20.2)
async def test_a_second_connect_to_the_same_channel_and_ids_is_refused_and_the_first_keeps_running() -> None:
    channel = unique_channel()
    with emulator(channel) as emu:
        async with robot_on(channel) as first:
            await hold_still(first)
            with pytest.raises(BusClaimedError, match=r"motor ids 1, 2, 3 by robot 'mit_leg'") as info:
                async with robot_on(channel):
                    pass
            assert f"virtual:{channel}" in str(info.value)
            await first.clock.sleep(0.2)
            assert first.safety.state is SafetyState.OK
            assert all(emu.snapshot(i).enabled for i in MOTORS)  # the refused one sent no DISABLE
            assert claims.claimed("virtual", channel) == dict.fromkeys(MOTORS, "robot 'mit_leg'")
        assert claims.claimed("virtual", channel) == {}
        async with robot_on(channel) as again:  # released on close
            assert again.safety.state is SafetyState.OK


async def test_a_failed_open_releases_its_claim() -> None:
    channel = unique_channel()
    with pytest.raises(agentsdk.BackendStartError, match="did not answer"):
        async with robot_on(channel, open_timeout=0.05):  # no motors on this channel yet
            pass
    assert claims.claimed("virtual", channel) == {}
    with emulator(channel):
        async with robot_on(channel) as robot:
            assert robot.safety.state is SafetyState.OK


def test_claims_are_per_channel_and_per_id() -> None:
    a = claims.claim("SocketCAN", "vcan7", [1, 2], "robot 'a'")
    try:
        b = claims.claim("socketcan", "vcan8", [1, 2], "robot 'b'")  # another channel
        c = claims.claim("socketcan", "vcan7", [3], "robot 'c'")  # other ids on the same channel
        with pytest.raises(BusClaimedError, match=r"motor id 2 by robot 'a'"):
            claims.claim("socketcan", " vcan7", [2, 5], "robot 'd'")
        assert claims.claimed("socketcan", "vcan7") == {1: "robot 'a'", 2: "robot 'a'", 3: "robot 'c'"}
        b.release()
        c.release()
        c.release()  # idempotent
    finally:
        a.release()
    assert claims.claimed("socketcan", "vcan7") == {}


@pytest.mark.parametrize("frame", ["command", "disable"])
async def test_a_foreign_commander_is_a_bus_conflict_naming_the_motor(frame: str) -> None:
    """Frames for our motor ids that this robot did not send: another controller (another process, a
    second host) streams to them, or closes and disables them under us."""
    channel = unique_channel()
    _, cfg = load_can_config("mit_leg")
    ranges = cfg.motors["knee"].motor_ranges
    data = DISABLE if frame == "disable" else encode_command(0.5, 0.0, 20.0, 0.5, 0.0, ranges)
    with emulator(channel), intruder(channel) as bus:
        async with robot_on(channel) as robot:
            await hold_still(robot)
            t0 = robot.clock.now()
            bus.send(can.Message(arbitration_id=3, data=data, is_extended_id=False))
            await wait_until(lambda: robot.safety.state is SafetyState.FAULT, "bus conflict")
            assert robot.clock.now() - t0 < 0.5
            cause = robot.safety.cause
            assert isinstance(cause, BusConflict), cause
            assert "motor id 3 (joint 'knee'" in str(cause) and "another controller" in str(cause)
            assert robot.backend.stats[2].foreign_commands == 1
            assert not robot.torque_enabled


async def test_a_duplicate_responder_is_a_bus_conflict_naming_the_ids() -> None:
    """A second device answering with our ids (two emulators of mit_leg on one channel)."""
    channel = unique_channel()
    with emulator(channel), emulator(channel):
        t_start = time.monotonic()
        with contextlib.suppress(BusConflict):  # it may already show while the motors are enabled
            async with robot_on(channel) as robot:
                await wait_until(lambda: robot.safety.state is SafetyState.FAULT, "duplicate responder")
                cause = robot.safety.cause
                assert isinstance(cause, BusConflict), cause
                assert "a second device answers with id" in str(cause)
                assert any(f"motor id {i}" in str(cause) for i in MOTORS)
        assert time.monotonic() - t_start < 30.0


async def test_our_own_emergency_disables_are_not_a_foreign_commander() -> None:
    channel = unique_channel()
    with emulator(channel):
        async with robot_on(channel) as robot:
            await hold_still(robot)
            for _ in range(3):
                robot.estop_threadsafe(0)  # DISABLE frames from the emergency handle (another socket)
                await robot.clock.sleep(0.1)
                await robot.reset()
                await robot.enable()
                await robot.clock.sleep(0.1)
                assert robot.safety.state is SafetyState.OK, robot.safety.cause
            assert all(s.foreign_commands == 0 for s in robot.backend.stats)


async def test_receive_own_messages_does_not_read_our_own_commands_as_foreign() -> None:
    channel = unique_channel()
    with emulator(channel):
        async with robot_on(channel, bus_kwargs={"receive_own_messages": True}) as robot:
            await hold_still(robot)
            await robot.estop(2)
            await robot.reset()
            await robot.enable()
            await robot.clock.sleep(0.2)
            assert robot.safety.state is SafetyState.OK, robot.safety.cause
