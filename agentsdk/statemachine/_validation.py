"""Definition-time validation: every mistake in a machine class raises, naming class, state and problem."""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING

from ._declaration import Edge, Spec, State, TransitionList
from ._errors import StateMachineDefinitionError

if TYPE_CHECKING:
    from ._machine import StateMachine

# --------------------------------------------------------------------------- validation


def build_spec(cls: type[StateMachine], reserved: frozenset[str]) -> Spec | None:
    """Collect and validate the declaration of ``cls``; ``None`` if it declares no states."""
    from ._machine import StateMachine  # deferred: runs at class creation, after _machine has loaded

    states: dict[str, State] = {}
    lists: dict[str, TransitionList] = {}
    for klass in reversed(cls.__mro__):
        for attr, value in vars(klass).items():
            if isinstance(value, State):
                states[attr] = value
            elif isinstance(value, TransitionList):
                lists[attr] = value
    if not states:
        if lists:
            raise StateMachineDefinitionError(f"{cls.__name__}: transitions are declared but no states")
        return None

    def fail(problem: str) -> StateMachineDefinitionError:
        return StateMachineDefinitionError(f"{cls.__name__}: {problem}")

    for name in (*states, *lists):
        if name in reserved:
            raise fail(f"{name!r} would shadow StateMachine.{name}; rename the state or event")
    names: dict[int, str] = {}
    for name, st in states.items():
        if id(st) in names:
            raise fail(f"states {names[id(st)]!r} and {name!r} are the same State object")
        names[id(st)] = name

    def state_name(ref: State | str, what: str, event: str) -> str:
        if isinstance(ref, str):
            if ref not in states:
                raise fail(f"transition {event!r} has {what} {ref!r}, which is not a state of {cls.__name__}")
            return ref
        if id(ref) not in names:
            raise fail(f"transition {event!r} has {what} {ref!r}, which is not a state of {cls.__name__}")
        return names[id(ref)]

    # states
    initial = [n for n, s in states.items() if s.initial]
    if not initial:
        raise fail("no initial state; mark one State(initial=True)")
    if len(initial) > 1:
        raise fail(f"two initial states: {initial[0]!r} and {initial[1]!r}")
    faults = [n for n, s in states.items() if s.fault]
    if len(faults) > 1:
        raise fail(f"more than one fault state: {', '.join(map(repr, faults))}")
    bodies = {
        n[3:]: fn
        for klass in reversed(cls.__mro__)
        for n, fn in vars(klass).items()
        if n.startswith("on_") and callable(fn)
    }
    for body_state, fn in bodies.items():
        if body_state not in states:
            raise fail(f"method on_{body_state} is the body of state {body_state!r}, which is not declared")
        if not inspect.iscoroutinefunction(fn):
            raise fail(f"state {body_state!r}: body on_{body_state} must be 'async def on_{body_state}(self, ctx)'")
    for name, st in states.items():
        if st.initial and st.final:
            raise fail(f"state {name!r} is both initial and final")
        if st.machine is not None and st.parallel is not None:
            raise fail(f"state {name!r} has both machine= and parallel=")
        nested = (st.machine,) if st.machine is not None else st.parallel or ()
        if st.parallel is not None and not st.parallel:
            raise fail(f"state {name!r}: parallel= needs at least one machine")
        for sub in nested:
            if not (isinstance(sub, type) and issubclass(sub, StateMachine)) or sub.is_abstract():
                raise fail(f"state {name!r}: {sub!r} is not a StateMachine subclass with states")
        if isinstance(st.done, Mapping):
            if st.machine is None:
                raise fail(f"state {name!r}: a done= mapping needs machine=")
            sub_spec = st.machine.definition()
            for key in st.done:
                if key not in sub_spec.states or not sub_spec.states[key].final:
                    raise fail(f"state {name!r}: done= key {key!r} is not a final state of {st.machine.__name__}")
        elif st.done is not None and not nested:
            raise fail(f"state {name!r}: done= is only for machine= or parallel= states")
        if nested and name in bodies:
            raise fail(f"state {name!r} runs a nested machine and also has a body on_{name}")
        if st.timeout is not None and not (isinstance(st.timeout, int | float) and math.isfinite(st.timeout)):
            raise fail(f"state {name!r}: timeout must be a finite number of seconds, not {st.timeout!r}")
        if st.timeout is not None and st.timeout <= 0:
            raise fail(f"state {name!r}: timeout must be > 0, not {st.timeout!r}")
        if st.final and (st.timeout is not None or nested or name in bodies):
            raise fail(f"final state {name!r} cannot have a body, a timeout or a nested machine")

    # transitions
    edges: list[Edge] = []
    for event, tl in lists.items():
        for t in tl:
            if t.event is None:
                t.event = event
            source = state_name(t.source, "source", event)
            target = state_name(t.target, "target", event)
            guard = t.guard
            if isinstance(guard, str):
                if not callable(getattr(cls, guard, None)):
                    raise fail(
                        f"transition {event!r} from {source!r}: guard {guard!r} is not a method of {cls.__name__}"
                    )
            elif guard is not None and not callable(guard):
                raise fail(
                    f"transition {event!r} from {source!r}: guard {guard!r} is neither a method name nor callable"
                )
            edges.append(Edge(source, target, event, guard))
    by_source: dict[str, dict[str, list[Edge]]] = {n: {} for n in states}
    for e in edges:
        by_source[e.source].setdefault(e.event, []).append(e)
    for name, st in states.items():
        out = by_source[name]
        if st.final and out:
            raise fail(f"final state {name!r} has outgoing transitions: {', '.join(map(repr, out))}")
        if st.timeout is not None and "timeout" not in out:
            raise fail(f"state {name!r} has timeout={st.timeout:g} but no 'timeout' transition from it")
        if not st.final and not out and name not in bodies and not st.is_composite:
            raise fail(f"state {name!r} is not final, has no body and no outgoing transitions (a trap)")
        for completion in completion_events(st):
            if completion not in out:
                raise fail(f"state {name!r} completes with event {completion!r} but has no {completion!r} transition")

    # reachability: from the initial state; the fault state is entered on any error
    reached = {initial[0]}
    todo = [initial[0]]
    if faults:
        reached.add(faults[0])
        todo.append(faults[0])
    while todo:
        for es in by_source[todo.pop()].values():
            for e in es:
                if e.target not in reached:
                    reached.add(e.target)
                    todo.append(e.target)
    for name in states:
        if name not in reached:
            raise fail(f"state {name!r} is unreachable from the initial state {initial[0]!r}")

    return Spec(
        states=MappingProxyType(dict(states)),
        initial=initial[0],
        fault=faults[0] if faults else None,
        edges=tuple(edges),
        by_source=MappingProxyType(
            {n: MappingProxyType({ev: tuple(es) for ev, es in d.items()}) for n, d in by_source.items()}
        ),
        events=frozenset(e.event for e in edges),
    )




def completion_events(st: State) -> list[str]:
    """The events a nested/parallel state can fire when its machine(s) finish."""
    if st.machine is not None:
        finals = [n for n, s in st.machine.definition().states.items() if s.final]
        return list(dict.fromkeys(st.completion_event(f) for f in finals))
    if st.parallel is not None:
        if all(any(s.final for s in r.definition().states.values()) for r in st.parallel):
            return [st.completion_event()]
    return []

