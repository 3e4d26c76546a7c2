"""Block lockstep's backend half (issue 28 item 1): K ticks in one call are tick-by-tick bit for bit.

``backends.mujoco.block.BlockStepper`` runs the setpoints of a moving reference (and a hold) on
arm3 and humanoid; its readings and MuJoCo states equal a tick-by-tick run from the same start
(``write``, ``await step``, ``read``), a restore to any tick continues identically tick by tick,
and a step that diverges ends the block at that tick with the backend's own error.
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Callable
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

import agentsdk
from agentsdk.backends.mujoco.block import BlockStepper
from agentsdk.errors import InvalidValueError, SimulationDiverged
from agentsdk.loop import Setpoint

SAFETY = {"stall_timeout": 5.0}
_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


def _stream(robot: agentsdk.Robot, ticks: int, seed: int, hold: bool) -> list[Setpoint]:
    """Setpoints of a smooth move (position, velocity, acceleration) from the current pose, or a hold."""
    b = robot.backend
    n = len(b.names)
    rng = np.random.default_rng(seed)
    q0 = b.data.qpos[b._qadr].copy()
    lo = np.where(np.isfinite(b.lower), b.lower, -np.pi)
    hi = np.where(np.isfinite(b.upper), b.upper, np.pi)
    goal = q0 if hold else np.clip(q0 + rng.uniform(-0.3, 0.3, n), lo, hi)
    duration = ticks * b.period
    kp = np.array([g.p for g in robot.gains.values()])
    kd = np.array([g.d for g in robot.gains.values()])
    out = []
    for k in range(ticks):
        s = (k + 1) / ticks
        sp = Setpoint(n)
        sp.position[:] = q0 + (10 * s**3 - 15 * s**4 + 6 * s**5) * (goal - q0)
        sp.velocity[:] = (30 * s**2 - 60 * s**3 + 30 * s**4) / duration * (goal - q0)
        sp.acceleration[:] = (60 * s - 180 * s**2 + 120 * s**3) / duration**2 * (goal - q0)
        sp.kp[:], sp.kd[:], sp.target[:] = kp, kd, goal
        out.append(sp)
    return out


@pytest.mark.parametrize("robot_name", ["arm3", "humanoid"])
@pytest.mark.parametrize("hold", [False, True])
async def test_a_block_is_tick_by_tick_bit_for_bit_and_restores_any_tick(robot_name: str, hold: bool) -> None:
    async with agentsdk.connect("mujoco", robot=robot_name, safety=SAFETY) as robot:
        b = robot.backend
        m, d = b.model, b.data
        n, K = len(b.names), 120
        stream = _stream(robot, K, seed=3, hold=hold)
        start = np.empty(mujoco.mj_stateSize(m, _STATE))
        mujoco.mj_getState(m, d, start, _STATE)
        expected = np.empty((K, 3, n))
        states = np.empty((K, start.size))
        for k, sp in enumerate(stream):
            b.write(sp.view)
            await b.step(b.period)
            q, v, e = b.read()
            expected[k] = (q, v, e)
            mujoco.mj_getState(m, d, states[k], _STATE)
        mujoco.mj_setState(m, d, start, _STATE)
        stepper = BlockStepper(b, K)
        readings = np.empty((K, 3, n))
        assert stepper.run(lambda k: b.write(stream[k].view), K, readings) == K
        assert stepper.fault is None
        assert readings.tobytes() == expected.tobytes()
        # a restore to tick k (from the latest checkpoint, replaying the ticks after it) puts MuJoCo
        # where tick by tick stood after tick k - 1 (its physics and warm start)
        sig = mujoco.mjtState.mjSTATE_FULLPHYSICS | mujoco.mjtState.mjSTATE_WARMSTART
        got, want = (np.empty(mujoco.mj_stateSize(m, sig)) for _ in range(2))
        rewrite = lambda k: b.write(stream[k].view)  # noqa: E731
        for k in range(1, K + 1):
            stepper.restore(k, rewrite)
            mujoco.mj_getState(m, d, got, sig)
            mujoco.mj_setState(m, d, states[k - 1], _STATE)
            mujoco.mj_getState(m, d, want, sig)
            assert got.tobytes() == want.tobytes(), k
        if not hold:
            assert np.abs(readings[-1, 0] - readings[0, 0]).max() > 0.05  # it moved
        # roll back to a tick inside the block (on a checkpoint or between) and continue tick by tick:
        # the same readings
        assert stepper.every == 16
        for k0 in (0, 16, 37, K - 1, K):
            stepper.restore(k0, rewrite)
            for k in range(k0, K):
                b.write(stream[k].view)
                await b.step(b.period)
                q, v, e = b.read()
                assert np.array([q, v, e]).tobytes() == expected[k].tobytes(), (k0, k)
        with pytest.raises(InvalidValueError):
            stepper.restore(K + 1, rewrite)
        with pytest.raises(InvalidValueError):
            stepper.run(lambda k: None, K + 1, readings)


async def _diverging_tick_by_tick(robot: agentsdk.Robot, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """Rows written, stepped and read tick by tick until one diverges: the readings, MuJoCo's state after the
    divergence and the backend's error; then MuJoCo and the backend back at the start, warning counters included."""
    b = robot.backend
    m, d = b.model, b.data
    start = np.empty(mujoco.mj_stateSize(m, _STATE))
    mujoco.mj_getState(m, d, start, _STATE)
    warn0 = (d.warning.number.copy(), d.warning.lastinfo.copy(), b._warn.copy(), b._warn_bytes)
    sp = Setpoint(len(b.names))
    expected = np.empty((len(rows), 3, len(b.names)))
    with pytest.raises(SimulationDiverged) as tick_by_tick:
        for k, row in enumerate(rows):
            sp.block[...] = row
            b.write(sp.view)
            await b.step(b.period)
            expected[k] = b.read()
    after = np.empty_like(start)
    mujoco.mj_getState(m, d, after, _STATE)
    mujoco.mj_setState(m, d, start, _STATE)
    d.warning.number[:], d.warning.lastinfo[:] = warn0[0], warn0[1]
    b._warn[:], b._warn_bytes = warn0[2], warn0[3]
    return expected, after, str(tick_by_tick.value)


