"""Tests of agentsdk.statemachine and agentsdk.scope (one test per semantic).

Time is virtual (FakeClock); nothing here sleeps on the wall clock.  Where a test
must wait for the engine to process something, it awaits an asyncio.Event set by
a state body, ``machine.wait_state(...)``, or ``until(predicate)`` (which only
yields to the event loop).
"""

from __future__ import annotations

import asyncio
import functools
import sys
from collections.abc import AsyncIterator, Callable, Generator
from typing import Any

import pytest

from agentsdk import scope
from agentsdk.statemachine import (
    EventNotAllowed,
    HistoryRecord,
    State,
    StateContext,
    StateMachine,
    StateMachineDefinitionError,
    StateMachineError,
    find_machines,
)

# --------------------------------------------------------------------------- helpers


class FakeClock:
    """Virtual time: only ``advance()`` moves it."""

    def __init__(self) -> None:
        self.t = 0.0
        self._sleepers: list[tuple[float, asyncio.Future[None]]] = []
        self._changed = asyncio.Event()

    def now(self) -> float:
        return self.t

    async def sleep(self, dt: float) -> None:
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        entry = (self.t + dt, fut)
        self._sleepers.append(entry)
        self._changed.set()
        try:
            await fut
        finally:
            self._sleepers.remove(entry)

    def sleepers(self) -> int:
        return sum(not f.done() for _, f in self._sleepers)

    async def wait_sleepers(self, n: int = 1) -> None:
        while self.sleepers() < n:
            self._changed.clear()
            await self._changed.wait()

    def advance(self, dt: float) -> None:
        self.t += dt
        for deadline, fut in list(self._sleepers):
            if deadline <= self.t and not fut.done():
                fut.set_result(None)


class FakeMotion:
    """A motion handle: cancel() requests a stop; the test decides when it has stopped."""

    def __init__(self, *, stop_on_cancel: bool = False) -> None:
        self._fut: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        self.stop_on_cancel = stop_on_cancel
        self.cancel_calls = 0
        self.await_count = 0
        self.cancelled = asyncio.Event()

    def cancel(self) -> None:
        self.cancel_calls += 1
        self.cancelled.set()
        if self.stop_on_cancel:
            self.stopped()

    def stopped(self) -> None:
        if not self._fut.done():
            self._fut.set_result("held")

    def done(self) -> bool:
        return self._fut.done()

    def __await__(self) -> Generator[Any, None, str]:
        self.await_count += 1
        return (yield from self._fut.__await__())


class FakeRobot:
    def __init__(self, clock: FakeClock) -> None:
        self.clock = clock
        self.estops: list[int] = []
        self.motions: list[FakeMotion] = []

    def follow(self, *, stop_on_cancel: bool = False) -> FakeMotion:
        motion = FakeMotion(stop_on_cancel=stop_on_cancel)
        self.motions.append(motion)
        scope.register(motion)  # what the real robot does
        return motion

    async def estop(self, category: int = 1) -> None:
        self.estops.append(category)


async def until(predicate: Callable[[], bool], steps: int = 1000) -> None:
    """Yield to the event loop until ``predicate()`` holds (no wall-clock time involved)."""
    for _ in range(steps):
        if predicate():
            return
        await asyncio.sleep(0)
    raise AssertionError("condition not reached")


@pytest.fixture(autouse=True)
async def no_leaked_tasks() -> AsyncIterator[None]:
    before = asyncio.all_tasks()
    yield
    leaked = [t for t in asyncio.all_tasks() - before if t is not asyncio.current_task() and not t.done()]
    for t in leaked:
        t.cancel()
    assert not leaked, f"tasks left pending: {leaked}"


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def robot(clock: FakeClock) -> FakeRobot:
    return FakeRobot(clock)


def moves(m: StateMachine) -> list[tuple[str | None, str | None, str | None]]:
    """The transitions of the history of ``m`` (its own machine only)."""
    return [(r.source, r.target, r.event) for r in m.history if r.target is not None and r.machine == m.machine_path]


# --------------------------------------------------------------------------- machines at module level


class Approach(StateMachine):
    reach = State(initial=True)
    grasp = State()
    held = State(final=True)

    reached = reach.to(grasp)
    closed = grasp.to(held)


class Patrol(StateMachine):
    idle = State(initial=True)
    moving = State(timeout=5.0)
    picking = State(machine=Approach)
    done = State(final=True)
    fault = State(fault=True)

    go = idle.to(moving)
    arrived = moving.to(picking)
    done_picking = picking.to(done)
    stop = moving.to(idle) | idle.to(done)
    timeout = moving.to(fault)
    retry = fault.to(idle, guard="can_retry") | fault.to(done)

    def can_retry(self) -> bool:
        return True


# --------------------------------------------------------------------------- definition-time validation


def test_unknown_target_rejected_at_class_definition() -> None:
    with pytest.raises(StateMachineDefinitionError, match=r"Bad: transition 'go' has target 'mooving'"):

        class Bad(StateMachine):
            idle = State(initial=True)
            moving = State(final=True)
            go = idle.to("mooving")


def test_unreachable_state_rejected() -> None:
    with pytest.raises(StateMachineDefinitionError, match=r"Bad: state 'orphan' is unreachable"):

        class Bad(StateMachine):
            idle = State(initial=True)
            orphan = State()
            done = State(final=True)
            go = idle.to(done)
            back = orphan.to(done)


