"""Sensor channels of a recording: one ``/sensors/<name>`` topic per non-camera sensor, as its ROS message.

The tick hook copies every recorded sensor's published values (the layout of
:data:`agentsdk.sensors.KINDS`) and stamps into preallocated block columns; the
writer keeps, per sensor, the rows whose sample is new (its stamp changed) among
the rows sampled at the recorder's ``sensor_rate``, and encodes them a block at a
time with a :class:`~._cdr.FixedLayout` (every message of one sensor has the
same size). Cameras are not recorded.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ._cdr import CONTACT_TYPE, JOINT_SENSOR_TYPE, FixedLayout

if TYPE_CHECKING:
    from ..robot import Robot

__all__ = ["SENSOR_PREFIX", "SensorSeries", "SensorTrack", "sensor_tracks", "tracks_from_metadata"]

#: topic prefix of the sensor channels
SENSOR_PREFIX = "/sensors/"

_VECTOR_KINDS = frozenset({"accelerometer", "gyro", "force", "torque"})
#: message type per sensor kind (others: joint sensors and temperature, ``agentsdk_msgs/msg/JointSensor``)
_TYPES = {
    "imu": "sensor_msgs/msg/Imu",
    "force_torque": "geometry_msgs/msg/WrenchStamped",
    "orientation": "geometry_msgs/msg/QuaternionStamped",
    "rangefinder": "sensor_msgs/msg/Range",
    "lidar": "sensor_msgs/msg/LaserScan",
    "contact": CONTACT_TYPE,
    **{k: "geometry_msgs/msg/Vector3Stamped" for k in _VECTOR_KINDS},
}
_LASER = ("angle_min", "angle_max", "angle_increment", "time_increment", "scan_time", "range_min", "range_max")


@dataclass(frozen=True)
class SensorTrack:
    """One recorded sensor: what its messages look like and where its values sit in a block row."""

    name: str
    kind: str
    frame_id: str
    joint: str
    size: int
    #: first column of its values in a block's sensor row
    offset: int = 0
    #: per-message constants (noise variance, range limits, scan angles)
    consts: dict[str, float] = field(default_factory=dict)

    @property
    def topic(self) -> str:
        """``/sensors/<name>``."""
        return SENSOR_PREFIX + self.name

    @property
    def msg_type(self) -> str:
        """The ROS message type of its topic."""
        return _TYPES.get(self.kind, JOINT_SENSOR_TYPE)

    def to_json(self) -> dict[str, Any]:
        """What the recording's metadata stores about it."""
        return {"name": self.name, "type": self.kind, "frame_id": self.frame_id, "joint": self.joint,
                "size": self.size, "consts": self.consts}

    def layout(self) -> FixedLayout:
        """The message's byte layout (built once per recording and reader)."""
        lay = FixedLayout()
        lay.header(self.frame_id)
        k = self.kind
        if k == "imu":
            for f, n in (("orientation", 4), ("orientation_covariance", 9), ("angular_velocity", 3),
                         ("angular_velocity_covariance", 9), ("linear_acceleration", 3),
                         ("linear_acceleration_covariance", 9)):
                lay.add_field(f, n, "<f8", 8)
        elif k == "force_torque":
            lay.add_field("force", 3, "<f8", 8)
            lay.add_field("torque", 3, "<f8", 8)
        elif k in _VECTOR_KINDS:
            lay.add_field("vector", 3, "<f8", 8)
        elif k == "orientation":
            lay.add_field("quaternion", 4, "<f8", 8)
        elif k == "rangefinder":
            lay.add_field("radiation_type", 1, "u1", 1)
            for f in ("field_of_view", "min_range", "max_range", "range"):
                lay.add_field(f, 1, "<f4", 4)
        elif k == "lidar":
            for f in _LASER:
                lay.add_field(f, 1, "<f4", 4)
            lay.seq("ranges", self.size, "<f4")
            lay.seq("intensities", 0, "<f4")
        elif k == "contact":
            lay.add_field("force", 1, "<f8", 8)
            lay.add_field("contacts", 1, "<u4", 4)
        else:
            lay.fixed_string(self.joint)
            lay.add_field("value", 1, "<f8", 8)
        return lay.finish()

    def columns(self, v: np.ndarray) -> dict[str, np.ndarray]:
        """Message fields of ``k`` samples ``v`` (``(k, size)``), constants broadcast."""
        k, c = self.kind, self.consts
        if k == "imu":
            cov = np.zeros(9)
            cov[[0, 4, 8]] = c.get("variance", 0.0)
            return {"orientation": v[:, 0:4], "orientation_covariance": np.zeros(9), "angular_velocity": v[:, 4:7],
                    "angular_velocity_covariance": cov, "linear_acceleration": v[:, 7:10],
                    "linear_acceleration_covariance": cov}
        if k == "force_torque":
            return {"force": v[:, 0:3], "torque": v[:, 3:6]}
        if k in _VECTOR_KINDS:
            return {"vector": v[:, 0:3]}
        if k == "orientation":
            return {"quaternion": v[:, 0:4]}
        if k == "rangefinder":
            return {"radiation_type": np.array([1], np.uint8), "field_of_view": np.zeros(1),
                    "min_range": np.array([c.get("min_range", 0.0)]),
                    "max_range": np.array([c.get("max_range", math.inf)]),
                    "range": v[:, 0:1]}
        if k == "lidar":
            cols: dict[str, np.ndarray] = {f: np.array([c.get(f, 0.0)]) for f in _LASER}
            cols["ranges"] = v
            return cols
        if k == "contact":
            return {"force": v[:, 0:1], "contacts": np.rint(v[:, 1:2]).astype(np.uint32)}
        return {"value": v[:, 0:1]}

    def values(self, lay: FixedLayout, block: np.ndarray) -> np.ndarray:
        """The ``(k, size)`` values (the :data:`~agentsdk.sensors.KINDS` layout) of a block of its messages."""
        k = self.kind
        names: tuple[str, ...]
        if k == "imu":
            names = ("orientation", "angular_velocity", "linear_acceleration")
        elif k == "force_torque":
            names = ("force", "torque")
        elif k in _VECTOR_KINDS:
            names = ("vector",)
        elif k == "orientation":
            names = ("quaternion",)
        elif k == "rangefinder":
            names = ("range",)
        elif k == "lidar":
            names = ("ranges",)
        elif k == "contact":
            names = ("force", "contacts")
        else:
            names = ("value",)
        return np.concatenate([lay.column(block, n).astype(np.float64) for n in names], axis=1)


