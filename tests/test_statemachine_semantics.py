"""State-machine semantics ported from SCXML, SMACH, python-statemachine and transitions (issue 26),
and "a state exits at rest, whatever ends it" (issue 20 item 10).

Every case runs on a real robot in lockstep, on the mock backend and on MuJoCo (arm3): state
bodies start real motions (``robot.move_to``) and the machine clock is ``robot.clock`` (simulated
time). Each test names the peer test or the SCXML section whose behaviour it ports; the code and
the machines are ours.
"""

from __future__ import annotations

import asyncio
import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pytest

import agentsdk
from agentsdk import Trajectory, TrajectoryPoint, scope
from agentsdk.statemachine import (
    HistoryRecord,
    RobotStoppedError,
    State,
    StateContext,
    StateMachine,
    StateMachineDefinitionError,
    StateMachineError,
)

BACKENDS = ["mock", "mujoco"]
SAFETY = {"stall_timeout": 5.0}  # lockstep on a loaded machine (see tests/test_behaviors.py)


@pytest.fixture(params=BACKENDS)
async def robot(request: pytest.FixtureRequest) -> AsyncIterator[agentsdk.Robot]:
    async with agentsdk.connect(request.param, robot="arm3", safety=SAFETY) as r:
        yield r


def speed(robot: agentsdk.Robot) -> float:
    return float(np.abs(robot.latest_state().velocity).max())


def moves(m: StateMachine) -> list[tuple[str, str | None, str | None, str | None]]:
    return [(r.machine, r.source, r.target, r.event) for r in m.history if r.target is not None]


# --------------------------------------------------------------------------- entry / exit actions


class Day(StateMachine):
    morning = State(initial=True)
    evening = State(final=True)
    dusk = morning.to(evening)

    def __init__(self, robot: Any, **kw: Any) -> None:
        super().__init__(robot, **kw)
        self.log: list[str] = []

    def on_enter_morning(self, ctx: StateContext) -> None:
        root_log(self).append(f"enter {ctx.state}")

    async def on_morning(self, ctx: StateContext) -> str:
        await ctx.robot.move_to({"joint1": 0.2}, duration=0.5)
        return "dusk"

    async def on_exit_morning(self, ctx: StateContext) -> None:
        root_log(self).append(f"exit {ctx.state}")

    def on_enter_evening(self, ctx: StateContext) -> None:
        root_log(self).append(f"enter {ctx.state}")


class Lamp(StateMachine):
    on = State(initial=True)
    off = State(final=True)
    switch = on.to(off)

    def on_enter_on(self, ctx: StateContext) -> None:
        root_log(self).append(f"enter {ctx.state}")

    async def on_on(self, ctx: StateContext) -> str:
        await ctx.sleep(0.1)
        return "switch"

    def on_exit_on(self, ctx: StateContext) -> None:
        root_log(self).append(f"exit {ctx.state}")


def root_log(m: StateMachine) -> list[str]:
    while m.parent is not None:
        m = m.parent
    return m.log  # type: ignore[attr-defined, no-any-return]


class Calendar(StateMachine):
    day = State(initial=True, machine=Day)
    both = State(parallel=[Lamp, Lamp])
    done = State(final=True)

    done_day = day.to(both)
    done_both = both.to(done)

    def __init__(self, robot: Any) -> None:
        super().__init__(robot)
        self.log: list[str] = []

    def on_enter_day(self, ctx: StateContext) -> None:
        self.log.append(f"enter {ctx.state}")

    def on_exit_day(self, ctx: StateContext) -> None:  # the example: once rejected as a body
        self.log.append(f"exit {ctx.state}")

    async def on_enter_both(self, ctx: StateContext) -> None:
        self.log.append(f"enter {ctx.state}")

    def on_exit_both(self, ctx: StateContext) -> None:
        self.log.append(f"exit {ctx.state}")


async def test_entry_and_exit_actions_on_nested_parallel_and_final_states(robot: agentsdk.Robot) -> None:
    """SCXML §3.7/§3.8 (<onentry>/<onexit>) and §3.13 (exit innermost first, entry outermost first);
    python-statemachine tests/examples/statechart_compound_machine.py and all_actions_machine.py."""
    m = Calendar(robot)
    assert await m.run() == "done"
    assert m.log[:5] == [
        "enter Calendar/day",
        "enter Calendar/day/Day/morning",
        "exit Calendar/day/Day/morning",
        "enter Calendar/day/Day/evening",
        "exit Calendar/day",
    ]
    rest = m.log[5:]
    assert rest[0] == "enter Calendar/both" and rest[-1] == "exit Calendar/both"
    assert sorted(rest[1:-1]) == sorted(["enter Calendar/both/Lamp/on", "exit Calendar/both/Lamp/on"] * 2)
    # the exit action ran after the state's motion had ended: the robot reached joint1 = 0.2
    assert robot.latest_state().position[robot.joint_index["joint1"]] == pytest.approx(0.2, abs=0.02)