def test_missing_initial_state_rejected() -> None:
    with pytest.raises(StateMachineDefinitionError, match=r"Bad: no initial state"):

        class Bad(StateMachine):
            idle = State()
            done = State(final=True)
            go = idle.to(done)


def test_two_initial_states_rejected() -> None:
    with pytest.raises(StateMachineDefinitionError, match=r"Bad: two initial states: 'a' and 'b'"):

        class Bad(StateMachine):
            a = State(initial=True)
            b = State(initial=True)
            done = State(final=True)
            go = a.to(done) | b.to(done)


def test_transition_from_undeclared_state_rejected() -> None:
    with pytest.raises(StateMachineDefinitionError, match=r"Bad: transition 'go' has source <State Patrol.idle>"):

        class Bad(StateMachine):
            start = State(initial=True)
            done = State(final=True)
            go = Patrol.idle.to(done)  # a state of another machine
            finish = start.to(done)


def test_final_state_with_outgoing_transition_rejected() -> None:
    with pytest.raises(StateMachineDefinitionError, match=r"Bad: final state 'done' has outgoing transitions: 'again'"):

        class Bad(StateMachine):
            idle = State(initial=True)
            done = State(final=True)
            go = idle.to(done)
            again = done.to(idle)


def test_timeout_without_timeout_transition_rejected() -> None:
    with pytest.raises(StateMachineDefinitionError, match=r"Bad: state 'moving' has timeout=5 but no 'timeout'"):

        class Bad(StateMachine):
            moving = State(initial=True, timeout=5.0)
            done = State(final=True)
            arrived = moving.to(done)


def test_misnamed_body_unknown_guard_and_reserved_name_rejected() -> None:
    with pytest.raises(StateMachineDefinitionError, match=r"Bad: method on_movng is the body of state 'movng'"):

        class Bad(StateMachine):
            moving = State(initial=True)
            done = State(final=True)
            arrived = moving.to(done)

            async def on_movng(self, ctx: StateContext) -> None: ...

    with pytest.raises(StateMachineDefinitionError, match=r"Bad2: .*guard 'is_ready' is not a method"):

        class Bad2(StateMachine):
            moving = State(initial=True)
            done = State(final=True)
            arrived = moving.to(done, guard="is_ready")

    with pytest.raises(StateMachineDefinitionError, match=r"Bad3: 'send' would shadow StateMachine.send"):

        class Bad3(StateMachine):
            moving = State(initial=True)
            done = State(final=True)
            send = moving.to(done)


def test_nested_state_without_completion_transition_rejected() -> None:
    with pytest.raises(StateMachineDefinitionError, match=r"Bad: state 'picking' completes with event 'done_picking'"):

        class Bad(StateMachine):
            picking = State(initial=True, machine=Approach)
            done = State(final=True)
            done_pick = picking.to(done)  # typo: the completion event is done_picking


# --------------------------------------------------------------------------- running


async def test_body_return_value_fires_completion_event_and_history_records(robot: FakeRobot, clock: FakeClock) -> None:
    class Seq(StateMachine):
        a = State(initial=True)
        b = State()
        c = State(final=True)
        next = a.to(b)
        finish = b.to(c)

        async def on_a(self, ctx: StateContext) -> str:
            assert ctx.state == "Seq/a" and ctx.robot is robot and ctx.clock is clock and ctx.machine is self
            assert ctx.event is None
            clock.advance(1.5)
            return "next"

        async def on_b(self, ctx: StateContext) -> str:
            assert ctx.event == "next"
            clock.advance(0.5)
            return "finish"

    m = Seq(robot)
    assert await m.run() == "c"
    assert m.state_path == "Seq/c"
    assert m.history == [
        HistoryRecord(0.0, None, "a", None, note="initial", machine="Seq"),
        HistoryRecord(1.5, "a", "b", "next", machine="Seq"),
        HistoryRecord(2.0, "b", "c", "finish", machine="Seq"),
    ]


async def test_guard_blocks_then_allows(robot: FakeRobot) -> None:
    calls: list[bool] = []

    class Guarded(StateMachine):
        idle = State(initial=True)
        done = State(final=True)
        go = idle.to(done, guard="armed")

        allowed = False

        async def armed(self) -> bool:  # async guard
            calls.append(self.allowed)
            return self.allowed

    m = Guarded(robot)
    task = asyncio.create_task(m.run())
    m.send("go")
    await until(lambda: len(calls) == 1)
    assert m.state == "idle"
    assert m.history[-1].note == "blocked by guard" and m.history[-1].target is None
    m.allowed = True
    m.send("go")
    assert await task == "done"
    assert calls == [False, True]
    assert moves(m)[-1] == ("idle", "done", "go")


async def test_callable_guard_and_ignored_events(robot: FakeRobot) -> None:
    class G(StateMachine):
        idle = State(initial=True)
        done = State(final=True)
        go = idle.to(done, guard=lambda m: m.robot is not None)

    m = G(robot)
    task = asyncio.create_task(m.run())
    m.send("nonsense")
    m.send("go")
    assert await task == "done"
    ignored = [r for r in m.history if r.note == "ignored"]
    assert [(r.source, r.event) for r in ignored] == [("idle", "nonsense")]

    strict = G(robot, strict=True)
    with pytest.raises(EventNotAllowed, match="nonsense"):
        strict.send("nonsense")


