"""Sensor readings as values shaped like the ROS messages users know.

Every reading carries a :class:`Header` (``stamp``: robot time of the sample in seconds,
``frame_id``: the link the sensor is attached to); arrays are private copies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "ContactState",
    "Header",
    "Image",
    "Imu",
    "JointSensorReading",
    "LaserScan",
    "QuaternionStamped",
    "Range",
    "SensorReading",
    "Vector3Stamped",
    "Wrench",
    "WrenchStamped",
]


@dataclass(frozen=True, slots=True)
class Header:
    """``std_msgs/Header``: robot time of the sample (s) and the frame the values are expressed in."""

    stamp: float
    frame_id: str


@dataclass(frozen=True, slots=True)
class Imu:
    """``sensor_msgs/Imu``: orientation (x, y, z, w) in the world, angular velocity (rad/s) and specific force (m/s²).

    ``linear_acceleration`` is what a real accelerometer measures: +9.81 m/s² along the
    sensor's up axis at rest. Covariances are row-major 3×3, the configured noise's variance
    on the diagonal (zeros for an exact simulated sensor).
    """

    header: Header
    orientation: np.ndarray
    angular_velocity: np.ndarray
    linear_acceleration: np.ndarray
    orientation_covariance: np.ndarray
    angular_velocity_covariance: np.ndarray
    linear_acceleration_covariance: np.ndarray


@dataclass(frozen=True, slots=True)
class Wrench:
    """``geometry_msgs/Wrench``: force (N) and torque (N·m)."""

    force: np.ndarray
    torque: np.ndarray


@dataclass(frozen=True, slots=True)
class WrenchStamped:
    """``geometry_msgs/WrenchStamped``: the wrench the sensor's link exerts on its parent, in the sensor frame."""

    header: Header
    wrench: Wrench


@dataclass(frozen=True, slots=True)
class Vector3Stamped:
    """``geometry_msgs/Vector3Stamped`` (an accelerometer, gyro, force or torque sensor alone)."""

    header: Header
    vector: np.ndarray


@dataclass(frozen=True, slots=True)
class QuaternionStamped:
    """``geometry_msgs/QuaternionStamped``: orientation (x, y, z, w) of the sensor frame in the world."""

    header: Header
    quaternion: np.ndarray


@dataclass(frozen=True, slots=True)
class ContactState:
    """Contact on a link (like a bumper / ``ContactsState`` summary): total normal force (N) and point count."""

    header: Header
    force: float
    contacts: int

    @property
    def in_contact(self) -> bool:
        """True when any contact point pushes on the link."""
        return self.contacts > 0 and self.force > 0.0


@dataclass(frozen=True, slots=True)
class Range:
    """``sensor_msgs/Range``: distance (m) to the first surface; ``inf`` when nothing is within ``max_range``."""

    header: Header
    range: float
    min_range: float
    max_range: float


@dataclass(frozen=True, slots=True)
class JointSensorReading:
    """One value of a joint sensor (position rad or m, velocity, effort N·m or N, temperature °C)."""

    header: Header
    joint: str
    value: float


@dataclass(frozen=True, slots=True)
class Image:
    """``sensor_msgs/Image``: ``rgb8`` (``data`` uint8, height × width × 3) or ``32FC1`` depth in metres."""

    header: Header
    height: int
    width: int
    encoding: str
    data: np.ndarray

    @property
    def step(self) -> int:
        """Bytes per row."""
        return int(self.data.strides[0])


@dataclass(frozen=True, slots=True)
class LaserScan:
    """``sensor_msgs/LaserScan``: ranges (m, ``inf`` beyond ``range_max``) counter-clockwise from ``angle_min``."""

    header: Header
    angle_min: float
    angle_max: float
    angle_increment: float
    time_increment: float
    scan_time: float
    range_min: float
    range_max: float
    ranges: np.ndarray


SensorReading = (
    Imu | WrenchStamped | Vector3Stamped | QuaternionStamped | ContactState | Range | JointSensorReading | Image
    | LaserScan
)
