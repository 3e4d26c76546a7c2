"""Block lockstep (issue 28 items 1, 4; on by default in lockstep): uneventful lockstep ticks run as one block.

In lockstep the control loop ticks while every other task waits. When nothing can happen for a
while (no task wakes, no check fires, the setpoints are known in advance), the ticks' phases are
bookkeeping around the physics: :class:`BlockLockstep` runs such a stretch as one *block*, the
backend's steps back to back (``block_stepper``: MuJoCo's or PyBullet's ``BlockStepper``) with each tick's
setpoint computed before the block, then judges all of its states at once with the vectorized
forms of the tick's rules (the safety filter's, the plausibility gate's, every check's and the
motion's path tolerance: :class:`agentsdk.safety._block.SafetyBlock`,
:class:`agentsdk.motion._block.BlockPlanner`), commits the ticks they pass quietly and, at the
first tick that would do anything (a check that fires, a reading the gate doubts, a limit the
filter would apply, the motion's end), puts the simulation back to where it stood before that
tick and lets the loop run it tick by tick. Every result, event, feedback message, state and
setpoint is bit for bit what tick-by-tick computes (``tests/test_block_lockstep.py`` compares
per-tick hashes of random runs). On MuJoCo, a block whose ticks after the first write only
precomputed controls (a motion) or nothing (a hold) is one ``mujoco.rollout`` call
(``backends.mujoco.block``). An emergency stop or latch from another thread lands at a tick
boundary either way: between two ticks of a block run step by step, and before the block's first
tick when it lands during a rollout (the block is undone; another thread cannot tell the two apart).

Blocked so far: a **hold** (no COMMAND hook) and **motions following their trajectories, settling
at their goals, running stop ramps or waiting for their scheduled start** (every COMMAND hook an
executor record; a steady speed scaling, samples the limiter provably leaves alone), with the
safety layer's filter as the only LIMIT hook, the safety watchdogs and :class:`BlockObserver` hooks
as the only OBSERVE hooks, safety state OK, every check a :class:`~agentsdk.checks.BlockCheck`, the
command watchdog not watching position mode. Anything else runs tick by tick, as without it.

On by default: :func:`agentsdk.connect` starts a runner of 256 ticks for every lockstep robot whose
backend has a ``block_stepper`` (MuJoCo, PyBullet; a stepper may still refuse a block, e.g. PyBullet's
for a floating base or while in contact); realtime robots and the other backends run every tick on its
own. ``connect(..., block_lockstep=False)`` (``agentsdk run --no-block-lockstep``) opts out.
:meth:`agentsdk.Robot.block_lockstep` returns the runner (or one of another capacity in its place),
:attr:`agentsdk.Robot.block_runner` reads it, :meth:`BlockLockstep.close` turns it off, and closing the
robot closes it (it has no task or thread of its own: the control loop calls :meth:`BlockLockstep.run`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

from .backend import SetpointView
from .clock import LockstepClock
from .errors import ConfigurationError, InvalidValueError, SimulationDiverged
from .loop import ControlLoop, Phase, StateView
from .types import FloatArray

if TYPE_CHECKING:
    from .motion._block import BlockPlan, BlockPlanner
    from .safety._block import SafetyBlock

__all__ = ["BlockLockstep", "BlockObserver", "BlockStepperLike"]

#: ``run()``'s answer when no block runs (no tuple per tick)
_NONE = (0, False)


@runtime_checkable
class BlockObserver(Protocol):
    """An OBSERVE hook that also takes a block of ticks at once; any other OBSERVE hook forces tick by tick.

    ``observe_block(ts, states, setpoints, setpoint)`` gets the block's committed ticks: their robot
    times ``ts`` (K,), their measured states ``states`` (K, 3, n: position, velocity and effort rows,
    as :attr:`agentsdk.loop.StateView.block`), the float rows of each tick's setpoint ``setpoints``
    (K, 7, n, in :attr:`agentsdk.loop.Setpoint.FIELDS` order; read-only, like ``states``) and the
    live setpoint view for the rest (``mode``, ``enabled``: constant over a block). It must do
    what K calls ``fn(ts[k], state_k, setpoint_k)`` would.
    """

    def __call__(self, t: float, state: StateView, setpoint: SetpointView) -> None:
        """The per-tick hook."""

    def observe_block(self, ts: FloatArray, states: FloatArray, setpoints: FloatArray,
                      setpoint: SetpointView) -> None:
        """The same for K ticks at once."""


def check_capacity(capacity: int) -> None:
    """``capacity`` is a block size :class:`BlockLockstep` takes (at least 2 ticks), else :class:`InvalidValueError`."""
    if capacity < 2:
        raise InvalidValueError(f"capacity must be at least 2 ticks, got {capacity}")


def available(loop: ControlLoop) -> bool:
    """Block lockstep can run on ``loop``: a lockstep clock and a backend with a ``block_stepper``."""
    return isinstance(loop.clock, LockstepClock) and callable(getattr(loop.backend, "block_stepper", None))


def lockstep_runner(loop: ControlLoop, safety: SafetyBlock, planner: BlockPlanner | None,
                    current: BlockLockstep | None, capacity: int) -> BlockLockstep:
    """``current`` if it is on at ``capacity`` ticks, else a new runner of that size in its place.

    What :meth:`agentsdk.Robot.block_lockstep` does (a bad ``capacity`` raises before ``current`` goes off).
    """
    check_capacity(capacity)
    if current is not None and current.active:
        if current.capacity == capacity:
            return current
        current.close()
    return BlockLockstep(loop, safety, planner, capacity)


class BlockStepperLike(Protocol):
    """What a backend's ``block_stepper(capacity)`` returns (``backends.mujoco.block``/``backends.pybullet.block``)."""

    fault: SimulationDiverged | None
    #: writing the same setpoint again changes nothing: a hold's block writes it at its first tick only
    write_once: bool

    def ready(self) -> bool:
        """A block may run now (False: e.g. the backend's step was replaced, which a block would bypass)."""

    def run(self, write: Callable[[int], bool | None], count: int, readings: FloatArray,
            stop: Callable[[], bool] | None = None, controls: Callable[[int], None] | None = None) -> int:
        """Run up to ``count`` ticks: write, step, read into ``readings[k]``; the ticks done.

        ``stop`` given: after tick 0, ``write(k)`` writes only ``controls(k)`` (this stepper's
        :meth:`controls`), or with ``controls`` None nothing, and returns False exactly when
        ``stop()`` is true; a stepper may then run the ticks after tick 0's write without calling
        ``write`` again, asking ``stop()`` once after them (true: no tick done, the simulation back
        before tick 0). A stepper may ignore both and call ``write`` every tick.
        """

    def controls(self, rows: FloatArray, setpoint: SetpointView) -> Callable[[int], None] | None:
        """``put(j)``: writes the controls the backend's write of setpoint ``rows[j]`` leaves, computed at once.

        ``rows`` (K, 7, n); None where the backend cannot (then each tick writes its setpoint).
        """

    def restore(self, k: int, write: Callable[[int], object]) -> None:
        """Put the simulation back to where it stood before tick ``k`` of the last run.

        ``write(j)`` writes tick ``j``'s setpoint again, as the run did, for a stepper that replays
        ticks to get there (MuJoCo's replays from its latest checkpoint).
        """