def test_entry_exit_action_names_are_checked_at_class_definition() -> None:
    """python-statemachine: callbacks naming unknown states are definition errors (tests/test_statemachine.py)."""
    with pytest.raises(StateMachineDefinitionError, match="on_exit_nigth is the body of state 'exit_nigth'"):

        class Bad(StateMachine):
            night = State(initial=True)
            dawn = State(final=True)
            go = night.to(dawn)

            def on_exit_nigth(self, ctx: StateContext) -> None: ...

    with pytest.raises(StateMachineDefinitionError, match="ambiguous"):

        class Ambiguous(StateMachine):
            a = State(initial=True)
            exit_a = State(final=True)
            go = a.to(exit_a)

            async def on_exit_a(self, ctx: StateContext) -> None: ...


# --------------------------------------------------------------------------- history


class Inner(StateMachine):
    i1 = State(initial=True)
    i2 = State()
    i_end = State(final=True)
    step = i1.to(i2) | i2.to(i_end)


class Steps(StateMachine):
    s1 = State(initial=True)
    s2 = State(machine=Inner)
    s3 = State(final=True)
    step = s1.to(s2)
    done_s2 = s2.to(s3)

    def __init__(self, robot: Any, **kw: Any) -> None:
        super().__init__(robot, **kw)
        self.entries: list[str] = []

    async def on_s1(self, ctx: StateContext) -> None:
        self.entries.append("s1")
        await ctx.robot.move_to({"joint2": 0.3}, duration=0.6)


def make_job(kind: Literal["shallow", "deep"] | None) -> type[StateMachine]:
    class Job(StateMachine):
        working = State(initial=True, machine=Steps, history=kind)
        paused = State()
        complete = State(final=True)
        pause = working.to(paused)
        resume = paused.to(working)
        done_working = working.to(complete)

    return Job


@pytest.mark.parametrize("kind", ["shallow", "deep", None])
async def test_history_resumes_a_compound_state_where_it_was_left(
    robot: agentsdk.Robot, kind: Literal["shallow", "deep"] | None
) -> None:
    """SCXML §3.10 (<history type="shallow|deep">); python-statemachine tests/examples/
    statechart_history_machine.py; transitions tests/test_nesting.py (re-entering a nested state)."""
    job = make_job(kind)(robot)
    runner = asyncio.create_task(job.run())
    await job.wait_state("s1")
    job.send("step")  # s1 -> s2 (its nested machine starts in i1)
    await job.wait_state("s2/Inner/i1")
    job.send("step")  # i1 -> i2
    await job.wait_state("i2")
    job.send("pause")
    await job.wait_state("paused")
    steps = job.children  # none while paused
    assert steps == ()
    job.send("resume")
    await job.wait_state("working")
    expected = {"shallow": "Job/working/Steps/s2/Inner/i1", "deep": "Job/working/Steps/s2/Inner/i2"}
    if kind is None:
        await job.wait_state("s1")
        assert job.state_path == "Job/working/Steps/s1"
        job.send("step")
        await job.wait_state("i1")
    else:
        await job.wait_state(expected[kind].rsplit("/", 1)[-1])
        assert job.state_path == expected[kind]
        assert job.configuration == (
            "Job/working", "Job/working/Steps/s2", expected[kind],
        )
        # the same nested instance resumed: its body ran once, not again
        assert job.children[0].entries == ["s1"]  # type: ignore[attr-defined]
    job.send("step")
    if job.state_path.endswith("i1"):
        await job.wait_state("i2")
        job.send("step")
    assert await runner == "complete"
    notes = [r.note for r in job.history if r.target is not None]
    assert ("history" in notes) == (kind is not None)


async def test_history_after_completion_starts_again_from_the_initial_state(robot: agentsdk.Robot) -> None:
    """SCXML §3.10: history records the configuration on exit; a nested machine that ended
    (reached its final state) has nothing to resume, so it starts from its initial state."""

    class Quick(StateMachine):
        a = State(initial=True)
        end = State(final=True)
        go = a.to(end)

        async def on_a(self, ctx: StateContext) -> str:
            await ctx.sleep(0.05)
            return "go"

    class Loop(StateMachine):
        work = State(initial=True, machine=Quick, history="deep")
        count = State()
        done = State(final=True)
        done_work = work.to(count)
        again = count.to(work, guard=lambda m: m.laps < 2)  # type: ignore[attr-defined]
        finish = count.to(done)

        laps = 0

        async def on_count(self, ctx: StateContext) -> str:
            self.laps += 1
            return "again" if self.laps < 2 else "finish"

    m = Loop(robot)
    assert await m.run() == "done"
    quick = [r for r in m.history if r.machine == "Loop/work/Quick" and r.source is None]
    assert [r.target for r in quick] == ["a", "a"] and {r.note for r in quick} == {"initial"}