async def test_per_state_timeout_fires_timeout_event(robot: FakeRobot, clock: FakeClock) -> None:
    class Wait(StateMachine):
        waiting = State(initial=True, timeout=5.0)
        late = State(final=True)
        timeout = waiting.to(late)

        async def on_waiting(self, ctx: StateContext) -> None:
            await asyncio.Event().wait()  # never finishes by itself

    m = Wait(robot)
    task = asyncio.create_task(m.run())
    await m.wait_state("waiting")
    await clock.wait_sleepers(1)
    clock.advance(4.9)
    await until(lambda: clock.sleepers() == 1)
    assert m.state == "waiting"
    clock.advance(0.1)
    assert await task == "late"
    assert moves(m)[-1] == ("waiting", "late", "timeout")
    assert m.history[-1].time == pytest.approx(5.0)


async def test_external_event_preempts_running_body(robot: FakeRobot) -> None:
    started = asyncio.Event()
    log: list[str] = []

    class Work(StateMachine):
        busy = State(initial=True)
        stopped = State(final=True)
        stop = busy.to(stopped)

        async def on_busy(self, ctx: StateContext) -> str:
            started.set()
            try:
                await asyncio.Event().wait()
            except asyncio.CancelledError:
                log.append("cancelled")
                raise
            finally:
                log.append("finally")
            return "unreachable"

    m = Work(robot)
    task = asyncio.create_task(m.run())
    await started.wait()
    m.send("stop")
    assert await task == "stopped"
    assert log == ["cancelled", "finally"]
    assert moves(m)[-1] == ("busy", "stopped", "stop")


async def test_nested_machine_completes_parent_state(robot: FakeRobot) -> None:
    class Grab(StateMachine):
        reach = State(initial=True)
        grasp = State()
        held = State(final=True)
        reached = reach.to(grasp)
        closed = grasp.to(held)

        async def on_reach(self, ctx: StateContext) -> str:
            assert ctx.state == "Task/picking/Grab/reach"
            return "reached"

        async def on_grasp(self, ctx: StateContext) -> str:
            return "closed"

    class Task(StateMachine):
        picking = State(initial=True, machine=Grab)
        done = State(final=True)
        done_picking = picking.to(done)

    m = Task(robot)
    assert await m.run() == "done"
    assert moves(m) == [(None, "picking", None), ("picking", "done", "done_picking")]
    # the root history also holds the nested machine's records
    assert [(r.machine, r.source, r.target) for r in m.history if r.machine != "Task"] == [
        ("Task/picking/Grab", None, "reach"),
        ("Task/picking/Grab", "reach", "grasp"),
        ("Task/picking/Grab", "grasp", "held"),
    ]


async def test_nested_done_mapping_selects_event_by_final_state(robot: FakeRobot) -> None:
    class Try(StateMachine):
        attempt = State(initial=True)
        ok = State(final=True)
        failed = State(final=True)
        success = attempt.to(ok)
        failure = attempt.to(failed)

        async def on_attempt(self, ctx: StateContext) -> str:
            return "failure"

    class Outer(StateMachine):
        trying = State(initial=True, machine=Try, done={"ok": "worked", "failed": "gave_up"})
        happy = State(final=True)
        sad = State(final=True)
        worked = trying.to(happy)
        gave_up = trying.to(sad)

    assert await Outer(robot).run() == "sad"


async def test_parent_event_preempts_nested_machine(robot: FakeRobot) -> None:
    in_grasp = asyncio.Event()
    log: list[str] = []

    class Grab(StateMachine):
        reach = State(initial=True)
        grasp = State()
        held = State(final=True)
        reached = reach.to(grasp)
        closed = grasp.to(held)

        async def on_reach(self, ctx: StateContext) -> str:
            return "reached"

        async def on_grasp(self, ctx: StateContext) -> str:
            robot.follow()
            in_grasp.set()
            try:
                await asyncio.Event().wait()
            finally:
                log.append(f"finally {ctx.state}")
            return "closed"

    class Task(StateMachine):
        picking = State(initial=True, machine=Grab)
        aborted = State(final=True)
        done = State(final=True)
        abort = picking.to(aborted)
        done_picking = picking.to(done)

    m = Task(robot)
    task = asyncio.create_task(m.run())
    await in_grasp.wait()
    assert m.state_path == "Task/picking/Grab/grasp"
    m.send("abort")
    await robot.motions[0].cancelled.wait()
    robot.motions[0].stopped()
    assert await task == "aborted"
    assert log == ["finally Task/picking/Grab/grasp"]
    assert robot.motions[0].cancel_calls == 1


async def test_event_forwarded_to_nested_machine(robot: FakeRobot) -> None:
    class Grab(StateMachine):
        grasp = State(initial=True)
        held = State(final=True)
        closed = grasp.to(held)

    class Task(StateMachine):
        picking = State(initial=True, machine=Grab)
        done = State(final=True)
        done_picking = picking.to(done)

    m = Task(robot, strict=True)
    task = asyncio.create_task(m.run())
    await m.wait_state("Grab/grasp")
    m.send("closed")  # not a Task event: the active nested machine takes it
    assert await task == "done"


