"""Sampling sensors inside the control tick and handing their readings to agents.

:class:`SensorHub` registers one OBSERVE hook (ordered before recorders and the safety layer's
checks) only when the backend serves sensors: a robot without sensors pays nothing. Each tick
it marks the channels due at their rate, lets the backend fill them
(:meth:`agentsdk.Backend.read_sensors`), fills the joint sensors from the measured state,
applies the opt-in realism (bias, seeded white noise, latency) in place, and publishes: no
array is allocated per tick (PyBullet's own query results aside).

Realism is deterministic in lockstep: each sensor's noise comes from its own
``numpy.random.Generator`` seeded from the robot.yaml ``sensor_seed`` (default 0) and the
sensor's name. Latency delays publication: a sample taken at ``t`` is published at the first
tick at or after ``t + latency``, stamped ``t`` (the header stamp is when it was measured).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InvalidValueError
from ._channel import SensorChannel
from ._readings import (
    ContactState,
    Header,
    Image,
    Imu,
    JointSensorReading,
    LaserScan,
    QuaternionStamped,
    Range,
    SensorReading,
    Vector3Stamped,
    Wrench,
    WrenchStamped,
)
from ._spec import JOINT_KINDS, SensorLimits, SensorSpec

if TYPE_CHECKING:
    from ..backend import Backend, SetpointView
    from ..loop import ControlLoop, HookHandle, StateView
    from ..safety import SafetyLayer

__all__ = ["SENSOR_OBSERVE_ORDER", "SensorHub", "SensorInfo", "Sensors", "UnknownSensorError"]

#: OBSERVE-phase order of the sensor sampling hook: before recorders (0) and the safety checks (1000)
SENSOR_OBSERVE_ORDER = -1000

_JOINT_ROW = {"joint_position": 0, "joint_velocity": 1, "joint_effort": 2}


class UnknownSensorError(InvalidValueError, KeyError):
    """A sensor name is not one of the robot's sensors."""

    def __str__(self) -> str:  # KeyError would repr() the message
        return str(self.args[0]) if self.args else ""


@dataclass(frozen=True, slots=True)
class SensorInfo:
    """What ``robot.sensors`` lists about one sensor."""

    name: str
    #: the sensor kind (:data:`~agentsdk.sensors.KINDS`)
    type: str
    #: the link its readings are attached to (``header.frame_id``)
    frame_id: str
    #: the joint of a joint sensor or of a force-torque sensor declared on a joint
    joint: str | None
    #: samples per second of robot time actually achieved (a whole number of control ticks apart)
    rate: float
    #: where it was declared (``mjcf``, ``gazebo``, ``ros2_control``, ``robot.yaml``, ``backend``)
    source: str
    spec: SensorSpec