async def test_a_diverging_step_ends_the_block_with_the_backends_error() -> None:
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
        b = robot.backend
        m, d = b.model, b.data
        n, K, bad = len(b.names), 30, 17
        stream = _stream(robot, K, seed=5, hold=False)
        stream[bad].effort[0] = np.inf  # MuJoCo rejects the control: a divergence warning
        expected, after, error = await _diverging_tick_by_tick(robot, np.stack([sp.block for sp in stream]))
        stepper = BlockStepper(b, K)
        readings = np.empty((K, 3, n))
        assert stepper.run(lambda k: b.write(stream[k].view), K, readings) == bad
        assert str(stepper.fault) == error
        assert readings[:bad].tobytes() == expected[:bad].tobytes()
        got = np.empty_like(after)
        mujoco.mj_getState(m, d, got, _STATE)
        assert got.tobytes() == after.tobytes()


@pytest.mark.parametrize("robot_name", ["arm3", "humanoid"])
async def test_a_hold_written_once_is_written_every_tick_bit_for_bit(robot_name: str) -> None:
    """``write_once``: ``mj_step`` leaves the controls as written, so a hold's block writes at tick 0 only."""
    async with agentsdk.connect("mujoco", robot=robot_name, safety=SAFETY) as robot:
        b = robot.backend
        m, d = b.model, b.data
        assert b.gravity_route != "host"
        n, K = len(b.names), 90
        moving = _stream(robot, K, seed=7, hold=False)
        hold = _stream(robot, K, seed=7, hold=True)
        hold[0].position[:] = moving[-1].position  # a step to another pose, held: the servos pull
        start = np.empty(mujoco.mj_stateSize(m, _STATE))
        mujoco.mj_getState(m, d, start, _STATE)
        # the controls after each step of a moving reference (speeds, contacts, clamped controls) are
        # the bytes written before it
        for sp in moving:
            b.write(sp.view)
            ctrl = d.ctrl.tobytes()
            await b.step(b.period)
            assert d.ctrl.tobytes() == ctrl
        mujoco.mj_setState(m, d, start, _STATE)
        stepper = BlockStepper(b, K)
        assert stepper.write_once
        every, once = np.empty((K, 3, n)), np.empty((K, 3, n))
        assert stepper.run(lambda k: b.write(hold[0].view), K, every) == K
        mujoco.mj_setState(m, d, start, _STATE)
        assert stepper.run(lambda k: None if k else b.write(hold[0].view), K, once) == K
        assert once.tobytes() == every.tobytes()
        assert np.abs(every[-1, 0] - every[0, 0]).max() > 0.01  # the servos pulled it over


_PANDA = str(Path(str(importlib.metadata.distribution("example-robot-data").locate_file(
    "cmeel.prefix/share/example-robot-data/robots"))) / "panda_description/urdf/panda.urdf")


