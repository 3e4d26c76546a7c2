"""ROS 2 without ROS: serve a robot on the ROS 2 graph over DDS (``pip install 'agentsdk[ros2]'``).

:func:`expose` makes a robot a ROS 2 node (joint_states, tf, robot_description, clock,
diagnostics, e-stop services, a JointTrajectoryController with its FollowJointTrajectory
action) that RViz, Foxglove, MoveIt and the ``ros2`` CLI see and drive; ``agentsdk serve``
does it from the command line. :mod:`agentsdk.ros2.msgs` holds the ROS message types.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ..errors import BackendUnavailableError

if TYPE_CHECKING:
    from .server import JTC, RosFace, expose

__all__ = ["JTC", "RosFace", "expose"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        try:
            from . import server
        except ImportError as exc:  # pragma: no cover - depends on the environment
            if exc.name and exc.name.startswith("cyclonedds"):
                raise BackendUnavailableError(
                    "the ROS 2 face needs the cyclonedds package: pip install 'agentsdk[ros2]'"
                ) from exc
            raise
        return getattr(server, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