async def test_parallel_regions_complete_when_all_final(robot: FakeRobot) -> None:
    gate = asyncio.Event()

    class Arm(StateMachine):
        reach = State(initial=True)
        there = State(final=True)
        reached = reach.to(there)

        async def on_reach(self, ctx: StateContext) -> str:
            return "reached"

    class Gripper(StateMachine):
        opening = State(initial=True)
        open = State(final=True)
        opened = opening.to(open)

        async def on_opening(self, ctx: StateContext) -> str:
            await gate.wait()
            return "opened"

    class Both(StateMachine):
        prepare = State(initial=True, parallel=[Arm, Gripper])
        ready = State(final=True)
        done_prepare = prepare.to(ready)

    m = Both(robot)
    task = asyncio.create_task(m.run())
    await m.wait_state("Arm/there")
    assert m.state_path == "Both/prepare/[Arm/there|Gripper/opening]"
    gate.set()
    assert await task == "ready"


async def test_parent_event_preempts_parallel_regions(robot: FakeRobot) -> None:
    cancelled: list[str] = []

    class Spin(StateMachine):
        spinning = State(initial=True)
        stopped = State(final=True)
        halt = spinning.to(stopped)

        async def on_spinning(self, ctx: StateContext) -> None:
            try:
                await asyncio.Event().wait()
            except asyncio.CancelledError:
                cancelled.append(ctx.state)
                raise

    class Blink(Spin):
        pass

    class Show(StateMachine):
        running = State(initial=True, parallel=[Spin, Blink])
        aborted = State(final=True)
        done = State(final=True)
        abort = running.to(aborted)
        done_running = running.to(done)

    m = Show(robot)
    task = asyncio.create_task(m.run())
    await m.wait_state("Spin/spinning")
    await m.wait_state("Blink/spinning")
    await until(lambda: m.state_path == "Show/running/[Spin/spinning|Blink/spinning]")
    m.send("abort")
    assert await task == "aborted"
    assert sorted(cancelled) == ["Show/running/Blink/spinning", "Show/running/Spin/spinning"]


async def test_every_failing_parallel_region_is_reported(robot: FakeRobot) -> None:
    """Before: of two regions failing in the same step only the first exception survived."""
    gate = asyncio.Event()

    class Left(StateMachine):
        work = State(initial=True)
        done = State(final=True)
        finish = work.to(done)

        async def on_work(self, ctx: StateContext) -> str:
            await gate.wait()
            raise ValueError("left gripper jammed")

    class Right(StateMachine):
        work = State(initial=True)
        done = State(final=True)
        finish = work.to(done)

        async def on_work(self, ctx: StateContext) -> str:
            await gate.wait()
            raise KeyError("right arm lost")

    class Both(StateMachine):
        run_both = State(initial=True, parallel=[Left, Right])
        end = State(final=True)
        done_run_both = run_both.to(end)

    m = Both(robot)
    task = asyncio.create_task(m.run())
    await m.wait_state("Left/work")
    await m.wait_state("Right/work")
    gate.set()
    with pytest.raises(StateMachineError, match=r"2 parallel regions of Both/run_both failed") as info:
        await task
    group = info.value.__cause__
    assert isinstance(group, ExceptionGroup)
    assert sorted(type(e).__name__ for e in group.exceptions) == ["KeyError", "ValueError"]
    assert robot.estops  # the robot was stopped


async def test_a_fault_state_receives_every_region_failure(robot: FakeRobot) -> None:
    gate = asyncio.Event()
    seen: list[BaseException | None] = []

    class One(StateMachine):
        work = State(initial=True)
        done = State(final=True)
        finish = work.to(done)

        async def on_work(self, ctx: StateContext) -> str:
            await gate.wait()
            raise RuntimeError(ctx.state)

    class Two(One):
        pass

    class Cell(StateMachine):
        run_both = State(initial=True, parallel=[One, Two])
        fault = State(fault=True)
        end = State(final=True)
        done_run_both = run_both.to(end)
        recover = fault.to(end)

        async def on_fault(self, ctx: StateContext) -> str:
            seen.append(ctx.error)
            return "recover"

    m = Cell(robot)
    task = asyncio.create_task(m.run())
    await m.wait_state("One/work")
    await m.wait_state("Two/work")
    gate.set()
    assert await task == "end"
    (error,) = seen
    assert isinstance(error, ExceptionGroup) and len(error.exceptions) == 2


async def test_timeout_restarts_on_each_visit(robot: FakeRobot, clock: FakeClock) -> None:
    class Loop(StateMachine):
        waiting = State(initial=True, timeout=5.0)
        other = State()
        late = State(final=True)
        poke = waiting.to(other)
        back = other.to(waiting)
        timeout = waiting.to(late)

    m = Loop(robot)
    task = asyncio.create_task(m.run())
    await clock.wait_sleepers(1)
    clock.advance(3.0)
    m.send("poke")
    m.send("back")
    await until(lambda: len(moves(m)) == 3 and clock.sleepers() == 1)  # re-entered, new timer
    clock.advance(3.0)  # 6 s since the first entry, 3 s since the second
    await until(lambda: clock.sleepers() == 1)
    assert m.state == "waiting"
    clock.advance(2.0)
    assert await task == "late"
    assert [(r.time, r.event) for r in m.history if r.target] == [
        (0.0, None),
        (3.0, "poke"),
        (3.0, "back"),
        (8.0, "timeout"),
    ]


