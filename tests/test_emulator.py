"""MIT motor emulator: physics, firmware behaviour and fault knobs over python-can.

Bus tests run on python-can's ``virtual`` interface (one unique channel per test); the
``vcan`` tests repeat the essentials on a real SocketCAN vcan0 (``scripts/run-in-vcan.sh``).
Waits are bounded polls on state, never assertions about how fast something happened.
"""

from __future__ import annotations

import math
import os
import random
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest

from agentsdk.backends.can.config import CanBusConfig, load_can_config, parse_can_config
from agentsdk.backends.can.emulator import EmulatedMotor, MotorEmulator, main
from agentsdk.backends.can.mit import (
    CLEAR_ERROR,
    DISABLE,
    ENABLE,
    PROFILES,
    ZERO,
    MotorReply,
    VendorProfile,
    decode_reply,
    encode_command,
    ranges_for,
)
from agentsdk.errors import ConfigurationError

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "fixtures" / "can_leg" / "robot.yaml"
HAS_VCAN = Path("/sys/class/net/vcan0").exists()
AK80_9 = ranges_for("AK80-9")
BOUND = 5.0  # generous upper bound for polls: a failure guard, not a speed requirement


def wait_for(predicate: Callable[[], bool], bound: float = BOUND, what: str = "condition") -> None:
    deadline = time.monotonic() + bound
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.002)


def emulator_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "mit-motor-emulator"]


class Host:
    """The host side of the bus: sends frames to motor ids, reads replies on master id 0."""

    def __init__(self, bus: can.BusABC, profile: VendorProfile = PROFILES["cubemars"]) -> None:
        self.bus = bus
        self.profile = profile

    def send(self, motor_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=motor_id, data=data, is_extended_id=False))

    def reply(self, bound: float = BOUND, ranges: object = AK80_9) -> MotorReply | None:
        """Next reply frame on id 0 (junk on other ids is skipped), or None after ``bound`` seconds."""
        deadline = time.monotonic() + bound
        while (left := deadline - time.monotonic()) > 0:
            msg = self.bus.recv(timeout=left)
            if msg is not None and msg.arbitration_id == 0:
                return decode_reply(msg.data, ranges, self.profile)  # type: ignore[arg-type]
        return None

    def reply_from(self, motor_id: int) -> MotorReply:
        """Skip replies of other motors until one from ``motor_id``."""
        deadline = time.monotonic() + BOUND
        while (rep := self.reply(max(0.0, deadline - time.monotonic()))) is not None:
            if rep.motor_id == motor_id:
                return rep
        raise AssertionError(f"no reply from motor {motor_id}")

    def request(self, motor_id: int, data: bytes) -> MotorReply:
        self.send(motor_id, data)
        rep = self.reply()
        assert rep is not None, f"no reply from motor {motor_id}"
        return rep

    def command(
        self, motor_id: int, p: float, v: float = 0.0, kp: float = 0.0, kd: float = 0.0, t: float = 0.0
    ) -> MotorReply:
        return self.request(motor_id, encode_command(p, v, kp, kd, t, AK80_9))


@pytest.fixture
def buses() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    channel = f"emu-{uuid.uuid4().hex}"
    host = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    motors = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        yield host, motors
    finally:
        host.shutdown()
        motors.shutdown()


def run(bus: can.BusABC, *motors: EmulatedMotor, **kw: object) -> MotorEmulator:
    return MotorEmulator(bus, {m.motor_id: m for m in motors}, **kw)  # type: ignore[arg-type]


# ---------------------------------------------------------------- physics (no bus, no thread)


def integrate(m: EmulatedMotor, seconds: float, h: float = 0.0005, t0: float = 0.0) -> float:
    t = t0
    for _ in range(round(seconds / h)):
        t += h
        m.substep(h, t)
    return t


def test_physics_position_law_converges() -> None:
    m = EmulatedMotor(1, inertia=0.01, damping=0.05, friction=0.0, timeout=10.0)
    m.apply_special("enable", 0.0)
    m.apply_command(1.0, 0.0, 50.0, 2.0, 0.0, 0.0)
    integrate(m, 2.0)
    assert m.position == pytest.approx(1.0, abs=1e-4)
    assert m.velocity == pytest.approx(0.0, abs=1e-3)


