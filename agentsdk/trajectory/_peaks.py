"""Exact extremes of piecewise polynomial motion: :class:`MotionPeaks` and the polynomial range search."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..types import FloatArray


@dataclass(frozen=True, slots=True)
class MotionPeaks:
    """Extremes of a sampler's interpolated motion, arrays of shape (segments, joints).

    ``knots`` (segments + 1,) are the segments' absolute start/end times; ``q_min``/``q_max``
    the position range, ``v_peak``/``a_peak`` the largest ``|velocity|`` and ``|acceleration|`` inside
    each segment, reached at ``v_time``/``a_time`` (absolute). NaN marks a segment whose
    polynomial is not finite (a duration too short or too long to represent).
    """

    knots: FloatArray
    q_min: FloatArray
    q_max: FloatArray
    v_peak: FloatArray
    a_peak: FloatArray
    v_time: FloatArray
    a_time: FloatArray


_SPLIT = 16  # cells a bracket is split into per refinement step
#: refinement steps: a bracket shrinks to T / 16**8 ~ T * 2e-10, so the extremum's value is exact to ~1e-19
#: of the polynomial's range (an error in the root moves the value only quadratically at an extremum)
_REFINE = 8
_FRACTIONS = np.linspace(0.0, 1.0, _SPLIT + 1)


def _polyval_per_joint(c: FloatArray, tau: FloatArray) -> FloatArray:
    """Evaluate ascending coefficients ``c`` (S, d+1, N) at per-joint local times ``tau`` (S, R, N)."""
    out = np.broadcast_to(c[:, -1][:, None, :], tau.shape).copy()
    for k in range(c.shape[1] - 2, -1, -1):
        out *= tau
        out += c[:, k][:, None, :]
    return out


def derivative(c: FloatArray) -> FloatArray:
    """Coefficients (S, d, N) of the derivative of the polynomials ``c`` (S, d+1, N), ascending powers."""
    return c[:, 1:] * np.arange(1.0, c.shape[1])[None, :, None]


def poly_roots(c: FloatArray, turns: FloatArray, T: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Real roots in (0, T) of each polynomial ``c`` (S, d+1, N), given the roots of its derivative.

    ``turns`` (S, m, N), NaN-padded, are where the polynomial may turn: between two of them (and the
    ends 0 and ``T``) it is monotone, so each such piece holds at most one root, where the values at
    its ends differ in sign. Those pieces are bisected, all at once. Returns ``(roots, breakpoints)``:
    roots (S, m+1, N), NaN where a piece has none, and the sorted breakpoints (S, m+2, N).
    Applied from the highest derivative down (a linear one has no turns), this finds every real root
    without an eigenvalue problem per polynomial.
    """
    S, _, N = c.shape
    ends = np.broadcast_to(T[:, None, None], (S, 1, N))
    inside = np.where(turns > 0.0, np.where(turns < ends, turns, ends), 0.0)
    inside = np.where(np.isfinite(turns), inside, ends)
    bp = np.sort(np.concatenate([np.zeros((S, 1, N)), inside, ends], axis=1), axis=1)
    g = _polyval_per_joint(c, bp)
    roots = np.full((S, bp.shape[1] - 1, N), np.nan)
    s_idx, c_idx, j_idx = np.nonzero((g[:, :-1, :] * g[:, 1:, :]) < 0.0)
    if len(s_idx):
        lo = bp[s_idx, c_idx, j_idx]
        hi = bp[s_idx, c_idx + 1, j_idx]
        g_lo = g[s_idx, c_idx, j_idx]
        coeffs = c[s_idx, :, j_idx]  # (K, d+1)
        ks = np.arange(len(s_idx))
        for _ in range(_REFINE):
            # split every bracket into _SPLIT cells at once and keep the first cell where the sign changes
            # (a bisection that gains 4 bits per step: 8 numpy passes instead of 32)
            pts = lo[:, None] + (hi - lo)[:, None] * _FRACTIONS[None, :]  # (K, _SPLIT + 1)
            gm = np.broadcast_to(coeffs[:, -1][:, None], pts.shape).copy()
            for k in range(coeffs.shape[1] - 2, -1, -1):
                gm *= pts
                gm += coeffs[:, k][:, None]
            changed = (gm[:, 1:] * g_lo[:, None]) <= 0.0
            changed[:, -1] = True  # the bracket's far end changes sign (rounding aside)
            m = np.argmax(changed, axis=1)
            lo, hi = pts[ks, m], pts[ks, m + 1]
            g_lo = gm[ks, m]
        roots[s_idx, c_idx, j_idx] = 0.5 * (lo + hi)
    return roots, bp


def poly_range(c: FloatArray, droots: FloatArray, dbreaks: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(min, max, (t_min, t_max)) over [0, T] of each joint's polynomial ``c`` (S, d+1, N).

    ``droots``/``dbreaks`` are :func:`poly_roots` of its derivative: the extremes are at the ends or
    at a root of the derivative; the breakpoints (ends and the derivative's turns) are values of the
    polynomial too, which covers a root the bisection could not separate from a turn (a double root).
    """
    tt = np.concatenate([dbreaks, np.where(np.isfinite(droots), droots, 0.0)], axis=1)
    f = _polyval_per_joint(c, tt)
    f_min = f.min(axis=1)
    f_max = f.max(axis=1)
    t_min = np.take_along_axis(tt, f.argmin(axis=1)[:, None, :], 1)[:, 0]
    t_max = np.take_along_axis(tt, f.argmax(axis=1)[:, None, :], 1)[:, 0]
    # a non-finite polynomial (overflowing coefficients) is reported as NaN, never as in range
    bad = ~np.isfinite(c).all(axis=1)
    if bad.any():
        f_min[bad] = np.nan
        f_max[bad] = np.nan
    return f_min, f_max, np.stack([t_min, t_max])
