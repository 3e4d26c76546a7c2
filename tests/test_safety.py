"""Safety layer under fault injection, on every backend.

Limits (NaN/inf, clamp/reject, rate-limited warnings), the command watchdog
(HOLD), the loop-stall watchdog thread, the e-stop latch (reset/enable), stop
categories 0/1/2, backend faults (FAULT, recovery) and ``estop_threadsafe``.

Everything runs in lockstep simulated time and is deterministic, except the
stall tests: a blocked event loop is wall time by nature (they opt in with
``stall_in_lockstep``, the watchdog being off in lockstep by default), and they
assert on the latency the watchdog thread measured itself (``robot.safety.stall_latency``).
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import math
import threading
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import numpy as np
import pytest
from conftest import lockstep_backends

import agentsdk
from agentsdk import (
    BackendFault,
    EStopActive,
    InvalidValueError,
    JointCommand,
    LimitViolation,
    ResultCode,
    SafetyEvent,
    SafetyFault,
    SafetyState,
    SimulationDiverged,
    Trajectory,
    TrajectoryPoint,
)
from agentsdk.cli import run_behavior

#: every lockstep backend in the registry (the realtime-only CAN backend has its own suite)
BACKENDS = lockstep_backends()
#: backends with physics (gravity acts on a joint without torque)
SIMULATORS = ("mujoco", "pybullet")


def _backend_params(names: tuple[str, ...]) -> list[Any]:
    params = []
    for name in names:
        try:
            agentsdk.load_backend(name)
            reason = ""
        except Exception as exc:  # a backend being written may fail to import in any way
            reason = f"backend {name!r} unavailable: {type(exc).__name__}: {exc}"
        params.append(pytest.param(name, id=name, marks=pytest.mark.skipif(bool(reason), reason=reason)))
    return params


@pytest.fixture(params=BACKENDS)
def backend(request: pytest.FixtureRequest) -> str:
    return str(request.param)


@pytest.fixture(params=_backend_params(SIMULATORS))
def simulator(request: pytest.FixtureRequest) -> str:
    return str(request.param)


@asynccontextmanager
async def arm(backend: str, **safety: Any) -> AsyncIterator[agentsdk.Robot]:
    async with agentsdk.connect(backend, robot="arm3", safety=safety or None) as robot:
        yield robot


# --------------------------------------------------------------- helpers
class Recorder:
    """Per-tick record of the measured state and the setpoint written in that tick."""

    def __init__(self, robot: agentsdk.Robot) -> None:
        self.rows: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        robot.add_tick_hook(agentsdk.Phase.OBSERVE, self._on_tick)

    def _on_tick(self, t: float, st: Any, sp: Any) -> None:
        self.rows.append(
            (t, st.position.copy(), st.velocity.copy(), st.effort.copy(), sp.position.copy(), sp.velocity.copy(),
             sp.enabled.copy())
        )

    def mark(self) -> int:
        return len(self.rows)

    def since(self, k: int) -> dict[str, np.ndarray]:
        rows = self.rows[k:]
        cols = ("t", "q", "v", "effort", "q_des", "v_des", "enabled")
        return {c: np.array([r[i] for r in rows]) for i, c in enumerate(cols)}


def setpoint_copy(robot: agentsdk.Robot) -> dict[str, np.ndarray]:
    sp = robot.setpoint
    return {a: getattr(sp, a).copy() for a in ("position", "velocity", "effort", "kp", "kd", "enabled", "mode")}


def assert_setpoint_equal(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    for k in a:
        assert np.array_equal(a[k], b[k]), f"setpoint.{k} changed: {a[k]} -> {b[k]}"


def events_since(robot: agentsdk.Robot, n: int) -> list[SafetyEvent]:
    return list(robot.safety.events)[n:]


def kinds(robot: agentsdk.Robot) -> list[tuple[str, str]]:
    return [(e.kind, e.detail) for e in robot.safety.events]


async def wait_for(robot: agentsdk.Robot, cond: Any, limit: float = 5.0) -> None:
    """Step robot time one period at a time until ``cond()`` holds (at most ``limit`` robot seconds)."""
    async with robot.clock.timeout(limit):
        while not cond():
            await robot.clock.sleep(robot.control_period)


def spawn(coro: Any) -> asyncio.Task[Any]:
    """A background task whose exception always counts as retrieved.

    (A failing test that leaves an unretrieved task exception behind makes CPython
    3.11.7 raise "AST constructor recursion depth mismatch" inside pytest's report.)
    """
    task = asyncio.ensure_future(coro)
    task.add_done_callback(lambda t: t.cancelled() or t.exception())
    return task


def limits(robot: agentsdk.Robot) -> dict[str, np.ndarray]:
    js = robot.joints
    return {
        "lower": np.array([j.lower for j in js]),
        "upper": np.array([j.upper for j in js]),
        "vel": np.array([j.max_velocity for j in js]),
        "acc": np.array([j.max_acceleration for j in js]),
        "effort": np.array([j.max_effort for j in js]),
    }


STEP_TRAJECTORY = Trajectory(["joint1"], [TrajectoryPoint(1.0, [0.3])])


# ------------------------------------------------------ 1. NaN / inf values
BAD_VALUES = [
    JointCommand("position", {"joint1": math.nan}),
    JointCommand("position", {"joint2": math.inf}),
    JointCommand("velocity", {"joint1": -math.inf}),
    JointCommand("effort", {"joint3": math.nan}),
    JointCommand("position", [0.1, math.nan, 0.0]),
    JointCommand("position", {"joint1": 0.1}, velocity={"joint1": math.nan}),
    JointCommand("position", {"joint1": 0.1}, effort={"joint1": math.inf}),
]


async def test_non_finite_commands_rejected_state_unchanged(backend: str) -> None:
    async with arm(backend) as robot:
        await robot.command(JointCommand("position", {"joint1": 0.2}))
        await robot.clock.sleep(0.3)
        target, sp, n_ev = robot.command_targets(), setpoint_copy(robot), len(robot.safety.events)
        for cmd in BAD_VALUES:
            with pytest.raises(InvalidValueError, match="non-finite"):
                await robot.command(cmd)
            assert np.array_equal(robot.command_targets(), target), cmd
            assert_setpoint_equal(sp, setpoint_copy(robot))
        with pytest.raises(InvalidValueError, match="non-finite"):
            await robot.move_to({"joint1": math.nan})
        with pytest.raises(InvalidValueError):
            Trajectory(["joint1"], [TrajectoryPoint(1.0, [math.inf])])
        assert_setpoint_equal(sp, setpoint_copy(robot))
        assert len(robot.safety.events) == n_ev
        assert robot.safety.state is SafetyState.OK
        # still usable
        applied = await robot.command(JointCommand("position", {"joint1": -0.2}))
        assert applied.values == {"joint1": -0.2}
        await robot.clock.sleep(1.0)
        assert (await robot.read()).position[0] == pytest.approx(-0.2, abs=0.02)


# ------------------------------------------------------------- 2. limits
def _limit_cases(robot: agentsdk.Robot) -> list[tuple[str, str, float, float]]:
    """(mode, joint, out-of-limit value, value it clamps to)."""
    lim = limits(robot)
    return [
        ("position", "joint1", lim["upper"][0] + 1.0, lim["upper"][0]),
        ("position", "joint2", lim["lower"][1] - 0.5, lim["lower"][1]),
        ("velocity", "joint1", 10 * lim["vel"][0], lim["vel"][0]),
        ("velocity", "joint3", -10 * lim["vel"][2], -lim["vel"][2]),
        ("effort", "joint3", 100.0 + lim["effort"][2], lim["effort"][2]),
        ("effort", "joint1", -1e6, -lim["effort"][0]),
    ]


async def test_out_of_limit_commands_clamped_and_recorded(backend: str) -> None:
    async with arm(backend, limit_policy="clamp") as robot:
        for mode, name, value, clamped in _limit_cases(robot):
            j = robot.joint_index[name]
            n_ev = len(robot.safety.events)
            applied = await robot.command(JointCommand(mode, {name: value}))
            assert applied.mode == mode
            assert applied.values == {name: clamped}
            assert robot.command_targets()[j] == clamped
            (ev,) = events_since(robot, n_ev)
            assert (ev.kind, ev.joint, ev.time) == ("clamp", name, robot.clock.now())
            assert f"{mode} command {value:.4g}" in ev.detail and f"clamped to {clamped:.4g}" in ev.detail
            assert robot.safety.state is SafetyState.OK
            assert robot.setpoint.mode[j] == agentsdk.MODES.index(mode)
        # driven at a clamped position target, the joint stops at its limit
        await robot.command(JointCommand("position", [0.0, 0.0, 0.0]))
        applied = await robot.command(JointCommand("position", {"joint3": 1e3}))
        upper = robot.joints[2].upper
        assert applied.values == {"joint3": upper}
        await robot.clock.sleep(2.0)
        assert (await robot.read()).position[2] == pytest.approx(upper, abs=0.02)


async def test_position_margin_shrinks_the_clamp_range() -> None:
    async with arm("mock", position_margin=0.1) as robot:
        upper = robot.joints[1].upper
        applied = await robot.command(JointCommand("position", {"joint2": upper}))
        assert applied.values["joint2"] == pytest.approx(upper - 0.1)


async def test_out_of_limit_commands_rejected_state_unchanged(backend: str) -> None:
    async with arm(backend, limit_policy="reject") as robot:
        await robot.clock.sleep(0.1)
        for mode, name, value, _ in _limit_cases(robot):
            target, sp, n_ev = robot.command_targets(), setpoint_copy(robot), len(robot.safety.events)
            with pytest.raises(LimitViolation, match=rf"{mode} command .* for joint '{name}' is outside"):
                await robot.command(JointCommand(mode, {name: value}))
            assert np.array_equal(robot.command_targets(), target)
            assert_setpoint_equal(sp, setpoint_copy(robot))
            assert len(robot.safety.events) == n_ev
            assert robot.safety.state is SafetyState.OK
        # a position jump beyond max_position_step is refused too (stream small steps or move_to)
        with pytest.raises(LimitViolation, match="max_position_step"):
            await robot.command(JointCommand("position", {"joint1": 0.5}))
        # in-limit commands apply unchanged
        applied = await robot.command(JointCommand("velocity", {"joint1": 0.5}))
        assert applied.values == {"joint1": 0.5}
        assert await robot.move_to({"joint1": 0.4}) is not None


async def test_feedforward_beyond_limits_never_reaches_the_backend() -> None:
    async with arm("mock", limit_policy="clamp") as robot:
        emax, vmax = limits(robot)["effort"][0], limits(robot)["vel"][0]
        await robot.command(JointCommand("position", {"joint1": 0.0}, velocity={"joint1": 1e3}, effort={"joint1": 1e3}))
        await robot.clock.sleep(robot.control_period)
        assert robot.setpoint.effort[0] == emax
        assert robot.setpoint.velocity[0] == vmax


async def test_feedforward_beyond_limits_rejected_under_reject() -> None:
    async with arm("mock", limit_policy="reject") as robot:
        with pytest.raises(LimitViolation, match="effort feed-forward"):
            await robot.command(JointCommand("position", {"joint1": 0.0}, effort={"joint1": 1e3}))


async def test_clamp_warnings_are_rate_limited(caplog: pytest.LogCaptureFixture) -> None:
    def clamp_warnings() -> list[logging.LogRecord]:
        return [r for r in caplog.records if r.name == "agentsdk.safety" and "clamped" in r.getMessage()]

    caplog.set_level(logging.WARNING, logger="agentsdk.safety")
    # warn_interval is wall time; 100 commands take milliseconds, far below it
    async with arm("mock", warn_interval=60.0) as robot:
        n_ev = len(robot.safety.events)
        for _ in range(100):
            await robot.command(JointCommand("velocity", {"joint1": 99.0}))
        assert len(clamp_warnings()) == 1
        assert "joint1" in clamp_warnings()[0].getMessage()
        # every clamp is still recorded as an event
        assert [e.kind for e in events_since(robot, n_ev)] == ["clamp"] * 100
        # another joint, or another limit of the same joint, gets its own warning
        await robot.command(JointCommand("velocity", {"joint3": 99.0}))
        await robot.command(JointCommand("effort", {"joint1": 99.0}))
        assert len(clamp_warnings()) == 3
    caplog.clear()
    async with arm("mock", warn_interval=0.0) as robot:
        for _ in range(5):
            await robot.command(JointCommand("velocity", {"joint1": 99.0}))
        assert len(clamp_warnings()) == 5


# ------------------------------------------------------ 3. command watchdog
@pytest.mark.parametrize(("mode", "value"), [("velocity", 0.5), ("effort", 0.01)])
async def test_stale_stream_holds_within_timeout_plus_one_period(backend: str, mode: str, value: float) -> None:
    timeout = 0.1
    async with arm(backend, command_timeout=timeout) as robot:
        period = robot.control_period
        cmd = JointCommand(mode, {"joint1": value})
        for _ in range(25):
            await robot.command(cmd)
            await robot.clock.sleep(period)
        await robot.command(cmd)
        t_last = robot.clock.now()
        n_ev = len(robot.safety.events)
        await wait_for(robot, lambda: robot.safety.state is not SafetyState.OK, limit=1.0)
        t_hold = robot.clock.now()
        assert robot.safety.state is SafetyState.HOLD
        assert t_last + timeout < t_hold <= t_last + timeout + period + 1e-9
        (ev,) = events_since(robot, n_ev)
        assert (ev.kind, ev.time) == ("watchdog", t_hold)
        assert "joint1" in ev.detail
        # the joint holds where it was
        q_hold = (await robot.read()).position[0]
        await robot.clock.sleep(0.5)
        st = await robot.read()
        assert abs(st.position[0] - q_hold) < 0.02
        assert abs(st.velocity[0]) < 0.01
        assert robot.safety.state is SafetyState.HOLD
        assert [e.kind for e in events_since(robot, n_ev)] == ["watchdog"]  # recorded once
        # a new command leaves HOLD
        await robot.command(cmd)
        assert robot.safety.state is SafetyState.OK
        assert robot.safety.events[-1].kind == "resume"


async def test_a_stream_resumed_after_a_hold_is_watched_again() -> None:
    """A command to a held joint ends its hold (``feed`` clears it): when that stream goes stale again, the
    watchdog holds it again, it does not stay unwatched."""
    async with arm("mock", command_timeout=0.1) as robot:
        cmd = JointCommand("velocity", {"joint1": 0.5})
        for _ in range(2):
            await robot.command(cmd)
            assert robot.safety.state is SafetyState.OK
            await wait_for(robot, lambda: robot.safety.state is SafetyState.HOLD, limit=1.0)
        assert [e.kind for e in robot.safety.events if e.kind in ("watchdog", "resume")] == [
            "watchdog", "resume", "watchdog"]


async def test_watchdog_holds_each_stream_that_goes_stale() -> None:
    async with arm("mock", command_timeout=0.1) as robot:
        await robot.command(JointCommand("velocity", {"joint1": 0.5}))
        await robot.clock.sleep(0.05)
        await robot.command(JointCommand("velocity", {"joint3": 0.5}))
        await robot.clock.sleep(0.5)
        assert robot.safety.state is SafetyState.HOLD
        assert np.all((await robot.read()).velocity == 0.0)
        held = [e.detail for e in robot.safety.events if e.kind == "watchdog"]
        assert len(held) == 2 and "joint1" in held[0] and "joint3" in held[1]


async def test_watchdog_damping_hold_records_once() -> None:
    async with arm("mock", command_timeout=0.1, hold="damping") as robot:
        await robot.command(JointCommand("velocity", {"joint1": 0.5}))
        await robot.clock.sleep(0.5)
        assert robot.safety.state is SafetyState.HOLD
        assert [e.kind for e in robot.safety.events].count("watchdog") == 1
        assert abs((await robot.read()).velocity[0]) < 0.01


async def test_position_commands_and_trajectories_are_not_watched() -> None:
    async with arm("mock", command_timeout=0.1) as robot:
        await robot.command(JointCommand("position", {"joint1": 0.3}))
        result = await robot.move_to({"joint2": 0.3}, duration=1.0)
        assert result.ok
        await robot.clock.sleep(0.5)
        assert robot.safety.state is SafetyState.OK
        assert "watchdog" not in [e.kind for e in robot.safety.events]


# ----------------------------------------------------- 4. loop stall watchdog
async def test_blocked_loop_is_stopped_by_the_watchdog_thread(
    backend: str, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    import traceback

    formats: list[int] = []
    real_format = traceback.StackSummary.format

    def count_format(self: traceback.StackSummary) -> list[str]:
        formats.append(id(self))
        return real_format(self)

    # the stack's source lines are read once: for the thread's log line and stall_traceback together
    monkeypatch.setattr(traceback.StackSummary, "format", count_format)
    caplog.set_level(logging.ERROR, logger="agentsdk.safety")
    async with arm(backend, stall_in_lockstep=True) as robot:
        ctl, safety = robot.backend, robot.safety
        timeout = safety.config.stall_timeout
        assert timeout is not None
        calls: list[tuple[str, float]] = []
        seen_at_stop: list[tuple[SafetyState, bool]] = []
        original = ctl._emergency_stop

        def spy(category: int) -> None:
            calls.append((threading.current_thread().name, time.monotonic()))
            # what anyone who sees the actuators stop sees: the latch and the report are already there
            seen_at_stop.append((safety.state, safety.stall_latency is not None))
            original(category)

        monkeypatch.setattr(ctl, "_emergency_stop", spy)
        await robot.command(JointCommand("velocity", {"joint1": 0.5}))
        await robot.clock.sleep(0.05)
        frame = inspect.currentframe()
        assert frame is not None
        stall_line = frame.f_lineno + 2
        t0 = time.monotonic()
        time.sleep(0.5)  # noqa: ASYNC251 - the behavior under test blocks the event loop
        t1 = time.monotonic()
        # the watchdog thread stopped the backend while the loop was still blocked
        assert len(calls) == 1, calls
        thread_name, t_stop = calls[0]
        assert thread_name.startswith("agentsdk-stall-watchdog")
        assert t0 < t_stop < t1
        assert (not robot.torque_enabled)
        assert seen_at_stop == [(SafetyState.ESTOP, True)]
        assert safety.state is SafetyState.ESTOP
        # latency from the last heartbeat to the stop, as the thread measured it
        assert safety.stall_latency is not None
        # (the upper bound allows for a busy machine's thread wake-up; the stop came during the block, above)
        assert timeout <= safety.stall_latency <= timeout + 0.2, safety.stall_latency
        assert safety.stall_traceback is not None
        assert f'test_safety.py", line {stall_line}' in safety.stall_traceback
        for _ in range(500):  # (the thread logs the stack once torque is off: at most a moment after the block)
            if any("event loop stalled" in r.getMessage() for r in caplog.records):
                break
            await asyncio.sleep(0.01)
        (logged,) = [r.getMessage() for r in caplog.records if "event loop stalled" in r.getMessage()]
        assert logged.endswith(safety.stall_traceback)
        assert len(formats) == 1, formats
        await robot.clock.sleep(robot.control_period)  # the loop records the thread's event
        (ev,) = [e for e in safety.events if e.kind == "stall"]
        assert f"test_safety.py:{stall_line}" in ev.detail
        with pytest.raises(EStopActive):
            await robot.command(JointCommand("velocity", {"joint1": 0.5}))
        await robot.reset()
        assert safety.stall_traceback is None
        await robot.enable()
        assert safety.state is SafetyState.OK
        await robot.command(JointCommand("velocity", {"joint1": 0.5}))


# ------------------------------------------------ 5. latch, reset, enable
@pytest.mark.parametrize("category", [0, 1, 2])
async def test_estop_latches_until_reset_and_enable(backend: str, category: int) -> None:
    async with arm(backend) as robot:
        # joint1 and joint3 turn about the vertical axis: no gravity torque, so torque off keeps them put
        motion = robot.follow(Trajectory(["joint1", "joint3"], [TrajectoryPoint(1.0, [1.0, -1.0])]))
        await robot.clock.sleep(0.4)
        await robot.estop(category)
        assert (await motion).code is ResultCode.ABORTED
        assert robot.safety.state is SafetyState.ESTOP
        for attempt in (
            robot.command(JointCommand("position", {"joint1": 0.0})),
            robot.move_to({"joint1": 0.0}),
        ):
            with pytest.raises(EStopActive, match="reset"):
                await attempt
        with pytest.raises(EStopActive):
            robot.follow(STEP_TRAJECTORY)
        with pytest.raises(EStopActive, match="reset"):
            await robot.enable()  # reset first
        await robot.clock.sleep(0.5)  # come to rest

        await robot.reset()
        assert robot.safety.state is SafetyState.DISABLED
        assert robot.safety.events[-1].kind == "reset"
        rec = Recorder(robot)
        await robot.clock.sleep(1.0)
        q = rec.since(0)["q"]
        assert np.abs(q - q[0]).max() < 1e-3, "the robot moved after reset() without enable()"
        with pytest.raises(EStopActive, match="enable"):
            await robot.command(JointCommand("position", {"joint1": 0.0}))
        with pytest.raises(EStopActive, match="enable"):
            await robot.move_to({"joint1": 0.0})
        with pytest.raises(EStopActive, match="enable"):
            robot.follow(STEP_TRAJECTORY)

        await robot.enable()
        assert robot.safety.state is SafetyState.OK
        assert not (not robot.torque_enabled)
        start = (await robot.read()).position[0]
        result = await robot.move_to({"joint1": start - 0.3})
        assert result.ok, result
        assert (await robot.read()).position[0] == pytest.approx(start - 0.3, abs=0.02)


async def test_estop_category_must_be_0_1_or_2() -> None:
    async with arm("mock") as robot:
        for bad in (3, -1):
            with pytest.raises(InvalidValueError, match="category"):
                await robot.estop(bad)
            with pytest.raises(InvalidValueError, match="category"):
                robot.estop_threadsafe(bad)
        assert robot.safety.state is SafetyState.OK


# ------------------------------------------- 6. exception in a behavior
async def test_behavior_exception_triggers_category_1_stop(backend: str) -> None:
    seen: list[agentsdk.Robot] = []
    records: list[tuple[float, np.ndarray]] = []

    def on_robot(robot: agentsdk.Robot) -> None:
        seen.append(robot)
        robot.add_tick_hook(agentsdk.Phase.OBSERVE, lambda t, st, sp: records.append((t, st.velocity.copy())))

    async def behavior(robot: agentsdk.Robot) -> None:
        await robot.command(JointCommand("velocity", {"joint1": 1.0}))
        await robot.clock.sleep(0.1)
        raise RuntimeError("gripper reported a jam at step 3")

    with pytest.raises(RuntimeError, match="gripper reported a jam at step 3"):
        await run_behavior(behavior, backend=backend, robot="arm3", on_robot=on_robot)
    (robot,) = seen
    assert robot.closed
    assert ("estop", "category 1 requested") in kinds(robot)
    assert ("estop", "category 1: stopped, torque removed") in kinds(robot)
    (t_req,) = [e.time for e in robot.safety.events if e.detail == "category 1 requested"]
    (t_end,) = [e.time for e in robot.safety.events if e.detail == "category 1: stopped, torque removed"]
    # it decelerated (1 rad/s within the deceleration limit takes time) and came to rest
    assert t_end - t_req >= 1.0 / robot.joints[0].max_acceleration - 1e-9
    v_end = next(v for t, v in records if t >= t_end)
    assert abs(v_end[0]) < 0.05


# ------------------------------------------------- 7. stop categories
async def _moving_arm(robot: agentsdk.Robot) -> tuple[agentsdk.Motion, Recorder]:
    """Tilt joint2 (gravity loads it), then cruise joint1 and joint3 on a long trajectory."""
    assert (await robot.move_to({"joint2": 0.4}, duration=1.0)).ok
    rec = Recorder(robot)
    motion = robot.follow(Trajectory(["joint1", "joint3"], [TrajectoryPoint(2.0, [2.5, -2.5])]))
    await robot.clock.sleep(0.7)
    return motion, rec


def _assert_decelerated_within_limits(robot: agentsdk.Robot, rec: Recorder, k0: int, t0: float, t1: float) -> None:
    """Desired motion continuous and within the deceleration limits; measured velocity follows it."""
    dt = robot.control_period
    acc = limits(robot)["acc"] * robot.safety.config.stop_deceleration_scale
    d = rec.since(k0 - 3)
    window = d["t"] <= t1 + 1e-9
    q_des, v_des = d["q_des"][window], d["v_des"][window]
    # the desired position neither jumps nor stalls: its 2nd difference is an acceleration
    acc_from_q = np.abs(np.diff(q_des, 2, axis=0)) / dt**2
    assert np.all(acc_from_q <= acc * 1.01 + 1e-6), acc_from_q.max(axis=0)
    acc_from_v = np.abs(np.diff(v_des, axis=0)) / dt
    assert np.all(acc_from_v <= acc * 1.01 + 1e-6), acc_from_v.max(axis=0)
    # measured: slows down no faster than the limit allows (with servo tracking slack), ends at rest
    v = d["v"][window]
    v0 = np.abs(v[2])
    t = d["t"][window]
    floor = v0 - acc * np.maximum(t - t0, 0.0)[:, None] - 0.3
    assert np.all(np.abs(v) >= floor), "measured velocity dropped faster than the deceleration limit"
    assert np.all(np.abs(v[-1]) < 0.05), v[-1]
    # not an instant stop: the fastest joint needs v/a
    assert t1 - t0 >= float(np.max(v0 / acc)) * 0.9


async def test_category_0_removes_torque_at_once(backend: str) -> None:
    async with arm(backend) as robot:
        motion, rec = await _moving_arm(robot)
        t0 = robot.clock.now()
        await robot.estop(0)
        assert robot.clock.now() == t0  # no control cycle needed
        assert (not robot.torque_enabled)
        assert not robot.setpoint.enabled.any()
        assert (await motion).code is ResultCode.ABORTED
        k = rec.mark()
        await robot.clock.sleep(0.3)
        d = rec.since(k)
        assert not d["enabled"].any()
        assert np.abs(d["effort"]).max() < 1e-9
        if backend in SIMULATORS:
            # nothing holds the tilted arm: gravity pulls joint2 further over
            q2 = d["q"][:, 1]
            assert q2[-1] - q2[0] > 0.05, q2[[0, -1]]
        assert robot.safety.state is SafetyState.ESTOP
        assert ("estop", "category 0 requested") in kinds(robot)


async def test_category_1_decelerates_then_removes_torque(backend: str) -> None:
    async with arm(backend) as robot:
        motion, rec = await _moving_arm(robot)
        k0, t0 = rec.mark(), robot.clock.now()
        await robot.estop(1)
        t1 = robot.clock.now()
        assert (await motion).code is ResultCode.ABORTED
        _assert_decelerated_within_limits(robot, rec, k0, t0, t1)
        # torque stayed on during the ramp, then was removed
        d = rec.since(k0)
        assert d["enabled"][d["t"] <= t1 - 1e-9].all()
        assert (not robot.torque_enabled) and not robot.setpoint.enabled.any()
        k = rec.mark()
        await robot.clock.sleep(0.3)
        d = rec.since(k)
        assert not d["enabled"].any() and np.abs(d["effort"]).max() < 1e-9
        if backend in SIMULATORS:
            assert d["q"][-1, 1] - d["q"][0, 1] > 0.05  # joint2 falls: no torque
        assert robot.safety.events[-1].detail == "category 1: stopped, torque removed"


async def test_category_2_decelerates_and_holds_with_torque(backend: str) -> None:
    async with arm(backend) as robot:
        motion, rec = await _moving_arm(robot)
        k0, t0 = rec.mark(), robot.clock.now()
        await robot.estop(2)
        t1 = robot.clock.now()
        assert (await motion).code is ResultCode.ABORTED
        _assert_decelerated_within_limits(robot, rec, k0, t0, t1)
        assert not (not robot.torque_enabled) and robot.setpoint.enabled.all()
        k = rec.mark()
        await robot.clock.sleep(1.0)
        d = rec.since(k)
        assert d["enabled"].all()
        drift = np.abs(d["q"] - d["q"][0]).max(axis=0)
        assert np.all(drift < 0.01), drift
        assert robot.safety.state is SafetyState.ESTOP
        assert robot.safety.events[-1].detail == "category 2: stopped, holding with torque on"


@pytest.mark.parametrize(("first", "second"), [(1, 1), (2, 1), (1, 2), (2, 2)])
async def test_a_second_stop_request_joins_the_running_stop(backend: str, first: int, second: int) -> None:
    """E.g. the button pressed twice: the ramp is not restarted, the stronger category's end state wins."""
    async with arm(backend) as robot:
        motion, rec = await _moving_arm(robot)
        k0, t0 = rec.mark(), robot.clock.now()
        stop = spawn(robot.estop(first))
        await robot.clock.sleep(0.05)
        await robot.estop(second)
        t1 = robot.clock.now()
        assert stop.done()
        await stop
        assert (await motion).code is ResultCode.ABORTED
        _assert_decelerated_within_limits(robot, rec, k0, t0, t1)
        assert (not robot.torque_enabled) is (min(first, second) == 1)
        ends = [e.detail for e in robot.safety.events if e.detail.startswith("category") and "stopped" in e.detail]
        assert ends == [f"category {min(first, second)}: stopped, " + (
            "torque removed" if min(first, second) == 1 else "holding with torque on")]


async def test_category_0_during_a_category_2_stop_removes_torque_at_once() -> None:
    async with arm("mock") as robot:
        motion, rec = await _moving_arm(robot)
        stop = spawn(robot.estop(2))
        await robot.clock.sleep(0.05)
        t = robot.clock.now()
        await robot.estop(0)
        assert robot.clock.now() == t and (not robot.torque_enabled)
        await stop
        assert (not robot.torque_enabled)  # the end of the category 2 stop does not re-enable torque
        k = rec.mark()
        await robot.clock.sleep(0.1)
        assert not rec.since(k)["enabled"].any()
        assert (await motion).code is ResultCode.ABORTED


async def test_close_during_a_stop_completes_the_stop_first(backend: str) -> None:
    """Issue 10.1: close() in the middle of a category 1 stop lets it reach rest, then removes torque."""
    robot = await agentsdk.connect(backend, robot="arm3")
    rec = Recorder(robot)
    motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(2.0, [2.0])]))
    await robot.clock.sleep(0.5)
    stop = spawn(robot.estop(1))
    await robot.clock.sleep(0.02)
    await robot.close()
    await stop  # completed, not cut short
    assert motion.done()
    last = rec.since(0)
    assert abs(last["v"][-1][0]) < 0.05, f"closed while moving at {last['v'][-1][0]:.3f} rad/s"
    kinds = [e.detail for e in robot.safety.events]
    assert "category 1: stopped, torque removed" in kinds


