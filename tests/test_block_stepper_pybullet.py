"""Block lockstep's backend half on PyBullet (issue 28 item 4): K ticks in one call are tick-by-tick bit for bit.

``backends.pybullet.block.BlockStepper`` runs the setpoints of a moving reference (and a hold) on
arm3 and humanoid; its readings equal a tick-by-tick run from the same start (``write``,
``substeps``, ``read``), a restore to any tick continues identically tick by tick (joint state
put back with ``resetJointStatesMultiDof``, not ``saveState``), a block ends after the first
tick that leaves a contact point and a restore from there (that point still in PyBullet's contact
cache) continues identically too, through the contact; a substep that diverges ends the block at
that tick with the backend's own error, and no block runs where the stepper cannot reproduce the
ticks (a replaced step, a floating base).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk.errors import BackendUnavailableError, InvalidValueError, SimulationDiverged
from agentsdk.loop import Setpoint
from agentsdk.registry import load_backend

try:
    load_backend("pybullet")
except BackendUnavailableError:  # pragma: no cover - an install without the extra
    pytest.skip("pybullet is not installed", allow_module_level=True)

import pybullet as p

from agentsdk.backends.pybullet.block import BlockStepper

SAFETY = {"stall_timeout": 5.0}


def _rows(robot: agentsdk.Robot, ticks: int, seed: int, amp: float, hold: bool = False) -> np.ndarray:
    """(ticks, 7, n) setpoint rows: a sum of sines around the current pose (velocity, acceleration), or a hold."""
    b = robot.backend
    n = len(b.names)
    rng = np.random.default_rng(seed)
    q0 = np.array(b.read()[0])
    t = np.arange(1, ticks + 1)[:, None] * b.period
    w = rng.uniform(1.0, 6.0, n)
    ph = rng.uniform(0.0, 2 * np.pi, n)
    a = 0.0 if hold else amp
    rows = np.zeros((ticks, 7, n))
    rows[:, 0] = q0 + a * (np.sin(w * t + ph) - np.sin(ph))
    rows[:, 1] = a * w * np.cos(w * t + ph)
    rows[:, 6] = -a * w * w * np.sin(w * t + ph)
    rows[:, 3] = [g.p for g in robot.gains.values()]
    rows[:, 4] = [g.d for g in robot.gains.values()]
    rows[:, 5] = rows[:, 0]
    return rows


def _setpoint(robot: agentsdk.Robot) -> Setpoint:
    sp = Setpoint(len(robot.backend.names))
    sp.enabled[:] = True
    sp.mode[:] = np.asarray(robot.setpoint.mode)
    return sp


def _ticks(b: Any, sp: Setpoint, rows: np.ndarray, k0: int, k1: int) -> list[bytes]:
    """Ticks ``k0 .. k1 - 1`` one by one: write, the substeps, read (each reading's bytes)."""
    out = []
    for k in range(k0, k1):
        sp.block[...] = rows[k]
        b.write(sp.view)
        b.substeps()
        q, v, e = b.read()
        out.append(q.tobytes() + v.tobytes() + e.tobytes())
    return out


def _block(b: Any, stepper: BlockStepper, sp: Setpoint, rows: np.ndarray, count: int) -> tuple[int, np.ndarray]:
    readings = np.empty((stepper.capacity, 3, len(b.names)))

    def write(k: int) -> bool:
        sp.block[...] = rows[k]
        b.write(sp.view)
        return True

    done = stepper.run(write, count, readings)
    return done, readings


def _reading(readings: np.ndarray, k: int) -> bytes:
    return b"".join(np.ascontiguousarray(readings[k, i]).tobytes() for i in range(3))


@pytest.mark.parametrize("robot_name", ["arm3", "humanoid"])
@pytest.mark.parametrize("hold", [False, True])
async def test_a_block_is_tick_by_tick_bit_for_bit_and_restores_any_tick(robot_name: str, hold: bool) -> None:
    async with agentsdk.connect("pybullet", robot=robot_name, safety=SAFETY, block_lockstep=False) as robot:
        b = robot.backend
        K = 120
        rows = _rows(robot, K, seed=3, amp=0.1, hold=hold)  # (no contact: see the next test)
        sp = _setpoint(robot)
        stepper = b.block_stepper(K)
        assert stepper.ready()
        assert stepper.controls(rows, sp.view) is None  # g(q) needs the measured state: every tick writes
        done, readings = _block(b, stepper, sp, rows, K)
        assert done == K and stepper.fault is None
        got = [_reading(readings, k) for k in range(K)]
        end = _ticks(b, sp, rows[-1:].repeat(3, axis=0), 0, 3)  # the state the block left, stepped on
        # the same ticks from the same start, one by one
        stepper.restore(0, lambda j: None)
        want = _ticks(b, sp, rows, 0, K)
        assert got == want
        assert _ticks(b, sp, rows[-1:].repeat(3, axis=0), 0, 3) == end
        # a restore to any tick continues as the block did (the state, the effort, the backend's time)
        for k in (K, 0, 1, 17, 64, K - 1):
            start = b"".join(np.array(x).tobytes() for x in b.read())
            done, readings = _block(b, stepper, sp, rows, K)  # (from wherever the last check left it)
            stepper.restore(k, lambda j: None)
            # the reading is the start state of tick k: what tick k - 1 read (tick 0: before the block)
            assert b"".join(np.array(x).tobytes() for x in b.read()) == (_reading(readings, k - 1) if k else start)
            again = _ticks(b, sp, rows, k, K)
            assert again == [_reading(readings, j) for j in range(k, K)], k
        with pytest.raises(InvalidValueError):
            stepper.restore(K + 1, lambda j: None)
        with pytest.raises(InvalidValueError):
            stepper.run(lambda k: True, K + 1, readings)


async def test_a_block_ends_after_a_contact_and_a_restore_from_there_is_tick_by_tick() -> None:
    """The humanoid swings its limbs into each other: the block ends at the first tick that leaves a contact
    point; a restore to any tick of it (the point left in the contact cache) goes on as tick by tick."""
    async with agentsdk.connect("pybullet", robot="humanoid", safety=SAFETY, block_lockstep=False) as robot:
        b = robot.backend
        cid = b._cid
        K = 1500
        rows = _rows(robot, K, seed=1, amp=1.5)
        sp = _setpoint(robot)
        stepper = b.block_stepper(K)
        assert stepper.ready()
        done, readings = _block(b, stepper, sp, rows, K)
        got = [_reading(readings, k) for k in range(done)]
        assert p.getContactPoints(physicsClientId=cid) and not stepper.ready()  # ticks run one by one now
        # the reference: from the same start, tick by tick, and the ticks after which PyBullet holds contacts
        stepper.restore(0, lambda j: None)
        want, touching = [], []
        for k in range(K):
            want += _ticks(b, sp, rows, k, k + 1)
            touching.append(bool(p.getContactPoints(physicsClientId=cid)))
        first = touching.index(True)
        assert 5 < first < K - 200  # (this motion touches: the test would not test otherwise)
        assert done == first + 1 and stepper.fault is None and got == want[:done]
        # a restore to any tick of the block, with contact points in the cache: the same ticks follow,
        # through the contact and on
        for k in (done - 1, done // 2, 0):
            stepper.restore(0, lambda j: None)
            assert _block(b, stepper, sp, rows, K)[0] == done
            stepper.restore(k, lambda j: None)
            assert _ticks(b, sp, rows, k, done + 150) == want[k:done + 150], k


async def test_a_substep_that_diverges_ends_the_block_with_the_backends_error() -> None:
    async with agentsdk.connect("pybullet", robot="arm3", safety=SAFETY, block_lockstep=False) as robot:
        b = robot.backend
        cid = b._cid
        K = 40
        rows = _rows(robot, K, seed=5, amp=0.2)
        sp = _setpoint(robot)
        stepper = b.block_stepper(K)
        g = p.getPhysicsEngineParameters(physicsClientId=cid)
        gravity = [g["gravityAccelerationX"], g["gravityAccelerationY"], g["gravityAccelerationZ"]]

        def blow_up(k: int) -> None:  # from tick 25 on, a gravity no servo holds: the joints' speed diverges
            p.setGravity(*(gravity if k < 25 else [0.0, 0.0, -1e12]), physicsClientId=cid)

        def write(k: int) -> bool:
            blow_up(k)
            sp.block[...] = rows[k]
            b.write(sp.view)
            return True

        readings = np.empty((K, 3, len(b.names)))
        done = stepper.run(write, K, readings)
        assert done == 25 and isinstance(stepper.fault, SimulationDiverged)
        stepper.restore(0, lambda j: None)
        with pytest.raises(SimulationDiverged) as tick_by_tick:
            for k in range(K):
                blow_up(k)
                _ticks(b, sp, rows, k, k + 1)
        assert str(stepper.fault) == str(tick_by_tick.value)
        stepper.restore(0, lambda j: None)
        assert stepper.run(write, K, readings) == done
        stepper.restore(done, lambda j: None)  # before the tick that diverged: it diverges again, alike
        with pytest.raises(SimulationDiverged) as again:
            _ticks(b, sp, rows, done, done + 1)
        assert str(again.value) == str(tick_by_tick.value)


async def test_no_block_where_the_stepper_cannot_reproduce_the_ticks() -> None:
    async with agentsdk.connect("pybullet", robot="arm3", safety=SAFETY) as robot:
        runner = robot.block_runner
        assert runner is not None  # on by default on PyBullet too
        b = robot.backend
        step = b.substeps
        calls = 0

        def counting() -> None:
            nonlocal calls
            calls += 1
            step()

        b.substeps = counting  # type: ignore[method-assign]
        try:
            ran = runner.block_ticks
            await robot.clock.sleep(0.1)
            assert calls > 0 and runner.block_ticks == ran  # a replaced step is not bypassed
        finally:
            del b.substeps
        await robot.clock.sleep(0.1)
        assert runner.block_ticks > ran
    async with agentsdk.connect("pybullet", robot="leveler", safety=SAFETY) as robot:
        runner = robot.block_runner
        assert runner is not None
        await robot.clock.sleep(0.1)
        assert runner.blocks == 0  # a floating base: every tick on its own