async def test_body_returning_unknown_event_is_an_error(robot: FakeRobot) -> None:
    class Typo(StateMachine):
        idle = State(initial=True)
        done = State(final=True)
        go = idle.to(done)

        async def on_idle(self, ctx: StateContext) -> str:
            return "goo"

    with pytest.raises(StateMachineError, match=r"Typo/idle.*unknown event 'goo'"):
        await Typo(robot).run()
    assert robot.estops == [1]


async def test_exit_cancels_and_awaits_motions(robot: FakeRobot) -> None:
    class Move(StateMachine):
        moving = State(initial=True)
        idle = State(final=True)
        stop = moving.to(idle)

        async def on_moving(self, ctx: StateContext) -> None:
            robot.follow()  # fire and forget: the state owns it anyway
            await asyncio.Event().wait()

    m = Move(robot)
    task = asyncio.create_task(m.run())
    await until(lambda: len(robot.motions) == 1)
    motion = robot.motions[0]
    m.send("stop")
    await motion.cancelled.wait()
    await until(lambda: motion.await_count == 1)  # the engine is waiting for the stop
    assert m.state == "moving" and not task.done()
    motion.stopped()
    assert await task == "idle"
    assert motion.cancel_calls == 1 and motion.await_count == 1


async def test_motion_that_does_not_stop_escalates(robot: FakeRobot, clock: FakeClock) -> None:
    class Move(StateMachine):
        moving = State(initial=True)
        idle = State(final=True)
        fault = State(fault=True, final=True)
        stop = moving.to(idle)

        async def on_moving(self, ctx: StateContext) -> None:
            robot.follow()

    m = Move(robot)
    task = asyncio.create_task(m.run())
    await until(lambda: len(robot.motions) == 1)
    m.send("stop")
    await clock.wait_sleepers(1)  # the stop deadline
    clock.advance(10.0)
    with pytest.raises(StateMachineError, match=r"Move/moving.*did not stop within 10 s"):
        await task
    assert robot.estops == [1]  # not routed to the fault state: the robot would not stop


async def test_exception_goes_to_fault_state(robot: FakeRobot) -> None:
    seen: list[BaseException | None] = []

    class Careful(StateMachine):
        working = State(initial=True)
        fault = State(fault=True)
        done = State(final=True)
        give_up = fault.to(done)

        async def on_working(self, ctx: StateContext) -> None:
            raise ValueError("sensor unplugged")

        async def on_fault(self, ctx: StateContext) -> str:
            seen.append(ctx.error)
            return "give_up"

    m = Careful(robot)
    assert await m.run() == "done"
    assert isinstance(m.last_error, ValueError) and seen == [m.last_error]
    assert m.last_error_path == "Careful/working"
    assert moves(m)[1] == ("working", "fault", "error")
    assert robot.estops == []


async def test_exception_in_nested_machine_goes_to_enclosing_fault_state(robot: FakeRobot) -> None:
    class Grab(StateMachine):
        grasp = State(initial=True)
        held = State(final=True)
        closed = grasp.to(held)

        async def on_grasp(self, ctx: StateContext) -> str:
            raise RuntimeError("gripper jammed")

    class Task(StateMachine):
        picking = State(initial=True, machine=Grab)
        fault = State(fault=True, final=True)
        done = State(final=True)
        done_picking = picking.to(done)

    m = Task(robot)
    assert await m.run() == "fault"
    assert str(m.last_error) == "gripper jammed" and m.last_error_path == "Task/picking/Grab/grasp"


async def test_exception_without_fault_state_estops_and_raises_with_path(robot: FakeRobot) -> None:
    class Grasping(StateMachine):
        grasp = State(initial=True)
        held = State(final=True)
        closed = grasp.to(held)

        async def on_grasp(self, ctx: StateContext) -> str:
            robot.follow(stop_on_cancel=True)
            raise RuntimeError("gripper jammed")

    class Approach(StateMachine):
        reach = State(initial=True, machine=Grasping)
        done = State(final=True)
        done_reach = reach.to(done)

    class Patrol(StateMachine):
        moving = State(initial=True, machine=Approach)
        done = State(final=True)
        done_moving = moving.to(done)

    m = Patrol(robot)
    with pytest.raises(StateMachineError) as info:
        await m.run()
    assert "Patrol/moving/Approach/reach/Grasping/grasp" in str(info.value)
    assert "gripper jammed" in str(info.value)
    assert isinstance(info.value.__cause__, RuntimeError)
    assert info.value.path == "Patrol/moving/Approach/reach/Grasping/grasp"
    assert robot.estops == [1]
    assert robot.motions[0].cancel_calls == 1  # the state's motion was stopped too


async def test_cancelling_run_cancels_state_and_propagates(robot: FakeRobot) -> None:
    started = asyncio.Event()
    log: list[str] = []

    class Forever(StateMachine):
        busy = State(initial=True)
        done = State(final=True)
        finish = busy.to(done)

        async def on_busy(self, ctx: StateContext) -> None:
            robot.follow()
            started.set()
            try:
                await asyncio.Event().wait()
            finally:
                log.append("finally")

    m = Forever(robot)
    task = asyncio.create_task(m.run())
    await started.wait()
    motion = robot.motions[0]
    task.cancel()
    await motion.cancelled.wait()
    await until(lambda: motion.await_count == 1)
    assert not task.done()  # run() waits for the robot to stop before propagating
    motion.stopped()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert log == ["finally"]
    assert motion.cancel_calls == 1
    assert robot.estops == []


