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

__all__ = ["CommandShapes", "ResolvedCommand", "map_values", "resolve_command"]

#: float64 as a dtype instance (numpy converts a scalar type given as dtype on every call)
_F64 = np.dtype(np.float64)

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
    cmd = _check_kind(cmd, modes, backend)
    idx, values = map_values(cmd.values, "values", names, index)
    vel = eff = None
    if cmd.velocity is not None:
        vidx, vel = map_values(cmd.velocity, "velocity", names, index)
        _check_same_joints(vidx, idx, "velocity")
    if cmd.effort is not None:
        eidx, eff = map_values(cmd.effort, "effort", names, index)
        _check_same_joints(eidx, idx, "effort")
    return idx, values, vel, eff


def _check_kind(cmd: object, modes: Collection[str], backend: str) -> JointCommand:
    """``cmd`` if it is a :class:`JointCommand` in a mode the backend supports, else the error naming why."""
    if not isinstance(cmd, JointCommand):
        raise InvalidValueError(f"expected a JointCommand, got {type(cmd).__name__}")
    if cmd.mode not in modes:
        raise UnsupportedModeError(
            f"backend {backend!r} does not support {cmd.mode!r} commands (supported: {', '.join(sorted(modes))})"
        )
    return cmd


def _check_same_joints(ff_idx: np.ndarray, idx: np.ndarray, what: str) -> None:
    """A feed-forward must name the joints its command's values name (same indices, same order)."""
    if ff_idx is not idx and not np.array_equal(ff_idx, idx):
        raise InvalidValueError(f"{what} feed-forward must name the same joints as values")


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
    _check_finite(arr, idx, what, names)
    return idx, arr


def _check_finite(arr: FloatArray, idx: np.ndarray, what: str, names: Sequence[str]) -> None:
    """Raise :class:`InvalidValueError` naming the first joint of ``idx`` whose value is NaN or infinite."""
    # NaN propagates through the largest and the smallest value, an infinity shows in one of them
    # (two ufunc reductions: ndarray.any's Python wrapper costs more on a few joints)
    if arr.size and not (math.isfinite(np.maximum.reduce(arr)) and math.isfinite(np.minimum.reduce(arr))):
        bad = ~np.isfinite(arr)
        j = int(idx[int(np.argmax(bad))])
        raise InvalidValueError(f"{what}: non-finite value {float(arr[bad][0])} for joint {names[j]!r}")


class CommandShapes:
    """:func:`resolve_command` for one robot, with the joint indices of each command shape made once.

    A behavior that commands every tick sends the same shape again and again (a full-length
    sequence, or a mapping naming the same joints in the same order); its joint-name lookup,
    index array and joint names are validated the first time and reused after that (a bounded
    cache: past :attr:`LIMIT` distinct joint sets, new ones are mapped every time). The checks
    and their errors are :func:`resolve_command`'s, in the same order; values are converted and
    checked for finiteness on every command.
    """

    #: distinct joint-name tuples of mapping commands kept
    LIMIT = 256

    def __init__(self, names: Sequence[str], index: Mapping[str, int]) -> None:
        self._names = tuple(names)
        self._index = index
        full = np.arange(len(self._names), dtype=np.intp)
        full.flags.writeable = False
        #: the (read-only) indices of a full-length command: every joint in order
        self.full = full
        self._by_keys: dict[tuple[str, ...], tuple[np.ndarray, tuple[str, ...]]] = {}

    def resolve(
        self, cmd: object, modes: Collection[str], backend: str
    ) -> tuple[np.ndarray, tuple[str, ...], FloatArray, FloatArray | None, FloatArray | None]:
        """``(indices, joint names, values, velocity_ff, effort_ff)`` of a validated command.

        The index array is shared between commands of the same shape (read-only). Raises what
        :func:`resolve_command` raises for the same command.
        """
        if type(cmd) is not JointCommand or cmd.mode not in modes:  # (the common case without a call)
            cmd = _check_kind(cmd, modes, backend)
        idx, names, values = self._map(cmd.values, "values")
        vel = eff = None
        if cmd.velocity is not None:
            vidx, _, vel = self._map(cmd.velocity, "velocity")
            _check_same_joints(vidx, idx, "velocity")
        if cmd.effort is not None:
            eidx, _, eff = self._map(cmd.effort, "effort")
            _check_same_joints(eidx, idx, "effort")
        return idx, names, values, vel, eff

    def _map(
        self, values: Mapping[str, float] | tuple[float, ...], what: str
    ) -> tuple[np.ndarray, tuple[str, ...], FloatArray]:
        """:func:`map_values` with the indices (and names) of a known shape taken from the cache."""
        names = self._names
        if type(values) is not tuple and isinstance(values, Mapping):  # (a tuple first: no ABC check)
            keys = tuple(values)
            hit = self._by_keys.get(keys)
            if hit is None:
                idx, arr = map_values(values, what, names, self._index)
                idx.flags.writeable = False
                hit = (idx, tuple(names[i] for i in idx.tolist()))
                if len(self._by_keys) < self.LIMIT:
                    self._by_keys[keys] = hit
                return hit[0], hit[1], arr
            idx, keys = hit
            total = sum(values.values())
            arr = np.fromiter(values.values(), _F64, len(keys))
        else:
            if len(values) != len(names):
                raise InvalidValueError(
                    f"{what}: expected {len(names)} values (one per joint: {', '.join(names)}), got {len(values)}"
                )
            idx, keys = self.full, names
            total = sum(values)
            arr = np.array(values, _F64)  # (a dtype instance, not np.float64: half the call's cost)
        # a JointCommand holds Python floats: their sum is finite when every value is (NaN and the
        # infinities propagate); a non-finite sum (or an overflow) takes the array check, which names
        # the joint
        if not math.isfinite(total):
            _check_finite(arr, idx, what, names)
        return idx, keys, arr
