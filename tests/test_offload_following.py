"""The following-error check on an offloaded goal: the trajectory controller that runs the goal owns its timing.

A backend whose own controller runs a whole trajectory (:mod:`agentsdk.offload`, the ``ros2`` backend's
FollowJointTrajectory goals) may run it later than the local sample: the goal's acceptance crosses a
link, and the controller's host may stall (a served robot on a loaded machine: issue 28's CI run).
A joint that follows what its controller reports as desired is following; a joint that follows
neither the local sample nor the controller's desired is a following error as on every backend.

The controller here is a mock backend that runs the goal itself, ``delay`` seconds of robot time late,
in lockstep (deterministic).
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk import SafetyState
from agentsdk.backends.mock import MockBackend
from agentsdk.motion import ResultCode
from agentsdk.offload import OffloadRequest
from agentsdk.registry import register_backend, unregister_backend

pytestmark = pytest.mark.timeout(60)


class _LateGoal:
    """A goal the mock's controller runs ``delay`` s of robot time after it was sent (linear between points)."""

    def __init__(self, backend: _LateController, request: OffloadRequest) -> None:
        traj = request.trajectory
        self.idx = np.array([backend.index[n] for n in traj.joint_names], dtype=np.intp)
        self.times = np.asarray(traj.times)
        self.positions = np.asarray(traj.positions)
        self.t0 = backend.now + backend.delay
        self.desired = self.positions[0].copy()
        self.ended: tuple[int, str] | None = None
        self.report = backend.report_desired

    def advance(self, now: float) -> np.ndarray:
        tau = min(max(now - self.t0, 0.0), float(self.times[-1]))
        for k in range(len(self.idx)):
            self.desired[k] = np.interp(tau, self.times, self.positions[:, k])
        if self.ended is None and now - self.t0 >= self.times[-1]:
            self.ended = (int(ResultCode.SUCCESSFUL), "")
        return self.desired

    # OffloadedGoal
    def outcome(self, now: float) -> tuple[int, str] | None:
        return self.ended

    def started(self) -> bool:
        return True

    def desired_into(self, position: np.ndarray, velocity: np.ndarray) -> bool:
        if not self.report:
            return False
        position[...] = self.desired
        velocity[...] = 0.0
        return True

    def cancel(self) -> None:
        if self.ended is None:
            self.ended = (int(ResultCode.CANCELED), "canceled")

    def release(self) -> None:
        self.cancel()


class _LateController(MockBackend):
    """The mock, with a trajectory controller that takes whole goals and runs them ``delay`` s late."""

    delay = 0.4
    report_desired = True

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.now = 0.0
        self.goal: _LateGoal | None = None
        self.goals = 0

    def offload_trajectory(self, request: OffloadRequest) -> _LateGoal:
        self.goal = _LateGoal(self, request)
        self.goals += 1
        return self.goal

    def _write(self, sp: Any) -> None:
        super()._write(sp)
        goal = self.goal
        if goal is not None and goal.ended is None:
            with self._lock:  # the controller, not the stream, drives the goal's joints
                self._sp_q[goal.idx] = goal.desired

    async def _step(self, dt: float) -> None:
        self.now += dt
        goal = self.goal
        if goal is not None and goal.ended is None:
            with self._lock:
                self._sp_q[goal.idx] = goal.advance(self.now)
        await super()._step(dt)


@pytest.fixture
async def late() -> AsyncIterator[tuple[agentsdk.Robot, _LateController]]:
    register_backend("late-controller", _LateController)
    try:
        async with agentsdk.connect("late-controller", robot="arm3", realtime=False) as robot:
            backend = robot.backend
            assert isinstance(backend, _LateController)
            yield robot, backend
    finally:
        unregister_backend("late-controller")
        _LateController.delay, _LateController.report_desired = 0.4, True


def _window(robot: agentsdk.Robot) -> float:
    check = robot.safety.following
    assert check is not None
    return float(check.windows[robot.joint_names.index("joint1")])


async def test_a_controller_running_the_goal_late_is_judged_by_its_own_desired(late: Any) -> None:
    robot, backend = late
    # the controller lags the local sample by 0.4 s of a ~1 rad/s move: farther from it than the window
    result = await robot.move_to({"joint1": 1.2}, duration=1.0)
    assert backend.goals == 1
    assert result.code is ResultCode.SUCCESSFUL, (result, robot.safety.events)
    assert robot.safety.state is SafetyState.OK, robot.safety.events
    assert abs((await robot.read()).positions()["joint1"] - 1.2) < 1e-6
    assert np.isnan(robot._loop.controller_desired).all()  # released with the motion


async def test_the_local_sample_alone_judges_a_controller_that_reports_no_desired(late: Any) -> None:
    """The same late controller without feedback: nothing says it is following, so the check latches."""
    robot, backend = late
    backend.report_desired = False
    result = await robot.move_to({"joint1": 1.2}, duration=1.0)
    assert result.code is not ResultCode.SUCCESSFUL
    assert robot.safety.state is SafetyState.ESTOP  # following_error_stop: category 2
    assert any("following error: joint 'joint1'" in str(e) for e in robot.safety.events), robot.safety.events


async def test_a_joint_near_neither_the_sample_nor_its_controllers_desired_is_a_following_error(late: Any) -> None:
    robot, backend = late
    window = _window(robot)
    backend.delay = 0.0
    # the joint is stuck: the controller reports the goal's path as desired, the joint stays where it was
    backend.frozen[robot.joint_names.index("joint1")] = True
    result = await robot.move_to({"joint1": 1.2}, duration=1.0)
    assert result.code is not ResultCode.SUCCESSFUL
    assert robot.safety.state is SafetyState.ESTOP  # following_error_stop: category 2
    events = [str(e) for e in robot.safety.events]
    assert any("following error: joint 'joint1'" in e and f"window {window:.4g}" in e for e in events), events


@pytest.mark.parametrize("category", [1, 2])
async def test_an_estop_stops_an_offloaded_goal_through_its_controller_and_never_pulls_back(
        late: Any, category: int) -> None:
    """The controller runs the goal 0.4 s behind the local sample: a stop ramp planned here, from the sample
    or the measurement, would not be where the controller stops. The goal is cancelled; the setpoint then
    follows the joint where the controller left it, and the robot never moves back."""
    robot, backend = late
    j = robot.joint_names.index("joint1")
    motion = asyncio.create_task(robot.move_to({"joint1": 1.2}, duration=1.0))
    trace: list[float] = []
    while (q := float((await robot.read()).position[j])) < 0.3:
        trace.append(q)
        await robot.clock.sleep(robot.control_period)
    await robot.estop(category)
    assert (await motion).code is ResultCode.ABORTED
    assert backend.goal is not None and backend.goal.ended == (int(ResultCode.CANCELED), "canceled")
    for _ in range(200):
        trace.append(float((await robot.read()).position[j]))
        await robot.clock.sleep(robot.control_period)
    steps = np.diff(trace)
    assert steps.min() >= -1e-9, f"moved back {-steps.min():.4g} rad"
    assert trace[-1] == trace[-50] < 1.2  # at rest, short of the goal
    assert robot.safety.state is SafetyState.ESTOP
    await robot.reset()
    await robot.enable()
    assert (await robot.move_to({"joint1": 0.0}, duration=1.0)).ok
