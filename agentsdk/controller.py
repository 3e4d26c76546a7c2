"""The backend side of the SDK: an abstract :class:`Controller`.

A backend implements a few narrow hooks; everything else (name mapping,
validation, the control loop, the clocks, logging, the safety layer hooks)
lives here once, as python-can does with ``BusABC.recv`` -> ``_recv_internal``.

Hooks a backend implements::

    async def _open(self) -> None            # connect / build the simulation
    async def _close(self) -> None           # leave actuators safe; idempotent
    def _write(self, sp: Setpoint) -> None   # apply the per-joint servo setpoint
    async def _step(self, dt: float) -> None # advance one control period / bus cycle
    def _read(self, out: StateBuffer) -> None  # latest measured state
    def _emergency_stop(self, category: int) -> None  # sync, thread-safe, no event loop

The joint servo law every backend implements is the MIT/ros2_control one::

    effort = kp * (q_des - q) + kd * (v_des - v) + effort_ff   (clamped to max_effort)

and a joint with ``enabled == False`` produces no torque. Position, velocity and
effort command modes are all expressed in that law (velocity: kp = 0; effort:
kp = kd = 0), so a backend needs only one code path.

The control cycle (one tick, like ros2_control's read/update/write)::

    updaters (trajectories, hold) write the setpoint for time t
    -> safety layer filters the setpoint
    -> _write(setpoint) -> await _step(dt) -> time advances -> _read(state)
    -> safety layer checks the new state (watchdogs, divergence)
"""

from __future__ import annotations

import asyncio
import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from pydantic import BaseModel, ValidationError

from .clock import Clock, LockstepClock, RealtimeClock
from .errors import (
    AgentSDKError,
    BackendFault,
    BackendStartError,
    ConfigurationError,
    InvalidValueError,
    RobotClosedError,
    UnknownJointError,
    UnsupportedModeError,
)
from .types import MODES, CommandMode, JointCommand, JointInfo, JointState

if TYPE_CHECKING:
    from .config import RobotConfig
    from .description import RobotDescription

__all__ = ["Capabilities", "Controller", "Setpoint", "StateBuffer"]

log = logging.getLogger("agentsdk.controller")

MODE_CODES: dict[str, int] = {m: i for i, m in enumerate(MODES)}


@dataclass(frozen=True, slots=True)
class Capabilities:
    """What a backend declares; the conformance kit gates its tests on this."""

    modes: frozenset[CommandMode]
    lockstep: bool
    realtime: bool
    #: True when the same inputs always give bit-identical states (lockstep sims)
    deterministic: bool = False


class StateBuffer:
    """Mutable measured-state arrays the backend fills in ``_read``."""

    __slots__ = ("effort", "position", "velocity")

    def __init__(self, n: int) -> None:
        self.position = np.zeros(n)
        self.velocity = np.zeros(n)
        self.effort = np.zeros(n)


class Setpoint:
    """Per-joint servo setpoint, in ``robot.joints`` order (mutable, reused every cycle)."""

    __slots__ = ("effort", "enabled", "kd", "kp", "mode", "position", "velocity")

    def __init__(self, n: int) -> None:
        self.position = np.zeros(n)
        self.velocity = np.zeros(n)
        self.effort = np.zeros(n)
        self.kp = np.zeros(n)
        self.kd = np.zeros(n)
        self.enabled = np.ones(n, dtype=bool)
        #: command mode code per joint (index into agentsdk.types.MODES)
        self.mode = np.zeros(n, dtype=np.int8)


#: an updater runs every control tick; returns False once it is finished
Updater = Callable[[float, StateBuffer, Setpoint], bool]