@pytest.mark.parametrize("robot_name", ["arm3", "humanoid", "panda"])
async def test_a_blocks_controls_are_the_writes_bit_for_bit(robot_name: str) -> None:
    """``controls(rows)`` computes the ctrl each tick's ``write`` leaves, for moving, resting and odd references.

    Rows at rest, with -0.0, tiny velocities whose squares round to 0 (the feed-forward's ``moving``
    says no), accelerations only, and gains and feed-forward efforts that vary per row; Panda's
    mimic fingers take the feed-forward's follower path.
    """
    name = _PANDA if robot_name == "panda" else robot_name
    async with agentsdk.connect("mujoco", robot=name, safety=SAFETY) as robot:
        b = robot.backend
        n = len(b.names)
        rng = np.random.default_rng(11)
        stepper = b.block_stepper(200)
        stream = _stream(robot, 200, seed=5, hold=False)
        rows = np.stack([sp.block for sp in stream])
        rows[:, 2] = rng.normal(0.0, 0.5, size=(200, n))  # effort feed-forward
        rows[:, 3:5] *= rng.uniform(0.5, 1.5, size=(200, 2, 1))
        rows[10:20, 1] = rows[10:20, 6] = 0.0  # at rest
        rows[20:25, 1] = rows[20:25, 6] = -0.0
        rows[25:30, 1], rows[25:30, 6] = 1e-170, 0.0  # squares round to 0: at rest for the feed-forward
        rows[30:35, 1] = 0.0  # accelerating from rest
        rows[35:40, 1] = 1e-150  # a square that does not round to 0
        sp = Setpoint(n)
        put = stepper.controls(rows, sp.view)
        assert put is not None
        ctrl = b.data.ctrl
        for j in range(len(rows)):
            sp.block[...] = rows[j]
            b.write(sp.view)
            expected = ctrl.tobytes()
            ctrl[...] = np.nan
            put(j)
            assert ctrl.tobytes() == expected, j
        sp.enabled[0] = False  # a joint with torque off: each tick writes its setpoint
        assert stepper.controls(rows, sp.view) is None


# ----------------------------------------------------------------------------- the open loop (one rollout)


async def _tick_by_tick(robot: agentsdk.Robot, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, bytes]:
    """Each row written, stepped and read as the loop does: the readings, the states, the last derived arrays."""
    b = robot.backend
    m, d = b.model, b.data
    sp = Setpoint(len(b.names))
    expected = np.empty((len(rows), 3, len(b.names)))
    states = np.empty((len(rows), mujoco.mj_stateSize(m, _STATE)))
    for k, row in enumerate(rows):
        sp.block[...] = row
        b.write(sp.view)
        await b.step(b.period)
        expected[k] = b.read()
        mujoco.mj_getState(m, d, states[k], _STATE)
    derived = d.xpos.tobytes() + d.qfrc_actuator.tobytes() + d.actuator_force.tobytes() + d.sensordata.tobytes()
    return expected, states, derived


def _open_loop_writes(b: Any, sp: Setpoint, rows: np.ndarray,
                      put: Callable[[int], None] | None) -> tuple[Callable[[int], None], list[int]]:
    """An open-loop block's ``write``: tick 0's setpoint through the backend, then ``put(k)`` (None: nothing),
    and the list of the ticks it was called for."""
    writes: list[int] = []

    def write(k: int) -> None:
        writes.append(k)
        if k == 0:
            sp.block[...] = rows[0]
            b.write(sp.view)
        elif put is not None:
            put(k)

    return write, writes


