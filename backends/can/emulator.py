"""A virtual MIT-protocol motor firmware on a python-can bus, for tests, demos and benchmarks.

:class:`MotorEmulator` listens on a bus (``virtual`` in unit tests, ``socketcan`` on vcan0 or a
real interface) and answers like a set of CubeMars/Damiao motors: every frame addressed to
a motor gets one reply on ``master_id``, laid out per vendor profile. Physics runs in a
background thread in real time (``time.monotonic``): each motor is a rigid rotor

    J * dv/dt = tau_motor - b * v - friction * sign(v) + tau_gravity

with the firmware law ``tau_motor = clamp(kp*(p_des - p) + kd*(v_des - v) + t_ff, t_min, t_max)``
while enabled and healthy, and ``tau_motor = 0`` (limp) when disabled, faulted or timed out.
The state is integrated in fixed substeps (default 0.5 ms), backward Euler in the PD and
viscous terms (stable for any gain the protocol can carry) with a stick-slip Coulomb model.
Physics is brought up to "now" before every reply, so a reply carries the state at the
moment its command arrived.

Firmware behaviour emulated (Katz mini-cheetah firmware, CubeMars/Damiao):

- special frames: enable (zeroes the command: limp until the first command), disable
  (limp), zero (current position becomes 0; optional ``zero_pause`` during which frames
  are ignored, like CubeMars' ~1 s), clear error (clears ``error_code``; any profile);
- motor-side timeout: when no frame reaches the motor for ``timeout`` seconds, kp, kd and
  t_ff are zeroed (limp) while the motor stays enabled; counted in ``counters.timeouts``.
  Like the Katz firmware, any frame addressed to the motor resets the timer;
- reply position wraps around at the range ends like the firmware's 16-bit truncation.

Fault knobs (thread-safe, change them at runtime): ``drop_rate`` (probability that a
received frame, and independently its reply, is lost; seeded RNG), ``reply_latency``
(replies leave after this delay, through a scheduled-send queue), per motor ``silent``
(ignores everything, never replies), ``wrong_id`` (reply byte 0 names another motor),
``error_code`` (reported in the reply; the motor goes limp), and a bus ``flood`` of junk
frames at ``flood_rate`` Hz on ``flood_id``.

CLI: ``python -m agentsdk.backends.can.emulator --robot mit_leg --interface socketcan --channel vcan0``.
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import logging
import math
import random
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any, Final, Protocol

import can

from agentsdk.backends.can.config import CanBusConfig, load_can_config
from agentsdk.backends.can.mit import (
    MotorRanges,
    SpecialFrame,
    VendorProfile,
    decode_command,
    encode_reply,
    is_special,
    profile_for,
    ranges_for,
)
from agentsdk.errors import AgentSDKError, ConfigurationError

__all__ = [
    "EmulatedMotor",
    "EmulatorCounters",
    "GravityFn",
    "MotorCounters",
    "MotorEmulator",
    "MotorSnapshot",
    "Plant",
    "main",
]

log = logging.getLogger(__name__)

#: ``gravity(positions) -> torques``: physical motor positions by motor id -> external torques by id.
GravityFn = Callable[[Mapping[int, float]], Mapping[int, float]]


class Plant(Protocol):
    """The physics the emulated motors drive (instead of each motor being a free rotor).

    ``attach`` is called once with the motors and the substep; then ``advance(h, t, n)``
    integrates ``n`` substeps of ``h`` seconds, the first ending at ``t``, with each motor's
    firmware law as it stands at ``t`` (:meth:`EmulatedMotor.active` and the last command), and
    writes back each motor's ``raw_position`` and ``velocity`` once, after the last substep.
    The emulator has run the motors' command timeouts up to ``t`` and cuts the batches where a
    law changes (a command timeout, the end of a zero pause, a frame), so a plant can step in
    one call (MuJoCo's ``mj_step(nstep=n)``) instead of one Python round per substep. Called
    with the emulator's lock held.
    """

    def attach(self, motors: Mapping[int, EmulatedMotor], substep: float) -> None:
        """Bind the motors (by CAN id) and the integration step."""

    def advance(self, h: float, t: float, n: int) -> None:
        """Integrate ``n`` substeps of ``h``, the first ending at ``t``, under the motors' laws at ``t``."""

#: Knobs of :meth:`MotorEmulator.set_faults`.
_MOTOR_KNOBS: Final = frozenset({"silent", "wrong_id", "error_code", "drop_rate", "reply_latency"})


def _check_rate(name: str, value: float | None) -> None:
    if value is not None and not 0.0 <= value <= 1.0:
        raise ConfigurationError(f"{name} must be a probability in [0, 1], got {value!r}")


def _check_delay(name: str, value: float | None) -> None:
    if value is not None and not (math.isfinite(value) and value >= 0.0):
        raise ConfigurationError(f"{name} must be a finite number of seconds >= 0, got {value!r}")


def _coulomb(drive: float, denom: float, friction: float) -> float:
    """Solve ``denom * v = drive - friction * sign(v)``; static friction holds when ``|drive| <= friction``."""
    if drive > friction:
        return (drive - friction) / denom
    if drive < -friction:
        return (drive + friction) / denom
    return 0.0


@dataclass
class MotorCounters:
    """Per-motor frame counters (copies are handed out by :meth:`MotorEmulator.counters`)."""

    received: int = 0  #: frames addressed to this motor
    commands: int = 0  #: command frames applied
    specials: int = 0  #: special frames applied
    sent: int = 0  #: replies put on the bus
    dropped_rx: int = 0  #: received frames lost to ``drop_rate``
    dropped_tx: int = 0  #: replies lost to ``drop_rate``
    ignored: int = 0  #: frames ignored (silent, zero pause, wrong DLC)
    timeouts: int = 0  #: motor-side command timeouts triggered


@dataclass
class EmulatorCounters:
    """Bus-level counters of one :class:`MotorEmulator`."""

    unknown_id: int = 0  #: frames for ids that are not an emulated motor (incl. other replies)
    ignored: int = 0  #: extended-id, remote and error frames
    flood_sent: int = 0  #: junk frames sent by the flood knob
    send_errors: int = 0  #: bus.send failures (e.g. socketcan TX buffer full)
    physics_skipped: float = 0.0  #: seconds of physics skipped because the thread fell behind


@dataclass(frozen=True, slots=True)
class MotorSnapshot:
    """A consistent copy of one motor's state (motor frame, after the zero offset)."""

    motor_id: int
    position: float
    velocity: float
    torque: float  #: torque the firmware applies right now (0 when limp)
    enabled: bool
    limp: bool
    error_code: int
    p_des: float
    v_des: float
    kp: float
    kd: float
    t_ff: float
    zero_offset: float  #: physical position that reads as 0
    temperature: float
    timeout_events: tuple[float, ...]  #: monotonic times at which the command timeout fired
    counters: MotorCounters


class EmulatedMotor:
    """State, parameters and firmware law of one emulated MIT motor (motor frame, SI units).

    Parameters: ``ranges`` (MIT field ranges; default AK80-9), ``inertia`` J [kg·m²] (rotor
    plus load, seen at the output), ``damping`` b [N·m·s/rad], ``friction`` Coulomb [N·m],
    ``timeout`` (motor-side command timeout [s], Katz firmware default 25 ms), ``zero_pause``
    (seconds the motor ignores frames after a zero frame; CubeMars ~1 s), ``temperature``
    [°C], ``position``/``velocity`` (initial physical state). Fault knobs: ``silent``,
    ``wrong_id``, ``error_code``, and per-motor overrides of the emulator's ``drop_rate`` and
    ``reply_latency`` (``None`` = use the emulator's).

    Not thread-safe by itself: inside a running :class:`MotorEmulator`, change it only
    through the emulator (:meth:`MotorEmulator.set_faults`, :meth:`MotorEmulator.motor`).
    """

    def __init__(
        self,
        motor_id: int,
        ranges: MotorRanges | None = None,
        *,
        inertia: float = 0.01,
        damping: float = 0.05,
        friction: float = 0.02,
        timeout: float = 0.025,
        zero_pause: float = 0.0,
        temperature: float = 30.0,
        position: float = 0.0,
        velocity: float = 0.0,
        silent: bool = False,
        wrong_id: int | None = None,
        error_code: int = 0,
        drop_rate: float | None = None,
        reply_latency: float | None = None,
    ) -> None:
        if not 0 < motor_id <= 0x7FF:
            raise ConfigurationError(f"motor id must be 1..2047, got {motor_id}")
        for name, value, positive in (
            ("inertia", inertia, True),
            ("damping", damping, False),
            ("friction", friction, False),
            ("timeout", timeout, True),
            ("zero_pause", zero_pause, False),
        ):
            if not math.isfinite(value) or value < 0 or (positive and value == 0):
                raise ConfigurationError(
                    f"motor {motor_id}: {name} must be {'> 0' if positive else '>= 0'}, got {value}"
                )
        _check_rate("drop_rate", drop_rate)
        _check_delay("reply_latency", reply_latency)
        self.motor_id = motor_id
        self.ranges = ranges if ranges is not None else ranges_for("AK80-9")
        self.inertia = float(inertia)
        self.damping = float(damping)
        self.friction = float(friction)
        self.timeout = float(timeout)
        self.zero_pause = float(zero_pause)
        self.temperature = float(temperature)
        # fault knobs
        self.silent = silent
        self.wrong_id = wrong_id
        self.error_code = error_code
        self.drop_rate = drop_rate
        self.reply_latency = reply_latency
        # physical state: raw (physical) position; the reported position is raw - zero_offset
        self.raw_position = float(position)
        self.velocity = float(velocity)
        self.zero_offset = 0.0
        self.enabled = False
        self.paused_until = -math.inf
        # last command (motor frame)
        self.p_des = self.v_des = self.kp = self.kd = self.t_ff = 0.0
        self.last_frame_time = -math.inf
        self._watchdog_armed = False
        self.timeout_events: list[float] = []
        self.counters = MotorCounters()

    # ----------------------------------------------------------------- firmware
    @property
    def position(self) -> float:
        """Reported position (motor frame, after the zero offset)."""
        return self.raw_position - self.zero_offset

    def active(self, t: float) -> bool:
        """True when the firmware law applies torque (enabled, no error, not pausing)."""
        return self.enabled and self.error_code == 0 and t >= self.paused_until

    def output_torque(self, t: float) -> float:
        """Torque the firmware applies at time ``t`` for the current state (0 when limp)."""
        if not self.active(t):
            return 0.0
        r = self.ranges
        tau = self.kp * (self.p_des - self.position) + self.kd * (self.v_des - self.velocity) + self.t_ff
        return r.t_min if tau < r.t_min else r.t_max if tau > r.t_max else tau

    def apply_command(self, p: float, v: float, kp: float, kd: float, t_ff: float, now: float) -> None:
        """A command frame arrived (values already decoded)."""
        self.p_des, self.v_des, self.kp, self.kd, self.t_ff = p, v, kp, kd, t_ff
        self.last_frame_time = now
        self._watchdog_armed = self.enabled and (kp != 0.0 or kd != 0.0 or t_ff != 0.0)
        self.counters.commands += 1

    def apply_special(self, kind: SpecialFrame, now: float) -> None:
        """A special frame arrived."""
        self.last_frame_time = now
        self.counters.specials += 1
        if kind == "enable":
            self.enabled = True
            self._zero_command()
        elif kind == "disable":
            self.enabled = False
            self._zero_command()
        elif kind == "zero":
            self.zero_offset = self.raw_position
            if self.zero_pause > 0:
                self.paused_until = now + self.zero_pause
        elif kind == "clear_error":
            self.error_code = 0

    def _zero_command(self) -> None:
        self.p_des = self.v_des = self.kp = self.kd = self.t_ff = 0.0
        self._watchdog_armed = False

    def law_until(self, t: float) -> float:
        """The time from which the firmware law in force at ``t`` may change by itself (without a frame).

        A command timeout fires after ``last_frame_time + timeout``; a zero pause ends at
        ``paused_until``; otherwise only a frame or a fault knob changes it (``math.inf``).
        """
        until = self.last_frame_time + self.timeout if self._watchdog_armed else math.inf
        if t < self.paused_until < until:
            until = self.paused_until
        return until

    def check_timeout(self, t: float) -> None:
        """The firmware's command timeout: no frame for ``timeout`` seconds zeroes kp, kd and t_ff (limp)."""
        if self._watchdog_armed and t - self.last_frame_time > self.timeout:
            self.kp = self.kd = self.t_ff = 0.0
            self._watchdog_armed = False
            self.counters.timeouts += 1
            self.timeout_events.append(t)

    def substep(self, h: float, t: float, external: float = 0.0) -> None:
        """Integrate ``h`` seconds ending at time ``t`` as a free rotor (implicit in PD and damping)."""
        self.check_timeout(t)
        # Backward Euler in the velocity: J (v' - v) / h = tau(x + h v', v') - b v' - friction + external.
        # The right side is non-increasing in v', so the solution is unique: try the linear
        # (unsaturated) region, and if the torque it implies is out of range, solve the saturated one.
        x = self.raw_position
        jh = self.inertia / h
        b = self.damping
        f = self.friction
        momentum = jh * self.velocity + external
        if self.active(t):
            r = self.ranges
            kp, kd, v_des, t_ff = self.kp, self.kd, self.v_des, self.t_ff
            err = self.p_des + self.zero_offset - x
            v_new = _coulomb(momentum + kp * err + kd * v_des + t_ff, jh + b + h * kp + kd, f)
            tau = kp * (err - h * v_new) + kd * (v_des - v_new) + t_ff
            if tau > r.t_max:
                v_new = _coulomb(momentum + r.t_max, jh + b, f)
            elif tau < r.t_min:
                v_new = _coulomb(momentum + r.t_min, jh + b, f)
        else:
            v_new = _coulomb(momentum, jh + b, f)
        self.velocity = v_new
        self.raw_position = x + h * v_new

    def snapshot(self, t: float) -> MotorSnapshot:
        """The motor's state at time ``t`` (for tests and the plant)."""
        return MotorSnapshot(
            motor_id=self.motor_id,
            position=self.position,
            velocity=self.velocity,
            torque=self.output_torque(t),
            enabled=self.enabled,
            limp=not self.active(t) or (self.kp == 0.0 and self.kd == 0.0 and self.t_ff == 0.0),
            error_code=self.error_code,
            p_des=self.p_des,
            v_des=self.v_des,
            kp=self.kp,
            kd=self.kd,
            t_ff=self.t_ff,
            zero_offset=self.zero_offset,
            temperature=self.temperature,
            timeout_events=tuple(self.timeout_events),
            counters=dataclasses.replace(self.counters),
        )

    def __repr__(self) -> str:
        return (
            f"<EmulatedMotor id={self.motor_id} p={self.position:.4f} v={self.velocity:.4f}"
            f" {'enabled' if self.enabled else 'disabled'} error={self.error_code}>"
        )


class MotorEmulator:
    """Answers MIT frames on ``bus`` for ``motors`` (by CAN id), with real-time physics in a thread.

    ``profile`` picks the reply layout (:data:`~agentsdk.backends.can.mit.PROFILES` name or a
    :class:`~agentsdk.backends.can.mit.VendorProfile`); replies go to ``master_id``. The bus is the
    caller's: :meth:`stop` does not shut it down. ``start()``/``stop()`` or ``with``::

        with can.Bus(interface="virtual", channel="t") as bus, MotorEmulator(bus, {1: EmulatedMotor(1)}):
            ...

    Knobs: ``drop_rate``, ``reply_latency`` (defaults for every motor), ``flood_rate`` [Hz]
    and ``flood_id`` (junk frames), ``seed`` (drops and junk), ``gravity`` (external
    torques from all physical positions, evaluated every substep), ``substep`` [s],
    ``poll_interval`` (longest recv wait, bounds how stale physics gets between frames),
    ``clock`` (monotonic time source), ``plant`` (what the motors drive: default each motor
    is a free rotor; :class:`~agentsdk.backends.can.plant.MujocoPlant` simulates the robot).
    """

    def __init__(
        self,
        bus: can.BusABC,
        motors: Mapping[int, EmulatedMotor],
        *,
        profile: str | VendorProfile = "cubemars",
        master_id: int = 0,
        drop_rate: float = 0.0,
        reply_latency: float = 0.0,
        flood_rate: float = 0.0,
        flood_id: int = 0x7FF,
        seed: int | None = 0,
        gravity: GravityFn | None = None,
        substep: float = 0.0005,
        poll_interval: float = 0.002,
        max_catchup: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
        plant: Plant | None = None,
    ) -> None:
        if not motors:
            raise ConfigurationError("MotorEmulator needs at least one motor")
        for mid, m in motors.items():
            if mid != m.motor_id:
                raise ConfigurationError(f"motors[{mid}] has motor_id {m.motor_id}")
        if master_id in motors:
            raise ConfigurationError(f"master_id {master_id} is also a motor id")
        if not 0 <= master_id <= 0x7FF or not 0 <= flood_id <= 0x7FF:
            raise ConfigurationError("master_id and flood_id must be 11-bit ids (0..2047)")
        if not (0 < substep <= 0.01 and 0 < poll_interval <= 0.1 and max_catchup > 0):
            raise ConfigurationError("need 0 < substep <= 0.01, 0 < poll_interval <= 0.1, max_catchup > 0")
        _check_rate("drop_rate", drop_rate)
        _check_delay("reply_latency", reply_latency)
        self._check_flood_rate(flood_rate)
        self._bus = bus
        self._motors: dict[int, EmulatedMotor] = dict(motors)
        self._profile = profile_for(profile)
        for m in self._motors.values():
            self._check_error_code(m.error_code)
        self._master_id = master_id
        self._drop_rate = float(drop_rate)
        self._reply_latency = float(reply_latency)
        self._flood_rate = float(flood_rate)
        self._flood_id = flood_id
        self._rng = random.Random(seed)
        self._gravity = gravity
        if plant is not None and gravity is not None:
            raise ConfigurationError("give either a plant or a gravity function, not both")
        self._plant = plant
        if plant is not None:
            plant.attach(self._motors, float(substep))
        self._h = float(substep)
        self._poll = float(poll_interval)
        self._max_catchup = float(max_catchup)
        self._clock = clock
        self._real_clock = clock is time.monotonic
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._pending: list[tuple[float, int, can.Message, int]] = []  # (due, seq, msg, motor id)
        self._seq = 0
        self._next_flood = math.inf
        self._sim_time = clock()
        self._counters = EmulatorCounters()

    # ----------------------------------------------------------------- construction from robot.yaml
    @classmethod
    def from_config(
        cls,
        config: CanBusConfig,
        bus: can.BusABC,
        *,
        profile: str | VendorProfile | None = None,
        timeout: float | None = None,
        silent: Iterable[int] = (),
        initial_positions: Mapping[str, float] | None = None,
        inertia: float = 0.01,
        damping: float = 0.05,
        friction: float = 0.02,
        zero_pause: float = 0.0,
        **knobs: Any,
    ) -> MotorEmulator:
        """Emulate the motors of a validated ``backends.can`` section.

        ``timeout`` overrides every motor's timeout; ``silent`` lists motor ids that never
        answer; ``initial_positions`` (joint name -> joint position) sets the starting
        physical position through ``motor = direction * gear_ratio * joint + zero_offset``;
        other keyword ``knobs`` go to :class:`MotorEmulator`.
        """
        silent_ids = set(silent)
        ids = {m.id for m in config.motors.values()}
        if silent_ids - ids:
            raise ConfigurationError(f"silent motor id(s) {sorted(silent_ids - ids)} not in the config: {sorted(ids)}")
        initial = dict(initial_positions or {})
        motors: dict[int, EmulatedMotor] = {}
        for joint, mc in config.motors.items():
            q0 = initial.get(joint, 0.0)
            motors[mc.id] = EmulatedMotor(
                mc.id,
                mc.motor_ranges,
                inertia=inertia,
                damping=damping,
                friction=friction,
                timeout=config.motor_timeout(joint) if timeout is None else timeout,
                zero_pause=zero_pause,
                position=mc.direction * mc.gear_ratio * q0 + mc.zero_offset,
                silent=mc.id in silent_ids,
            )
        return cls(
            bus,
            motors,
            profile=config.profile if profile is None else profile,
            master_id=config.master_id,
            **knobs,
        )

    @classmethod
    def from_robot(
        cls, robot: str | Path, bus: can.BusABC, *, plant: str | Plant | None = None, **knobs: Any
    ) -> MotorEmulator:
        """Emulate the motors of ``robots/<robot>/robot.yaml`` (or a robot.yaml path / its directory).

        Reads the ``backends.can`` section; the robot's ``initial_positions`` become the
        starting pose. ``plant="mujoco"`` drives a MuJoCo simulation of the robot
        (:class:`~agentsdk.backends.can.plant.MujocoPlant`) instead of free rotors; other
        keyword ``knobs`` as in :meth:`from_config`.
        """
        robot_cfg, can_cfg = load_can_config(robot)
        knobs.setdefault("initial_positions", robot_cfg.initial_positions)
        if plant == "mujoco":
            from .plant import MujocoPlant

            plant = MujocoPlant(robot, can_cfg)
        elif plant == "rotor":
            plant = None
        elif isinstance(plant, str):
            raise ConfigurationError(f"unknown plant {plant!r}: 'rotor' or 'mujoco'")
        return cls.from_config(can_cfg, bus, plant=plant, **knobs)

    # ----------------------------------------------------------------- lifecycle
    def start(self) -> None:
        """Start answering frames (background thread). Raises RuntimeError when already running."""
        if self._thread is not None and self._thread.is_alive():
            raise RuntimeError("MotorEmulator is already running")
        self._stop.clear()
        self._error = None
        with self._lock:
            self._sim_time = self._clock()
            self._next_flood = self._sim_time if self._flood_rate > 0 else math.inf
        self._thread = threading.Thread(target=self._run, name="mit-motor-emulator", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread and wait for it (idempotent; pending delayed replies are discarded)."""
        self._stop.set()
        thread = self._thread
        if thread is None or thread is threading.current_thread():
            return
        thread.join(timeout)
        if thread.is_alive():
            raise RuntimeError(f"MotorEmulator thread did not stop within {timeout} s")
        self._thread = None
        with self._lock:
            self._pending.clear()

    def __enter__(self) -> MotorEmulator:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        """True while the emulator's bus thread runs."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def error(self) -> BaseException | None:
        """The exception that ended the thread, if any (e.g. the bus was shut down)."""
        return self._error

    @property
    def profile(self) -> VendorProfile:
        """The vendor profile the emulated motors speak."""
        return self._profile

    @property
    def master_id(self) -> int:
        """The CAN id the replies are sent to."""
        return self._master_id

    @property
    def motor_ids(self) -> tuple[int, ...]:
        """The ids of the emulated motors."""
        return tuple(self._motors)

    # ----------------------------------------------------------------- knobs (thread-safe)
    @property
    def drop_rate(self) -> float:
        """Fraction of requests left unanswered (fault injection, 0..1)."""
        return self._drop_rate

    @drop_rate.setter
    def drop_rate(self, value: float) -> None:
        _check_rate("drop_rate", value)
        with self._lock:
            self._drop_rate = float(value)

    @property
    def reply_latency(self) -> float:
        """Delay (s) before each reply is sent (fault injection)."""
        return self._reply_latency

    @reply_latency.setter
    def reply_latency(self, value: float) -> None:
        _check_delay("reply_latency", value)
        with self._lock:
            self._reply_latency = float(value)

    def set_flood(self, rate: float, arbitration_id: int | None = None) -> None:
        """Flood the bus with junk frames at ``rate`` Hz (0 stops) on ``arbitration_id``."""
        self._check_flood_rate(rate)
        if arbitration_id is not None and not 0 <= arbitration_id <= 0x7FF:
            raise ConfigurationError(f"flood id must be 0..2047, got {arbitration_id}")
        with self._lock:
            self._flood_rate = float(rate)
            if arbitration_id is not None:
                self._flood_id = arbitration_id
            self._next_flood = self._clock() if rate > 0 else math.inf

    def set_faults(self, motor_id: int | None = None, **knobs: Any) -> None:
        """Change fault knobs of one motor (or every motor when ``motor_id`` is None).

        Knobs: ``silent`` (bool), ``wrong_id`` (int | None), ``error_code`` (int; the motor
        goes limp while it is non-zero; Damiao: a status 8..0xE), ``drop_rate`` and
        ``reply_latency`` (``None`` = the emulator default).
        """
        unknown = set(knobs) - _MOTOR_KNOBS
        if unknown:
            raise ConfigurationError(f"unknown fault knob(s) {sorted(unknown)}; known: {sorted(_MOTOR_KNOBS)}")
        if "drop_rate" in knobs:
            _check_rate("drop_rate", knobs["drop_rate"])
        if "reply_latency" in knobs:
            _check_delay("reply_latency", knobs["reply_latency"])
        if "error_code" in knobs:
            self._check_error_code(knobs["error_code"])
        motors = self._select(motor_id)
        with self._lock:
            self._advance(self._clock())
            for m in motors:
                for name, value in knobs.items():
                    setattr(m, name, value)

    def motor(self, motor_id: int, **params: Any) -> MotorSnapshot:
        """Snapshot of one motor; keyword ``params`` first set physical parameters or state.

        Settable: ``inertia``, ``damping``, ``friction``, ``timeout``, ``zero_pause``,
        ``temperature``, ``raw_position``, ``velocity``.
        """
        allowed = {"inertia", "damping", "friction", "timeout", "zero_pause", "temperature", "raw_position", "velocity"}
        if set(params) - allowed:
            raise ConfigurationError(f"cannot set {sorted(set(params) - allowed)}; settable: {sorted(allowed)}")
        (m,) = self._select(motor_id)
        with self._lock:
            now = self._clock()
            self._advance(now)
            for name, value in params.items():
                setattr(m, name, float(value))
            return m.snapshot(now)

    def snapshot(self, motor_id: int) -> MotorSnapshot:
        """A consistent copy of one motor's state, physics brought up to now."""
        return self.motor(motor_id)

    def counters(self, motor_id: int) -> MotorCounters:
        """A copy of one motor's frame counters."""
        (m,) = self._select(motor_id)
        with self._lock:
            return dataclasses.replace(m.counters)

    def bus_counters(self) -> EmulatorCounters:
        """A copy of the bus-level counters."""
        with self._lock:
            return dataclasses.replace(self._counters)

    def _select(self, motor_id: int | None) -> list[EmulatedMotor]:
        if motor_id is None:
            return list(self._motors.values())
        try:
            return [self._motors[motor_id]]
        except KeyError:
            raise ConfigurationError(f"no emulated motor {motor_id}; motors: {sorted(self._motors)}") from None

    def _check_error_code(self, code: int) -> None:
        limit = 0xF if self._profile.id_byte == "status_id" else 0xFF
        if not 0 <= code <= limit:
            raise ConfigurationError(f"error_code must be 0..{limit} for the {self._profile.name} profile, got {code}")

    @staticmethod
    def _check_flood_rate(rate: float) -> None:
        if not (math.isfinite(rate) and 0.0 <= rate <= 100_000.0):
            raise ConfigurationError(f"flood_rate must be 0..100000 Hz, got {rate!r}")

    # ----------------------------------------------------------------- thread
    def _run(self) -> None:
        bus = self._bus
        stop = self._stop
        clock = self._clock
        out: list[can.Message] = []
        try:
            while not stop.is_set():
                now = clock()
                with self._lock:
                    wait = self._poll
                    if self._pending:
                        wait = min(wait, self._pending[0][0] - now)
                    wait = min(wait, self._next_flood - now)
                msg = bus.recv(timeout=max(0.0, wait))
                now = clock()
                with self._lock:
                    if msg is not None:
                        self._handle(msg, now, out)
                    self._advance(now)
                    self._due(now, out)
                    self._flood(now, out)
                if out:
                    self._send(out)
                    out.clear()
        except Exception as exc:  # the bus failed or was shut down under us: record it and end
            self._error = exc
            if not stop.is_set():
                log.exception("MIT motor emulator stopped: %s", exc)

    def _send(self, messages: list[can.Message]) -> None:
        for msg in messages:
            try:
                self._bus.send(msg)
            except can.CanOperationError as exc:
                with self._lock:
                    self._counters.send_errors += 1
                    first = self._counters.send_errors == 1
                if first:
                    log.warning("emulator could not send a frame (%s); counting further failures", exc)

    def _advance(self, now: float) -> None:
        """Integrate every motor up to ``now`` in fixed substeps (lock held)."""
        h = self._h
        t = self._sim_time
        lag = now - t
        if lag > self._max_catchup:  # the thread was starved: skip instead of a long catch-up burst
            if not self._counters.physics_skipped:  # once: the physics cannot keep up with the wall clock here
                log.warning("the emulator's physics fell %.3f s behind the wall clock and skips ahead (a starved "
                            "CPU, or a plant too costly for it; see bus_counters().physics_skipped)", lag)
            self._counters.physics_skipped += lag - self._max_catchup
            t = now - self._max_catchup
        motors = self._motors.values()
        gravity = self._gravity
        plant = self._plant
        if plant is not None:  # in batches of substeps under one set of firmware laws (see Plant)
            while t + h <= now:
                t1 = t + h
                until = math.inf
                for m in motors:
                    m.check_timeout(t1)
                    u = m.law_until(t1)
                    if u < until:
                        until = u
                n = max(1, int((now - t) / h))
                if until < math.inf:  # the substeps that end strictly before the law may change
                    n = max(1, min(n, math.ceil((until - t) / h) - 1))
                plant.advance(h, t1, n)
                t += n * h
            self._sim_time = t
            return
        while t + h <= now:
            t += h
            if gravity is None:
                for m in motors:
                    m.substep(h, t)
            else:
                ext = gravity({m.motor_id: m.raw_position for m in motors})
                for m in motors:
                    m.substep(h, t, float(ext.get(m.motor_id, 0.0)))
        self._sim_time = t

    def _rx_time(self, msg: can.Message, now: float) -> float:
        """When ``msg`` reached the bus, on our monotonic clock (frames may queue while we integrate)."""
        if not self._real_clock or not msg.timestamp:
            return now
        t = msg.timestamp + (now - time.time())
        if t > now or t < now - self._max_catchup:  # clocks disagree: trust our own
            return now
        return max(t, self._sim_time)

    def _dropped(self, motor: EmulatedMotor) -> bool:
        rate = self._drop_rate if motor.drop_rate is None else motor.drop_rate
        return rate > 0.0 and self._rng.random() < rate

    def _handle(self, msg: can.Message, now: float, out: list[can.Message]) -> None:
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            self._counters.ignored += 1
            return
        motor = self._motors.get(msg.arbitration_id)
        if motor is None:
            self._counters.unknown_id += 1
            return
        c = motor.counters
        c.received += 1
        if motor.silent:
            c.ignored += 1
            return
        if self._dropped(motor):
            c.dropped_rx += 1
            return
        t_rx = self._rx_time(msg, now)
        self._advance(t_rx)
        if t_rx < motor.paused_until:
            c.ignored += 1
            return
        data = msg.data
        kind = is_special(data)
        if kind is not None:
            motor.apply_special(kind, t_rx)
        elif len(data) == 8:
            motor.apply_command(*decode_command(data, motor.ranges), t_rx)
        else:
            c.ignored += 1
            return
        reply = can.Message(
            arbitration_id=self._master_id,
            is_extended_id=False,
            data=self._reply_bytes(motor, t_rx),
        )
        if self._dropped(motor):
            c.dropped_tx += 1
            return
        latency = self._reply_latency if motor.reply_latency is None else motor.reply_latency
        if latency > 0.0:
            self._seq += 1
            heapq.heappush(self._pending, (t_rx + latency, self._seq, reply, motor.motor_id))
        else:
            c.sent += 1
            out.append(reply)

    def _reply_bytes(self, motor: EmulatedMotor, t: float) -> bytes:
        profile = self._profile
        err = motor.error_code
        status = None
        if profile.id_byte == "status_id":
            status = err if err else (1 if motor.enabled else 0)
        return encode_reply(
            motor.motor_id if motor.wrong_id is None else motor.wrong_id,
            motor.position,
            motor.velocity,
            motor.output_torque(t),
            motor.ranges,
            profile,
            temperature=motor.temperature,
            error_code=err,
            status=status,
            rotor_temperature=motor.temperature,
        )

    def _due(self, now: float, out: list[can.Message]) -> None:
        pending = self._pending
        while pending and pending[0][0] <= now:
            _, _, msg, mid = heapq.heappop(pending)
            self._motors[mid].counters.sent += 1
            out.append(msg)

    def _flood(self, now: float, out: list[can.Message]) -> None:
        if self._next_flood > now:
            return
        period = 1.0 / self._flood_rate
        if now - self._next_flood > 0.1:  # fell behind: don't burst the backlog
            self._next_flood = now
        rng = self._rng
        while self._next_flood <= now:
            out.append(
                can.Message(arbitration_id=self._flood_id, is_extended_id=False, data=rng.randbytes(8)),
            )
            self._counters.flood_sent += 1
            self._next_flood += period

    def __repr__(self) -> str:
        state = "running" if self.running else "stopped"
        return f"<MotorEmulator {self._profile.name} motors={sorted(self._motors)} master_id={self._master_id} {state}>"


# --------------------------------------------------------------------------- CLI


def _motor_latency(text: str) -> tuple[int, float]:
    """``ID=SECONDS`` of ``--motor-latency``."""
    ident, sep, seconds = text.partition("=")
    try:
        if not sep:
            raise ValueError(text)
        pair = int(ident, 0), float(seconds)
        _check_delay("reply_latency", pair[1])
    except (ValueError, ConfigurationError) as exc:
        raise argparse.ArgumentTypeError(f"expected ID=SECONDS with SECONDS >= 0, got {text!r}") from exc
    return pair


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="agentsdk emulate-can",
        description="Emulate the MIT-protocol motors of a robot.yaml (backends.can) on a CAN bus.",
    )
    p.add_argument("--robot", required=True, help="robot name under robots/, or a robot.yaml path")
    p.add_argument("--interface", help="python-can interface (default: robot.yaml, e.g. socketcan)")
    p.add_argument("--channel", help="CAN channel (default: robot.yaml, e.g. vcan0)")
    p.add_argument("--profile", help="reply layout: cubemars | damiao | katz (default: robot.yaml)")
    p.add_argument("--drop-rate", type=float, default=0.0, help="probability a frame or a reply is lost")
    p.add_argument("--latency", type=float, default=0.0, help="reply latency [s]")
    p.add_argument(
        "--motor-latency", type=_motor_latency, nargs="+", action="extend", default=[], metavar="ID=SECONDS",
        help="reply latency of one motor [s], overriding --latency (e.g. 2=0.003)",
    )
    p.add_argument(
        "--silent", type=int, nargs="+", action="extend", default=[], metavar="ID", help="motors that never reply"
    )
    p.add_argument("--timeout", type=float, help="motor-side command timeout [s] (default: robot.yaml, 0.025)")
    p.add_argument("--flood-rate", type=float, default=0.0, help="junk frames per second (0 = off)")
    p.add_argument("--flood-id", type=lambda s: int(s, 0), default=0x7FF, help="arbitration id of the junk frames")
    p.add_argument("--seed", type=int, default=0, help="seed of the drop/junk RNG")
    p.add_argument("--poll", type=float, default=0.02,
                   help="longest wait between physics updates without frames [s] (default 0.02; the physics is "
                   "also brought up to date on every frame, so this only bounds staleness while the bus is idle)")
    p.add_argument("--substep", type=float, default=0.0005,
                   help="physics substep [s] (default 0.0005; a slow host needs a coarser one for the MuJoCo plant)")
    p.add_argument("--plant", choices=("rotor", "mujoco"), default="rotor",
                   help="what the motors drive: free rotors (default) or a MuJoCo simulation of the robot "
                   "(gravity, coupled inertia, contacts)")
    p.add_argument("--log-level", default="INFO", help="logging level (default INFO)")
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the emulator until SIGINT/SIGTERM; returns the process exit status."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        robot_cfg, can_cfg = load_can_config(args.robot)
    except AgentSDKError as exc:
        print(f"emulate-can: {exc}", file=sys.stderr)  # noqa: T201
        return 2
    interface = args.interface or can_cfg.interface
    channel = args.channel or can_cfg.channel
    try:
        bus = can.Bus(interface=interface, channel=channel)
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        from .hints import bus_open_hint

        hint = bus_open_hint(interface, channel, exc)
        print(f"emulate-can: cannot open {interface}:{channel}: {exc}" + (f"; {hint}" if hint else ""),  # noqa: T201
              file=sys.stderr)
        return 1
    stop = threading.Event()

    def _on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, _on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        plant: Plant | None = None
        if args.plant == "mujoco":
            from .plant import MujocoPlant, untimed_mujoco

            untimed_mujoco()  # this process owns MuJoCo: no clock reads inside mj_step (see untimed_mujoco)
            plant = MujocoPlant(args.robot, can_cfg)
        emulator = MotorEmulator.from_config(
            can_cfg,
            bus,
            plant=plant,
            profile=args.profile,
            timeout=args.timeout,
            silent=args.silent,
            substep=args.substep,
            poll_interval=args.poll,
            initial_positions=robot_cfg.initial_positions,
            drop_rate=args.drop_rate,
            reply_latency=args.latency,
            flood_rate=args.flood_rate,
            flood_id=args.flood_id,
            seed=args.seed,
        )
        for motor_id, latency in args.motor_latency:
            emulator.set_faults(motor_id, reply_latency=latency)
        with emulator:
            motors = ", ".join(f"{j}=id {m.id} {m.model}" for j, m in can_cfg.motors.items())
            log.info(
                "emulating %s on %s:%s (%s replies to id %d, %s plant): %s",
                robot_cfg.name,
                interface,
                channel,
                emulator.profile.name,
                can_cfg.master_id,
                args.plant,
                motors,
            )
            while not stop.wait(0.2):
                if not emulator.running:
                    log.error("emulator thread ended: %s", emulator.error)
                    return 1
    except AgentSDKError as exc:
        print(f"emulate-can: {exc}", file=sys.stderr)  # noqa: T201
        return 2
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        bus.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
