"""``np.linalg.solve(a, b)`` for the servo step's small systems, without the wrapper's per-call work.

The implicit-damping step solves ``(M + h D) qacc = rhs`` once or twice per substep. For a few
joints numpy's Python wrapper (array checks, type resolution, an ``errstate`` context) costs
several times the LAPACK solve itself; :func:`solve` calls the same LAPACK gufunc the wrapper
calls, so the result is bit for bit the same. A result that is not finite (a singular matrix,
which a mass matrix plus damping is not: the gufunc returns NaN, with numpy's "invalid value"
warning) is solved again through ``np.linalg.solve``, which raises its ``LinAlgError`` as before.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

try:  # numpy >= 1.x keeps the gufunc here; another layout falls back to the public function
    from numpy.linalg import _umath_linalg

    _SOLVE1: Any = _umath_linalg.solve1
except (ImportError, AttributeError):  # pragma: no cover - depends on the numpy build
    _SOLVE1 = None

__all__ = ["solve"]


def solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.linalg.solve(a, b)`` for a float64 square ``a`` and a 1-D float64 ``b`` (same bits)."""
    if _SOLVE1 is None:
        return np.linalg.solve(a, b)
    x: np.ndarray = _SOLVE1(a, b, signature="dd->d")  # (an errstate context would cost more than the solve)
    if math.isfinite(x.dot(x)):
        return x
    return np.linalg.solve(a, b)  # singular (LinAlgError) or a non-finite input: as before
