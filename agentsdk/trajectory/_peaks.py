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


_GRID = 16  # cells per segment where derivative roots are bracketed
_SPLIT = 16  # cells a bracket is split into per refinement step
#: refinement steps: a bracket shrinks to T / 16**8 ~ T * 2e-10, so the extremum's value is exact to ~1e-19
#: of the polynomial's range (an error in the root moves the value only quadratically at an extremum)
_REFINE = 7
_FRACTIONS = np.linspace(0.0, 1.0, _SPLIT + 1)


def _polyval(c: FloatArray, tau: FloatArray) -> FloatArray:
    """Evaluate ascending coefficients ``c`` (S, d+1, N) at local times ``tau`` (S, G) -> (S, G, N)."""
    out = np.broadcast_to(c[:, -1][:, None, :], (c.shape[0], tau.shape[1], c.shape[2])).copy()
    t = tau[:, :, None]
    for k in range(c.shape[1] - 2, -1, -1):
        out *= t
        out += c[:, k][:, None, :]
    return out


def _polyval_per_joint(c: FloatArray, tau: FloatArray) -> FloatArray:
    """Evaluate ascending coefficients ``c`` (S, d+1, N) at per-joint local times ``tau`` (S, R, N)."""
    out = np.broadcast_to(c[:, -1][:, None, :], tau.shape).copy()
    for k in range(c.shape[1] - 2, -1, -1):
        out *= tau
        out += c[:, k][:, None, :]
    return out


def _root_candidates(dc: FloatArray, T: FloatArray) -> FloatArray:
    """Real parts of the roots of each polynomial ``dc`` (S, d+1, N), clipped into [0, T]: (S, d, N).

    Eigenvalues of the companion matrices, all at once. A vanishing leading coefficient (a lower
    degree) is replaced by a tiny one of the same scale: the root it adds lies far outside [0, T]
    (clipped to an end, which is a candidate anyway) and the others move by rounding only.
    """
    S, d1, N = dc.shape
    d = d1 - 1
    if d < 1 or S == 0:
        return np.zeros((S, 0, N))
    p = np.moveaxis(dc, 2, 1).reshape(S * N, d1)  # (K, d+1) ascending
    ok = np.asarray(np.isfinite(p).all(axis=1))
    p = np.where(ok[:, None], p, 0.0)
    scale = np.abs(p).max(axis=1)
    lead = p[:, -1]
    tiny = np.maximum(scale, 1.0) * 1e-13
    lead = np.where(np.abs(lead) < tiny, np.where(lead < 0.0, -tiny, tiny), lead)
    comp = np.zeros((len(p), d, d))
    if d > 1:
        comp[:, np.arange(1, d), np.arange(d - 1)] = 1.0
    comp[:, :, -1] = -p[:, :d] / lead[:, None]
    roots = np.linalg.eigvals(comp).real  # (K, d)
    roots = np.where(np.isfinite(roots), roots, 0.0)
    roots = roots.reshape(S, N, d).transpose(0, 2, 1)  # (S, d, N)
    return np.clip(roots, 0.0, T[:, None, None])


def poly_range(c: FloatArray, dc: FloatArray, T: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(min, max, (t_min, t_max)) over [0, T] of each joint's polynomial ``c`` whose derivative is ``dc``."""
    grid = np.linspace(0.0, 1.0, _GRID + 1)[None, :] * T[:, None]  # (S, G+1)
    f = _polyval(c, grid)  # (S, G+1, N)
    g = _polyval(dc, grid)
    # cells where the derivative changes sign hold an extremum: bisect them all at once
    sign_change = (g[:, :-1, :] * g[:, 1:, :]) < 0.0
    s_idx, c_idx, j_idx = np.nonzero(sign_change)
    if len(s_idx):
        lo = grid[s_idx, c_idx].copy()
        hi = grid[s_idx, c_idx + 1].copy()
        g_lo = g[s_idx, c_idx, j_idx]
        coeffs = dc[s_idx, :, j_idx]  # (K, d+1)
        ks = np.arange(len(s_idx))
        for _ in range(_REFINE):
            # split every bracket into _SPLIT cells at once and keep the first cell where the sign changes
            # (a bisection that gains 4 bits per step: 7 numpy passes instead of 28)
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
        root = 0.5 * (lo + hi)
        cf = c[s_idx, :, j_idx]
        fr = cf[:, -1].copy()
        for k in range(cf.shape[1] - 2, -1, -1):
            fr = fr * root + cf[:, k]
    # a cell can hold two roots (no sign change: an extremum pair the bisection cannot see): the
    # derivative's roots from its companion matrix are candidates too. Any point of [0, T] is a
    # true value of the polynomial, so spurious candidates (complex roots' real parts) are harmless.
    cand = _root_candidates(dc, T)  # (S, R, N)
    if cand.shape[1]:
        fc = _polyval_per_joint(c, cand)
        grid_n = np.broadcast_to(grid[:, :, None], f.shape)
        f = np.concatenate([f, fc], axis=1)
        tt = np.concatenate([grid_n, cand], axis=1)
    else:
        tt = np.broadcast_to(grid[:, :, None], f.shape)
    f_min = f.min(axis=1)
    f_max = f.max(axis=1)
    t_min = np.take_along_axis(tt, f.argmin(axis=1)[:, None, :], 1)[:, 0]
    t_max = np.take_along_axis(tt, f.argmax(axis=1)[:, None, :], 1)[:, 0]
    if len(s_idx):
        np.minimum.at(f_min, (s_idx, j_idx), fr)
        np.maximum.at(f_max, (s_idx, j_idx), fr)
        hit = fr <= f_min[s_idx, j_idx]
        t_min[s_idx[hit], j_idx[hit]] = root[hit]
        hit = fr >= f_max[s_idx, j_idx]
        t_max[s_idx[hit], j_idx[hit]] = root[hit]
    # a non-finite polynomial (overflowing coefficients) is reported as NaN, never as in range
    bad = ~np.isfinite(c).all(axis=1)
    if bad.any():
        f_min[bad] = np.nan
        f_max[bad] = np.nan
    return f_min, f_max, np.stack([t_min, t_max])
