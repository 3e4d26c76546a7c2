"""The control loop: one per robot, owning the setpoint, the measured state and the tick phases.

One tick, like ros2_control's read -> update -> write::

    COMMAND hooks   write the reference for time t (trajectories, stop ramps, replay)
    LIMIT hooks     filter it (the safety layer: limits, ramps)
    torque-off rule every joint disabled while an emergency stop holds
    backend.write(setpoint view) -> await backend.step(dt) -> backend.read()
    OBSERVE hooks   see the fresh state and the setpoint that was written
                    (recorders first, watchdogs last: ``order``)

Extension points are explicit: :meth:`ControlLoop.add_hook` registers a
function in a named :class:`Phase` and returns a :class:`HookHandle`
(``handle.remove()``); :meth:`ControlLoop.add_fault_listener` is told once if
the loop dies. No module writes the loop's buffers except through these
hooks (which receive the writable :class:`Setpoint` in the COMMAND and LIMIT
phases only) and the loop's own methods.

Time models: in lockstep the loop advances the :class:`~agentsdk.clock.LockstepClock`
by one control period per tick, only while every other task on the event loop
is waiting (see :func:`_settle`), many ticks per pass through the event loop
while they wake nothing (see :meth:`ControlLoop._run_lockstep`); in realtime it
runs paced to the wall clock.
"""

from __future__ import annotations

import asyncio
import contextvars
import enum
import functools
import logging
import math
import threading
import time
import types
from collections.abc import Callable, Generator
from typing import Any

import numpy as np

from .backend import Backend, ModeCode, SetpointView
from .clock import Clock, LockstepClock, RealtimeClock
from .errors import (
    BackendFault,
    BackendStartError,
    EStopActive,
    InvalidValueError,
    RobotClosedError,
)
from .plausibility import SensorGate
from .types import CommandMode, FloatArray, JointState

__all__ = [
    "CommandHook",
    "ControlLoop",
    "FaultListener",
    "HookHandle",
    "ObserveHook",
    "Phase",
    "Setpoint",
    "StateBuffer",
    "StateView",
]

log = logging.getLogger("agentsdk.loop")

#: mode codes as plain ints (numpy compares arrays with an IntEnum member slowly, through enum attribute lookups)
_POS, _VEL, _EFF = int(ModeCode.POSITION), int(ModeCode.VELOCITY), int(ModeCode.EFFORT)


class Phase(enum.Enum):
    """The named phases of a control tick, in the order they run."""

    #: write the reference setpoint for this tick: ``fn(t, state, setpoint) -> bool | None``;
    #: returning False unregisters the hook (a finished trajectory)
    COMMAND = "command"
    #: filter the setpoint before it is written: ``fn(t, state, setpoint) -> None``
    LIMIT = "limit"
    #: after the backend stepped and was read: ``fn(t, state, setpoint_view) -> None``
    OBSERVE = "observe"


class StateView:
    """Read-only measured joint state: ``position``, ``velocity``, ``effort`` arrays in joint order.

    ``block`` is the three as the rows of one read-only ``(3, n)`` array (for reading
    several of them in one numpy operation), or None for a view built from separate arrays.
    """

    __slots__ = ("block", "effort", "position", "velocity")

    position: FloatArray
    velocity: FloatArray
    effort: FloatArray
    block: FloatArray | None

    def __init__(
        self, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray, block: np.ndarray | None = None
    ) -> None:
        for name, arr in (("position", position), ("velocity", velocity), ("effort", effort), ("block", block)):
            if arr is None:
                object.__setattr__(self, name, None)
                continue
            view = arr.view()
            view.flags.writeable = False
            object.__setattr__(self, name, view)

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"StateView is read-only (cannot set {name!r})")


class StateBuffer:
    """The loop's measured-state arrays (written only by the loop, from ``Backend.read``).

    ``position``, ``velocity`` and ``effort`` are the rows of ``block`` (shape ``(3, n)``).
    """

    __slots__ = ("block", "effort", "position", "velocity", "view")

    def __init__(self, n: int) -> None:
        self.block = np.zeros((3, n))
        self.position, self.velocity, self.effort = self.block
        #: a read-only view of these arrays (what hooks receive)
        self.view = StateView(self.position, self.velocity, self.effort, self.block)