@pytest.mark.parametrize("category", [1, 2])
async def test_stop_during_direct_position_ramp_decelerates_and_stays(backend: str, category: int) -> None:
    """A direct position command ramps at max velocity; a stop must not resume that ramp."""
    async with arm(backend) as robot:
        rec = Recorder(robot)
        await robot.command(JointCommand("position", {"joint1": 2.0}))
        await robot.clock.sleep(0.3)
        k0, t0 = rec.mark(), robot.clock.now()
        await robot.estop(category)
        t1 = robot.clock.now()
        d = rec.since(k0 - 3)
        acc = limits(robot)["acc"][0]
        v_des = np.diff(d["q_des"][d["t"] <= t1 + 1e-9, 0]) / robot.control_period
        assert np.all(np.abs(np.diff(v_des)) / robot.control_period <= acc * 1.01 + 1e-6)
        assert t1 - t0 >= 0.9 * robot.joints[0].max_velocity / acc
        q_stop = (await robot.read()).position[0]
        await robot.clock.sleep(1.0)
        assert abs((await robot.read()).position[0] - q_stop) < 0.01
        assert q_stop < 1.5  # stopped well short of the old goal


# ------------------------------------------------------------ 8. faults
@pytest.mark.parametrize("knob", ["step_error", "read_error"])
async def test_mock_backend_fault_then_reset_and_enable(knob: str) -> None:
    async with arm("mock") as robot:
        ctl = robot.backend
        motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(2.0, [1.0])]))
        sleeper = spawn(robot.clock.sleep(5.0))
        await robot.clock.sleep(0.2)
        setattr(ctl, knob, True)
        with pytest.raises(BackendFault, match="injected"):
            await robot.clock.sleep(1.0)
        # every waiting behavior gets the error
        with pytest.raises(BackendFault, match="injected"):
            await motion
        with pytest.raises(BackendFault, match="injected"):
            await sleeper
        safety = robot.safety
        assert safety.state is SafetyState.FAULT
        assert isinstance(safety.cause, BackendFault) and "injected" in str(safety.cause)
        assert safety.events[-1].kind == "fault" and "injected" in safety.events[-1].detail
        assert (not robot.torque_enabled)
        with pytest.raises(SafetyFault, match="injected"):
            await robot.command(JointCommand("position", {"joint1": 0.0}))
        with pytest.raises(SafetyFault, match="injected"):
            await robot.read()
        with pytest.raises(SafetyFault):
            await robot.enable()
        await robot.estop(1)  # returns at once: the loop is down, torque is already off

        await robot.reset()
        assert safety.state is SafetyState.DISABLED and safety.cause is None
        q = (await robot.read()).position
        await robot.clock.sleep(0.5)
        assert np.allclose((await robot.read()).position, q)
        with pytest.raises(EStopActive, match="enable"):
            await robot.command(JointCommand("position", {"joint1": 0.0}))
        await robot.enable()
        assert (await robot.move_to({"joint1": 0.0})).ok


