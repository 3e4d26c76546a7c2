"""The inline tick (issue 28, acceptance 2): a behavior that sleeps one period per tick runs the ticks itself.

In lockstep, after a tick that woke the only sleeper, one that sleeps one period per tick, the control
loop lends it the ticks (:meth:`agentsdk.clock.LockstepClock.lend`): its next sleep runs the tick in
its own task when nothing else could run first. Everything observable must be what the control loop
computes tick by tick: these runs compare a lent run with one where the backend does not declare
``step_never_suspends`` (no lending), and check faults, cancellation and steps that suspend.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk import BackendFault, JointCommand
from agentsdk.backends.mock import MockBackend
from agentsdk.clock import LockstepClock
from agentsdk.registry import load_backend, register_backend, unregister_backend

#: guards against a hang (the bug); never a timing assertion
HANG_GUARD = 60.0


def _simulators() -> list[Any]:
    out = []
    for name in ("mock", "mujoco", "pybullet"):
        try:
            load_backend(name)
        except Exception as exc:  # an optional simulator that is not installed
            out.append(pytest.param(name, marks=pytest.mark.skip(reason=f"{name}: {exc}")))
        else:
            out.append(name)
    return out


def _clock(robot: agentsdk.Robot) -> LockstepClock:
    clock = robot.clock
    assert isinstance(clock, LockstepClock)
    return clock


async def _scenario(backend: str) -> tuple[dict[str, Any], int]:
    """One behavior commanding every tick beside others; everything it and the robot saw, and the inline ticks."""
    log: list[tuple[Any, ...]] = []
    rows: list[bytes] = []
    async with agentsdk.connect(backend, robot="arm3") as robot:
        clock = _clock(robot)
        period = robot.control_period
        robot.add_tick_hook(agentsdk.Phase.OBSERVE, lambda t, st, sp: rows.append(b"".join(
            a.tobytes() for a in (st.position, st.velocity, st.effort, sp.position, sp.velocity, sp.effort,
                                  sp.kp, sp.kd, sp.enabled))))
        q0 = (await robot.read()).position.copy()

        async def slow_sleeper() -> None:  # wakes every 13 ticks, between the behavior's
            for j in range(8):
                await clock.sleep(13 * period)
                log.append(("slow", j, robot.ticks, clock.now()))

        async def spawned(k: int) -> None:  # a task started by the behavior: runs before the next tick
            for j in range(3):
                log.append(("spawned", k, j, robot.ticks))
                await asyncio.sleep(0)

        async def behavior() -> None:
            children: list[asyncio.Task[None]] = []
            for k in range(400):
                state = await robot.read()
                log.append(("read", k, robot.ticks, state.stamp, state.position.tobytes()))
                target = q0 + 0.3 * math.sin(0.05 * k)
                if k == 120:
                    target = target + 10.0  # beyond the limits: clamped, an event
                applied = await robot.command(JointCommand("position", target.tolist()))
                log.append(("applied", k, tuple(applied.values.values())))
                if k == 60:
                    children.append(asyncio.create_task(spawned(k)))
                if k == 200:
                    await clock.sleep(3 * period)  # not one period: the control loop ticks
                elif k == 250:
                    await clock.sleep_until(clock.now() + period)
                elif k == 300:
                    await asyncio.sleep(0)  # another kind of wait ends the lease
                    await clock.sleep(period)
                else:
                    await clock.sleep(period)
            await asyncio.gather(*children)

        slow = asyncio.create_task(slow_sleeper())
        async with asyncio.timeout(HANG_GUARD):
            await behavior()
            await slow
            # a robot-time timeout around one-period sleeps (its watcher sleeps too: no lending)
            with pytest.raises(agentsdk.AgentTimeoutError):
                async with clock.timeout(20 * period):
                    while True:
                        await clock.sleep(period)
            log.append(("timeout", robot.ticks))
            # cancelled by another task while it sleeps one period per tick
            runner = asyncio.create_task(_forever(robot, period, log))
            await clock.sleep(30 * period)
            runner.cancel()
            with pytest.raises(asyncio.CancelledError):
                await runner
            log.append(("cancelled", robot.ticks))
        events = [(e.kind, e.detail, e.joint, e.time) for e in robot.safety.events]
        final = (await robot.read()).position.tobytes()
        inline = clock.inline_ticks
    return {"log": log, "rows": rows, "events": events, "final": final}, inline


async def _forever(robot: agentsdk.Robot, period: float, log: list[tuple[Any, ...]]) -> None:
    while True:
        await robot.command(JointCommand("position", (await robot.read()).position.tolist()))
        log.append(("forever", robot.ticks))
        await robot.clock.sleep(period)


@pytest.fixture
def no_lending() -> Iterator[None]:
    """Every backend as one whose step may suspend: the control loop runs every tick."""
    saved = {}
    for name in ("mock", "mujoco", "pybullet"):
        try:
            cls = load_backend(name)
        except Exception:
            continue
        saved[cls] = cls.__dict__["step_never_suspends"]
        cls.step_never_suspends = False
    try:
        yield
    finally:
        for cls, value in saved.items():
            cls.step_never_suspends = value


@pytest.mark.parametrize("backend", _simulators())
async def test_a_behavior_commanding_every_tick_runs_its_ticks_bit_for_bit(backend: str, request: Any) -> None:
    assert load_backend(backend).step_never_suspends
    lent, inline = await _scenario(backend)
    assert inline > 100, "the behavior ran no ticks itself: nothing was compared"
    request.getfixturevalue("no_lending")
    ticked, none = await _scenario(backend)
    assert none == 0
    assert any("clamped" in e[1] for e in lent["events"]), lent["events"]
    for key in ("log", "events", "rows", "final"):
        assert lent[key] == ticked[key], key


async def test_a_fault_in_an_inline_tick_reaches_the_sleeper_and_one_control_loop_runs_after_recovery() -> None:
    async with agentsdk.connect("mock", robot="arm3") as robot:
        clock, period = _clock(robot), robot.control_period
        backend = robot.backend
        assert isinstance(backend, MockBackend)
        robot._loop.batch_seconds = 3600.0  # no lease ends on wall time: the faulting tick runs in the sleep
        async with asyncio.timeout(HANG_GUARD):
            q = (await robot.read()).position.tolist()
            for _ in range(20):
                await robot.command(JointCommand("position", q))
                await clock.sleep(period)
            before = clock.inline_ticks
            assert before > 0
            backend.step_error = True  # the next tick's step faults: that tick runs in the sleep below
            with pytest.raises(BackendFault, match="injected step error"):
                await robot.command(JointCommand("position", q))
                await clock.sleep(period)
            assert clock.inline_ticks == before + 1
            assert robot.safety.state is agentsdk.SafetyState.FAULT and not robot.torque_enabled
            await robot.reset()
            await robot.enable()
            for _ in range(30):
                ticks = robot.ticks
                await robot.command(JointCommand("position", q))
                await clock.sleep(period)
                assert robot.ticks == ticks + 1  # one tick per period: one control loop
            controls = [t for t in asyncio.all_tasks() if t.get_name().endswith("-control") and not t.done()]
            assert len(controls) == 1
            assert clock.inline_ticks > before + 1


async def test_a_step_replaced_on_the_instance_is_not_run_inline() -> None:
    async with agentsdk.connect("mock", robot="arm3") as robot:
        clock, period = _clock(robot), robot.control_period
        backend = robot.backend
        original = backend._step
        suspended = 0

        async def slow_step(dt: float) -> None:  # a fault injection that waits: it must not run in a sleep
            nonlocal suspended
            await asyncio.sleep(0)
            suspended += 1
            await original(dt)

        async with asyncio.timeout(HANG_GUARD):
            q = (await robot.read()).position.tolist()
            for _ in range(10):
                await robot.command(JointCommand("position", q))
                await clock.sleep(period)
            assert clock.inline_ticks > 0
            backend._step = slow_step  # type: ignore[method-assign]
            before = clock.inline_ticks
            for _ in range(20):
                ticks = robot.ticks
                await robot.command(JointCommand("position", q))
                await clock.sleep(period)
                assert robot.ticks == ticks + 1
            assert clock.inline_ticks == before and suspended == 20
            del backend._step
            for _ in range(10):
                await robot.command(JointCommand("position", q))
                await clock.sleep(period)
            assert clock.inline_ticks > before
            assert robot.safety.state is agentsdk.SafetyState.OK


class _SuspendingMock(MockBackend):
    """Declares a step that never suspends, and suspends."""

    step_never_suspends = True

    async def _step(self, dt: float) -> None:
        await asyncio.sleep(0)
        await super()._step(dt)


async def test_a_backend_whose_declared_step_suspends_faults_the_loop_naming_it() -> None:
    register_backend("suspending-mock", _SuspendingMock)
    try:
        async with agentsdk.connect("suspending-mock", robot="arm3") as robot:
            clock, period = _clock(robot), robot.control_period
            robot._loop.batch_seconds = 3600.0  # no lease ends on wall time
            async with asyncio.timeout(HANG_GUARD):
                q = (await robot.read()).position.tolist()
                with pytest.raises(BackendFault, match=r"'mock' \(_SuspendingMock\) suspended"):
                    for _ in range(10):
                        await robot.command(JointCommand("position", q))
                        await clock.sleep(period)
                assert not robot.torque_enabled
                assert clock.inline_ticks == 1  # the first tick lent faulted
    finally:
        unregister_backend("suspending-mock")


async def test_a_sleeper_runs_its_tick_only_when_nobody_else_can_run() -> None:
    """Lending ends when another task is ready; the ticks then come from the control loop again."""
    async with agentsdk.connect("mock", robot="arm3") as robot:
        clock, period = _clock(robot), robot.control_period
        async with asyncio.timeout(HANG_GUARD):
            q = (await robot.read()).position.tolist()
            for _ in range(5):
                await robot.command(JointCommand("position", q))
                await clock.sleep(period)
            ran: list[int] = []

            async def other() -> None:
                ran.append(robot.ticks)

            before = clock.inline_ticks
            task = asyncio.create_task(other())  # ready now: the next tick must wait for it
            await clock.sleep(period)
            assert ran and ran[0] == robot.ticks - 1  # it ran before that tick
            assert clock.inline_ticks == before
            await task
    assert np.isfinite(clock.now())


async def _record_commanding(path: Any, backend: str) -> tuple[int, int]:
    from agentsdk.recording import Recorder

    async with agentsdk.connect(backend, robot="arm3", safety={"stall_timeout": None}) as robot:
        clock, period = _clock(robot), robot.control_period
        rec = Recorder(robot, path, block_ticks=100, metadata={"created": "fixed"})
        q0 = (await robot.read()).position.copy()
        for k in range(600):
            await robot.read()
            await robot.command(JointCommand("position", (q0 + 0.2 * math.sin(0.02 * k)).tolist()))
            if k == 400:
                await robot.estop(1)  # a stop ramp (a task) and its events
                await robot.safety.wait_stopped()
                await robot.reset()
                await robot.enable()
            await clock.sleep(period)
        ticks, inline = robot.ticks, clock.inline_ticks
    rec.finish()
    return ticks, inline


@pytest.mark.parametrize("backend", _simulators())
async def test_a_recording_of_a_behavior_commanding_every_tick_is_byte_equal_lent_or_not(
    backend: str, tmp_path: Any, request: Any, monkeypatch: pytest.MonkeyPatch,
) -> None:
    from agentsdk.recording import _recorder as recorder_module

    monkeypatch.setattr(recorder_module, "FLUSH_INTERVAL", 1e9)  # chunks cut by rows, not by the wall clock
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a, b = tmp_path / "a" / "run.mcap", tmp_path / "b" / "run.mcap"  # (the name is in the file)
    ticks_a, inline = await _record_commanding(a, backend)
    assert inline > 200
    request.getfixturevalue("no_lending")
    ticks_b, none = await _record_commanding(b, backend)
    assert none == 0 and ticks_a == ticks_b
    assert a.read_bytes() == b.read_bytes()


# ------------------------------------------------ lent and unlent runs of the same scenario (mock backend)
async def _both(scenario: Any) -> tuple[Any, int]:
    """``scenario()`` lent and unlent: its result in both (asserted equal), and the lent run's inline ticks."""
    lent = await scenario()
    saved = MockBackend.step_never_suspends
    MockBackend.step_never_suspends = False
    try:
        ticked = await scenario()
    finally:
        MockBackend.step_never_suspends = saved
    assert ticked[1] == 0
    assert lent[0] == ticked[0]
    return lent[0], lent[1]


