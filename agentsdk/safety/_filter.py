"""The per-tick filter and command limiting: every setpoint passes the one :class:`StepLimiter`."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import (
    LimitViolation,
)
from ..loop import Setpoint, StateView
from ..types import CommandMode
from ._state import _EFF, _POS, _VEL, SafetyState, _SafetyCore

if TYPE_CHECKING:
    pass



class _Filter(_SafetyCore):
    """Limits direct commands when admitted and every setpoint in the LIMIT phase of each tick."""

    def _limit_command(self, mode: CommandMode, idx: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Check a validated command against limits: returns the (possibly clamped) values or raises."""
        limiter = self.limiter
        lo, hi, what, unit = limiter.command_range(mode, idx)
        out = limiter.clamp_command(mode, idx, values)
        bad = out != values
        # one ufunc reduction, kept (ndarray.any goes through a Python wrapper, and it was asked twice)
        any_bad = bool(np.logical_or.reduce(bad))
        reject = self.config.limit_policy == "reject"
        names = self.loop.names
        if reject and any_bad:
            k = int(np.argmax(bad))
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
        if not any_bad:
            return values
        self._record_clamps(what, unit, idx, values, out, lo, hi)
        return out

    def _record_clamps(
        self, what: str, unit: str, idx: np.ndarray, values: np.ndarray, out: np.ndarray, lo: Any, hi: Any
    ) -> None:
        lo = np.broadcast_to(lo, values.shape)
        hi = np.broadcast_to(hi, values.shape)
        for k in np.flatnonzero(out != values).tolist():
            j = int(idx[k])
            name = self.loop.names[j]
            msg = f"{what} command {values[k]:.4g} {unit} for joint {name!r} is outside [{lo[k]:.4g}, {hi[k]:.4g}]"
            self.record("clamp", f"{msg}; clamped to {out[k]:.4g}", name)
            self._warn(f"clamp {what}", j, msg + "; clamped")

    def _limit_feedforward(
        self, idx: np.ndarray, velocity: np.ndarray | None, effort: np.ndarray | None
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Check position-mode feed-forward terms against the velocity and effort limits.

        Same policy as :meth:`_limit_command`: clamp (and record) or raise :class:`LimitViolation`.
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
                if self.config.limit_policy == "reject":
                    k = int(np.argmax(bad))
                    raise LimitViolation(
                        f"{what} {arr[k]:.4g} {unit} for joint {self.loop.names[int(idx[k])]!r} is outside "
                        f"[{-hi[k]:.4g}, {hi[k]:.4g}]"
                    )
                self._record_clamps(what, unit, idx, arr, clipped, -hi, hi)
                arr = clipped
            out.append(arr)
        return out[0], out[1]

    def _rebase_reference(self, idx: np.ndarray, positions: np.ndarray) -> None:
        """An abort reset the reference of joints ``idx`` to their measured ``positions``: the
        position-step limiter measures the next step from there (a jump back to where the
        joint is reduces the servo effort; it is not a step to limit).
        """
        self._written[idx] = positions

    def _ramp_start(self, mode: CommandMode, idx: np.ndarray) -> np.ndarray | None:
        """Where a direct position command's setpoint starts this tick (the ramp's current position)."""
        return self._written[idx] if mode == "position" else None

    def _feed(self, mode: CommandMode, idx: np.ndarray, values: np.ndarray) -> None:
        """A command was applied to these joints: refresh the command watchdog, start position ramps.

        A direct position command becomes the *goal* of a ramp limited to
        ``max_position_step`` per cycle; the setpoint keeps showing where the
        ramp is (:meth:`_ramp_start`), so a stop started before the next tick starts from there.
        """
        self._fed[idx] = self.loop.stamp
        self._held[idx] = False
        if mode == "position":
            self._goal[idx] = values
            self._ramping[idx] = True
        else:
            self._ramping[idx] = False
        if self._state is SafetyState.HOLD:
            self._state = SafetyState.OK
            self.record("resume", "command received; leaving HOLD")

    # ---------------------------------------------------------- per cycle
    def _filter(self, t: float, st: StateView, sp: Setpoint) -> None:
        """LIMIT phase, every tick: keep position setpoints in limits and ramp their steps.

        A joint with a direct position command ramps towards its goal (see :meth:`_feed`);
        every other position-mode joint (trajectory, stop ramp, hold) is limited to what
        its writer put in the setpoint for this cycle. Feed-forward terms are clipped to
        the velocity and effort limits as a backstop.

        Allocation-free: preallocated scratch arrays and ufuncs with ``out=`` (``np.clip``
        and ``ndarray.any`` cost microseconds of dispatch on small arrays); the common case,
        every joint in position mode with torque on and no ramp, skips the masks.
        """
        if self._latched.is_set() and not self._latch_handled:
            self._enforce_latch()
        ramping = self._ramping
        no_ramp = ramping.tobytes() == self._all_false
        if not no_ramp:
            np.greater(ramping, self.motions.owned_mask, out=ramping)  # ramping &= ~owned
        if no_ramp and self._all_position_on(sp.mode, sp.enabled):
            # position, velocity and effort (rows 0:3) into [lo, hi], +-max velocity, +-max effort at once
            # (ufunc input and out are the same array object: a second view would cost an overlap check)
            rows = self._rows
            if self._rows_of is not sp or rows is None:
                self._rows_of, self._rows = sp, sp.block[0:3]
                rows = self._rows
            limiter = self.limiter
            limiter.clamp_rows(rows)
            pos, written = sp.position, self._written
            if limiter.step is not None:
                limiter.clamp_step(pos, written, pos)
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
                    f"the limiter clipped the setpoint of joint {self.loop.names[j]!r} from {sp.position[j]:.6g} "
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

    def _all_position_on(self, mode: np.ndarray, enabled: np.ndarray) -> bool:
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
