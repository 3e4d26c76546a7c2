"""Definition-time validation: every mistake in a machine class raises, naming class, state and problem."""

from __future__ import annotations

import inspect
import math
import typing
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal

from ._declaration import Edge, Spec, State, TransitionList, region_names
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
    methods = {
        n: fn
        for klass in reversed(cls.__mro__)
        for n, fn in vars(klass).items()
        if n.startswith("on_") and callable(fn)
    }
    bodies: dict[str, Callable[..., Any]] = {}
    actions: dict[tuple[str, str], Callable[..., Any]] = {}  # ("enter"|"exit", state) -> method
    for meth, fn in methods.items():
        rest = meth[3:]
        kind = next((k for k in ("enter", "exit") if rest.startswith(k + "_") and rest[len(k) + 1 :] in states), None)
        if kind is not None and rest in states:
            raise fail(f"method {meth} is ambiguous: the body of state {rest!r} or the {kind} action of state "
                       f"{rest[len(kind) + 1 :]!r}; rename one of the states")
        if kind is not None:
            actions[(kind, rest[len(kind) + 1 :])] = fn
            continue
        if rest not in states:
            raise fail(f"method {meth} is the body of state {rest!r}, which is not declared "
                       f"(entry/exit actions are on_enter_<state> / on_exit_<state>)")
        if not inspect.iscoroutinefunction(fn):
            raise fail(f"state {rest!r}: body {meth} must be 'async def {meth}(self, ctx)'")
        bodies[rest] = fn
    outcomes: dict[str, frozenset[str]] = {}
    for name, st in states.items():
        declared = set(st.outcomes or ())
        if st.outcomes is not None and name not in bodies:
            raise fail(f"state {name!r} declares outcomes= but has no body on_{name} to return them")
        if name in bodies:
            declared |= _literal_outcomes(bodies[name])
        if declared:
            outcomes[name] = frozenset(declared)
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
        if st.history is not None:
            if st.history not in ("shallow", "deep"):
                raise fail(f"state {name!r}: history must be 'shallow' or 'deep', not {st.history!r}")
            if not nested:
                raise fail(f"state {name!r}: history= is only for machine= or parallel= states")
        if st.preempt_timeout is not None and not (
            isinstance(st.preempt_timeout, int | float) and math.isfinite(st.preempt_timeout) and st.preempt_timeout > 0
        ):
            raise fail(f"state {name!r}: preempt_timeout must be a finite number of seconds > 0, "
                       f"not {st.preempt_timeout!r}")
        if (st.remap or st.args is not None) and not nested:
            raise fail(f"state {name!r}: remap= and args= are only for machine= or parallel= states")
        for key, parent_key in st.remap.items():
            if not (isinstance(key, str) and key and isinstance(parent_key, str) and parent_key):
                raise fail(f"state {name!r}: remap= maps userdata key names to key names, got {key!r}: {parent_key!r}")
        if st.args is not None and not (isinstance(st.args, Mapping) or callable(st.args)):
            raise fail(f"state {name!r}: args= must be a mapping or fn(machine) -> mapping, not {st.args!r}")
        if st.data is not None:
            if not st.final:
                raise fail(f"state {name!r}: data= (the done event's data) is only for final states")
            if not callable(st.data) and not all(isinstance(k, str) and k for k in st.data):
                raise fail(f"final state {name!r}: data= must be userdata key names or fn(machine), not {st.data!r}")
        if st.finish not in ("all", "first") and not callable(st.finish):
            raise fail(f"state {name!r}: finish must be 'all', 'first' or fn(results) -> bool, not {st.finish!r}")
        if (st.finish != "all" or st.outcome_map is not None) and st.parallel is None:
            raise fail(f"state {name!r}: finish= and outcome_map= are only for parallel= states")
        if st.outcome_map is not None and st.parallel is not None:
            regions = dict(zip(region_names(st.parallel), st.parallel, strict=True))
            for event, conditions in st.outcome_map.items():
                if not isinstance(event, str) or not event.isidentifier():
                    raise fail(f"state {name!r}: outcome_map key {event!r} is not an event name")
                if not conditions:
                    raise fail(f"state {name!r}: outcome {event!r} has no conditions")
                for region, final in conditions.items():
                    if region not in regions:
                        raise fail(f"state {name!r}: outcome {event!r} names region {region!r}; "
                                   f"the regions are {', '.join(regions)}")
                    region_states = regions[region].definition().states
                    if final not in region_states or not region_states[final].final:
                        raise fail(f"state {name!r}: outcome {event!r} needs {region}.{final}, "
                                   f"which is not a final state of {regions[region].__name__}")

    # transitions
    edges: list[Edge] = []
    for event, tl in lists.items():
        for t in tl:
            if t.event is None:
                t.event = event
            source = state_name(t.source, "source", event)
            target = state_name(t.target, "target", event)
            guard = t.guard
            if t.internal and target != source:
                raise fail(f"transition {event!r} from {source!r} is internal but targets {target!r}; "
                           f"an internal transition stays in its source state")
            if isinstance(t.action, str):
                if not callable(getattr(cls, t.action, None)):
                    raise fail(f"transition {event!r} from {source!r}: action {t.action!r} is not a method of "
                               f"{cls.__name__}")
            elif t.action is not None and not callable(t.action):
                raise fail(f"transition {event!r} from {source!r}: action {t.action!r} is neither a method name "
                           f"nor callable")
            if isinstance(guard, str):
                if not callable(getattr(cls, guard, None)):
                    raise fail(
                        f"transition {event!r} from {source!r}: guard {guard!r} is not a method of {cls.__name__}"
                    )
            elif guard is not None and not callable(guard):
                raise fail(
                    f"transition {event!r} from {source!r}: guard {guard!r} is neither a method name nor callable"
                )
            edges.append(Edge(source, target, event, guard, t.action, t.internal))
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
        for outcome in sorted(outcomes.get(name, ())):
            if outcome not in out:
                raise fail(f"state {name!r} declares outcome {outcome!r} but has no {outcome!r} transition from it")
    priority = getattr(cls, "event_priority", "outer")
    if priority not in ("outer", "inner"):
        raise fail(f"event_priority must be 'outer' (the default) or 'inner' (SCXML), not {priority!r}")

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
        outcomes=MappingProxyType(outcomes),
        regions=MappingProxyType({n: region_names(s.parallel) for n, s in states.items() if s.parallel is not None}),
    )


def _literal_outcomes(fn: Callable[..., Any]) -> set[str]:
    """The event names of a body annotated ``-> Literal["a", "b"]`` (or ``Literal[...] | None``)."""
    try:
        ret = typing.get_type_hints(fn).get("return")
    except Exception:  # an annotation that cannot be evaluated declares nothing
        return set()
    found: set[str] = set()

    def walk(tp: Any) -> None:
        if typing.get_origin(tp) is Literal:
            found.update(a for a in typing.get_args(tp) if isinstance(a, str))
        else:
            for arg in typing.get_args(tp):
                walk(arg)

    walk(ret)
    return found




def completion_events(st: State) -> list[str]:
    """The events a nested/parallel state can fire when its machine(s) finish."""
    if st.machine is not None:
        finals = [n for n, s in st.machine.definition().states.items() if s.final]
        return list(dict.fromkeys(st.completion_event(f) for f in finals))
    if st.parallel is not None:
        # the outcome map's events, and the default (SMACH default_outcome) when none matches
        events = list(st.outcome_map or ())
        if st.finish != "all" or all(any(s.final for s in r.definition().states.values()) for r in st.parallel):
            events.append(st.completion_event())
        return list(dict.fromkeys(events))
    return []