@pytest.mark.parametrize("robot_name", ["arm3", "humanoid"])
@pytest.mark.parametrize("rate", [1000.0, 500.0, 200.0])  # 1, 2 and 5 physics steps per tick
@pytest.mark.parametrize("hold", [False, True])
async def test_an_open_loop_block_is_one_rollout_and_tick_by_tick_bit_for_bit(
    robot_name: str, rate: float, hold: bool,
) -> None:
    """``run(..., stop, controls)``: tick 0's write, then one ``mujoco.rollout``, the same bits as tick by tick.

    With applied forces set (a rollout resets the user inputs it is not given), a motion's
    precomputed controls or a hold written once; the readings, the state (warm start included) and
    the arrays MuJoCo derives in a step (poses, actuation, sensors) end as tick by tick left them, the
    warning counters unchanged, and a restore to any tick (replayed from tick 0) is tick by tick's.
    """
    async with agentsdk.connect("mujoco", robot=robot_name, safety=SAFETY, update_rate=rate) as robot:
        b = robot.backend
        m, d = b.model, b.data
        n, K = len(b.names), 70
        d.qfrc_applied[:] = 0.01
        d.xfrc_applied[2, :] = (0.3, -0.2, 0.1, 0.01, 0.0, -0.01)
        d.warning.lastinfo[int(mujoco.mjtWarning.mjWARN_CONTACTFULL)] = 7  # (a rollout clears it: it comes back)
        rows = np.stack([sp.block for sp in _stream(robot, K, seed=4, hold=hold)])
        start = np.empty(mujoco.mj_stateSize(m, _STATE))
        mujoco.mj_getState(m, d, start, _STATE)
        warnings = d.warning.number.tobytes() + d.warning.lastinfo.tobytes()
        expected, states, derived = await _tick_by_tick(robot, rows)
        mujoco.mj_setState(m, d, start, _STATE)
        stepper = BlockStepper(b, K)
        sp = Setpoint(n)
        put = None if hold else stepper.controls(rows, sp.view)
        assert hold or put is not None
        write, writes = _open_loop_writes(b, sp, rows, put)

        readings = np.full((K, 3, n), np.nan)
        assert stepper.run(write, K, readings, lambda: False, put) == K
        assert writes == [0]  # one rollout after tick 0's write
        assert stepper.fault is None
        assert readings.tobytes() == expected.tobytes()
        got = np.empty_like(start)
        mujoco.mj_getState(m, d, got, _STATE)
        assert got.tobytes() == states[-1].tobytes()
        assert d.xpos.tobytes() + d.qfrc_actuator.tobytes() + d.actuator_force.tobytes() + d.sensordata.tobytes() \
            == derived
        assert d.warning.number.tobytes() + d.warning.lastinfo.tobytes() == warnings
        if not hold:
            assert np.abs(readings[-1, 0] - readings[0, 0]).max() > 0.05  # it moved

        def rewrite(k: int) -> None:
            sp.block[...] = rows[k]
            b.write(sp.view)

        for k in (K - 1, 37, 16, 1, K):  # (the end again, after restores: replayed from tick 0 too)
            stepper.restore(k, rewrite)
            mujoco.mj_getState(m, d, got, _STATE)
            assert got.tobytes() == states[k - 1].tobytes(), k


async def test_a_stop_during_the_rollout_puts_mujoco_back_before_tick_0() -> None:
    """``stop()`` true after the rollout (an e-stop landed meanwhile): no tick done, state and counters as before."""
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
        b = robot.backend
        m, d = b.model, b.data
        n, K = len(b.names), 40
        rows = np.stack([sp.block for sp in _stream(robot, K, seed=8, hold=False)])
        sp = Setpoint(n)
        stepper = BlockStepper(b, K)
        put = stepper.controls(rows, sp.view)
        start = np.empty(mujoco.mj_stateSize(m, _STATE))
        mujoco.mj_getState(m, d, start, _STATE)
        d.warning.lastinfo[int(mujoco.mjtWarning.mjWARN_CNSTRFULL)] = 2  # (a rollout clears it: it comes back)
        warn = (d.warning.number.tobytes(), d.warning.lastinfo.tobytes(), b._warn_bytes)
        asked: list[float] = []

        def write(k: int) -> None:
            sp.block[...] = rows[k]
            b.write(sp.view)

        def stop() -> bool:
            asked.append(d.time)  # asked once, after the rollout
            return True

        readings = np.zeros((K, 3, n))
        assert stepper.run(write, K, readings, stop, put) == 0
        assert len(asked) == 1 and asked[0] > 0.9 * K * b.period
        got = np.empty_like(start)
        mujoco.mj_getState(m, d, got, _STATE)
        assert got.tobytes() == start.tobytes()
        assert (d.warning.number.tobytes(), d.warning.lastinfo.tobytes(), b._warn_bytes) == warn
        assert not readings.any()


async def test_a_diverging_step_in_an_open_loop_block_ends_it_as_tick_by_tick() -> None:
    """A rollout stops at a warning: the block runs again tick by tick and ends at that tick with the backend's error.
    """
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
        b = robot.backend
        m, d = b.model, b.data
        n, K, bad = len(b.names), 30, 17
        rows = np.stack([sp.block for sp in _stream(robot, K, seed=5, hold=False)])
        rows[bad, 2, 0] = np.inf  # MuJoCo rejects the control: a divergence warning
        expected, after, error = await _diverging_tick_by_tick(robot, rows)
        sp = Setpoint(n)
        stepper = BlockStepper(b, K)
        put = stepper.controls(rows, sp.view)
        assert put is not None

        write, writes = _open_loop_writes(b, sp, rows, put)

        readings = np.empty((K, 3, n))
        assert stepper.run(write, K, readings, lambda: False, put) == bad
        # the rollout (tick 0's write only), then the block step by step, then again with the checks
        assert writes == [0, *range(K), *range(bad + 1)]
        assert str(stepper.fault) == error
        assert readings[:bad].tobytes() == expected[:bad].tobytes()
        got = np.empty_like(after)
        mujoco.mj_getState(m, d, got, _STATE)
        assert got.tobytes() == after.tobytes()


