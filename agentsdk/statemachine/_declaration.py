"""Declaring a machine: ``State``, transitions (``a.to(b)``, ``|``) and the validated definition."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:
    from ._machine import StateMachine

Guard = str | Callable[["StateMachine"], "bool | Awaitable[bool]"]
"""A method name of the machine, or ``callable(machine) -> bool`` (sync or async)."""

Action = str | Callable[..., Any]
"""A transition action: a method name of the machine, or ``callable(machine, event, data)`` (sync or async)."""

History = Literal["shallow", "deep"]
"""``State(history=...)``: re-enter a nested/parallel state where it was left."""

Finish = Literal["all", "first"] | Callable[[Mapping[str, "str | None"]], bool]
"""When a parallel state ends: every region final, the first one, or ``fn(results) -> True``."""

DoneData = Sequence[str] | Callable[["StateMachine"], Mapping[str, Any]]
"""A final state's ``data=``: userdata keys to carry, or ``fn(machine) -> mapping``."""

Args = Mapping[str, Any] | Callable[["StateMachine"], Mapping[str, Any]]
"""A nested machine's ``args=``: userdata set on entry, or ``fn(parent) -> mapping``."""

# --------------------------------------------------------------------------- declaration


class State:
    """A state, declared as a class attribute of a :class:`StateMachine`.

    :param initial: the state the machine starts in (exactly one per machine).
    :param final: reaching it ends the machine; no body, no outgoing transitions.
    :param fault: where exceptions raised in state bodies and guards go (at most one).
    :param timeout: seconds (machine clock) after entry at which the event
        ``"timeout"`` fires; a ``timeout`` transition from this state is required.
    :param machine: a :class:`StateMachine` subclass run as this state's body.
    :param parallel: machine classes run concurrently as this state's body.
    :param done: completion event of a nested/parallel state (default
        ``"done_<state>"``); for ``machine=``, a mapping from the nested machine's
        final state names to events is also accepted.  For a parallel state with
        ``outcome_map``, the event fired when no outcome matches.
    :param history: ``"shallow"`` or ``"deep"`` (nested/parallel states only):
        re-entering the state resumes the nested machine(s) in the state they
        were left in (deep: their nested states too), on the same instances.
        A nested machine that reached a final state starts from its initial state.
    :param outcomes: the events the body may return (SMACH's declared outcomes);
        each needs a transition from this state, checked at class definition.
        A body annotated ``-> Literal["a", "b"]`` declares them too.
    :param preempt_timeout: seconds (machine clock) the body gets to wind down
        when the state is left by an external event or its timeout: the body
        sees ``ctx.preempt_requested()``; it is cancelled after the bound.
    :param outcome_map: parallel states (SMACH ``Concurrence``): ``{event:
        {region: final_state}}``; the first event whose conditions all hold when
        the state ends fires (regions are named by class, ``Name2`` for a repeat).
    :param finish: parallel states: ``"all"`` (default) waits for every region,
        ``"first"`` ends the state when one region is final (the others are
        preempted), a callable ``fn(results) -> bool`` is asked after each region
        finishes (SMACH ``child_termination_cb``).
    :param remap: nested machine's userdata keys shared with this machine's:
        ``{nested_key: parent_key}`` (SMACH remapping); other keys stay local.
    :param args: userdata set on the nested machine(s) each time the state is
        entered: a mapping, or ``fn(parent_machine) -> mapping``.
    :param data: final states: the completion event's data (SCXML donedata):
        userdata keys of the machine, or ``fn(machine) -> mapping``.
    """

    def __init__(
        self,
        *,
        initial: bool = False,
        final: bool = False,
        fault: bool = False,
        timeout: float | None = None,
        machine: type[StateMachine] | None = None,
        parallel: Sequence[type[StateMachine]] | None = None,
        done: str | Mapping[str, str] | None = None,
        history: History | None = None,
        outcomes: Sequence[str] | None = None,
        preempt_timeout: float | None = None,
        outcome_map: Mapping[str, Mapping[str, str]] | None = None,
        finish: Finish = "all",
        remap: Mapping[str, str] | None = None,
        args: Args | None = None,
        data: DoneData | None = None,
    ) -> None:
        self.initial = initial
        self.final = final
        self.fault = fault
        self.timeout = timeout
        self.machine = machine
        self.parallel: tuple[type[StateMachine], ...] | None = tuple(parallel) if parallel is not None else None
        self.done: str | Mapping[str, str] | None = MappingProxyType(dict(done)) if isinstance(done, Mapping) else done
        self.history = history
        self.outcomes: tuple[str, ...] | None = (
            (outcomes,) if isinstance(outcomes, str) else tuple(outcomes) if outcomes is not None else None
        )
        self.preempt_timeout = preempt_timeout
        self.outcome_map: Mapping[str, Mapping[str, str]] | None = (
            MappingProxyType({k: MappingProxyType(dict(v)) for k, v in outcome_map.items()})
            if outcome_map is not None
            else None
        )
        self.finish = finish
        self.remap: Mapping[str, str] = MappingProxyType(dict(remap or {}))
        self.args = args
        self.data: DoneData | None = (data,) if isinstance(data, str) else data
        self.name: str | None = None
        self.owner: type | None = None

    def __set_name__(self, owner: type, name: str) -> None:
        if self.name is None:
            self.name = name
            self.owner = owner

    def __repr__(self) -> str:
        where = f"{self.owner.__name__}." if self.owner is not None else ""
        return f"<State {where}{self.name or '(unnamed)'}>"

    def to(
        self,
        target: State | str,
        *,
        guard: Guard | None = None,
        action: Action | None = None,
        internal: bool = False,
    ) -> TransitionList:
        """A transition from this state to ``target`` (a state or its name).

        The event is the name of the class attribute the result is assigned to.
        ``action`` runs between leaving this state and entering ``target``
        (SCXML transition content).  ``internal=True`` (``target`` must be this
        state) handles the event without leaving: no exit, no entry, the body
        and its motions keep running; only ``action`` runs.
        """
        return TransitionList([Transition(self, target, guard, action=action, internal=internal)])

    def internal(self, action: Action | None = None, *, guard: Guard | None = None) -> TransitionList:
        """``state.to(state, internal=True, action=...)``: handle an event without leaving the state."""
        return self.to(self, guard=guard, action=action, internal=True)

    @property
    def is_composite(self) -> bool:
        """True for a state with a nested machine or parallel regions."""
        return self.machine is not None or self.parallel is not None

    def completion_event(self, final_state: str | None = None) -> str:
        """The event fired when this composite state completes (optionally per final state reached)."""
        if isinstance(self.done, Mapping):
            if final_state is not None and final_state in self.done:
                return self.done[final_state]
        elif self.done is not None:
            return self.done
        return f"done_{self.name}"


