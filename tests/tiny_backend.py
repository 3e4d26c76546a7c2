"""A tiny backend defined in the test suite: the whole backend contract (agentsdk.backend) in under 60 lines."""

from __future__ import annotations

import threading

import numpy as np

from agentsdk import Backend, Capabilities, JointReading, SetpointView


class TinyController(Backend):
    """An ideal servo on unit-inertia-per-100 joints, integrated semi-implicitly."""

    name = "tiny"
    capabilities = Capabilities(modes=frozenset({"position", "velocity", "effort"}), lockstep=True,
                                realtime=True, deterministic=True)

    async def _open(self) -> None:
        n = len(self.joints)
        self.q, self.v, self.tau = self.initial_positions.copy(), np.zeros(n), np.zeros(n)
        self.sp = {k: np.zeros(n) for k in ("position", "velocity", "effort", "kp", "kd")}
        self.on = np.zeros(n, dtype=bool)
        self.lock = threading.Lock()  # _emergency_stop may come from another thread

    async def _close(self) -> None:
        self.on[:] = False

    def _write(self, sp: SetpointView) -> None:
        with self.lock:
            for k, arr in self.sp.items():
                np.copyto(arr, getattr(sp, k))
            np.copyto(self.on, sp.enabled)

    async def _step(self, dt: float) -> None:
        s, h = self.sp, dt / 10
        for _ in range(10):
            tau = s["kp"] * (s["position"] - self.q) + s["kd"] * (s["velocity"] - self.v) + s["effort"]
            self.tau = np.where(self.on, np.clip(tau, -self.max_effort, self.max_effort), 0.0)
            self.v = self.v + h * np.where(self.on, self.tau, -5.0 * self.v) / 0.01
            self.q = np.clip(self.q + h * self.v, self.lower, self.upper)

    def _read(self) -> JointReading:
        return self.q, self.v, self.tau

    def _emergency_stop(self, category: int) -> None:
        with self.lock:
            self.on[:] = False
