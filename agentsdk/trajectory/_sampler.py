"""JTC-style interpolation: per-segment polynomials and the :class:`TrajectorySampler`."""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..errors import InvalidValueError, UnknownJointError
from ..types import FloatArray
from ._peaks import MotionPeaks, derivative, poly_range, poly_roots
from ._types import Interpolation, Trajectory, Values, vector

#: the factors of the velocity and acceleration rows of sample_block's bases
_ROW1 = np.array([2.0, 3.0, 4.0])
_ROW2 = np.array([6.0, 12.0, 20.0])


def quintic(
    q0: FloatArray, v0: FloatArray, a0: FloatArray, q1: FloatArray, v1: FloatArray, a1: FloatArray, T: FloatArray
) -> FloatArray:
    """Coefficients (segments, 6, joints) of quintic Hermite polynomials in local time.

    Durations too short or too long to represent give non-finite coefficients (no warning), which
    :func:`check_motion_limits` refuses.
    """
    T = T[:, None]
    h = q1 - q0
    c = np.empty((len(T), 6, q0.shape[1]))
    c[:, 0] = q0
    c[:, 1] = v0
    c[:, 2] = 0.5 * a0
    with np.errstate(all="ignore"):
        c[:, 3] = (20.0 * h - (8.0 * v1 + 12.0 * v0) * T - (3.0 * a0 - a1) * T**2) / (2.0 * T**3)
        c[:, 4] = (-30.0 * h + (14.0 * v1 + 16.0 * v0) * T + (3.0 * a0 - 2.0 * a1) * T**2) / (2.0 * T**4)
        c[:, 5] = (12.0 * h - 6.0 * (v1 + v0) * T + (a1 - a0) * T**2) / (2.0 * T**5)
    return c


def _cubic(q0: FloatArray, v0: FloatArray, q1: FloatArray, v1: FloatArray, T: FloatArray) -> FloatArray:
    T = T[:, None]
    h = q1 - q0
    c = np.zeros((len(T), 6, q0.shape[1]))
    c[:, 0] = q0
    c[:, 1] = v0
    with np.errstate(all="ignore"):
        c[:, 2] = (3.0 * h - (2.0 * v0 + v1) * T) / T**2
        c[:, 3] = (-2.0 * h + (v0 + v1) * T) / T**3
    return c


def _linear(q0: FloatArray, q1: FloatArray, T: FloatArray) -> FloatArray:
    c = np.zeros((len(T), 6, q0.shape[1]))
    c[:, 0] = q0
    with np.errstate(all="ignore"):
        c[:, 1] = (q1 - q0) / T[:, None]
    return c


def _clamped_spline_velocities(t: FloatArray, q: FloatArray, v_start: FloatArray, v_end: FloatArray) -> FloatArray:
    """Knot velocities of the C2 cubic spline through ``q`` at ``t`` with clamped end velocities."""
    n = len(t)
    m = np.empty_like(q)
    m[0], m[-1] = v_start, v_end
    if n <= 2:
        return m
    h = np.diff(t)
    d = np.diff(q, axis=0) / h[:, None]
    # row k (interior knot k=1..n-2): m[k-1]/h[k-1] + 2(1/h[k-1]+1/h[k]) m[k] + m[k+1]/h[k] = 3(d[k-1]/h[k-1]+d[k]/h[k])
    sub = 1.0 / h[:-1]
    sup = 1.0 / h[1:]
    diag = 2.0 * (sub + sup)
    rhs = 3.0 * (d[:-1] * sub[:, None] + d[1:] * sup[:, None])
    rhs[0] -= sub[0] * m[0]
    rhs[-1] -= sup[-1] * m[-1]
    # Thomas algorithm (diagonally dominant, stable), vectorized over joints
    k = n - 2
    cp = np.empty(k)
    dp = np.empty_like(rhs)
    cp[0] = sup[0] / diag[0]
    dp[0] = rhs[0] / diag[0]
    for i in range(1, k):
        den = diag[i] - sub[i] * cp[i - 1]
        cp[i] = sup[i] / den
        dp[i] = (rhs[i] - sub[i] * dp[i - 1]) / den
    x = np.empty_like(rhs)
    x[-1] = dp[-1]
    for i in range(k - 2, -1, -1):
        x[i] = dp[i] - cp[i] * x[i + 1]
    m[1:-1] = x
    return m


