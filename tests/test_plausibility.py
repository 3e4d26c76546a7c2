"""Issue 20.1: the plausibility gate -- the rule itself (lockstep, no robot), and robots that must not trip it."""

from __future__ import annotations

import math

import numpy as np
import pytest

import agentsdk
from agentsdk import JointCommand, SafetyState
from agentsdk.plausibility import SensorGate
from agentsdk.types import JointInfo

PERIOD = 0.01
JOINTS = (
    JointInfo("a", "revolute", -1.0, 1.0, max_velocity=2.0, max_effort=100.0),
    JointInfo("b", "revolute", -1.0, 1.0, max_velocity=2.0, max_effort=100.0),
)


def gate(age: np.ndarray | None = None, **kw: float) -> tuple[SensorGate, np.ndarray]:
    state = np.zeros((3, len(JOINTS)))
    opts = {"margin": 2.0, "floor": 0.02, "tolerance": 0.1} | kw
    g = SensorGate(JOINTS, state[0], state[1], state[2], margin=opts["margin"], floor=opts["floor"],
                   tolerance=opts["tolerance"], period=PERIOD, age=(lambda: age) if age is not None else None)
    assert g.baseline(np.zeros(2), np.zeros(2), np.zeros(2), 0.0) == -1
    return g, state


def read(g: SensorGate, t: float, a: float, b: float = 0.0, va: float = 0.0, ea: float = 0.0) -> None:
    g.accept(np.array([a, b]), np.array([va, 0.0]), np.array([ea, 0.0]), t)


def test_a_fast_but_reachable_motion_passes_and_a_jump_is_a_fault_keeping_the_last_plausible_state() -> None:
    g, st = gate()
    # reach per reading: 2 x 2 rad/s x (0.01 + 0.01) s + 0.02 = 0.1 rad
    q = 0.0
    for k in range(1, 30):
        q = min(q + 0.035, 0.9)  # 3.5 rad/s: beyond max_velocity, within the margin
        read(g, k * PERIOD, q)
        assert not g.pending
    assert st[0, 0] == pytest.approx(0.9)
    read(g, 0.2, 0.9 + 0.15)  # 0.15 rad in 10 ms: 15 rad/s
    (r,) = g.take_new()
    assert (r.index, r.quantity, r.value, r.last) == (0, "position", pytest.approx(1.05), pytest.approx(0.9))
    assert "from the last plausible 0.9" in r.reason and "max_velocity 2" in r.reason
    assert st[0, 0] == pytest.approx(0.9) and g.suspect.tolist() == [True, False]
    read(g, 0.21, 0.9)  # the sensor recovers: plausible again, taken back, not reported twice
    assert not g.pending and not g.suspect.any()


@pytest.mark.parametrize("which", ["position", "velocity", "effort"])
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_a_non_finite_value_is_a_fault(which: str, value: float) -> None:
    g, st = gate()
    read(g, PERIOD, 0.01, 0.0, 0.1, 0.2)
    args = {"position": (value, 0.0, 0.0), "velocity": (0.0, value, 0.0), "effort": (0.0, 0.0, value)}[which]
    read(g, 2 * PERIOD, args[0], 0.0, args[1], args[2])
    (r,) = g.take_new()
    assert r.quantity == which and r.index == 0
    assert np.isfinite(st).all() and st[0, 0] == pytest.approx(0.01) and st[1, 0] == pytest.approx(0.1)


def test_the_reach_covers_a_joint_already_faster_than_its_limit() -> None:
    """A link falling with torque off may exceed max_velocity: its own measured speed extends the reach."""
    g, _ = gate()
    q, v = 0.0, 0.0
    for k in range(1, 60):
        v += 30.0 * PERIOD  # 30 rad/s^2, no limit in a fall
        q += v * PERIOD
        read(g, k * PERIOD, q, 0.0, v)
        assert not g.pending, (k, q, v)
    assert v > 8 * JOINTS[0].max_velocity


def test_a_late_reading_credits_its_age() -> None:
    """A bus reading repeats an old reply, then a fresh one arrives: the motion since the old sample counts."""
    age = np.zeros(2)
    g, _ = gate(age)
    read(g, 0.01, 0.02)
    age[0] = 0.01  # the next two readings repeat the reply sampled at t = 0.01
    read(g, 0.02, 0.02)
    age[0] = 0.02
    read(g, 0.03, 0.02)
    age[0] = 0.0
    # 0.15 rad in the 30 ms since that sample: reach 2 x 2 rad/s x (0.03 + 0.01) s + 0.02 = 0.18
    read(g, 0.04, 0.02 + 0.15)
    assert not g.pending
    # without the age, the same jump between two 10 ms readings is a fault (reach 0.1)
    g2, _ = gate()
    for t in (0.01, 0.02, 0.03):
        read(g2, t, 0.02)
    read(g2, 0.04, 0.17)
    assert [r.index for r in g2.take_new()] == [0]


def test_leaving_the_limits_in_one_step_after_an_outage_is_a_fault() -> None:
    """After the sensor failed for a long time the reach is large, but a reading far past the limits
    must still be reachable from the last plausible position in one step."""
    g, st = gate()
    read(g, 0.01, 0.5)
    read(g, 0.02, math.nan)  # the sensor fails
    assert [r.quantity for r in g.take_new()] == ["position"]
    read(g, 3.0, 0.7)  # 3 s later, inside the limits: plausible (it may have moved)
    assert not g.pending and st[0, 0] == pytest.approx(0.7)
    read(g, 3.01, math.nan)
    g.take_new()
    g.clear()
    read(g, 6.0, 5.0)  # far past the limits + tolerance after an outage: not in one step
    (r,) = g.take_new()
    assert "outside the limits" in r.reason and st[0, 0] == pytest.approx(0.7)