async def test_injected_backend_fault_on_every_backend(backend: str, monkeypatch: pytest.MonkeyPatch) -> None:
    async with arm(backend) as robot:
        ctl = robot.backend
        original = ctl._step
        armed = False

        async def failing_step(dt: float) -> None:
            nonlocal armed
            if armed:
                armed = False
                raise BackendFault(f"{backend}: injected bus loss")
            await original(dt)

        monkeypatch.setattr(ctl, "_step", failing_step)
        motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(2.0, [1.0])]))
        await robot.clock.sleep(0.2)
        armed = True
        with pytest.raises(BackendFault, match="injected bus loss"):
            await motion
        assert robot.safety.state is SafetyState.FAULT
        assert "injected bus loss" in str(robot.safety.cause)
        assert (not robot.torque_enabled)
        if type(ctl)._recover is agentsdk.Backend._recover:
            with pytest.raises(BackendFault, match="cannot recover"):
                await robot.reset()
            assert robot.safety.state is SafetyState.FAULT
            return
        await robot.reset()
        assert robot.safety.state is SafetyState.DISABLED
        await robot.enable()
        assert robot.safety.state is SafetyState.OK
        assert (await robot.move_to({"joint1": 0.3})).ok


async def test_fault_during_a_category_1_stop_ends_the_stop(monkeypatch: pytest.MonkeyPatch) -> None:
    async with arm("mock") as robot:
        motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(2.0, [2.0])]))
        await robot.clock.sleep(0.5)
        stop = spawn(robot.estop(1))
        await robot.clock.sleep(0.05)
        robot.backend.step_error = True
        await stop  # must not hang waiting for a ramp the dead loop never finishes
        assert robot.safety.state is SafetyState.FAULT
        assert robot.safety.events[-1].detail == "category 1: interrupted by a fault; torque removed"
        assert (await motion).code is ResultCode.ABORTED


