"""Conformance fixture for the CAN backend: the MIT motor emulator on python-can's virtual bus."""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import AsyncIterator
from typing import Any, ClassVar

import can

from agentsdk.robot import Robot, connect
from agentsdk.testing import BackendConformance

from .emulator import MotorEmulator

__all__ = ["EmulatedCanConformance"]

_channels = itertools.count()


class EmulatedCanConformance(BackendConformance):
    """Runs the conformance kit on ``can`` against in-process emulated motors."""

    backend: ClassVar[str] = "can"
    robot: ClassVar[str] = "mit_leg"
    settle_time: ClassVar[float] = 3.0
    #: the in-process emulator shares the GIL and 2 CPUs with the control loop: under load
    #: it answers late for tens of cycles with nothing wrong, so escalate only on real loss.
    #: Its free motors have no gravity, so the host's gravity feed-forward is off.
    connect_options: ClassVar[dict[str, Any]] = {"max_missed_replies": 250, "gravity_compensation": False}

    @contextlib.asynccontextmanager
    async def open_robot(self, **overrides: Any) -> AsyncIterator[Robot]:
        """Connect a robot to emulated motors on a fresh python-can virtual bus (for the conformance kit)."""
        channel = f"agentsdk-conformance-{next(_channels)}"
        bus = can.Bus(interface="virtual", channel=channel)
        emulator = MotorEmulator.from_robot(self.robot, bus)
        emulator.start()
        try:
            opts = {"interface": "virtual", "channel": channel, **self.connect_options, **overrides}
            async with connect(self.backend, robot=self.robot, **opts) as robot:
                yield robot
        finally:
            emulator.stop()
            bus.shutdown()