class Setpoint:
    """The per-joint servo setpoint, in joint order; COMMAND and LIMIT hooks may write it.

    ``position``/``velocity``/``effort`` (feed-forward), ``kp``/``kd`` gains,
    ``enabled`` (bool), ``mode`` (:class:`~agentsdk.backend.ModeCode` values),
    ``target`` (the last commanded value per joint, before any ramping: a
    position, velocity or effort according to ``mode``) and ``acceleration`` (the
    desired acceleration of this tick's reference, for the servo law's inverse-dynamics
    term: the loop zeroes it before the COMMAND hooks, so only a writer that sets it
    every tick, e.g. a trajectory, feeds it forward). ``view`` is the
    read-only :class:`~agentsdk.backend.SetpointView` backends and observers get.

    The float fields are the rows of one array, :attr:`block` (shape ``(7, n)``,
    rows in :attr:`FIELDS` order), so that a hook can write several fields of the
    same joints in one numpy operation (e.g. ``sp.block[0:2, idx] = q_and_v``).
    """

    __slots__ = (
        "acceleration", "block", "effort", "enabled", "kd", "kp", "mode", "position", "target", "velocity", "view",
    )

    #: the rows of :attr:`block`
    FIELDS = ("position", "velocity", "effort", "kp", "kd", "target", "acceleration")

    def __init__(self, n: int) -> None:
        self.block = np.zeros((7, n))
        self.position, self.velocity, self.effort, self.kp, self.kd, self.target, self.acceleration = self.block
        self.enabled = np.ones(n, dtype=bool)
        self.mode = np.zeros(n, dtype=np.int8)
        self.view = SetpointView(
            position=self.position, velocity=self.velocity, effort=self.effort, kp=self.kp, kd=self.kd,
            enabled=self.enabled, mode=self.mode, target=self.target, acceleration=self.acceleration,
        )


#: COMMAND / LIMIT hook: ``fn(t, state_view, setpoint)``; a COMMAND hook may return False to unregister
CommandHook = Callable[[float, StateView, Setpoint], bool | None]
#: OBSERVE hook: ``fn(t, state_view, setpoint_view)``
ObserveHook = Callable[[float, StateView, SetpointView], None]
#: told once when the control loop dies
FaultListener = Callable[[BaseException], None]


class HookHandle:
    """Returned by every registration (tick hooks, fault listeners, safety checks); :meth:`remove` undoes it."""

    __slots__ = ("_is_active", "_remove")

    def __init__(self, remove: Callable[[], None], is_active: Callable[[], bool]) -> None:
        self._remove = remove
        self._is_active = is_active

    @property
    def active(self) -> bool:
        """True while the registration is in effect."""
        return self._is_active()

    def remove(self) -> None:
        """Unregister (idempotent; safe to call from inside the hook itself)."""
        if self._is_active():
            self._remove()


class _Hook:
    __slots__ = ("active", "fn", "order", "seq")

    def __init__(self, fn: Callable[..., Any], order: int, seq: int) -> None:
        self.fn = fn
        self.order = order
        self.seq = seq
        self.active = True


class _HookList:
    """Hooks of one phase, sorted by (order, registration); ``fns`` is the tuple the tick iterates."""

    __slots__ = ("_entries", "_seq", "fns")

    def __init__(self) -> None:
        self._entries: list[_Hook] = []
        self._seq = 0
        self.fns: tuple[Callable[..., Any], ...] = ()

    def add(self, fn: Callable[..., Any], order: int) -> HookHandle:
        self._seq += 1
        entry = _Hook(fn, order, self._seq)
        self._entries.append(entry)
        self._entries.sort(key=lambda e: (e.order, e.seq))
        self._rebuild()
        return HookHandle(lambda: self.remove(entry), lambda: entry.active)

    def remove(self, entry: _Hook) -> None:
        if entry.active:
            entry.active = False
            self._entries.remove(entry)
            self._rebuild()

    def remove_fn(self, fn: Callable[..., Any]) -> None:
        for e in self._entries:
            if e.fn is fn:
                self.remove(e)
                return

    def clear(self) -> None:
        for e in self._entries:
            e.active = False
        self._entries.clear()
        self._rebuild()

    def _rebuild(self) -> None:
        self.fns = tuple(e.fn for e in self._entries)

    def __len__(self) -> int:
        return len(self._entries)


