"""The loaded robot: immutable records of links, joints, inertials, geometry and repairs.

A :class:`RobotDescription` is what every backend and tool works from. It is
the robot *after* the repairs the loader applied (each listed in
``repairs``), so both simulators receive exactly the same masses, inertias,
limits and collision geometry.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import UnknownJointError
from ..types import JointInfo

__all__ = [
    "ACTUATED_TYPES",
    "DEFAULT_VELOCITY",
    "Geometry",
    "Inertial",
    "JointRecord",
    "LinkRecord",
    "Mimic",
    "Repair",
    "RobotDescription",
    "quat_from_rpy",
    "rotation_from_rpy",
    "rpy_from_rotation",
]

Vec3 = tuple[float, float, float]

#: joint types the SDK commands (when they do not mimic another joint)
ACTUATED_TYPES = ("revolute", "continuous", "prismatic")

#: velocity limit used when a description gives none (or 0): rad/s for rotary, m/s for prismatic joints
DEFAULT_VELOCITY: Mapping[str, float] = {"revolute": 1.0, "continuous": 1.0, "prismatic": 0.25}


# --------------------------------------------------------------------------- small geometry helpers


def rotation_from_rpy(rpy: Vec3) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw to a rotation matrix, ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def rpy_from_rotation(rot: np.ndarray) -> Vec3:
    """Inverse of :func:`rotation_from_rpy` (pitch in [-pi/2, pi/2])."""
    sp = -float(rot[2, 0])
    if abs(sp) >= 1.0 - 1e-12:
        # gimbal lock: put everything in yaw
        pitch = math.copysign(math.pi / 2, sp)
        roll = 0.0
        yaw = math.atan2(-float(rot[0, 1]), float(rot[1, 1]))
        return (roll, pitch, yaw)
    pitch = math.asin(max(-1.0, min(1.0, sp)))
    roll = math.atan2(float(rot[2, 1]), float(rot[2, 2]))
    yaw = math.atan2(float(rot[1, 0]), float(rot[0, 0]))
    return (roll, pitch, yaw)


def quat_from_rpy(rpy: Vec3) -> tuple[float, float, float, float]:
    """URDF roll-pitch-yaw to a unit quaternion ``(w, x, y, z)`` (MuJoCo's order)."""
    r, p, y = (0.5 * a for a in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


# --------------------------------------------------------------------------- records


@dataclass(frozen=True, slots=True)
class Repair:
    """One change the loader made so that the simulators can take the robot.

    ``element`` names what was changed (``"link 'foot'"``), ``line`` is its line
    in the file when known, ``detail`` says what was wrong and what it became.
    """

    element: str
    detail: str
    line: int | None = None

    def __str__(self) -> str:
        where = f" (line {self.line})" if self.line else ""
        return f"{self.element}{where}: {self.detail}"


@dataclass(frozen=True, slots=True)
class Inertial:
    """Mass properties of a link in its own frame (URDF ``<inertial>``).

    ``xyz``/``rpy`` place the inertial frame; ``inertia`` is
    ``(ixx, ixy, ixz, iyy, iyz, izz)`` about the centre of mass in that frame.
    """

    mass: float
    xyz: Vec3 = (0.0, 0.0, 0.0)
    rpy: Vec3 = (0.0, 0.0, 0.0)
    inertia: tuple[float, float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    def tensor(self) -> np.ndarray:
        """The 3x3 inertia tensor in the inertial frame."""
        ixx, ixy, ixz, iyy, iyz, izz = self.inertia
        return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])

    def principal(self) -> tuple[Vec3, np.ndarray]:
        """Principal moments (ascending) and the rotation of the principal axes in the link frame.

        The rotation's columns are the principal axes; it is a proper rotation (det +1).
        """
        ixx, ixy, ixz, iyy, iyz, izz = self.inertia
        rot0 = rotation_from_rpy(self.rpy)
        if ixy == 0.0 and ixz == 0.0 and iyz == 0.0:
            order = sorted(range(3), key=lambda i: (ixx, iyy, izz)[i])
            moments = tuple(float((ixx, iyy, izz)[i]) for i in order)
            axes = np.eye(3)[:, order]
        else:
            values, axes = np.linalg.eigh(self.tensor())
            moments = tuple(float(v) for v in values)
        if np.linalg.det(axes) < 0:
            axes = axes.copy()
            axes[:, 2] = -axes[:, 2]
        return (moments[0], moments[1], moments[2]), rot0 @ axes


@dataclass(frozen=True, slots=True)
class Geometry:
    """One ``<visual>`` or ``<collision>`` shape of a link, in the link frame.

    ``size``: box ``(x, y, z)`` edge lengths; sphere ``(radius,)``; cylinder and
    capsule ``(radius, length)``; mesh the ``scale`` ``(sx, sy, sz)``.
    ``filename`` is the resolved absolute mesh path (meshes only).
    """

    kind: Literal["box", "sphere", "cylinder", "capsule", "mesh"]
    size: tuple[float, ...]
    xyz: Vec3 = (0.0, 0.0, 0.0)
    rpy: Vec3 = (0.0, 0.0, 0.0)
    filename: Path | None = None
    name: str | None = None
    rgba: tuple[float, float, float, float] | None = None


@dataclass(frozen=True, slots=True)
class LinkRecord:
    """One link: repaired mass properties (``None``: massless), visuals and collision shapes.

    ``inertial_as_written`` keeps the file's values when a repair changed them.
    """

    name: str
    inertial: Inertial | None = None
    visuals: tuple[Geometry, ...] = ()
    collisions: tuple[Geometry, ...] = ()
    inertial_as_written: Inertial | None = None

    @property
    def mass(self) -> float:
        """Mass in kg (0 for a link without ``<inertial>``)."""
        return self.inertial.mass if self.inertial is not None else 0.0


@dataclass(frozen=True, slots=True)
class JointRecord:
    """One URDF ``<joint>`` of any type, after the loader's repairs.

    ``lower``/``upper``/``velocity``/``effort`` are ``None`` for joints without
    limits (fixed); a continuous joint has ``lower=-inf, upper=inf``; an effort
    limit the file does not give (or gives as 0) is ``inf``. ``axis`` is
    normalised. ``mimic`` names the joint this one follows (already resolved to
    a commanded joint through mimic chains):
    ``q = mimic_multiplier * q[mimic] + mimic_offset``.
    """

    name: str
    type: str
    parent: str
    child: str
    xyz: Vec3 = (0.0, 0.0, 0.0)
    rpy: Vec3 = (0.0, 0.0, 0.0)
    axis: Vec3 = (1.0, 0.0, 0.0)
    lower: float | None = None
    upper: float | None = None
    velocity: float | None = None
    effort: float | None = None
    damping: float = 0.0
    friction: float = 0.0
    mimic: str | None = None
    mimic_multiplier: float = 1.0
    mimic_offset: float = 0.0

    @property
    def actuated(self) -> bool:
        """True for revolute/continuous/prismatic joints that do not mimic another joint."""
        return self.type in ACTUATED_TYPES and self.mimic is None

    @property
    def movable(self) -> bool:
        """True for revolute/continuous/prismatic joints (mimic joints included)."""
        return self.type in ACTUATED_TYPES

    @property
    def limited(self) -> bool:
        """True when the position range is finite."""
        return self.lower is not None and self.upper is not None and math.isfinite(self.lower - self.upper)


@dataclass(frozen=True, slots=True)
class Mimic:
    """A joint that follows a commanded joint: ``q[joint] = multiplier * q[leader] + offset``."""

    joint: str
    leader: str
    multiplier: float
    offset: float


@dataclass(frozen=True)
class RobotDescription:
    """A loaded robot description (URDF, xacro or MJCF).

    ``joints`` holds the commanded joints (revolute, continuous, prismatic;
    not mimic joints) in document order with their limits; use
    :func:`agentsdk.description.apply_overrides` for robot.yaml ``joint_limits``.
    ``all_joints`` and ``link_records`` hold the whole tree after repairs.

    ``format`` is ``"urdf"`` (from a URDF or xacro file: ``urdf_xml`` is the
    resolved, repaired URDF, every mesh an absolute path) or ``"mjcf"`` (a
    MuJoCo model: ``source`` is the MJCF file, which the MuJoCo backend loads
    itself with its ``<include>``s, assets and defaults; ``urdf_xml`` is empty;
    links and joints are read from the compiled model).
    """

    name: str
    source: Path
    urdf_xml: str = field(repr=False)
    joints: tuple[JointInfo, ...]
    all_joints: tuple[JointRecord, ...] = field(repr=False)
    links: tuple[str, ...]
    root_link: str
    mesh_files: tuple[Path, ...] = ()
    format: Literal["urdf", "mjcf"] = "urdf"
    link_records: tuple[LinkRecord, ...] = field(default=(), repr=False)
    #: changes the loader made so both simulators can take the robot (strict mode refuses them)
    repairs: tuple[Repair, ...] = field(default=(), repr=False)
    #: values the description does not give and the SDK filled in (not repairs: the file is legal)
    defaults: tuple[Repair, ...] = field(default=(), repr=False)
    #: an SRDF found beside the description (its ``<disable_collisions>`` are honoured)
    srdf: Path | None = None
    #: start positions the description itself gives (an MJCF keyframe, see ``default_state``)
    default_positions: Mapping[str, float] = field(default_factory=dict, repr=False)
    #: the named poses the description holds (MJCF keyframes): ``{name: {joint: position}}``
    named_states: Mapping[str, Mapping[str, float]] = field(default_factory=dict, repr=False)
    #: the named pose ``default_positions`` comes from (an MJCF keyframe), or None
    default_state: str | None = None
    #: servo gains the description declares per joint, ``{joint: (kp, kd)}`` in N·m/rad and N·m·s/rad
    #: (an MJCF position actuator's, see :mod:`agentsdk.description.actuators`): the robot author's gains
    declared_gains: Mapping[str, tuple[float, float]] = field(default_factory=dict, repr=False)

    @property
    def free_root(self) -> str | None:
        """The link a free (floating) joint attaches to the root (an MJCF ``<freejoint>``), or None.

        That link is the floating base: the simulators leave it free and report its pose. Only
        a body carrying commanded joints counts (a free object in a scene, a ball, is not the base).
        """
        commanded = {j.child for j in self.joints}
        children: dict[str, list[str]] = {}
        for j in self.all_joints:
            children.setdefault(j.parent, []).append(j.child)
        for j in self.all_joints:
            if j.type != "floating" or j.parent != self.root_link:
                continue
            stack = [j.child]
            while stack:
                link = stack.pop()
                if link in commanded:
                    return j.child
                stack.extend(children.get(link, ()))
        return None

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Names of the commanded joints, in ``joints`` order."""
        return tuple(j.name for j in self.joints)

    def joint(self, name: str) -> JointInfo:
        """The commanded joint called ``name``; raises ``UnknownJointError`` listing the known ones."""
        for j in self.joints:
            if j.name == name:
                return j
        raise UnknownJointError(
            f"robot '{self.name}' has no actuated joint '{name}'; known joints: {', '.join(self.joint_names)}"
        )

    def link(self, name: str) -> LinkRecord:
        """The link record called ``name`` (KeyError if unknown)."""
        for rec in self.link_records:
            if rec.name == name:
                return rec
        raise KeyError(f"robot '{self.name}' has no link '{name}'")

    def joint_record(self, name: str) -> JointRecord:
        """The joint record (any type) called ``name`` (KeyError if unknown)."""
        for rec in self.all_joints:
            if rec.name == name:
                return rec
        raise KeyError(f"robot '{self.name}' has no joint '{name}'")

    def child_joints(self, link: str) -> tuple[JointRecord, ...]:
        """Joints (any type) whose parent is ``link``, in document order."""
        return tuple(j for j in self.all_joints if j.parent == link)

    def parent_joint(self, link: str) -> JointRecord | None:
        """The joint whose child is ``link`` (None for the root)."""
        for j in self.all_joints:
            if j.child == link:
                return j
        return None

    @property
    def base_link(self) -> str:
        """The link a floating base floats by: the root link, or its single child.

        The child when the root is a massless link rigidly attached to it (ROS's
        ``world -> base_link`` pattern). With a free joint at the root (:attr:`free_root`), the
        link it carries.
        """
        free = self.free_root
        if free is not None:
            return free
        root = self.link(self.root_link) if any(r.name == self.root_link for r in self.link_records) else None
        out = self.child_joints(self.root_link)
        if (root is None or root.mass == 0.0) and len(out) == 1 and out[0].type == "fixed":
            return out[0].child
        return self.root_link

    @property
    def mimics(self) -> tuple[Mimic, ...]:
        """Joints that follow a commanded joint, in document order."""
        return tuple(
            Mimic(j.name, j.mimic, j.mimic_multiplier, j.mimic_offset)
            for j in self.all_joints
            if j.mimic is not None and j.movable
        )

    def tree_order(self) -> tuple[str, ...]:
        """Link names, every parent before its children (depth first, document order among siblings)."""
        out: list[str] = []
        stack = [self.root_link]
        while stack:
            link = stack.pop()
            out.append(link)
            stack.extend(reversed([j.child for j in self.child_joints(link)]))
        return tuple(out)

    def total_mass(self) -> float:
        """Sum of all link masses (kg), after repairs."""
        return float(sum(rec.mass for rec in self.link_records))

    def tree_lines(self) -> list[str]:
        """The kinematic tree in the spirit of ROS ``check_urdf``.

        A summary line, the root link, then one line per joint (type, axis,
        limits) ending with its child link, indented under its parent, e.g.
        ``└─ joint1 [revolute] z  lower=-3.140 upper=3.140 vel=2.5 effort=20 → link1``.
        """
        lines = [
            f"robot '{self.name}': root link '{self.root_link}', {len(self.links)} links, "
            f"{len(self.all_joints)} joints ({len(self.joints)} actuated)",
            self.root_link,
        ]

        def walk(link: str, indent: str) -> None:
            children = self.child_joints(link)
            for i, joint in enumerate(children):
                last = i == len(children) - 1
                lines.append(f"{indent}{'└─' if last else '├─'} {_joint_label(joint)} → {joint.child}")
                walk(joint.child, indent + ("   " if last else "│  "))

        walk(self.root_link, "")
        return lines

    def write_urdf(self, directory: str | Path, filename: str | None = None) -> Path:
        """Write ``urdf_xml`` to ``directory/filename`` (default ``<name>.urdf``) and return the path."""
        if self.format != "urdf":
            raise ValueError(f"robot '{self.name}' is an MJCF model ({self.source}); it has no URDF to write")
        path = Path(directory) / (filename or f"{self.name}.urdf")
        path.write_text(self.urdf_xml, encoding="utf-8")
        return path


def _fmt(v: float) -> str:
    return f"{v:g}"


def _axis_label(axis: Vec3) -> str:
    for i, letter in enumerate("xyz"):
        unit = [0.0, 0.0, 0.0]
        unit[i] = 1.0
        if all(math.isclose(a, u, abs_tol=1e-9) for a, u in zip(axis, unit, strict=True)):
            return letter
        if all(math.isclose(a, -u, abs_tol=1e-9) for a, u in zip(axis, unit, strict=True)):
            return "-" + letter
    return "axis=(" + " ".join(f"{a:.3g}" for a in axis) + ")"


def _joint_label(j: JointRecord) -> str:
    parts = [f"{j.name} [{j.type}]"]
    if j.type != "fixed":
        parts.append(" " + _axis_label(j.axis))
    limits: list[str] = []
    if j.type in ("revolute", "prismatic") and j.lower is not None and j.upper is not None:
        limits.append(f"lower={j.lower:.3f} upper={j.upper:.3f}")
    if j.type != "fixed" and j.velocity is not None and j.effort is not None:
        limits.append(f"vel={_fmt(j.velocity)} effort={_fmt(j.effort)}")
    if j.mimic is not None:
        limits.append(f"mimic={j.mimic} x{_fmt(j.mimic_multiplier)}{j.mimic_offset:+g}")
    if limits:
        parts.append("  " + " ".join(limits))
    return "".join(parts)
