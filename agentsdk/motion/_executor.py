"""The executor: the per-tick hot path that samples each running motion and writes its setpoint."""

from __future__ import annotations

import math
from functools import partial
from types import MappingProxyType
from typing import Any

import numpy as np

from ..errors import CommandRejected
from ..limits import StepGuard, StepLimiter
from ..loop import ControlLoop, Phase, Setpoint, StateView
from ..offload import OffloadedGoal, OffloadRequest, TrajectoryOffload
from ..trajectory import Trajectory
from ._admission import _Admission
from ._ownership import _Ownership
from ._records import _Exec, _MotionTable, _TickBuffers
from ._stops import _StopPlanner
from ._types import (
    _BOUND_TOL,
    _POS,
    _REMOTE_STILL,
    _REMOTE_STILL_SPEED,
    _TWO_PI,
    MotionPhase,
    MotionResult,
    ResultCode,
    _wrap_angle,
)


def _wrap_into(x: np.ndarray, wrap: np.ndarray, tmp: np.ndarray) -> None:
    """``x[wrap] = _wrap_angle(x[wrap])`` in place (the same arithmetic, no allocation)."""
    np.add(x, math.pi, out=tmp)
    np.remainder(tmp, _TWO_PI, out=tmp)
    np.subtract(tmp, math.pi, out=tmp)
    np.copyto(x, tmp, where=wrap)