def test_a_frame_change_on_purpose_is_not_a_fault() -> None:
    state = np.zeros((3, 2))
    changing = np.zeros(2, dtype=bool)
    changes = [0]
    g = SensorGate(JOINTS, state[0], state[1], state[2], margin=2.0, floor=0.02, tolerance=0.1, period=PERIOD,
                   changing=changing, changes=changes)
    g.baseline(np.array([0.8, 0.0]), np.zeros(2), np.zeros(2), 0.0)
    changing[0] = True
    changes[0] = 1
    read(g, 0.01, 0.0)  # a new zero: 0.8 -> 0.0 at once
    assert not g.pending and state[0, 0] == 0.0
    changing[0] = False
    changes[0] = 0
    read(g, 0.02, 0.8)
    assert g.pending


def test_the_fast_path_allocates_no_array() -> None:
    import tracemalloc

    g, _ = gate()
    q, v, e = np.zeros(2), np.zeros(2), np.zeros(2)
    for k in range(1, 50):
        g.accept(q, v, e, k * PERIOD)
    tracemalloc.start()
    try:
        before = tracemalloc.take_snapshot()
        for k in range(50, 1050):
            g.accept(q, v, e, k * PERIOD)
        after = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
    grown = sum(s.size_diff for s in after.compare_to(before, "lineno") if "plausibility" in str(s.traceback))
    assert grown < 1000, grown


# --------------------------------------------------------------- robots that must not trip it
@pytest.mark.parametrize("backend", ["mock", "mujoco", "pybullet"])
async def test_full_speed_moves_and_a_fall_with_torque_off_are_not_sensor_faults(backend: str) -> None:
    # (lockstep: the wall-clock stall watchdog protects nothing here and trips on a busy host)
    async with agentsdk.connect(backend, robot="arm3", safety={"stall_timeout": None}) as robot:
        for _ in range(3):
            for sign in (1.0, -1.0):
                goal = {j.name: sign * 0.8 * min(j.upper, 2.0) for j in robot.joints}
                await robot.move_to(goal)
        assert robot.safety.state is SafetyState.OK, robot.safety.events
        await robot.command(JointCommand("position", {j.name: 0.0 for j in robot.joints}))
        await robot.clock.sleep(1.0)
        await robot.estop(0)  # torque off: the arm falls under gravity, as fast as it falls
        await robot.clock.sleep(2.0)
        assert not [e for e in robot.safety.events if e.kind == "sensor"], robot.safety.events
        assert robot.safety.state is SafetyState.ESTOP


async def test_sensor_check_off_takes_readings_as_they_are() -> None:
    async with agentsdk.connect("mock", robot="arm3", safety={"sensor_check": False, "stall_timeout": None}) as robot:
        assert robot.safety.sensor_gate is None
        backend = robot.backend
        real = backend._read

        def nan_read():  # type: ignore[no-untyped-def]
            q, v, e = real()
            q = np.array(q, dtype=float)
            q[0] = math.nan
            return q, v, e

        backend._read = nan_read  # type: ignore[method-assign]
        try:
            await robot.clock.sleep(0.05)
            assert math.isnan(robot.latest_state().position[0])
        finally:
            del backend._read


async def test_sensor_fault_stop_category_0_removes_torque() -> None:
    async with agentsdk.connect("mock", robot="arm3", safety={"sensor_fault_stop": 0, "stall_timeout": None}) as robot:
        await robot.clock.sleep(0.05)
        backend = robot.backend
        real = backend._read
        once = [True]

        def spoof():  # type: ignore[no-untyped-def]
            q, v, e = real()
            if once[0]:
                once[0] = False
                q = np.array(q, dtype=float)
                q[1] += 5.0
            return q, v, e

        backend._read = spoof  # type: ignore[method-assign]
        try:
            await robot.clock.sleep(0.05)
        finally:
            del backend._read
        assert robot.safety.state is SafetyState.FAULT
        await robot.safety.wait_stopped()
        assert not robot.torque_enabled
        assert isinstance(robot.safety.cause, agentsdk.SensorFault) and robot.safety.cause.joint == "joint2"


def test_after_a_loop_stall_a_reading_far_past_the_limits_is_a_fault_and_one_inside_is_not() -> None:
    """A stalled loop reads again after 0.5 s: the joint may have moved anywhere inside its limits, but a
    leap more than the tolerance past them is not something a joint does in one step."""
    g, st = gate()
    read(g, 0.5, -0.6)  # 0.6 rad in 0.5 s at max_velocity 2: plausible
    assert not g.pending and st[0, 0] == pytest.approx(-0.6)
    read(g, 1.0, -0.6, 1.5)  # joint b: 0.4 rad past its upper limit 1.0 (+ 0.1) after another stall
    (r,) = g.take_new()
    assert r.index == 1 and "outside the limits" in r.reason and st[0, 1] == 0.0


def test_huge_finite_velocities_and_efforts_take_the_fast_path() -> None:
    """The fast path learns 'every velocity and effort is finite' from their sum; a sum that overflows
    (finite values, an infinite sum) asks the elements: the reading is taken as on any fast tick."""
    g, st = gate()
    read(g, PERIOD, 0.01)
    calls: list[float] = []
    full = g._full
    g._full = lambda *a: calls.append(a[3]) or full(*a)  # type: ignore[method-assign]
    g.accept(np.array([0.02, 0.0]), np.array([1e308, 1e308]), np.array([1e308, -1e308]), 2 * PERIOD)
    assert not calls and not g.pending
    assert st[1].tolist() == [1e308, 1e308] and st[2].tolist() == [1e308, -1e308]