@pytest.mark.parametrize("phase", [agentsdk.Phase.COMMAND, agentsdk.Phase.OBSERVE])
async def test_a_cancel_from_a_tick_hook_lands_at_that_ticks_sleep(phase: agentsdk.Phase) -> None:
    async def scenario() -> tuple[Any, int]:
        log: list[tuple[str, int]] = []
        async with agentsdk.connect("mock", robot="arm3") as robot:
            clock, period = _clock(robot), robot.control_period
            robot._loop.batch_seconds = 3600.0  # without the fix, a lease would run every tick to the end
            me: list[asyncio.Task[None]] = []
            robot.add_tick_hook(phase, lambda t, st, sp: me[0].cancel() if robot.ticks == 30 else None)

            async def behavior() -> None:
                me.append(asyncio.current_task())  # type: ignore[arg-type]
                try:
                    for _ in range(200):
                        await robot.command(JointCommand("position", [0.0, 0.0, 0.0]))
                        await clock.sleep(period)
                        log.append(("B", robot.ticks))
                except asyncio.CancelledError:
                    log.append(("cancelled", robot.ticks))
                    raise

            task = asyncio.create_task(behavior())
            async with asyncio.timeout(HANG_GUARD):
                with pytest.raises(asyncio.CancelledError):
                    await task
            # cancelling itself before a sleep: at that sleep, before its tick
            ticks = robot.ticks
            asyncio.current_task().cancel()  # type: ignore[union-attr]
            with pytest.raises(asyncio.CancelledError):
                await clock.sleep(period)
            asyncio.current_task().uncancel()  # type: ignore[union-attr]
            log.append(("self-cancelled", robot.ticks - ticks))
            return log, clock.inline_ticks

    log, inline = await _both(scenario)
    assert inline > 10 and log[-2][0] == "cancelled" and log[-1] == ("self-cancelled", 0)


