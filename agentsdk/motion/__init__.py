"""Trajectory execution: the :class:`Motion` handle and the executor that runs inside the control tick.

Modelled on ros2_controllers' JointTrajectoryController (JTC) and the
FollowJointTrajectory action:

* ``robot.follow(traj)`` returns a :class:`Motion` at once; ``await motion``
  gives a :class:`MotionResult` whose code is named after FollowJointTrajectory
  (plus CANCELED, PREEMPTED, ABORTED).
* Validation like JTC, and on the whole motion: joint names, positions, velocities,
  accelerations of every point against the joints' limits; a last point at rest
  (unless ``allow_nonzero_velocity_at_end``); and the *interpolated* motion, including the
  segment from the current state, within the position, velocity and acceleration limits
  (or, with ``stretch_to_limits=True``, slowed down uniformly until it is).
* The executor samples the trajectory every control tick (no asyncio timers in
  the loop), so tracking is identical in lockstep and in real time.
* ``start_time`` schedules the start on the robot clock (JTC's ``header.stamp``); a
  start in the past skips the points that have elapsed.
* Speed scaling (:meth:`MotionManager.set_speed_scaling`, JTC's speed scaling, a UR
  teach pendant's speed slider): every running trajectory advances its own time at the
  factor, which each motion follows with a bounded rate, so velocities never jump.
* ``motion.cancel()`` -- or cancelling the task awaiting the motion, e.g. via
  ``asyncio.timeout`` -- decelerates every joint to rest within its deceleration
  limit (a jerk-limited ruckig profile from the current desired state), then
  holds position. Not an instant freeze, not a runaway.
* An *abort* (path or goal tolerance violated, a safety stop) drops the reference at once:
  every joint decelerates from its *measured* position and velocity (ruckig stop profile)
  and holds where it stopped. A joint whose servo tracks its setpoint within
  :data:`TRACKING_BAND` starts the stop from its setpoint instead: the same state up to
  servo accuracy, and a setpoint that neither jumps nor stalls.
* A new ``follow`` on overlapping joints preempts the running motion (PREEMPTED)
  and starts from its *desired* position, velocity and acceleration, so the
  desired velocity is continuous at the switch.
* ``continuous`` joints take the shortest angle from the current state (the trajectory is
  moved by whole turns) and their errors wrap around (tolerances, feedback, results).

The package, one job a module, each importing only the ones above it in this list; the objects
of the last four hold each other (none inherits from another) and share one ``_MotionTable``:

* :mod:`._types`: result codes, phases, results, tolerances, feedback (values)
* :mod:`._handle`: the :class:`Motion` handle
* :mod:`._envelope`: where a motion's samples need no limiting (the tick's shortcut)
* :mod:`._records`: the executor's record of one motion, its tick buffers, the table of them
* :mod:`._ownership`: joint ownership, speed scaling, the desired state, how a motion ends
* :mod:`._stops`: stop planning (where a stop starts, its ramp)
* :mod:`._admission`: validation and preparation of a trajectory
* :mod:`._executor`: the per-tick hot path
* :mod:`._manager`: :class:`MotionManager`, the facade that builds them: the robot's entry point
  and the safety layer's stop port
"""

from __future__ import annotations

from ._handle import Motion
from ._manager import MotionManager as MotionManager
from ._types import TRACKING_BAND, Feedback, MotionResult, ResultCode, Tolerances
from ._types import MotionPhase as MotionPhase

__all__ = ["TRACKING_BAND", "Feedback", "Motion", "MotionResult", "ResultCode", "Tolerances"]