@pytest.mark.parametrize("inertia", [1e-5, 1e-3, 0.1])
def test_physics_stable_at_maximum_gains(inertia: float) -> None:
    m = EmulatedMotor(1, inertia=inertia, damping=0.0, friction=0.0, timeout=10.0)
    m.apply_special("enable", 0.0)
    m.apply_command(0.5, 0.0, 500.0, 5.0, 0.0, 0.0)
    integrate(m, 1.0)
    assert math.isfinite(m.position) and abs(m.position - 0.5) < 1e-3


def test_physics_torque_saturates_at_range() -> None:
    m = EmulatedMotor(1, inertia=1.0, damping=0.0, friction=0.0, timeout=10.0)
    m.apply_special("enable", 0.0)
    m.apply_command(10.0, 0.0, 500.0, 0.0, 0.0, 0.0)
    assert m.output_torque(0.0) == AK80_9.t_max
    integrate(m, 0.1)
    # constant saturated torque from rest: v = t_max / J * t
    assert m.velocity == pytest.approx(AK80_9.t_max * 0.1, rel=1e-6)


def test_physics_limp_when_disabled_and_coulomb_friction_stops_it() -> None:
    m = EmulatedMotor(1, inertia=0.01, damping=0.0, friction=0.05, velocity=2.0)
    m.apply_command(0.0, 0.0, 50.0, 1.0, 0.0, 0.0)  # ignored: not enabled
    assert m.output_torque(0.0) == 0.0
    integrate(m, 1.0)
    # decelerates at friction/J = 5 rad/s^2 to a stop at v0^2 / (2a) = 0.4 rad, then sticks
    assert m.velocity == 0.0
    assert m.position == pytest.approx(0.4, abs=2e-3)


def test_physics_timeout_zeroes_gains_and_records_the_event() -> None:
    m = EmulatedMotor(1, timeout=0.025)
    m.apply_special("enable", 0.0)
    m.apply_command(1.0, 0.0, 50.0, 1.0, 0.5, 0.0)
    integrate(m, 0.02)
    assert m.counters.timeouts == 0 and m.kp == 50.0
    t = integrate(m, 0.02, t0=0.02)
    assert m.counters.timeouts == 1 and (m.kp, m.kd, m.t_ff) == (0.0, 0.0, 0.0)
    assert m.enabled and 0.025 < m.timeout_events[0] <= 0.0255
    integrate(m, 0.1, t0=t)
    assert m.counters.timeouts == 1  # recorded once per silence


def test_physics_gravity_callback_in_emulator(buses: tuple[can.BusABC, can.BusABC]) -> None:
    _, bus = buses
    seen: list[dict[int, float]] = []

    def gravity(positions: dict[int, float]) -> dict[int, float]:
        seen.append(dict(positions))
        return {1: -1.0}

    em = run(bus, EmulatedMotor(1, inertia=0.1, damping=0.0, friction=0.0), gravity=gravity)  # type: ignore[arg-type]
    with em:
        wait_for(lambda: em.snapshot(1).velocity < -0.05, what="the motor to fall")
    assert seen and set(seen[0]) == {1}


# ---------------------------------------------------------------- over the bus


def test_enable_gets_a_reply(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, position=0.25, temperature=33.0)) as em:
        rep = host.request(1, ENABLE)
        assert rep.motor_id == 1 and rep.ok and rep.temperature == 33.0
        assert rep.position == pytest.approx(0.25, abs=AK80_9.lsb("p"))
        snap = em.snapshot(1)
        assert snap.enabled and snap.counters.received == 1 and snap.counters.sent == 1


def test_position_command_converges(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, inertia=0.01, timeout=1.0)) as em:
        host.request(1, ENABLE)
        deadline = time.monotonic() + BOUND
        rep = host.command(1, 1.0, kp=50.0, kd=2.0)
        while abs(rep.position - 1.0) > 0.01 or abs(rep.velocity) > 0.1:
            assert time.monotonic() < deadline, f"did not converge: {rep}"
            time.sleep(0.002)
            rep = host.command(1, 1.0, kp=50.0, kd=2.0)
        snap = em.snapshot(1)
        assert snap.position == pytest.approx(1.0, abs=0.01) and not snap.limp