class ControlLoop:
    """Runs one backend: owns the buffers, the clock, the tick phases and the torque-off rule.

    Created by :func:`agentsdk.connect`; the safety layer, the motion executor
    and tools (recorders, replay) attach to it through :meth:`add_hook`.
    """

    def __init__(self, backend: Backend) -> None:
        self.backend = backend
        joints = backend.joints
        self.joints = joints
        self.names = backend.names
        self.index = backend.index
        self.period = backend.period
        self.realtime = backend.realtime
        n = len(joints)
        self._state = StateBuffer(n)
        self._sp = Setpoint(n)
        #: robot time of the latest state (s)
        self.stamp = 0.0
        gains = backend.servo_gains  # robot.yaml gains, else from the model
        self.gain_p = _readonly([g.p for g in gains])
        self.gain_d = _readonly([g.d for g in gains])
        self.gain_v = _readonly([g.d if g.v is None else g.v for g in gains])
        #: :meth:`apply_position_all`'s setpoint block: zero velocity, effort and acceleration rows, the
        #: default gains; the position and target rows are written per command
        self._pos_all = np.zeros((7, n))
        self._pos_all[3] = self.gain_p
        self._pos_all[4] = self.gain_d
        #: the bytes of its mode row (every joint in position mode) and torque row (on everywhere)
        self._pos_all_mode = np.full(n, _POS, dtype=np.int8).tobytes()
        self._pos_all_on = np.ones(n, dtype=bool).tobytes()
        self.clock: Clock = RealtimeClock() if self.realtime else LockstepClock(self.period)
        self._hooks = {phase: _HookList() for phase in Phase}
        self._command = self._hooks[Phase.COMMAND]
        self._limit = self._hooks[Phase.LIMIT]
        self._observe = self._hooks[Phase.OBSERVE]
        self._fault_listeners = _HookList()
        self._task: asyncio.Task[None] | None = None
        self._fault: BaseException | None = None
        #: set by emergency_stop (any thread); every write is torque-off until enable()
        self._torque_off = False
        self._torque_lock = threading.Lock()
        #: emergency stops so far (under the torque lock): an enable that spans one leaves torque off
        self._estops = 0
        self._closed = False
        #: serializes commands (Robot.command, follow)
        self.lock = asyncio.Lock()
        self.ticks = 0
        self.missed_deadlines = 0
        #: lockstep only: wall time (s) a batch of ticks may run before the loop passes through the
        #: event loop again (asyncio timers and I/O run between batches); 0 runs one tick per pass,
        #: as before batching. Either way the ticks compute the same thing (see :meth:`_run_lockstep`).
        self.batch_seconds = BATCH_SECONDS
        #: the plausibility gate every reading passes before it becomes the state (None: readings
        #: are taken as they are); see :meth:`install_sensor_gate`
        self.sensor_gate: SensorGate | None = None
        #: per joint, the position a trajectory controller running an offloaded goal (:mod:`agentsdk.offload`)
        #: last reported as its desired state (NaN: none): that controller owns the goal's timing, so the
        #: following-error check also accepts a joint within its window of this (written by the motion layer)
        self.controller_desired = np.full(n, np.nan)
        #: the realtime clock's time.monotonic() at robot time 0 (None in lockstep), and the robot time of
        #: the reading being gated (NaN: none): a backend's reading ages without another clock read
        self._origin: float | None = getattr(self.clock, "origin", None)
        self._read_t = math.nan
        #: block lockstep (:mod:`agentsdk.block`, connect's default in MuJoCo/PyBullet lockstep; None: off): asked
        #: before each lockstep tick, it runs as many ticks as it can prove uneventful at once and returns
        #: how many (0: the tick runs as usual) and whether the last one woke a sleeper
        self.block_runner: Callable[[], tuple[int, bool]] | None = None

    # ------------------------------------------------------------ views
    @property
    def state(self) -> StateView:
        """Read-only view of the latest measured state."""
        return self._state.view

    @property
    def setpoint(self) -> SetpointView:
        """Read-only view of the setpoint (as last written, or as it will be written next tick)."""
        return self._sp.view

    @property
    def setpoint_buffer(self) -> Setpoint:
        """The writable setpoint the COMMAND and LIMIT hooks get (block lockstep writes each tick's rows into it)."""
        return self._sp

    @property
    def state_buffer(self) -> StateBuffer:
        """The measured-state arrays the loop writes (block lockstep commits a block's last reading into them)."""
        return self._state

    def hook_functions(self, phase: Phase) -> tuple[Callable[..., Any], ...]:
        """The functions registered in ``phase``, in the order the tick calls them."""
        return self._hooks[phase].fns

    @property
    def targets(self) -> FloatArray:
        """Read-only view of the last commanded value per joint (position, velocity or effort per its mode)."""
        view = self._sp.target.view()
        view.flags.writeable = False
        return view

    @property
    def torque_off(self) -> bool:
        """True after an emergency stop removed torque, until :meth:`enable`."""
        return self._torque_off

    @property
    def closed(self) -> bool:
        """True once :meth:`stop` ran."""
        return self._closed

    @property
    def fault(self) -> BaseException | None:
        """Why the control loop died, or None while it runs."""
        return self._fault

    @property
    def busy(self) -> bool:
        """True while a time-dependent COMMAND hook (trajectory, stop ramp, replay) is registered."""
        return bool(self._hooks[Phase.COMMAND].fns)

    def check_open(self) -> None:
        """Raise :class:`RobotClosedError` after :meth:`stop`."""
        if self._closed:
            raise RobotClosedError(f"robot on backend {self.backend.name!r} is closed")

    # ------------------------------------------------------------ hooks
    def add_hook(self, phase: Phase, fn: Callable[..., Any], *, order: int = 0) -> HookHandle:
        """Call ``fn`` every tick in ``phase``, after hooks of lower ``order`` (ties: first registered first)."""
        if not isinstance(phase, Phase):
            raise InvalidValueError(f"phase must be an agentsdk.loop.Phase, got {phase!r}")
        handle = self._hooks[phase].add(fn, order)
        if phase is Phase.COMMAND and isinstance(self.clock, LockstepClock):
            self.clock.wakeup.set()  # an idle lockstep loop starts ticking again
        return handle

    def add_fault_listener(self, fn: FaultListener) -> HookHandle:
        """Call ``fn(exc)`` once if the control loop dies (backend fault, divergence)."""
        return self._fault_listeners.add(fn, 0)

    def install_sensor_gate(self, *, margin: float, floor: float, tolerance: float | None) -> SensorGate:
        """Pass every reading through a :class:`~agentsdk.plausibility.SensorGate` (the safety layer calls this).

        From then on the state holds each joint's last *plausible* reading: a value the physics
        cannot explain never reaches the state buffer (see :mod:`agentsdk.plausibility`).
        """
        st = self._state
        backend = self.backend
        # a backend that keeps Backend.reading_age (no override, none on the instance) reads the present:
        # the gate asks for no ages (two calls per tick fewer)
        current = type(backend).reading_age is Backend.reading_age and "reading_age" not in getattr(
            backend, "__dict__", ())
        gate = SensorGate(self.joints, st.position, st.velocity, st.effort, margin=margin, floor=floor,
                          tolerance=tolerance, period=self.period, age=None if current else self._reading_age,
                          changing=self.backend.frame_changing, changes=self.backend.frame_changes,
                          driven=self._driven)
        self.sensor_gate = gate
        return gate

    def _reading_age(self) -> np.ndarray | None:
        """The backend's reading ages as of the tick's own clock read (:meth:`_read`: no second read)."""
        origin = self._origin
        t = self._read_t
        self._read_t = math.nan  # used once: a reading without a tick time reads the clock
        return self.backend.reading_age(None if origin is None or t != t else origin + t)

    def _driven(self) -> np.ndarray:
        """Which joints have torque on now (the setpoint's enabled flags, none after an emergency stop)."""
        enabled = self._sp.enabled
        return enabled & (not self._torque_off)

    # ------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Open the backend, read the initial state, hold it, start the control loop task."""
        backend = self.backend
        await backend.open()  # closes the backend again and raises BackendStartError on failure
        problem = self._read_baseline()
        if problem:
            await backend.close()
            raise BackendStartError(f"{problem} at start")
        self.hold_current()
        backend.write(self._sp.view)
        self._spawn()

    def _spawn(self) -> None:
        # the task's own context, kept: an inline tick (LockstepClock.lend) runs the hooks in it too
        self._context = contextvars.copy_context()
        self._task = asyncio.get_running_loop().create_task(
            self._run_realtime() if self.realtime else self._run_lockstep(),
            name=f"agentsdk-{self.backend.name}-control", context=self._context,
        )

    async def stop(self) -> None:
        """Stop the control loop and close the backend. Idempotent; completes even if cancelled."""
        if self._closed:
            return
        self._closed = True
        task, self._task = self._task, None
        cancelled = False
        if task is not None:
            task.cancel()
            try:
                await asyncio.shield(asyncio.gather(task, return_exceptions=True))
            except asyncio.CancelledError:
                cancelled = True
        self.block_runner = None  # block lockstep ends with the loop (its runner has no task of its own)
        self.clock.fail(RobotClosedError(f"robot on backend {self.backend.name!r} is closed"), final=True)
        if isinstance(self.clock, RealtimeClock):
            self.clock.release()  # its timerfd (after fail: the pending sleepers got the reason)
        self._hooks[Phase.COMMAND].clear()
        try:
            await asyncio.shield(self.backend.close())
        except asyncio.CancelledError:
            cancelled = True
        if cancelled:
            raise asyncio.CancelledError

    def emergency_stop(self, category: int = 0) -> None:
        """Thread-safe: remove torque now; every later write is torque-off until :meth:`enable`."""
        with self._torque_lock:
            self._torque_off = True
            self._estops += 1
        self.backend.emergency_stop(category)

    async def enable(self, veto: Callable[[], BaseException | None] | None = None) -> None:
        """Re-arm the backend and hold the measured position with torque on.

        The loop keeps running while the backend re-arms (a bus backend awaits its motors'
        replies): a fault or an emergency stop that comes meanwhile stands, torque stays off,
        and this raises (:class:`BackendFault`, :class:`EStopActive`) instead of switching it on.
        ``veto``: asked under the torque lock, just before torque goes on; an exception it returns
        is raised instead (the safety layer's FAULT or latch, set by any thread meanwhile).
        """
        with self._torque_lock:
            estops = self._estops
        await self.backend.enable()
        if self._fault is not None:
            raise BackendFault(f"the control loop faulted while the backend was enabled ({self._fault}); "
                               "torque stays off") from self._fault
        self._read()
        with self._torque_lock:
            if self._estops != estops:
                raise EStopActive("an emergency stop came while the backend was enabled; torque stays off")
            refused = veto() if veto is not None else None
            if refused is not None:
                raise refused
            self.hold_current()
            self._torque_off = False

    async def recover(self) -> None:
        """Recover from a fault: backend ``_recover``, then restart the loop holding position, torque off."""
        if self._fault is None:
            return
        await self.backend.recover()
        problem = self._read_baseline()  # a simulator reset on purpose: not a jump to judge
        if problem:
            raise BackendFault(f"{problem} after recovering")
        self._fault = None
        self.clock.resume()
        self.hold_current()
        with self._torque_lock:
            self._torque_off = True  # stays limp until enable()
        self._sp.enabled[:] = False
        self._spawn()

    # ------------------------------------------------------------ the tick
    def _read_baseline(self) -> str:
        """Read the state as it is (start, recover); a problem in words if a value is not finite."""
        gate = self.sensor_gate
        if gate is None:
            self._read()
            return ""
        backend = self.backend
        q, v, e = backend.read()
        bad = gate.baseline(q, v, e, self.clock.now())
        if bad < 0:
            return ""
        src = backend.joint_source(bad)
        return (
            f"joint {self.names[bad]!r}{f' ({src})' if src else ''} reads a non-finite value (position "
            f"{float(q[bad])}, velocity {float(v[bad])}, effort {float(e[bad])}): sensor fault"
        )

    def _read(self, t: float | None = None) -> None:
        q, v, e = self.backend.read()
        gate = self.sensor_gate
        if gate is not None:
            if t is None:
                t = self.clock.now()
            self._read_t = t  # for _reading_age, right after this read
            gate.accept(q, v, e, t)
            return
        st = self._state
        st.position[...] = q  # [...] = is the cheapest in-place copy (np.copyto dispatches in Python)
        st.velocity[...] = v
        st.effort[...] = e

    def _before_step(self) -> None:
        """The tick up to the step: COMMAND hooks, LIMIT hooks, the torque-off rule, ``backend.write``."""
        sp, stv, t = self._sp, self._state.view, self.stamp
        command = self._command
        sp.acceleration.fill(0.0)  # a per-tick feed-forward: only this tick's writers set it
        if command.fns:
            for fn in command.fns:
                if fn(t, stv, sp) is False:
                    command.remove_fn(fn)
        for fn in self._limit.fns:
            fn(t, stv, sp)
        off = self._torque_off
        if off:
            sp.enabled[:] = False
        backend = self.backend
        backend.write(sp.view)
        if not off and self._torque_off:
            # an emergency stop from another thread landed during write: enforce it again
            backend.emergency_stop(0)

    async def _tick(self) -> None:
        self._before_step()
        await self.backend.step(self.period)

    def _after_tick(self) -> None:
        # one clock read per tick for the gate, the stamp, the hooks and the pacing (a read is a
        # system call where there is no vDSO, e.g. user-mode Linux)
        t = self.clock.now()
        self._read(t)
        self.stamp = t
        self.ticks += 1
        stv, spv = self._state.view, self._sp.view
        for fn in self._observe.fns:
            fn(t, stv, spv)

    async def _run_lockstep(self) -> None:
        """Lockstep: tick while every other task waits, many ticks per pass through the event loop.

        After :func:`_settle` (nothing else runnable), ticks run back to back as a
        *batch* without returning to the event loop, for as long as none of them makes
        another task runnable: a batch ends after the tick that wakes a sleeper
        (``clock.advance``), resolves a future someone awaits, schedules a callback or
        a task (the event loop's ready queue grew), leaves the loop idle, or after
        ``batch_seconds`` of wall time (asyncio timers and I/O, e.g. the stall
        watchdog's heartbeat, still run). Every tick runs every phase, so a batch is
        tick-for-tick what one tick per settle computes: nothing else could have run
        in between.
        """
        clock = self.clock
        assert isinstance(clock, LockstepClock)
        loop = asyncio.get_running_loop()
        ready = _ready_queue(loop)
        command, limit, observe = self._command, self._limit, self._observe
        backend = self.backend
        write, step, read = backend.write, backend.step, backend.read
        period = self.period
        sp, spv = self._sp, self._sp.view
        acceleration = sp.acceleration
        st, stv = self._state, self._state.view
        position, velocity, effort = st.position, st.velocity, st.effort
        advance, now = clock.advance, clock.now
        perf_counter = time.perf_counter
        # a behavior that sleeps one period per tick may run the ticks itself (LockstepClock.lend)
        lend = ready is not None and type(backend).step_never_suspends
        # the inline tick runs in this task's context (what the tick's hooks and the tasks they start see)
        clock.inline_tick = functools.partial(self._context.run, self._tick_inline, clock.advance) if lend else None
        park = False
        _lockstep_loops[loop] = _lockstep_loops.get(loop, 0) + 1
        try:
            while True:
                if park:
                    park = False
                    if await clock.lend(ready, self.batch_seconds):
                        return  # an inline tick faulted the loop (reported there)
                await _settle(loop, ready)
                idle_after = clock.next_deadline() is None
                if idle_after and not command.fns:
                    clock.wakeup.clear()
                    await clock.wakeup.wait()
                    continue
                budget = self.batch_seconds
                # without a ready queue to watch (uvloop), or with batching off: one tick per pass
                single = ready is None or budget <= 0.0
                n_ready = -1 if single else len(ready)
                end = perf_counter() + budget
                while True:
                    runner = self.block_runner
                    if runner is not None:
                        ran, woke_ = runner()  # a block of ticks, each what a tick here computes
                        if ran:
                            if woke_ or single or len(ready) != n_ready or perf_counter() >= end:
                                break
                            if idle_after and not command.fns:
                                break
                            continue
                    # one tick: _before_step, step, advance, _after_tick (inlined: this is the hot path)
                    t = self.stamp
                    acceleration.fill(0.0)  # a per-tick feed-forward: only this tick's writers set it
                    if command.fns:
                        for fn in command.fns:
                            if fn(t, stv, sp) is False:
                                command.remove_fn(fn)
                    for fn in limit.fns:
                        fn(t, stv, sp)
                    off = self._torque_off
                    if off:
                        sp.enabled[:] = False
                    write(spv)
                    if not off and self._torque_off:
                        backend.emergency_stop(0)  # an e-stop from another thread landed during write
                    await step(period)
                    woke = advance()
                    q, v, e = read()
                    t = now()
                    gate = self.sensor_gate
                    if gate is not None:
                        gate.accept(q, v, e, t)  # writes the plausible joints into the state rows
                    else:
                        position[...] = q  # [...] = is the cheapest in-place copy (np.copyto dispatches in Python)
                        velocity[...] = v
                        effort[...] = e
                    self.stamp = t
                    self.ticks += 1
                    for fn in observe.fns:
                        fn(t, stv, spv)
                    # end the batch when this tick made another task runnable, or went idle
                    if woke or single or len(ready) != n_ready or perf_counter() >= end:
                        # it woke the one sleeper, who sleeps one period per tick: lend it the ticks (not beside
                        # another lockstep robot: the two loops' settles decide how their ticks interleave)
                        park = (lend and not single and woke == 1 and clock.one_tick_sleeper
                                and clock.next_deadline() is None and _lockstep_loops[loop] == 1)
                        break
                    if idle_after and not command.fns:
                        break
        except asyncio.CancelledError as exc:
            if _cancelled_here():
                raise
            self._on_loop_fault(exc)  # a hook's CancelledError (or an awaited future's): the tick failed
        except Exception as exc:
            self._on_loop_fault(exc)
        finally:
            n = _lockstep_loops[loop] - 1
            if n:
                _lockstep_loops[loop] = n
            else:
                del _lockstep_loops[loop]

    def _tick_inline(self, advance: Callable[[], int]) -> bool:
        """One lockstep tick run in a behavior's sleep (:meth:`LockstepClock.lend`): the tick of :meth:`_run_lockstep`.

        False (nothing done) when the step may suspend (:meth:`Backend.step_runs_inline`). A
        fault ends the control loop as one in its own tick does (:meth:`_on_loop_fault`: torque off, the
        listeners told, the clock failed), so the sleeper gets it.
        """
        if not self.backend.step_runs_inline():
            return False  # a step replaced on a subclass or the instance (a test's fault injection) may suspend
        try:
            self._before_step()
            stepping = self.backend.step(self.period).__await__()
            # driven by iteration: a step that returns ends the loop at once (send() would raise a StopIteration
            # to catch; ~40 % of driving the step); one that yields instead comes here
            for _ in stepping:
                stepping.close()
                raise BackendFault(f"the step of backend {self.backend.name!r} ({type(self.backend).__qualname__}) "
                                   "suspended, but the backend declares step_never_suspends")
            advance()  # (wakes nobody: the one sleeper is the caller)
            self._after_tick()
        except (Exception, asyncio.CancelledError) as exc:  # (a hook's CancelledError is its failure: the
            self._on_loop_fault(exc)                          # sleeper's own cancel cannot land in a tick)
        return True

    async def _run_realtime(self) -> None:
        clock = self.clock
        period = self.period
        deadline = clock.now()
        try:
            while True:
                await self._tick()
                self._after_tick()
                deadline += period
                late = self.stamp - deadline  # (read at the end of the tick)
                if late > period:
                    # skip the missed periods instead of bursting to catch up
                    skipped = math.floor(late / period)
                    self.missed_deadlines += skipped
                    deadline += skipped * period
                await clock.sleep_until(deadline)
        except asyncio.CancelledError as exc:
            if _cancelled_here():
                raise
            self._on_loop_fault(exc)  # a hook's CancelledError (or an awaited future's): the tick failed
        except Exception as exc:
            self._on_loop_fault(exc)

    def _on_loop_fault(self, exc: BaseException) -> None:
        """The control loop died: remove torque and tell every fault listener."""
        if isinstance(exc, BackendFault):
            fault: BaseException = exc
        else:
            fault = BackendFault(f"control loop of backend {self.backend.name!r} failed: {exc!r}")
            fault.__cause__ = exc
        self._fault = fault
        log.error("control loop stopped: %s", fault)
        try:
            self.emergency_stop(0)
        except Exception:  # the hook must not mask the original fault
            log.exception("emergency stop hook failed")
        for listener in self._fault_listeners.fns:
            try:
                listener(fault)
            except Exception:
                log.exception("fault listener failed")
        self.clock.fail(fault)

    # ------------------------------------------------------------ setpoint writers
    def hold_current(self, joints: np.ndarray | None = None) -> None:
        """Position-hold at the measured position (all joints, or the given indices)."""
        sp, st = self._sp, self._state
        idx: Any = slice(None) if joints is None else joints
        sp.position[idx] = st.position[idx]
        sp.velocity[idx] = 0.0
        sp.acceleration[idx] = 0.0
        sp.effort[idx] = 0.0
        sp.kp[idx] = self.gain_p[idx]
        sp.kd[idx] = self.gain_d[idx]
        sp.enabled[idx] = True
        sp.mode[idx] = _POS
        sp.target[idx] = st.position[idx]

    def hold_at(self, joints: np.ndarray, positions: np.ndarray) -> None:
        """Position-hold the given joints at ``positions`` (zero velocity and feed-forward, default gains)."""
        sp = self._sp
        sp.position[joints] = positions
        sp.velocity[joints] = 0.0
        sp.acceleration[joints] = 0.0
        sp.effort[joints] = 0.0
        sp.kp[joints] = self.gain_p[joints]
        sp.kd[joints] = self.gain_d[joints]
        sp.enabled[joints] = True
        sp.mode[joints] = _POS
        sp.target[joints] = positions

    def damp(self, joints: np.ndarray, kd: np.ndarray | float) -> None:
        """Velocity mode at zero velocity with gain ``kd``: the joints only damp (no position hold)."""
        sp = self._sp
        sp.mode[joints] = _VEL
        sp.kp[joints] = 0.0
        sp.kd[joints] = kd
        sp.velocity[joints] = 0.0
        sp.acceleration[joints] = 0.0
        sp.effort[joints] = 0.0
        sp.target[joints] = 0.0

    def set_reference(self, joints: np.ndarray, positions: np.ndarray, velocities: np.ndarray) -> None:
        """Overwrite the desired position and velocity of position-mode joints (a stop's starting point)."""
        sp = self._sp
        sp.position[joints] = positions
        sp.velocity[joints] = velocities

    def remove_torque(self) -> None:
        """Torque off on every joint now (zero gains and feed-forward, the backend's emergency stop)."""
        sp = self._sp
        sp.enabled[:] = False
        sp.kp[:] = 0.0
        sp.kd[:] = 0.0
        sp.effort[:] = 0.0
        self.emergency_stop(0)

    def apply(
        self,
        mode: CommandMode,
        idx: np.ndarray,
        values: np.ndarray,
        vel: np.ndarray | None = None,
        eff: np.ndarray | None = None,
        *,
        position_now: np.ndarray | None = None,
    ) -> None:
        """Write an already-validated, already-limited command into the setpoint.

        ``position_now`` (position mode) is where the setpoint starts this tick when it
        differs from the commanded value (the safety layer ramps towards ``values``).
        """
        sp = self._sp
        sp.mode[idx] = ModeCode.of(mode)
        sp.enabled[idx] = True
        sp.acceleration[idx] = 0.0
        sp.target[idx] = values
        if mode == "position":
            sp.position[idx] = values if position_now is None else position_now
            sp.velocity[idx] = 0.0 if vel is None else vel
            sp.effort[idx] = 0.0 if eff is None else eff
            sp.kp[idx] = self.gain_p[idx]
            sp.kd[idx] = self.gain_d[idx]
        elif mode == "velocity":
            sp.position[idx] = self._state.position[idx]
            sp.velocity[idx] = values
            sp.effort[idx] = 0.0
            sp.kp[idx] = 0.0
            sp.kd[idx] = self.gain_v[idx]
        else:
            sp.position[idx] = self._state.position[idx]
            sp.velocity[idx] = 0.0
            sp.effort[idx] = values
            sp.kp[idx] = 0.0
            sp.kd[idx] = 0.0

    def apply_position_all(self, values: np.ndarray, position_now: np.ndarray) -> None:
        """:meth:`apply` of a position command to every joint in order, without feed-forward.

        The same setpoint as ``apply("position", every joint, values, position_now=position_now)``
        (zero velocity, effort and acceleration, the default gains, torque on, position mode),
        written as one copy of the whole setpoint block instead of a row write per field.
        """
        sp, block = self._sp, self._pos_all
        block[0] = position_now
        block[5] = values
        sp.block[...] = block
        # the mode and torque rows usually say so already (a behavior streaming poses): a bytes compare
        # costs half a write
        mode, enabled = sp.mode, sp.enabled
        if mode.tobytes() != self._pos_all_mode:
            mode[...] = _POS
        if enabled.tobytes() != self._pos_all_on:
            enabled[...] = True

    def snapshot(self) -> JointState:
        """The latest measured state as an immutable :class:`JointState` (private copies)."""
        return JointState.from_block(self.names, self._state.block.copy(), self.stamp)


