"""The per-tick filter and command limiting: every setpoint passes the one :class:`StepLimiter`."""

from __future__ import annotations

import time
from types import EllipsisType
from typing import Any

import numpy as np

from ..errors import (
    LimitViolation,
)
from ..limits import StepLimiter
from ..loop import ControlLoop, Setpoint, StateView
from ..types import CommandMode
from ._config import SafetyConfig
from ._state import _EFF, _POS, _VEL, SafetyCore, StopPort, log


def _readonly(arr: np.ndarray) -> np.ndarray:
    arr.flags.writeable = False
    return arr


class CommandFilter:
    """Limits direct commands when admitted and every setpoint in the LIMIT phase of each tick.

    Owns the limiter's origin (the position setpoint the filter let through last tick) and the
    ramps of direct position commands towards their goals. Reads the latch of ``core`` once a
    tick and takes a latch set from another thread over (:meth:`enforce_latch`).
    """

    def __init__(
        self, loop: ControlLoop, config: SafetyConfig, limiter: StepLimiter, core: SafetyCore, motions: StopPort
    ) -> None:
        self._loop = loop
        self._config = config
        self._core = core
        #: the stop port of the motion manager (replaced by SafetyLayer.attach_motions)
        self.motions = motions
        n = len(loop.joints)
        #: the one limiting rule (position bounds, step per period, velocity and effort limits)
        self.limiter = limiter
        self._lo, self._hi = limiter.lo, limiter.hi
        self._step = limiter.step
        #: the step window around an origin holds the origin itself (every step >= 0, none NaN): a
        #: position equal to its origin passes the step clamp unchanged
        self._window_holds_origin = limiter.step is None or bool(np.all(limiter.step >= 0.0))
        self._vmax, self._emax = limiter.vmax, limiter.emax
        #: the limiter's origin: the position setpoint written last tick (always updated in place)
        self._written = loop.state.position.copy()
        #: goal of a direct position command being ramped (max_position_step), per joint (updated in place)
        self._goal = loop.setpoint.position.copy()
        self._ramping = np.zeros(n, dtype=bool)
        #: scratch of the per-tick filter's slow path (a joint ramping or outside position mode)
        self._target = np.zeros(n)
        self._limited = np.zeros(n)
        self._unreached = np.zeros(n, dtype=bool)
        #: ``tobytes()`` of a mode row with every joint in position mode, of an all-true / all-false mask:
        #: the per-tick checks compare bytes (no array, ~5x cheaper than ufunc + np.count_nonzero)
        self._all_position = np.full(n, _POS, dtype=np.int8).tobytes()
        self._all_true = np.ones(n, dtype=bool).tobytes()
        self._all_false = np.zeros(n, dtype=bool).tobytes()
        #: views of the loop's setpoint rows (made once per setpoint object, not per tick)
        self._rows_of: object = None
        self._rows: np.ndarray | None = None
        #: the bytes the last bounds clip of those rows left (a clip's result is its own fixed point)
        self._rows_clipped = b""
        #: the velocity and effort rows among them (views made with ``_rows``), and the bytes the last clip of
        #: the ramp path left in them
        self._ff = np.zeros((2, n))
        self._ff_clipped = b""
        #: deceleration available to stop a velocity stream before a position limit
        self._amax = np.array([j.max_acceleration for j in loop.joints]) * config.stop_deceleration_scale
        self._last_warn: dict[tuple[str, int], float] = {}
        #: the indices a full-length command resolves to (set by the safety layer to its command
        #: shapes' array): such a command is limited against the limiter's whole rows, not copies
        self.full_index: np.ndarray | None = None
        #: limit_command's scratch row for a full-length command
        self._clipped = np.empty(len(limiter.lo))
        self._full_range = {
            "position": (limiter.lo, limiter.hi, "position", "rad"),
            "velocity": (_readonly(np.negative(limiter.vmax)), limiter.vmax, "velocity", "rad/s"),
            "effort": (_readonly(np.negative(limiter.emax)), limiter.emax, "effort", "N·m"),
        }

    # -------------------------------------------------------------- origin and ramps
    def origin(self) -> np.ndarray:
        """A read-only live view of the limiter's origin (what the motion manager measures its steps from)."""
        view = self._written.view()
        view.flags.writeable = False
        return view

    def restart(self, position: np.ndarray) -> None:
        """The limiter starts from ``position`` with no ramp goal pending (start, enable)."""
        np.copyto(self._written, position)
        np.copyto(self._goal, self._written)
        # a ramping joint's goal is always a command limit_command returned (the LIMIT tick relies on it): these
        # goals are measured positions, maybe outside the bounds
        self._ramping[:] = False

    def cancel_ramps(self) -> None:
        """End every direct position ramp where it is."""
        self._ramping[:] = False

    def end_ramps(self) -> np.ndarray:
        """End every direct position ramp; the joints that were ramping (a new mask)."""
        ramping = self._ramping.copy()
        self._ramping[:] = False
        return ramping

    def ramp_next(self, ramping: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where the ramps of joints ``ramping`` would be at the next tick, and at what velocity.

        A stop starts them from there at the ramp's velocity (not from rest: that would be a step).
        Returns ``(idx, position, velocity)``.
        """
        step = self._step if self._step is not None else np.inf
        written = self._written
        nxt = np.clip(np.clip(self._goal, self._lo, self._hi), written - step, written + step)
        idx = np.flatnonzero(ramping)
        return idx, nxt[idx], ((nxt - written) / self._loop.period)[idx]

    def track_measured(self, position: np.ndarray, where: np.ndarray) -> None:
        """The origin of joints ``where`` (outside position mode) is their fresh measurement."""
        np.copyto(self._written, position, where=where)

    def enforce_latch(self) -> None:
        """Loop side, once per latch set from another thread (stall watchdog, estop_threadsafe).

        Category 0: torque is already off; running motions end ABORTED. Categories 1
        and 2: the stop task scheduled on the loop decelerates them (no freeze here).
        """
        core = self._core
        core.take_latch()
        if core._latch_category == 0:
            self._ramping[:] = False
            self.motions.abort_all("e-stop")

    def _warn(self, kind: str, j: int, msg: str) -> None:
        """Log a warning at most once per ``warn_interval`` (wall time) per (kind, joint)."""
        now = time.monotonic()
        key = (kind, j)
        if now - self._last_warn.get(key, -1e9) >= self._config.warn_interval:
            self._last_warn[key] = now
            log.warning(msg)

    def limit_command(self, mode: CommandMode, idx: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Check a validated command against limits: returns the (possibly clamped) values or raises."""
        limiter = self.limiter
        out: np.ndarray
        if idx is self.full_index:
            lo, hi, what, unit = self._full_range[mode]
            # limiter.clamp_command's clip, on the range looked up once, into a scratch row (handed out
            # only as a copy, when something was clipped)
            out = self._clipped
            np.maximum(values, lo, out=out)
            np.minimum(out, hi, out=out)
        else:
            lo, hi, what, unit = limiter.command_range(mode, idx)
            out = np.minimum(np.maximum(values, lo), hi)
        same = out.tobytes() == values.tobytes()
        if same:
            # nothing clipped (the common case; one bytes compare instead of a ufunc and a reduction)
            any_bad = False
        else:  # something clipped, or only the sign of a zero differs (then nothing counts as clipped)
            bad = out != values
            # one ufunc reduction, kept (ndarray.any goes through a Python wrapper, and it was asked twice)
            any_bad = bool(np.logical_or.reduce(bad))
        reject = self._config.limit_policy == "reject"
        names = self._loop.names
        if reject and any_bad:
            k = int(np.argmax(out != values))
            raise LimitViolation(
                f"{what} command {values[k]:.4g} {unit} for joint {names[int(idx[k])]!r} is outside "
                f"[{lo[k]:.4g}, {hi[k]:.4g}]"
            )
        if mode == "position" and reject:
            jump = limiter.step_exceeded(values, self._written, idx)
            if jump is not None:
                assert self._step is not None
                k = int(np.argmax(jump))
                j = int(idx[k])
                raise LimitViolation(
                    f"position step for joint {names[j]!r} is {abs(values[k] - self._written[j]):.4f} rad, "
                    f"above max_position_step {self._step[j]:.4f} rad per cycle (stream smaller steps, "
                    "use robot.move_to, or set limit_policy='clamp' to ramp)"
                )
        if same:
            return values
        if out is self._clipped:
            out = out.copy()
        if any_bad:
            self._record_clamps(what, unit, idx, values, out, lo, hi)
        # (not clipped but other bytes: a zero's sign at a bound; the clip's result is what the ramp's goal needs,
        # a fixed point of the bounds clip)
        return out

    def _record_clamps(
        self, what: str, unit: str, idx: np.ndarray, values: np.ndarray, out: np.ndarray, lo: Any, hi: Any
    ) -> None:
        lo = np.broadcast_to(lo, values.shape)
        hi = np.broadcast_to(hi, values.shape)
        for k in np.flatnonzero(out != values).tolist():
            j = int(idx[k])
            name = self._loop.names[j]
            msg = f"{what} command {values[k]:.4g} {unit} for joint {name!r} is outside [{lo[k]:.4g}, {hi[k]:.4g}]"
            self._core.record("clamp", f"{msg}; clamped to {out[k]:.4g}", name)
            self._warn(f"clamp {what}", j, msg + "; clamped")

    def limit_feedforward(
        self, idx: np.ndarray, velocity: np.ndarray | None, effort: np.ndarray | None
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Check position-mode feed-forward terms against the velocity and effort limits.

        Same policy as :meth:`limit_command`: clamp (and record) or raise :class:`LimitViolation`.
        """
        out: list[np.ndarray | None] = []
        for what, unit, arr, lim in (
            ("velocity feed-forward", "rad/s", velocity, self._vmax),
            ("effort feed-forward", "N·m", effort, self._emax),
        ):
            if arr is None:
                out.append(None)
                continue
            hi = lim[idx]
            clipped = np.clip(arr, -hi, hi)
            bad = clipped != arr
            if bad.any():
                if self._config.limit_policy == "reject":
                    k = int(np.argmax(bad))
                    raise LimitViolation(
                        f"{what} {arr[k]:.4g} {unit} for joint {self._loop.names[int(idx[k])]!r} is outside "
                        f"[{-hi[k]:.4g}, {hi[k]:.4g}]"
                    )
                self._record_clamps(what, unit, idx, arr, clipped, -hi, hi)
                arr = clipped
            out.append(arr)
        return out[0], out[1]

    def rebase_reference(self, idx: np.ndarray, positions: np.ndarray) -> None:
        """An abort reset the reference of joints ``idx`` to their measured ``positions``: the
        position-step limiter measures the next step from there (a jump back to where the
        joint is reduces the servo effort; it is not a step to limit).
        """
        self._written[idx] = positions

    def ramp_start(self, mode: CommandMode, idx: np.ndarray) -> np.ndarray | None:
        """Where a direct position command's setpoint starts this tick (the ramp's current position)."""
        return self._written[idx] if mode == "position" else None

    def start_ramp(self, mode: CommandMode, idx: np.ndarray | EllipsisType, values: np.ndarray) -> None:
        """A command was applied to joints ``idx`` (indices, or ``...`` for every joint): a position command
        starts their ramps, another ends them. ``values`` are what :meth:`limit_command` returned.

        A direct position command becomes the *goal* of a ramp limited to
        ``max_position_step`` per cycle; the setpoint keeps showing where the
        ramp is (:meth:`ramp_start`), so a stop started before the next tick starts from there.
        """
        if mode == "position":
            self._goal[idx] = values
            self._ramping[idx] = True
        else:
            self._ramping[idx] = False

    # ---------------------------------------------------------- per cycle
    def tick(self, t: float, st: StateView, sp: Setpoint) -> None:
        """LIMIT phase, every tick: keep position setpoints in limits and ramp their steps.

        A joint with a direct position command ramps towards its goal (see :meth:`start_ramp`);
        every other position-mode joint (trajectory, stop ramp, hold) is limited to what
        its writer put in the setpoint for this cycle. Feed-forward terms are clipped to
        the velocity and effort limits as a backstop.

        Allocation-free: preallocated scratch arrays and ufuncs with ``out=`` (``np.clip``
        and ``ndarray.any`` cost microseconds of dispatch on small arrays); the common case,
        every joint in position mode with torque on and no ramp, skips the masks.
        """
        if self._core.latched and not self._core._latch_handled:
            self.enforce_latch()
        ramping = self._ramping
        no_ramp = ramping.tobytes() == self._all_false
        if not no_ramp:
            owned = self.motions.owned_mask
            # a direct command ramping with no motion running (a behavior commanding every tick) takes
            # the short path below as well; a motion's joints take the long one (its clip report)
            ramp_only = owned.tobytes() == self._all_false
            if not ramp_only:  # (no joint owned: ramping &= ~owned changes nothing)
                np.greater(ramping, owned, out=ramping)  # ramping &= ~owned
        else:
            ramp_only = True
        if ramp_only and self.all_position_on(sp.mode, sp.enabled):
            # position, velocity and effort (rows 0:3) into [lo, hi], +-max velocity, +-max effort at once
            # (ufunc input and out are the same array object: a second view would cost an overlap check)
            rows = self._rows
            if self._rows_of is not sp or rows is None:
                self._rows_of, self._rows, self._ff = sp, sp.block[0:3], sp.block[1:3]
                rows = self._rows
            limiter = self.limiter
            pos, written = sp.position, self._written
            if no_ramp:
                # the bounds clip is idempotent bit for bit: a y it produced is either the bits of hi (then
                # max(hi, lo) then min(., hi) gives hi again, for hi above, equal to or below lo), or
                # strictly below hi and then the bits of lo or an x strictly between (kept by both); a NaN
                # stays the same NaN; signed zeros only meet in ties, which return a bound's bits both
                # times. So rows holding the bytes the last clip left (a hold: nobody wrote them since)
                # are skipped
                if rows.tobytes() != self._rows_clipped:
                    limiter.clamp_rows(rows)
                    self._rows_clipped = rows.tobytes()
                if self._window_holds_origin and pos.tobytes() == written.tobytes():
                    # a hold: clip(q, q - step, q + step) is q, bit for bit (q - step <= q <= q + step for
                    # any step >= 0, inf included; a NaN q is np.maximum's and np.minimum's first operand,
                    # returned as it is), and the origin already holds q
                    return
                if limiter.step is not None:
                    limiter.clamp_step(pos, written, pos)
                written[...] = pos
                return
            # the ramping joints' target is their goal (the long path's target row, bit for bit:
            # the same clamps in the same order on the same values)
            ff = self._ff
            if ramping.tobytes() == self._all_true:
                pos[...] = self._goal
                short = ff.tobytes() == self._ff_clipped
            else:
                np.putmask(pos, ramping, self._goal)
                short = False
            if short:
                # every joint ramps: its goal is a command limit_command returned, a fixed point of the bounds
                # clip (start_ramp, restart), and the feed-forward rows hold the bytes the last clip left
                # (a pose stream writes zeros every time): the bounds clip of the rows is the identity, so
                # the target is the goal itself (a zero's sign at a bound of zero aside: numpy's loops for
                # n and 3n elements may break that tie differently)
                target = self._goal
                limiter.clamp_step(pos, written, pos)
            else:
                limiter.clamp_rows(rows)
                self._ff_clipped = ff.tobytes()
                target = self._target
                target[...] = pos
                limiter.clamp_step(target, written, pos)
            # a ramp ends where the step no longer clips it: ramping &= pos != target
            if pos.tobytes() == target.tobytes():
                # every ramp reached its goal this tick (the common case: a goal inside the step window).
                # Equal bytes are equal values except NaN, and no ramping joint's target is NaN: its goal
                # is an admitted command (finite), clipped to bounds that are never NaN. A joint not
                # ramping stays so. So ramping &= pos != target clears every flag.
                ramping.fill(False)
            else:
                unreached = self._unreached
                np.not_equal(pos, target, out=unreached)
                np.logical_and(ramping, unreached, out=ramping)
            written[...] = pos
            return
        pos_mode = (sp.mode == _POS) & sp.enabled
        written = self._written
        # joints not in position mode track the measured position (bumpless switch)
        np.copyto(written, st.position, where=~pos_mode)
        ramping &= pos_mode
        limiter = self.limiter
        target = self._target
        np.copyto(target, sp.position)
        np.copyto(target, self._goal, where=ramping)
        limiter.clamp_bounds(target, target)
        out = limiter.clamp_step(target, written, self._limited)
        owned = self.motions.owned_mask
        if owned.any():
            # a planned motion is never clipped silently (the motions check their steps first, so
            # this only fires for a writer that did not): report it, the motion aborts
            clipped = (out != sp.position) & owned & pos_mode
            if clipped.any():
                j = int(np.argmax(clipped))
                self.motions.limiter_clipped(
                    np.flatnonzero(clipped),
                    f"the limiter clipped the setpoint of joint {self._loop.names[j]!r} from {sp.position[j]:.6g} "
                    f"to {out[j]:.6g} (position bounds or max_position_step)",
                )
        np.copyto(sp.position, out, where=pos_mode)
        ramping &= out != target
        np.copyto(written, out, where=pos_mode)
        ff = sp.block[1:3]
        limiter.clamp_feedforward(ff)
        streamed = sp.enabled & (sp.mode != _POS)
        if streamed.any():
            self._limit_streams(st.position, sp, streamed)

    def block_quiet(self, rows: np.ndarray, mode: np.ndarray, enabled: np.ndarray) -> int:
        """Block lockstep: how many leading ticks of a block the LIMIT tick would leave as they are.

        ``rows`` (K, 3, n) are the position, velocity and effort rows each tick's COMMAND phase
        leaves in the setpoint; ``mode`` and ``enabled`` are the setpoint's (constant over a
        block). A tick is quiet when :meth:`tick` takes its common path (no latch to take over, no
        ramp, every joint in position mode with torque on) and changes no bit of the rows: the
        bounds clip and the step window around the previous tick's position are the identity.
        Computed with the tick's own element operations on all rows at once; the first tick that
        is not quiet (K: none) must run through :meth:`tick`. :meth:`commit_block` then takes
        the state ``k`` quiet ticks leave.
        """
        K = len(rows)
        if K == 0 or self._core.latched or self._ramping.tobytes() != self._all_false:
            return 0
        if not self.all_position_on(mode, enabled):
            return 0
        limiter = self.limiter
        clipped = np.maximum(rows, limiter.rows_min)
        np.minimum(clipped, limiter.rows_max, out=clipped)
        quiet = (clipped.view(np.uint64) == rows.view(np.uint64)).all(axis=(1, 2))
        step = limiter.step
        if step is not None:
            prev = np.empty((K, rows.shape[2]))
            prev[0] = self._written
            prev[1:] = rows[:-1, 0]
            pos = rows[:, 0]
            out = np.maximum(pos, np.subtract(prev, step))
            np.minimum(out, np.add(prev, step, out=prev), out=out)
            quiet &= (out.view(np.uint64) == np.ascontiguousarray(pos).view(np.uint64)).all(axis=1)
        return K if quiet.all() else int(np.argmin(quiet))

    def commit_block(self, rows: np.ndarray, k: int) -> None:
        """The state ``k`` quiet LIMIT ticks of a block leave: the last position written."""
        if k > 0:
            self._written[...] = rows[k - 1, 0]

    def all_position_on(self, mode: np.ndarray, enabled: np.ndarray) -> bool:
        """Every joint in position mode with torque on (the common case)."""
        return mode.tobytes() == self._all_position and enabled.tobytes() == self._all_true

    def _limit_streams(self, q: np.ndarray, sp: Setpoint, streamed: np.ndarray) -> None:
        """Keep velocity and effort streams from driving a joint through its position limits.

        Like ros2_control's joint saturation limiter: a velocity command is limited so the
        joint can still stop (at its deceleration limit) before the limit,
        ``|v| <= sqrt(2 * a_max * distance)``; an effort command that pushes a joint at or
        beyond a limit further out is dropped (it may rest against its stop).
        """
        vel = streamed & (sp.mode == _VEL)
        if vel.any():
            up = np.sqrt(2.0 * self._amax * np.maximum(self._hi - q, 0.0))
            down = -np.sqrt(2.0 * self._amax * np.maximum(q - self._lo, 0.0))
            limited = np.minimum(np.maximum(sp.velocity, down), up)
            np.copyto(sp.velocity, limited, where=vel)
        eff = streamed & (sp.mode == _EFF)
        if eff.any():
            outward = ((q >= self._hi) & (sp.effort > 0.0)) | ((q <= self._lo) & (sp.effort < 0.0))
            sp.effort[eff & outward] = 0.0
