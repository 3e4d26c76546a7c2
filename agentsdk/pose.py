"""Rigid transforms: :class:`Pose`, a position and a unit quaternion in ROS order (x, y, z, w).

``Pose`` is shaped like ROS ``geometry_msgs/Pose``: ``position`` (3,) in metres and
``orientation`` a unit quaternion ``(x, y, z, w)``. It is immutable and composes like
tf2 transforms: ``a @ b`` (also ``a * b``) is the pose ``b`` expressed in the frame in
which ``a`` is given, i.e. ``(a @ b).matrix == a.matrix @ b.matrix``; ``a.inverse()``
undoes ``a``. The quaternion arithmetic is a few lines of numpy (Hamilton convention,
as ROS, Eigen and MuJoCo use), kept here so ``Pose`` has no dependency beyond numpy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from .errors import InvalidValueError

__all__ = ["BaseState", "Pose"]

FloatArray = npt.NDArray[np.float64]

#: a quaternion whose norm differs from 1 by more than this is rejected (not silently normalised)
_QUAT_NORM_TOL = 1e-3
#: tolerance of the orthonormality check of :meth:`Pose.from_matrix`
_ROT_TOL = 1e-6


def _vector(value: Any, n: int, what: str) -> FloatArray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidValueError(f"{what}: expected {n} numbers, got {value!r}") from exc
    if arr.shape != (n,):
        raise InvalidValueError(f"{what}: expected {n} numbers, got shape {arr.shape} ({value!r})")
    if not np.isfinite(arr).all():
        raise InvalidValueError(f"{what}: values must be finite, got {arr.tolist()}")
    return arr


def _frozen(arr: FloatArray) -> FloatArray:
    arr.setflags(write=False)
    return arr


def quat_multiply(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton product of quaternions in (x, y, z, w) order."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def quat_to_matrix(q: FloatArray) -> FloatArray:
    """Rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(r: FloatArray) -> FloatArray:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix (Shepperd's method)."""
    t = r[0, 0] + r[1, 1] + r[2, 2]
    if t > 0.0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = np.array([(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s])
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = np.array([0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s])
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = np.array([(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s])
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = np.array([(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s])
    if q[3] < 0.0:
        q = -q
    unit: FloatArray = q / np.linalg.norm(q)
    return unit


def rotation_vector(q: FloatArray) -> FloatArray:
    """Axis * angle (angle in [0, pi]) of a unit quaternion (x, y, z, w): the SO(3) log."""
    if q[3] < 0.0:
        q = -q
    s = float(np.linalg.norm(q[:3]))
    if s < 1e-12:
        return 2.0 * q[:3]  # first order, exact to 1e-24
    angle = 2.0 * math.atan2(s, q[3])
    return q[:3] * (angle / s)


def quat_from_rotation_vector(v: FloatArray) -> FloatArray:
    """Unit quaternion (x, y, z, w) of the rotation ``v`` = axis * angle (the SO(3) exp)."""
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        q = np.array([0.5 * v[0], 0.5 * v[1], 0.5 * v[2], 1.0])
        unit: FloatArray = q / np.linalg.norm(q)
        return unit
    s = math.sin(0.5 * angle) / angle
    return np.array([v[0] * s, v[1] * s, v[2] * s, math.cos(0.5 * angle)])


def quat_from_rpy(roll: float, pitch: float, yaw: float) -> FloatArray:
    """Quaternion of URDF/ROS fixed-axis roll-pitch-yaw: ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return np.array(
        [
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ]
    )


class Pose:
    """A rigid transform: ``position`` (3,) in metres, ``orientation`` unit quaternion (x, y, z, w).

    ``Pose()`` is the identity. The orientation must be a unit quaternion (a norm within
    1e-3 of 1 is renormalised; anything else raises :class:`InvalidValueError`, as do
    non-finite values and wrong shapes). Poses are immutable; ``a @ b`` / ``a * b``
    composes (``(a @ b).matrix == a.matrix @ b.matrix``), ``a.inverse()`` inverts,
    ``a.apply(points)`` transforms points.
    """

    __slots__ = ("_matrix", "orientation", "position")

    position: FloatArray
    orientation: FloatArray
    _matrix: FloatArray | None

    def __init__(
        self,
        position: Sequence[float] | npt.ArrayLike = (0.0, 0.0, 0.0),
        orientation: Sequence[float] | npt.ArrayLike = (0.0, 0.0, 0.0, 1.0),
    ) -> None:
        p = _vector(position, 3, "Pose position")
        q = _vector(orientation, 4, "Pose orientation (x, y, z, w)")
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > _QUAT_NORM_TOL:
            raise InvalidValueError(
                f"Pose orientation must be a unit quaternion (x, y, z, w); got {q.tolist()} with norm {norm:.6g}"
            )
        object.__setattr__(self, "position", _frozen(p))
        object.__setattr__(self, "orientation", _frozen(q / norm))
        object.__setattr__(self, "_matrix", None)

    @classmethod
    def from_trusted_arrays(cls, position: FloatArray, orientation: FloatArray) -> Pose:
        """Build from arrays already known valid (a (3,) position, a unit (x, y, z, w) quaternion) without checks.

        The arrays are taken over (made read-only), not copied: pass private copies. For
        hot paths such as FK; everything else should use the validating constructor.
        """
        self = object.__new__(cls)
        object.__setattr__(self, "position", _frozen(position))
        object.__setattr__(self, "orientation", _frozen(orientation))
        object.__setattr__(self, "_matrix", None)
        return self

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError("Pose is immutable")

    # ------------------------------------------------------------ builders
    @classmethod
    def identity(cls) -> Pose:
        """The identity transform."""
        return cls.from_trusted_arrays(np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))

    @classmethod
    def from_matrix(cls, matrix: npt.ArrayLike) -> Pose:
        """From a 4x4 homogeneous transform (or a 3x4 ``[R | p]``).

        The rotation block must be orthonormal with determinant +1 (to 1e-6) and a 4x4
        matrix must end with the row ``0 0 0 1``; otherwise :class:`InvalidValueError`.
        """
        try:
            m = np.array(matrix, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InvalidValueError(f"Pose.from_matrix: expected a 4x4 matrix, got {matrix!r}") from exc
        if m.shape not in ((4, 4), (3, 4)):
            raise InvalidValueError(f"Pose.from_matrix: expected a 4x4 (or 3x4) matrix, got shape {m.shape}")
        if not np.isfinite(m).all():
            raise InvalidValueError("Pose.from_matrix: the matrix has non-finite entries")
        if m.shape == (4, 4) and not np.allclose(m[3], (0.0, 0.0, 0.0, 1.0), atol=1e-9):
            raise InvalidValueError(f"Pose.from_matrix: the last row must be 0 0 0 1, got {m[3].tolist()}")
        r = m[:3, :3]
        ortho = float(np.abs(r.T @ r - np.eye(3)).max())
        det = float(np.linalg.det(r))
        if ortho > _ROT_TOL or abs(det - 1.0) > _ROT_TOL:
            raise InvalidValueError(
                "Pose.from_matrix: the rotation block is not a rotation "
                f"(max |R^T R - I| = {ortho:.3g}, det = {det:.6g})"
            )
        return cls.from_trusted_arrays(m[:3, 3].copy(), matrix_to_quat(r))

    @classmethod
    def from_xyz_rpy(cls, xyz: Sequence[float] | npt.ArrayLike, rpy: Sequence[float] | npt.ArrayLike) -> Pose:
        """From a position and URDF/ROS roll-pitch-yaw angles (fixed axes X, Y, Z; radians)."""
        p = _vector(xyz, 3, "Pose position")
        r = _vector(rpy, 3, "Pose roll-pitch-yaw")
        return cls.from_trusted_arrays(p, quat_from_rpy(*r.tolist()))

    # ------------------------------------------------------------ views
    @property
    def matrix(self) -> FloatArray:
        """The 4x4 homogeneous transform (a read-only array)."""
        m = self._matrix
        if m is None:
            m = np.eye(4)
            m[:3, :3] = quat_to_matrix(self.orientation)
            m[:3, 3] = self.position
            m.setflags(write=False)
            object.__setattr__(self, "_matrix", m)
        return m

    @property
    def rotation(self) -> FloatArray:
        """The 3x3 rotation matrix."""
        return self.matrix[:3, :3]

    @property
    def rpy(self) -> FloatArray:
        """Roll, pitch, yaw (URDF/ROS fixed axes X, Y, Z), pitch in [-pi/2, pi/2]."""
        r = self.rotation
        pitch = math.asin(max(-1.0, min(1.0, -r[2, 0])))
        if abs(r[2, 0]) < 1.0 - 1e-12:
            roll = math.atan2(r[2, 1], r[2, 2])
            yaw = math.atan2(r[1, 0], r[0, 0])
        else:  # gimbal lock: put everything in yaw
            roll = 0.0
            yaw = math.atan2(-r[0, 1], r[1, 1])
        return np.array([roll, pitch, yaw])

    # ------------------------------------------------------------ algebra
    def __matmul__(self, other: Pose) -> Pose:
        if not isinstance(other, Pose):
            return NotImplemented
        rot = quat_to_matrix(self.orientation)
        q = quat_multiply(self.orientation, other.orientation)
        return Pose.from_trusted_arrays(self.position + rot @ other.position, q / np.linalg.norm(q))

    __mul__ = __matmul__

    def inverse(self) -> Pose:
        """The inverse transform: ``p @ p.inverse()`` is the identity."""
        x, y, z, w = self.orientation
        qi = np.array([-x, -y, -z, w])
        return Pose.from_trusted_arrays(-(quat_to_matrix(qi) @ self.position), qi)

    def apply(self, points: npt.ArrayLike) -> FloatArray:
        """Transform a point (3,) or points (n, 3) from this pose's frame to its parent frame."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape[-1:] != (3,) or pts.ndim > 2:
            raise InvalidValueError(f"Pose.apply: expected a point (3,) or points (n, 3), got shape {pts.shape}")
        return pts @ self.rotation.T + self.position

    # ------------------------------------------------------------ comparisons
    def distance(self, other: Pose) -> tuple[float, float]:
        """``(translation distance in m, rotation angle in rad)`` between two poses."""
        if not isinstance(other, Pose):
            raise InvalidValueError(f"Pose.distance: expected a Pose, got {type(other).__name__}")
        dq = quat_multiply(self.inverse().orientation, other.orientation)
        return float(np.linalg.norm(self.position - other.position)), float(np.linalg.norm(rotation_vector(dq)))

    def isclose(self, other: Pose, atol: float = 1e-9, angle_tol: float = 1e-9) -> bool:
        """True when the positions agree within ``atol`` (m) and the orientations within ``angle_tol`` (rad)."""
        d, a = self.distance(other)
        return d <= atol and a <= angle_tol

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Pose):
            return NotImplemented
        return bool(
            np.array_equal(self.position, other.position) and np.array_equal(self.orientation, other.orientation)
        )

    def __hash__(self) -> int:
        return hash((self.position.tobytes(), self.orientation.tobytes()))

    def __repr__(self) -> str:
        p = ", ".join(f"{v:.6g}" for v in self.position)
        q = ", ".join(f"{v:.6g}" for v in self.orientation)
        return f"Pose(position=[{p}], orientation=[{q}])"

    def __reduce__(self) -> tuple[Any, ...]:
        return (Pose, (self.position.tolist(), self.orientation.tolist()))


class BaseState:
    """Where a robot's base is and how it moves: ``pose`` in the world, ``linear_velocity`` and
    ``angular_velocity`` (3,) in the world frame, like ``nav_msgs/Odometry`` without covariances.

    ``linear_velocity`` is the velocity of the base frame's origin (m/s), ``angular_velocity``
    the base's rotation rate (rad/s); ``stamp`` is robot time (s). A fixed base is the world's
    identity pose at rest. Immutable; the arrays are read-only.
    """

    __slots__ = ("angular_velocity", "linear_velocity", "pose", "stamp")

    pose: Pose
    linear_velocity: FloatArray
    angular_velocity: FloatArray
    stamp: float

    def __init__(
        self,
        pose: Pose,
        linear_velocity: Sequence[float] | npt.ArrayLike = (0.0, 0.0, 0.0),
        angular_velocity: Sequence[float] | npt.ArrayLike = (0.0, 0.0, 0.0),
        stamp: float = 0.0,
    ) -> None:
        if not isinstance(pose, Pose):
            raise InvalidValueError(f"pose: expected a Pose, got {type(pose).__name__}")
        object.__setattr__(self, "pose", pose)
        object.__setattr__(self, "linear_velocity", _frozen(_vector(linear_velocity, 3, "linear_velocity")))
        object.__setattr__(self, "angular_velocity", _frozen(_vector(angular_velocity, 3, "angular_velocity")))
        object.__setattr__(self, "stamp", float(stamp))

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"BaseState is immutable (cannot set {name!r})")

    @property
    def position(self) -> FloatArray:
        """The base's position in the world (m), ``pose.position``."""
        return self.pose.position

    @property
    def height(self) -> float:
        """The base's height above the world's ``z = 0`` (the ground plane of a floating base), m."""
        return float(self.pose.position[2])

    def __repr__(self) -> str:
        return (
            f"BaseState(pose={self.pose!r}, linear_velocity={self.linear_velocity.tolist()}, "
            f"angular_velocity={self.angular_velocity.tolist()}, stamp={self.stamp:g})"
        )
