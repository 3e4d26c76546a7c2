"""Safety checks: the per-tick rules that latch an e-stop when they fail.

A :data:`SafetyCheck` is ``check(t, state) -> SafetyViolation | None``; the safety layer
(:mod:`agentsdk.safety`) runs every registered check each tick while motion is allowed.
This module holds the check protocol, the violation value and the built-in measured-position
check; it imports nothing above the control loop's state view, so checks (the following-error
check, sensor limits) depend on it, not on the safety layer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from .loop import StateView
from .types import FloatArray, JointInfo

__all__ = ["BlockCheck", "MeasuredPositionCheck", "SafetyCheck", "SafetyViolation"]

#: a pluggable safety check: ``check(t, state) -> SafetyViolation | None``, run every tick while motion is allowed
SafetyCheck = Callable[[float, StateView], "SafetyViolation | None"]


@runtime_checkable
class BlockCheck(Protocol):
    """A :data:`SafetyCheck` that can also judge a block of K lockstep ticks at once (issue 28, block lockstep).

    ``ts`` (K,) are the ticks' robot times, ``states`` (K, 3, n) their measured state blocks
    (position, velocity, effort rows, as :attr:`StateView.block`) and ``setpoints`` (K, n) the
    position setpoint each tick wrote. :meth:`block_quiet` returns how many leading ticks the
    check passes *quietly*: called once per tick it would return None each time and change
    nothing but what :meth:`commit_block` reproduces. The tick it stops at (K: none) must run
    through ``__call__`` instead. :meth:`commit_block` then brings the check's state to where
    ``k`` quiet calls would have left it. The mode, enabled and gain rows of the setpoint are
    the live ones (constant over a block).
    """

    def __call__(self, t: float, state: StateView) -> SafetyViolation | None:
        """The per-tick check."""

    def block_ready(self) -> bool:
        """False when :meth:`block_quiet` would return 0 whatever the states (a cheap test before a block runs)."""

    def block_quiet(self, ts: FloatArray, states: FloatArray, setpoints: FloatArray) -> int:
        """How many leading ticks of the block pass quietly."""

    def commit_block(self, ts: FloatArray, states: FloatArray, setpoints: FloatArray, k: int) -> None:
        """Take the state ``k`` quiet per-tick calls leave."""


@dataclass(frozen=True, slots=True)
class SafetyViolation:
    """What a :data:`SafetyCheck` returns to stop the robot: a latched e-stop of ``category``."""

    kind: str
    detail: str
    joint: str | None = None
    #: IEC 60204-1 stop category of the e-stop it triggers
    category: int = 2


class MeasuredPositionCheck:
    """Built-in :data:`SafetyCheck`: a measured position beyond a joint's limits by more than ``tolerance``.

    Simulated joint limits are soft and a real joint can be pushed past its limit
    (a collision, a wrong effort command): that is a protective stop, not something
    to keep driving. A joint is watched once it has been measured inside its limits
    (+ tolerance): a robot switched on outside them can still be moved back in.
    """

    def __init__(self, joints: tuple[JointInfo, ...], tolerance: float, category: int) -> None:
        self._lo = np.array([j.lower for j in joints]) - tolerance
        self._hi = np.array([j.upper for j in joints]) + tolerance
        self._names = tuple(j.name for j in joints)
        self._tol = tolerance
        self._category = category
        self._armed = np.zeros(len(joints), dtype=bool)
        self._all_armed = False
        n = len(joints)
        # allocation-free per tick: [q, -q] >= [lo, -hi] in one comparison (NaN compares False: outside)
        self._bounds = np.vstack([self._lo, -self._hi])
        self._pm_q = np.zeros((2, n))
        self._pm_rows = (self._pm_q[0], self._pm_q[1])  # views made once (a broadcast ufunc allocates an iterator)
        self._ok = np.zeros((2, n), dtype=bool)
        #: ``ok.tobytes()`` when every comparison holds (a bytes compare is ~5x cheaper than np.count_nonzero)
        self._all_ok = np.ones((2, n), dtype=bool).tobytes()

    def block_ready(self) -> bool:
        """:class:`BlockCheck`: every joint is armed."""
        return self._all_armed

    def fused_bounds(self) -> tuple[FloatArray, FloatArray]:
        """``(lo, hi)`` with the tolerance: the rule as ``lo <= q`` and ``q <= hi`` (the safety layer's fused
        tick; the same comparisons, NaN fails both). Only while every joint is armed (:meth:`block_ready`)
        does a pass of both mean that :meth:`__call__` would return None and change nothing.
        """
        return self._bounds[0], -self._bounds[1]

    def block_quiet(self, ts: FloatArray, states: FloatArray, setpoints: FloatArray) -> int:
        """:class:`BlockCheck`: leading ticks with every joint measured inside (0 until every joint is armed)."""
        if not self._all_armed:
            return 0  # arming changes state: per tick until every joint is armed
        q = states[:, 0, :]
        # the per-tick comparison [q, -q] >= [lo, -hi], on every tick at once (NaN: outside)
        ok = np.greater_equal(q, self._bounds[0]) & np.greater_equal(np.negative(q), self._bounds[1])
        quiet = ok.all(axis=1)
        return len(quiet) if quiet.all() else int(np.argmin(quiet))

    def commit_block(self, ts: FloatArray, states: FloatArray, setpoints: FloatArray, k: int) -> None:
        """:class:`BlockCheck`: a quiet tick changes nothing."""

    def __call__(self, t: float, state: StateView) -> SafetyViolation | None:
        """Return a violation naming the first watched joint outside its limits (+ tolerance), else None."""
        q = state.position
        plus, minus = self._pm_rows
        plus[...] = q
        np.negative(q, out=minus)
        ok = self._ok
        np.greater_equal(self._pm_q, self._bounds, out=ok)
        if self._all_armed and ok.tobytes() == self._all_ok:
            return None
        inside = ok[0] & ok[1]
        if not self._all_armed:
            self._armed |= inside
            self._all_armed = bool(self._armed.all())
        bad = self._armed & ~inside
        if not bad.any():
            return None
        j = int(np.argmax(bad))
        return SafetyViolation(
            "limit",
            f"measured position {float(q[j]):.4g} of joint {self._names[j]!r} is more than {self._tol:g} outside "
            f"its limits [{self._lo[j] + self._tol:.4g}, {self._hi[j] - self._tol:.4g}]",
            self._names[j],
            self._category,
        )
