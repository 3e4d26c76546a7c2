"""What a sensor is: its kind, where it sits, how often it samples and how realistic it is.

A :class:`SensorSpec` is a plain value, the same whichever way the sensor was declared
(an MJCF ``<sensor>``, a URDF Gazebo ``<sensor>`` or ros2_control ``<sensor>`` block, a
robot.yaml ``sensors:`` entry). Backends read the specs they serve from
:attr:`agentsdk.Backend.sensors`; every value a backend writes follows the conventions
documented on :data:`KINDS` (SI units, radians, ROS message layouts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["KINDS", "CameraSpec", "RaySpec", "SensorKind", "SensorLimits", "SensorSpec", "SensorYaml"]

#: the sensor kinds and the values a backend writes for one sample (float64 unless noted)
SensorKind = Literal[
    "imu",
    "accelerometer",
    "gyro",
    "orientation",
    "force_torque",
    "force",
    "torque",
    "contact",
    "rangefinder",
    "camera",
    "lidar",
    "joint_position",
    "joint_velocity",
    "joint_effort",
    "temperature",
]

#: kind -> number of float64 values per sample (cameras keep their pixels in separate arrays)
KINDS: dict[str, int] = {
    # orientation quaternion (x, y, z, w) of the sensor frame in the world, angular velocity (rad/s)
    # and linear acceleration (m/s²) in the sensor frame; the acceleration is the specific force
    # (what a real accelerometer measures): +9.81 along the sensor's up axis at rest (sensor_msgs/Imu)
    "imu": 10,
    "accelerometer": 3,  # specific force in the sensor frame (m/s²)
    "gyro": 3,  # angular velocity in the sensor frame (rad/s)
    "orientation": 4,  # quaternion x, y, z, w of the sensor frame in the world
    # the wrench the sensor's link (with everything attached below it) exerts on its parent, in the
    # sensor frame, moments about the sensor origin: Gazebo's default (frame child,
    # measure_direction child_to_parent). A payload of mass m hanging at rest reads m·g downwards.
    "force_torque": 6,
    "force": 3,
    "torque": 3,
    # total normal contact force on the link (N, >= 0) and the number of contact points
    "contact": 2,
    # distance along the sensor's +z axis (MuJoCo rangefinder) or +x axis (Gazebo ray) to the first
    # surface (m); inf when nothing is in range
    "rangefinder": 1,
    "camera": 0,
    "lidar": 0,  # samples ranges (m), inf when nothing is in range
    "joint_position": 1,
    "joint_velocity": 1,
    "joint_effort": 1,
    "temperature": 1,  # degrees Celsius
}

#: kinds every backend serves from the measured joint state (the loop fills them)
JOINT_KINDS = frozenset({"joint_position", "joint_velocity", "joint_effort"})

_Positive = Annotated[float, Field(gt=0.0)]
_NonNegative = Annotated[float, Field(ge=0.0)]


@dataclass(frozen=True, slots=True)
class CameraSpec:
    """A pinhole camera looking along the sensor frame's +x axis (Gazebo's camera convention, z up)."""

    width: int = 320
    height: int = 240
    #: horizontal field of view (rad)
    horizontal_fov: float = 1.047
    near: float = 0.05
    far: float = 50.0
    #: also render depth (m along the optical axis)
    depth: bool = False


@dataclass(frozen=True, slots=True)
class RaySpec:
    """A planar laser scanner (sensor_msgs/LaserScan): rays in the sensor's x-y plane, counter-clockwise."""

    samples: int = 180
    min_angle: float = -math.pi / 2
    max_angle: float = math.pi / 2
    range_min: float = 0.05
    range_max: float = 10.0


@dataclass(frozen=True, slots=True)
class SensorLimits:
    """Safety limits on a sensor's reading: exceeding one latches a protective stop of ``category``."""

    #: force (N): ``|force|`` of a force-torque sensor, the normal force of a contact sensor
    max_force: float | None = None
    #: ``|torque|`` of a force-torque sensor (N·m)
    max_torque: float | None = None
    #: tilt (rad) of an IMU's or orientation sensor's z axis from the world's up axis
    max_tilt: float | None = None
    #: IEC 60204-1 stop category of the protective stop
    category: int = 2

    @property
    def any(self) -> bool:
        """True when at least one limit is set."""
        return self.max_force is not None or self.max_torque is not None or self.max_tilt is not None


@dataclass(frozen=True, slots=True)
class SensorSpec:
    """One declared sensor."""

    name: str
    kind: SensorKind
    #: the link the sensor is attached to (its ``frame_id``)
    link: str
    #: the joint of a joint sensor (and of a force-torque sensor declared on a joint)
    joint: str | None = None
    #: sensor frame in the link frame: position (m) and quaternion (x, y, z, w)
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    #: samples per second of robot time; None: every control tick
    rate: float | None = None
    #: white noise standard deviation added to every value (same unit as the value)
    noise: float = 0.0
    #: constant offset added to every value
    bias: float = 0.0
    #: robot seconds between a sample and when it is published
    latency: float = 0.0
    #: where it was declared: ``mjcf``, ``gazebo``, ``ros2_control``, ``robot.yaml``, ``backend``
    source: str = "robot.yaml"
    #: MuJoCo names the model uses for it (an MJCF sensor's own name, its site)
    site: str | None = None
    camera: CameraSpec | None = None
    ray: RaySpec | None = None
    limits: SensorLimits = field(default_factory=SensorLimits)
    #: sampled from connect on; False for cameras declared only by the description (``Sensors.start`` them)
    active: bool = True

    @property
    def size(self) -> int:
        """Number of float64 values per sample (a lidar: its ray count; a camera: 0, pixels apart)."""
        if self.kind == "lidar":
            return self.ray.samples if self.ray is not None else RaySpec().samples
        return KINDS[self.kind]

    @property
    def realistic(self) -> bool:
        """True when noise, bias or latency are configured."""
        return self.noise > 0.0 or self.bias != 0.0 or self.latency > 0.0


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class _CameraYaml(_Strict):
    width: int = Field(default=320, ge=1, le=8192)
    height: int = Field(default=240, ge=1, le=8192)
    horizontal_fov: float = Field(default=1.047, gt=0.0, lt=math.pi)
    near: _Positive = 0.05
    far: _Positive = 50.0
    depth: bool = False


class _RayYaml(_Strict):
    samples: int = Field(default=180, ge=1, le=100_000)
    min_angle: float = Field(default=-math.pi / 2, ge=-math.pi, le=math.pi)
    max_angle: float = Field(default=math.pi / 2, ge=-math.pi, le=math.pi)
    range_min: _NonNegative = 0.05
    range_max: _Positive = 10.0


class SensorYaml(_Strict):
    """One robot.yaml ``sensors:`` entry (a sensor of the same name declared elsewhere is replaced)."""

    name: str = Field(min_length=1)
    type: SensorKind
    link: str | None = None
    joint: str | None = None
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rate: _Positive | None = None
    noise: _NonNegative = 0.0
    bias: float = 0.0
    latency: _NonNegative = 0.0
    camera: _CameraYaml | None = None
    ray: _RayYaml | None = None
    max_force: _Positive | None = None
    max_torque: _Positive | None = None
    max_tilt: Annotated[float, Field(gt=0.0, le=math.pi)] | None = None
    stop_category: Literal[0, 1, 2] = 2
