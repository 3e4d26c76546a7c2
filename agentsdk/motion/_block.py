"""Block lockstep's motion side (issue 28 item 1): a running motion's references for K ticks at once.

:class:`BlockPlanner` answers, for one executor record, what :meth:`._executor._Executor.update`
would write in each of the coming K ticks and how many of them are *pre-planned* (fixed before the
block runs, whatever the measured state), without changing the record
(``tests/test_block_seam.py`` checks its answers against what real ticks write). For
:mod:`agentsdk.block` it takes over one following motion or stop ramp for a block (:meth:`~BlockPlanner.follow`,
its path tolerance over the block's states, :meth:`~BlockPlanner.path_quiet`) and leaves the
record where the block's committed ticks leave it (:meth:`~BlockPlanner.commit`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from ..limits import StepLimiter
from ..loop import ControlLoop
from ._envelope import _Envelope, envelope
from ._executor import _Executor
from ._records import _Exec, _MotionTable
from ._types import _POS, MotionPhase

#: the phases whose ticks a block can plan: following, settling at the goal, a stop ramp
_PLANNED = (MotionPhase.FOLLOW, MotionPhase.SETTLE, MotionPhase.STOPPING)


class BlockPlan:
    """A following motion's samples for one block, and the scratch arrays of its path check.

    ``k``: the ticks planned; ``sel``: its joints (a slice when consecutive); ``samples`` (capacity,
    3, joints): each tick's position, velocity and acceleration. One per joint count, reused.
    """

    def __init__(self, capacity: int, m: int, n: int) -> None:
        self.ex: _Exec | None = None
        self.sel: Any = slice(0, m)
        self.k = 0
        self.ts = np.empty(capacity)
        self.taus = np.empty(capacity)
        self.samples = np.empty((capacity, 3, m))
        self.regions = np.empty(capacity, dtype=np.intp)
        self.pre = np.empty((2, m))
        self.pre_all = np.empty(n)
        self.actual = np.empty((capacity, m))
        self.err = np.empty((capacity, m))
        self.gerr = np.empty((capacity, m))
        #: the setpoint's velocity and acceleration rows when the speed scaling is not 1 (else the samples')
        self.va = np.empty((capacity, 2, m))
        self.scaled = False
        self.tmp = np.empty((capacity, m))
        self.ticks = np.empty(capacity, dtype=np.int64)
        self.zero_to_k = np.arange(capacity, dtype=np.int64)


class BlockPlanner:
    """The references of a motion's coming ticks, computed at once (bit for bit the tick's), and how many are fixed."""

    def __init__(self, loop: ControlLoop, table: _MotionTable, origin: np.ndarray | None,
                 executor: _Executor | None = None) -> None:
        self.loop = loop
        self.table = table
        #: the live origin of each joint's step window (the safety limiter's), or None
        self._origin = origin
        self._executor = executor
        self._plans: dict[tuple[int, int, int], BlockPlan] = {}

    # ------------------------------------------------------------ a following motion in a block
    def _records(self, hooks: tuple[Callable[..., object], ...]) -> list[_Exec] | None:
        """The motions the COMMAND hooks run, if every hook is one a block can take over (else None).

        Each follows its trajectory, settles at its goal or runs a stop ramp (:data:`_PLANNED`), with
        its first tick done.
        """
        executor = self._executor
        if executor is None or not hooks:
            return None
        out = []
        for hook in hooks:
            ex = executor.record_of(hook)
            if ex is not None and ex.phase is MotionPhase.PENDING:
                out.append(ex)  # a scheduled motion: its ticks do nothing until its start time
                continue
            if ex is None or ex.phase not in _PLANNED or ex.remote is not None:
                return None
            w = ex.work
            if w is None or w.bound is None or w.sel is None:
                return None  # its first tick has not run
            if w.bound[0] is not self.loop.setpoint_buffer or w.bound[1] is not self.loop.state:
                return None
            out.append(ex)
        return out

    def follow(self, hooks: tuple[Callable[..., object], ...], K: int, tick0: int,
               capacity: int) -> tuple[int, list[BlockPlan]] | None:
        """Plan the coming ticks (at most ``K``, from clock tick ``tick0``) of the motions ``hooks`` run.

        None when a hook is not a motion a block can take over (:meth:`_records`), or fewer than 2
        of the coming ticks are pre-planned for every one of them (:meth:`reference`; a scheduled
        motion's are until the tick it starts at). Otherwise writes the rows their ticks write
        besides the samples (mode, torque on, effort, gains: the same every tick) into the
        setpoint, as their next tick would, and returns the ticks planned and one plan per running
        motion.
        """
        records = self._records(hooks)
        if records is None:
            return None
        period = self.loop.period
        for ex in records:
            if ex.phase is MotionPhase.PENDING:
                # its hook returns at once while t < t0 - 1e-9 (the tick's own test), then it starts
                first = (ex.t0 - 1e-9 - tick0 * period) / period  # a guess, checked with the tick's test:
                j = max(0, min(K, math.floor(first) - 1))
                while j < K and (tick0 + j) * period < ex.t0 - 1e-9:
                    j += 1
                K = j
        if K < 2:
            return None
        plans = []
        st = self.loop.state.block
        assert st is not None
        for slot, ex in enumerate(r for r in records if r.phase is not MotionPhase.PENDING):
            w = ex.work
            assert w is not None
            m = len(ex.idx)
            plan = self._plans.get((capacity, m, slot))
            if plan is None:
                plan = self._plans[(capacity, m, slot)] = BlockPlan(capacity, m, len(self.loop.joints))
            plan.ex, plan.sel = ex, w.sel
            if w.sp_rows is not None:  # (consecutive joints: the tick's views)
                mode, enabled = w.sp_views[0], w.sp_views[1]
                mode.fill(_POS)
                enabled.fill(True)
                w.sp_rows[1][...] = w.const
            else:  # the tick's writes through the index array
                sp, sel, loop = self.loop.setpoint_buffer, w.sel, self.loop
                sp.mode[sel] = _POS
                sp.enabled[sel] = True
                sp.effort[sel] = 0.0
                sp.kp[sel] = np.take(loop.gain_p, sel, out=w.gain, mode="clip")
                sp.kd[sel] = np.take(loop.gain_d, sel, out=w.gain, mode="clip")
            # tick j's COMMAND phase runs at (tick0 + j) * period, the clock's own product
            ticks = np.add(plan.zero_to_k[:K], tick0, out=plan.ticks[:K])
            ts = np.multiply(ticks, self.loop.period, out=plan.ts[:K])
            K = self.reference(ex, ts, plan.taus[:K], plan.samples[:K], plan.regions[:K])
            if K < 2:
                return None
            s = ex.s
            plan.scaled = ex.phase is not MotionPhase.STOPPING and s != 1.0
            if plan.scaled:  # the tick's v = vt * s, a = at * s^2 + vt * sdot (sdot = 0: s holds)
                va, smp = plan.va[:K], plan.samples[:K]
                np.multiply(smp[:, 1], s, out=va[:, 0])
                np.multiply(smp[:, 2], s * s, out=va[:, 1])
                tmp = np.multiply(smp[:, 1], 0.0, out=plan.tmp[:K])
                np.add(va[:, 1], tmp, out=va[:, 1])
            # the measured position and velocity of its joints as the first tick's COMMAND phase sees them
            # (and of every joint, for a stream of link poses)
            plan.pre[...] = st[0:2, plan.sel]
            plan.pre_all[...] = st[0]
            plans.append(plan)
        for plan in plans:
            plan.k = K
        return K, plans

    def path_quiet(self, plan: BlockPlan, states: np.ndarray, q: int) -> int:
        """How many of the first ``q`` ticks pass the motion's path (or, settling, goal) test quietly, at once.

        Tick j compares its sample with the state after tick j - 1 (``states`` (K, 3, n): the block's).
        """
        ex = plan.ex
        assert ex is not None
        sel = plan.sel
        actual = plan.actual[:q]
        actual[0] = plan.pre[0]
        actual[1:] = states[: q - 1, 0, sel]
        err = np.subtract(plan.samples[:q, 0], actual, out=plan.err[:q])
        if ex.wrap is not None:  # _wrap_into's operations
            tmp = plan.tmp[:q]
            np.add(err, math.pi, out=tmp)
            np.remainder(tmp, 2.0 * math.pi, out=tmp)
            np.subtract(tmp, math.pi, out=tmp)
            np.copyto(err, tmp, where=ex.wrap)
        if ex.phase is MotionPhase.STOPPING:
            return q  # a stop ramp has no path tolerance (its error is still published)
        if ex.phase is MotionPhase.SETTLE:
            # the goal test: the first tick with every joint within its goal tolerance ends the motion
            gerr = np.subtract(ex.goal, actual, out=plan.gerr[:q])
            if ex.wrap is not None:
                tmp = plan.tmp[:q]
                np.add(gerr, math.pi, out=tmp)
                np.remainder(tmp, 2.0 * math.pi, out=tmp)
                np.subtract(tmp, math.pi, out=tmp)
                np.copyto(gerr, tmp, where=ex.wrap)
            np.abs(gerr, out=gerr)
            reached = np.less_equal(gerr, ex.goal_tol).all(axis=1)
            return int(np.argmax(reached)) if reached.any() else q
        if ex.path_unbounded:
            # err <= inf fails only for NaN: a sum without NaN had none (a NaN sum from inf - inf: the test below)
            if not math.isnan(np.add.reduce(err, axis=None)):
                return q
            ok = np.less_equal(err, ex.path_tol)
        else:
            ok = np.less_equal(np.abs(err), ex.path_tol)
        good = ok.all(axis=1)
        return q if good.all() else int(np.argmin(good))

    def commit(self, plan: BlockPlan, states: np.ndarray, q: int) -> None:
        """Leave the motion as ``q`` ticks of :meth:`_Executor.update` leave it: trajectory time, sample, feedback."""
        ex = plan.ex
        assert ex is not None and ex.work is not None
        w = ex.work
        j = q - 1
        w.sample[...] = plan.samples[j]
        ex.sampler.region = int(plan.regions[j])
        ex.tau = float(plan.taus[j])
        ex.t_last = t = float(plan.ts[j])
        ex.sdot = 0.0
        ex.vt, ex.at = w.vt, w.at
        stopping = ex.phase is MotionPhase.STOPPING
        lim, env = ex.limits, ex.env
        steps = lim is not None and lim.step is not None and self._origin is not None
        if stopping or (steps and w.st_views[2] is None):
            # a stop ramp's tick, or one of joints that are not consecutive under a step window, takes the
            # limiter's full path (``_limited``), whose output buffer then holds the sample (the envelope
            # proves it unchanged)
            w.out[...] = plan.samples[j, 0]
            qc = w.out
        else:
            qc = w.q
        if stopping:
            ex.s = 1.0  # (a stop ramp's speed scaling)
        elif env is not None and steps:
            env.prev = w.q.tobytes()  # both paths keep the unclipped sample's bytes
        if w.sp_rows is None:
            w.actual[...] = plan.actual[j]  # (the tick's gathered measured position)
        v, a = w.vt, w.at
        if plan.scaled:
            v, a = w.v, w.a
            v[...] = plan.va[j, 0]
            a[...] = plan.va[j, 1]
        ex.des_q, ex.des_v, ex.des_a = qc, v, a
        w.err[...] = plan.err[j]
        motion = ex.motion
        if motion is None:
            return
        snap = motion._publish()
        if not stopping:  # a stop ramp is no progress along the trajectory
            dur = ex.sampler.duration
            snap.progress = min(1.0, (ex.tau - ex.t0) / dur) if dur > 0 else 1.0
        snap.time = t
        snap.q, snap.v, snap.err = qc, v, w.err
        w.measured[...] = plan.pre if j == 0 else states[j - 1][0:2, plan.sel]
        snap.actual_q, snap.actual_v = w.act, w.actual_v
        snap.seq += q
        if snap.keep_measured:  # a stream of link poses: every joint's measured position at that tick
            motion._keep_measured(plan.pre_all if j == 0 else states[j - 1, 0])

    def reference(self, ex: _Exec, ts: np.ndarray, taus: np.ndarray, out: np.ndarray,
                  regions: np.ndarray | None = None) -> int:
        """The references of ``ex`` for the coming ticks at robot times ``ts`` (K,), all at once.

        Block lockstep's seam (issue 28 item 1): writes each tick's trajectory time into ``taus``
        (K,) and its sample ``[q, v, a]`` into ``out`` (K, 3, joints of ``ex``) and returns how many
        leading ticks are *pre-planned*: for those, :meth:`update` would write exactly that sample
        (bit for bit, as position, velocity and acceleration), whatever the measured state is,
        unless its path tolerance fails (the block's checks decide that from the measured states;
        :meth:`_Executor.update` is the per-tick rule this reproduces).
        The count stops before the first tick that is an event of the motion (its trajectory ends,
        its goal time runs out while it settles, its stop ramp ends; reaching the goal tolerance is
        a test of the measured state, :meth:`path_quiet`) and is 0 where anything is not proven: a
        scheduled, offloaded or first tick, a speed scaling ramp, a sample the limiter might
        change (see :mod:`._envelope`; a stop ramp's envelope is computed here, once per ramp, while
        its tick keeps the full path).
        Nothing of ``ex`` changes. ``regions`` (K,), if given, receives each sample's sampler region
        (as ``ex.sampler.region`` is after that tick).
        """
        K = len(ts)
        if K == 0 or ex.remote is not None or ex.phase not in _PLANNED:
            return 0
        stopping = ex.phase == MotionPhase.STOPPING
        if not stopping and ex.s != self.table.speed:
            return 0  # the speed scaling ramps (``_Ownership.advance``): per tick
        w, lim = ex.work, ex.limits
        if w is None or lim is None:
            return 0
        env = self._ramp_envelope(ex, lim) if stopping else ex.env
        if env is None or env.sampler is not ex.sampler:
            return 0
        if lim.step is not None and self._origin is not None:
            # the step proof needs the limiter's origin to hold the previous tick's sample, unclipped
            o = w.st_views[2]
            if o is None:  # joints that are not consecutive: the origin's values (the tick takes them too)
                o = self._origin[ex.idx]
            if not env.step_free:
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
        if not stopping and ex.s != 1.0:
            np.multiply(dts[1:], ex.s, out=dts[1:])  # tau += s * dt (s = 1: the same bits, skipped)
        np.add.accumulate(dts, out=dts)
        taus[...] = dts[1:]
        sampler = ex.sampler
        region = sampler.region
        if regions is None:
            regions = np.empty(K, dtype=np.intp)
        try:
            sampler.sample_block(taus, out, regions)
        finally:
            sampler.region = region
        # the motion's own event: its trajectory (or ramp) ends, at the first elapsed >= duration; while it
        # settles at the goal, its goal time runs out (the goal tolerance itself is a measured test: path_quiet)
        end = sampler.duration + ex.goal_time if ex.phase is MotionPhase.SETTLE else sampler.duration
        # (taus grows, and so does a rounded difference: none has ended when the last has not)
        if float(taus[-1]) - ex.t0 >= end:
            ended = np.flatnonzero(np.subtract(taus, ex.t0) >= end)
            k = int(ended[0]) if len(ended) else K
        else:
            k = K
        if k == 0:
            return 0
        # a sample outside the proven envelope takes the limiter's full path: per tick from there (the
        # regions grow too: when every region from the first tick's to the last's is inside, every tick is)
        first, last = int(regions[0]), int(regions[k - 1])
        if not all(env.inside[first + 1 : last + 2]):
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