# --------------------------------------------------------------------------- internal transitions


class Sweep(StateMachine):
    moving = State(initial=True)
    done = State(final=True)
    tick = moving.internal("count")
    arrived = moving.to(done)

    def __init__(self, robot: Any) -> None:
        super().__init__(robot)
        self.ticks: list[dict[str, Any]] = []
        self.entries = 0
        self.exits = 0
        self.results: list[Any] = []

    def count(self, event: str, data: Any) -> None:
        self.ticks.append(dict(data))

    def on_enter_moving(self, ctx: StateContext) -> None:
        self.entries += 1

    def on_exit_moving(self, ctx: StateContext) -> None:
        self.exits += 1

    async def on_moving(self, ctx: StateContext) -> str:
        result = await ctx.robot.move_to({"joint1": 0.4}, duration=0.8)
        self.results.append(result)
        return "arrived"


async def test_internal_transition_neither_exits_nor_cancels_the_motion(robot: agentsdk.Robot) -> None:
    """SCXML §3.13 (<transition type="internal">: no exit, no entry); transitions tests/test_core.py
    (internal transitions: dest=None keeps the state); python-statemachine ``to.itself(internal=True)``."""
    m = Sweep(robot)
    runner = asyncio.create_task(m.run())
    await m.wait_state("moving")
    for i in range(3):
        await robot.clock.sleep(0.1)
        m.send("tick", {"i": i})
    assert await runner == "done"
    assert m.ticks == [{"i": 0}, {"i": 1}, {"i": 2}]
    assert (m.entries, m.exits) == (1, 1)
    assert [r.code.name for r in m.results] == ["SUCCESSFUL"]  # not CANCELED: the state was never left
    internal = [r for r in m.history if r.note == "internal"]
    assert len(internal) == 3 and all(r.source == r.target == "moving" for r in internal)


def test_internal_transition_must_stay_in_its_state() -> None:
    """SCXML §3.13: an internal transition's targets are its source's descendants; ours, the source itself."""
    with pytest.raises(StateMachineDefinitionError, match="internal but targets 'b'"):

        class Bad(StateMachine):
            a = State(initial=True)
            b = State(final=True)
            go = a.to(b, internal=True)


# --------------------------------------------------------------------------- parallel outcome policy


class Arm(StateMachine):
    reaching = State(initial=True)
    reached = State(final=True)
    missed = State(final=True)
    ok = reaching.to(reached)
    fail = reaching.to(missed)

    async def on_reaching(self, ctx: StateContext) -> str:
        await ctx.robot.move_to({"joint1": ctx.userdata["goal"]}, duration=ctx.userdata.get("time", 0.6))
        return "fail" if ctx.userdata.get("miss") else "ok"


class Gripper(StateMachine):
    opening = State(initial=True)
    opened = State(final=True)
    ok = opening.to(opened)

    def __init__(self, robot: Any, **kw: Any) -> None:
        super().__init__(robot, **kw)
        self.exited = False

    async def on_opening(self, ctx: StateContext) -> str:
        await ctx.sleep(ctx.userdata.get("grip_time", 0.1))
        return "ok"

    def on_exit_opening(self, ctx: StateContext) -> None:
        self.exited = True


def concurrent(finish: Any, miss: bool, arm_time: float = 0.6, grip_time: float = 0.1) -> type[StateMachine]:
    class Pick(StateMachine):
        both = State(
            initial=True,
            parallel=[Arm, Gripper],
            outcome_map={"ready": {"Arm": "reached", "Gripper": "opened"}, "lost": {"Arm": "missed"}},
            finish=finish,
            args=lambda m: {"goal": 0.3, "miss": miss, "time": arm_time, "grip_time": grip_time},
        )
        good = State(final=True)
        bad = State(final=True)
        partial = State(final=True)
        ready = both.to(good)
        lost = both.to(bad)
        done_both = both.to(partial)

        def on_enter_good(self, ctx: StateContext) -> None:
            self.results = dict(ctx.data)

        on_enter_bad = on_enter_partial = on_enter_good

    return Pick