class TrajectorySampler:
    """Evaluates a :class:`Trajectory` against time, like JTC's ``Trajectory::sample``.

    ``start_time`` is when the trajectory starts executing (``time_from_start``
    is relative to it); ``start_positions``/``start_velocities``/``start_accelerations``
    are the current desired state then. They are mappings by joint name or
    sequences, in the trajectory's ``joint_names`` order or, when ``joint_order`` is
    given, in that order (e.g. all of the robot's joint names). ``joint_order`` may also
    be a sequence of ints: for each trajectory joint, its index in the start arrays.
    :attr:`indices` maps trajectory joints to that order, so an executor can scatter
    ``q_full[sampler.indices] = q``.

    Segments: start state -> point 0 (only if ``points[0].time_from_start > 0``;
    always quintic from the start velocity/acceleration), then point i -> i+1:
    positions only: linear (``interpolation="linear"``, JTC's behaviour) or a C2
    cubic spline through all knots (``"spline"``, clamped to the start velocity and
    to rest at the end, whose last segment arrives with zero acceleration); +velocities: cubic Hermite;
    +accelerations: quintic. When point 0 is at time 0 the start state is not used
    and point 0 is output from ``start_time`` on (a jump if they differ, as in JTC).
    After the end the last point is held: its positions, its velocities and
    accelerations if given (as JTC), else zeros.

    Construction does the work; :meth:`sample` is a bisect and one small matrix
    product. A sampler is meant for one control loop (it reuses a scratch buffer).
    """

    __slots__ = (
        "_B",
        "_Bblock",
        "_Bm",
        "_T",
        "_c",
        "_end_state",
        "_has_start",
        "_knots",
        "_knots_arr",
        "_knots_block",
        "_n",
        "_peaks",
        "_segs",
        "_start_state",
        "end_time",
        "indices",
        "joint_names",
        "region",
        "start_time",
        "trajectory",
    )

    def __init__(
        self,
        trajectory: Trajectory,
        start_time: float = 0.0,
        start_positions: Values | None = None,
        start_velocities: Values | None = None,
        start_accelerations: Values | None = None,
        *,
        joint_order: Sequence[str] | Sequence[int] | None = None,
        interpolation: Interpolation = "linear",
    ) -> None:
        if interpolation not in ("linear", "spline"):
            raise InvalidValueError(f"interpolation must be 'linear' or 'spline', got {interpolation!r}")
        if not math.isfinite(start_time):
            raise InvalidValueError(f"start_time {start_time} is not finite")
        self.trajectory = trajectory
        self.joint_names = trajectory.joint_names
        n = self._n = len(self.joint_names)
        self.start_time = float(start_time)
        self.end_time = self.start_time + trajectory.duration

        # -- where the trajectory's joints are in the start arrays
        exact_width: int | None = None  # start arrays must have this length (None: any length > max index)
        if joint_order is None:
            self.indices = np.arange(n)
            exact_width = n
        elif len(joint_order) > 0 and all(isinstance(i, int | np.integer) for i in joint_order):
            self.indices = np.array(joint_order, dtype=np.intp)
            if self.indices.shape != (n,):
                raise InvalidValueError(f"joint_order: {len(joint_order)} indices for {n} trajectory joints")
            if (self.indices < 0).any() or len(set(self.indices.tolist())) != n:
                raise InvalidValueError(f"joint_order: indices {self.indices.tolist()} must be distinct and >= 0")
        else:
            order = list(joint_order)
            pos = {nm: i for i, nm in enumerate(order)}
            missing = [nm for nm in self.joint_names if nm not in pos]
            if missing:
                raise UnknownJointError(f"trajectory joint(s) {missing} are not in joint_order {order}")
            self.indices = np.array([pos[nm] for nm in self.joint_names], dtype=np.intp)
            exact_width = len(order)
        self.indices.setflags(write=False)

        def start_vec(values: Values | None, what: str, default: float | None) -> FloatArray:
            if isinstance(values, Mapping):  # may name more joints than the trajectory's
                missing = [nm for nm in self.joint_names if nm not in values]
                if missing:
                    raise InvalidValueError(f"{what}: missing joint(s) {missing}")
                values = {nm: values[nm] for nm in self.joint_names}
            elif values is not None:
                arr = np.asarray(values, dtype=np.float64)
                ok = arr.ndim == 1 and (
                    len(arr) == exact_width if exact_width is not None else len(arr) > int(self.indices.max())
                )
                if not ok:
                    raise InvalidValueError(
                        f"{what}: got shape {arr.shape}, expected "
                        + (f"{exact_width} values" if exact_width is not None else "values for joint_order indices")
                    )
                values = arr[self.indices]
            return vector(values, self.joint_names, what, default)

        pts = trajectory
        t_pts = self.start_time + pts.times
        has_start = pts.points[0].time_from_start > 0.0
        if has_start:
            if start_positions is None:
                raise InvalidValueError(
                    f"the first point is at time_from_start={pts.points[0].time_from_start} s > 0: "
                    "start_positions (the current desired state) are required to interpolate to it"
                )
            q_s = start_vec(start_positions, "start_positions", None)
            v_s = start_vec(start_velocities, "start_velocities", 0.0)
            a_s = start_vec(start_accelerations, "start_accelerations", 0.0)
        else:
            q_s = pts.positions[0]
            v_s = pts.velocities[0] if pts.velocities is not None else np.zeros(n)
            a_s = np.zeros(n)

        P = np.asarray(pts.positions)
        m = len(P)
        seg_coeffs: list[FloatArray] = []
        knots = [self.start_time] if has_start else []
        knots.extend(t_pts.tolist())
        # segment durations from the relative times: a difference of absolute robot times carries their
        # rounding (~eps * t, 4e-14 s at t = 190 s), which a short segment's quintic turns into an
        # acceleration error ~ 6 |v| eps t / T^2 (0.05 rad/s^2 on a 2.5 µs segment of a planned profile)
        T = np.diff(pts.times)

        if pts.accelerations is not None:
            V = np.asarray(pts.velocities)
            A = np.asarray(pts.accelerations)
            body = quintic(P[:-1], V[:-1], A[:-1], P[1:], V[1:], A[1:], T) if m > 1 else None
            v_end, a_end = V[-1], A[-1]
            first_v, first_a = V[0], A[0]
        elif pts.velocities is not None:
            V = np.asarray(pts.velocities)
            body = _cubic(P[:-1], V[:-1], P[1:], V[1:], T) if m > 1 else None
            v_end, a_end = V[-1], np.zeros(n)
            first_v = V[0]
            first_a = 2.0 * body[0, 2] if body is not None else np.zeros(n)
        elif interpolation == "linear":
            body = _linear(P[:-1], P[1:], T) if m > 1 else None
            v_end, a_end = np.zeros(n), np.zeros(n)
            first_v = body[0, 1] if body is not None else np.zeros(n)
            first_a = np.zeros(n)
        else:  # C2 cubic spline through (start,) points, clamped to v_s at the start and 0 at the end;
            # all segments quintic: the cubic spline exactly, except the first (from a_s) and the
            # last (which arrives with zero acceleration, so holding the end is smooth)
            tk = np.concatenate(([0.0], pts.times)) if has_start else np.asarray(pts.times, dtype=np.float64)
            Qk = np.vstack([q_s[None, :], P]) if has_start else P
            M = _clamped_spline_velocities(tk, Qk, v_s, np.zeros(n))
            if len(tk) > 1:
                h = np.diff(tk)[:, None]
                d = np.diff(Qk, axis=0) / h
                acc_left = (6.0 * d - 4.0 * M[:-1] - 2.0 * M[1:]) / h  # acceleration at each segment's start
                Ak = np.vstack([acc_left, np.zeros((1, n))])  # arrive at rest: a = 0
            else:
                Ak = np.zeros((1, n))
            off = 1 if has_start else 0
            body = quintic(P[:-1], M[off:-1], Ak[off:-1], P[1:], M[off + 1 :], Ak[off + 1 :], T) if m > 1 else None
            v_end, a_end = np.zeros(n), np.zeros(n)
            first_v, first_a = M[off], Ak[off]
        if has_start:
            seg_coeffs.append(
                quintic(
                    q_s[None, :],
                    v_s[None, :],
                    a_s[None, :],
                    P[:1],
                    first_v[None, :],
                    first_a[None, :],
                    np.array([pts.points[0].time_from_start]),
                )
            )
        if body is not None:
            seg_coeffs.append(body)
        self._c = np.concatenate(seg_coeffs, axis=0) if seg_coeffs else np.zeros((0, 6, n))
        self._knots = knots
        self._knots_arr = np.array(knots, dtype=np.float64)
        #: sample_block's stacked bases (K, 3, 6), constant entries written once; grown on demand
        self._Bblock = np.zeros((0, 3, 6))
        #: sample_block's knot of each sample's segment (K,), grown with it
        self._knots_block = np.zeros(0)
        self._T = np.concatenate(([pts.points[0].time_from_start], T)) if has_start else T
        self._has_start = has_start
        self._B = np.zeros((3, 6))
        # the tick path allocates nothing: B's entries are written through a flat memoryview, and
        # each segment's coefficient matrix is a view made once
        flat: Any = self._B.reshape(-1)  # numpy arrays are buffers; its stubs do not say so
        self._Bm: Any = memoryview(flat)
        flat[0] = flat[7] = 1.0  # B's constant entries, written once
        flat[14] = 2.0
        self._segs = list(self._c)
        self._end_state = np.vstack([P[-1], v_end, a_end])
        if len(self._c):  # the state at the start of the first segment
            c0 = self._c[0]
            self._start_state = np.vstack([c0[0], c0[1], 2.0 * c0[2]])
        else:
            self._start_state = self._end_state
        self._start_state.setflags(write=False)
        self._end_state.setflags(write=False)
        self._peaks: MotionPeaks | None = None
        #: where the last :meth:`sample_into` sampled: -1 before the first segment, ``i`` in segment ``i``,
        #: :attr:`segments` after the last (the executor looks up what it precomputed per segment)
        self.region = -1

    @property
    def segments(self) -> int:
        """Number of polynomial segments (the start state -> point 0 one included)."""
        return len(self._c)

    def coefficients(self) -> FloatArray:
        """The segments' polynomial coefficients, shape (segments, 6, joints), ascending powers of local time.

        Read-only: segment ``i`` is ``sum(c[i, k] * tau**k)`` for ``tau`` from 0 to its duration.
        """
        c = self._c.view()
        c.setflags(write=False)
        return c

    @property
    def duration(self) -> float:
        """Seconds from ``start_time`` to the last point."""
        return self.end_time - self.start_time

    @property
    def final_positions(self) -> FloatArray:
        """Joint positions at the end of the trajectory (full joint order)."""
        positions: FloatArray = self._end_state[0]
        return positions

    def finished(self, t: float) -> bool:
        """True once ``t`` is at or past the last point's time."""
        return t >= self.end_time

    def sample_into(self, t: float, out: FloatArray) -> FloatArray:
        """Write ``[q, qd, qdd]`` at absolute time ``t`` into ``out`` (shape (3, joints)) and return it."""
        knots = self._knots
        i = bisect_right(knots, t) - 1
        if i >= len(self._c):
            self.region = len(self._c)
            out[...] = self._end_state
            return out
        if i < 0:
            self.region = -1
            out[...] = self._start_state
            return out
        self.region = i
        tau = t - knots[i]
        t2 = tau * tau
        t3 = t2 * tau
        # B = [[1, tau, t2, t3, t3 tau, t3 t2], [0, 1, 2 tau, 3 t2, 4 t3, 5 t3 tau], [0, 0, 2, 6 tau, 12 t2, 20 t3]]
        m = self._Bm  # (entries 0, 7 and 14 are constant: set once)
        m[1] = tau
        m[2] = t2
        m[3] = t3
        m[4] = t3 * tau
        m[5] = t3 * t2
        m[8] = 2.0 * tau
        m[9] = 3.0 * t2
        m[10] = 4.0 * t3
        m[11] = 5.0 * t3 * tau
        m[15] = 6.0 * tau
        m[16] = 12.0 * t2
        m[17] = 20.0 * t3
        np.dot(self._B, self._segs[i], out=out)
        return out

    def sample_block(self, ts: FloatArray, out: FloatArray, regions: np.ndarray | None = None) -> FloatArray:
        """Write ``[q, qd, qdd]`` at each absolute time ``ts[k]`` into ``out[k]`` (shape (K, 3, joints)).

        Bit for bit what :meth:`sample_into` writes at each ``ts[k]`` (the same basis entries from
        the same float operations, and one matrix product per segment with the stacked bases as
        its rows: a row of a product does not depend on the other rows), for block lockstep, which
        computes the setpoints of many ticks at once. ``ts`` must be non-decreasing (trajectory
        time). :attr:`region` ends where the last sample lies; ``regions`` (K,), if given, receives
        each sample's region (as :attr:`region` would be after it).
        """
        K = len(ts)
        if K == 0:
            return out
        n_seg = len(self._c)
        knots = self._knots
        # the segments of the first and the last time (bisect_right, as sample_into), clipped to
        # -1 (before the first) .. n_seg (after the last); ts is sorted, so each segment's ticks
        # are consecutive and begin at the first tick at or after its knot (knots[i] <= t, the
        # same comparison as bisect_right's)
        i0 = min(bisect_right(knots, float(ts[0])) - 1, n_seg)
        i1 = min(bisect_right(knots, float(ts[-1])) - 1, n_seg)
        cuts = np.searchsorted(ts, self._knots_arr[i0 + 1 : i1 + 1], side="left").tolist() if i1 > i0 else []
        n = self._n
        chunks = list(zip(range(i0, i1 + 1), [*cuts, K], strict=True))
        B = self._Bblock
        if i1 >= 0 and i0 < n_seg:  # a sample inside the segments: the bases of all K at once
            if len(B) < K:
                B = self._Bblock = np.zeros((max(K, 2 * len(B)), 3, 6))
                B[:, 0, 0] = B[:, 1, 1] = 1.0  # the constant entries, written once
                B[:, 2, 2] = 2.0
                self._knots_block = np.zeros(len(B))
            kn = self._knots_block[:K]  # each sample's segment start (0.0 outside the segments: not used)
            a = 0
            for i, b in chunks:
                kn[a:b] = knots[i] if 0 <= i < n_seg else 0.0
                a = b
            # B = [[1, tau, t2, t3, t3 tau, t3 t2], [0, 1, 2 tau, 3 t2, 4 t3, 5 t3 tau], [0, 0, 2, 6 tau,
            # 12 t2, 20 t3]]: the entries sample_into writes, from the same float operations (element by
            # element: each row the same whatever the other rows are)
            Bk = B[:K]
            x = Bk[:, 0, 1:4]  # tau, t2, t3
            np.subtract(ts, kn, out=x[:, 0])
            np.multiply(x[:, 0], x[:, 0], out=x[:, 1])
            np.multiply(x[:, 1], x[:, 0], out=x[:, 2])
            np.multiply(x[:, 2:3], x[:, 0:2], out=Bk[:, 0, 4:6])  # t3 tau, t3 t2
            np.multiply(x, _ROW1, out=Bk[:, 1, 2:5])  # 2 tau, 3 t2, 4 t3
            np.multiply(x[:, 2], 5.0, out=Bk[:, 1, 5])
            np.multiply(Bk[:, 1, 5], x[:, 0], out=Bk[:, 1, 5])  # (5 t3) tau
            np.multiply(x, _ROW2, out=Bk[:, 2, 3:6])  # 6 tau, 12 t2, 20 t3
        flat_out = out.flags.c_contiguous
        a = 0
        for i, b in chunks:
            if a == b:
                continue  # a segment no tick falls in
            if regions is not None:
                regions[a:b] = i
            if i >= n_seg:
                out[a:b] = self._end_state
            elif i < 0:
                out[a:b] = self._start_state
            elif flat_out:  # one matrix product per segment, the stacked bases its rows
                np.dot(B[a:b].reshape(-1, 6), self._segs[i], out=out[a:b].reshape(-1, n))
            else:
                out[a:b] = np.dot(B[a:b].reshape(-1, 6), self._segs[i]).reshape(b - a, 3, n)
            a = b
        self.region = i1
        return out

    def sample(self, t: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(q, qd, qdd)`` at absolute time ``t``, in the trajectory's joint order (fresh arrays)."""
        out = self.sample_into(t, np.empty((3, self._n)))
        return out[0], out[1], out[2]

    def segment_label(self, i: int) -> str:
        """Human name of segment ``i``: ``"start state -> point 0"`` or ``"point k -> point k+1"``."""
        if self._has_start:
            return "start state -> point 0" if i == 0 else f"point {i - 1} -> point {i}"
        return f"point {i} -> point {i + 1}"

    def peaks(self) -> MotionPeaks:
        """Exact extremes of the interpolated motion, per segment and joint (see :class:`MotionPeaks`).

        Every segment is a polynomial of degree <= 5 per joint; the extremes are its values at
        the segment ends and at the roots of its derivative inside the segment. Those roots are
        isolated from the bottom up (a derivative is monotone between the roots of the next one,
        so each piece holds at most one, bisected to machine precision), for all segments and
        joints at once: a few numpy passes, ~20 ms for 1000 points of 12 joints. Velocity steps at the points of a
        positions-only (linear) trajectory are not motion inside a segment and are not counted.
        Computed once per sampler (the admission's limit check and the executor share it).
        """
        pk = self._peaks
        if pk is None:
            pk = self._peaks = self._compute_peaks()
            for a in (pk.knots, pk.q_min, pk.q_max, pk.v_peak, pk.a_peak, pk.v_time, pk.a_time):
                a.setflags(write=False)  # shared by every caller
        return pk

    def _compute_peaks(self) -> MotionPeaks:
        c = self._c
        n_seg = len(c)
        n = self._n
        if n_seg == 0:
            empty = np.zeros((0, n))
            return MotionPeaks(np.array(self._knots[:1] or [self.start_time]), empty, empty, empty, empty, empty, empty)
        T = self._T
        with np.errstate(all="ignore"):
            cq = c
            cv = derivative(cq)  # degree 4
            ca = derivative(cv)  # degree 3
            cj = derivative(ca)  # degree 2
            cs = derivative(cj)  # degree 1: monotone, no turns
            # each derivative's roots split the one above it into monotone pieces (see poly_roots)
            s_roots = poly_roots(cs, np.full((n_seg, 0, n), np.nan), T)
            j_roots = poly_roots(cj, s_roots[0], T)
            a_roots = poly_roots(ca, j_roots[0], T)
            v_roots = poly_roots(cv, a_roots[0], T)
            q_lo, q_hi, _ = poly_range(cq, *v_roots)
            v_lo, v_hi, v_at = poly_range(cv, *a_roots)
            a_lo, a_hi, a_at = poly_range(ca, *j_roots)
        v_abs = np.maximum(np.abs(v_lo), np.abs(v_hi))
        a_abs = np.maximum(np.abs(a_lo), np.abs(a_hi))
        v_t = np.where(np.abs(v_hi) >= np.abs(v_lo), v_at[1], v_at[0])
        a_t = np.where(np.abs(a_hi) >= np.abs(a_lo), a_at[1], a_at[0])
        knots = np.array(self._knots, dtype=np.float64)
        return MotionPeaks(knots, q_lo, q_hi, v_abs, a_abs, knots[:-1, None] + v_t, knots[:-1, None] + a_t)
