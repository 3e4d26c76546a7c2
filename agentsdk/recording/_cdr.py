"""ROS 2 CDR for recordings: ``ros2msg`` definitions and fixed-layout messages encoded a block at a time.

A recording's per-tick messages (``sensor_msgs/msg/JointState``,
``agentsdk_msgs/msg/JointCommand``, ``tf2_msgs/msg/TFMessage``) have the same
joint and link names in every message, so every message of a channel has the
same byte layout: only the stamp and the numbers change.  :class:`FixedLayout`
serializes the message once as a template (OMG CDR, XCDR1 little endian, what
ROS 2 and rosbag2 use) and remembers where each variable field sits; a block of
``k`` messages is then a ``(k, size)`` byte array filled column by column with
numpy (no Python work per message), and read back the same way.

The rare messages (safety events, transitions, the robot description) are
variable-length and encoded one at a time with :class:`CdrWriter` and decoded
with :class:`CdrReader`.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

import numpy as np

__all__ = [
    "COMMAND_TYPE",
    "EVENT_TYPE",
    "MSGDEFS",
    "TRANSITION_TYPE",
    "CdrReader",
    "CdrWriter",
    "FixedLayout",
    "command_layout",
    "joint_state_layout",
    "tf_layout",
]

NS_PER_S = 1_000_000_000
ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR little endian, no options

COMMAND_TYPE = "agentsdk_msgs/msg/JointCommand"
EVENT_TYPE = "agentsdk_msgs/msg/SafetyEvent"
TRANSITION_TYPE = "agentsdk_msgs/msg/Transition"

# ------------------------------------------------------------------ ros2msg definitions
_SEP = "=" * 80 + "\n"
_TIME = _SEP + "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
_HEADER = _SEP + "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"

#: the ``ros2msg`` schema text of every message type a recording uses (what rosbag2's MCAP plugin writes)
MSGDEFS: dict[str, str] = {
    "sensor_msgs/msg/JointState": (
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n"
        + _HEADER + _TIME
    ),
    COMMAND_TYPE: (
        "# Servo setpoint written to the backend (after safety filtering):\n"
        "# effort = kp*(position - q) + kd*(velocity - v) + effort, zero where not enabled\n"
        "uint8 POSITION=0\nuint8 VELOCITY=1\nuint8 EFFORT=2\n"
        "std_msgs/Header header\nstring[] name\n"
        "float64[] position\nfloat64[] velocity\n"
        "float32[] acceleration  # desired acceleration fed forward (inverse dynamics, which rounds it to float32)\n"
        "float64[] effort\n"
        "float64[] target  # last commanded value (per mode) before ramping\n"
        "float64[] kp\nfloat64[] kd\nuint8[] mode\nbool[] enabled\n"
        + _HEADER + _TIME
    ),
    EVENT_TYPE: (
        "# clamp, watchdog, estop, reset, enable, fault, stall, ...; joint is empty when none\n"
        "std_msgs/Header header\nstring kind\nstring joint\nstring detail\n" + _HEADER + _TIME
    ),
    TRANSITION_TYPE: (
        "# a state-machine history record; empty source/target/event stand for none\n"
        "std_msgs/Header header\nstring machine\nstring source\nstring target\nstring event\nstring note\n"
        "string configuration  # the root machine's active configuration after it\n"
        "float64 duration  # seconds spent in source (transitions); NaN for none\n"
        + _HEADER + _TIME
    ),
    "tf2_msgs/msg/TFMessage": (
        "geometry_msgs/TransformStamped[] transforms\n"
        + _SEP + "MSG: geometry_msgs/TransformStamped\n"
        + "std_msgs/Header header\nstring child_frame_id\nTransform transform\n"
        + _HEADER + _TIME
        + _SEP + "MSG: geometry_msgs/Transform\nVector3 translation\nQuaternion rotation\n"
        + _SEP + "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
        + _SEP + "MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
    ),
    "std_msgs/msg/String": "string data\n",
}

_VECTOR3 = _SEP + "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
_QUATERNION = _SEP + "MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
CONTACT_TYPE = "agentsdk_msgs/msg/Contact"
JOINT_SENSOR_TYPE = "agentsdk_msgs/msg/JointSensor"

#: the ``ros2msg`` schemas of the sensor messages (``/sensors/<name>`` topics)
MSGDEFS.update({
    "sensor_msgs/msg/Imu": (
        "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n"
        + _HEADER + _TIME + _QUATERNION + _VECTOR3
    ),
    "geometry_msgs/msg/WrenchStamped": (
        "std_msgs/Header header\ngeometry_msgs/Wrench wrench\n" + _HEADER + _TIME
        + _SEP + "MSG: geometry_msgs/Wrench\nVector3 force\nVector3 torque\n" + _VECTOR3
    ),
    "geometry_msgs/msg/Vector3Stamped": "std_msgs/Header header\ngeometry_msgs/Vector3 vector\n" + _HEADER + _TIME
    + _VECTOR3,
    "geometry_msgs/msg/QuaternionStamped": (
        "std_msgs/Header header\ngeometry_msgs/Quaternion quaternion\n" + _HEADER + _TIME + _QUATERNION
    ),
    "sensor_msgs/msg/Range": (
        "uint8 ULTRASOUND=0\nuint8 INFRARED=1\nstd_msgs/Header header\nuint8 radiation_type\n"
        "float32 field_of_view\nfloat32 min_range\nfloat32 max_range\nfloat32 range\n" + _HEADER + _TIME
    ),
    "sensor_msgs/msg/LaserScan": (
        "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\n"
        "float32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\n"
        "float32[] ranges\nfloat32[] intensities\n" + _HEADER + _TIME
    ),
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n" + _HEADER + _TIME,
    CONTACT_TYPE: (
        "# contact on a link: total normal force (N, >= 0) and the number of contact points\n"
        "std_msgs/Header header\nfloat64 force\nuint32 contacts\n" + _HEADER + _TIME
    ),
    JOINT_SENSOR_TYPE: (
        "# one value of a joint sensor (position rad or m, velocity, effort N*m or N, temperature degC)\n"
        "std_msgs/Header header\nstring joint\nfloat64 value\n" + _HEADER + _TIME
    ),
})


# ------------------------------------------------------------------ scalar writer / reader
class CdrWriter:
    """A little-endian CDR body; alignment counts from the end of the 4-byte encapsulation header."""

    __slots__ = ("buf",)

    def __init__(self) -> None:
        self.buf = bytearray()

    def align(self, n: int) -> None:
        """Pad to a multiple of ``n`` bytes."""
        self.buf += b"\x00" * (-len(self.buf) % n)

    def u32(self, x: int) -> None:
        """An unsigned 32-bit integer (also a sequence length)."""
        self.align(4)
        self.buf += struct.pack("<I", x)

    def i32(self, x: int) -> None:
        """A signed 32-bit integer."""
        self.align(4)
        self.buf += struct.pack("<i", x)

    def f64(self, x: float) -> None:
        """A float64."""
        self.align(8)
        self.buf += struct.pack("<d", x)

    def string(self, s: str) -> None:
        """A string: uint32 length including the terminating NUL, the UTF-8 bytes, NUL."""
        b = s.encode("utf-8", "replace")
        self.u32(len(b) + 1)
        self.buf += b + b"\x00"

    def header(self, ns: int, frame_id: str = "") -> None:
        """A ``std_msgs/Header``."""
        sec, nsec = divmod(ns, NS_PER_S)
        self.i32(sec)
        self.u32(nsec)
        self.string(frame_id)

    def message(self) -> bytes:
        """The serialized message, encapsulation header first."""
        return ENCAPSULATION + bytes(self.buf)


def strings_message(ns: int | None, fields: Sequence[str | float]) -> bytes:
    """A message of an optional header followed by strings and float64s (SafetyEvent, Transition, String)."""
    w = CdrWriter()
    if ns is not None:
        w.header(ns)
    for s in fields:
        if isinstance(s, str):
            w.string(s)
        else:
            w.f64(s)
    return w.message()


class CdrReader:
    """Reads a little-endian CDR message written as above."""

    __slots__ = ("data", "pos")

    def __init__(self, data: bytes) -> None:
        if data[:2] not in (b"\x00\x01", b"\x00\x03"):
            raise ValueError("not a little-endian CDR message")
        self.data = memoryview(data)[4:]
        self.pos = 0

    def _align(self, n: int) -> None:
        self.pos += -self.pos % n

    def u32(self) -> int:
        """An unsigned 32-bit integer."""
        self._align(4)
        (x,) = struct.unpack_from("<I", self.data, self.pos)
        self.pos += 4
        return int(x)

    def i32(self) -> int:
        """A signed 32-bit integer."""
        self._align(4)
        (x,) = struct.unpack_from("<i", self.data, self.pos)
        self.pos += 4
        return int(x)

    def f64(self) -> float:
        """A float64."""
        self._align(8)
        (x,) = struct.unpack_from("<d", self.data, self.pos)
        self.pos += 8
        return float(x)

    def string(self) -> str:
        """A string."""
        n = self.u32()
        if n < 1 or self.pos + n > len(self.data):
            raise ValueError("bad CDR string length")
        s = bytes(self.data[self.pos : self.pos + n - 1]).decode("utf-8", "replace")
        self.pos += n
        return s

    def header(self) -> int:
        """A ``std_msgs/Header``; returns its stamp in ns."""
        sec = self.i32()
        nsec = self.u32()
        self.string()
        return sec * NS_PER_S + nsec


# ------------------------------------------------------------------ fixed layouts
class FixedLayout:
    """The byte layout of a message type whose every instance has the same size.

    ``fields`` maps a field name to ``(offset, count, dtype)`` in the message
    (offsets include the encapsulation header); :meth:`encode` fills a block of
    messages from columns, :meth:`decode` reads columns back from a block.
    """

    def __init__(self) -> None:
        self._w = CdrWriter()
        self.fields: dict[str, tuple[int, int, str]] = {}

    # building (used once per recording)
    def add_field(self, name: str, count: int, dtype: str, align: int) -> None:
        w = self._w
        if count:
            w.align(align)
        self.fields[name] = (4 + len(w.buf), count, dtype)
        w.buf += b"\x00" * (count * np.dtype(dtype).itemsize)

    def header(self, frame_id: str = "", prefix: str = "") -> None:
        self.add_field(prefix + "sec", 1, "<i4", 4)
        self.add_field(prefix + "nanosec", 1, "<u4", 4)
        self._w.string(frame_id)

    def fixed_string(self, text: str) -> None:
        """A string that is the same in every message of this layout (written once into the template)."""
        self._w.string(text)

    def seq(self, name: str, count: int, dtype: str) -> None:
        self._w.u32(count)
        self.add_field(name, count, dtype, np.dtype(dtype).itemsize)

    def finish(self) -> FixedLayout:
        self.template = np.frombuffer(ENCAPSULATION + bytes(self._w.buf), dtype=np.uint8)
        self.size = len(self.template)
        return self

    # per block
    def encode(self, ns: np.ndarray, columns: dict[str, np.ndarray], stamps: Sequence[str] = ("",)) -> np.ndarray:
        """``(k, size)`` bytes of ``k`` messages stamped ``ns`` with ``columns[name]`` of shape ``(k, count)``."""
        k = len(ns)
        out = np.empty((k, self.size), dtype=np.uint8)
        out[:] = self.template
        sec, nsec = np.divmod(ns, NS_PER_S)
        for p in stamps:
            self.column(out, p + "sec")[:, 0] = sec
            self.column(out, p + "nanosec")[:, 0] = nsec
        for name, values in columns.items():
            self.column(out, name)[...] = values
        return out

    def column(self, block: np.ndarray, name: str) -> np.ndarray:
        """A writable ``(k, count)`` view of field ``name`` in a ``(k, size)`` block."""
        off, count, dtype = self.fields[name]
        width = count * np.dtype(dtype).itemsize
        return block[:, off : off + width].view(dtype)

    def matches(self, block: np.ndarray) -> np.ndarray:
        """Rows of ``block`` whose constant bytes (names, lengths, padding) are the template's."""
        mask = np.ones(self.size, dtype=bool)
        for off, count, dtype in self.fields.values():
            mask[off : off + count * np.dtype(dtype).itemsize] = False
        return np.asarray((block[:, mask] == self.template[mask]).all(axis=1))