async def test_mujoco_divergence_is_a_fault_and_recoverable() -> None:
    # arm3's URDF effort limits cap every joint force in MuJoCo, so absurd gains alone cannot
    # destabilise it (and absurd gravity is refused by the options); a huge joint damping
    # integrated explicitly (rk4) does, as soon as a joint moves
    async with agentsdk.connect("mujoco", robot="arm3", joint_damping=1e9, integrator="rk4") as robot:
        await robot.clock.sleep(0.1)  # upright: balanced, nothing happens
        assert robot.safety.state is SafetyState.OK
        sleeper = spawn(robot.clock.sleep(5.0))
        motion = robot.follow(Trajectory(["joint2"], [TrajectoryPoint(1.0, [0.3])]))
        with pytest.raises(SimulationDiverged, match="diverged"):
            await robot.clock.sleep(1.0)
        # every waiting behavior gets the error
        with pytest.raises(SimulationDiverged):
            await sleeper
        with pytest.raises(SimulationDiverged):
            await motion
        assert robot.safety.state is SafetyState.FAULT
        assert isinstance(robot.safety.cause, SimulationDiverged)
        assert any(e.kind == "fault" and "diverged" in e.detail for e in robot.safety.events)
        with pytest.raises(SafetyFault, match="diverged"):
            await robot.command(JointCommand("position", {"joint1": 0.0}))
        await robot.reset()  # MuJoCo resets the world to the initial state
        assert robot.safety.state is SafetyState.DISABLED
        with pytest.raises(EStopActive, match="enable"):
            await robot.command(JointCommand("position", {"joint1": 0.0}))
        await robot.enable()
        assert robot.safety.state is SafetyState.OK
        await robot.clock.sleep(0.2)  # holds the initial pose (any motion would diverge again here)
        assert robot.safety.state is SafetyState.OK
        st = await robot.read()
        assert np.abs(st.position).max() < 1e-6 and np.isfinite(st.velocity).all()