def _readonly(values: Any) -> FloatArray:
    arr = np.array(values, dtype=np.float64)
    arr.flags.writeable = False
    return arr


#: default :attr:`ControlLoop.batch_seconds`: wall time a lockstep batch may run before the
#: control loop passes through the event loop again (s)
BATCH_SECONDS = 0.001


def _ready_queue(loop: asyncio.AbstractEventLoop) -> Any:
    """The event loop's queue of runnable callbacks (``BaseEventLoop._ready``), or None (see :func:`_settle`)."""
    ready = getattr(loop, "_ready", None)
    return ready if hasattr(ready, "__len__") else None


def _cancelled_here() -> bool:
    """The running task was cancelled: a ``CancelledError`` a tick hook raised, or that came from a future
    someone else cancelled, is not that, and would otherwise end the control loop without a fault.
    """
    task = asyncio.current_task()
    return task is None or task.cancelling() > 0


#: lockstep control loops running, per event loop (one alone may lend its ticks: LockstepClock.lend)
_lockstep_loops: dict[asyncio.AbstractEventLoop, int] = {}

#: lockstep control loops currently settling, per event loop (their own yields are not "work")
_settling: dict[asyncio.AbstractEventLoop, int] = {}


#: :func:`_settle`'s default ``ready``: look the queue up
_UNKNOWN: Any = object()