async def test_motion_scope_outside_machine(clock: FakeClock) -> None:
    scope.register(FakeMotion())  # no scope: no-op
    async with scope.MotionScope("script", clock=clock) as s:
        assert scope.current_scope() is s
        motion = FakeMotion(stop_on_cancel=True)
        scope.register(motion)
    assert scope.current_scope() is None
    assert motion.cancel_calls == 1 and motion.done()
    late = FakeMotion()
    s.add(late)  # registered after close: stopped at once
    assert late.cancel_calls == 1


# --------------------------------------------------------------------------- introspection


def test_mermaid_of_sample_machine() -> None:
    assert Patrol.mermaid() == (
        "stateDiagram-v2\n"
        "    idle\n"
        "    moving : timeout 5s\n"
        "    state picking {\n"
        "        %% Approach\n"
        '        state "reach" as picking__reach\n'
        '        state "grasp" as picking__grasp\n'
        '        state "held" as picking__held\n'
        "        [*] --> picking__reach\n"
        "        picking__reach --> picking__grasp : reached\n"
        "        picking__grasp --> picking__held : closed\n"
        "        picking__held --> [*]\n"
        "    }\n"
        "    done\n"
        "    fault : fault handler\n"
        "    [*] --> idle\n"
        "    idle --> moving : go\n"
        "    moving --> picking : arrived\n"
        "    picking --> done : done_picking\n"
        "    moving --> idle : stop\n"
        "    idle --> done : stop\n"
        "    moving --> fault : timeout\n"
        "    fault --> idle : retry [can_retry]\n"
        "    fault --> done : retry\n"
        "    done --> [*]\n"
    )


def test_find_machines_lists_module_machines_in_order(tmp_path: Any) -> None:
    assert find_machines(sys.modules[__name__]) == [Approach, Patrol]
    behavior = tmp_path / "patrol_behavior.py"
    behavior.write_text(
        "from agentsdk.statemachine import State, StateMachine\n"
        "class Base(StateMachine):  # abstract: not listed\n"
        "    pass\n"
        "class Walk(Base):\n"
        "    start = State(initial=True)\n"
        "    end = State(final=True)\n"
        "    go = start.to(end)\n"
    )
    assert [m.__name__ for m in find_machines(str(behavior))] == ["Walk"]


# --------------------------------------------------------------------------- issue 26 constructs (virtual time)


@functools.cache
def regions() -> tuple[type[StateMachine], type[StateMachine]]:
    """Two region machines (built once, not at module level: find_machines' test lists those)."""

    class RegionA(StateMachine):
        a1 = State(initial=True)
        a2 = State()
        a_end = State(final=True)
        step = a1.to(a2) | a2.to(a_end)

    class RegionB(StateMachine):
        b1 = State(initial=True)
        b2 = State()
        b_end = State(final=True)
        step = b1.to(b2) | b2.to(b_end)

    return RegionA, RegionB


async def test_history_of_a_parallel_state_resumes_every_region(robot: FakeRobot) -> None:
    """SCXML §3.10 with a <parallel> parent: the history holds every region's active state."""

    RegionA, RegionB = regions()

    class Par(StateMachine):
        both = State(initial=True, parallel=[RegionA, RegionB], history="shallow")
        away = State()
        end = State(final=True)
        leave = both.to(away)
        back = away.to(both)
        done_both = both.to(end)

    m = Par(robot)
    runner = asyncio.create_task(m.run())
    await m.wait_state("a1")
    m.send("step")  # forwarded to both regions: a1 -> a2, b1 -> b2
    await m.wait_state("a2")
    await m.wait_state("b2")
    m.send("leave")
    await m.wait_state("away")
    m.send("back")
    await m.wait_state("both")
    await until(lambda: m.state_path == "Par/both/[RegionA/a2|RegionB/b2]")
    m.send("step")
    assert await runner == "end"


async def test_entry_and_exit_action_errors_go_to_the_fault_state(robot: FakeRobot) -> None:
    """python-statemachine tests/machines/error/error_in_on_enter_sc.py: an error in an action is an
    error of the state (SCXML §5.10 error.execution), routed to the fault state."""

    class Boom(StateMachine):
        a = State(initial=True)
        b = State()
        end = State(final=True)
        fault = State(fault=True)
        go = a.to(b)
        fin = b.to(end)
        recover = fault.to(end)

        def __init__(self, robot: Any, where: str) -> None:
            super().__init__(robot)
            self.where = where
            self.errors: list[str] = []

        async def on_a(self, ctx: StateContext) -> str:
            return "go"

        def on_exit_a(self, ctx: StateContext) -> None:
            if self.where == "exit":
                raise ValueError("exit failed")

        async def on_enter_b(self, ctx: StateContext) -> None:
            if self.where == "enter":
                raise ValueError("enter failed")

        async def on_fault(self, ctx: StateContext) -> str:
            self.errors.append(str(ctx.error))
            return "recover"

    for where in ("exit", "enter"):
        m = Boom(robot, where)
        assert await m.run() == "end"
        assert m.errors == [f"{where} failed"]
        assert [t for _, t, _ in moves(m)][-2] == "fault"


