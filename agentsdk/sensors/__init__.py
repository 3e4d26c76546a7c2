"""Sensors: IMUs, force-torque, contact, range, cameras and joint sensors on every backend.

Declared by the description (MJCF ``<sensor>``, URDF Gazebo ``<sensor>`` and ros2_control
``<sensor>`` blocks) and the robot.yaml ``sensors:`` section; served by a backend through one
hook (:meth:`agentsdk.Backend._read_sensors`) that fills preallocated arrays; sampled inside
the control tick; read as values shaped like the ROS messages (``robot.sensors.read(name)``).
"""

from ._channel import SensorChannel
from ._conditions import Condition, contact, force_above, range_below, torque_above
from ._declare import declared_sensors
from ._hub import SENSOR_OBSERVE_ORDER, SensorHub, SensorInfo, Sensors, UnknownSensorError, connect_sensors
from ._limits import SensorLimitCheck, tilt
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
from ._spec import JOINT_KINDS, KINDS, CameraSpec, RaySpec, SensorKind, SensorLimits, SensorSpec

__all__ = [
    "JOINT_KINDS",
    "KINDS",
    "SENSOR_OBSERVE_ORDER",
    "CameraSpec",
    "Condition",
    "ContactState",
    "Header",
    "Image",
    "Imu",
    "JointSensorReading",
    "LaserScan",
    "QuaternionStamped",
    "Range",
    "RaySpec",
    "SensorChannel",
    "SensorHub",
    "SensorInfo",
    "SensorKind",
    "SensorLimitCheck",
    "SensorLimits",
    "SensorReading",
    "SensorSpec",
    "Sensors",
    "UnknownSensorError",
    "Vector3Stamped",
    "Wrench",
    "WrenchStamped",
    "connect_sensors",
    "contact",
    "declared_sensors",
    "force_above",
    "range_below",
    "tilt",
    "torque_above",
]
