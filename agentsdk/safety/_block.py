"""Block lockstep's safety side (issue 28 item 1, :mod:`agentsdk.block`): the LIMIT and OBSERVE rules over K ticks.

:class:`SafetyBlock` answers for the safety layer's per-tick hooks (the filter's LIMIT tick, the
watchdogs' OBSERVE tick with its checks and the plausibility gate) whether a block of ticks may
run now, how many leading ticks of a block they pass *quietly* (a per-tick call would change
nothing but what the commit reproduces) and brings their state to where those ticks leave it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..checks import BlockCheck
from ..loop import ControlLoop
from ._filter import CommandFilter
from ._state import SafetyCore, SafetyState
from ._watchdogs import Watchdogs


class SafetyBlock:
    """The safety layer's rules over a block of lockstep ticks (made by the :class:`SafetyLayer`)."""

    def __init__(self, loop: ControlLoop, core: SafetyCore, command_filter: CommandFilter,
                 watchdogs: Watchdogs) -> None:
        self._loop = loop
        self._core = core
        self._filter = command_filter
        self._watchdogs = watchdogs
        self._filter_tick = command_filter.tick
        #: the LIMIT hooks a block allows (built once: ready() runs before every lockstep tick and allocates nothing)
        self._filter_only = (self._filter_tick,)
        self._wd_tick = watchdogs.tick
        #: the checks' version (``Watchdogs.checks_version``) the block forms were last looked up at, and
        #: the checks then if each had one (else None): a Protocol isinstance costs microseconds and
        #: allocates, so once per change of the list, not per tick
        self._checks_seen = -1
        self._block_checks: tuple[BlockCheck, ...] | None = None

    def _checks(self) -> tuple[BlockCheck, ...] | None:
        """The watchdogs' checks if every one has a block form (:class:`BlockCheck`), else None."""
        wd = self._watchdogs
        if wd.checks_version != self._checks_seen:
            self._checks_seen = wd.checks_version
            checks = tuple(wd._checks)
            self._block_checks = checks if all(isinstance(c, BlockCheck) for c in checks) else None  # type: ignore[assignment]
        return self._block_checks

    def ready(self, limit_hooks: tuple[Callable[..., object], ...]) -> bool:
        """The cheap preconditions: the filter is the only LIMIT hook, state OK, every check has a block form.

        Also: no latch, no sensor fault to report, the gate and every check ready for a block
        (:meth:`~agentsdk.checks.BlockCheck.block_ready`) and the command watchdog not watching
        position mode (its per-tick test would then have to run).
        """
        if limit_hooks != self._filter_only:
            return False
        if self._core._state is not SafetyState.OK or self._core.latched:
            return False
        gate = self._loop.sensor_gate
        if gate is not None and (gate.pending or not gate.block_ready()):
            return False
        wd = self._watchdogs
        if wd._watch_position:
            return False
        checks = self._checks()
        if checks is None:
            return False
        for c in checks:  # (a loop, not all() of a generator: nothing allocated per tick)
            if not c.block_ready():
                return False
        return True

    def latched(self) -> bool:
        """True once an e-stop latch is set (any thread): a block ends before its next write."""
        return self._core.latched

    def is_watchdog_hook(self, fn: Callable[..., object]) -> bool:
        """True for the safety watchdogs' OBSERVE hook (its block form is :meth:`observe_quiet`)."""
        return fn == self._wd_tick

    def limit_quiet(self, rows: np.ndarray, mode: np.ndarray, enabled: np.ndarray) -> int:
        """Leading ticks of ``rows`` (K, 3, n) the LIMIT tick leaves as they are (see ``CommandFilter.block_quiet``)."""
        return self._filter.block_quiet(rows, mode, enabled)

    def observe_quiet(self, ts: np.ndarray, states: np.ndarray, setpoints: np.ndarray) -> tuple[int, int]:
        """How many leading ticks the OBSERVE rules pass quietly, and in how many of them the checks run.

        ``ts`` (K,) the ticks' OBSERVE times, ``states`` (K, 3, n) their readings, ``setpoints``
        (K, n) the position each wrote. The gate takes every reading of the quiet ticks as it is;
        the checks run while no latch is set: a latch set from another thread during the block
        ended it at its next write, and tick by tick the last tick's watchdogs would have seen it.
        """
        done = len(ts)
        q = done
        gate = self._loop.sensor_gate
        if gate is not None:
            q = min(q, gate.block_quiet(ts, states))
        checked = min(q, done - 1 if self._core.latched else done)
        checks = self._checks()
        assert checks is not None  # (ready() said so, and nothing runs between ready() and the block)
        for c in checks:
            if checked == 0:
                break
            quiet = c.block_quiet(ts[:checked], states[:checked], setpoints[:checked])
            if quiet < checked:
                checked = q = quiet  # this tick's check acts: it runs alone
        return q, checked

    def commit(self, ts: np.ndarray, states: np.ndarray, rows: np.ndarray, setpoints: np.ndarray, q: int,
               checked: int) -> bool:
        """Take the state ``q`` quiet ticks leave (the checks ran in ``checked``); False: no gate wrote the state."""
        self._filter.commit_block(rows, q)
        checks = self._checks()
        assert checks is not None
        for c in checks:
            c.commit_block(ts, states, setpoints, checked)
        gate = self._loop.sensor_gate
        if gate is None:
            return False
        gate.commit_block(ts, states, q)
        return True
