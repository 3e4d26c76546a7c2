"""The values of the motion layer: result codes, phases, results, tolerances, feedback, and the
shared constants and helpers of the executor.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np

from ..backend import ModeCode
from ..errors import InvalidValueError, UnknownJointError

if TYPE_CHECKING:
    from ..pose import Pose




_POS = int(ModeCode.POSITION)  # a plain int: numpy compares arrays with an IntEnum member slowly


_TWO_PI = 2.0 * math.pi


#: (position rad or m, velocity rad/s or m/s): a joint whose measured state is this close to its
#: setpoint (plus the servo's lag ``kd/kp * |v|`` at speed) is tracking it; an abort then starts its
#: stop from the setpoint (the same state up to servo accuracy, no jump), else from the measured state
TRACKING_BAND = (0.02, 0.2)


#: fraction of max_acceleration the speed-scaling ramp may add to a trajectory's own acceleration
_SCALE_ACC_MARGIN = 0.95


_MAX_STRETCH_ITERATIONS = 12


#: the ``poses`` of a feedback message nobody asked link poses for (shared, immutable)
_NO_POSES: Mapping[str, Pose] = MappingProxyType({})
#: an ended offloaded goal's joints are at rest when their mean speed stays below this (rad/s or m/s) ...
_REMOTE_STILL_SPEED = 1e-2
#: ... for this long (s): then the setpoint holds there and the backend streams again
_REMOTE_STILL = 0.1


#: a planned position beyond the bounds by more than this is not float noise (rad or m)
_BOUND_TOL = 2e-6


class ResultCode(enum.IntEnum):
    """FollowJointTrajectory result codes, plus the outcomes of an action goal."""

    SUCCESSFUL = 0
    INVALID_GOAL = -1
    INVALID_JOINTS = -2
    #: a controller refused a goal stamped too far in the past (offloaded goals, :mod:`agentsdk.offload`)
    OLD_HEADER_TIMESTAMP = -3
    PATH_TOLERANCE_VIOLATED = -4
    GOAL_TOLERANCE_VIOLATED = -5
    #: motion.cancel() or the awaiting task was cancelled: decelerated and holding
    CANCELED = -10
    #: replaced by a newer follow() on overlapping joints
    PREEMPTED = -11
    #: stopped by the safety layer (e-stop, fault), the robot closing, or a setpoint step the
    #: position-step limiter would have had to clip
    ABORTED = -12


class MotionPhase(enum.Enum):
    """Where a running motion is in its life (internal bookkeeping, shown in debug logs)."""

    #: scheduled with a future ``start_time``: validated, waiting for its start
    PENDING = "pending"
    #: sampling its trajectory
    FOLLOW = "follow"
    #: the trajectory has ended; waiting for the goal tolerance within ``goal_time``
    SETTLE = "settle"
    #: decelerating to rest (cancel, preemption, abort, e-stop)
    STOPPING = "stopping"
    #: finished: its result is set and it writes nothing
    DEAD = "dead"


@dataclass(frozen=True, slots=True)
class MotionResult:
    """How a motion ended.

    A FollowJointTrajectory-style result code, the final error per joint, a message and the robot time.
    """

    code: ResultCode
    #: final position error per joint (desired goal - actual, wrapped for continuous joints), rad or m
    error: Mapping[str, float]
    message: str = ""
    #: robot time when the motion ended
    time: float = 0.0

    @property
    def ok(self) -> bool:
        """True when the motion ended SUCCESSFUL."""
        return self.code is ResultCode.SUCCESSFUL


def _check_tolerance_value(value: object, what: str) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InvalidValueError(f"{what} tolerance must be a number, got {value!r}") from None
    if not v > 0.0:  # NaN, zero and negatives
        raise InvalidValueError(f"{what} tolerance must be > 0 (math.inf: not checked), got {value!r}")
    return v


@dataclass(frozen=True, slots=True)
class Tolerances:
    """Per-joint tolerances (a float for all joints, or ``{joint: value}``), rad or m.

    ``path``: max ``|desired - actual|`` position error while moving (None: not checked).
    ``goal``: max ``|goal - actual|`` position error at the end (None: not checked).
    ``goal_time``: how long after the trajectory's end (in trajectory time, which speed
    scaling slows down) the goal tolerance may take to be met; 0 means no slack
    (``math.inf``: wait indefinitely). Values must be > 0 (``math.inf`` = not checked);
    NaN, zero or negative values raise :class:`InvalidValueError` here.
    Errors of ``continuous`` joints wrap around (shortest angle).
    """

    path: float | Mapping[str, float] | None = None
    goal: float | Mapping[str, float] | None = 0.02
    goal_time: float = 1.0

    def __post_init__(self) -> None:
        for what in ("path", "goal"):
            value = getattr(self, what)
            if value is None:
                continue
            if isinstance(value, Mapping):
                for name, v in value.items():
                    if not isinstance(name, str):
                        raise InvalidValueError(f"{what} tolerance: joint names must be strings, got {name!r}")
                    _check_tolerance_value(v, f"{what} ({name!r})")
            else:
                _check_tolerance_value(value, what)
        try:
            gt = float(self.goal_time)
        except (TypeError, ValueError):
            raise InvalidValueError(f"goal_time must be a number of seconds, got {self.goal_time!r}") from None
        if not gt >= 0.0:
            raise InvalidValueError(f"goal_time must be >= 0 s (math.inf: wait indefinitely), got {self.goal_time!r}")


@dataclass(frozen=True, slots=True)
class Feedback:
    """Like FollowJointTrajectory feedback: desired, actual and error at ``time``.

    ``poses`` and ``desired_poses`` hold the poses (root frame) of the links chosen with
    ``motion.feedback(links=...)``; empty when no links were chosen.
    """

    time: float
    joint_names: tuple[str, ...]
    desired_positions: np.ndarray
    desired_velocities: np.ndarray
    actual_positions: np.ndarray
    actual_velocities: np.ndarray
    #: desired - actual position (wrapped for continuous joints)
    error: np.ndarray
    #: 0.0 at the start, 1.0 at the end of the trajectory (in trajectory time)
    progress: float
    #: ``{link: Pose}`` of the chosen links at the measured state of ``time`` (all joints' measured
    #: positions), computed host-side by ``robot.kinematics``
    poses: Mapping[str, Pose] = field(default_factory=lambda: _NO_POSES)
    #: ``{link: Pose}`` of the chosen links with the motion's joints at their desired positions
    #: (the robot's other joints at their measured positions)
    desired_poses: Mapping[str, Pose] = field(default_factory=lambda: _NO_POSES)
    #: ``{sensor: reading}`` of the sensors chosen with ``motion.feedback(sensors=...)``, latest at ``time``
    sensors: Mapping[str, Any] = field(default_factory=lambda: _NO_POSES)


def _link_names(links: Sequence[str] | str) -> tuple[str, ...]:
    """``links`` as a tuple of names: one name, or a sequence of names."""
    if isinstance(links, str):
        return (links,)
    try:
        names = tuple(links)
    except TypeError:
        raise InvalidValueError(f"links must be a link name or a sequence of link names, got {links!r}") from None
    for link in names:
        if not isinstance(link, str):
            raise InvalidValueError(f"links must be link names (str), got {link!r}")
    return names


def _per_joint(value: float | Mapping[str, float] | None, names: tuple[str, ...], what: str) -> np.ndarray:
    if value is None:
        return np.full(len(names), np.inf)
    if isinstance(value, Mapping):
        unknown = set(value) - set(names)
        if unknown:
            raise UnknownJointError(f"{what} tolerance for joints not in the trajectory: {sorted(unknown)}")
        return np.array([_check_tolerance_value(value[n], f"{what} ({n!r})") if n in value else np.inf
                         for n in names])
    return np.full(len(names), _check_tolerance_value(value, what))


def _wrap_angle(x: np.ndarray) -> np.ndarray:
    """``x`` wrapped into [-pi, pi) (shortest angular distance)."""
    return np.remainder(x + math.pi, _TWO_PI) - math.pi


def _turns_to(current: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Whole turns (multiples of 2*pi) to add to ``target`` so it is the nearest equivalent of ``current``.

    Like JTC's ``wraparound_joint`` (angles::shortest_angular_distance): at exactly half a turn
    the joint turns in the direction of the target's raw value.
    """
    dist = _wrap_angle(target - current)
    half = np.abs(np.abs(dist) - math.pi) < 1e-9
    dist = np.where(half, np.where(target > current, np.abs(dist), -np.abs(dist)), dist)
    turns: np.ndarray = np.round(((current + dist) - target) / _TWO_PI) * _TWO_PI
    return turns