@types.coroutine
def _yield() -> Generator[None, None, None]:
    """Let every other ready callback run once: what ``asyncio.sleep(0)`` does, without its own coroutine."""
    yield


async def _settle(loop: asyncio.AbstractEventLoop, ready: Any = _UNKNOWN) -> None:
    """Yield until no other task on the event loop is ready to run.

    Lockstep time may only advance when every task is waiting, and asyncio has no
    public way to ask "is anything runnable?". CPython's ``BaseEventLoop`` keeps
    its ready queue in ``_ready`` (a deque of handles, stable since Python 3.4);
    this is the one place the SDK reads a private asyncio attribute, because
    without it lockstep time would have to guess when the behavior has finished
    reacting (it would not be deterministic). Event loops without ``_ready``
    (uvloop) fall back to yielding a fixed number of times, which is correct for
    chains of up to 64 hand-offs per tick. Tested in tests/test_core.py.

    Several lockstep robots on one loop each yield here: their own settle steps
    are discounted, or they would keep each other spinning.
    """
    _settling[loop] = _settling.get(loop, 0) + 1
    try:
        await _yield()
        if ready is _UNKNOWN:
            ready = _ready_queue(loop)
        if ready is None:
            for _ in range(64):
                await asyncio.sleep(0)
            return
        spins = 0
        while len(ready) > _settling[loop] - 1 and spins < 100_000:
            await _yield()
            spins += 1
    finally:
        n = _settling[loop] - 1
        if n:
            _settling[loop] = n
        else:
            del _settling[loop]
