"""Trajectory offload: an optional backend capability for robots whose own controller runs a whole trajectory.

A backend that drives a remote trajectory controller (the ``ros2`` backend and a
JointTrajectoryController's ``FollowJointTrajectory`` action) implements
:class:`TrajectoryOffload`. The motion layer checks for it (``isinstance``) and, for a
trajectory it has already validated and checked against every limit, asks the backend to
send it as one goal instead of streaming it setpoint by setpoint:

* the motion layer keeps sampling the trajectory locally (the safety layer's limiter checks
  every setpoint, the setpoint stays where the robot is meant to be), its trajectory time
  running from the moment the controller has taken the goal (``started()``), but while the
  goal is held the backend sends no setpoint of its own to the controller;
* the controller's result (FollowJointTrajectory ``error_code`` and the goal's final status)
  ends the motion; its feedback's desired state is the motion's feedback;
* ``cancel()`` (motion.cancel(), preemption, e-stop, a limit the executor hits) cancels the
  goal; ``release()`` (the motion ended, whatever the reason) cancels it if it still runs and
  lets the backend stream again.

Nothing here is ROS-specific: the codes are FollowJointTrajectory's (:class:`agentsdk.motion.ResultCode`
values), the only vocabulary every trajectory controller shares.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    import numpy as np

    from .trajectory import Trajectory

__all__ = ["OffloadRequest", "OffloadedGoal", "TrajectoryOffload"]


@dataclass(frozen=True, slots=True)
class OffloadRequest:
    """A validated trajectory to run as one goal on the robot's own controller.

    ``trajectory`` is the trajectory as the motion layer executes it (continuous joints moved
    by whole turns, stretched if asked), starting now from the current state.
    ``path_tolerance``/``goal_tolerance`` are per joint of the trajectory, rad or m
    (``inf``: not checked); ``goal_time``: seconds after the end the goal tolerance may take.
    ``hold``: the robot's other joints and the positions they keep meanwhile.
    """

    trajectory: Trajectory
    path_tolerance: np.ndarray
    goal_tolerance: np.ndarray
    goal_time: float
    hold: Mapping[str, float]


class OffloadedGoal(Protocol):
    """A goal sent by :meth:`TrajectoryOffload.offload_trajectory` (called from the control tick: never blocks)."""

    def outcome(self, now: float) -> tuple[int, str] | None:
        """``(FollowJointTrajectory error code, message)`` once the goal has ended, else None.

        ``now`` is the robot time; a goal whose controller stays silent past its deadline ends
        with an error code here (the backend's own bound).
        """
        ...

    def started(self) -> bool:
        """True once the controller has taken the goal (or it has ended): its trajectory time runs from then."""
        ...

    def desired_into(self, position: np.ndarray, velocity: np.ndarray) -> bool:
        """Copy the controller's latest desired state (trajectory joint order) in; False when it sent none yet."""
        ...

    def cancel(self) -> None:
        """Ask the controller to cancel the goal (idempotent; the outcome follows)."""
        ...

    def release(self) -> None:
        """The motion has ended: cancel the goal if it still runs, and stream setpoints again (idempotent)."""
        ...


@runtime_checkable
class TrajectoryOffload(Protocol):
    """A backend whose controller can run a whole trajectory itself (see the module documentation)."""

    def offload_trajectory(self, request: OffloadRequest) -> OffloadedGoal | None:
        """Send ``request`` as one goal; None when it cannot be offloaded now (the motion is then streamed)."""
        ...