class _Slot:
    """One sensor's published sample, its realism and its latency ring (all preallocated)."""

    __slots__ = (
        "active",
        "channel",
        "count",
        "decim",
        "depth",
        "head",
        "image",
        "info",
        "latency",
        "noise",
        "noise_idx",
        "noise_view",
        "noisy",
        "raw",
        "ring_depth",
        "ring_image",
        "ring_stamp",
        "ring_values",
        "rng",
        "scratch",
        "spec",
        "stamp",
        "values",
    )

    def __init__(self, channel: SensorChannel, info: SensorInfo, decim: int, seed: int, period: float) -> None:
        spec = channel.spec
        self.channel = channel
        self.spec = spec
        self.info = info
        self.decim = decim
        #: sampled in the tick; a camera declared only by the description starts inactive (like a ROS camera
        #: without subscribers, it costs nothing) until ``robot.sensors.start`` it
        self.active = spec.active
        delayed = spec.latency > 0.0
        #: noise or bias configured: they apply to a copy of the backend's sample (never accumulate)
        # (an orientation quaternion stays exact: noise and bias apply to measured rates and forces)
        self.noisy = (spec.noise > 0.0 or spec.bias != 0.0) and spec.kind != "orientation"
        # without realism the published sample *is* the channel's (the backend writes it in the tick):
        # no copy per tick; with latency it is the ring's oldest sample whose time has come
        self.values = channel.values.copy() if delayed or self.noisy else channel.values
        #: the sample with its noise and bias (what is published or delayed)
        self.raw = channel.values.copy() if delayed and self.noisy else self.values
        self.image = None if channel.image is None else (channel.image.copy() if delayed else channel.image)
        self.depth = None if channel.depth is None else (channel.depth.copy() if delayed else channel.depth)
        self.stamp = -math.inf
        # white noise on the measured components (an IMU's orientation is left exact)
        self.noise = spec.noise
        size = spec.size
        self.noise_idx = slice(4, 10) if spec.kind == "imu" else slice(0, size)
        if spec.kind == "orientation":
            self.noise = 0.0
        n_noise = len(range(size)[self.noise_idx])
        self.scratch = np.zeros(n_noise)
        #: the values the noise and bias apply to (a view made once)
        self.noise_view = self.raw[self.noise_idx]
        self.rng = np.random.default_rng([seed, zlib.crc32(spec.name.encode("utf-8"))])
        self.latency = spec.latency
        # a ring of samples waiting for their latency to pass
        depth = math.ceil(spec.latency / (decim * period) - 1e-9) + 1 if spec.latency > 0 else 0
        self.ring_values = np.zeros((depth, size))
        self.ring_stamp = np.full(depth, math.inf)
        self.ring_image = None if self.image is None or depth == 0 else np.zeros((depth, *self.image.shape), np.uint8)
        self.ring_depth = None if self.depth is None or depth == 0 else np.zeros((depth, *self.depth.shape), np.float32)
        self.head = 0
        self.count = 0