@dataclass(slots=True)
class Transition:
    """One edge; ``event`` is filled in when the :class:`TransitionList` is named."""

    source: State
    target: State | str
    guard: Guard | None = None
    event: str | None = None
    action: Action | None = None
    internal: bool = False


class TransitionList:
    """Transitions sharing one event: ``stop = moving.to(idle) | idle.to(done)``."""

    def __init__(self, transitions: Sequence[Transition]) -> None:
        self.transitions: list[Transition] = list(transitions)
        self.event: str | None = None

    def __or__(self, other: TransitionList) -> TransitionList:
        if not isinstance(other, TransitionList):
            return NotImplemented
        return TransitionList([*self.transitions, *other.transitions])

    def __set_name__(self, owner: type, name: str) -> None:
        if self.event is None:
            self.event = name
            for t in self.transitions:
                t.event = name

    def __iter__(self) -> Iterator[Transition]:
        return iter(self.transitions)

    def __repr__(self) -> str:
        return f"<TransitionList {self.event!r}: {len(self.transitions)} transition(s)>"


@dataclass(frozen=True, slots=True)
class Edge:
    source: str
    target: str
    event: str
    guard: Guard | None
    action: Action | None = None
    internal: bool = False

    @property
    def guard_label(self) -> str | None:
        if self.guard is None:
            return None
        if isinstance(self.guard, str):
            return self.guard
        name = getattr(self.guard, "__name__", "")
        return name if name.isidentifier() else "guard"


@dataclass(frozen=True, slots=True)
class Spec:
    states: Mapping[str, State]
    initial: str
    fault: str | None
    edges: tuple[Edge, ...]
    by_source: Mapping[str, Mapping[str, tuple[Edge, ...]]]
    events: frozenset[str]
    outcomes: Mapping[str, frozenset[str]] = field(default_factory=lambda: MappingProxyType({}))
    """The events each state's body is declared to return (``outcomes=`` or a ``Literal`` annotation)."""
    regions: Mapping[str, tuple[str, ...]] = field(default_factory=lambda: MappingProxyType({}))
    """Parallel states: the region names, in order (class names, ``Name2`` for a repeated class)."""



def region_names(classes: Sequence[type[StateMachine]]) -> tuple[str, ...]:
    """The names of parallel regions: class names, ``Name2``, ``Name3`` for repeats."""
    seen: dict[str, int] = {}
    out = []
    for cls in classes:
        n = seen[cls.__name__] = seen.get(cls.__name__, 0) + 1
        out.append(cls.__name__ if n == 1 else f"{cls.__name__}{n}")
    return tuple(out)
