"""Values a running machine creates: history records, state contexts, queue items, region failures."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Iterator, Mapping, MutableMapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from ..scope import ClockLike, MotionScope

if TYPE_CHECKING:
    from ._declaration import Edge
    from ._machine import StateMachine

EMPTY: Mapping[str, Any] = MappingProxyType({})

_log = logging.getLogger("agentsdk.statemachine")

# --------------------------------------------------------------------------- runtime values


@dataclass(frozen=True, slots=True)
class HistoryRecord:
    """One entry of :attr:`StateMachine.history`.

    ``target`` is ``None`` for events that did not cause a transition (see ``note``).
    ``machine`` is the path of the machine the states belong to ("Patrol",
    "Patrol/moving/Approach"); the root's history holds the records of nested
    machines as well.  ``duration`` and ``configuration`` are observations
    (timing, the active configuration) and take no part in equality.
    """

    time: float
    source: str | None
    target: str | None
    event: str | None
    note: str = ""
    machine: str = ""
    duration: float | None = field(default=None, compare=False)
    """Seconds (machine clock) spent in ``source`` (a transition); ``None`` otherwise."""
    configuration: str = field(default="", compare=False)
    """The root machine's active configuration after this record (:attr:`StateMachine.state_path`)."""


class UserData(MutableMapping[str, Any]):
    """A machine's userdata: a dict, where remapped keys live in the parent's userdata (SMACH remapping).

    ``remap`` maps this machine's key to the parent's key; reads and writes of a
    remapped key go to the parent, every other key is this machine's own.
    """

    def __init__(self, parent: MutableMapping[str, Any] | None = None, remap: Mapping[str, str] | None = None) -> None:
        self._local: dict[str, Any] = {}
        self._parent = parent
        self._remap: Mapping[str, str] = dict(remap or {}) if parent is not None else {}

    def _where(self, key: str) -> tuple[MutableMapping[str, Any], str]:
        if self._parent is not None and key in self._remap:
            return self._parent, self._remap[key]
        return self._local, key

    def __getitem__(self, key: str) -> Any:
        where, k = self._where(key)
        try:
            return where[k]
        except KeyError:
            raise KeyError(key) from None

    def __setitem__(self, key: str, value: Any) -> None:
        where, k = self._where(key)
        where[k] = value

    def __delitem__(self, key: str) -> None:
        where, k = self._where(key)
        del where[k]

    def __iter__(self) -> Iterator[str]:
        keys = dict.fromkeys(self._local)
        if self._parent is not None:
            keys.update(dict.fromkeys(k for k, pk in self._remap.items() if pk in self._parent))
        return iter(keys)

    def __len__(self) -> int:
        return sum(1 for _ in self)

    def __repr__(self) -> str:
        return f"UserData({dict(self)!r})"


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
    data: Mapping[str, Any] = field(default_factory=lambda: EMPTY)
    """The data of the event that entered this state (``send(event, data)``, a nested
    machine's done data, a parallel state's result per region)."""
    preempt: asyncio.Event | None = field(default=None, repr=False)

    @property
    def userdata(self) -> MutableMapping[str, Any]:
        """The machine's :attr:`~StateMachine.userdata`."""
        return self.machine.userdata

    def preempt_requested(self) -> bool:
        """True once the state is being left and the body may wind down.

        Requested by this state's ``State(preempt_timeout=...)``, or an enclosing
        composite state's (which asks its nested machines' active states).
        """
        return self.preempt is not None and self.preempt.is_set()

    async def wait_preempt(self) -> None:
        """Return when preemption is requested (see :meth:`preempt_requested`)."""
        if self.preempt is None:
            await asyncio.get_running_loop().create_future()  # forever; cancelled when the state is left
        else:
            await self.preempt.wait()

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
    data: Mapping[str, Any] = field(default_factory=lambda: EMPTY)


@dataclass(frozen=True, slots=True)
class Completion:
    token: object
    event: str | None
    data: Mapping[str, Any] = field(default_factory=lambda: EMPTY)


@dataclass(frozen=True, slots=True)
class Poke:
    """The safety layer recorded something: check whether the robot was stopped."""


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


Item = External | Completion | TimerFired | Failure | Poke


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
    data: Mapping[str, Any] = field(default_factory=lambda: EMPTY)
    edge: Edge | None = None
    preemptive: bool = False  # taken while the body may still run (an external event or the timeout)


@dataclass(slots=True)
class Waiter:
    machine: StateMachine
    target: str
    future: asyncio.Future[None] = field(repr=False)