@pytest.mark.parametrize("miss", [False, True])
async def test_concurrence_outcome_map(robot: agentsdk.Robot, miss: bool) -> None:
    """SMACH Concurrence (executive_smach smach_ros/test/concurrence.py, test_concurrence): the outcome is the
    first map entry whose region outcomes all hold once every region ended; the result per region is
    the event's data."""
    m = concurrent("all", miss)(robot)
    assert await m.run() == ("bad" if miss else "good")
    assert m.results == {"Arm": "missed" if miss else "reached", "Gripper": "opened"}  # type: ignore[attr-defined]


async def test_first_region_to_finish_preempts_the_others(robot: agentsdk.Robot) -> None:
    """SMACH Concurrence ``child_termination_cb`` returning True (smach_ros/test/concurrence.py,
    test_preempt): the first child to terminate preempts
    the rest; the preempted region's state exits (its exit action runs, its motion stops)."""
    m = concurrent("first", False, arm_time=2.0, grip_time=0.1)(robot)
    assert await m.run() == "partial"  # the default outcome: Arm never reached
    assert m.results == {"Arm": None, "Gripper": "opened"}  # type: ignore[attr-defined]
    assert any("regions preempted: Arm" in r.note for r in m.history)
    assert robot.clock.now() < 1.0 and speed(robot) < 0.05  # the 2 s arm move was stopped, at rest


async def test_termination_callback_decides_when_a_parallel_state_ends(robot: agentsdk.Robot) -> None:
    """SMACH ``child_termination_cb(outcome_map) -> bool``, called each time a child terminates
    (smach_ros/test/concurrence.py, test_no_preempt / test_outcome_cb)."""
    calls: list[dict[str, str | None]] = []

    def arm_done(results: Any) -> bool:
        calls.append(dict(results))
        return results["Arm"] is not None

    m = concurrent(arm_done, False, arm_time=0.6, grip_time=2.0)(robot)
    assert await m.run() == "partial"
    assert calls == [{"Arm": "reached", "Gripper": None}]
    assert m.results == {"Arm": "reached", "Gripper": None}  # type: ignore[attr-defined]


def test_outcome_map_is_checked_at_class_definition() -> None:
    """SMACH checks outcome maps against its children's outcomes when the container is built."""
    with pytest.raises(StateMachineDefinitionError, match=r"outcome 'ready' needs Arm\.arrived"):

        class Bad(StateMachine):
            both = State(initial=True, parallel=[Arm, Gripper], outcome_map={"ready": {"Arm": "arrived"}})
            end = State(final=True)
            ready = both.to(end)
            done_both = both.to(end)

    with pytest.raises(StateMachineDefinitionError, match="completes with event 'ready'"):

        class NoTransition(StateMachine):
            both = State(initial=True, parallel=[Arm, Gripper], outcome_map={"ready": {"Arm": "reached"}})
            end = State(final=True)
            done_both = both.to(end)


# --------------------------------------------------------------------------- data


class Reach(StateMachine):
    going = State(initial=True)
    there = State(final=True, data=("reached", "speed"))
    ok = going.to(there)

    async def on_going(self, ctx: StateContext) -> str:
        ud = ctx.userdata
        result = await ctx.robot.move_to({"joint3": ud["goal"]}, duration=0.4 / ud["speed"])
        ud["reached"] = round(ud["goal"] + result.error["joint3"], 2)  # remapped: lands in the parent
        ud["scratch"] = "local"  # not remapped: stays in the nested machine
        return "ok"


async def test_event_data_reaches_the_state_it_enters(robot: agentsdk.Robot) -> None:
    """SCXML §5.10 (``_event.data``) and python-statemachine's event arguments: ``send(event, data)``
    hands ``data`` to the entered state as ``ctx.data``."""

    class Go(StateMachine):
        idle = State(initial=True)
        moving = State()
        end = State(final=True)
        go = idle.to(moving)
        arrived = moving.to(end)

        async def on_moving(self, ctx: StateContext) -> str:
            await ctx.robot.move_to({"joint1": ctx.data["target"]}, duration=0.6)
            return "arrived"

    m = Go(robot)
    runner = asyncio.create_task(m.run())
    await m.wait_state("idle")
    m.send("go", {"target": 0.25})
    assert await runner == "end"
    assert robot.latest_state().position[robot.joint_index["joint1"]] == pytest.approx(0.25, abs=0.02)