# ---------------------------------------------------- 9. estop_threadsafe
def _from_thread(fn: Any, *args: Any) -> None:
    errors: list[BaseException] = []

    def run() -> None:
        try:
            fn(*args)
        except BaseException as exc:  # re-raised in the test
            errors.append(exc)

    t = threading.Thread(target=run, name="test-estop-button")
    t.start()
    t.join()
    if errors:
        raise errors[0]


async def test_estop_threadsafe_category_0_latches_and_stops(backend: str, monkeypatch: pytest.MonkeyPatch) -> None:
    async with arm(backend) as robot:
        ctl = robot.backend
        callers: list[str] = []
        original = ctl._emergency_stop

        def spy(category: int) -> None:
            callers.append(threading.current_thread().name)
            original(category)

        monkeypatch.setattr(ctl, "_emergency_stop", spy)
        motion, rec = await _moving_arm(robot)
        t0 = robot.clock.now()
        _from_thread(robot.estop_threadsafe, 0)
        # acted in the calling thread, before any control cycle
        assert callers == ["test-estop-button"]
        assert (not robot.torque_enabled)
        assert robot.safety.state is SafetyState.ESTOP  # reading the state must not hide the latch from the loop
        with pytest.raises(EStopActive):
            await robot.command(JointCommand("position", {"joint1": 0.0}))
        k = rec.mark()
        await robot.clock.sleep(robot.control_period)
        assert (await motion).code is ResultCode.ABORTED
        assert robot.clock.now() == pytest.approx(t0 + robot.control_period)
        (ev,) = [e for e in robot.safety.events if e.kind == "estop"]
        assert ev.time == t0 and "category 0" in ev.detail
        await robot.clock.sleep(0.2)
        d = rec.since(k)
        assert not d["enabled"].any() and np.abs(d["effort"]).max() < 1e-9