def test_disable_makes_the_motor_limp(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, timeout=1.0, position=0.5)) as em:
        host.request(1, ENABLE)
        rep = host.command(1, 0.0, kp=50.0)
        assert rep.torque < -20.0 * 0.5  # pulling towards 0 (saturated at -18)
        rep = host.request(1, DISABLE)
        assert rep.torque == pytest.approx(0.0, abs=AK80_9.lsb("t"))
        em.motor(1, velocity=0.0, raw_position=0.5)
        for _ in range(5):
            rep = host.command(1, 0.0, kp=50.0)
            assert rep.torque == pytest.approx(0.0, abs=AK80_9.lsb("t"))
        snap = em.snapshot(1)
        assert not snap.enabled and snap.limp and snap.torque == 0.0
        assert snap.position == pytest.approx(0.5, abs=1e-3)  # nothing pulls it to 0


def test_zero_sets_the_current_position_as_zero(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, position=0.75, friction=0.0, damping=0.0)) as em:
        before = host.request(1, ENABLE)
        assert before.position == pytest.approx(0.75, abs=AK80_9.lsb("p"))
        after = host.request(1, ZERO)
        assert after.position == pytest.approx(0.0, abs=AK80_9.lsb("p"))
        snap = em.snapshot(1)
        assert snap.zero_offset == 0.75 and snap.position == 0.0


def test_zero_pause_ignores_frames(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, zero_pause=30.0), EmulatedMotor(2)) as em:
        host.request(1, ZERO)  # the zero frame itself is answered
        host.send(1, ENABLE)  # ignored during the pause
        assert host.request(2, ENABLE).motor_id == 2  # motor 2's reply comes first: 1 stayed quiet
        assert em.counters(1).ignored == 1 and not em.snapshot(1).enabled


def test_timeout_goes_limp_after_host_silence(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, timeout=0.05, position=0.3)) as em:
        host.request(1, ENABLE)
        host.command(1, 0.0, kp=20.0, kd=1.0)
        wait_for(lambda: em.counters(1).timeouts == 1, what="the motor-side timeout")
        snap = em.snapshot(1)
        assert snap.enabled and snap.limp and (snap.kp, snap.kd, snap.t_ff) == (0.0, 0.0, 0.0)
        assert len(snap.timeout_events) == 1
        rep = host.command(1, 0.0, kp=20.0, kd=1.0)  # a new command re-arms it
        assert em.snapshot(1).kp > 0 and rep.ok


def test_commands_keep_the_timeout_from_firing(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, timeout=2.0)) as em:
        host.request(1, ENABLE)
        for _ in range(50):
            host.command(1, 0.1, kp=20.0, kd=1.0)
        assert em.counters(1).timeouts == 0 and em.snapshot(1).kp > 0


def test_silent_motor_never_replies_and_ignores_commands(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, silent=True), EmulatedMotor(2)) as em:
        host.send(1, ENABLE)
        rep = host.request(2, ENABLE)  # replies keep frame order: nothing came from motor 1 first
        assert rep.motor_id == 2
        c = em.counters(1)
        assert c.received == 1 and c.ignored == 1 and c.sent == 0
        assert not em.snapshot(1).enabled
        em.set_faults(1, silent=False)
        assert host.request(1, ENABLE).motor_id == 1


def test_wrong_id(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, wrong_id=9)) as em:
        assert host.request(1, ENABLE).motor_id == 9
        em.set_faults(1, wrong_id=None)
        assert host.request(1, ENABLE).motor_id == 1


def test_error_code_surfaces_and_motor_goes_limp(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, position=0.5, timeout=1.0, inertia=1.0)) as em:
        host.request(1, ENABLE)
        em.set_faults(1, error_code=1)
        rep = host.command(1, 0.0, kp=50.0)
        assert rep.error_code == 1 and rep.error == "over-temperature" and not rep.ok
        assert rep.torque == pytest.approx(0.0, abs=AK80_9.lsb("t"))
        assert em.snapshot(1).limp
        rep = host.request(1, CLEAR_ERROR)
        assert rep.ok
        assert host.command(1, 0.0, kp=50.0).torque < -10.0


