"""The :class:`SafetyLayer`: builds and wires the safety objects around one control loop, and is the command gate.

Who holds whom (each object gets exactly its collaborators; calls only point down this list)::

    SafetyLayer ─→ Watchdogs ─→ Stops ─→ CommandFilter ─→ SafetyCore
         │             │          │            │
         └─────────────┴──────────┴────────────┴─→ StopPort (the motion manager, attached later)
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING

from ..checks import MeasuredPositionCheck, SafetyCheck
from ..commands import CommandShapes
from ..errors import CommandRejected
from ..limits import PositionBounds, StepGuard, StepLimiter
from ..loop import ControlLoop, HookHandle, Phase
from ..types import AppliedCommand, JointCommand
from ._block import SafetyBlock
from ._config import SafetyConfig
from ._filter import CommandFilter
from ._state import SAFETY_OBSERVE_ORDER, SafetyCore, SafetyEvent, SafetyState, StopPort, _NoMotions
from ._stops import Stops
from ._watchdogs import Watchdogs

if TYPE_CHECKING:
    from ..following import FollowingErrorCheck


#: every joint, as an index (what a full-length command's index array selects): ``x[...] = v`` is the
#: cheapest in-place write numpy has (a slice is parsed into one first)
_EVERY = Ellipsis


class SafetyLayer:
    """Wraps one control loop. Created by :func:`agentsdk.connect`; reach it as ``robot.safety``.

    A facade: the state machine, latch and event log (``SafetyCore``), the command filter
    (``CommandFilter``), the stops (``Stops``) and the watchdogs (``Watchdogs``) are separate
    objects it builds and wires; it owns the command gate :meth:`admit`.
    """

    def __init__(
        self, loop: ControlLoop, config: SafetyConfig, bounds: PositionBounds, motions: StopPort | None = None
    ) -> None:
        self.loop = loop
        self.config = config
        self._motions: StopPort = _NoMotions(len(loop.joints)) if motions is None else motions
        #: the one limiting rule (position bounds, step per period, velocity and effort limits)
        self.limiter = limiter = StepLimiter.for_joints(loop.joints, bounds, config.max_position_step, loop.period)
        #: the plausibility gate of every reading (None: sensor_check off)
        self.sensor_gate = (
            loop.install_sensor_gate(
                margin=config.sensor_jump_margin, floor=config.sensor_jump_floor,
                tolerance=config.position_limit_tolerance,
            )
            if config.sensor_check
            else None
        )
        self._core = core = SafetyCore(loop)
        self._filter = command_filter = CommandFilter(loop, config, limiter, core, self._motions)
        self._stops = stops = Stops(loop, config, limiter, core, command_filter, self._motions)
        self._watchdogs = watchdogs = Watchdogs(
            loop, config, core, command_filter, stops, self._motions, self.sensor_gate
        )
        #: block lockstep's view of the filter, the watchdogs and the gate (see :mod:`agentsdk.block`)
        self.block_seam = SafetyBlock(loop, core, command_filter, watchdogs)
        #: the command shapes seen so far (joint indices and names validated once per shape)
        self._shapes = shapes = CommandShapes(loop.names, loop.index)
        command_filter.full_index = shapes.full
        # the gate's calls, bound once
        self._resolve = shapes.resolve
        self._check_motion_allowed = core.check_motion_allowed
        self._limit_command = command_filter.limit_command
        self._limit_feedforward = command_filter.limit_feedforward
        self._ramp_start = command_filter.ramp_start
        self._start_ramp = command_filter.start_ramp
        self._feed = watchdogs.feed
        self._full = shapes.full
        #: where a position ramp starts (the filter's last written position: read-only, live)
        self._origin = command_filter.origin()
        self._handles = [
            loop.add_hook(Phase.LIMIT, command_filter.tick),
            loop.add_hook(Phase.OBSERVE, watchdogs.tick, order=SAFETY_OBSERVE_ORDER),
            loop.add_fault_listener(stops.on_fault),
        ]
        #: what the motion manager checks its planned steps against before writing (a planned motion
        #: is never clipped silently; an abort that resets a reference to the measured state says so)
        self.step_guard = StepGuard(limiter, command_filter.origin(), command_filter.rebase_reference, core.record)
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

    @property
    def motions(self) -> StopPort:
        """The stop port of the motion manager (see :meth:`attach_motions`; assigning it attaches it)."""
        return self._motions

    @motions.setter
    def motions(self, motions: StopPort) -> None:
        self.attach_motions(motions)

    def attach_motions(self, motions: StopPort) -> None:
        """Connect the motion manager (through the :class:`StopPort` this layer defines)."""
        self._motions = motions
        self._filter.motions = motions
        self._stops.motions = motions
        self._watchdogs.motions = motions

    # ---------------------------------------------------------- lifecycle
    def start(self) -> None:
        """Start the heartbeat and the stall watchdog thread (called by connect once the loop runs)."""
        self._stops.bind(asyncio.get_running_loop())
        self._filter.restart(self.loop.setpoint.position)
        self._watchdogs.start_stall_watchdog()

    async def shutdown(self) -> None:
        """Stop the watchdog thread and heartbeat, end stop tasks (awaited); called by Robot.close()."""
        self._watchdogs.stop_stall_watchdog_now()
        await self._stops.cancel()
        await self._watchdogs.stop_stall_watchdog()

    def shutdown_now(self) -> None:
        """Synchronous part of :meth:`shutdown` (no event loop): signal the watchdog thread to stop."""
        self._watchdogs.stop_stall_watchdog_now()

    # ---------------------------------------------------------- state and events (SafetyCore)
    @property
    def state(self) -> SafetyState:
        """OK, HOLD, ESTOP, DISABLED or FAULT (an e-stop latched from another thread shows at once)."""
        return self._core.state

    @property
    def cause(self) -> BaseException | None:
        """The exception behind a FAULT, or None."""
        return self._core._cause

    @property
    def events(self) -> tuple[SafetyEvent, ...]:
        """Recorded safety events, oldest first (the last 10,000), including ones from the watchdog thread."""
        return self._core.events

    @property
    def event_count(self) -> int:
        """How many events were ever recorded (a cursor for :meth:`events_since`)."""
        return self._core._event_count

    def events_since(self, count: int) -> list[SafetyEvent]:
        """Events recorded after the first ``count`` (``count`` from :attr:`event_count`)."""
        return self._core.events_since(count)

    def record(self, kind: str, detail: str, joint: str | None = None) -> SafetyEvent:
        """Append an event (any thread) stamped with the robot time of the latest state."""
        return self._core.record(kind, detail, joint)

    def check_fault(self) -> None:
        """Raise :class:`~agentsdk.errors.SafetyFault` (with the cause) while in FAULT."""
        core = self._core
        if core._state is SafetyState.FAULT:  # (every read asks: the core's call only when it raises)
            core.check_fault()

    def check_motion_allowed(self) -> None:
        """Raise :class:`~agentsdk.errors.EStopActive` / :class:`~agentsdk.errors.SafetyFault` unless OK or HOLD."""
        self._core.check_motion_allowed()

    def latch_cause(self) -> str:
        """The detail of the event that latched the e-stop (the first stopping event since the last reset)."""
        return self._core.latch_cause()

    # ---------------------------------------------------------- stops (Stops)
    @property
    def stop_in_progress(self) -> bool:
        """True while a controlled stop (category 1 or 2) is decelerating the robot."""
        return self._stops.stop_in_progress

    async def estop(self, category: int = 1) -> None:
        """Latch an e-stop of the given category and wait until its end state is reached.

        The stop runs in its own task: cancelling the caller does not interrupt it.
        """
        await self._stops.estop(category)

    def estop_threadsafe(self, category: int = 0) -> None:
        """Latch an e-stop from any thread. Category 0 acts at once in the calling thread;
        categories 1 and 2 are scheduled on the robot's event loop (category 0 if it is gone).
        """
        self._stops.estop_threadsafe(category)

    async def wait_stopped(self) -> None:
        """Wait until every stop in progress has reached its end state (returns at once if none)."""
        await self._stops.wait_stopped()

    async def reset(self) -> None:
        """Clear the latch (ESTOP -> DISABLED) or recover a FAULT. Never moves the robot.

        A stop in progress completes first. Anything still driving the joints over time
        (a trajectory, a stop ramp) ends here; the setpoint stays exactly as the stop
        left it: torque off stays off, a hold keeps holding where it is.
        """
        await self._stops.reset()
        self._watchdogs.rearm_after_reset()

    async def enable(self) -> None:
        """Allow motion again: hold the current position with torque on (ESTOP must be reset first)."""
        await self._stops.enable()
        self._watchdogs.rearm_commands()

    # ---------------------------------------------------------- watchdogs (Watchdogs)
    def add_check(self, check: SafetyCheck) -> HookHandle:
        """Run ``check(t, state)`` every tick while motion is allowed; a returned violation latches an e-stop."""
        return self._watchdogs.add_check(check)

    @property
    def stall_watchdog_active(self) -> bool:
        """True if the stall watchdog watches this robot (see :mod:`agentsdk.safety`).

        That is: a ``stall_timeout`` is set and the robot runs in real time, or in lockstep with
        ``stall_in_lockstep``.
        """
        return self._watchdogs.stall_watchdog_active

    @property
    def stall_traceback(self) -> str | None:
        """Stack of the event-loop thread when the stall watchdog fired (None since the last reset)."""
        return self._watchdogs.stall_traceback

    @property
    def stall_detected_at(self) -> float | None:
        """Wall-clock time (``time.monotonic``) the stall watchdog fired, or None."""
        return self._watchdogs.stall_detected_at

    @property
    def stall_latency(self) -> float | None:
        """How long after the last heartbeat the stall watchdog fired (s), or None."""
        return self._watchdogs.stall_latency

    # ---------------------------------------------------------- the command gate
    def admit(self, cmd: JointCommand) -> AppliedCommand:
        """The one way a direct command reaches the setpoint; returns the command actually applied.

        In order: motion must be allowed (no latched e-stop, no fault), the command is validated
        (:func:`~agentsdk.commands.resolve_command`; :class:`~agentsdk.commands.CommandShapes` keeps
        each command shape's joint indices), its joints must not be driven by a motion, its
        values are limited (clamped and recorded, or rejected under ``limit_policy: reject``), it
        is written into the setpoint (a position command starts its ramp where the limiter is),
        and the command watchdog is fed. Raises a :class:`CommandRejected` subclass or
        :class:`EStopActive` with the setpoint unchanged. The caller holds the loop's lock.
        """
        loop = self.loop
        backend = loop.backend
        core = self._core
        if core._state is not SafetyState.OK or core.latched:
            self._check_motion_allowed()  # (OK without a latch: nothing to check)
        idx, names, values, vel, eff = self._resolve(cmd, backend.capabilities.modes, backend.name)
        assert isinstance(cmd, JointCommand)  # resolve checked it
        owner = self._motions.owner_of(idx)
        if owner is not None:
            raise CommandRejected(
                f"joint {loop.names[owner[0]]!r} is driven by a running trajectory (or reserved by a "
                "scheduled one); cancel it (motion.cancel()) before sending direct commands"
            )
        mode = cmd.mode
        values = self._limit_command(mode, idx, values)
        if vel is not None or eff is not None:
            vel, eff = self._limit_feedforward(idx, vel, eff)
        if idx is self._full and vel is None and eff is None and mode == "position":
            # every joint, no feed-forward (a behavior streaming whole poses): one block write; the
            # setpoint starts at the ramp's position, the filter's origin (copied into the setpoint)
            loop.apply_position_all(values, self._origin)
        else:
            loop.apply(mode, idx, values, vel, eff, position_now=self._ramp_start(mode, idx))
        # every joint: the same elements by basic indexing (a slice: no index array walked per write)
        sel = _EVERY if idx is self._full else idx
        self._feed(sel)
        self._start_ramp(mode, sel, values)
        return AppliedCommand.of_arrays(mode, names, values, vel, eff)
