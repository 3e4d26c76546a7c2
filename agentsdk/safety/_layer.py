"""The :class:`SafetyLayer`: built around one control loop, the one command gate (:meth:`~SafetyLayer.admit`)."""

from __future__ import annotations

import asyncio
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from ..checks import MeasuredPositionCheck, SafetyCheck
from ..clock import RealtimeClock
from ..commands import resolve_command
from ..errors import (
    CommandRejected,
    InvalidValueError,
)
from ..limits import PositionBounds, StepGuard
from ..loop import ControlLoop, HookHandle, Phase
from ..stall import StallWatchdog
from ..types import AppliedCommand, JointCommand
from ._config import SafetyConfig
from ._state import SAFETY_OBSERVE_ORDER, StopPort
from ._watchdogs import _Watchdogs

if TYPE_CHECKING:
    from ..following import FollowingErrorCheck



class SafetyLayer(_Watchdogs):
    """Wraps one control loop. Created by :func:`agentsdk.connect`; reach it as ``robot.safety``."""

    def __init__(
        self, loop: ControlLoop, config: SafetyConfig, bounds: PositionBounds, motions: StopPort | None = None
    ) -> None:
        super().__init__(loop, config, bounds, motions)
        self._handles = [
            loop.add_hook(Phase.LIMIT, self._filter),
            loop.add_hook(Phase.OBSERVE, self._on_tick, order=SAFETY_OBSERVE_ORDER),
            loop.add_fault_listener(self._on_fault),
        ]
        origin = self._written.view()
        origin.flags.writeable = False
        #: what the motion manager checks its planned steps against before writing (a planned motion
        #: is never clipped silently; an abort that resets a reference to the measured state says so)
        self.step_guard = StepGuard(self.limiter, origin, self._rebase_reference, self.record)
        #: the plausibility gate of every reading (None: sensor_check off)
        self.sensor_gate = (
            loop.install_sensor_gate(
                margin=config.sensor_jump_margin, floor=config.sensor_jump_floor,
                tolerance=config.position_limit_tolerance,
            )
            if config.sensor_check
            else None
        )
        if config.position_limit_tolerance is not None:
            self.add_check(
                MeasuredPositionCheck(loop.joints, config.position_limit_tolerance, config.position_limit_stop)
            )
        #: the following-error check (None: ``following_error_window: null``), see :mod:`agentsdk.following`
        self.following: FollowingErrorCheck | None = None
        if config.following_error_window is not None:
            from ..following import FollowingErrorCheck, following_windows

            windows = following_windows(loop.joints, loop.gain_p, config.following_error_window,
                                        config.following_error_min, config.following_error_max)
            self.following = FollowingErrorCheck(loop, windows, config.following_error_time,
                                                 config.following_error_stop)
            self.add_check(self.following)

    def attach_motions(self, motions: StopPort) -> None:
        """Connect the motion manager (through the :class:`StopPort` this layer defines)."""
        self.motions = motions

    # ---------------------------------------------------------- lifecycle
    def start(self) -> None:
        """Start the heartbeat and the stall watchdog thread (called by connect once the loop runs)."""
        self._aloop = asyncio.get_running_loop()
        np.copyto(self._written, self.loop.setpoint.position)
        self._goal = self._written.copy()
        timeout = self.config.stall_timeout
        if self.stall_watchdog_active and timeout is not None and self._stall is None:
            loop = self.loop
            self._stall = StallWatchdog(
                timeout, f"agentsdk-stall-watchdog-{loop.backend.name}",
                idle=lambda: loop.torque_off or loop.closed,
                emergency_stop=lambda: loop.emergency_stop(0),
                on_stall=self._on_stall,
            )
            if isinstance(loop.clock, RealtimeClock):  # every tick beats, at the time the tick read anyway
                loop.add_hook(Phase.OBSERVE, self._stall.tick_beats(loop.clock.origin))
            self._stall.start()

    async def shutdown(self) -> None:
        """Stop the watchdog thread and heartbeat, end stop tasks (awaited); called by Robot.close()."""
        stall = self._stall
        if stall is not None:
            stall.stop_now()
        tasks = list(self._stop_tasks)
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)
        if stall is not None:
            await stall.stop()

    def shutdown_now(self) -> None:
        """Synchronous part of :meth:`shutdown` (no event loop): signal the watchdog thread to stop."""
        if self._stall is not None:
            self._stall.stop_now()

    # ---------------------------------------------------------- the command gate
    def admit(self, cmd: JointCommand) -> AppliedCommand:
        """The one way a direct command reaches the setpoint; returns the command actually applied.

        In order: motion must be allowed (no latched e-stop, no fault), the command is validated
        (:func:`~agentsdk.commands.resolve_command`), its joints must not be driven by a motion, its
        values are limited (clamped and recorded, or rejected under ``limit_policy: reject``), it
        is written into the setpoint (a position command starts its ramp where the limiter is),
        and the command watchdog is fed. Raises a :class:`CommandRejected` subclass or
        :class:`EStopActive` with the setpoint unchanged. The caller holds the loop's lock.
        """
        loop = self.loop
        backend = loop.backend
        self.check_motion_allowed()
        idx, values, vel, eff = resolve_command(cmd, loop.names, loop.index, backend.capabilities.modes, backend.name)
        assert isinstance(cmd, JointCommand)  # resolve_command checked it
        owner = self.motions.owner_of(idx)
        if owner is not None:
            raise CommandRejected(
                f"joint {loop.names[owner[0]]!r} is driven by a running trajectory (or reserved by a "
                "scheduled one); cancel it (motion.cancel()) before sending direct commands"
            )
        values = self._limit_command(cmd.mode, idx, values)
        vel, eff = self._limit_feedforward(idx, vel, eff)
        loop.apply(cmd.mode, idx, values, vel, eff, position_now=self._ramp_start(cmd.mode, idx))
        self._feed(cmd.mode, idx, values)
        names = [loop.names[i] for i in idx.tolist()]
        return AppliedCommand(
            cmd.mode,
            MappingProxyType(dict(zip(names, values.tolist(), strict=True))),
            None if vel is None else MappingProxyType(dict(zip(names, vel.tolist(), strict=True))),
            None if eff is None else MappingProxyType(dict(zip(names, eff.tolist(), strict=True))),
        )

    def add_check(self, check: SafetyCheck) -> HookHandle:
        """Run ``check(t, state)`` every tick while motion is allowed; a returned violation latches an e-stop."""
        if not callable(check):
            raise InvalidValueError(f"a safety check must be callable, got {check!r}")
        self._checks.append(check)
        checks = self._checks
        return HookHandle(lambda: checks.remove(check) if check in checks else None, lambda: check in checks)
