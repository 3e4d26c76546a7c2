"""What a motion's sampled reference can never do, computed once, so the executor's tick can skip the limiter.

The executor passes every sample of a trajectory through the safety layer's
:class:`~agentsdk.limits.StepLimiter` (position bounds, then the step window around the last
written setpoint) to catch a planned setpoint the limiter would clip. For a validated motion
away from its limits both are the identity, and the sampler's exact per-segment extremes
(:meth:`~agentsdk.trajectory.TrajectorySampler.peaks`, computed by the admission anyway) prove it
ahead of time:

- **bounds**: a segment whose position range, widened by the rounding of its evaluation, lies
  strictly inside ``(lo, hi)`` samples values ``clip`` returns unchanged, bit for bit;
- **steps**: trajectory time advances by at most one control period per tick (speed scaling
  only slows it), so two consecutive samples differ by at most ``max |v| * period`` plus their
  rounding; below ``max_position_step`` on every joint, the step window never clips a sample
  whose predecessor is the setpoint the limiter measures from. The tick checks that last part
  (the limiter's origin still holds, byte for byte, the previous sample: nothing else wrote or
  clipped it) with one bytes compare.

Anything not proven (a segment touching a bound, a plan at the velocity limit, joints that are
not consecutive, the first tick of a motion) takes the limiter's full path, so the setpoints
are bit-identical either way (``tests/test_tick_hashes.py``).
"""

from __future__ import annotations

import numpy as np

from ..limits import StepLimiter
from ..trajectory import TrajectorySampler

#: allowance for the rounding of one sample (the polynomial's terms, local time from absolute times),
#: in units of eps times their magnitude; generous: a looser bound only sends more ticks the full path
_ROUNDING = 64.0
_EPS = float(np.finfo(np.float64).eps)


class _Envelope:
    """Per-region answers for one sampler and limiter (regions: before, each segment, after)."""

    __slots__ = ("inside", "prev", "sampler", "step_free")

    def __init__(self, sampler: TrajectorySampler, inside: tuple[bool, ...], step_free: bool) -> None:
        self.sampler = sampler
        #: ``inside[sampler.region + 1]``: every sample of that region is strictly within the bounds
        self.inside = inside
        #: consecutive samples never step more than the limiter's window (or there is no window)
        self.step_free = step_free
        #: bytes of the previous tick's setpoint when it was the unclipped sample (else None)
        self.prev: bytes | None = None


def envelope(sampler: TrajectorySampler, lim: StepLimiter, period: float) -> _Envelope | None:
    """The :class:`_Envelope` of ``sampler`` under ``lim`` at control ``period``, or None if nothing is proven."""
    c = sampler.coefficients()
    n_seg = len(c)
    lo, hi = lim.lo, lim.hi
    start_q, end_q = sampler.sample(sampler.start_time - 1.0)[0], sampler.sample(sampler.end_time + 1.0)[0]
    with np.errstate(all="ignore"):
        ends_inside = [bool(np.all((lo < q) & (q < hi))) for q in (start_q, end_q)]
        if n_seg == 0:
            return _Envelope(sampler, (ends_inside[0], ends_inside[1]), lim.step is None)
        pk = sampler.peaks()
        T = np.diff(pk.knots)
        powers = np.abs(T)[:, None] ** np.arange(6.0)  # (segments, 6)
        magnitude = np.einsum("skj,sk->sj", np.abs(c), powers)  # sum_k |c_k| T^k, (segments, joints)
        v_max = np.max(pk.v_peak, axis=0)  # (joints,)
        t_max = float(np.max(np.abs(pk.knots)))
        err = _ROUNDING * _EPS * (magnitude + v_max * t_max)  # (segments, joints)
        seg_inside = np.all((pk.q_min - err > lo) & (pk.q_max + err < hi), axis=1)
        step = lim.step
        if step is None:
            step_free = True
        else:
            rounding = 2.0 * np.max(err, axis=0)
            step_free = bool(np.all(v_max * period * (1.0 + 1e-9) + rounding < step))
    inside = (ends_inside[0], *(bool(x) for x in seg_inside.tolist()), ends_inside[1])
    if not any(inside):
        return None
    return _Envelope(sampler, inside, step_free)