def _names(lay: FixedLayout, names: Sequence[str]) -> None:
    lay._w.u32(len(names))
    for n in names:
        lay._w.string(n)


def joint_state_layout(names: Sequence[str]) -> FixedLayout:
    """``sensor_msgs/msg/JointState`` with these joint names: fields position, velocity, effort."""
    lay = FixedLayout()
    lay.header()
    _names(lay, names)
    for f in ("position", "velocity", "effort"):
        lay.seq(f, len(names), "<f8")
    return lay.finish()


def command_layout(names: Sequence[str], *, acceleration: bool = True) -> FixedLayout:
    """``agentsdk_msgs/msg/JointCommand`` with these joint names.

    ``acceleration=False``: the layout of format-2 recordings, written before the message carried
    the setpoint's acceleration.
    """
    n = len(names)
    lay = FixedLayout()
    lay.header()
    _names(lay, names)
    # the fields that change every tick of a motion first, the ones that rarely change together
    lay.seq("position", n, "<f8")
    lay.seq("velocity", n, "<f8")
    if acceleration:  # float32: the precision the servo law's inverse-dynamics term uses
        lay.seq("acceleration", n, "<f4")
    for f in ("effort", "target", "kp", "kd"):
        lay.seq(f, n, "<f8")
    lay.seq("mode", n, "u1")
    lay.seq("enabled", n, "u1")
    return lay.finish()


def tf_layout(parents: Sequence[str], children: Sequence[str]) -> FixedLayout:
    """``tf2_msgs/msg/TFMessage`` with one transform per (parent, child): fields ``t{i}`` (xyz), ``r{i}`` (xyzw)."""
    lay = FixedLayout()
    lay._w.u32(len(children))
    for i, (parent, child) in enumerate(zip(parents, children, strict=True)):
        lay.header(parent, prefix=f"{i}.")
        lay._w.string(child)
        lay.add_field(f"t{i}", 3, "<f8", 8)
        lay.add_field(f"r{i}", 4, "<f8", 8)
    return lay.finish()
