"""Conformance fixture for the ``ros2`` backend: a robot served in-process (:func:`agentsdk.ros2.expose`).

The served robot (``served_backend``, lockstep) and the ``ros2`` robot driving it share the
event loop; DDS traffic stays on 127.0.0.1, on a random domain per robot.
"""

from __future__ import annotations

import contextlib
import random
from collections.abc import AsyncIterator
from typing import Any, ClassVar

from agentsdk.robot import Robot, connect
from agentsdk.ros2 import expose
from agentsdk.testing import BackendConformance

__all__ = ["ServedRos2Conformance"]


class ServedRos2Conformance(BackendConformance):
    """Runs the conformance kit on ``ros2`` against an agentsdk robot served on a loopback DDS domain."""

    backend: ClassVar[str] = "ros2"
    robot: ClassVar[str] = "arm3"
    #: lockstep: each tick steps the served robot by one period (and :meth:`capabilities` needs no remote)
    realtime: ClassVar[bool | None] = False
    #: the backend of the served robot
    served_backend: ClassVar[str] = "mock"
    #: the client's safety overrides (a loaded test machine runs two robots and DDS on one event loop)
    safety: ClassVar[dict[str, Any]] = {"stall_timeout": 5.0}

    @contextlib.asynccontextmanager
    async def open_robot(self, **overrides: Any) -> AsyncIterator[Robot]:
        """Serve ``robot`` on ``served_backend`` and connect ``ros2`` to it (for the conformance kit)."""
        domain_id = random.SystemRandom().randint(30, 230)
        namespace = "/conformance"
        safety = overrides.pop("safety", self.safety)
        opts = {"namespace": namespace, "domain_id": domain_id, **self.connect_options, **overrides}
        async with (
            connect(self.served_backend, robot=self.robot, realtime=self.realtime,
                    safety={"stall_timeout": 5.0}) as served,
            expose(served, namespace, domain_id=domain_id),
            connect(self.backend, robot=self.robot, realtime=self.realtime, safety=safety, **opts) as robot,
        ):
            yield robot
