"""Declaring a machine: ``State``, transitions (``a.to(b)``, ``|``) and the validated definition."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ._machine import StateMachine

Guard = str | Callable[["StateMachine"], "bool | Awaitable[bool]"]
"""A method name of the machine, or ``callable(machine) -> bool`` (sync or async)."""

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
        final state names to events is also accepted.
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
    ) -> None:
        self.initial = initial
        self.final = final
        self.fault = fault
        self.timeout = timeout
        self.machine = machine
        self.parallel: tuple[type[StateMachine], ...] | None = tuple(parallel) if parallel is not None else None
        self.done: str | Mapping[str, str] | None = MappingProxyType(dict(done)) if isinstance(done, Mapping) else done
        self.name: str | None = None
        self.owner: type | None = None

    def __set_name__(self, owner: type, name: str) -> None:
        if self.name is None:
            self.name = name
            self.owner = owner

    def __repr__(self) -> str:
        where = f"{self.owner.__name__}." if self.owner is not None else ""
        return f"<State {where}{self.name or '(unnamed)'}>"

    def to(self, target: State | str, *, guard: Guard | None = None) -> TransitionList:
        """A transition from this state to ``target`` (a state or its name).

        The event is the name of the class attribute the result is assigned to.
        """
        return TransitionList([Transition(self, target, guard)])

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