async def test_a_task_a_tick_wakes_runs_before_the_sleeper_as_it_does_without_lending() -> None:
    async def scenario() -> tuple[Any, int]:
        log: list[tuple[str, int]] = []
        async with agentsdk.connect("mock", robot="arm3") as robot:
            clock, period = _clock(robot), robot.control_period
            robot._loop.batch_seconds = 3600.0
            fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
            fut2: asyncio.Future[None] = asyncio.get_running_loop().create_future()

            def hook(t: float, st: Any, sp: Any) -> None:
                for f, at in ((fut, 30), (fut2, 60)):
                    if robot.ticks == at and not f.done():
                        f.set_result(None)  # a COMMAND hook finishing something (as a motion's end does)

            robot.add_tick_hook(agentsdk.Phase.COMMAND, hook)

            async def waiter() -> None:
                await fut
                log.append(("waiter", robot.ticks))

            async def sleeper() -> None:  # woken by the hook, then it sleeps: ahead of the behavior's wake-up
                await fut2
                log.append(("sleeper woke", robot.ticks))
                await clock.sleep(2.5 * period)
                log.append(("sleeper slept", robot.ticks))

            tasks = [asyncio.create_task(waiter()), asyncio.create_task(sleeper())]
            async with asyncio.timeout(HANG_GUARD):
                for k in range(90):
                    if k == 60:
                        await asyncio.sleep(0)  # ends the lease: the control loop runs tick 61, parks after
                    await clock.sleep(period)
                    log.append(("B", robot.ticks))
                await asyncio.gather(*tasks)
            return log, clock.inline_ticks

    log, inline = await _both(scenario)
    assert inline > 30 and ("waiter", 31) in log and ("sleeper slept", 64) in log