@pytest.mark.parametrize("category", [1, 2])
async def test_estop_threadsafe_category_1_and_2_run_on_the_loop(backend: str, category: int) -> None:
    async with arm(backend) as robot:
        motion, rec = await _moving_arm(robot)
        k0, t0 = rec.mark(), robot.clock.now()
        _from_thread(robot.estop_threadsafe, category)
        assert robot.safety.state is SafetyState.ESTOP
        done = f"category {category}: stopped"
        await wait_for(robot, lambda: any(e.detail.startswith(done) for e in robot.safety.events))
        t1 = robot.clock.now()
        assert (await motion).code is ResultCode.ABORTED
        _assert_decelerated_within_limits(robot, rec, k0, t0, t1)
        assert (not robot.torque_enabled) is (category == 1)
        assert ("estop", f"category {category} requested (threadsafe)") in kinds(robot)


async def test_estop_threadsafe_after_close_is_harmless() -> None:
    robot = await agentsdk.connect("mock", robot="arm3")
    await robot.close()
    _from_thread(robot.estop_threadsafe, 1)
    _from_thread(robot.estop_threadsafe, 0)
    assert robot.safety.state is SafetyState.ESTOP


# --------------------------------------------------- observable state
async def test_safety_events_and_state_are_observable() -> None:
    async with arm("mock", command_timeout=0.1) as robot:
        assert robot.safety.state is SafetyState.OK
        assert "OK" in repr(robot)
        await robot.command(JointCommand("velocity", {"joint1": 50.0}))
        await robot.clock.sleep(0.2)
        await robot.estop(2)
        await robot.reset()
        await robot.enable()
        evs = list(robot.safety.events)
        assert [e.kind for e in evs] == ["clamp", "watchdog", "estop", "estop", "reset", "enable"]
        for e in evs:
            assert isinstance(e, SafetyEvent)
            assert isinstance(e.time, float) and isinstance(e.detail, str) and e.detail
        assert evs[0].joint == "joint1" and evs[2].joint is None
        assert [e.time for e in evs] == sorted(e.time for e in evs)
        with pytest.raises(AttributeError):
            evs[0].kind = "x"  # type: ignore[misc]