class SensorHub:
    """Samples a backend's sensors in the control tick; ``robot.sensors`` reads from it."""

    def __init__(self, loop: ControlLoop, backend: Backend, seed: int = 0) -> None:
        self._loop = loop
        self._backend = backend
        specs = backend.sensors
        self.channels = tuple(SensorChannel(s, k) for k, s in enumerate(specs))
        period = loop.period
        self._slots: dict[str, _Slot] = {}
        for ch in self.channels:
            spec = ch.spec
            decim = 1 if spec.rate is None else max(1, round(1.0 / (spec.rate * period)))
            info = SensorInfo(spec.name, spec.kind, spec.link, spec.joint, 1.0 / (decim * period), spec.source, spec)
            self._slots[spec.name] = _Slot(ch, info, decim, seed, period)
        self._ordered = tuple(self._slots.values())
        self._backend_channels = tuple(ch for ch in self.channels if ch.spec.kind not in JOINT_KINDS)
        # joint sensors: one-element views of the loop's state rows (the buffer lives as long as the loop)
        block = loop.state.block
        assert block is not None
        self._joint = tuple(
            (self._slots[ch.spec.name], block[_JOINT_ROW[ch.spec.kind], j : j + 1])
            for ch in self.channels if ch.spec.kind in JOINT_KINDS
            for j in (loop.index[ch.spec.joint or ""],)
        )
        self._tick = 0
        self._handle: HookHandle | None = None
        if self.channels:
            from ..loop import Phase

            self._handle = loop.add_hook(Phase.OBSERVE, self._on_tick, order=SENSOR_OBSERVE_ORDER)

    def prime(self) -> None:
        """Take a first sample of every sensor at the current state (called once the loop runs)."""
        if not self.channels:
            return
        for slot in self._ordered:
            slot.channel.due = slot.active
        self._sample(self._loop.stamp, self._loop.state)

    def prepare(self, name: str) -> None:
        """Take one sample of sensor ``name`` into its channel (from a worker thread: a renderer's set-up)."""
        slot = self.slot(name)
        slot.channel.due = True
        self._backend.read_sensors((slot.channel,))  # raises (e.g. no offscreen GL) before activating

    def activate(self, name: str) -> None:
        """Sample sensor ``name`` in the tick at its rate from now on, publishing the sample taken now."""
        slot = self.slot(name)
        if slot.active:
            return
        for other in self._ordered:
            other.channel.due = other is slot
        self._backend.read_sensors((slot.channel,))
        slot.active = True
        if slot.latency > 0.0:
            self._push(slot, self._loop.stamp)
        else:
            slot.stamp = self._loop.stamp

    def remove(self) -> None:
        """Stop sampling (the robot closes)."""
        if self._handle is not None:
            self._handle.remove()
            self._handle = None

    # ------------------------------------------------------------------ the tick
    def _on_tick(self, t: float, st: StateView, sp: SetpointView) -> None:
        self._tick += 1
        tick = self._tick
        work = False
        for slot in self._ordered:
            due = slot.active and tick % slot.decim == 0
            slot.channel.due = due
            work = work or due or slot.count > 0
        if work:
            self._sample(t, st)

    def _sample(self, t: float, st: StateView) -> None:
        if self._backend_channels:
            self._backend.read_sensors(self._backend_channels)
        for slot, src in self._joint:
            if slot.channel.due:
                np.copyto(slot.channel.values, src)
        for slot in self._ordered:
            ch = slot.channel
            if ch.due:
                if slot.noisy:
                    np.copyto(slot.raw, ch.values)
                    self._realism(slot)
                if slot.latency > 0.0:
                    self._push(slot, t)
                else:  # published in place (slot.values is ch.values, or the noisy copy)
                    slot.stamp = t
            if slot.count:
                self._pop(slot, t)

    @staticmethod
    def _realism(slot: _Slot) -> None:
        spec = slot.spec
        if slot.noise <= 0.0 and spec.bias == 0.0:
            return
        part = slot.noise_view
        if spec.bias != 0.0:
            part += spec.bias
        if slot.noise > 0.0:
            scratch = slot.scratch
            slot.rng.standard_normal(out=scratch)
            scratch *= slot.noise
            part += scratch

    @staticmethod
    def _push(slot: _Slot, t: float) -> None:
        n = len(slot.ring_stamp)
        k = (slot.head + slot.count) % n
        if slot.count == n:  # full (cannot happen with the ring sized from the latency): drop the oldest
            slot.head = (slot.head + 1) % n
            slot.count -= 1
        ch = slot.channel
        slot.ring_values[k] = slot.raw if slot.noisy else ch.values
        slot.ring_stamp[k] = t
        if slot.ring_image is not None and ch.image is not None:
            slot.ring_image[k] = ch.image
        if slot.ring_depth is not None and ch.depth is not None:
            slot.ring_depth[k] = ch.depth
        slot.count += 1

    @staticmethod
    def _pop(slot: _Slot, t: float) -> None:
        n = len(slot.ring_stamp)
        while slot.count and slot.ring_stamp[slot.head] + slot.latency <= t + 1e-9:
            k = slot.head
            np.copyto(slot.values, slot.ring_values[k])
            if slot.image is not None and slot.ring_image is not None:
                np.copyto(slot.image, slot.ring_image[k])
            if slot.depth is not None and slot.ring_depth is not None:
                np.copyto(slot.depth, slot.ring_depth[k])
            slot.stamp = float(slot.ring_stamp[k])
            slot.head = (k + 1) % n
            slot.count -= 1

    # ------------------------------------------------------------------ lookups
    def slot(self, name: str) -> _Slot:
        """The published state of sensor ``name``; :class:`UnknownSensorError` lists the known ones."""
        try:
            return self._slots[name]
        except KeyError:
            known = ", ".join(self._slots) or "none"
            raise UnknownSensorError(f"unknown sensor {name!r}; this robot's sensors are: {known}") from None

    @property
    def names(self) -> tuple[str, ...]:
        """Sensor names in declaration order."""
        return tuple(self._slots)

    def infos(self) -> tuple[SensorInfo, ...]:
        """Every sensor's :class:`SensorInfo`."""
        return tuple(s.info for s in self._ordered)