async def test_a_fault_listeners_waiter_runs_before_the_sleeper_gets_the_fault() -> None:
    async def scenario() -> tuple[Any, int]:
        log: list[tuple[str, int, str]] = []
        async with agentsdk.connect("mock", robot="arm3") as robot:
            clock, period = _clock(robot), robot.control_period
            robot._loop.batch_seconds = 3600.0
            backend = robot.backend
            assert isinstance(backend, MockBackend)
            faulted = asyncio.Event()
            robot.add_fault_listener(lambda exc: faulted.set())

            async def monitor() -> None:
                await faulted.wait()
                log.append(("monitor", robot.ticks, robot.safety.state.name))

            task = asyncio.create_task(monitor())
            async with asyncio.timeout(HANG_GUARD):
                try:
                    for k in range(100):
                        if k == 40:
                            backend.step_error = True
                        await clock.sleep(period)
                except BackendFault as exc:
                    log.append(("behavior", robot.ticks, type(exc).__name__))
                await task
            return log, clock.inline_ticks

    log, inline = await _both(scenario)
    assert inline > 30 and [e[0] for e in log] == ["monitor", "behavior"]


async def test_two_lockstep_robots_on_one_event_loop_interleave_as_without_lending() -> None:
    async def scenario() -> tuple[Any, int]:
        log: list[tuple[str, int, int, int]] = []
        async with agentsdk.connect("mock", robot="arm3") as ra, agentsdk.connect("mock", robot="arm3") as rb:
            async def behavior(name: str, robot: agentsdk.Robot, n: int) -> None:
                clock, period = robot.clock, robot.control_period
                for k in range(n):
                    await clock.sleep(period)
                    log.append((name, k, ra.ticks, rb.ticks))

            async with asyncio.timeout(HANG_GUARD):
                await asyncio.gather(behavior("a", ra, 40), behavior("b", rb, 25))
                await behavior("a alone", ra, 40)  # one robot's behavior, the other robot idle
            return log, _clock(ra).inline_ticks + _clock(rb).inline_ticks

    await _both(scenario)