def test_damiao_profile_reports_status(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    dm = PROFILES["damiao"]
    host = Host(host_bus, dm)
    r = ranges_for("DM4310")
    with run(bus, EmulatedMotor(5, r), profile="damiao") as em:
        host.send(5, ENABLE)
        rep = host.reply(ranges=r)
        assert rep is not None and rep.status == 1 and rep.motor_id == 5 and rep.ok
        em.set_faults(5, error_code=0xB)
        host.send(5, DISABLE)
        rep = host.reply(ranges=r)
        assert rep is not None and rep.status == 0xB and rep.error == "MOSFET over-temperature"
        with pytest.raises(ConfigurationError):
            em.set_faults(5, error_code=0x1F)  # doesn't fit the status nibble


def test_drop_rate_one_drops_everything(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1), EmulatedMotor(2, drop_rate=0.0), drop_rate=1.0) as em:
        for _ in range(10):
            host.send(1, ENABLE)
        assert host.request(2, ENABLE).motor_id == 2  # motor 2 overrides the rate: the marker
        c = em.counters(1)
        assert c.received == 10 and c.dropped_rx == 10 and c.sent == 0
        assert not em.snapshot(1).enabled  # dropped frames are never applied
        em.drop_rate = 0.0
        assert host.request(1, ENABLE).motor_id == 1


def test_drop_rate_is_seeded(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, drop_rate=0.5), EmulatedMotor(2), seed=1234) as em:
        for _ in range(40):
            host.send(1, ENABLE)
        host.send(2, ENABLE)
        host.reply_from(2)  # frames are handled in order: motor 1's 40 are done
        c = em.counters(1)
    rng = random.Random(1234)
    expected_rx = expected_tx = 0
    for _ in range(40):
        if rng.random() < 0.5:
            expected_rx += 1
        elif rng.random() < 0.5:
            expected_tx += 1
    assert (c.dropped_rx, c.dropped_tx) == (expected_rx, expected_tx)


def test_reply_latency_delays_without_blocking_other_motors(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1, reply_latency=0.3), EmulatedMotor(2)) as em:
        host.send(1, ENABLE)
        assert host.request(2, ENABLE).motor_id == 2  # overtakes motor 1's delayed reply
        rep = host.reply()
        assert rep is not None and rep.motor_id == 1
        assert em.counters(1).sent == 1


def test_flood(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1), flood_rate=2000.0, flood_id=0x555) as em:
        junk = 0
        while junk < 20:
            msg = host_bus.recv(timeout=BOUND)
            assert msg is not None
            junk += msg.arbitration_id == 0x555
        assert host.request(1, ENABLE).motor_id == 1  # still answers amid the flood
        em.set_flood(0.0)
        assert em.bus_counters().flood_sent >= 20