class Sensors:
    """``robot.sensors``: the robot's sensors (names, types, frames) and their latest readings.

    Readings are sampled inside the control tick (each at its rate), so ``read`` returns at once
    with the sample of the latest due tick, stamped with the robot time it was measured at.
    """

    def __init__(self, hub: SensorHub, safety: SafetyLayer | None = None) -> None:
        self._hub = hub
        self._safety = safety

    # ------------------------------------------------------------------ listing
    @property
    def names(self) -> tuple[str, ...]:
        """Sensor names in declaration order."""
        return self._hub.names

    def __iter__(self) -> Iterator[SensorInfo]:
        return iter(self._hub.infos())

    def __len__(self) -> int:
        return len(self._hub.names)

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and name in self._hub.names

    def __getitem__(self, name: str) -> SensorInfo:
        return self._hub.slot(name).info

    def __repr__(self) -> str:
        inner = ", ".join(f"{i.name}: {i.type} @ {i.frame_id}" for i in self._hub.infos())
        return f"<Sensors {inner or 'none'}>"

    # ------------------------------------------------------------------ reading
    def values(self, name: str) -> np.ndarray:
        """A read-only view of sensor ``name``'s latest published values (no copy: for per-tick conditions)."""
        view = self._hub.slot(name).values.view()
        view.flags.writeable = False
        return view

    def image_view(self, name: str) -> np.ndarray | None:
        """A read-only view of camera ``name``'s latest published image (no copy; ``None`` for other sensors)."""
        image = self._hub.slot(name).image
        if image is None:
            return None
        view = image.view()
        view.flags.writeable = False
        return view

    def stamp(self, name: str) -> float:
        """Robot time of sensor ``name``'s latest published sample (``-inf`` before the first)."""
        return self._hub.slot(name).stamp

    def read(self, name: str) -> SensorReading:
        """The latest reading of sensor ``name``, shaped like its ROS message (private copies).

        A camera declared only by the description (a URDF Gazebo camera) is sampled once started
        (:meth:`start`); reading it before raises :class:`~agentsdk.errors.InvalidValueError`.
        """
        slot = self._hub.slot(name)
        if not slot.active:
            self._not_started(name)
        spec = slot.spec
        header = Header(slot.stamp, spec.link)
        v = slot.values
        kind = spec.kind
        var = spec.noise * spec.noise
        if kind == "imu":
            cov = np.diag([var] * 3).reshape(9)
            return Imu(header, v[0:4].copy(), v[4:7].copy(), v[7:10].copy(), np.zeros(9), cov, cov.copy())
        if kind == "force_torque":
            return WrenchStamped(header, Wrench(v[0:3].copy(), v[3:6].copy()))
        if kind in ("accelerometer", "gyro", "force", "torque"):
            return Vector3Stamped(header, v[0:3].copy())
        if kind == "orientation":
            return QuaternionStamped(header, v[0:4].copy())
        if kind == "contact":
            return ContactState(header, float(v[0]), int(v[1]))
        if kind == "rangefinder":
            ray = spec.ray
            return Range(header, float(v[0]), ray.range_min if ray else 0.0, ray.range_max if ray else math.inf)
        if kind == "lidar":
            ray = spec.ray
            assert ray is not None
            inc = (ray.max_angle - ray.min_angle) / max(ray.samples - 1, 1)
            return LaserScan(header, ray.min_angle, ray.max_angle, inc, 0.0, 1.0 / slot.info.rate,
                             ray.range_min, ray.range_max, v.copy())
        if kind == "camera":
            assert slot.image is not None
            h, w = slot.image.shape[:2]
            return Image(header, h, w, "rgb8", slot.image.copy())
        return JointSensorReading(header, spec.joint or "", float(v[0]))

    def depth(self, name: str) -> Image:
        """The latest depth image of camera ``name``: ``32FC1``, metres along the optical axis."""
        slot = self._hub.slot(name)
        if slot.depth is not None and not slot.active:
            self._not_started(name)
        if slot.depth is None:
            raise InvalidValueError(
                f"sensor {name!r} has no depth image (a camera with depth: robot.yaml camera.depth: true, "
                "or a Gazebo depth camera)"
            )
        h, w = slot.depth.shape
        return Image(Header(slot.stamp, slot.spec.link), h, w, "32FC1", slot.depth.copy())

    def _not_started(self, name: str) -> None:
        raise InvalidValueError(
            f"camera {name!r} is declared by the robot description and not started: "
            f"`await robot.sensors.start({name!r})` (or declare it in robot.yaml sensors:, which starts it at connect)"
        )

    @property
    def started(self) -> tuple[str, ...]:
        """Names of the sensors sampled in the tick (every one but cameras not started yet)."""
        return tuple(i.name for i in self._hub.infos() if self._hub.slot(i.name).active)

    async def start(self, name: str) -> None:
        """Start sampling camera ``name`` at its rate (its offscreen renderer is prepared off the event loop).

        Its first frame is taken at once. Idempotent; other sensors are always sampled.
        """
        from ..threads import run_blocking

        slot = self._hub.slot(name)
        if slot.active:
            return
        await run_blocking(self._hub.prepare, name, name=f"agentsdk-sensor-start-{name}")
        self._hub.activate(name)

    def snapshot(self, names: tuple[str, ...] | None = None) -> MappingProxyType[str, SensorReading]:
        """``{name: reading}`` of the given sensors (default: every one but cameras, whose images are large)."""
        if names is None:
            names = tuple(i.name for i in self._hub.infos() if i.type != "camera")
        for n in names:
            if not self._hub.slot(n).active:
                self._not_started(n)
        return MappingProxyType({n: self.read(n) for n in names})

    # ------------------------------------------------------------------ safety
    def add_limit(
        self,
        name: str,
        *,
        max_force: float | None = None,
        max_torque: float | None = None,
        max_tilt: float | None = None,
        category: int = 2,
    ) -> HookHandle:
        """Latch a protective stop of ``category`` when sensor ``name`` exceeds a limit; ``handle.remove()`` undoes it.

        ``max_force`` (N): a force-torque or force sensor's ``|force|``, a contact sensor's normal force;
        ``max_torque`` (N·m): a force-torque or torque sensor's ``|torque|``; ``max_tilt`` (rad): the angle
        of an IMU's (or orientation sensor's) z axis from the world's up axis. The event names the sensor.
        """
        from ._limits import SensorLimitCheck, check_limits

        if self._safety is None:
            raise InvalidValueError("this robot has no safety layer to add sensor limits to")
        if category not in (0, 1, 2):
            raise InvalidValueError(f"stop category must be 0, 1 or 2, got {category!r}")
        slot = self._hub.slot(name)
        limits = SensorLimits(max_force, max_torque, max_tilt, category)
        check_limits(slot.spec, limits)
        return self._safety.add_check(SensorLimitCheck(self, slot.spec, limits))


def connect_sensors(loop: ControlLoop, safety: SafetyLayer) -> Sensors:
    """The robot's sensors once its loop runs: sampled from now on, first sample taken, robot.yaml limits armed."""
    backend = loop.backend
    seed = int(getattr(backend.config, "sensor_seed", 0))
    hub = SensorHub(loop, backend, seed)
    hub.prime()
    sensors = Sensors(hub, safety)
    for info in hub.infos():
        lim = info.spec.limits
        if lim.any:
            sensors.add_limit(info.name, max_force=lim.max_force, max_torque=lim.max_torque,
                              max_tilt=lim.max_tilt, category=lim.category)
    return sensors