class BlockLockstep:
    """Runs a lockstep robot's uneventful ticks as blocks (see the module); :meth:`close` turns it off.

    Made by :meth:`agentsdk.Robot.block_lockstep`. ``capacity``: the most ticks per block.
    Counters: :attr:`blocks` run, :attr:`block_ticks` committed through them (:attr:`motion_ticks`
    of them while a motion followed its trajectory), :attr:`rollbacks` (blocks cut short by a
    tick that had to run alone).
    """

    def __init__(self, loop: ControlLoop, safety: SafetyBlock, planner: BlockPlanner | None,
                 capacity: int = 256) -> None:
        clock = loop.clock
        if not isinstance(clock, LockstepClock):
            raise ConfigurationError("block lockstep needs a lockstep robot (realtime=False)")
        check_capacity(capacity)
        make = getattr(loop.backend, "block_stepper", None)
        if make is None:
            raise ConfigurationError(f"backend {loop.backend.name!r} cannot run a block of ticks (no block_stepper)")
        if loop.block_runner is not None:
            raise ConfigurationError("block lockstep is already on for this robot")
        self._loop = loop
        self._clock = clock
        self._stepper: BlockStepperLike = make(capacity)
        self._safety = safety
        self._planner = planner
        self.capacity = capacity
        n = len(loop.joints)
        self._rows = np.empty((capacity, 7, n))
        self._readings = np.empty((capacity, 3, n))
        self._ts = np.empty(capacity)
        self._itick = np.empty(capacity, dtype=np.int64)
        self._one_to_k = np.arange(1, capacity + 1, dtype=np.int64)
        #: ticks to run as usual before trying a block again (after a block cut short at once)
        self._skip = 0
        self._backoff = 1
        self.blocks = 0
        self.block_ticks = 0
        self.motion_ticks = 0
        self.rollbacks = 0
        #: the OBSERVE hooks last looked at and :meth:`_observers`' answer for them (the loop builds a new
        #: tuple whenever its hooks change: the scan and its list are not redone, nor allocated, per tick)
        self._observe_fns: tuple[Callable[..., object], ...] | None = None
        self._observe_ok: list[BlockObserver] | None = None
        loop.block_runner = self.run

    @property
    def active(self) -> bool:
        """The loop runs its blocks through this runner (not closed, not replaced)."""
        return self._loop.block_runner == self.run

    def close(self) -> None:
        """Turn block lockstep off (ticks run one by one again). Idempotent."""
        if self._loop.block_runner == self.run:
            self._loop.block_runner = None

    def _observers(self) -> list[BlockObserver] | None:
        """The OBSERVE hooks besides the watchdogs if each takes blocks (None: one does not, or no watchdogs)."""
        fns = self._loop.hook_functions(Phase.OBSERVE)
        if fns is not self._observe_fns:  # (held here: a tuple seen before cannot be another one now)
            self._observe_fns = fns
            self._observe_ok = self._scan(fns)
        return self._observe_ok

    def _scan(self, fns: tuple[Callable[..., object], ...]) -> list[BlockObserver] | None:
        out: list[BlockObserver] = []
        seen = False
        for fn in fns:
            if self._safety.is_watchdog_hook(fn):
                seen = True
            elif isinstance(fn, BlockObserver):
                out.append(fn)
            else:
                return None
        return out if seen else None

    def run(self) -> tuple[int, bool]:
        """One block if one can run now: ``(ticks committed, whether the last woke a sleeper)``, else ``(0, False)``."""
        if self._skip:
            self._skip -= 1
            return _NONE
        loop, clock, safety = self._loop, self._clock, self._safety
        # the tests a tick that cannot be blocked fails most often come first: a task that wakes at the
        # next tick (a behavior commanding every tick: one clock call), an OBSERVE hook without a block
        # form (a recorder)
        if clock.wakes_next_tick():
            return _NONE
        observers = self._observers()
        if observers is None:
            return _NONE
        K = clock.ticks_until_wake(self.capacity)
        if K < 2:
            return _NONE
        if loop.torque_off or loop.fault is not None or not safety.ready(loop.hook_functions(Phase.LIMIT)):
            return _NONE
        hooks = loop.hook_functions(Phase.COMMAND)
        if hooks and self._planner is None:
            return _NONE
        tick0, period = clock.ticks, clock.period
        stamp = loop.stamp
        if stamp != tick0 * period:
            return _NONE  # (the COMMAND phases' times below are the clock's products)
        return self._block(K, hooks, observers, tick0, period, stamp)

    def _block(self, K: int, hooks: tuple[Callable[..., object], ...], observers: list[BlockObserver],
               tick0: int, period: float, stamp: float) -> tuple[int, bool]:
        """Try a block of up to ``K`` ticks from tick ``tick0`` (:meth:`run`'s checks passed).

        Apart from :meth:`run`: its closures' cells are made on every call, and :meth:`run` runs
        before every lockstep tick, most of them without a block (nothing allocated there).
        """
        stepper = self._stepper
        if not stepper.ready():
            return self._cut_short()
        loop, clock, safety = self._loop, self._clock, self._safety
        sp = loop.setpoint_buffer
        before = sp.block.copy()
        sp.acceleration.fill(0.0)  # as each tick does first (only a motion writes it again)
        plans: list[BlockPlan] = []
        if hooks:
            assert self._planner is not None
            planned = self._planner.follow(hooks, K, tick0, self.capacity)
            if planned is None:
                sp.block[...] = before
                return self._cut_short()
            K, plans = planned
        rows = self._rows[:K]  # every tick's setpoint rows after its COMMAND and LIMIT phases
        rows[...] = sp.block
        for plan in plans:
            sel, samples = plan.sel, plan.samples[:K]
            va = plan.va[:K] if plan.scaled else samples[:, 1:3]  # (speed scaling: v = vt s, ...)
            rows[:, 0, sel] = samples[:, 0]  # position
            rows[:, 1, sel] = va[:, 0]  # velocity
            rows[:, 5, sel] = samples[:, 0]  # target
            rows[:, 6, sel] = va[:, 1]  # acceleration
        if plans:
            k = safety.limit_quiet(np.ascontiguousarray(rows[:, 0:3]), sp.mode, sp.enabled)
        else:
            # a hold: every row the same, so ticks 1.. all run the LIMIT rule on the same row with the
            # same previous position (the row's own): the first two ticks decide them all
            k = safety.limit_quiet(np.ascontiguousarray(rows[:2, 0:3]), sp.mode, sp.enabled)
            if k == 2:
                k = K
        if k < 2:
            sp.block[...] = before
            return self._cut_short()
        backend, spv, latched, spb = loop.backend, sp.view, safety.latched, sp.block
        # a hold's rows are all the same: where the backend's controls depend on the setpoint alone,
        # the controls written at tick 0 stand for the whole block
        every_tick = bool(plans) or not stepper.write_once
        # a motion's controls for every tick at once, where the backend computes them from the setpoint
        # alone (tick 0 still writes its setpoint: that sets what the gains and enabled joints decide)
        put = stepper.controls(rows[:k], spv) if plans else None

        def write(j: int) -> bool:
            # an emergency stop or latch from another thread ends the block before the next write:
            # tick by tick it would land at that tick
            if loop.torque_off or latched():
                return False
            if j:  # the robot time of the latest state as tick j's write sees it (another thread's events)
                loop.stamp = (tick0 + j) * period
                if not every_tick:
                    return True
                if put is not None:
                    put(j)
                    if loop.torque_off:
                        backend.emergency_stop(0)  # it landed during the write: enforce it again
                    return True
            spb[...] = rows[j]
            backend.write(spv)
            if loop.torque_off:
                backend.emergency_stop(0)  # it landed during write: enforce it again (as the tick does)
            return True

        def stop() -> bool:
            return loop.torque_off or latched()

        def rewrite(j: int) -> None:
            # a replayed tick (restore): the same write, whatever the torque state now (the next tick enforces it)
            spb[...] = rows[j]
            backend.write(spv)

        # ticks 1.. write precomputed controls or nothing: the stepper may run them without write()
        open_loop = put is not None or not every_tick
        done = stepper.run(write, k, self._readings, stop if open_loop else None, put)
        fault = stepper.fault
        loop.stamp = stamp
        if done == 0:
            sp.block[...] = before
            if fault is not None:
                stepper.restore(0, rewrite)  # tick 0 runs alone and diverges there, tick by tick
            return self._cut_short()
        # tick j's OBSERVE phase runs at (T + j + 1) * period, the clock's own product
        itick = np.add(self._one_to_k[:done], tick0, out=self._itick[:done])
        ts = np.multiply(itick, period, out=self._ts[:done])
        states = self._readings[:done]
        setpoints = rows[:done, 0]
        q, checked = safety.observe_quiet(ts, states, setpoints)
        for plan in plans:
            if q == 0:
                break
            assert self._planner is not None
            q = self._planner.path_quiet(plan, states, q)  # a motion's path (goal) test, at each tick's COMMAND
            checked = min(checked, q)
        if q < done or fault is not None:
            # tick q runs alone, from where it started (a step that diverged: again, tick by tick)
            stepper.restore(q, rewrite)
            self.rollbacks += 1
        if q == 0:
            sp.block[...] = before
            return self._cut_short()
        for plan in plans:
            assert self._planner is not None
            self._planner.commit(plan, states, q)
        if plans:
            self.motion_ticks += q
        if not safety.commit(ts, states, rows[:, 0:3], setpoints, q, checked):
            loop.state_buffer.block[...] = states[q - 1]  # no plausibility gate: the reading is the state
        spb[...] = rows[q - 1]
        if observers:
            view = states[:q]
            view.flags.writeable = False
            sps = rows[:q]
            sps.flags.writeable = False
            for obs in observers:
                obs.observe_block(ts[:q], view, sps, spv)
        woke = clock.advance_ticks(q)  # (only the last can wake)
        loop.stamp = clock.now()
        loop.ticks += q
        self.blocks += 1
        self.block_ticks += q
        self._backoff = 1
        return q, woke > 0

    def _cut_short(self) -> tuple[int, bool]:
        """No block now: run the next ticks as usual, for longer each time this repeats."""
        self._skip = self._backoff
        self._backoff = min(2 * self._backoff, 64)
        return _NONE