# ------------------------------------------------- issue 10: regressions
async def test_reset_while_a_trajectory_runs_brings_the_robot_to_rest(backend: str) -> None:
    """Issue 10.2: reset() during a trajectory used to leave it running in DISABLED (0.10 -> 0.50 rad)."""
    async with arm(backend) as robot:
        motion = robot.follow(Trajectory(["joint1"], [TrajectoryPoint(1.5, [1.0])]))
        await robot.clock.sleep(0.4)
        await robot.reset()
        assert robot.safety.state is SafetyState.DISABLED
        assert motion.done() and motion.result().code is ResultCode.ABORTED
        assert not robot.busy
        before = (await robot.read()).position.copy()
        await robot.clock.sleep(0.5)
        after = await robot.read()
        assert np.abs(after.position - before).max() < 0.01, (before, after.position)
        assert np.abs(after.velocity).max() < 0.05
        with pytest.raises(EStopActive):
            await robot.command(JointCommand("position", {"joint1": 0.0}))
        await robot.enable()
        assert (await robot.move_to({"joint1": 0.0})).ok


async def test_reset_while_a_velocity_stream_runs_brings_the_robot_to_rest(backend: str) -> None:
    async with arm(backend) as robot:
        await robot.command(JointCommand("velocity", {"joint1": 0.5}))
        await robot.clock.sleep(0.1)
        await robot.reset()
        before = (await robot.read()).position.copy()
        await robot.clock.sleep(0.5)
        assert np.abs((await robot.read()).position - before).max() < 0.01


async def test_stall_watchdog_is_off_in_lockstep_and_on_in_realtime() -> None:
    """Issue 20.9: a stalled lockstep loop cannot advance simulated time, so nothing moves and nothing stops;
    in real time (and on hardware) the same stall latches a category 0 e-stop."""
    async with agentsdk.connect("mock", robot="arm3", safety={"stall_timeout": 0.05}) as robot:
        assert not robot.realtime and not robot.safety.stall_watchdog_active
        await robot.command(JointCommand("velocity", {"joint1": 0.5}))
        await robot.clock.sleep(0.05)
        t, before = robot.clock.now(), (await robot.read()).position.copy()
        _block_event_loop(0.3)
        assert robot.clock.now() == t  # robot time stood still during the stall ...
        assert np.array_equal((await robot.read()).position, before)  # ... and so did the robot
        assert robot.safety.state is SafetyState.OK
        assert "stall" not in [e.kind for e in robot.safety.events]
        assert [th for th in threading.enumerate() if th.name.startswith("agentsdk-stall-watchdog")] == []
    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety={"stall_timeout": 0.05}) as robot:
        assert robot.safety.stall_watchdog_active
        await robot.command(JointCommand("velocity", {"joint1": 0.5}))
        await robot.clock.sleep(0.05)
        _block_event_loop(0.3)
        assert robot.safety.state is SafetyState.ESTOP
        assert "stall" in [e.kind for e in robot.safety.events]