async def test_data_flows_through_remapped_userdata(robot: agentsdk.Robot) -> None:
    """SMACH remapping (smach_ros/test/state_machine.py, test_userdata_remapping, test_userdata_nesting):
    the nested machine's ``goal``/``reached`` are the parent's ``target``/``result``,
    its other keys are its own; ``args=`` seeds its userdata on entry; the final state's ``data=``
    is the done event's data (SCXML <donedata>)."""

    class Driver(StateMachine):
        reach = State(initial=True, machine=Reach, remap={"goal": "target", "reached": "result"}, args={"speed": 0.5})
        report = State()
        end = State(final=True)
        done_reach = reach.to(report)
        ok = report.to(end)

        async def on_report(self, ctx: StateContext) -> str:
            self.report_data = dict(ctx.data)
            return "ok"

    m = Driver(robot)
    m.userdata["target"] = 0.25
    assert await m.run() == "end"
    assert m.userdata["result"] == pytest.approx(0.25, abs=0.02)
    assert "scratch" not in m.userdata and "speed" not in m.userdata
    assert m.report_data == {"reached": m.userdata["result"], "speed": 0.5}
    assert robot.clock.now() >= 0.8  # duration 0.4 / speed 0.5


# --------------------------------------------------------------------------- declared outcomes


def test_declared_outcomes_are_checked_at_class_definition() -> None:
    """SMACH: a state's outcomes are declared and every one must be connected when the container is
    built (StateMachine.check_consistency); here at class definition, from ``outcomes=`` or a
    ``Literal`` return annotation."""
    with pytest.raises(StateMachineDefinitionError, match="declares outcome 'dropped' but has no 'dropped'"):

        class Bad(StateMachine):
            grasp = State(initial=True, outcomes=("held", "dropped"))
            end = State(final=True)
            held = grasp.to(end)

            async def on_grasp(self, ctx: StateContext) -> str:
                return "held"

    with pytest.raises(StateMachineDefinitionError, match="declares outcome 'slipped'"):

        class Annotated(StateMachine):
            grasp = State(initial=True)
            end = State(final=True)
            held = grasp.to(end)

            async def on_grasp(self, ctx: StateContext) -> Literal["held", "slipped"] | None:
                return "held"


async def test_a_body_returning_an_undeclared_outcome_goes_to_the_fault_state(robot: agentsdk.Robot) -> None:
    """SMACH raises InvalidUserCodeError when execute() returns an undeclared outcome."""

    class Picky(StateMachine):
        grasp = State(initial=True, outcomes=("held",))
        end = State(final=True)
        fault = State(fault=True)
        held = grasp.to(end)
        other = grasp.to(end)
        giveup = fault.to(end)

        async def on_grasp(self, ctx: StateContext) -> str:
            return "other"  # an event of the machine, but not one this state declared

        async def on_fault(self, ctx: StateContext) -> str:
            self.error = ctx.error
            return "giveup"

    m = Picky(robot)
    assert await m.run() == "end"
    assert "not one of its declared outcomes ['held']" in str(m.error)


# --------------------------------------------------------------------------- graceful preemption


class Grasp(StateMachine):
    grasping = State(initial=True, preempt_timeout=2.0)
    away = State(final=True)
    stop = grasping.to(away)

    def __init__(self, robot: Any, *, wind_down: bool) -> None:
        super().__init__(robot)
        self.wind_down = wind_down
        self.finished_grasp: Any = None

    async def on_grasping(self, ctx: StateContext) -> None:
        while True:
            result = await ctx.robot.move_to({"joint2": 0.5}, duration=0.7)
            if self.wind_down and ctx.preempt_requested():
                self.finished_grasp = result  # the last move ran to the end
                await ctx.robot.move_to({"joint2": 0.2}, duration=0.7)  # park before leaving
                return
            await ctx.robot.move_to({"joint2": 0.2}, duration=0.7)


@pytest.mark.parametrize("wind_down", [True, False])
async def test_graceful_preemption_with_a_bound(robot: agentsdk.Robot, wind_down: bool) -> None:
    """SMACH ``request_preempt()`` / ``preempt_requested()`` / ``service_preempt()`` (smach_ros/test/
    concurrence.py: the Getter state polls ``preempt_requested()``): the state is asked to wind down; here bounded by
    ``preempt_timeout``, after which it is cancelled anyway (motions decelerate and hold)."""
    m = Grasp(robot, wind_down=wind_down)
    runner = asyncio.create_task(m.run())
    await m.wait_state("grasping")
    await robot.clock.sleep(0.1)
    t_stop = robot.clock.now()
    m.send("stop")
    assert await runner == "away"
    left = robot.clock.now() - t_stop
    j2 = robot.latest_state().position[robot.joint_index["joint2"]]
    cancelled = [r for r in m.history if r.note.startswith("preempted: body cancelled")]
    if wind_down:
        assert m.finished_grasp.code.name == "SUCCESSFUL"
        assert j2 == pytest.approx(0.2, abs=0.03) and left < 2.0 and not cancelled
    else:
        assert left >= 2.0 and cancelled  # the bound expired; the body was cancelled
    assert speed(robot) < 0.05


# --------------------------------------------------------------------------- event priority


class Child(StateMachine):
    busy = State(initial=True)
    calm = State()
    end = State(final=True)
    stop = busy.to(calm)
    finish = calm.to(end)


