"""Block lockstep (issue 28 item 1, opt-in, experimental): uneventful lockstep ticks run as one block.

In lockstep the control loop ticks while every other task waits. When nothing can happen for a
while (no task wakes, nothing is commanded per tick, no check fires), the ticks' phases are pure
bookkeeping around the physics: :class:`BlockLockstep` runs such a stretch as one *block*, the
backend's steps back to back (``block_stepper``, MuJoCo's
:class:`~agentsdk.backends.mujoco.block.BlockStepper`), then judges all of its states at once with
the vectorized forms of the tick's rules (the safety filter's, the plausibility gate's and every
check's ``block_quiet``), commits the ticks they pass quietly and, at the first tick that would do
anything (a check that fires, a reading the gate doubts, a limit the filter would apply), puts the
simulation back to where it stood before that tick and lets the loop run it tick by tick. Every
result, event, state and setpoint is bit for bit what tick-by-tick computes
(``tests/test_block_lockstep.py`` compares per-tick hashes of random runs).

This first slice blocks a **hold** only: no COMMAND hook (no motion, stop ramp or scheduled
motion runs), the safety layer's filter as the only LIMIT hook, the safety watchdogs and
:class:`BlockObserver` hooks as the only OBSERVE hooks, safety state OK, every check a
:class:`~agentsdk.checks.BlockCheck`, the command watchdog not watching position mode. Anything
else runs tick by tick, as without it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

from .backend import SetpointView
from .checks import BlockCheck
from .clock import LockstepClock
from .errors import ConfigurationError, InvalidValueError, SimulationDiverged
from .loop import StateView
from .safety import SafetyState
from .types import FloatArray

if TYPE_CHECKING:
    from collections.abc import Callable

    from .robot import Robot

__all__ = ["BlockLockstep", "BlockObserver", "BlockStepperLike"]

#: ``run()``'s answer when no block runs (no tuple per tick)
_NONE = (0, False)


@runtime_checkable
class BlockObserver(Protocol):
    """An OBSERVE hook that also takes a block of ticks at once; any other OBSERVE hook forces tick by tick.

    ``observe_block(ts, states, setpoint)`` gets the block's committed ticks: their robot times
    ``ts`` (K,), their measured states ``states`` (K, 3, n: position, velocity and effort rows, as
    :attr:`agentsdk.loop.StateView.block`, read-only) and the setpoint (constant over a block). It
    must do what K calls ``fn(ts[k], state_k, setpoint)`` would.
    """

    def __call__(self, t: float, state: StateView, setpoint: SetpointView) -> None:
        """The per-tick hook."""

    def observe_block(self, ts: FloatArray, states: FloatArray, setpoint: SetpointView) -> None:
        """The same for K ticks at once."""


class BlockStepperLike(Protocol):
    """What a backend's ``block_stepper(capacity)`` returns (MuJoCo: ``backends.mujoco.block.BlockStepper``)."""

    fault: SimulationDiverged | None

    def run(self, write: Callable[[int], bool | None], count: int, readings: FloatArray) -> int:
        """Run up to ``count`` ticks: write, step, read into ``readings[k]``; the ticks done."""

    def restore(self, k: int) -> None:
        """Put the simulation back to where it stood before tick ``k`` of the last run."""