def _block_event_loop(seconds: float) -> None:
    time.sleep(seconds)  # deliberately blocking: the stall watchdog thread must see it


async def test_stall_is_detected_while_holding_after_a_category_2_stop(backend: str) -> None:
    """Issue 10.5: the stall watchdog skipped whenever a latch was set, even with torque on (category 2)."""
    async with arm(backend, stall_timeout=0.1, stall_in_lockstep=True) as robot:
        await robot.estop(2)
        assert robot.torque_enabled  # category 2 holds with torque on
        _block_event_loop(0.6)
        assert any(e.kind == "stall" for e in robot.safety.events)
        assert not robot.torque_enabled
        await robot.clock.sleep(robot.control_period)
        assert not robot.setpoint.enabled.any()


async def test_stall_event_is_visible_as_soon_as_the_watchdog_latches() -> None:
    """Issue 10.6: the event log used to lag the latch until a later tick drained the thread's events."""
    async with arm("mock", stall_timeout=0.1, stall_in_lockstep=True) as robot:
        await robot.clock.sleep(0.05)
        _block_event_loop(0.6)
        assert robot.safety.state is SafetyState.ESTOP
        kinds = [e.kind for e in robot.safety.events]  # no tick has run since the thread latched
        assert "stall" in kinds


async def test_measured_position_outside_the_limits_is_a_protective_stop() -> None:
    """The README's known gap: a joint pushed past its (soft) limit now latches a category 2 stop."""
    async with arm("mujoco", position_limit_tolerance=0.005) as robot:
        upper = robot.joints[0].upper
        await robot.command(JointCommand("position", {"joint1": upper}))
        await robot.clock.sleep(1.0)
        assert robot.safety.state is SafetyState.OK
        await robot.command(JointCommand("effort", {"joint1": robot.joints[0].max_effort}))
        for _ in range(200):
            await robot.clock.sleep(0.01)
            if robot.safety.state is not SafetyState.OK:
                break
        assert robot.safety.state is SafetyState.ESTOP
        (ev,) = [e for e in robot.safety.events if e.kind == "limit"]
        assert ev.joint == "joint1" and "outside its limits" in ev.detail
        await robot.safety.wait_stopped()
        assert robot.torque_enabled  # category 2 by default


def test_measured_position_check_watches_a_joint_once_it_was_inside() -> None:
    from agentsdk.loop import StateBuffer
    from agentsdk.safety import MeasuredPositionCheck

    joints = (agentsdk.JointInfo("a", "revolute", -1.0, 1.0, 1.0, 1.0), agentsdk.JointInfo("b", "revolute", 0.5, 2.0,
                                                                                          1.0, 1.0))
    check = MeasuredPositionCheck(joints, tolerance=0.1, category=1)
    st = StateBuffer(2)
    st.position[:] = [0.0, 0.0]  # b starts outside its limits: not watched yet (it can be moved back in)
    assert check(0.0, st.view) is None
    st.position[:] = [0.0, 0.45]  # b enters [0.4, 2.1]
    assert check(0.1, st.view) is None
    st.position[:] = [0.0, 0.3]
    v = check(0.2, st.view)
    assert v is not None and v.joint == "b" and v.category == 1
    st.position[:] = [math.nan, 1.0]
    v = check(0.3, st.view)
    assert v is not None and v.joint == "a"


async def test_a_pluggable_safety_check_latches_its_stop_and_can_be_removed() -> None:
    async with arm("mock") as robot:
        calls: list[float] = []

        def never(t: float, st: Any) -> None:
            calls.append(t)

        handle = robot.safety.add_check(never)
        await robot.clock.sleep(0.05)
        assert calls and handle.active
        handle.remove()
        handle.remove()  # idempotent
        n = len(calls)
        await robot.clock.sleep(0.05)
        assert len(calls) == n and not handle.active

        def too_far(t: float, st: Any) -> agentsdk.SafetyViolation | None:
            if st.position[0] > 0.3:
                return agentsdk.SafetyViolation("workspace", "joint1 left the allowed workspace", "joint1", 1)
            return None

        robot.safety.add_check(too_far)
        await robot.command(JointCommand("position", {"joint1": 0.6}))
        await robot.clock.sleep(1.0)
        assert robot.safety.state is SafetyState.ESTOP
        assert any(e.kind == "workspace" for e in robot.safety.events)
        assert not robot.torque_enabled  # category 1 ends with torque off


async def test_velocity_stream_stops_at_the_position_limit(backend: str) -> None:
    """Like ros2_control's saturation limiter: a velocity stream decelerates to stop at the limit."""
    async with arm(backend) as robot:
        j = robot.joints[2]  # joint3
        rec = Recorder(robot)
        for _ in range(300):
            await robot.command(JointCommand("velocity", {j.name: j.max_velocity}))
            await robot.clock.sleep(0.01)
        data = rec.since(0)
        q = data["q"][:, 2]
        assert q.max() <= j.upper + 0.01, f"passed its upper limit {j.upper}: {q.max()}"
        assert q[-1] == pytest.approx(j.upper, abs=0.02)
        assert abs(data["v"][-1, 2]) < 0.05
        assert robot.safety.state is SafetyState.OK


async def test_effort_pushing_a_joint_out_of_its_limit_is_dropped() -> None:
    async with arm("mock") as robot:
        j = robot.joints[0]
        await robot.command(JointCommand("position", {j.name: j.upper}))
        await robot.clock.sleep(2.0)
        await robot.command(JointCommand("effort", {j.name: 0.5 * j.max_effort}))
        await robot.clock.sleep(robot.control_period)
        assert robot.setpoint.effort[0] == 0.0  # outward: dropped
        await robot.command(JointCommand("effort", {j.name: -0.5 * j.max_effort}))
        await robot.clock.sleep(robot.control_period)
        assert robot.setpoint.effort[0] == -0.5 * j.max_effort  # inward: applied
