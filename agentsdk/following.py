"""Following error: a joint that does not follow its position command latches a stop.

A servo drive latches a *following error* when the measured position stays outside a
window around the command: the joint is blocked, the servo is saturated, unstable
(a simulator's integrator meeting a model it cannot servo, gains too low or too high)
or not connected to what it drives. :class:`FollowingErrorCheck` is that check, run by the
safety layer on every backend (a :data:`~agentsdk.safety.SafetyCheck`, registered by
default).

What is watched: joints the servo holds to a position, that is in position mode, with
torque on and a position gain ``kp > 0``. The command is the position setpoint the servo
tracks this tick (a trajectory's desired position, a ramped position command, a hold);
a velocity or effort command has no position to follow, and a torque-off or damping-only
joint is not servoed, so those joints are skipped (and their persistence timers reset).

The window per joint (robot.yaml ``safety: following_error_window``):

* ``"auto"`` (default): twice the error at which the servo's P term alone demands the
  joint's effort limit (``2 * max_effort / kp``: beyond it the drive is saturated and
  cannot pull the joint back), bounded to ``[following_error_min, following_error_max]``
  (a joint without effort limit or gain gets the maximum; a hold with gains so low that
  the joint sags further than the maximum is caught too);
* a number: that window for every joint; a mapping ``{joint: window}``: per joint (the
  others ``"auto"``); ``None`` disables the check.

The defaults (0.25..0.5 rad or m, 0.1 s) are loose enough for every corpus robot's healthy
tracking with its default gains (a hand's finger on PyBullet lags up to 0.19 rad during a
fast move and still reaches its goal) and catch a joint that sags, swings or is stuck.

A joint moved by a trajectory controller that runs the whole goal itself (an offloaded
``FollowJointTrajectory`` goal, :mod:`agentsdk.offload`) is also following when it is inside its
window of the controller's own desired position (its feedback): that controller runs the goal on
its own clock, which may lag the local sample by the link's delays or a stall of its host. A joint
near neither is a following error as anywhere else.

The error must stay outside the window for ``following_error_time`` seconds of robot time
(a transient, e.g. a collision bump, is not a fault); then the check returns a violation
naming the joint, its error and window, and the safety layer latches a stop of category
``following_error_stop``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from .backend import ModeCode, SetpointView
from .checks import SafetyViolation
from .errors import ConfigurationError
from .loop import ControlLoop, StateView
from .types import FloatArray, JointInfo

__all__ = ["FollowingErrorCheck", "following_windows"]

_POS = int(ModeCode.POSITION)


def following_windows(
    joints: Sequence[JointInfo],
    gains_p: Sequence[float] | FloatArray,
    window: float | Mapping[str, float] | str,
    minimum: float,
    maximum: float,
) -> FloatArray:
    """Per-joint following-error windows (rad or m) in ``joints`` order (see the module documentation).

    Raises :class:`ConfigurationError` for a mapping naming an unknown joint, or bounds in the wrong order.
    """
    if minimum > maximum:
        raise ConfigurationError(
            f"safety.following_error_min ({minimum:g}) is larger than safety.following_error_max ({maximum:g})"
        )
    emax = np.array([j.max_effort for j in joints], dtype=np.float64)
    kp = np.array(gains_p, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        sat = np.where((kp > 0.0) & np.isfinite(emax) & (emax > 0.0), 2.0 * emax / kp, math.inf)
    auto: FloatArray = np.clip(np.nan_to_num(sat, nan=math.inf), minimum, maximum)
    if isinstance(window, str):
        return auto
    if isinstance(window, Mapping):
        names = [j.name for j in joints]
        unknown = sorted(set(window) - set(names))
        if unknown:
            raise ConfigurationError(
                f"safety.following_error_window names unknown joint(s) {unknown}; this robot's joints are: "
                f"{', '.join(names)}"
            )
        out = auto.copy()
        for k, name in enumerate(names):
            if name in window:
                out[k] = float(window[name])
        return out
    out = np.full(len(joints), float(window))
    return out


class FollowingErrorCheck:
    """Built-in :data:`~agentsdk.safety.SafetyCheck`: a position-servoed joint outside its following-error window
    for ``persist`` seconds of robot time (see the module documentation). Allocation-free per tick while every
    watched joint is inside its window.
    """

    def __init__(self, loop: ControlLoop, windows: np.ndarray, persist: float, category: int) -> None:
        n = len(loop.joints)
        self._loop = loop
        self._names = tuple(j.name for j in loop.joints)
        self.windows = np.array(windows, dtype=np.float64)
        self.windows.flags.writeable = False
        self._persist = float(persist)
        self._category = category
        self._continuous = np.array([j.type == "continuous" for j in loop.joints], dtype=bool)
        self._any_continuous = bool(self._continuous.any())
        self._err = np.zeros(n)
        self._zeros = np.zeros(n)
        self._maskf = np.zeros(n)
        self._pos_row = np.full(n, _POS, dtype=np.int8)
        self._wrapped = np.zeros(n)
        self._mask = np.zeros(n, dtype=bool)
        self._tmp = np.zeros(n, dtype=bool)
        #: robot time each joint was first seen outside its window (NaN: inside, or not watched)
        self._since = np.full(n, np.nan)
        self._tracking = False
        self._last_t = -math.inf
        self._period = loop.period
        self._none = np.zeros(n, dtype=bool).tobytes()
        self._all = np.ones(n, dtype=bool).tobytes()
        self._gain = np.zeros(n, dtype=bool)
        #: the (mode, enabled, kp > 0) bytes the watched mask (``_mask``, ``_maskf``) was computed for
        self._mask_key: tuple[bytes, bytes, bytes] = (b"", b"", b"")
        self._all_watched = False
        #: largest error seen per watched joint since construction or :meth:`reset_peak` (diagnostics)
        self.peak = np.zeros(n)
        # block lockstep's work arrays: the errors of the last block judged, their per-joint peak, and
        # which block that was (its states' and setpoints' buffers, first time and length)
        self._blk_err = np.empty((0, n))
        self._blk_peak = np.empty(n)
        self._gain_tmp = np.empty(n, dtype=bool)
        self._blk_key: tuple[int, int, float, int] | None = None

    def reset_peak(self) -> None:
        """Start a new :attr:`peak` measurement."""
        self.peak[:] = 0.0

    def _block_errors(self, states: FloatArray, setpoints: FloatArray) -> FloatArray:
        """The per-tick error of every tick of a block (K, n): the same element operations as :meth:`__call__`.

        Into a work array kept between blocks (grown when a longer block comes).
        """
        K = len(setpoints)
        buf = self._blk_err
        if len(buf) < K:
            buf = self._blk_err = np.empty((max(K, 2 * len(buf)), len(self._err)))
        err = np.subtract(states[:, 0, :], setpoints, out=buf[:K])
        if self._any_continuous:
            wrapped = np.add(err, math.pi)
            np.remainder(wrapped, 2.0 * math.pi, out=wrapped)
            np.subtract(wrapped, math.pi, out=wrapped)
            np.copyto(err, wrapped, where=self._continuous)
        np.abs(err, out=err)
        self._update_mask(self._loop.setpoint)  # the mode, enabled and gain rows: constant over a block
        if not self._all_watched:
            np.multiply(err, self._maskf, out=err)
        return err

    def fused_ready(self, all_position: bytes, all_on: bytes) -> bool:
        """The safety layer's fused tick may stand in for :meth:`__call__`: no joint is outside its window
        (no persistence timer runs), no continuous joint, and the watched mask was last computed for every
        joint in position mode (``all_position``: the mode row's bytes) with torque on and ``kp > 0``
        (``all_on``: an all-True row's bytes). If the setpoint still says so and every error is within its
        window, :meth:`__call__` would only take the peak and the time: :meth:`fused_pass`.
        """
        return not self._tracking and not self._any_continuous and self._mask_key == (all_position, all_on, all_on)

    def fused_pass(self, t: float, err: FloatArray) -> None:
        """What :meth:`__call__` leaves when every watched joint's error ``err`` (``|q - q_ref|``) is inside."""
        np.fmax(self.peak, err, out=self.peak)
        self._last_t = t

    def block_ready(self) -> bool:
        """:class:`~agentsdk.checks.BlockCheck`: no joint is outside its window (no persistence timer runs)."""
        return not self._tracking

    def block_quiet(self, ts: FloatArray, states: FloatArray, setpoints: FloatArray) -> int:
        """:class:`~agentsdk.checks.BlockCheck`: leading ticks with every watched joint inside its window.

        Keeps the block's errors and their per-joint peak for :meth:`commit_block` of the same block.
        """
        self._blk_key = None
        if self._tracking or len(ts) == 0:
            return 0  # a joint is outside: its persistence timer runs per tick
        err = self._block_errors(states, setpoints)
        # fmax ignores NaN, as the tick's ``err > window`` does (NaN is inside): every tick is inside
        # exactly when every joint's largest error is; the same peak is what the commit takes
        peak = np.fmax.reduce(err, axis=0, out=self._blk_peak)
        self._blk_key = (states.ctypes.data, setpoints.ctypes.data, float(ts[0]), len(ts))
        if np.greater(peak, self.windows, out=self._gain_tmp).tobytes() == self._none:
            return len(ts)
        quiet = ~np.greater(err, self.windows).any(axis=1)
        return len(ts) if quiet.all() else int(np.argmin(quiet))

    def commit_block(self, ts: FloatArray, states: FloatArray, setpoints: FloatArray, k: int) -> None:
        """:class:`~agentsdk.checks.BlockCheck`: the peak error of ``k`` quiet ticks and the last tick's time."""
        if k <= 0:
            return
        key = self._blk_key
        self._blk_key = None
        if key is not None and key == (states.ctypes.data, setpoints.ctypes.data, float(ts[0]), key[3]) and k <= key[3]:
            # the block block_quiet judged: its errors are still in the work array
            err = self._blk_err[:k]
            peak = self._blk_peak if k == key[3] else np.fmax.reduce(err, axis=0, out=self._blk_peak)
        else:
            err = self._block_errors(states[:k], setpoints[:k])
            peak = np.fmax.reduce(err, axis=0, out=self._blk_peak)
        # fmax keeps the larger of two numbers and ignores NaN: the same in any order
        np.fmax(self.peak, peak, out=self.peak)
        self._last_t = float(ts[k - 1])

    def _update_mask(self, sp: SetpointView) -> None:
        """The watched joints (position mode, torque on, kp > 0), recomputed only when those rows changed."""
        mask, gain = self._mask, self._gain
        np.greater(sp.kp, self._zeros, out=gain)
        key = self._mask_key
        if gain.tobytes() != key[2] or sp.mode.tobytes() != key[0] or sp.enabled.tobytes() != key[1]:
            np.equal(sp.mode, self._pos_row, out=mask)
            np.logical_and(mask, sp.enabled, out=mask)
            np.logical_and(mask, gain, out=mask)
            np.copyto(self._maskf, mask)  # (a bool -> float copy allocates nothing; a mixed multiply does)
            self._all_watched = mask.tobytes() == self._all
            self._mask_key = (sp.mode.tobytes(), sp.enabled.tobytes(), gain.tobytes())

    def _judge_by_controller(self, position: FloatArray, err: FloatArray, outside: np.ndarray) -> None:
        """Joints outside their window of the setpoint but inside it of the position their trajectory controller
        reports it is tracking (an offloaded goal, :attr:`ControlLoop.controller_desired`) are following: that
        controller runs the goal on its own clock (it started later, or its host stalled). Their error is the
        smaller one. Only on a tick some joint is outside (allocates).
        """
        desired = self._loop.controller_desired
        if np.isnan(desired).all():
            return
        e = np.subtract(position, desired)
        if self._any_continuous:
            wrapped = np.remainder(e + math.pi, 2.0 * math.pi) - math.pi
            np.copyto(e, wrapped, where=self._continuous)
        np.abs(e, out=e)
        follows = outside & (e <= self.windows)  # (NaN: no controller's desired, not following it)
        if follows.any():
            err[follows] = e[follows]
            outside &= ~follows

    def __call__(self, t: float, state: StateView) -> SafetyViolation | None:
        """Return a violation naming the joint whose error stayed outside its window longest, else None."""
        sp = self._loop.setpoint
        err = self._err
        np.subtract(state.position, sp.position, out=err)
        if self._any_continuous:
            # a continuous joint's error is an angle: the shortest way round
            wrapped = self._wrapped
            np.add(err, math.pi, out=wrapped)
            np.remainder(wrapped, 2.0 * math.pi, out=wrapped)
            np.subtract(wrapped, math.pi, out=wrapped)
            np.copyto(err, wrapped, where=self._continuous)
        np.abs(err, out=err)
        # watched: position mode, torque on, a position gain; the mask changes only with those rows,
        # so it is kept while their bytes repeat (bytes compares instead of four ufunc calls and a
        # multiply; one small bytes object at a time, compared and dropped: the tick's peak memory stays low)
        # (operands of one dtype with preallocated outputs: a Python scalar or a cast allocates per tick)
        self._update_mask(sp)
        if not self._all_watched:  # (times 1.0 everywhere would change no bit: skipped)
            np.multiply(err, self._maskf, out=err)  # unwatched joints: no error
        outside = self._tmp
        np.greater(err, self.windows, out=outside)
        if outside.tobytes() != self._none:
            self._judge_by_controller(state.position, err, outside)
        np.fmax(self.peak, err, out=self.peak)  # (NaN: not an error figure)
        gap = t - self._last_t > 1.5 * self._period  # the check did not run meanwhile (stopped, disabled)
        self._last_t = t
        if outside.tobytes() == self._none:
            if self._tracking:
                self._since[:] = np.nan
                self._tracking = False
            return None
        since = self._since
        if gap:
            since[:] = np.nan
        since[~outside] = np.nan
        since[outside & np.isnan(since)] = t
        self._tracking = True
        age = t - since
        # (an age of 0 with persist 0: a single tick outside is enough)
        due = np.flatnonzero(outside & (age >= self._persist - 1e-9))
        if not len(due):
            return None
        j = int(due[np.argmax(err[due])])
        return SafetyViolation(
            "following_error",
            f"following error: joint {self._names[j]!r} is {err[j]:.4g} from its position command "
            f"(window {self.windows[j]:.4g}) for {age[j]:.3g} s",
            self._names[j],
            self._category,
        )