def priority_machine(order: Literal["outer", "inner"]) -> type[StateMachine]:
    class Parent(StateMachine):
        event_priority = order
        nested = State(initial=True, machine=Child)
        stopped = State(final=True)
        complete = State(final=True)
        stop = nested.to(stopped)
        other = nested.to(stopped)
        done_nested = nested.to(complete)

    return Parent


@pytest.mark.parametrize("order", ["outer", "inner"])
async def test_event_priority(robot: agentsdk.Robot, order: Literal["outer", "inner"]) -> None:
    """SCXML §3.13 (document order: transitions of the innermost active state are selected first);
    transitions tests/test_nesting.py (a nested state's trigger wins). Our default keeps the parent
    first so a nested machine cannot swallow ``stop``; ``event_priority = "inner"`` is the SCXML order."""
    m = priority_machine(order)(robot)
    runner = asyncio.create_task(m.run())
    await m.wait_state("busy")
    m.send("stop")
    if order == "outer":
        assert await runner == "stopped"
        return
    await m.wait_state("calm")  # the child took it; the parent stayed
    assert m.state == "nested"
    m.send("other")  # no child transition for it: the parent takes it
    assert await runner == "stopped"


def test_event_priority_is_validated() -> None:
    with pytest.raises(StateMachineDefinitionError, match="event_priority must be"):

        class Bad(StateMachine):
            event_priority = "innermost"  # type: ignore[assignment]
            a = State(initial=True)
            b = State(final=True)
            go = a.to(b)


# --------------------------------------------------------------------------- introspection


async def test_live_transitions_configuration_and_run_diagram(robot: agentsdk.Robot) -> None:
    """SCXML §3.11 (the active configuration); python-statemachine ``configuration`` and its diagram
    of the current state; transitions tests/test_mermaid.py (diagram with the active state marked)."""
    m = Calendar(robot)
    seen: list[HistoryRecord] = []
    configs: list[tuple[str, ...]] = []

    async def watch() -> None:
        async for rec in m.transitions():
            seen.append(rec)
            configs.append(m.configuration)

    watcher = asyncio.create_task(watch())
    await asyncio.sleep(0)
    assert await m.run() == "done"
    await watcher  # the iterator ends when the machine finishes
    assert [(r.machine, r.source, r.target) for r in seen if r.target is not None] == [
        (r.machine, r.source, r.target) for r in m.history if r.target is not None
    ]
    day = next(r for r in seen if r.source == "day")
    assert day.duration == pytest.approx(0.5, abs=0.05) and day.configuration.startswith("Calendar/both")
    assert ("Calendar/day", "Calendar/day/Day/morning") in configs
    diagram = m.mermaid_run()
    visited_line = next(ln for ln in diagram.splitlines() if ln.strip().startswith("class "))
    hit = set(visited_line.split()[1].split(","))
    assert {"day", "day__morning", "day__evening", "both", "done"} <= hit
    assert "classDef visited" in diagram
    # a state never entered is not highlighted
    assert Calendar.mermaid(visited=["Calendar/day"]).splitlines()[-1].strip() == "class day visited"


# --------------------------------------------------------------------------- issue 20 item 10: exit at rest


class ReadmePatrol(StateMachine):
    """The README's example, with a fault body that records how the robot was when it started."""

    idle = State(initial=True)
    moving = State(timeout=5.0)
    done = State(final=True)
    fault = State(fault=True)

    go = idle.to(moving)
    arrived = moving.to(done)
    timeout = moving.to(fault)
    recover = fault.to(done)

    async def on_idle(self, ctx: StateContext) -> str:
        return "go"

    async def on_moving(self, ctx: StateContext) -> str:
        await ctx.robot.move_to({"joint1": 1.5})
        return "arrived"

    async def on_fault(self, ctx: StateContext) -> str:
        self.at_fault = (ctx.robot.safety.stop_in_progress, speed(ctx.robot), ctx.error)
        return "recover"


@pytest.mark.parametrize("category", [1, 2])
async def test_readme_example_with_an_estop_ends_in_the_fault_state_at_rest(
    robot: agentsdk.Robot, category: int
) -> None:
    """Issue 20 acceptance 7: the e-stop resolves the motion ABORTED at once while the stop still
    decelerates; the body returns "arrived" anyway; the machine goes to the fault state and starts its
    body only once the stop has brought the robot to rest."""
    m = ReadmePatrol(robot)

    async def estop_mid_move() -> None:
        await m.wait_state("moving")
        await robot.clock.sleep(0.4)
        assert speed(robot) > 1.0  # at speed
        await robot.estop(category=category)

    stopper = asyncio.create_task(estop_mid_move())
    assert await m.run() == "done"
    await stopper
    stopping, v, error = m.at_fault  # type: ignore[attr-defined]
    assert not stopping and v < robot.safety.config.rest_velocity
    assert isinstance(error, RobotStoppedError) and error.reason == "estop"
    assert ("ReadmePatrol", "moving", "fault", "error") in moves(m)
    assert ("ReadmePatrol", "moving", "done", "arrived") not in moves(m)