class Controller(ABC):
    """Base class of every backend. Users never see it: they get a ``Robot``."""

    #: entry-point name, set by subclasses
    name: ClassVar[str] = ""
    capabilities: ClassVar[Capabilities]
    #: pydantic model validating the backend options (robot.yaml ``backends.<name>`` + connect kwargs)
    options_model: ClassVar[type[BaseModel] | None] = None

    def __init__(
        self,
        config: RobotConfig,
        description: RobotDescription,
        joints: tuple[JointInfo, ...],
        *,
        realtime: bool | None = None,
        **options: Any,
    ) -> None:
        caps = self.capabilities
        if realtime is None:
            realtime = not caps.lockstep
        if realtime and not caps.realtime:
            raise ConfigurationError(f"backend {self.name!r} does not support realtime=True")
        if not realtime and not caps.lockstep:
            raise ConfigurationError(f"backend {self.name!r} runs in real time only; lockstep is not supported")
        self.config = config
        self.description = description
        self.joints = joints
        self.realtime = realtime
        self.names: tuple[str, ...] = tuple(j.name for j in joints)
        self.index: dict[str, int] = {n: i for i, n in enumerate(self.names)}
        self.period = config.control_period
        merged = {**config.backend_options(self.name), **options}
        self.options = self._validate_options(merged)

        n = len(joints)
        self.state = StateBuffer(n)
        self.stamp = 0.0
        self.setpoint = Setpoint(n)
        #: last directly commanded value per joint (before ramping), see setpoint_target()
        self.target = np.zeros(n)
        gains = [config.gains_for(j.name) for j in joints]
        self.gain_p = np.array([g.p for g in gains])
        self.gain_d = np.array([g.d for g in gains])
        self.gain_v = np.array([g.d if g.v is None else g.v for g in gains])
        self.max_effort = np.array([j.max_effort for j in joints])
        self.lower = np.array([j.lower for j in joints])
        self.upper = np.array([j.upper for j in joints])
        self.max_velocity = np.array([j.max_velocity for j in joints])

        self.clock: Clock = RealtimeClock() if realtime else LockstepClock(self.period)
        self._updaters: list[Updater] = []
        #: called after every tick with the fresh state (safety layer, feedback)
        self.tick_hooks: list[Callable[[float, StateBuffer], None]] = []
        #: called on every setpoint before it is written (safety layer limits)
        self.setpoint_filters: list[Callable[[float, StateBuffer, Setpoint], None]] = []
        #: called once if the control loop dies (safety layer -> FAULT)
        self.fault_hooks: list[Callable[[BaseException], None]] = []
        self._loop_task: asyncio.Task[None] | None = None
        self._fault: BaseException | None = None
        #: set by emergency_stop (any thread); every write is torque-off until enable_hook()
        self.torque_disabled = False
        self._open_done = False
        self._closed = False
        self.lock = asyncio.Lock()
        self.ticks = 0
        self.missed_deadlines = 0

    # ------------------------------------------------------------------ hooks
    @abstractmethod
    async def _open(self) -> None:
        """Connect to the hardware or build the simulation. Raise BackendStartError on failure."""

    @abstractmethod
    async def _close(self) -> None:
        """Leave actuators safe and release resources. Must tolerate being called once after a failed open."""

    @abstractmethod
    def _write(self, sp: Setpoint) -> None:
        """Apply the servo setpoint (called once per tick, before ``_step``)."""

    @abstractmethod
    async def _step(self, dt: float) -> None:
        """Advance one control period (simulation step, or one bus cycle)."""

    @abstractmethod
    def _read(self, out: StateBuffer) -> None:
        """Fill ``out`` with the latest measured joint state."""

    @abstractmethod
    def _emergency_stop(self, category: int) -> None:
        """Synchronous, thread-safe stop called from any thread (watchdog).

        Category 0 must remove actuator torque at once, without the event loop.
        Categories 1 and 2 are driven by the safety layer through setpoints;
        this hook is only asked to do what the backend can do without the loop.
        """

    async def _enable(self) -> None:  # noqa: B027 - optional hook
        """Optional: re-arm actuators after an e-stop (CAN: enter motor mode again)."""

    async def _recover(self) -> None:
        """Optional: bring a faulted backend back to a usable state (sims: reset the world)."""
        raise BackendFault(f"backend {self.name!r} cannot recover from a fault; close and reconnect")

    # ----------------------------------------------------------- lifecycle
    def emergency_stop(self, category: int = 0) -> None:
        """Thread-safe: remove torque now (every later write is torque-off until ``enable_hook``)."""
        self.torque_disabled = True
        self._emergency_stop(category)

    async def enable_hook(self) -> None:
        await self._enable()
        self.torque_disabled = False

    async def recover(self) -> None:
        """Recover from a fault: backend ``_recover``, then restart the control loop holding position."""
        if self._fault is None:
            return
        await self._recover()
        self._fault = None
        self._read(self.state)
        self.hold_current()
        self.setpoint.enabled[:] = False  # stays limp until enable()
        self.torque_disabled = True
        self._loop_task = asyncio.get_running_loop().create_task(
            self._run_realtime() if self.realtime else self._run_lockstep(), name=f"agentsdk-{self.name}-control"
        )

    def _validate_options(self, options: dict[str, Any]) -> Any:
        model = self.options_model
        if model is None:
            if options:
                raise ConfigurationError(
                    f"backend {self.name!r} takes no options, got {', '.join(sorted(options))}"
                )
            return None
        try:
            return model(**options)
        except ValidationError as exc:
            raise ConfigurationError(f"invalid options for backend {self.name!r}:\n{exc}") from exc

    async def start(self) -> None:
        """Open the backend, read the initial state, hold it, start the control loop."""
        try:
            await self._open()
        except asyncio.CancelledError:
            await self._close()
            raise
        except AgentSDKError:
            await self._close()
            raise
        except Exception as exc:
            await self._close()
            raise BackendStartError(f"backend {self.name!r} failed to start: {exc}") from exc
        self._open_done = True
        self._read(self.state)
        self.hold_current()
        self._write(self.setpoint)
        self._loop_task = asyncio.get_running_loop().create_task(
            self._run_realtime() if self.realtime else self._run_lockstep(), name=f"agentsdk-{self.name}-control"
        )

    async def stop(self) -> None:
        """Stop the control loop and close the backend. Idempotent; completes even if cancelled."""
        if self._closed:
            return
        self._closed = True
        task, self._loop_task = self._loop_task, None
        cancelled = False
        if task is not None:
            task.cancel()
            try:
                await asyncio.shield(asyncio.gather(task, return_exceptions=True))
            except asyncio.CancelledError:
                cancelled = True
        if isinstance(self.clock, LockstepClock):
            self.clock.cancel_all(RobotClosedError("robot closed"))
        for upd in list(self._updaters):
            self.remove_updater(upd)
        try:
            await asyncio.shield(self._close())
        except asyncio.CancelledError:
            cancelled = True
        if cancelled:
            raise asyncio.CancelledError

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def fault(self) -> BaseException | None:
        return self._fault

    def check_open(self) -> None:
        if self._closed:
            raise RobotClosedError(f"robot on backend {self.name!r} is closed")

    # ------------------------------------------------------------ the loop
    def add_updater(self, updater: Updater) -> None:
        self._updaters.append(updater)
        if isinstance(self.clock, LockstepClock):
            self.clock.wakeup.set()

    @property
    def busy(self) -> bool:
        """True while a time-dependent activity (trajectory, stop ramp) runs."""
        return bool(self._updaters)

    def remove_updater(self, updater: Updater) -> None:
        try:
            self._updaters.remove(updater)
        except ValueError:
            pass

    async def _tick(self) -> None:
        sp = self.setpoint
        t = self.stamp
        st = self.state
        if self._updaters:
            for upd in tuple(self._updaters):
                if not upd(t, st, sp):
                    self.remove_updater(upd)
        for f in self.setpoint_filters:
            f(t, st, sp)
        if self.torque_disabled:
            sp.enabled[:] = False
        self._write(sp)
        await self._step(self.period)

    def _after_tick(self) -> None:
        self._read(self.state)
        self.stamp = self.clock.now()
        self.ticks += 1
        for hook in self.tick_hooks:
            hook(self.stamp, self.state)

    async def _run_lockstep(self) -> None:
        clock = self.clock
        assert isinstance(clock, LockstepClock)
        loop = asyncio.get_running_loop()
        try:
            while True:
                await _settle(loop)
                if clock.next_deadline() is None and not self._updaters:
                    clock.wakeup.clear()
                    await clock.wakeup.wait()
                    continue
                await self._tick()
                clock.advance()
                self._after_tick()
        except asyncio.CancelledError:
            raise
        except BaseException as exc:
            self._on_loop_fault(exc)

    async def _run_realtime(self) -> None:
        clock = self.clock
        period = self.period
        deadline = clock.now()
        try:
            while True:
                await self._tick()
                self._after_tick()
                deadline += period
                late = clock.now() - deadline
                if late > period:
                    # skip the missed periods instead of bursting to catch up
                    skipped = math.floor(late / period)
                    self.missed_deadlines += skipped
                    deadline += skipped * period
                await clock.sleep_until(deadline)
        except asyncio.CancelledError:
            raise
        except BaseException as exc:
            self._on_loop_fault(exc)

    def _on_loop_fault(self, exc: BaseException) -> None:
        """The control loop died: stop the actuators and fail every waiter."""
        if not isinstance(exc, BackendFault):
            fault: BaseException = BackendFault(f"control loop of backend {self.name!r} failed: {exc!r}")
            fault.__cause__ = exc
        else:
            fault = exc
        self._fault = fault
        log.error("control loop stopped: %s", fault)
        try:
            self.emergency_stop(0)
        except Exception:  # the hook must not mask the original fault
            log.exception("emergency stop hook failed")
        for hook in self.fault_hooks:
            hook(fault)
        if isinstance(self.clock, LockstepClock):
            self.clock.cancel_all(fault)

    # ------------------------------------------------------------ commands
    def hold_current(self, joints: np.ndarray | None = None) -> None:
        """Position-hold at the measured position (all joints, or the given indices)."""
        sp, st = self.setpoint, self.state
        idx = slice(None) if joints is None else joints
        sp.position[idx] = st.position[idx]
        sp.velocity[idx] = 0.0
        sp.effort[idx] = 0.0
        sp.kp[idx] = self.gain_p[idx]
        sp.kd[idx] = self.gain_d[idx]
        sp.enabled[idx] = True
        sp.mode[idx] = MODE_CODES["position"]
        self.target[idx] = st.position[idx]

    def resolve(self, cmd: JointCommand) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Map a command onto joint indices; validate mode, names, length, finiteness.

        Returns ``(indices, values, velocity_ff, effort_ff)``. Raises a
        :class:`CommandRejected` subclass; nothing is modified.
        """
        if not isinstance(cmd, JointCommand):
            raise InvalidValueError(f"expected a JointCommand, got {type(cmd).__name__}")
        if cmd.mode not in self.capabilities.modes:
            raise UnsupportedModeError(
                f"backend {self.name!r} does not support {cmd.mode!r} commands "
                f"(supported: {', '.join(sorted(self.capabilities.modes))})"
            )
        idx, values = self._map(cmd.values, "values")
        vel = eff = None
        if cmd.velocity is not None:
            vidx, vel = self._map(cmd.velocity, "velocity")
            if not np.array_equal(vidx, idx):
                raise InvalidValueError("velocity feed-forward must name the same joints as values")
        if cmd.effort is not None:
            eidx, eff = self._map(cmd.effort, "effort")
            if not np.array_equal(eidx, idx):
                raise InvalidValueError("effort feed-forward must name the same joints as values")
        return idx, values, vel, eff

    def _map(self, values: Mapping[str, float] | tuple[float, ...], what: str) -> tuple[np.ndarray, np.ndarray]:
        if isinstance(values, Mapping):
            if not values:
                raise InvalidValueError(f"{what}: empty command")
            try:
                idx = np.fromiter((self.index[k] for k in values), dtype=np.intp, count=len(values))
            except KeyError as exc:
                raise UnknownJointError(
                    f"unknown joint {exc.args[0]!r}; this robot's joints are: {', '.join(self.names)}"
                ) from None
            arr = np.fromiter(values.values(), dtype=np.float64, count=len(values))
        else:
            if len(values) != len(self.names):
                raise InvalidValueError(
                    f"{what}: expected {len(self.names)} values (one per joint: {', '.join(self.names)}), "
                    f"got {len(values)}"
                )
            idx = np.arange(len(self.names))
            arr = np.asarray(values, dtype=np.float64)
        bad = ~np.isfinite(arr)
        if bad.any():
            j = int(idx[int(np.argmax(bad))])
            raise InvalidValueError(f"{what}: non-finite value {arr[bad][0]!r} for joint {self.names[j]!r}")
        return idx, arr

    def apply(
        self,
        mode: CommandMode,
        idx: np.ndarray,
        values: np.ndarray,
        vel: np.ndarray | None = None,
        eff: np.ndarray | None = None,
    ) -> None:
        """Write an already-validated, already-limited command into the setpoint."""
        sp = self.setpoint
        sp.mode[idx] = MODE_CODES[mode]
        sp.enabled[idx] = True
        self.target[idx] = values
        if mode == "position":
            sp.position[idx] = values
            sp.velocity[idx] = 0.0 if vel is None else vel
            sp.effort[idx] = 0.0 if eff is None else eff
            sp.kp[idx] = self.gain_p[idx]
            sp.kd[idx] = self.gain_d[idx]
        elif mode == "velocity":
            sp.position[idx] = self.state.position[idx]
            sp.velocity[idx] = values
            sp.effort[idx] = 0.0
            sp.kp[idx] = 0.0
            sp.kd[idx] = self.gain_v[idx]
        else:
            sp.position[idx] = self.state.position[idx]
            sp.velocity[idx] = 0.0
            sp.effort[idx] = values
            sp.kp[idx] = 0.0
            sp.kd[idx] = 0.0

    def setpoint_target(self) -> np.ndarray:
        """The last commanded value per joint (position, velocity or effort, per its mode)."""
        return self.target.copy()

    def snapshot(self) -> JointState:
        st = self.state
        return JointState._trusted(self.names, st.position.copy(), st.velocity.copy(), st.effort.copy(), self.stamp)


#: lockstep control loops currently settling, per event loop (their own yields are not "work")
_settling: dict[asyncio.AbstractEventLoop, int] = {}


async def _settle(loop: asyncio.AbstractEventLoop) -> None:
    """Yield until no other task on the loop is ready to run.

    Lockstep time may only advance when every task is waiting. CPython's event
    loop keeps its ready queue in ``_ready``; where that is absent we fall back
    to yielding a fixed number of times. Several lockstep robots on one loop
    each yield here: their settle steps are discounted, or they would keep each
    other spinning.
    """
    _settling[loop] = _settling.get(loop, 0) + 1
    try:
        await asyncio.sleep(0)
        ready = getattr(loop, "_ready", None)
        if ready is None:
            for _ in range(64):
                await asyncio.sleep(0)
            return
        spins = 0
        while len(ready) > _settling[loop] - 1 and spins < 100_000:
            await asyncio.sleep(0)
            spins += 1
    finally:
        n = _settling[loop] - 1
        if n:
            _settling[loop] = n
        else:
            del _settling[loop]