def test_unknown_ids_and_extended_frames_are_ignored(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    with run(bus, EmulatedMotor(1)) as em:
        host.send(7, ENABLE)
        host_bus.send(can.Message(arbitration_id=1, data=ENABLE, is_extended_id=True))
        host.send(1, b"\x01\x02")  # wrong DLC: no reply
        assert host.request(1, ENABLE).motor_id == 1
        bc = em.bus_counters()
        assert bc.unknown_id == 1 and bc.ignored == 1 and em.counters(1).ignored == 1


def test_stop_is_idempotent_and_leaves_no_thread(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    em = run(bus, EmulatedMotor(1))
    em.stop()  # never started: fine
    em.start()
    with pytest.raises(RuntimeError):
        em.start()
    assert em.running and len(emulator_threads()) == 1
    em.stop()
    em.stop()
    assert not em.running and emulator_threads() == []
    with em:  # restartable
        assert Host(host_bus).request(1, ENABLE).motor_id == 1
    em.stop()
    assert emulator_threads() == [] and em.error is None


def test_bus_shut_down_under_the_emulator_ends_the_thread(buses: tuple[can.BusABC, can.BusABC]) -> None:
    _, bus = buses
    em = run(bus, EmulatedMotor(1))
    em.start()
    bus.shutdown()
    wait_for(lambda: not em.running, what="the thread to end")
    assert em.error is not None
    em.stop()


def test_knob_validation(buses: tuple[can.BusABC, can.BusABC]) -> None:
    _, bus = buses
    em = run(bus, EmulatedMotor(1))
    with pytest.raises(ConfigurationError):
        em.drop_rate = 1.5
    with pytest.raises(ConfigurationError):
        em.reply_latency = -1.0
    with pytest.raises(ConfigurationError, match="unknown fault knob"):
        em.set_faults(1, loud=True)
    with pytest.raises(ConfigurationError, match="no emulated motor"):
        em.set_faults(4, silent=True)
    with pytest.raises(ConfigurationError):
        run(bus, EmulatedMotor(1), master_id=1)
    with pytest.raises(ConfigurationError):
        EmulatedMotor(1, inertia=0.0)


# ---------------------------------------------------------------- robot.yaml


def test_from_robot_fixture(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = buses
    host = Host(host_bus)
    em = MotorEmulator.from_robot(FIXTURE.parent, bus, timeout=1.0)
    assert em.motor_ids == (1, 3) and em.profile.name == "cubemars" and em.master_id == 0
    # q_motor = direction * gear_ratio * q_joint + zero_offset; knee: -1 * 2 * -0.5 + 0.1 = 1.1
    assert em.snapshot(3).position == pytest.approx(1.1)
    assert em.snapshot(1).position == 0.0
    with em:
        rep = host.request(3, ENABLE)
        assert rep.motor_id == 3
        assert rep.position == pytest.approx(1.1, abs=AK80_9.lsb("p"))


@pytest.mark.skipif(not (ROOT / "robots" / "mit_leg" / "robot.yaml").exists(), reason="robots/mit_leg not there")
def test_from_robot_by_name(buses: tuple[can.BusABC, can.BusABC]) -> None:
    _, bus = buses
    try:
        _, cfg = load_can_config("mit_leg")
    except ConfigurationError as exc:
        if "no backends.can section" in str(exc):
            pytest.skip("robots/mit_leg/robot.yaml has no backends.can section yet")
        raise
    em = MotorEmulator.from_robot("mit_leg", bus)
    assert set(em.motor_ids) == {m.id for m in cfg.motors.values()}


def can_section(**changes: object) -> dict[str, object]:
    base: dict[str, object] = {
        "interface": "socketcan",
        "channel": "vcan0",
        "profile": "cubemars",
        "master_id": 0,
        "motors": {"hip": {"id": 1, "model": "AK80-9"}, "knee": {"id": 3, "model": "AK70-10"}},
    }
    base.update(changes)
    return base


def test_can_config_defaults_and_overrides() -> None:
    cfg = parse_can_config(can_section(timeout=0.05))
    assert isinstance(cfg, CanBusConfig) and cfg.bitrate == 1_000_000 and cfg.motor_timeout("hip") == 0.05
    knee = parse_can_config(
        can_section(motors={"knee": {"id": 3, "model": "AK70-10", "ranges": {"t_max": 30.0}, "timeout": 0.1}})
    )
    assert knee.motors["knee"].motor_ranges.t_max == 30.0 and knee.motor_timeout("knee") == 0.1


@pytest.mark.parametrize(
    ("section", "match"),
    [
        (can_section(motors={"a": {"id": 1, "model": "AK80-9"}, "b": {"id": 1, "model": "AK80-9"}}), "share CAN id"),
        (can_section(master_id=3), "equals master_id"),
        (can_section(motors={"a": {"id": 0, "model": "AK80-9"}}), r"id: expected an integer >= 1 and <= 2047, got 0"),
        (can_section(motors={"a": {"id": 2048, "model": "AK80-9"}}), r"<= 2047, got 2048"),
        (can_section(motors={"a": {"id": 1, "model": "AK99"}}), "known models"),
        (can_section(motors={"a": {"id": 1, "model": "AK80-9", "direction": 2}}), "direction"),
        (can_section(motors={"a": {"id": 1, "model": "AK80-9", "gear_ratio": 0}}), "gear_ratio"),
        (can_section(motors={"a": {"id": 1, "model": "AK80-9", "ranges": {"t_mx": 1}}}), "t_mx"),
        (can_section(motors={"a": {"id": 1, "model": "AK80-9", "kp": 1}}), r"motors\.a\.kp: unknown key"),
        (can_section(bogus=1), r"backends\.can\.bogus: unknown key"),
        (can_section(profile="odrive"), "known"),
        (can_section(motors={}), "at least 1"),
        (  # Damiao replies carry only id & 0xF
            can_section(
                profile="damiao", motors={"a": {"id": 1, "model": "DM4310"}, "b": {"id": 17, "model": "DM4310"}}
            ),
            "indistinguishable",
        ),
    ],
)
def test_can_config_validation(section: dict[str, object], match: str) -> None:
    with pytest.raises(ConfigurationError, match=match):
        parse_can_config(section, source="robot.yaml")


def test_missing_section() -> None:
    with pytest.raises(ConfigurationError, match=r"no backends\.can section"):
        parse_can_config({})


# ---------------------------------------------------------------- CLI


def test_cli_rejects_bad_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "robot.yaml").write_text("description: x.urdf\n")
    assert main(["--robot", str(tmp_path), "--interface", "virtual", "--channel", "x"]) == 2
    assert "backends.can" in capsys.readouterr().err


def _spawn_cli(*args: str) -> subprocess.Popen[str]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return subprocess.Popen(
        [sys.executable, "-m", "agentsdk.backends.can.emulator", "--robot", str(FIXTURE), *args],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _wait_started(proc: subprocess.Popen[str]) -> str:
    """The emulator's start line from its stderr (fails with the whole output if it exits first)."""
    assert proc.stderr is not None
    seen = []
    for line in proc.stderr:
        seen.append(line)
        if "emulating" in line:
            return line
    raise AssertionError(f"emulator exited with {proc.wait()}: {''.join(seen)}")


def _interrupt(proc: subprocess.Popen[str]) -> int:
    """SIGINT the emulator, collect its exit status and close its pipes."""
    proc.send_signal(signal.SIGINT)
    try:
        proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
    return proc.returncode


def test_cli_runs_until_sigint() -> None:
    proc = _spawn_cli("--interface", "virtual", "--channel", f"cli-{uuid.uuid4().hex}", "--silent", "3")
    try:
        line = _wait_started(proc)
        assert "hip=id 1 AK80-9" in line and "virtual" in line
    finally:
        rc = _interrupt(proc)
    assert rc == 0


# ---------------------------------------------------------------- real SocketCAN (vcan0)

vcan = pytest.mark.skipif(not HAS_VCAN, reason="no vcan0 (run via scripts/run-in-vcan.sh)")


@pytest.fixture
def vcan_buses() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    host = can.Bus(interface="socketcan", channel="vcan0", can_filters=[{"can_id": 0, "can_mask": 0x7FF}])
    motors = can.Bus(interface="socketcan", channel="vcan0")
    try:
        yield host, motors
    finally:
        host.shutdown()
        motors.shutdown()


@pytest.mark.vcan
@vcan
def test_vcan_round_trip_faults_and_convergence(vcan_buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, bus = vcan_buses
    host = Host(host_bus)
    motors = (EmulatedMotor(1, timeout=1.0), EmulatedMotor(2, silent=True), EmulatedMotor(3, wrong_id=9))
    with run(bus, *motors, flood_rate=500.0, flood_id=0x555) as em:
        assert host.request(1, ENABLE).motor_id == 1  # junk on 0x555 is filtered in the kernel
        host.send(2, ENABLE)
        assert host.request(3, ENABLE).motor_id == 9
        assert em.counters(2).ignored == 1
        deadline = time.monotonic() + 10 * BOUND  # the UML guest is slow: a wider guard
        rep = host.command(1, -0.5, kp=50.0, kd=2.0)
        while abs(rep.position + 0.5) > 0.01 or abs(rep.velocity) > 0.1:
            assert time.monotonic() < deadline, f"did not converge: {rep}"
            time.sleep(0.002)
            rep = host.command(1, -0.5, kp=50.0, kd=2.0)
        em.set_faults(1, error_code=2)
        assert host.command(1, -0.5, kp=50.0, kd=2.0).error == "over-current"
        assert em.bus_counters().flood_sent > 0
    assert emulator_threads() == []


@pytest.mark.vcan
@vcan
def test_vcan_cli(vcan_buses: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, _ = vcan_buses
    host = Host(host_bus)
    proc = _spawn_cli("--interface", "socketcan", "--channel", "vcan0", "--silent", "3")
    try:
        _wait_started(proc)
        rep = host.request(1, ENABLE)
        assert rep.motor_id == 1 and rep.ok
        host.send(3, ENABLE)  # silent
        rep = host.request(1, DISABLE)
        assert rep.motor_id == 1
    finally:
        rc = _interrupt(proc)
    assert rc == 0


# ---------------------------------------------------------------- MuJoCo plant (issue 13.5)
def test_mujoco_plant_gravity_moves_limp_joints_and_a_servo_holds_them(buses: tuple[can.BusABC, can.BusABC]) -> None:
    """The motors drive a MuJoCo simulation of mit_leg: gravity, coupled inertia, the gearbox mapping."""
    from agentsdk.backends.can.mit import encode_command as enc
    from agentsdk.backends.can.plant import MujocoPlant

    host_bus, bus = buses
    host = Host(host_bus)
    em = MotorEmulator.from_robot("mit_leg", bus, plant="mujoco", timeout=1.0)
    assert isinstance(em._plant, MujocoPlant)
    start = {mid: em.snapshot(mid).position for mid in em.motor_ids}
    knee = 3
    r = ranges_for("AK70-10")
    with em:
        time.sleep(0.3)  # disabled motors: limp, the shank falls under gravity
        fallen = em.snapshot(knee).position
        assert abs(fallen - start[knee]) > 0.05, (start[knee], fallen)
        host.send(knee, ENABLE)
        wait_for(lambda: em.snapshot(knee).enabled, what="knee enabled")
        target = start[knee]
        for _ in range(300):  # stream a stiff hold at the start pose for ~0.6 s
            host.send(knee, enc(target, 0.0, 200.0, 2.0, 0.0, r))
            time.sleep(0.002)
        held = em.snapshot(knee)
        assert abs(held.position - target) < 0.1, (held.position, target)
        assert abs(held.torque) > 0.01  # holding against gravity takes torque


def test_unknown_plant_is_a_configuration_error(buses: tuple[can.BusABC, can.BusABC]) -> None:
    _, bus = buses
    with pytest.raises(ConfigurationError, match="unknown plant"):
        MotorEmulator.from_robot("mit_leg", bus, plant="gazebo")


# ---------------------------------------------------------------- plant batches (issue 20: the plant in a slow VM)
class _FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class _RecordingPlant:
    """A plant that records each batch: (time the first substep ends, substeps, kp and activity of motor 1)."""

    def __init__(self) -> None:
        self.batches: list[tuple[float, int, float, bool]] = []
        self.h = 0.0

    def attach(self, motors: dict[int, EmulatedMotor], substep: float) -> None:
        self.motors, self.h = motors, substep

    def advance(self, h: float, t: float, n: int) -> None:
        m = self.motors[1]
        self.batches.append((t, n, m.kp, m.active(t)))


def _batched(bus: can.BusABC, motor: EmulatedMotor) -> tuple[MotorEmulator, _RecordingPlant, _FakeClock]:
    """An emulator (thread not started) whose physics runs on a fake clock into a recording plant."""
    plant, clock = _RecordingPlant(), _FakeClock()
    em = MotorEmulator(bus, {1: motor}, plant=plant, clock=clock, substep=0.0005)
    return em, plant, clock


def _law_changes(plant: _RecordingPlant) -> list[tuple[float, float, float, bool]]:
    """Per batch: first and last substep end times, kp, active."""
    return [(t, t + (n - 1) * plant.h, kp, on) for t, n, kp, on in plant.batches]


def test_plant_steps_in_batches_cut_where_the_command_timeout_fires(buses: tuple[can.BusABC, can.BusABC]) -> None:
    """Half a second of physics in a handful of plant calls, not 1000: the firmware law is constant
    between frames, and the batch ends exactly where the per-substep timeout rule would fire."""
    motor = EmulatedMotor(1, timeout=0.1)
    em, plant, clock = _batched(buses[1], motor)
    motor.apply_special("enable", 0.0)
    motor.apply_command(0.0, 0.0, 10.0, 0.5, 0.0, 0.0)
    clock.t = 0.5
    em.snapshot(1)  # brings the physics up to now
    assert sum(n for _, n, _, _ in plant.batches) == round(0.5 / 0.0005)
    assert len(plant.batches) <= 3, plant.batches
    changes = _law_changes(plant)
    held = [c for c in changes if c[2] == 10.0]
    limp = [c for c in changes if c[2] == 0.0]
    assert held and limp
    # the per-substep rule: the timeout fires at the first substep that ends more than 0.1 s after the frame
    assert max(last for _, last, _, _ in held) <= 0.1 + 1e-9
    assert 0.1 < min(first for first, _, _, _ in limp) <= 0.1 + 0.0005 + 1e-9
    (fired,) = motor.timeout_events
    assert 0.1 < fired <= 0.1 + 0.0005 + 1e-9


def test_plant_batches_end_where_a_zero_pause_ends(buses: tuple[can.BusABC, can.BusABC]) -> None:
    motor = EmulatedMotor(1, timeout=10.0, zero_pause=0.2)
    em, plant, clock = _batched(buses[1], motor)
    motor.apply_special("enable", 0.0)
    motor.apply_command(0.0, 0.0, 10.0, 0.5, 0.0, 0.0)
    motor.apply_special("zero", 0.0)  # the motor ignores frames and applies no torque until 0.2 s
    clock.t = 0.4
    em.snapshot(1)
    changes = _law_changes(plant)
    paused = [c for c in changes if not c[3]]
    active = [c for c in changes if c[3]]
    assert paused and active
    assert max(last for _, last, _, _ in paused) < 0.2
    assert 0.2 <= min(first for first, _, _, _ in active) < 0.2 + 0.0005 + 1e-9
    assert sum(n for _, n, _, _ in plant.batches) == round(0.4 / 0.0005)


def test_mujoco_plant_batch_is_step_for_step_the_same_physics() -> None:
    """One ``advance(h, t, n)`` of the MuJoCo plant computes exactly what n single substeps compute."""
    from agentsdk.backends.can.plant import MujocoPlant

    _, cfg = load_can_config("mit_leg")
    states = []
    for batch in (True, False):
        motors = {m.id: EmulatedMotor(m.id, m.motor_ranges, timeout=10.0) for m in cfg.motors.values()}
        plant = MujocoPlant("mit_leg", cfg)
        plant.attach(motors, 0.001)
        for mot in motors.values():  # a servo law on every motor: nothing limp
            mot.apply_special("enable", 0.0)
            mot.apply_command(mot.position + 0.1, 0.0, 5.0, 0.2, 0.1, 0.0)
        if batch:
            plant.advance(0.001, 0.001, 200)
        else:
            for k in range(200):
                plant.advance(0.001, 0.001 * (k + 1), 1)
        states.append([(m.raw_position, m.velocity) for m in motors.values()])
    assert states[0] == states[1]
    assert states[0] != [(0.0, 0.0)] * len(states[0])


def test_untimed_mujoco_turns_the_profiling_timers_off() -> None:
    """MuJoCo reads the clock ~30 times per mj_step for its timers (a system call each in user-mode Linux)."""
    import mujoco

    from agentsdk.backends.can.plant import untimed_mujoco

    model = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint type='hinge'/><geom size='.1'/></body></worldbody></mujoco>"
    )
    data = mujoco.MjData(model)
    assert mujoco.get_mjcb_time() is None
    try:
        untimed_mujoco()
        mujoco.mj_step(model, data, nstep=5)
        step = data.timer[mujoco.mjtTimer.mjTIMER_STEP]
        assert step.number == 5 and step.duration == 0.0
    finally:
        mujoco.set_mjcb_time(None)  # process-wide: leave the default for the other tests
