"""Joint trajectories: value types, JTC-style interpolation, time parameterization.

Pure math, no asyncio and no robot. The pieces:

* :class:`TrajectoryPoint` / :class:`Trajectory` are shaped like ROS
  ``trajectory_msgs/JointTrajectory`` (times relative to the start of execution).
* :class:`TrajectorySampler` interpolates a trajectory the way ros2_controllers'
  JointTrajectoryController (JTC) does: a segment from the current desired state
  to point 0 (when ``points[0].time_from_start > 0``), then point i -> i+1 with
  linear (positions only), cubic Hermite (+velocities) or quintic (+accelerations)
  polynomials, and a hold of the last point after the end. The segment from the
  start state is always quintic and starts from its velocity and acceleration, so
  a trajectory that preempts another one starts without a velocity jump. Sampling
  is a bisect plus one (3x6)@(6xN) product on precomputed coefficients.
* :func:`plan`, :func:`plan_point_to_point` and :func:`plan_stop` derive timing
  from the joints' velocity, acceleration and jerk limits (ruckig) and return a
  :class:`Trajectory` whose points are the exact phase breakpoints of the jerk-limited
  profiles, with positions, velocities and accelerations. Between breakpoints every
  joint moves on a single cubic (plus a tiny quintic that absorbs ruckig's ~1e-8 end
  error), which the quintic interpolation reproduces exactly, so executing the
  trajectory reproduces the planned motion and its limits.

Choice of time parameterization. ``plan()`` runs ruckig (Community: one target state per
call) segment by segment, with through-velocities at the waypoints from a finite-difference
estimate refined by a small search, rejecting any candidate whose profile would leave the
joint position limits. On a 7-joint, 10-waypoint random problem (Franka-like velocity and
position limits, 3.75-10 rad/s^2, 100-200 rad/s^3) it plans in about 7 ms and gives a 12.8 s
motion (13.4 s when stopping at every waypoint); toppra (time-optimal along a cubic spline
through the waypoints) gives 11.1 s in 25 ms (4 ms on a coarse grid), and is 8 % faster on
average over 100 such problems, a third to 40 % of which is only because it ignores jerk.
But toppra's acceleration jumps (jerk spikes of 1e4 rad/s^3), it exceeded the velocity or
acceleration limits between grid points (by more than 0.1 % / 1 %) on 42 of the 100 problems,
its spline left the joint position limits on 11, and it cannot start from an arbitrary
(position, velocity, acceleration), which preemption needs; ruckig-segment-wise respects
position, velocity, acceleration and jerk limits on every problem, is already a dependency,
and also gives the minimum-time point-to-point move and the velocity-interface stop.
(ruckig 0.19's ``Trajectory.position_extrema`` misses extrema inside constant-acceleration
phases, so the limits check computes them from the profile phases itself.)
"""

from . import _types
from ._limits import check_motion_limits, time_scale_for_limits
from ._peaks import MotionPeaks
from ._planning import plan, plan_point_to_point, plan_stop
from ._ruckig import MAX_PROFILE_DURATION as MAX_PROFILE_DURATION
from ._ruckig import recording_solves
from ._sampler import TrajectorySampler
from ._types import Interpolation, Trajectory, TrajectoryPoint
from ._types import Values as Values

# re-bound here with their documentation, which Sphinx reads from the assignments in this module
#: longest ``time_from_start`` accepted (s, ~11.6 days): beyond it the polynomial coefficients lose
#: their precision (and at ~1e60 s overflow to NaN setpoints)
MAX_TIME_FROM_START = _types.MAX_TIME_FROM_START
#: shortest time between two points (and from the start to a first point at a time > 0), s
MIN_SEGMENT_DURATION = _types.MIN_SEGMENT_DURATION
StartState = _types.StartState
"""``(positions, velocities, accelerations)``; velocities/accelerations may be None (zero)."""

__all__ = [
    "MAX_TIME_FROM_START",
    "MIN_SEGMENT_DURATION",
    "Interpolation",
    "MotionPeaks",
    "StartState",
    "Trajectory",
    "TrajectoryPoint",
    "TrajectorySampler",
    "check_motion_limits",
    "plan",
    "plan_point_to_point",
    "plan_stop",
    "recording_solves",
    "time_scale_for_limits",
]

for _name in __all__:
    _obj = globals()[_name]
    if getattr(_obj, "__module__", "").startswith(__name__ + "."):
        _obj.__module__ = __name__  # documented and pickled as agentsdk.trajectory.X