async def test_an_estop_while_a_body_waits_leaves_the_state_without_a_fault_state(robot: agentsdk.Robot) -> None:
    """Issue 20 item 10, "whatever ends it": a body that does not await its motion (it sleeps) is left
    when the robot is e-stopped; with no fault state run() raises with the cause, after rest."""

    class Sleeper(StateMachine):
        busy = State(initial=True)
        end = State(final=True)
        finish = busy.to(end)

        async def on_busy(self, ctx: StateContext) -> str:
            ctx.robot.follow(Trajectory(["joint1"], [TrajectoryPoint(1.0, np.array([-1.2]))]))  # not awaited
            await ctx.sleep(30.0)
            return "finish"

    m = Sleeper(robot)

    async def estop_soon() -> None:
        await m.wait_state("busy")
        await robot.clock.sleep(0.3)
        robot.estop_threadsafe(category=1)  # as from another thread (a watchdog, a button)

    stopper = asyncio.create_task(estop_soon())
    with pytest.raises(StateMachineError, match="unhandled RobotStoppedError in state Sleeper/busy") as info:
        await m.run()
    await stopper
    assert isinstance(info.value.__cause__, RobotStoppedError)
    assert not robot.safety.stop_in_progress and speed(robot) < robot.safety.config.rest_velocity
    assert robot.clock.now() < 5.0  # left long before the 30 s sleep


async def test_an_estop_in_a_nested_state_reaches_the_enclosing_fault_state_at_rest(robot: agentsdk.Robot) -> None:
    """Issue 20 item 10 with nesting: the innermost active state is left through the fault path, which
    (no fault state inside) is the enclosing machine's; every level exits at rest first."""

    class Move(StateMachine):
        go = State(initial=True)
        end = State(final=True)
        ok = go.to(end)

        async def on_go(self, ctx: StateContext) -> str:
            await ctx.robot.move_to({"joint2": 1.0})
            return "ok"

    class Outer(StateMachine):
        work = State(initial=True, machine=Move)
        fault = State(fault=True)
        end = State(final=True)
        done_work = work.to(end)
        give_up = fault.to(end)

        async def on_fault(self, ctx: StateContext) -> str:
            self.at_fault = (ctx.robot.safety.stop_in_progress, speed(ctx.robot), ctx.error)
            return "give_up"

    m = Outer(robot)

    async def estop_soon() -> None:
        await m.wait_state("go")
        await robot.clock.sleep(0.3)
        await robot.estop(category=2)

    stopper = asyncio.create_task(estop_soon())
    assert await m.run() == "end"
    await stopper
    stopping, v, error = m.at_fault  # type: ignore[attr-defined]
    assert not stopping and v < robot.safety.config.rest_velocity and isinstance(error, RobotStoppedError)


class _AbortedMotion:
    """A finished motion whose result is ABORTED (as the limiter's or a stop's abort leaves it)."""

    class _Code:
        name = "ABORTED"

    class _Result:
        message = "aborted: clipped"

    _Result.code = _Code()  # type: ignore[attr-defined]

    def cancel(self) -> None: ...

    def done(self) -> bool:
        return True

    def result(self) -> Any:
        return self._Result()

    def __await__(self) -> Any:
        return self.result
        yield


async def test_a_body_ignoring_an_aborted_motion_cannot_take_its_transition(robot: agentsdk.Robot) -> None:
    """Issue 20 item 10: a body that ignores its motion's ABORTED result and returns "arrived" goes to
    the fault path (RobotStoppedError, reason "aborted"); a later successful motion clears it."""

    class Ignorant(StateMachine):
        moving = State(initial=True)
        arrived_state = State(final=True)
        fault = State(fault=True)
        failed = State(final=True)
        arrived = moving.to(arrived_state)
        give_up = fault.to(failed)

        retry = False

        async def on_moving(self, ctx: StateContext) -> str:
            scope.register(_AbortedMotion())  # type: ignore[arg-type]
            if self.retry:
                await ctx.robot.move_to({"joint1": 0.1}, duration=0.5)  # a later motion that succeeds
            return "arrived"

        async def on_fault(self, ctx: StateContext) -> str:
            self.error = ctx.error
            return "give_up"

    m = Ignorant(robot)
    assert await m.run() == "failed"
    assert isinstance(m.error, RobotStoppedError) and m.error.reason == "aborted"
    again = Ignorant(robot)
    again.retry = True
    assert await again.run() == "arrived_state"