async def test_a_replaced_mj_step_or_a_foreign_put_runs_the_block_tick_by_tick(monkeypatch: pytest.MonkeyPatch) -> None:
    """No rollout where it would bypass something (``mujoco.mj_step`` replaced, a ``put`` not this stepper's) or
    log a warning again (MuJoCo has counted one)."""
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
        b = robot.backend
        n, K = len(b.names), 20
        hold = np.stack([sp.block for sp in _stream(robot, 1, seed=1, hold=True)])
        stepper = BlockStepper(b, K)
        readings = np.empty((K, 3, n))
        write, writes = _open_loop_writes(b, Setpoint(n), hold, None)
        step = mujoco.mj_step
        steps: list[int] = []
        monkeypatch.setattr(mujoco, "mj_step", lambda m, d, nstep=1: (steps.append(nstep), step(m, d, nstep=nstep)))
        assert stepper.run(write, K, readings, lambda: False, None) == K
        assert writes == list(range(K)) and len(steps) == K
        monkeypatch.undo()
        writes.clear()
        assert stepper.run(write, K, readings, lambda: False, lambda k: None) == K
        assert writes == list(range(K))
        writes.clear()
        assert stepper.run(write, K, readings, lambda: False, None) == K
        assert writes == [0]
        # MuJoCo has counted a warning: no rollout (it clears the counters, so MuJoCo would log the warning again)
        b.data.warning.number[int(mujoco.mjtWarning.mjWARN_CONTACTFULL)] = 1
        writes.clear()
        assert stepper.run(write, K, readings, lambda: False, None) == K
        assert writes == list(range(K))


async def test_rk4_and_a_control_callback_run_the_block_step_by_step_bit_for_bit() -> None:
    """No rollout where its readings or inputs could differ: RK4 (its last stages skip the sensors the
    efforts come from) or a callback MuJoCo calls inside the step that may change the inputs."""
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY, integrator="rk4") as robot:
        b = robot.backend
        m, d = b.model, b.data
        n, K = len(b.names), 30
        rows = np.stack([sp.block for sp in _stream(robot, K, seed=2, hold=False)])
        start = np.empty(mujoco.mj_stateSize(m, _STATE))
        mujoco.mj_getState(m, d, start, _STATE)
        expected, _states, _derived = await _tick_by_tick(robot, rows)
        mujoco.mj_setState(m, d, start, _STATE)
        stepper = BlockStepper(b, K)
        sp = Setpoint(n)
        put = stepper.controls(rows, sp.view)
        assert put is not None
        write, writes = _open_loop_writes(b, sp, rows, put)

        readings = np.empty((K, 3, n))
        assert stepper.run(write, K, readings, lambda: False, put) == K
        assert writes == list(range(K))
        assert readings.tobytes() == expected.tobytes()
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
        b = robot.backend
        stepper = BlockStepper(b, K)
        hold = np.stack([sp.block for sp in _stream(robot, 1, seed=1, hold=True)])
        write_hold, writes = _open_loop_writes(b, Setpoint(n), hold, None)
        mujoco.set_mjcb_control(lambda m, d: None)
        try:
            assert stepper.run(write_hold, K, readings, lambda: False, None) == K
        finally:
            mujoco.set_mjcb_control(None)
        assert writes == list(range(K))
        writes.clear()
        assert stepper.run(write_hold, K, readings, lambda: False, None) == K
        assert writes == [0]


@pytest.mark.parametrize("realtime", [False, True])
async def test_the_effort_sensors_are_in_a_lockstep_model_only(realtime: bool) -> None:
    """One effort sensor per joint, last in the model, reading the effort ``read()`` returns; none in realtime."""
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY, realtime=realtime) as robot:
        b = robot.backend
        n = len(b.names)
        assert b.model.nsensor == (0 if realtime else n)
        if not realtime:
            await robot.clock.sleep(0.05)
            a = b._effort_sensor_adr
            assert b.data.sensordata[a : a + n].tobytes() == b.read()[2].tobytes()
            assert b.block_stepper(8)._open_loop
