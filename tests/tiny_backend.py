"""A tiny backend defined in the test suite: the whole Controller contract in ~50 lines."""

from __future__ import annotations

import numpy as np

from agentsdk import Capabilities, Controller, Setpoint, StateBuffer


class TinyController(Controller):
    """An ideal first-order servo, defined here to show the whole backend contract."""

    name = "tiny"
    capabilities = Capabilities(modes=frozenset({"position", "velocity", "effort"}), lockstep=True,
                                realtime=True, deterministic=True)

    async def _open(self) -> None:
        n = len(self.joints)
        self.q = np.zeros(n)
        self.v = np.zeros(n)
        self.tau = np.zeros(n)
        self._sp = Setpoint(n)

    async def _close(self) -> None:
        pass

    def _write(self, sp: Setpoint) -> None:
        for a in ("position", "velocity", "effort", "kp", "kd", "enabled"):
            np.copyto(getattr(self._sp, a), getattr(sp, a))

    async def _step(self, dt: float) -> None:
        sp = self._sp
        tau = sp.kp * (sp.position - self.q) + sp.kd * (sp.velocity - self.v) + sp.effort
        tau = np.where(sp.enabled, np.clip(tau, -self.max_effort, self.max_effort), 0.0)
        self.tau = tau
        # critically damped unit-inertia joint, integrated semi-implicitly in 10 substeps
        h = dt / 10
        for _ in range(10):
            acc = sp.kp * (sp.position - self.q) + sp.kd * (sp.velocity - self.v) + sp.effort
            acc = np.where(sp.enabled, np.clip(acc, -self.max_effort, self.max_effort), -5.0 * self.v)
            self.v = self.v + h * acc / 0.01
            self.q = np.clip(self.q + h * self.v, self.lower, self.upper)

    def _read(self, out: StateBuffer) -> None:
        out.position[:] = self.q
        out.velocity[:] = self.v
        out.effort[:] = self.tau

    def _emergency_stop(self, category: int) -> None:
        pass


