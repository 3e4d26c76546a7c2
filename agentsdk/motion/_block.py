"""Block lockstep's planning seam (issue 28 item 1): a running motion's references for K ticks at once.

:class:`_BlockPlanner` answers, for one executor record, what :meth:`._executor._Executor.update`
would write in each of the coming K ticks and how many of them are *pre-planned* (fixed before the
block runs, whatever the measured state), without changing the record. The control loop does not
use it yet; ``tests/test_block_seam.py`` checks its answers against what real ticks write.
"""

from __future__ import annotations

import numpy as np

from ..limits import StepLimiter
from ..loop import ControlLoop
from ._envelope import _Envelope, envelope
from ._records import _Exec, _MotionTable
from ._types import MotionPhase


class _BlockPlanner:
    """The references of a motion's coming ticks, computed at once (bit for bit the tick's), and how many are fixed."""

    def __init__(self, loop: ControlLoop, table: _MotionTable, origin: np.ndarray | None) -> None:
        self.loop = loop
        self.table = table
        #: the live origin of each joint's step window (the safety limiter's), or None
        self._origin = origin

    def reference(self, ex: _Exec, ts: np.ndarray, taus: np.ndarray, out: np.ndarray) -> int:
        """The references of ``ex`` for the coming ticks at robot times ``ts`` (K,), all at once.

        Block lockstep's seam (issue 28 item 1): writes each tick's trajectory time into ``taus``
        (K,) and its sample ``[q, v, a]`` into ``out`` (K, 3, joints of ``ex``) and returns how many
        leading ticks are *pre-planned*: for those, :meth:`update` would write exactly that sample
        (bit for bit, as position, velocity and acceleration), whatever the measured state is,
        unless its path tolerance fails (the block's checks decide that from the measured states;
        :meth:`_Executor.update` is the per-tick rule this reproduces).
        The count stops before the first tick that is an event of the motion (its trajectory ends,
        its stop ramp ends) and is 0 where anything is not proven: a scheduled, offloaded or first
        tick, speed scaling other than 1, a sample the limiter might change (see :mod:`._envelope`;
        a stop ramp's envelope is computed here, once per ramp, while its tick keeps the full path).
        Nothing of ``ex`` changes.
        """
        K = len(ts)
        if K == 0 or ex.remote is not None or ex.phase not in (MotionPhase.FOLLOW, MotionPhase.STOPPING):
            return 0
        stopping = ex.phase == MotionPhase.STOPPING
        if not stopping and not (ex.s == 1.0 and self.table.speed == 1.0):
            return 0
        w, lim = ex.work, ex.limits
        if w is None or lim is None:
            return 0
        env = self._ramp_envelope(ex, lim) if stopping else ex.env
        if env is None or env.sampler is not ex.sampler:
            return 0
        if lim.step is not None and self._origin is not None:
            # the step proof needs the limiter's origin to hold the previous tick's sample, unclipped
            o = w.st_views[2]
            if not env.step_free or o is None:
                return 0
            if stopping:  # (the tick keeps no bytes of its last sample for a stop ramp: sample it again)
                region = ex.sampler.region
                prev = ex.sampler.sample(ex.tau)[0]
                ex.sampler.region = region
                if o.tobytes() != prev.tobytes():
                    return 0
            elif env.prev is None or o.tobytes() != env.prev:
                return 0
        # trajectory time: tau += min(t - t_last, period) per tick (s = 1: s * dt is dt), accumulated in order
        dts = np.empty(K + 1)
        dts[0] = ex.tau
        np.subtract(ts[1:], ts[:-1], out=dts[2:])
        dts[1] = ts[0] - ex.t_last
        if not dts[1] > 0.0:
            return 0
        np.minimum(dts[1:], self.loop.period, out=dts[1:])
        np.add.accumulate(dts, out=dts)
        taus[...] = dts[1:]
        sampler = ex.sampler
        region = sampler.region
        regions = np.empty(K, dtype=np.intp)
        try:
            sampler.sample_block(taus, out, regions)
        finally:
            sampler.region = region
        # the motion's own event: its trajectory (or ramp) ends, at the first elapsed >= duration
        ended = np.flatnonzero(np.subtract(taus, ex.t0) >= sampler.duration)
        k = int(ended[0]) if len(ended) else K
        # a sample outside the proven envelope takes the limiter's full path: per tick from there
        inside = np.asarray(env.inside)[regions[:k] + 1]
        if not inside.all():
            k = int(np.argmin(inside))
        return k

    def _ramp_envelope(self, ex: _Exec, lim: StepLimiter) -> _Envelope | None:
        """The envelope of ``ex``'s stop ramp under ``lim`` (cached per sampler), for :meth:`reference`."""
        cached = ex.ramp_env
        if cached is None or cached[0] is not ex.sampler:
            cached = ex.ramp_env = (ex.sampler, envelope(ex.sampler, lim, self.loop.period))
        return cached[1]
