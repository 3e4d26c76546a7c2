"""Checks of an interpolated motion against joint limits, and the slow-down that satisfies them."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from ..errors import LimitViolation
from ..types import FloatArray
from ._peaks import MotionPeaks
from ._sampler import TrajectorySampler
from ._types import ACC_RTOL, POS_TOL, VEL_RTOL


def check_motion_limits(
    sampler: TrajectorySampler,
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    max_velocity: npt.ArrayLike,
    max_acceleration: npt.ArrayLike,
    *,
    hint: str = "",
) -> None:
    """Raise :class:`LimitViolation` where the interpolated motion of ``sampler`` leaves a limit.

    Limits are per trajectory joint (in ``sampler.joint_names`` order). The whole motion is
    checked, not only the points: the segment from the start state, and between the points the
    exact extremes of position, velocity and acceleration (:meth:`TrajectorySampler.peaks`).
    The message names the segment, the joint, the value, the limit and when it is reached;
    ``hint`` is appended to it. A motion that cannot be represented (non-finite) is rejected too.
    """
    pk = sampler.peaks()
    if pk.q_min.size == 0:
        return
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    vmax = np.asarray(max_velocity, dtype=np.float64)
    amax = np.asarray(max_acceleration, dtype=np.float64)
    v_round, a_round = rounding_allowance(pk)
    checks = (
        ("position", ~((pk.q_min >= lo - POS_TOL) & (pk.q_max <= hi + POS_TOL))),
        ("velocity", ~(pk.v_peak <= vmax * (1.0 + VEL_RTOL) + 1e-9 + v_round)),
        ("acceleration", ~(pk.a_peak <= amax * (1.0 + ACC_RTOL) + 1e-9 + a_round)),
    )
    first: tuple[int, int, str] | None = None
    for what, bad in checks:
        if bad.any():
            seg, j = (int(i) for i in np.argwhere(bad)[0])
            if first is None or seg < first[0]:
                first = (seg, j, what)
    if first is None:
        return
    seg, j, what = first
    name = sampler.joint_names[j]
    t0 = sampler.start_time
    span = f"{pk.knots[seg] - t0:.6g}-{pk.knots[seg + 1] - t0:.6g} s"
    where = f"segment {sampler.segment_label(seg)} ({span}): joint {name!r}"
    if not (np.isfinite(pk.q_min[seg, j]) and np.isfinite(pk.v_peak[seg, j]) and np.isfinite(pk.a_peak[seg, j])):
        msg = f"{where}: the interpolated motion is not finite (a segment too short or too long to represent)"
    elif what == "position":
        msg = (
            f"{where} position reaches [{pk.q_min[seg, j]:.6g}, {pk.q_max[seg, j]:.6g}] between the points, "
            f"outside its limits [{lo[j]:.6g}, {hi[j]:.6g}]"
        )
    elif what == "velocity":
        msg = (
            f"{where} velocity reaches {pk.v_peak[seg, j]:.6g} at {pk.v_time[seg, j] - t0:.6g} s, above "
            f"max_velocity {vmax[j]:.6g}"
        )
    else:
        msg = (
            f"{where} acceleration reaches {pk.a_peak[seg, j]:.6g} at {pk.a_time[seg, j] - t0:.6g} s, above "
            f"max_acceleration {amax[j]:.6g}"
        )
    raise LimitViolation(msg + hint)


#: float rounding multiplier of :func:`rounding_allowance` (the quintic's derivatives amplify an error
#: of its end values by up to ~6/T^2; the rest covers the rounding of the coefficients themselves)
_ROUNDING_FACTOR = 64.0


def rounding_allowance(pk: MotionPeaks) -> tuple[FloatArray, FloatArray]:
    """(velocity, acceleration) that float rounding alone can put into each segment's interpolation.

    A segment of duration T is a quintic through its end states; a rounding error of the end
    positions (relative ``eps``) shows as a velocity error ~ ``eps * |q| / T`` and an acceleration
    error ~ ``eps * (|q| / T**2 + |v| / T)``. Negligible for any segment a robot can notice
    (< 1e-7 rad/s^2 at T = 1 ms), but a 2 µs segment between two nearby breakpoints of a planned
    profile reads as 8.00008 against a limit of 8 without it. Shape (segments, joints).
    """
    eps = float(np.finfo(np.float64).eps) * _ROUNDING_FACTOR
    with np.errstate(all="ignore"):
        T = np.diff(pk.knots)[:, None]
        q_scale = np.maximum(np.abs(pk.q_min), np.abs(pk.q_max))
        v_round = eps * q_scale / T
        a_round = eps * (q_scale / T + pk.v_peak) / T
    # non-finite (a segment that is not representable): no allowance, the check reports it
    return np.nan_to_num(v_round, nan=0.0, posinf=0.0), np.nan_to_num(a_round, nan=0.0, posinf=0.0)


def time_scale_for_limits(
    sampler: TrajectorySampler, max_velocity: npt.ArrayLike, max_acceleration: npt.ArrayLike
) -> float:
    """Smallest uniform slow-down factor (>= 1) that brings the peak velocities and accelerations within the limits.

    Exact for the segments between the points (velocities scale with 1/k, accelerations with
    1/k^2); the segment from a moving start state changes shape when stretched, so callers
    re-check and iterate. ``inf`` if the motion is not finite.
    """
    pk = sampler.peaks()
    if pk.v_peak.size == 0:
        return 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        kv = np.max(pk.v_peak / np.asarray(max_velocity, dtype=np.float64))
        ka = math.sqrt(float(np.max(pk.a_peak / np.asarray(max_acceleration, dtype=np.float64))))
    k = max(1.0, float(kv), ka)
    return k if math.isfinite(k) else math.inf


# --------------------------------------------------------------------------- planning