class _Executor:
    """Runs every motion in the control tick: samples, checks tolerances, limits, writes (allocation-free)."""

    def __init__(self, loop: ControlLoop, table: _MotionTable, ownership: _Ownership, stops: _StopPlanner,
                 admission: _Admission, limiter: StepLimiter, guard: StepGuard | None,
                 offload: TrajectoryOffload | None) -> None:
        self.loop = loop
        self.table = table
        self.ownership = ownership
        self.stops = stops
        self.admission = admission
        #: the limiter every sample passes through: the safety layer's, else the position bounds alone
        self._limiter = limiter
        #: the safety layer's limiter the setpoints pass through (None: none), so that a planned step
        #: it would clip is caught here and reported, never clipped silently
        self._guard = guard
        #: the live origin of each joint's step window (the setpoint the limiter measures from), or None
        self._origin = None if guard is None else guard.origin
        #: the backend's controller runs whole trajectories (goals) instead of streamed setpoints, or None
        self._offload = offload
        # what the tick calls on its collaborators, bound once (no attribute chain per tick)
        self._advance = ownership.advance
        self._finish = ownership.finish
        self._resolve = ownership.resolve
        self._abort = stops.abort
        self._begin_stop = stops.begin_stop

    def install(self, ex: _Exec) -> None:
        """Run ``ex`` (its joints are now its own) from the next tick on."""
        self.ownership.own(ex)
        self._add_hook(ex)

    def schedule(self, ex: _Exec) -> None:
        """Run the scheduled ``ex`` from the next tick on: it waits for its start time, then takes its joints."""
        self.table.pending.append(ex)
        self._add_hook(ex)

    def _add_hook(self, ex: _Exec) -> None:
        # a partial, not a lambda: block lockstep tells the executor's hooks (and their records) from
        # any other COMMAND hook by it (``hook.func == executor.update``, ``hook.args == (ex,)``)
        self.loop.add_hook(Phase.COMMAND, partial(self.update, ex))

    def record_of(self, hook: Any) -> _Exec | None:
        """The record a COMMAND hook runs if it is one of this executor's, else None (block lockstep)."""
        if isinstance(hook, partial) and hook.func == self.update and len(hook.args) == 1 and not hook.keywords:
            ex = hook.args[0]
            return ex if isinstance(ex, _Exec) else None
        return None

    def start_ramp(self, idx: np.ndarray, q: Any, v: Any, a: Any, code: ResultCode | None, msg: str,
                   on_done: Any = None) -> _Exec:
        """A stop ramp of joints ``idx`` from (q, v, a), run from now; it ends with ``code`` (None: no motion)."""
        t0 = self.loop.stamp
        sampler = self.stops.plan_stop_sampler(idx, q, v, a, t0)
        n = len(idx)
        ex = _Exec(None, idx, sampler, t0, np.full(n, np.inf), np.full(n, np.inf), 0.0, goal=q.copy(),
                   phase=MotionPhase.STOPPING, stop_code=code, stop_msg=msg, on_done=on_done)
        ex.tau = ex.t_last = t0
        ex.des_q, ex.des_v, ex.des_a = q.copy(), v.copy(), a.copy()
        self.install(ex)
        return ex

    def preempt(self, idx: np.ndarray) -> None:
        """End (PREEMPTED) what drives joints ``idx``; its other joints come to rest along a stop ramp."""
        seen: list[_Exec] = []
        owner = self.table.owner
        for j in idx.tolist():
            ex = owner[j]
            if ex is not None and ex not in seen:
                seen.append(ex)
        taken = set(idx.tolist())
        for ex in seen:
            rest = np.array([j for j in ex.idx.tolist() if j not in taken], dtype=np.intp)
            q, v, a = self.ownership.desired(rest) if len(rest) else (None, None, None)
            self._finish(ex, ResultCode.PREEMPTED, "preempted by a newer trajectory")
            if len(rest):
                # joints the new trajectory does not cover come to rest smoothly
                self.start_ramp(rest, q, v, a, None, "")

    def _activate(self, ex: _Exec, t: float) -> bool:
        """A scheduled motion's start time has come: take over its joints from whatever drives them."""
        pending = self.table.pending
        if ex in pending:
            pending.remove(ex)
        idx = ex.idx
        q0, v0, a0 = self.ownership.desired(idx)
        traj = ex.pending_traj
        assert traj is not None
        try:
            late = t - ex.t0
            if late > 1e-9:  # the start fell between two ticks: what elapsed since is skipped
                traj = traj.after(late)
            traj, sampler = self.admission.prepare(ex, traj, q0, v0, a0, t)
        except CommandRejected as exc:
            ex.phase = MotionPhase.DEAD
            if ex.motion is not None:
                ex.motion._settle(
                    MotionResult(ResultCode.INVALID_GOAL, {n: 0.0 for n in ex.motion.joint_names},
                                 f"invalid at its scheduled start: {exc}", t))
            return False
        if ex.motion is not None:
            ex.motion.trajectory = traj
        self.preempt_offloaded()
        self.preempt(idx)
        self.ownership.own(ex)
        self.admission.begin(ex, sampler, q0, v0, a0, t)
        self.try_offload(ex, traj)
        return True

    def update(self, ex: _Exec, t: float, st: StateView, sp: Setpoint) -> bool:
        """One tick of ``ex`` at robot time ``t``: sample, check, limit, write; False once it has ended."""
        if ex.phase == MotionPhase.DEAD:
            return False
        if ex.phase == MotionPhase.PENDING:
            if t < ex.t0 - 1e-9:
                return True
            if not self._activate(ex, t):
                return False
        idx = ex.idx
        w = ex.work
        if w is None:
            w = ex.work = _TickBuffers(len(idx))
        remote = ex.remote
        if remote is not None and ex.remote_rest < 0.0 and not remote.started():
            ex.t_last = t  # the controller has not taken the goal yet: its trajectory time has not begun
        dt = t - ex.t_last
        s = ex.s
        if dt > 0.0 and s == self.table.speed and ex.phase != MotionPhase.STOPPING:  # _advance's common case, inline
            if dt > self.loop.period:
                dt = self.loop.period
            tau = ex.tau = ex.tau + s * dt
            sdot = ex.sdot = 0.0
        else:
            tau, s, sdot = self._advance(ex, t)
            ex.tau, ex.s, ex.sdot = tau, s, sdot
        ex.t_last = t
        ex.sampler.sample_into(tau, w.sample)
        q, vt, at = w.q, w.vt, w.at
        stopping = ex.phase == MotionPhase.STOPPING
        if stopping or (s == 1.0 and sdot == 0.0):
            v, a = vt, at
        else:  # v = vt * s, a = at * s^2 + vt * sdot
            v, a = w.v, w.a
            np.multiply(vt, s, out=v)
            np.multiply(at, s * s, out=a)
            np.multiply(vt, sdot, out=w.tmp)
            np.add(a, w.tmp, out=a)
        ex.vt, ex.at = vt, at
        bound = w.bound
        if bound is None or bound[0] is not sp or bound[1] is not st or bound[2] is not self._origin:
            w.bind(idx, sp, st, self._origin, self.loop)
        pos_view = w.st_views[0]
        actual = pos_view if pos_view is not None else np.take(st.position, idx, out=w.actual, mode="clip")
        err = np.subtract(q, actual, out=w.err)
        if ex.wrap is not None:
            _wrap_into(err, ex.wrap, w.tmp)
        m = ex.motion
        elapsed = tau - ex.t0
        if ex.remote is not None:
            return self._update_remote(ex, ex.remote, t, st, sp, q, v, a, err, elapsed)
        if ex.phase == MotionPhase.FOLLOW:
            if ex.path_unbounded:  # |err| <= inf fails only where err is NaN, as err <= inf does
                np.less_equal(err, ex.path_tol, out=w.mask)
            else:
                np.less_equal(np.abs(err, out=w.tmp), ex.path_tol, out=w.mask)
            if w.mask.tobytes() != w.all:
                over = ~w.mask
                k = int(np.argmax(over))
                name = m.joint_names[k] if m else str(k)
                self._abort(ex, ResultCode.PATH_TOLERANCE_VIOLATED,
                            f"path tolerance violated on joint {name!r}: error {err[k]:.4f} > {ex.path_tol[k]:.4f}",
                            t, q, v, a, over)
                return self._write_stop(ex, t, st, sp)
            if elapsed >= ex.sampler.duration:
                if ex.end_moving:  # ends moving (allow_nonzero_velocity_at_end): decelerate, then hold
                    self._begin_stop(ex, ResultCode.SUCCESSFUL, "ended moving; decelerated to rest", t, q, v, a,
                                     None)
                    return self._write_stop(ex, t, st, sp)
                ex.phase = MotionPhase.SETTLE
        qc = self._limited_sample(ex, w, q, v, a)
        if qc is None:  # a step the limiter would have clipped: aborted
            return self._write_stop(ex, t, st, sp)
        if ex.phase == MotionPhase.SETTLE:
            gerr = np.subtract(ex.goal, actual, out=w.tmp)
            if ex.wrap is not None:
                _wrap_into(gerr, ex.wrap, w.dev)
            np.abs(gerr, out=gerr)
            np.less_equal(gerr, ex.goal_tol, out=w.mask)
            if w.mask.tobytes() == w.all:
                self._write(ex, t, st, sp, qc, v, a, err)
                self._finish(ex, ResultCode.SUCCESSFUL, "")
                self.loop.hold_at(idx, qc)
                return False
            if elapsed >= ex.sampler.duration + ex.goal_time:
                bad = ~(gerr <= ex.goal_tol)
                k = int(np.argmax(gerr - ex.goal_tol))
                name = m.joint_names[k] if m else str(k)
                msg = f"goal tolerance violated on joint {name!r}: error {gerr[k]:.4f} > {ex.goal_tol[k]:.4f}"
                self._abort(ex, ResultCode.GOAL_TOLERANCE_VIOLATED, msg, t, q, v, a, bad)
                # like JTC the result is known now; the stop from the measured state carries on
                self._resolve(ex, ResultCode.GOAL_TOLERANCE_VIOLATED, msg)
                ex.motion = None
                return self._write_stop(ex, t, st, sp)
        elif stopping and elapsed >= ex.sampler.duration:
            self._write(ex, t, st, sp, qc, v, a, err)
            self._finish(ex, ex.stop_code, ex.stop_msg)
            self.loop.hold_at(idx, qc)
            return False
        self._write(ex, t, st, sp, qc, v, a, err)
        return True

    def _write_stop(self, ex: _Exec, t: float, st: StateView, sp: Setpoint) -> bool:
        """The reference was just replaced by a stop starting at ``t``: write its first sample."""
        q, v, a = ex.sampler.sample(t)
        ex.vt, ex.at = v, a
        err = q - st.position[ex.idx]
        if ex.wrap is not None:
            err = np.where(ex.wrap, _wrap_angle(err), err)
        qc = self._limited(ex, q, v, a)
        assert qc is not None  # only a FOLLOW sample aborts instead of being limited; this is a stop
        self._write(ex, t, st, sp, qc, v, a, err)
        if ex.sampler.duration <= 0.0:
            self._finish(ex, ex.stop_code, ex.stop_msg)
            self.loop.hold_at(ex.idx, qc)
            return False
        return True

    def _limited_sample(self, ex: _Exec, w: _TickBuffers, q: np.ndarray, v: np.ndarray,
                        a: np.ndarray) -> np.ndarray | None:
        """:meth:`_limited` for this tick's sample ``q``, skipped where the motion's envelope proves it the identity.

        See :mod:`._envelope`: the sample's segment lies strictly inside the bounds, and either no
        step window applies or consecutive samples stay within it and the limiter's origin still
        holds the previous (unclipped) sample. Then ``q`` is what the limiter would return, bit for bit.
        """
        env = ex.env
        if env is None or env.sampler is not ex.sampler:
            return self._limited(ex, q, v, a)
        lim = ex.limits
        steps = lim is not None and lim.step is not None and self._origin is not None
        if env.inside[env.sampler.region + 1]:
            if not steps:
                return q
            o = w.st_views[2]
            prev = env.prev
            if env.step_free and o is not None and prev is not None and o.tobytes() == prev:
                env.prev = q.tobytes()
                return q
        qc = self._limited(ex, q, v, a)
        env.prev = None
        if qc is not None and steps and env.step_free:
            b = qc.tobytes()
            if b == q.tobytes():
                env.prev = b
        return qc

    def _limited(self, ex: _Exec, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray | None:
        """``q`` through the safety layer's :class:`~agentsdk.limits.StepLimiter` (the same calls its filter makes).

        For a validated motion this only removes float noise (a plan exactly at the limits), so the
        filter never clips what a motion writes. A planned step beyond it (e.g. a first point at
        time 0 away from the robot) aborts the motion before anything is written (None is returned:
        the caller writes the stop instead); a stop ramp limited by more than noise (stopping a
        joint that moves towards its limit) is reported once. Never silent.
        """
        guard = self._guard
        lim = ex.limits
        if lim is None:
            lim = ex.limits = self._limiter.select(ex.idx)
        w = ex.work
        if w is None:
            w = ex.work = _TickBuffers(len(ex.idx))
        out = lim.clamp_bounds(q, w.out)
        what = ""
        np.not_equal(out, q, out=w.mask)
        if w.mask.tobytes() != w.none and float(np.max(np.abs(out - q))) > _BOUND_TOL:
            what = "bounds"
        step, step_tol = lim.step, lim.step_tol
        origin = self._origin
        if step is not None and step_tol is not None and origin is not None:
            o = w.st_views[2]
            if o is None or w.bound is None or w.bound[2] is not origin:
                o = np.take(origin, ex.idx, out=w.o, mode="clip")
            dev = np.abs(np.subtract(out, o, out=w.dev), out=w.dev)
            # beyond the limiter's window: float noise is clamped, more aborts
            np.greater(dev, step, out=w.mask)
            if w.mask.tobytes() != w.none:
                if not what and (dev > step_tol).any():
                    what = "step"
                lim.clamp_step(out, o, out)
        if not what:
            return out
        lo, hi = lim.lo, lim.hi
        idx = ex.idx
        k = int(np.argmax(np.abs(out - q)))
        name = self.loop.names[int(idx[k])]
        if ex.phase == MotionPhase.FOLLOW:
            if what == "step":
                assert step is not None and origin is not None
                detail = (f"the planned setpoint of joint {name!r} steps {abs(q[k] - origin[idx[k]]):.4g} in one "
                          f"control period, more than max_position_step {step[k]:.4g}: the motion does not continue "
                          "from the current reference (e.g. a first point at time_from_start 0 away from the "
                          "robot); aborted, not clipped")
            else:
                detail = (f"the planned setpoint of joint {name!r} ({q[k]:.6g}) leaves its bounds "
                          f"[{lo[k]:.6g}, {hi[k]:.6g}]; aborted, not clipped")
            if guard is not None:
                guard.report(what, detail, name)
            bad = np.abs(out - q) > 0.0
            # the joints that would step stop from their measured state, the others from this sample
            self._abort(ex, ResultCode.ABORTED, f"aborted: {detail}", ex.t_last, q, v, a, bad)
            return None
        if not ex.reported_clip:
            ex.reported_clip = True
            if guard is not None:
                kind = "stop ramp" if ex.phase is MotionPhase.STOPPING else "motion"
                guard.report("clip", f"the {kind} of joint {name!r} "
                             f"was limited by {abs(out[k] - q[k]):.4g} ({what}: position bounds or "
                             "max_position_step)", name)
        return out

    def _write(self, ex: _Exec, t: float, st: StateView, sp: Setpoint, qc: np.ndarray, v: np.ndarray,
               a: np.ndarray, err: np.ndarray) -> None:
        """Write the (already limited) reference ``qc``/``v`` of ``ex``'s joints; publish its feedback."""
        idx = ex.idx
        loop = self.loop
        ex.des_q, ex.des_v, ex.des_a = qc, v, a
        w = ex.work
        if w is None:
            w = ex.work = _TickBuffers(len(idx))
        bound = w.bound
        if bound is None or bound[0] is not sp or bound[1] is not st:
            w.bind(idx, sp, st, self._origin, loop)
        sel = ex.sel = w.sel
        rows = w.sp_rows
        if rows is not None:  # consecutive joints, through views made once (basic indexing makes a view per write)
            mode, enabled, position, velocity, _effort, _kp, _kd, target, _gp, _gd, acceleration = w.sp_views
            mode.fill(_POS)
            enabled.fill(True)
            qv, const = rows
            if qc is w.q and v is w.vt:  # the sample's rows as they are: position and velocity in one copy
                qv[...] = w.qv
            else:
                position[...] = qc
                velocity[...] = v
            const[...] = w.const  # effort 0, the loop's kp and kd (read-only: copied when bound)
            target[...] = qc
            acceleration[...] = a  # the servo law's inverse-dynamics feed-forward
        else:
            sp.mode[sel] = _POS
            sp.enabled[sel] = True
            sp.position[sel] = qc
            sp.velocity[sel] = v
            sp.acceleration[sel] = a
            sp.effort[sel] = 0.0
            sp.kp[sel] = np.take(loop.gain_p, sel, out=w.gain, mode="clip")
            sp.kd[sel] = np.take(loop.gain_d, sel, out=w.gain, mode="clip")
            sp.target[sel] = qc
        m = ex.motion
        if m is not None:
            # the feedback of this tick, by reference (a Feedback is built only when someone reads it)
            snap = m._publish()
            if ex.phase != MotionPhase.STOPPING:  # a stop ramp is no progress along the trajectory: keep the last
                dur = ex.sampler.duration
                snap.progress = min(1.0, (ex.tau - ex.t0) / dur) if dur > 0 else 1.0
            snap.time = t
            snap.q, snap.v, snap.err = qc, v, err
            pos_view, vel_view, _ = w.st_views
            st_rows = w.st_rows
            if st_rows is not None:
                w.measured[...] = st_rows
            elif pos_view is not None and vel_view is not None:
                w.act[...] = pos_view
                w.actual_v[...] = vel_view
            else:
                np.take(st.position, idx, out=w.act, mode="clip")
                np.take(st.velocity, idx, out=w.actual_v, mode="clip")
            snap.actual_q, snap.actual_v = w.act, w.actual_v
            remote = ex.remote
            if remote is not None and remote.desired_into(ex.remote_q, ex.remote_v):
                # an offloaded goal: the desired state is the controller's, from its feedback (and what the
                # following-error check may judge these joints by: the controller runs the goal on its own clock)
                snap.q, snap.v = ex.remote_q, ex.remote_v
                self.loop.controller_desired[ex.idx] = ex.remote_q
                np.subtract(ex.remote_q, w.act, out=err)
                if ex.wrap is not None:
                    _wrap_into(err, ex.wrap, w.tmp)
            snap.seq += 1
            if snap.keep_measured:
                m._keep_measured(st.position)

    # ------------------------------------------------------------ offload (agentsdk.offload)
    def try_offload(self, ex: _Exec, traj: Trajectory) -> None:
        """Hand ``ex``'s validated trajectory to the backend's controller as one goal, where it can take it.

        Only a motion that alone drives the robot (the other joints hold) and ends at rest is
        offloaded; the executor then keeps sampling it locally (limits, setpoint) while the
        backend streams nothing, and the controller's outcome ends it (:meth:`_update_remote`).
        """
        if self._offload is None or ex.motion is None or ex.end_moving:
            return
        if any(o is not None and o is not ex for o in self.table.owner):
            return  # another motion or stop ramp drives joints: streamed
        names, sp = self.loop.names, self.loop.setpoint
        others = np.ones(len(names), dtype=bool)
        others[ex.idx] = False
        hold = MappingProxyType({names[j]: float(sp.position[j]) for j in np.flatnonzero(others).tolist()})
        remote = self._offload.offload_trajectory(
            OffloadRequest(traj, ex.path_tol.copy(), ex.goal_tol.copy(), ex.goal_time, hold))
        if remote is None:
            return
        ex.remote, ex.s, ex.sdot = remote, 1.0, 0.0
        self.loop.controller_desired[ex.idx] = np.nan  # until this goal's controller reports its own
        ex.remote_q, ex.remote_v = np.zeros(len(ex.idx)), np.zeros(len(ex.idx))

    def preempt_offloaded(self) -> None:
        """A new motion on any joint preempts an offloaded goal (the controller runs one trajectory at a time)."""
        for ex in [o for o in dict.fromkeys(self.table.owner) if o is not None and o.remote is not None]:
            if ex.remote_rest >= 0.0:  # its goal has ended: the joints hold where the setpoint is
                self._finish(ex, None, "")
                continue
            q, v, a = self.ownership.desired_next(ex)
            self._finish(ex, ResultCode.PREEMPTED, "preempted by a newer trajectory")
            self.start_ramp(ex.idx, q, v, a, None, "")

    def _update_remote(self, ex: _Exec, remote: OffloadedGoal, t: float, st: StateView, sp: Setpoint,
                       q: np.ndarray, v: np.ndarray, a: np.ndarray, err: np.ndarray, elapsed: float) -> bool:
        """One tick of an offloaded motion: follow the local sample (not streamed) until the controller's outcome.

        Success: the local sample runs to its end (the goal), then the joints hold there. Any other
        outcome (or a cancel asked here): the motion's result is known at once; the controller stops
        the robot itself, and the setpoint follows the measured position (nothing streamed) until
        the joints have been still for :data:`_REMOTE_STILL` s, then holds there and streaming resumes.
        """
        outcome = remote.outcome(t)
        if ex.remote_rest >= 0.0:  # the goal ended: wait for the controller's own stop to come to rest
            return self._follow_remote_stop(ex, t, st, sp)
        if outcome is not None:
            try:
                code = ResultCode(outcome[0])
            except ValueError:
                code = ResultCode.ABORTED
            msg = outcome[1]
            if ex.phase == MotionPhase.STOPPING and ex.stop_code is not None:
                code, msg = ex.stop_code, ex.stop_msg  # asked here (cancel, abort, stop_early): that is the result
            elif code is ResultCode.SUCCESSFUL:
                if elapsed >= ex.sampler.duration:
                    qc = self._limited(ex, q, v, a)
                    if qc is None:
                        return self._write_stop(ex, t, st, sp)
                    self._write(ex, t, st, sp, qc, v, a, err)
                    self._finish(ex, ResultCode.SUCCESSFUL, msg)
                    self.loop.hold_at(ex.idx, qc)
                    return False
                outcome = None  # reached early: the local sample catches up before the motion ends
            if outcome is not None:
                self._resolve(ex, code, msg)
                ex.motion = None
                ex.phase = MotionPhase.STOPPING
                ex.remote_rest = t
                return self._follow_remote_stop(ex, t, st, sp)
        if ex.phase == MotionPhase.FOLLOW and elapsed >= ex.sampler.duration:
            ex.phase = MotionPhase.SETTLE  # the controller's goal tolerance and goal time decide
        qc = self._limited(ex, q, v, a)
        if qc is None:
            return self._write_stop(ex, t, st, sp)
        self._write(ex, t, st, sp, qc, v, a, err)
        return True

    def _follow_remote_stop(self, ex: _Exec, t: float, st: StateView, sp: Setpoint) -> bool:
        """The setpoint of an ended offloaded goal's joints is their measured position until they are still."""
        idx = ex.idx
        n = len(idx)
        w = ex.work
        if w is None:
            w = ex.work = _TickBuffers(n)
        qm = np.take(st.position, idx, out=w.actual, mode="clip")
        if np.count_nonzero(np.isfinite(qm, out=w.mask)) != n:
            np.copyto(qm, ex.des_q)  # a failing sensor: hold the last setpoint
        # still: the measured position stays within _REMOTE_STILL_SPEED * _REMOTE_STILL of where the window
        # began (a velocity is not needed: some controllers report none, and encoder noise stays well below)
        ref = ex.remote_q  # no feedback is published any more (the motion has its result): free buffers
        if ex.remote_rest == t:  # the goal has just ended: the setpoint is the measured position from now on
            ref[...] = qm
            if self._guard is not None:
                # the local sample was never sent (the controller ran the goal): no step to limit from it
                self._guard.rebase(idx, qm)
        moved = float(np.abs(np.subtract(qm, ref, out=w.dev), out=w.dev).max(initial=0.0))
        zero = ex.remote_v
        zero.fill(0.0)
        qc = self._limited(ex, qm, zero, zero)
        assert qc is not None  # a stopping executor is limited, never aborted
        err = np.subtract(qm, qc, out=w.err)
        # ... and the setpoint has reached it (the step limiter moves it at most max_position_step a tick)
        if (moved > _REMOTE_STILL_SPEED * _REMOTE_STILL
                or float(np.abs(err, out=w.tmp).max(initial=0.0)) > 1e-9):
            ex.remote_rest = t
            ref[...] = qm
        self._write(ex, t, st, sp, qc, zero, zero, err)
        if t - ex.remote_rest >= _REMOTE_STILL:
            self._finish(ex, None, "")
            self.loop.hold_at(idx, qc)
            return False
        return True
