"""Validation of a direct joint command against one robot: names, length, finiteness, mode.

The first step of the command gate (:meth:`agentsdk.safety.SafetyLayer.admit`): a command is
checked here, before anything is locked, limited or written; the control loop sees only
validated, limited commands. Pure functions of the command and the robot's joint names.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence

import numpy as np

from .errors import InvalidValueError, UnknownJointError, UnsupportedModeError
from .types import FloatArray, JointCommand

__all__ = ["ResolvedCommand", "map_values", "resolve_command"]

#: ``(indices, values, velocity_ff, effort_ff)`` of a validated command
ResolvedCommand = tuple[np.ndarray, FloatArray, FloatArray | None, FloatArray | None]


def resolve_command(
    cmd: object, names: Sequence[str], index: Mapping[str, int], modes: Collection[str], backend: str
) -> ResolvedCommand:
    """Map a command onto joint indices; validate its type, mode, names, length and finiteness.

    ``names``/``index``: the robot's joints in order and by name; ``modes``: the command modes
    the backend ``backend`` supports. Returns ``(indices, values, velocity_ff, effort_ff)``;
    raises a :class:`~agentsdk.errors.CommandRejected` subclass naming the problem.
    """
    if not isinstance(cmd, JointCommand):
        raise InvalidValueError(f"expected a JointCommand, got {type(cmd).__name__}")
    if cmd.mode not in modes:
        raise UnsupportedModeError(
            f"backend {backend!r} does not support {cmd.mode!r} commands (supported: {', '.join(sorted(modes))})"
        )
    idx, values = map_values(cmd.values, "values", names, index)
    vel = eff = None
    if cmd.velocity is not None:
        vidx, vel = map_values(cmd.velocity, "velocity", names, index)
        if not np.array_equal(vidx, idx):
            raise InvalidValueError("velocity feed-forward must name the same joints as values")
    if cmd.effort is not None:
        eidx, eff = map_values(cmd.effort, "effort", names, index)
        if not np.array_equal(eidx, idx):
            raise InvalidValueError("effort feed-forward must name the same joints as values")
    return idx, values, vel, eff


def map_values(
    values: Mapping[str, float] | tuple[float, ...], what: str, names: Sequence[str], index: Mapping[str, int]
) -> tuple[np.ndarray, FloatArray]:
    """``(indices, values)`` of a mapping by joint name or a full-length sequence; checks finiteness."""
    if isinstance(values, Mapping):
        if not values:
            raise InvalidValueError(f"{what}: empty command")
        try:
            idx = np.fromiter((index[k] for k in values), dtype=np.intp, count=len(values))
        except KeyError as exc:
            raise UnknownJointError(
                f"unknown joint {exc.args[0]!r}; this robot's joints are: {', '.join(names)}"
            ) from None
        arr = np.fromiter(values.values(), dtype=np.float64, count=len(values))
    else:
        if len(values) != len(names):
            raise InvalidValueError(
                f"{what}: expected {len(names)} values (one per joint: {', '.join(names)}), got {len(values)}"
            )
        idx = np.arange(len(names))
        arr = np.asarray(values, dtype=np.float64)
    # NaN propagates through the largest and the smallest value, an infinity shows in one of them
    # (two ufunc reductions: ndarray.any's Python wrapper costs more on a few joints)
    if arr.size and not (math.isfinite(np.maximum.reduce(arr)) and math.isfinite(np.minimum.reduce(arr))):
        bad = ~np.isfinite(arr)
        j = int(idx[int(np.argmax(bad))])
        raise InvalidValueError(f"{what}: non-finite value {float(arr[bad][0])} for joint {names[j]!r}")
    return idx, arr
