"""Immutable value types: joint metadata, joint state, joint commands.

Units are SI and radians; joint names are exactly as in the URDF (the ROS
``sensor_msgs/JointState`` convention).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal, get_args

import numpy as np
import numpy.typing as npt

from .errors import InvalidValueError, UnsupportedModeError

__all__ = ["MODES", "AppliedCommand", "CommandMode", "JointCommand", "JointInfo", "JointState"]

CommandMode = Literal["position", "velocity", "effort"]
MODES: tuple[CommandMode, ...] = get_args(CommandMode)

FloatArray = npt.NDArray[np.float64]


def _frozen(a: npt.ArrayLike) -> FloatArray:
    arr = np.array(a, dtype=np.float64)  # always a private copy
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, slots=True)
class JointInfo:
    """One actuated joint, as described by the URDF (plus robot.yaml overrides).

    ``lower``/``upper`` are ``-inf``/``inf`` for continuous joints.
    ``max_acceleration`` and ``max_jerk`` are not part of URDF; they come from
    robot.yaml ``joint_limits`` (ros2_control style) or a conservative default.
    """

    name: str
    type: Literal["revolute", "continuous", "prismatic"]
    lower: float
    upper: float
    max_velocity: float
    max_effort: float
    max_acceleration: float = 10.0
    max_jerk: float = 200.0
    parent: str = ""
    child: str = ""
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def within(self, position: float, margin: float = 0.0) -> bool:
        """True when ``position`` lies within the limits shrunk by ``margin`` on both sides."""
        return self.lower + margin <= position <= self.upper - margin


@dataclass(frozen=True, slots=True)
class JointState:
    """Measured joint state, shaped like ``sensor_msgs/JointState``.

    Arrays are read-only and in ``names`` order; ``stamp`` is robot clock time (s).
    """

    names: tuple[str, ...]
    position: FloatArray
    velocity: FloatArray
    effort: FloatArray
    stamp: float

    def __post_init__(self) -> None:
        for attr in ("position", "velocity", "effort"):
            arr = getattr(self, attr)
            if not (isinstance(arr, np.ndarray) and not arr.flags.writeable):
                object.__setattr__(self, attr, _frozen(arr))

    @classmethod
    def from_arrays(
        cls, names: tuple[str, ...], position: FloatArray, velocity: FloatArray, effort: FloatArray, stamp: float
    ) -> JointState:
        """Build from float64 arrays the caller hands over (they become read-only), without copying.

        The control loop's fast path: the caller passes private copies of the right
        shape and gives up writing to them; nothing is re-validated.
        """
        self = object.__new__(cls)
        setattr_ = object.__setattr__
        position.setflags(write=False)
        velocity.setflags(write=False)
        effort.setflags(write=False)
        setattr_(self, "position", position)
        setattr_(self, "velocity", velocity)
        setattr_(self, "effort", effort)
        setattr_(self, "names", names)
        setattr_(self, "stamp", stamp)
        return self

    @classmethod
    def from_block(cls, names: tuple[str, ...], block: FloatArray, stamp: float) -> JointState:
        """Build from a ``(3, n)`` float64 array the caller hands over (rows position, velocity, effort).

        :meth:`from_arrays` of the rows, with one copy and one flag change for the three: the
        block becomes read-only, so its rows are read-only views that cannot be made writable.
        """
        self = _new(cls)
        block.setflags(write=False)
        _state_position(self, block[0])  # (each slot by its descriptor: no object.__setattr__ call)
        _state_velocity(self, block[1])
        _state_effort(self, block[2])
        _state_names(self, names)
        _state_stamp(self, stamp)
        return self

    def index(self, name: str) -> int:
        """Index of joint ``name`` in ``names``."""
        return self.names.index(name)

    def positions(self) -> dict[str, float]:
        """``{joint name: position}``."""
        return dict(zip(self.names, self.position.tolist(), strict=True))

    def velocities(self) -> dict[str, float]:
        """``{joint name: velocity}``."""
        return dict(zip(self.names, self.velocity.tolist(), strict=True))

    def efforts(self) -> dict[str, float]:
        """``{joint name: effort}``."""
        return dict(zip(self.names, self.effort.tolist(), strict=True))


def _freeze_values(
    values: Mapping[str, float] | Sequence[float] | npt.ArrayLike | None,
    what: str,
) -> Mapping[str, float] | tuple[float, ...] | None:
    if values is None:
        return None
    cls: type = type(values)
    if cls is list or cls is tuple:  # the common case (a .tolist()), before the ABC checks below
        try:
            return tuple(map(float, values))  # type: ignore[arg-type]
        except (TypeError, ValueError):
            pass  # the general path names the offending entry
    if isinstance(values, Mapping):
        try:  # fast path; the loop below only runs to name the offending entry
            out = {k: float(v) for k, v in values.items()}
            if all(type(k) is str for k in out):
                return MappingProxyType(out)
        except (TypeError, ValueError):
            pass
        out = {}
        for k, v in values.items():
            if not isinstance(k, str):
                raise InvalidValueError(f"{what}: joint names must be strings, got {k!r}")
            out[k] = _as_float(v, f"{what}[{k!r}]")
        return MappingProxyType(out)
    if isinstance(values, str | bytes):
        raise InvalidValueError(f"{what}: expected a mapping or a sequence of floats, got {values!r}")
    try:
        seq = list(np.asarray(values, dtype=object).ravel()) if not isinstance(values, Sequence) else list(values)
    except TypeError as exc:
        raise InvalidValueError(f"{what}: expected a mapping or a sequence of floats, got {values!r}") from exc
    try:
        return tuple(map(float, seq))
    except (TypeError, ValueError):
        return tuple(_as_float(v, f"{what}[{i}]") for i, v in enumerate(seq))


def _as_float(v: object, where: str) -> float:
    try:
        return float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise InvalidValueError(f"{where}: {v!r} is not a number") from exc


@dataclass(frozen=True, slots=True, init=False)
class JointCommand:
    """A command for some or all joints, as an immutable value.

    ``values`` is either ``{joint name: value}`` (a subset of joints) or a
    full-length sequence in ``robot.joints`` order. ``mode`` is "position"
    (rad or m), "velocity" (rad/s or m/s) or "effort" (N·m or N).

    In position mode, optional ``velocity`` and ``effort`` feed-forward terms
    (same shape as ``values``) are added by the joint servo:
    ``effort = kp*(q_des - q) + kd*(v_ff - v) + effort_ff``.

    ``robot.command(cmd)`` returns the command actually applied, an
    :class:`AppliedCommand` whose values are a mapping covering the joints it
    touched, after safety limiting.
    """

    mode: CommandMode
    values: Mapping[str, float] | tuple[float, ...]
    velocity: Mapping[str, float] | tuple[float, ...] | None = field(default=None)
    effort: Mapping[str, float] | tuple[float, ...] | None = field(default=None)

    def __init__(
        self,
        mode: CommandMode,
        values: Mapping[str, float] | Sequence[float] | npt.ArrayLike,
        velocity: Mapping[str, float] | Sequence[float] | npt.ArrayLike | None = None,
        effort: Mapping[str, float] | Sequence[float] | npt.ArrayLike | None = None,
    ) -> None:
        if mode not in MODES:
            raise UnsupportedModeError(f"unsupported command mode {mode!r}; expected one of {', '.join(MODES)}")
        if mode != "position" and (velocity is not None or effort is not None):
            raise InvalidValueError("velocity/effort feed-forward terms are only valid in position mode")
        _command_mode(self, mode)  # (each slot by its descriptor: no object.__setattr__ call)
        _command_values(self, _freeze_values(values, "values"))
        _command_velocity(self, None if velocity is None else _freeze_values(velocity, "velocity"))
        _command_effort(self, None if effort is None else _freeze_values(effort, "effort"))

    def __repr__(self) -> str:
        vals = dict(self.values) if isinstance(self.values, Mapping) else list(self.values)
        return f"JointCommand(mode={self.mode!r}, values={vals!r})"



class JointValues(Mapping[str, float]):
    """``{joint name: value}`` of an :class:`AppliedCommand`, read-only, in the command's joint order.

    A behavior that commands every tick rarely looks at what was applied: the dict is made on first use.
    """

    __slots__ = ("_dict", "_names", "_values")

    def __init__(self, names: tuple[str, ...], values: list[float]) -> None:
        self._names = names
        self._values = values
        self._dict: dict[str, float] | None = None

    def _mapping(self) -> dict[str, float]:
        d = self._dict
        if d is None:
            d = self._dict = dict(zip(self._names, self._values, strict=True))
        return d

    def __getitem__(self, name: str) -> float:
        return self._mapping()[name]

    def __contains__(self, name: object) -> bool:
        return name in self._mapping()

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)

    def __repr__(self) -> str:
        return f"JointValues({self._mapping()!r})"


_new = object.__new__


@dataclass(frozen=True, slots=True)
class AppliedCommand:
    """The command a robot actually applied (returned by ``robot.command``), after safety limiting.

    ``values`` (and the feed-forward ``velocity``/``effort``, when the command had
    them) map each joint the command touched to the value written, in the
    command's order. It can be sent again as is: ``await robot.command(applied)``.
    """

    mode: CommandMode
    values: Mapping[str, float]
    velocity: Mapping[str, float] | None = None
    effort: Mapping[str, float] | None = None

    @classmethod
    def of_arrays(cls, mode: CommandMode, names: tuple[str, ...], values: FloatArray, velocity: FloatArray | None,
                  effort: FloatArray | None) -> AppliedCommand:
        """The command applied to ``names`` (the arrays' values, copied): the command gate's, once per command.

        What the dataclass's ``__init__`` makes, without its four ``object.__setattr__`` calls (each
        slot is set by its own descriptor) and with :class:`JointValues` for the mappings.
        """
        self = _new(cls)
        _set_mode(self, mode)
        _set_values(self, JointValues(names, values.tolist()))
        _set_velocity(self, None if velocity is None else JointValues(names, velocity.tolist()))
        _set_effort(self, None if effort is None else JointValues(names, effort.tolist()))
        return self

    def as_command(self) -> JointCommand:
        """The same command as a :class:`JointCommand`."""
        return JointCommand(self.mode, dict(self.values), velocity=self.velocity, effort=self.effort)

    def __repr__(self) -> str:
        ff = "".join(
            f", {k}={dict(v)!r}" for k, v in (("velocity", self.velocity), ("effort", self.effort)) if v is not None
        )
        return f"AppliedCommand(mode={self.mode!r}, values={dict(self.values)!r}{ff})"


#: the slots of the frozen value types the control path makes per call, set by their descriptors (half the
#: cost of ``object.__setattr__``, which looks each name up and parses an argument tuple)
_state_position, _state_velocity, _state_effort, _state_names, _state_stamp = (
    JointState.__dict__[name].__set__ for name in ("position", "velocity", "effort", "names", "stamp"))
_command_mode, _command_values, _command_velocity, _command_effort = (
    JointCommand.__dict__[name].__set__ for name in ("mode", "values", "velocity", "effort"))
_set_mode, _set_values, _set_velocity, _set_effort = (
    AppliedCommand.__dict__[name].__set__ for name in ("mode", "values", "velocity", "effort"))