async def test_transition_action_runs_between_exit_and_entry_with_the_event_data(robot: FakeRobot) -> None:
    """SCXML §3.13 (executable content of a transition runs after the exits and before the entries)."""
    log: list[str] = []

    class Act(StateMachine):
        a = State(initial=True)
        b = State(final=True)
        go = a.to(b, action=lambda m, event, data: log.append(f"action {event} {dict(data)}"))

        def on_exit_a(self, ctx: StateContext) -> None:
            log.append("exit a")

        def on_enter_b(self, ctx: StateContext) -> None:
            log.append(f"enter b {dict(ctx.data)}")

    m = Act(robot)
    runner = asyncio.create_task(m.run())
    await m.wait_state("a")
    m.send("go", {"n": 1})
    assert await runner == "b"
    assert log == ["exit a", "action go {'n': 1}", "enter b {'n': 1}"]


async def test_guarded_internal_transition_and_inner_priority_two_levels_deep(robot: FakeRobot) -> None:
    """transitions tests/test_nesting.py (the deepest state's trigger wins) and SCXML §3.13; a blocked
    guard on the inner transitions hands the event to the outer machine."""
    counted: list[str] = []

    class Leaf(StateMachine):
        x = State(initial=True)
        y = State(final=True)
        poke = x.internal(lambda m, e, d: counted.append("leaf"), guard=lambda m: m.armed)
        finish = x.to(y)
        armed = True

    class Mid(StateMachine):
        event_priority = "inner"
        inner = State(initial=True, machine=Leaf)
        out = State(final=True)
        done_inner = inner.to(out)

    class Top(StateMachine):
        event_priority = "inner"
        mid = State(initial=True, machine=Mid)
        stopped = State(final=True)
        poke = mid.to(stopped)
        done_mid = mid.to(stopped)

    m = Top(robot)
    runner = asyncio.create_task(m.run())
    await m.wait_state("x")
    m.send("poke")  # the leaf takes it in place
    await until(lambda: counted == ["leaf"])
    assert m.state_path == "Top/mid/Mid/inner/Leaf/x"
    m.children[0].children[0].armed = False  # type: ignore[attr-defined]
    m.send("poke")  # the leaf's guard blocks: the top takes it
    assert await runner == "stopped"
    assert counted == ["leaf"]


async def test_preemption_grace_applies_to_the_timeout_and_done_data_callable(
    robot: FakeRobot, clock: FakeClock
) -> None:
    """SMACH preemption with a bound, triggered by the state's own timeout; SCXML <donedata> computed."""

    class Slow(StateMachine):
        work = State(initial=True, timeout=1.0, preempt_timeout=0.5)
        end = State(final=True, data=lambda m: {"wound_down": m.wound_down})
        timeout = work.to(end)
        wound_down = False

        async def on_work(self, ctx: StateContext) -> None:
            await ctx.wait_preempt()
            await ctx.sleep(0.2)  # wind down within the bound
            self.wound_down = True

    m = Slow(robot)
    runner = asyncio.create_task(m.run())
    await clock.wait_sleepers(1)
    clock.advance(1.0)  # the timeout: preemption requested
    await clock.wait_sleepers(2)  # the body's wind-down sleep and the bound
    clock.advance(0.2)
    assert await runner == "end"
    assert m.done_data == {"wound_down": True}


async def test_remapped_key_missing_in_the_parent_is_an_error_of_the_state(robot: FakeRobot) -> None:
    """SMACH: reading a remapped key the parent does not have is a KeyError in the state's code."""

    class Needs(StateMachine):
        read = State(initial=True)
        end = State(final=True)
        ok = read.to(end)

        async def on_read(self, ctx: StateContext) -> str:
            ctx.userdata["value"]
            return "ok"

    class Holder(StateMachine):
        sub = State(initial=True, machine=Needs, remap={"value": "missing"})
        end = State(final=True)
        fault = State(fault=True)
        done_sub = sub.to(end)
        out = fault.to(end)

        async def on_fault(self, ctx: StateContext) -> str:
            self.error = ctx.error
            return "out"

    m = Holder(robot)
    assert await m.run() == "end"
    assert isinstance(m.error, KeyError) and m.error.args == ("value",)


def test_issue26_options_are_validated_at_class_definition() -> None:
    """python-statemachine validates declarations when the class is created (factory.py)."""
    RegionA, RegionB = regions()
    cases: list[tuple[str, dict[str, Any]]] = [
        ("history= is only for machine= or parallel=", {"history": "deep"}),
        ("history must be 'shallow' or 'deep'", {"history": "full", "machine": RegionA}),
        ("preempt_timeout must be", {"preempt_timeout": -1.0}),
        ("remap= and args= are only for", {"remap": {"a": "b"}}),
        ("finish= and outcome_map= are only for parallel", {"finish": "first", "machine": RegionA}),
        ("finish must be", {"finish": "some", "parallel": [RegionA]}),
        ("names region 'RegionC'", {"parallel": [RegionA, RegionB], "outcome_map": {"ok": {"RegionC": "a_end"}}}),
    ]
    for message, kw in cases:
        with pytest.raises(StateMachineDefinitionError, match=message):
            type(
                "Bad",
                (StateMachine,),
                {"s": (s := State(initial=True, **kw)), "end": (e := State(final=True)), "go": s.to(e),
                 "done_s": s.to(e), "ok": s.to(e)},
            )
    with pytest.raises(StateMachineDefinitionError, match=r"data= .* is only for final states"):

        class NotFinal(StateMachine):
            s = State(initial=True, data=("x",))
            end = State(final=True)
            go = s.to(end)


