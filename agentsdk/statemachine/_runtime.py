"""Values a running machine creates: history records, state contexts, queue items, region failures."""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ..scope import ClockLike, MotionScope

if TYPE_CHECKING:
    from ._machine import StateMachine

_log = logging.getLogger("agentsdk.statemachine")

# --------------------------------------------------------------------------- runtime values


@dataclass(frozen=True, slots=True)
class HistoryRecord:
    """One entry of :attr:`StateMachine.history`.

    ``target`` is ``None`` for events that did not cause a transition (see ``note``).
    ``machine`` is the path of the machine the states belong to ("Patrol",
    "Patrol/moving/Approach"); the root's history holds the records of nested
    machines as well.
    """

    time: float
    source: str | None
    target: str | None
    event: str | None
    note: str = ""
    machine: str = ""


@dataclass(frozen=True, slots=True)
class StateContext:
    """What a state body receives."""

    robot: Any
    machine: StateMachine
    state: str
    """The full path of the state, e.g. ``"Patrol/moving/Approach/grasp"``."""
    clock: ClockLike
    event: str | None = None
    """The event that entered this state (``None`` for the initial state)."""
    error: BaseException | None = None
    """In a fault state: the exception that led here (also ``machine.last_error``)."""
    scope: MotionScope | None = None
    """The motions started by this state so far (stopped when the state is left)."""

    @property
    def name(self) -> str:
        """The state's own name (the last path segment)."""
        return self.state.rsplit("/", 1)[-1]

    async def sleep(self, dt: float) -> None:
        """Sleep ``dt`` seconds on the robot's clock (simulated time in lockstep)."""
        await self.clock.sleep(dt)


@dataclass(frozen=True, slots=True)
class External:
    event: str


@dataclass(frozen=True, slots=True)
class Completion:
    token: object
    event: str | None


@dataclass(frozen=True, slots=True)
class TimerFired:
    token: object


@dataclass(frozen=True, slots=True)
class Failure:
    token: object
    exc: BaseException
    path: str
    estopped: bool = False
    fatal: bool = False  # not routed to fault states (the robot would not stop)


Item = External | Completion | TimerFired | Failure


class Unhandled(Exception):
    """Carries an unhandled failure up through enclosing machines."""

    def __init__(self, exc: BaseException, path: str, *, estopped: bool, fatal: bool) -> None:
        super().__init__(path, exc)
        self.exc = exc
        self.path = path
        self.estopped = estopped
        self.fatal = fatal


def exception_leaves(eg: BaseExceptionGroup) -> list[BaseException]:
    out: list[BaseException] = []
    for exc in eg.exceptions:
        out.extend(exception_leaves(exc) if isinstance(exc, BaseExceptionGroup) else [exc])
    return out


def merge_region_failures(eg: BaseExceptionGroup, path: str) -> BaseException:
    """What a parallel state raises when its regions failed: every failure, none dropped.

    One failure is raised as it is. Several (regions failing in the same step) become
    one :class:`Unhandled` carrying an ``ExceptionGroup`` of every region's exception,
    e-stopped/fatal if any of them was. A leaf that is not an ``Exception``
    (``KeyboardInterrupt``, ``SystemExit``) wins: the group is re-raised as it came.
    """
    leaves = [e for e in exception_leaves(eg) if not isinstance(e, asyncio.CancelledError)]
    if not leaves:
        return asyncio.CancelledError()
    if any(not isinstance(e, Exception) for e in leaves):
        return eg
    if len(leaves) == 1:
        return leaves[0]
    causes: list[Exception] = [e.exc if isinstance(e, Unhandled) else e for e in leaves if isinstance(e, Exception)]  # type: ignore[misc]
    where = [e.path for e in leaves if isinstance(e, Unhandled)]
    group = ExceptionGroup(f"{len(causes)} parallel regions of {path} failed: {', '.join(where) or path}", causes)
    unhandled = [e for e in leaves if isinstance(e, Unhandled)]
    return Unhandled(
        group,
        path,
        estopped=any(u.estopped for u in unhandled),
        fatal=any(u.fatal for u in unhandled),
    )


@dataclass(slots=True)
class Step:
    target: str | None
    event: str | None
    time: float
    error: Unhandled | None = None


@dataclass(slots=True)
class Waiter:
    machine: StateMachine
    target: str
    future: asyncio.Future[None] = field(repr=False)

