"""Mock backend, like ros2_control's mock components: no physics, fast and deterministic.

Each control period the measured state follows the servo setpoint:

* position mode: the position moves to the setpoint (ideally, or through a
  first-order lag with time constant ``lag``), velocity is the finite difference;
* velocity mode: the velocity follows the setpoint (same lag) and is integrated;
* effort mode: ``effort / inertia`` is integrated as an acceleration;
* torque off (e-stop category 0 or disabled joints): the joint coasts to rest
  with ``coast_damping``.

Positions stay within the URDF limits like a joint against its hard stop.
Fault knobs for tests (options or attributes at runtime): ``lag`` (s),
``frozen_joints`` (names that never move), ``read_error`` (the next ``_read``
raises :class:`BackendFault`), ``step_error``.
"""

from __future__ import annotations

import math
import threading

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from agentsdk.backend import Backend, Capabilities, JointReading, ModeCode, SetpointView
from agentsdk.errors import BackendFault, ConfigurationError
from agentsdk.types import MODES, CommandMode

__all__ = ["MockBackend", "MockController", "MockOptions"]

#: mode codes as plain ints (numpy compares arrays with an IntEnum member slowly, through enum attribute lookups)
_POS, _VEL, _EFF = int(ModeCode.POSITION), int(ModeCode.VELOCITY), int(ModeCode.EFFORT)


class MockOptions(BaseModel):
    """robot.yaml ``backends.mock`` / ``connect("mock", ...)`` options (every number finite)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    #: first-order lag time constant (s); 0 = ideal tracking
    lag: float = Field(default=0.0, ge=0.0)
    #: joints that never move (fault injection)
    frozen_joints: tuple[str, ...] = ()
    #: inertia used to integrate effort commands (kg·m²); tiny values would overflow the integration
    inertia: float = Field(default=0.05, ge=1e-9)
    #: damping of a joint with torque off (1/s)
    coast_damping: float = Field(default=20.0, ge=0.0)
    #: fail the next read/step with a BackendFault (fault injection)
    read_error: bool = False
    step_error: bool = False
    #: supported command modes (to test capability gating)
    modes: tuple[CommandMode, ...] = MODES


class MockBackend(Backend):
    """A kinematic stand-in for fast tests.

    Ideal or first-order tracking, effort integrated on a fixed inertia, fault injection.
    """

    name = "mock"
    step_never_suspends = True  # its _step computes the step and returns
    capabilities = Capabilities(
        modes=frozenset(MODES), lockstep=True, realtime=True, deterministic=True
    )
    options_model = MockOptions

    def __init__(self, *args: object, **kw: object) -> None:
        super().__init__(*args, **kw)  # type: ignore[arg-type]
        opts: MockOptions = self.options
        unknown = [n for n in opts.frozen_joints if n not in self.index]
        if unknown:
            raise ConfigurationError(f"mock: frozen_joints names unknown joint(s) {unknown}")
        bad = [m for m in opts.modes if m not in MODES]
        if bad:
            raise ConfigurationError(f"mock: unknown modes {bad}")
        # per-instance capabilities (the modes knob lets tests build a restricted backend)
        self.capabilities = Capabilities(
            modes=frozenset(opts.modes), lockstep=True, realtime=True, deterministic=True
        )
        self.lag = opts.lag
        self.frozen = np.zeros(len(self.joints), dtype=bool)
        for n in opts.frozen_joints:
            self.frozen[self.index[n]] = True
        self.read_error = opts.read_error
        self.step_error = opts.step_error
        self._lock = threading.Lock()

    async def _open(self) -> None:
        n = len(self.joints)
        self._q = self.initial_positions.copy()
        self._v = np.zeros(n)
        self._tau = np.zeros(n)
        self._sp_mode = np.zeros(n, dtype=np.int8)
        self._sp_q = self._q.copy()
        self._sp_v = np.zeros(n)
        self._sp_tau = np.zeros(n)
        self._enabled = np.ones(n, dtype=bool)

    async def _close(self) -> None:
        if hasattr(self, "_enabled"):
            self._enabled[:] = False

    def _write(self, sp: SetpointView) -> None:
        with self._lock:
            np.copyto(self._sp_mode, sp.mode)
            np.copyto(self._sp_q, sp.position)
            np.copyto(self._sp_v, sp.velocity)
            np.copyto(self._sp_tau, sp.effort)
            np.copyto(self._enabled, sp.enabled)

    async def _step(self, dt: float) -> None:
        if self.step_error:
            self.step_error = False
            raise BackendFault("mock: injected step error")
        with self._lock:
            q, v = self._q, self._v
            alpha = 1.0 if self.lag == 0.0 else 1.0 - math.exp(-dt / self.lag)
            mode, en = self._sp_mode, self._enabled
            q_prev = q.copy()
            pos = en & (mode == _POS)
            vel = en & (mode == _VEL)
            eff = en & (mode == _EFF)
            off = ~en
            # position: move toward the setpoint
            q_new = q + alpha * (self._sp_q - q)
            # velocity: velocity follows setpoint, integrate
            v_vel = v + alpha * (self._sp_v - v)
            # effort: integrate acceleration
            v_eff = v + dt * self._sp_tau / self.options.inertia
            v_off = v * math.exp(-self.options.coast_damping * dt)
            v_next = np.where(vel, v_vel, np.where(eff, v_eff, np.where(off, v_off, v)))
            q_next = np.where(pos, q_new, q + v_next * dt)
            q_next = np.clip(q_next, self.lower, self.upper)
            q_next = np.where(self.frozen, q_prev, q_next)
            self._v = np.where(pos | self.frozen | (q_next != q + v_next * dt), (q_next - q_prev) / dt, v_next)
            self._q = q_next
            self._tau = np.where(eff, self._sp_tau, 0.0)

    def _read(self) -> JointReading:
        if self.read_error:
            self.read_error = False
            raise BackendFault("mock: injected read error")
        with self._lock:
            return self._q, self._v, self._tau

    def _emergency_stop(self, category: int) -> None:
        with self._lock:
            if hasattr(self, "_enabled"):
                self._enabled[:] = False

    async def _recover(self) -> None:
        with self._lock:
            self._v[:] = 0.0

#: the former name of :class:`MockBackend` (deprecated: import MockBackend)
MockController = MockBackend