async def test_preemption_of_a_composite_state_reaches_its_nested_active_state(
    robot: FakeRobot, clock: FakeClock
) -> None:
    """SMACH: ``request_preempt()`` on a container is passed to its running children; the nested
    machine winds down (here through its own ``park`` state) within the composite's bound."""

    class Tool(StateMachine):
        working = State(initial=True)
        parking = State()
        parked = State(final=True)
        park = working.to(parking)
        stowed = parking.to(parked)

        async def on_working(self, ctx: StateContext) -> str:
            await ctx.wait_preempt()
            return "park"

        async def on_parking(self, ctx: StateContext) -> str:
            assert not ctx.preempt_requested()  # a new state: not asked to stop
            await ctx.sleep(0.3)
            return "stowed"

    class Cell(StateMachine):
        tool = State(initial=True, machine=Tool, preempt_timeout=1.0)
        off = State(final=True)
        stop = tool.to(off)
        done_tool = tool.to(off)

    m = Cell(robot)
    runner = asyncio.create_task(m.run())
    await m.wait_state("working")
    m.send("stop")
    await m.wait_state("parking")
    await clock.wait_sleepers(2)  # parking's sleep and the bound
    clock.advance(0.3)
    assert await runner == "off"
    tool = [t for mach, t in ((r.machine, r.target) for r in m.history) if mach == "Cell/tool/Tool" and t]
    assert tool == ["working", "parking", "parked"]
    assert not any(r.note.startswith("preempted: body cancelled") for r in m.history)


# --------------------------------------------------------------------------- random machines (nobody named them)


def _random_machine(rng: Any, depth: int, log: list[tuple[str, str]], tag: str) -> type[StateMachine]:
    n = rng.randint(2, 4)
    ns: dict[str, Any] = {"event_priority": rng.choice(["outer", "inner"])}
    names = [f"s{i}" for i in range(n)]
    for i, name in enumerate(names):
        kw: dict[str, Any] = {"initial": i == 0}
        if depth > 0 and rng.random() < 0.5:
            if rng.random() < 0.7:
                kw["machine"] = _random_machine(rng, depth - 1, log, f"{tag}{i}")
            else:
                kw["parallel"] = [_random_machine(rng, depth - 1, log, f"{tag}{i}p{k}") for k in range(2)]
            kw["history"] = rng.choice([None, "shallow", "deep"])
        ns[name] = State(**kw)
    ns["end"] = State(final=True)
    lists: dict[str, Any] = {}
    for i, name in enumerate(names):
        target = names[i + 1] if i + 1 < n else "end"
        lists.setdefault("next", []).append(ns[name].to(ns[target]))
        if ns[name].is_composite:
            lists.setdefault(f"done_{name}", []).append(ns[name].to(ns[target]))
        for event in ("back", "jump", "poke"):
            if rng.random() < 0.4:
                other = rng.choice(names)
                internal = event == "poke" and rng.random() < 0.5
                lists.setdefault(event, []).append(ns[name].to(ns[name] if internal else ns[other], internal=internal))
    for event, tls in lists.items():
        combined = tls[0]
        for tl in tls[1:]:
            combined = combined | tl
        ns[event] = combined

    def actions(state: str) -> tuple[Callable[..., None], Callable[..., None]]:
        return (lambda self, ctx: log.append(("enter", ctx.state)), lambda self, ctx: log.append(("exit", ctx.state)))

    for name in [*names, "end"]:
        ns[f"on_enter_{name}"], ns[f"on_exit_{name}"] = actions(name)
    return type(f"M{tag}", (StateMachine,), ns)


@pytest.mark.parametrize("seed", range(40))
async def test_random_machines_keep_entry_exit_nesting_and_a_consistent_configuration(
    robot: FakeRobot, seed: int
) -> None:
    """SCXML §3.13 on machines nobody named: every exit follows its entry, a state is entered only
    inside its active parent and exits only after its active descendants, and the configuration is
    the set of entered-but-not-exited states (checked after every event and after cancellation)."""
    import random

    rng = random.Random(seed)
    log: list[tuple[str, str]] = []
    cls = _random_machine(rng, 2, log, "")
    m = cls(robot)
    runner = asyncio.create_task(m.run())

    def active() -> set[str]:
        open_: set[str] = set()
        for kind, path in log:
            if kind == "enter":
                assert path not in open_, f"{path} entered twice: {log}"
                parent = path.rsplit("/", 2)[0]  # ".../state/Machine/child" -> ".../state"
                assert path.count("/") == 1 or parent in open_, f"{path} entered outside {parent}: {log}"
                open_.add(path)
            else:
                assert path in open_, f"{path} exited without entry: {log}"
                assert not any(p.startswith(path + "/") for p in open_), f"{path} exited before its children"
                open_.discard(path)
        return open_

    for _ in range(25):
        if runner.done():
            break
        m.send(rng.choice(["next", "back", "jump", "poke", "next"]))
        for _ in range(30):
            await asyncio.sleep(0)
        still = active()
        if not runner.done():
            assert still == set(m.configuration), (still, m.configuration)
    if not runner.done():
        runner.cancel()
        with pytest.raises(asyncio.CancelledError):
            await runner
    else:
        assert await runner == "end"
    assert active() == set(), log