README = Path(__file__).resolve().parents[1] / "README.md"


async def test_the_readme_patrol_block_with_an_estop_ends_in_fault_at_rest(robot: agentsdk.Robot) -> None:
    """Issue 20 acceptance 7, on the README's own block: its ``Patrol`` (whose ``on_moving`` awaits
    ``move_to`` and returns "arrived") with an e-stop injected mid-move ends in the fault state, and the
    fault body starts with the robot at rest."""
    block = next(b for b in re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S) if "class Patrol(" in b)
    namespace: dict[str, Any] = {"__name__": "readme_patrol"}
    exec(compile(block, "README.md[Patrol]", "exec"), namespace)

    class Observed(namespace["Patrol"]):  # type: ignore[misc, name-defined]
        async def on_fault(self, ctx: StateContext) -> Any:
            self.at_fault = (ctx.robot.safety.stop_in_progress, speed(ctx.robot), ctx.error, ctx.clock.now())
            return await super().on_fault(ctx)

    m = Observed(robot)

    async def estop_mid_move() -> None:
        await m.wait_state("moving")
        await robot.clock.sleep(0.1)
        assert speed(robot) > 0.3
        await robot.estop(category=2)

    stopper = asyncio.create_task(estop_mid_move())
    assert await m.run() == "done"
    await stopper
    stopping, v, error, _ = m.at_fault
    assert not stopping and v < robot.safety.config.rest_velocity
    assert isinstance(error, RobotStoppedError) and error.reason == "estop"
    assert [r.target for r in m.history if r.target] == ["idle", "moving", "fault", "done"]


async def test_the_fault_state_may_stop_and_reset_the_robot_itself(robot: agentsdk.Robot) -> None:
    """The fault state handles stops: an e-stop its own body requests (to be safe, then reset and
    enable) does not send the machine round the fault path again; it still exits at rest."""

    class Careful(StateMachine):
        work = State(initial=True)
        fault = State(fault=True)
        again = State()
        end = State(final=True)
        recovered = fault.to(again)
        ok = again.to(end)

        async def on_work(self, ctx: StateContext) -> None:
            raise RuntimeError("gripper jammed")

        async def on_fault(self, ctx: StateContext) -> str:
            await ctx.robot.estop(category=2)
            await ctx.robot.reset()
            await ctx.robot.enable()
            return "recovered"

        async def on_again(self, ctx: StateContext) -> str:
            self.moved = (await ctx.robot.move_to({"joint1": 0.2}, duration=0.5)).ok
            return "ok"

    m = Careful(robot)
    assert await m.run() == "end"
    assert [r.target for r in m.history if r.target] == ["work", "fault", "again", "end"]
    assert m.moved  # type: ignore[attr-defined]


async def test_an_estop_in_parallel_regions_reaches_the_fault_state_at_rest(robot: agentsdk.Robot) -> None:
    """Issue 20 item 10 with parallel regions: both regions' moving states are left through the fault
    path (their failures merged), and the enclosing fault body starts with the robot at rest."""

    class J1(StateMachine):
        go = State(initial=True)
        end = State(final=True)
        ok = go.to(end)

        async def on_go(self, ctx: StateContext) -> str:
            await ctx.robot.move_to({"joint1": 1.2})
            return "ok"

    class J3(StateMachine):
        go = State(initial=True)
        end = State(final=True)
        ok = go.to(end)

        async def on_go(self, ctx: StateContext) -> str:
            await ctx.robot.move_to({"joint3": -1.0})
            return "ok"

    class Both(StateMachine):
        work = State(initial=True, parallel=[J1, J3])
        fault = State(fault=True)
        end = State(final=True)
        done_work = work.to(end)
        out = fault.to(end)

        async def on_fault(self, ctx: StateContext) -> str:
            self.at_fault = (ctx.robot.safety.stop_in_progress, speed(ctx.robot), ctx.error)
            return "out"

    m = Both(robot)

    async def estop_soon() -> None:
        await m.wait_state("J3/go")
        await robot.clock.sleep(0.3)
        await robot.estop(category=2)

    stopper = asyncio.create_task(estop_soon())
    assert await m.run() == "end"
    await stopper
    stopping, v, error = m.at_fault  # type: ignore[attr-defined]
    assert not stopping and v < robot.safety.config.rest_velocity
    causes = list(error.exceptions) if isinstance(error, ExceptionGroup) else [error]
    assert causes and all(isinstance(c, RobotStoppedError) for c in causes)
    assert ("Both", "work", "end", "done_work") not in moves(m)