async def test_tick_hooks_see_the_control_loops_context_variables_lent_or_not() -> None:
    import contextvars

    counter: contextvars.ContextVar[int] = contextvars.ContextVar("counter", default=0)

    async def scenario() -> tuple[Any, int]:
        log: list[tuple[int, int]] = []
        async with agentsdk.connect("mock", robot="arm3") as robot:
            clock, period = _clock(robot), robot.control_period

            def hook(t: float, st: Any, sp: Any) -> None:
                counter.set(counter.get() + 1)
                log.append((robot.ticks, counter.get()))

            robot.add_tick_hook(agentsdk.Phase.OBSERVE, hook)
            async with asyncio.timeout(HANG_GUARD):
                for k in range(60):
                    await clock.sleep(period if k % 10 else 3 * period)
            return log, clock.inline_ticks

    log, inline = await _both(scenario)
    assert inline > 10 and all(tick == n for tick, n in log)


@pytest.mark.parametrize("realtime", [False, True])
@pytest.mark.parametrize("lending", [True, False])
async def test_a_tick_hook_raising_cancelled_error_faults_the_loop_instead_of_ending_it(
    realtime: bool, lending: bool, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A hook's CancelledError is a failed tick: torque off, FAULT, the sleepers told; before, the control
    task ended as if cancelled and every sleeper waited for ever."""
    monkeypatch.setattr(MockBackend, "step_never_suspends", lending)
    async with agentsdk.connect("mock", robot="arm3", realtime=realtime) as robot:
        clock, period = robot.clock, robot.control_period
        at = robot.ticks + 20

        def hook(t: float, st: Any, sp: Any) -> None:
            if robot.ticks == at:
                raise asyncio.CancelledError  # a hook's own bug (e.g. a cancelled future's result read in it)

        handle = robot.add_tick_hook(agentsdk.Phase.COMMAND, hook)
        q = (await robot.read()).position.tolist()
        async with asyncio.timeout(HANG_GUARD):
            with pytest.raises(BackendFault, match="CancelledError"):
                for _ in range(200):
                    await robot.command(JointCommand("position", q))
                    await clock.sleep(period)
            assert robot.safety.state is agentsdk.SafetyState.FAULT and not robot.torque_enabled
            handle.remove()
            await robot.reset()
            await robot.enable()
            assert (await robot.move_to({"joint1": 0.1})).ok