class BlockLockstep:
    """Runs a lockstep robot's uneventful ticks as blocks (see the module); :meth:`close` turns it off.

    ``capacity``: the most ticks per block. Counters: :attr:`blocks` run, :attr:`block_ticks`
    committed through them, :attr:`rollbacks` (blocks cut short by a tick that had to run alone).
    """

    def __init__(self, robot: Robot, capacity: int = 256) -> None:
        loop = robot._loop
        if not isinstance(loop.clock, LockstepClock):
            raise ConfigurationError("block lockstep needs a lockstep robot (realtime=False)")
        if capacity < 2:
            raise InvalidValueError(f"capacity must be at least 2 ticks, got {capacity}")
        make = getattr(loop.backend, "block_stepper", None)
        if make is None:
            raise ConfigurationError(f"backend {loop.backend.name!r} cannot run a block of ticks (no block_stepper)")
        if loop.block_runner is not None:
            raise ConfigurationError("block lockstep is already on for this robot")
        self._loop = loop
        self._clock = loop.clock
        self._stepper: BlockStepperLike = make(capacity)
        safety = robot.safety
        self._filter = safety._filter
        self._filter_tick = safety._filter.tick
        self._watchdogs = safety._watchdogs
        self._wd_tick = safety._watchdogs.tick
        self._core = safety._core
        self._latched = safety._core._latched.is_set
        self.capacity = capacity
        n = len(loop.joints)
        self._rows = np.empty((capacity, 3, n))
        self._readings = np.empty((capacity, 3, n))
        self._ts = np.empty(capacity)
        self._itick = np.empty(capacity, dtype=np.int64)
        self._one_to_k = np.arange(1, capacity + 1, dtype=np.int64)
        #: ticks to run as usual before trying a block again (after a block cut short at once)
        self._skip = 0
        self._backoff = 1
        self.blocks = 0
        self.block_ticks = 0
        self.rollbacks = 0
        loop.block_runner = self.run

    def close(self) -> None:
        """Turn block lockstep off (ticks run one by one again)."""
        if self._loop.block_runner == self.run:
            self._loop.block_runner = None

    def _observers(self) -> list[BlockObserver] | None:
        """The OBSERVE hooks besides the watchdogs if each takes blocks (None: one does not, or no watchdogs)."""
        out: list[BlockObserver] = []
        seen = False
        for fn in self._loop._observe.fns:
            if fn == self._wd_tick:
                seen = True
            elif isinstance(fn, BlockObserver):
                out.append(fn)
            else:
                return None
        return out if seen else None

    def _eligible(self) -> bool:
        """The cheap preconditions of a hold block (see the module)."""
        loop = self._loop
        if loop._torque_off or loop._fault is not None or loop._command.fns:
            return False
        if loop._limit.fns != (self._filter_tick,):
            return False
        if self._core._state is not SafetyState.OK or self._latched():
            return False
        gate = loop.sensor_gate
        if gate is not None and (gate.pending or not gate.block_ready()):
            return False
        wd = self._watchdogs
        if wd._watch_position:
            return False
        return all(isinstance(c, BlockCheck) and c.block_ready() for c in wd._checks)

    def run(self) -> tuple[int, bool]:
        """One block if one can run now: ``(ticks committed, whether the last woke a sleeper)``, else ``(0, False)``."""
        if self._skip:
            self._skip -= 1
            return _NONE
        if not self._eligible():
            return _NONE
        observers = self._observers()
        if observers is None:
            return _NONE
        loop, clock = self._loop, self._clock
        K = clock.ticks_until_wake(self.capacity)
        if K < 2:
            return _NONE
        sp = loop._sp
        sp.acceleration.fill(0.0)  # as each tick does first (nobody else writes it during a hold)
        rows = self._rows[:K]
        rows[...] = sp.block[0:3]  # a hold: the same rows every tick
        k = self._filter.block_quiet(rows, sp.mode, sp.enabled)
        if k < 2:
            return self._cut_short()
        backend, spv, latched = loop.backend, sp.view, self._latched
        stamp, tick0, period = loop.stamp, clock.ticks, clock.period

        def write(j: int) -> bool:
            # an emergency stop or latch from another thread ends the block before the next write:
            # tick by tick it would land at that tick
            if loop._torque_off or latched():
                return False
            if j:  # the robot time of the latest state as tick j's write sees it (another thread's events)
                loop.stamp = (tick0 + j) * period
            backend.write(spv)
            if loop._torque_off:
                backend.emergency_stop(0)  # it landed during write: enforce it again (as the tick does)
            return True

        stepper = self._stepper
        readings = self._readings
        done = stepper.run(write, k, readings)
        fault = stepper.fault
        loop.stamp = stamp
        if done == 0:
            if fault is not None:
                raise fault
            return self._cut_short()
        # tick j's OBSERVE phase runs at (T + j + 1) * period, the clock's own product
        itick = np.add(self._one_to_k[:done], clock.ticks, out=self._itick[:done])
        ts = np.multiply(itick, clock.period, out=self._ts[:done])
        states = readings[:done]
        setpoints = rows[:done, 0]
        q = done
        gate = loop.sensor_gate
        if gate is not None:
            q = min(q, gate.block_quiet(ts, states))
        # the ticks whose OBSERVE phase runs the checks: a latch set from another thread during the block
        # ended it (write); tick by tick, the last tick's watchdogs would have seen it and skipped them
        checked = min(q, done - 1 if self._latched() else done)
        for c in self._watchdogs._checks:
            if checked == 0:
                break
            assert isinstance(c, BlockCheck)
            quiet = c.block_quiet(ts[:checked], states[:checked], setpoints[:checked])
            if quiet < checked:
                checked = q = quiet  # this tick's check acts: it runs alone
        if q < done:
            stepper.restore(q)  # tick q runs alone, from where it started
            self.rollbacks += 1
        if q == 0:
            return self._cut_short()
        self._commit(ts, states, rows, setpoints, q, checked, observers)
        woke = 0
        advance = clock.advance
        for _ in range(q):
            woke += advance()
        loop.stamp = clock.now()
        loop.ticks += q
        self.blocks += 1
        self.block_ticks += q
        self._backoff = 1
        if fault is not None and q == done:
            raise fault  # the next tick's step diverged: as tick by tick, after the ticks before it
        return q, woke > 0

    def _commit(self, ts: FloatArray, states: FloatArray, rows: FloatArray, setpoints: FloatArray, q: int,
                checked: int, observers: list[BlockObserver]) -> None:
        """Bring every per-tick rule's state to where ``q`` quiet ticks leave it, and tell the observers.

        The checks ran in the first ``checked`` of them.
        """
        loop = self._loop
        self._filter.commit_block(rows, q)
        gate = loop.sensor_gate
        if gate is not None:
            gate.commit_block(ts, states, q)
        else:
            loop._state.block[...] = states[q - 1]
        for c in self._watchdogs._checks:
            assert isinstance(c, BlockCheck)
            c.commit_block(ts, states, setpoints, checked)
        if observers:
            view = states[:q]
            view.flags.writeable = False
            spv = loop._sp.view
            for obs in observers:
                obs.observe_block(ts[:q], view, spv)

    def _cut_short(self) -> tuple[int, bool]:
        """No block now: run the next ticks as usual, for longer each time this repeats."""
        self._skip = self._backoff
        self._backoff = min(2 * self._backoff, 64)
        return _NONE