@dataclass
class SensorSeries:
    """One recorded sensor read back: ``time`` (header stamps, ns of robot time) and ``values`` (``(k, size)``).

    ``values`` rows have the layout of :data:`agentsdk.sensors.KINDS` (what
    ``robot.sensors.values(name)`` returns); ranges and scans were stored as float32.
    """

    name: str
    type: str
    msg_type: str
    frame_id: str
    joint: str
    time: np.ndarray
    values: np.ndarray


def sensor_tracks(robot: Robot) -> tuple[SensorTrack, ...]:
    """The recorded sensors of ``robot``: every one but cameras, in declaration order."""
    sensors = getattr(robot, "sensors", None)
    if sensors is None:
        return ()
    tracks: list[SensorTrack] = []
    offset = 0
    for info in sensors:
        spec = info.spec
        if info.type == "camera":
            continue
        size = spec.size
        consts: dict[str, float] = {}
        if info.type == "imu":
            consts["variance"] = float(spec.noise) ** 2
        elif info.type == "rangefinder":
            ray = spec.ray
            consts = {"min_range": ray.range_min if ray else 0.0, "max_range": ray.range_max if ray else math.inf}
        elif info.type == "lidar" and spec.ray is not None:
            ray = spec.ray
            consts = {"angle_min": ray.min_angle, "angle_max": ray.max_angle,
                      "angle_increment": (ray.max_angle - ray.min_angle) / max(ray.samples - 1, 1),
                      "scan_time": 1.0 / info.rate, "range_min": ray.range_min, "range_max": ray.range_max}
        tracks.append(SensorTrack(info.name, info.type, info.frame_id, info.joint or "", size, offset, consts))
        offset += size
    return tuple(tracks)


def tracks_from_metadata(text: str) -> tuple[SensorTrack, ...]:
    """The tracks a recording's ``sensors`` metadata lists."""
    tracks: list[SensorTrack] = []
    offset = 0
    for d in json.loads(text):
        size = int(d["size"])
        consts = {str(k): float(v) for k, v in dict(d.get("consts", {})).items()}
        tracks.append(SensorTrack(str(d["name"]), str(d["type"]), str(d["frame_id"]), str(d.get("joint", "")),
                                  size, offset, consts))
        offset += size
    return tuple(tracks)


def tracks_json(tracks: Sequence[SensorTrack]) -> str:
    """The ``sensors`` metadata value (JSON; an infinite range limit is written as Infinity)."""
    return json.dumps([t.to_json() for t in tracks])
