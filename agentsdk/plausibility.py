"""Plausibility before authority: a measurement the physics cannot explain is a sensor fault.

The control loop passes every backend reading through one :class:`SensorGate` before it
becomes the measured state (:attr:`agentsdk.loop.ControlLoop.state`) that the safety layer,
the stop ramps, holds and observers use. The rule is the same on every backend, because
it is applied here, between ``Backend.read`` and the state buffer:

* every value (position, velocity, effort) must be finite;
* a position may move from the joint's last plausible position by at most
  ``sensor_jump_margin * max(max_velocity, |last plausible velocity|) * (elapsed + period) + sensor_jump_floor``,
  where ``elapsed`` is the time between the two readings' *samples*: a backend whose readings
  can be old (a bus: the newest reply may predate this cycle) reports each joint's age
  (:meth:`agentsdk.Backend.reading_age`), simulators read the present. A joint whose sensor
  is failing gains reach all the time it fails (it may have moved meanwhile); the extra
  period covers sampling jitter; a joint already moving faster than its limit (e.g. falling
  with torque off) keeps a reach that covers its own speed;
* a position more than ``tolerance`` (the safety layer's ``position_limit_tolerance``) outside
  the joint's limits must also be reachable *in one step* (at most two periods, within the time
  the sensor was still good) from the last plausible position, for a joint with torque on: a
  driven joint that is pushed past its limit gets there gradually, and a reading that lands
  there after a loop stall or a sensor outage does not count as gradual (a joint without torque
  moves freely; the jump rule still applies to it).

A reading that fails is a *sensor fault*: that joint's state keeps its last plausible
position, velocity and effort (the implausible value never reaches the state buffer), the
joint is marked suspect, and the gate reports it once (:meth:`SensorGate.take_new`) so the
safety layer can latch a fault and stop from the reference. A suspect joint's readings are
accepted again as soon as they are plausible relative to its last plausible state.

The per-tick path is allocation-free: preallocated scratch arrays and ufuncs with ``out=``;
the common case (every joint plausible, none suspect) compares one bytes string.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .types import JointInfo

__all__ = ["SensorGate", "SensorReport"]

#: the reach of a joint whose reading frame is being changed on purpose: any finite position
_FINITE = 1e300
#: the speed used for a joint without a velocity limit
_NO_LIMIT = 1e150


@dataclass(frozen=True, slots=True)
class SensorReport:
    """One joint whose reading failed the plausibility rule (what :meth:`SensorGate.take_new` returns)."""

    #: joint index in the loop's order
    index: int
    #: robot time of the reading (s)
    time: float
    #: which value failed: ``"position"``, ``"velocity"`` or ``"effort"``
    quantity: str
    #: the implausible value
    value: float
    #: the joint's last plausible value of that quantity
    last: float
    #: the largest change the rule allowed (position only; NaN otherwise)
    reach: float
    #: robot seconds since the joint's last plausible reading
    elapsed: float
    #: why, in words
    reason: str


class SensorGate:
    """Checks each reading against the last plausible state and writes only plausible joints.

    ``position``, ``velocity`` and ``effort`` are the loop's state rows: the gate writes them
    (they hold the last plausible state of every joint). ``margin``/``floor`` are the safety
    settings ``sensor_jump_margin``/``sensor_jump_floor``; ``tolerance`` is
    ``position_limit_tolerance`` (None: no limit rule). ``age`` returns how old each joint's
    reading is (s), or None when every reading is current (:meth:`agentsdk.Backend.reading_age`).
    ``changing``/``changes``: the backend's joints whose reading frame it is changing on purpose
    and the count of such changes in progress (:meth:`agentsdk.Backend.frame_change`). ``driven``
    returns which joints have torque on (default: all).
    """

    def __init__(
        self,
        joints: Sequence[JointInfo],
        position: np.ndarray,
        velocity: np.ndarray,
        effort: np.ndarray,
        *,
        margin: float,
        floor: float,
        tolerance: float | None,
        period: float,
        age: Callable[[], np.ndarray | None] | None = None,
        changing: np.ndarray | None = None,
        changes: list[int] | None = None,
        driven: Callable[[], np.ndarray] | None = None,
    ) -> None:
        n = len(joints)
        self.names = tuple(j.name for j in joints)
        self._position, self._velocity, self._effort = position, velocity, effort
        vmax = np.array([j.max_velocity for j in joints], dtype=float)
        #: per joint: the speed bound of the reach (a missing velocity limit disables the jump rule:
        #: a huge finite speed, so that no time elapsed still allows just the floor, not NaN)
        self._vmax = np.where(np.isfinite(vmax) & (vmax > 0.0), vmax, _NO_LIMIT)
        self._margin = float(margin)
        self._floor = float(floor)
        self._period = float(period)
        lower = np.array([j.lower for j in joints], dtype=float)
        upper = np.array([j.upper for j in joints], dtype=float)
        tol = math.inf if tolerance is None else float(tolerance)
        self._lo = np.where(np.isfinite(lower), lower - tol, -np.inf)
        self._hi = np.where(np.isfinite(upper), upper + tol, np.inf)
        self._tolerance = tolerance
        # scratch (allocation-free per tick)
        self._d = np.zeros(n)
        self._reach = np.zeros(n)
        self._reach_fast = np.zeros(n)
        self._dt = math.nan
        self._fin_v = np.zeros(n, dtype=bool)
        self._fin_e = np.zeros(n, dtype=bool)
        self._speed = np.zeros(n)
        self._ok = np.zeros(n, dtype=bool)
        self._outside = np.zeros(n, dtype=bool)
        self._above = np.zeros(n, dtype=bool)
        self._all_false = np.zeros(n, dtype=bool).tobytes()
        self._all_ok = np.ones(n, dtype=bool).tobytes()
        #: robot time of the last reading; while ``_uniform`` every joint's sample time is that
        self._t_read = 0.0
        self._uniform = False
        self._age = age
        self._changing = np.zeros(n, dtype=bool) if changing is None else changing
        self._changes = [0] if changes is None else changes
        #: which joints have torque on now (the limit rule's "in one step" holds for a driven joint)
        self._driven = driven
        #: robot time each joint's last plausible reading was sampled, and the new reading's
        self._t_ok = np.zeros(n)
        self._t_new = np.zeros(n)
        #: robot time of a suspect joint's first rejected reading (inf while plausible)
        self._t_bad = np.full(n, np.inf)
        #: a joint is suspect from its first implausible reading until it reads plausibly again
        self.suspect = np.zeros(n, dtype=bool)
        self._any_suspect = False
        #: joints flagged since the last acknowledgement (:meth:`take_new`), and their reports
        self._new: list[SensorReport] = []
        #: joints whose fault was reported and not yet cleared (reported once per latch)
        self._reported = np.zeros(n, dtype=bool)
        #: readings rejected since connect, per joint
        self.rejected = np.zeros(n, dtype=np.int64)
        #: block_quiet's work arrays (made on the first block)
        self._blk: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ queries
    @property
    def pending(self) -> bool:
        """True when a new sensor fault waits to be taken (:meth:`take_new`)."""
        return bool(self._new)

    def take_new(self) -> list[SensorReport]:
        """The sensor faults found since the last call (each joint once until :meth:`clear`)."""
        out, self._new = self._new, []
        return out

    def clear(self) -> None:
        """Forget which faults were reported (after a reset): a joint still failing is reported again."""
        self._reported[:] = False
        self._new = []

    # ------------------------------------------------------------------ readings
    def _sample_times(self, t: float) -> np.ndarray:
        """When each joint's reading was sampled (robot time), into the scratch ``_t_new``."""
        out = self._t_new
        age = self._age() if self._age is not None else None
        if age is None:
            out.fill(t)
        else:
            np.subtract(t, age, out=out)
        return out

    def baseline(self, q: np.ndarray, v: np.ndarray, e: np.ndarray, t: float) -> int:
        """Take a first reading as it is (at start); returns the index of a non-finite joint, or -1.

        A non-finite value is not copied (that joint keeps 0) and the joint is marked suspect.
        """
        bad = ~(np.isfinite(q) & np.isfinite(v) & np.isfinite(e))
        ok = ~bad
        np.copyto(self._position, q, where=ok)
        np.copyto(self._velocity, v, where=ok)
        np.copyto(self._effort, e, where=ok)
        self._t_ok[:] = self._sample_times(t)
        self._t_read = t
        self._uniform = False
        self._t_bad[:] = np.where(bad, t, np.inf)
        self.suspect[:] = bad
        self._any_suspect = bool(bad.any())
        return int(np.argmax(bad)) if self._any_suspect else -1

    def accept(self, q: np.ndarray, v: np.ndarray, e: np.ndarray, t: float) -> None:
        """Check a reading taken at robot time ``t`` and write its plausible joints into the state.

        Fast path (a backend whose readings are current, no suspect joint, no frame change): the
        reach with ``max_velocity`` alone, cached while the time between readings repeats (every
        tick in lockstep), one comparison and two finiteness checks. Anything else, or
        a joint beyond that reach, goes through :meth:`_full` (the velocity-aware reach, the
        samples' own times).
        """
        d = self._d
        np.subtract(q, self._position, out=d)
        np.abs(d, out=d)  # NaN stays NaN (and inf - inf is NaN): every comparison below is False
        age = self._age() if self._age is not None else None
        if age is not None or self._any_suspect or self._changes[0]:
            self._full(q, v, e, t, age)
            return
        dt = t - self._t_read
        if dt > 2.0 * self._period:  # a late reading (a stalled loop): the limit rule applies
            self._full(q, v, e, t, age)
            return
        reach = self._reach_fast
        if not abs(dt - self._dt) <= 1e-12:  # (the first time: NaN)
            self._dt = dt
            np.multiply(self._vmax, self._margin * (dt + self._period), out=reach)
            np.add(reach, self._floor, out=reach)
        ok, fin_v, fin_e, all_ok = self._ok, self._fin_v, self._fin_e, self._all_ok
        np.less_equal(d, reach, out=ok)
        # every velocity and effort finite: a finite sum of them says so without a ufunc (NaN and the
        # infinities propagate through the sum); a non-finite sum (one of them, or an overflow) asks
        # the elements as before
        if ok.tobytes() == all_ok and (
            math.isfinite(sum(v.tolist()) + sum(e.tolist()))
            or (np.isfinite(v, out=fin_v).tobytes() == all_ok and np.isfinite(e, out=fin_e).tobytes() == all_ok)
        ):
            self._position[...] = q
            self._velocity[...] = v
            self._effort[...] = e
            self._t_read = t
            self._uniform = True
            return
        self._full(q, v, e, t, age)

    def block_ready(self) -> bool:
        """False when :meth:`block_quiet` would return 0 whatever the readings (a cheap test before a block runs)."""
        return not self._any_suspect and not self._changes[0] and math.isfinite(self._dt)

    def block_quiet(self, ts: np.ndarray, states: np.ndarray) -> int:
        """How many leading readings of a lockstep block (``states`` (K, 3, n), taken at ``ts``) take the fast path.

        Block lockstep (issue 28): a reading is *quiet* when :meth:`accept` would take it through its
        fast path, every joint within the cached reach and finite, without recomputing the reach.
        Those readings are written as they are, so the position each is compared with is the
        previous reading of the block. The reading it stops at (K: none) must go through
        :meth:`accept`; :meth:`commit_block` takes the state ``k`` quiet readings leave.
        """
        K = len(ts)
        if K == 0 or self._any_suspect or self._changes[0]:
            return 0
        if self._age is not None and self._age() is not None:
            return 0  # readings that can be old: the full rule, per tick
        if not math.isfinite(self._dt):
            return 0  # the reach is computed on the first fast-path reading
        q = states[:, 0, :]
        d, ok, fin, dt = self._block_scratch(K)
        # each reading against the previous one (the last accepted, then the block's own)
        np.subtract(q[0], self._position, out=d[0])
        np.subtract(q[1:], q[:-1], out=d[1:])
        np.abs(d, out=d)
        dt[0] = ts[0] - self._t_read
        np.subtract(ts[1:], ts[:-1], out=dt[1:])
        np.less_equal(d, self._reach_fast, out=ok)
        # the common case at once: every time step the cached one (|dt - _dt| <= 1e-12 for all of them
        # exactly when it holds for the largest and the smallest: a rounded difference is monotone),
        # none late, every joint within reach, every velocity and effort finite
        hi, lo = float(np.maximum.reduce(dt)), float(np.minimum.reduce(dt))
        np.isfinite(states[:, 1:, :], out=fin)
        if (hi <= 2.0 * self._period and abs(hi - self._dt) <= 1e-12 and abs(lo - self._dt) <= 1e-12
                and np.logical_and.reduce(ok, axis=None) and np.logical_and.reduce(fin, axis=None)):
            return K
        # where it stops: the fast path's tests per reading
        quiet = (dt <= 2.0 * self._period) & (np.abs(dt - self._dt) <= 1e-12)
        quiet &= ok.all(axis=1)
        quiet &= fin.all(axis=(1, 2))
        return K if quiet.all() else int(np.argmin(quiet))

    def _block_scratch(self, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`block_quiet`'s work arrays for K readings (kept, grown when a longer block comes)."""
        scratch = self._blk
        if scratch is None or len(scratch[3]) < K:
            n = len(self._position)
            size = max(K, 2 * len(scratch[3]) if scratch is not None else 0)
            scratch = self._blk = (np.empty((size, n)), np.empty((size, n), dtype=bool),
                                   np.empty((size, 2, n), dtype=bool),
                                   np.empty(size))
        d, ok, fin, dt = scratch
        return d[:K], ok[:K], fin[:K], dt[:K]

    def commit_block(self, ts: np.ndarray, states: np.ndarray, k: int) -> None:
        """The state ``k`` quiet readings of a block leave: the last one is the state, taken at its time."""
        if k <= 0:
            return
        self._position[...] = states[k - 1, 0]
        self._velocity[...] = states[k - 1, 1]
        self._effort[...] = states[k - 1, 2]
        self._t_read = float(ts[k - 1])
        self._uniform = True

    def _full(self, q: np.ndarray, v: np.ndarray, e: np.ndarray, t: float, age: np.ndarray | None) -> None:
        """The whole rule: per-joint sample times, the velocity-aware reach, suspects, the limit rule."""
        t_ok, t_new = self._t_ok, self._t_new
        if self._uniform:  # the fast path kept every joint's sample time in _t_read
            t_ok.fill(self._t_read)
            self._uniform = False
        if age is None:
            t_new.fill(t)
        else:
            np.subtract(t, age, out=t_new)
        # reach = margin * max(vmax, |v_last|) * (time between the samples + one period) + floor
        speed, reach = self._speed, self._reach
        np.abs(self._velocity, out=speed)
        np.maximum(speed, self._vmax, out=speed)
        np.subtract(t_new, t_ok, out=reach)
        np.maximum(reach, 0.0, out=reach)  # sample stamps from another clock may run back a little
        np.add(reach, self._period, out=reach)
        np.multiply(reach, speed, out=reach)
        np.multiply(reach, self._margin, out=reach)
        np.add(reach, self._floor, out=reach)
        if self._changes[0]:  # a frame change on purpose (a new zero): any finite position
            np.copyto(reach, _FINITE, where=self._changing)
        ok, fin_v, fin_e, all_ok = self._ok, self._fin_v, self._fin_e, self._all_ok
        np.less_equal(self._d, reach, out=ok)
        outside, above = self._outside, self._above
        np.less(q, self._lo, out=outside)
        np.greater(q, self._hi, out=above)
        np.logical_or(outside, above, out=outside)
        if outside.tobytes() != self._all_false:
            # more than the tolerance outside the limits: plausible only if reachable in one step
            # (a period, within the time the sensor was still good) from the last plausible position;
            # a joint pushed past its limit gets there gradually, not across a stall or an outage
            good_until = np.minimum(self._t_bad, t_new)
            one = np.minimum(np.maximum(good_until - t_ok, 0.0), self._period) + self._period
            one_step = self._speed * self._margin * one + self._floor
            free = np.zeros(len(ok), dtype=bool) if self._driven is None else ~self._driven()
            ok &= ~outside | (self._d <= one_step) | self._changing | free
        np.isfinite(v, out=fin_v)
        np.isfinite(e, out=fin_e)
        finite = fin_v.tobytes() == all_ok and fin_e.tobytes() == all_ok
        if finite and not self._any_suspect and ok.tobytes() == all_ok:
            self._position[...] = q
            self._velocity[...] = v
            self._effort[...] = e
            t_ok[...] = t_new
            self._t_read = t
            return
        self._reject(q, v, e, t, ok & fin_v & fin_e, outside.copy())
        self._t_read = t

    def _reject(
        self, q: np.ndarray, v: np.ndarray, e: np.ndarray, t: float, row: np.ndarray, outside: np.ndarray
    ) -> None:
        """Some joint failed, or some joint is suspect: per-joint bookkeeping (rare; may allocate)."""
        bad = ~row
        np.copyto(self._position, q, where=row)
        np.copyto(self._velocity, v, where=row)
        np.copyto(self._effort, e, where=row)
        np.copyto(self._t_ok, self._t_new, where=row)
        self._t_bad[row] = np.inf
        self._t_bad[bad & ~self.suspect] = t
        self.suspect[:] = bad
        self._any_suspect = bool(bad.any())
        if not self._any_suspect:
            return
        self.rejected += bad
        for j in np.flatnonzero(bad & ~self._reported).tolist():
            self._reported[j] = True
            self._new.append(self._report(j, q, v, e, t, bool(outside[j])))

    def _report(self, j: int, q: np.ndarray, v: np.ndarray, e: np.ndarray, t: float, outside: bool) -> SensorReport:
        elapsed = float(self._t_new[j] - self._t_ok[j])
        for quantity, arr, last in (("velocity", v, self._velocity), ("effort", e, self._effort)):
            if not math.isfinite(float(arr[j])):
                return SensorReport(j, t, quantity, float(arr[j]), float(last[j]), math.nan, elapsed,
                                    f"measured {quantity} {float(arr[j])} is not a number a sensor can report")
        value, last_q = float(q[j]), float(self._position[j])
        if not math.isfinite(value):
            return SensorReport(j, t, "position", value, last_q, math.nan, elapsed,
                                f"measured position {value} is not a number a sensor can report")
        reach = float(self._reach[j])
        if outside and abs(value - last_q) <= reach:
            return SensorReport(j, t, "position", value, last_q, reach, elapsed,
                                f"measured position {value:.4g} is more than {self._tolerance:g} outside the limits, "
                                f"{abs(value - last_q):.4g} from the last plausible {last_q:.4g} (read before the "
                                "sensor failed): not reachable in one step")
        return SensorReport(j, t, "position", value, last_q, reach, elapsed,
                            f"measured position {value:.4g} is {abs(value - last_q):.4g} from the last plausible "
                            f"{last_q:.4g} after {elapsed:.4g} s; the joint can move at most {reach:.4g} "
                            f"(max_velocity {float(self._vmax[j]):.4g} x margin {self._margin:g} + {self._floor:g})")
