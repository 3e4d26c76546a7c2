"""Asynchronous, hierarchical state machines for robot behaviours.

Why our own engine and not python-statemachine underneath: its async engine
awaits callbacks inline inside one run-to-completion step (``on_enter`` is
awaited before the next queued event is even looked at), so a long-running
state body cannot be preempted by an external event, and a state never owns a
task that could be cancelled.  It has no per-state timeouts, no injectable
clock (we need the robot's simulated time), and no hook to cancel and await a
state's child work (motions, nested machines) when the state is left -- all of
that would be our code wrapped around its transition table.  What it would still
give us, class-based declaration and definition-time validation, is the small
part; so we keep its declaration style (``State``, ``a.to(b)``, ``|``) and
implement a small engine on ``asyncio.TaskGroup``: one task per state body, one
event queue per machine, and task cancellation as the preemption mechanism.

Declaring a machine::

    class Patrol(StateMachine):
        idle = State(initial=True)
        moving = State(timeout=5.0)          # "timeout" fires after 5 s of machine clock
        done = State(final=True)
        fault = State(fault=True)            # exceptions in any state land here

        go = idle.to(moving)                 # the attribute name is the event name
        arrived = moving.to(done)
        stop = moving.to(idle) | idle.to(done)
        timeout = moving.to(fault)
        retry = fault.to(idle, guard="can_retry") | fault.to(done)

        async def on_idle(self, ctx: StateContext) -> str | None:
            return "go"                      # completion event

        async def on_moving(self, ctx: StateContext) -> str | None:
            await ctx.robot.follow(path)     # motion registered in the state's scope
            return "arrived"

        def can_retry(self) -> bool:
            return self.attempts < 3

    final_state = await Patrol(robot).run()

Semantics:

* The class is validated when it is defined; mistakes raise
  :class:`StateMachineDefinitionError` naming the class, the state and the problem.
* Entering a state starts its body ``async def on_<state>(self, ctx)`` as its own
  task, inside a fresh :class:`~agentsdk.scope.MotionScope`.  A returned string is
  fired as an event; ``None`` means "wait here for an event or the timeout".
* ``machine.send(event)`` (synchronous) queues an external event.  If the current
  state has an enabled transition for it, the state is left: its body task is
  cancelled (its ``finally`` runs), its motions are asked to decelerate and hold
  and are awaited (bounded by ``stop_timeout``; on expiry the robot is e-stopped
  and :class:`StateMachineError` is raised).  Events nobody handles are recorded
  in :attr:`StateMachine.history` (or raise :class:`EventNotAllowed` when
  ``strict=True``).
* ``State(machine=Sub)`` runs a nested machine as the state body; reaching a
  final state of ``Sub`` fires ``done_<state>`` (or ``done=``).
  ``State(parallel=[A, B])`` runs several machines as concurrent regions and
  fires ``done_<state>`` when all of them are final.  Events are offered to the
  outer machine first: an outer transition preempts the whole nested machine
  (an inner machine cannot swallow the outer ``stop``); events the outer state
  does not take are forwarded to the active nested machine(s).
* An exception in a state body (or guard) goes to the nearest ``fault=True``
  state of the machine or an enclosing one (``machine.last_error``,
  ``ctx.error``).  With no fault state, the robot is stopped with
  ``await robot.estop(category=1)`` and ``run()`` raises :class:`StateMachineError`
  naming the state path, chained to the original exception.
* Cancelling ``run()`` leaves the active state (same cleanup) and re-raises
  ``CancelledError``.
"""

from __future__ import annotations

import asyncio
import importlib
import importlib.util
import inspect
import logging
import math
import os
import sys
from collections.abc import Awaitable, Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType, ModuleType
from typing import Any, ClassVar

from .errors import AgentSDKError, ConfigurationError
from .loop import HookHandle
from .scope import DEFAULT_STOP_TIMEOUT, ClockLike, LoopClock, MotionScope, MotionStopTimeoutError

__all__ = [
    "ClockLike",
    "EventNotAllowed",
    "HistoryRecord",
    "LoopClock",
    "State",
    "StateContext",
    "StateMachine",
    "StateMachineDefinitionError",
    "StateMachineError",
    "Transition",
    "TransitionList",
    "TransitionListener",
    "find_machines",
]

_log = logging.getLogger(__name__)

Guard = str | Callable[["StateMachine"], "bool | Awaitable[bool]"]
"""A method name of the machine, or ``callable(machine) -> bool`` (sync or async)."""


# --------------------------------------------------------------------------- errors


class StateMachineDefinitionError(ConfigurationError):
    """A machine class is malformed; raised when the class statement executes."""


class StateMachineError(AgentSDKError):
    """A machine failed while running (unhandled error in a state, motion would not stop...)."""

    def __init__(self, message: str, *, path: str | None = None) -> None:
        super().__init__(message)
        self.path = path


class EventNotAllowed(StateMachineError):
    """``strict=True`` and no active state has a transition for the event."""


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
class _Edge:
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
class _Spec:
    states: Mapping[str, State]
    initial: str
    fault: str | None
    edges: tuple[_Edge, ...]
    by_source: Mapping[str, Mapping[str, tuple[_Edge, ...]]]
    events: frozenset[str]


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
class _External:
    event: str


@dataclass(frozen=True, slots=True)
class _Completion:
    token: object
    event: str | None


@dataclass(frozen=True, slots=True)
class _TimerFired:
    token: object


@dataclass(frozen=True, slots=True)
class _Failure:
    token: object
    exc: BaseException
    path: str
    estopped: bool = False
    fatal: bool = False  # not routed to fault states (the robot would not stop)


_Item = _External | _Completion | _TimerFired | _Failure


class _Unhandled(Exception):
    """Carries an unhandled failure up through enclosing machines."""

    def __init__(self, exc: BaseException, path: str, *, estopped: bool, fatal: bool) -> None:
        super().__init__(path, exc)
        self.exc = exc
        self.path = path
        self.estopped = estopped
        self.fatal = fatal


@dataclass(slots=True)
class _Step:
    target: str | None
    event: str | None
    time: float
    error: _Unhandled | None = None


@dataclass(slots=True)
class _Waiter:
    machine: StateMachine
    target: str
    future: asyncio.Future[None] = field(repr=False)


# --------------------------------------------------------------------------- the machine


#: ``fn(machine, record)``: told of every transition any state machine records
TransitionListener = Callable[["StateMachine", HistoryRecord], None]
_transition_listeners: list[TransitionListener] = []


class StateMachine:
    """Base class of declared machines; see the module documentation.

    :param robot: passed to state bodies as ``ctx.robot``; ``robot.estop(category=1)``
        is awaited on unhandled errors and ``robot.clock`` is the default clock.
    :param clock: overrides ``robot.clock``; default :class:`LoopClock`.
    :param strict: :meth:`send` raises :class:`EventNotAllowed` for events no
        active state has a transition for (instead of recording them as ignored).
    :param stop_timeout: seconds (clock) motions get to stop when a state is left.

    A subclass that declares no states is abstract (a base for shared methods).
    """

    _spec: ClassVar[_Spec | None] = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls._spec = _build_spec(cls)

    def __init__(
        self,
        robot: Any = None,
        *,
        clock: ClockLike | None = None,
        strict: bool = False,
        stop_timeout: float = DEFAULT_STOP_TIMEOUT,
    ) -> None:
        if self._spec is None:
            raise StateMachineDefinitionError(f"{type(self).__name__} declares no states; it cannot be run")
        if clock is None:
            clock = getattr(robot, "clock", None)
        if clock is None:
            clock = LoopClock()
        self.robot = robot
        self.clock: ClockLike = clock
        self.strict = strict
        self.stop_timeout = stop_timeout
        self.parent: StateMachine | None = None
        self.history: list[HistoryRecord] = []
        self.last_error: BaseException | None = None
        self.last_error_path: str | None = None
        self._sm_path = type(self).__name__
        self._sm_state: str | None = None
        self._sm_children: list[StateMachine] = []
        self._sm_queue: asyncio.Queue[_Item] = asyncio.Queue()
        self._sm_started = False
        self._sm_finished = False
        self._sm_waiters: list[_Waiter] = []

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.state_path}>"

    # ----------------------------------------------------------------- introspection

    @property
    def machine_path(self) -> str:
        """``"Patrol"``, or ``"Patrol/moving/Approach"`` for a nested machine."""
        return self._sm_path

    @property
    def state(self) -> str | None:
        """The current state's name (``None`` before :meth:`run`)."""
        return self._sm_state

    @property
    def state_path(self) -> str:
        """The active configuration, e.g. ``"Patrol/moving/Approach/grasp"``.

        Parallel regions are shown as ``"Patrol/work/[Arm/reach|Gripper/open]"``.
        """
        if self._sm_state is None:
            return self._sm_path
        base = f"{self._sm_path}/{self._sm_state}"
        children = self._sm_children
        if len(children) == 1:
            return children[0].state_path
        if children:
            inner = "|".join(c.state_path[len(base) + 1 :] for c in children)
            return f"{base}/[{inner}]"
        return base

    @property
    def children(self) -> tuple[StateMachine, ...]:
        """The nested machines of the current state (empty for a simple state)."""
        return tuple(self._sm_children)

    @property
    def finished(self) -> bool:
        """True once the machine has reached a final state."""
        return self._sm_finished

    @classmethod
    def states(cls) -> tuple[str, ...]:
        """Every state path of this machine, nested ones included."""
        return tuple(cls._require_spec().states)

    @classmethod
    def events(cls) -> tuple[str, ...]:
        """Every event name used by a transition, in declaration order."""
        spec = cls._require_spec()
        return tuple(dict.fromkeys(e.event for e in spec.edges))

    @classmethod
    def _require_spec(cls) -> _Spec:
        if cls._spec is None:
            raise StateMachineDefinitionError(f"{cls.__name__} declares no states")
        return cls._spec

    # ----------------------------------------------------------------- running

    async def run(self) -> str:
        """Run until a final state is reached; returns its name.

        Raises :class:`StateMachineError` on unhandled errors (after
        ``robot.estop(category=1)``).  Cancelling the call leaves the active
        state (body cancelled, motions stopped and awaited) and propagates.
        A machine instance runs once.
        """
        if self.parent is not None:
            raise StateMachineError(f"{self._sm_path} is nested; run its root machine")
        self._sm_claim()
        try:
            return await self._sm_loop()
        except _Unhandled as u:
            raise StateMachineError(
                f"unhandled {type(u.exc).__name__} in state {u.path}: {u.exc}", path=u.path
            ) from u.exc
        finally:
            self._sm_finish()

    def send(self, event: str) -> None:
        """Queue an external event (synchronous; call from any task on the machine's loop).

        It is offered to the current state first, then to nested machines.  If a
        transition takes it, the running state body is cancelled.
        """
        if not isinstance(event, str) or not event:
            raise TypeError(f"event must be a non-empty str, not {event!r}")
        if self._sm_finished:
            if self.strict:
                raise EventNotAllowed(f"{self._sm_path} has finished; event {event!r} not allowed")
            self._sm_record(self._sm_state, None, event, note="ignored (machine finished)")
            return
        if self.strict and not self._sm_accepts(event):
            raise EventNotAllowed(f"no transition for event {event!r} in {self.state_path}")
        self._sm_queue.put_nowait(_External(event))

    async def wait_state(self, target: str) -> None:
        """Return once the machine is in ``target``.

        ``target`` is a state name of this machine, or a suffix of the path of an
        active state (``"grasp"``, ``"Approach/grasp"``, ``"Patrol/moving"``).  Raises
        :class:`StateMachineError` if the machine finishes without getting there.
        """
        if self._sm_matches(target):
            return
        if self._sm_finished:
            raise StateMachineError(f"{self._sm_path} finished in {self.state_path} without reaching {target!r}")
        root = self._sm_root()
        waiter = _Waiter(self, target, asyncio.get_running_loop().create_future())
        root._sm_waiters.append(waiter)
        try:
            await waiter.future
        finally:
            if waiter in root._sm_waiters:
                root._sm_waiters.remove(waiter)

    # ----------------------------------------------------------------- engine internals

    def _sm_claim(self) -> None:
        if self._sm_started:
            raise StateMachineError(f"{self._sm_path} has already been run; create a new instance")
        self._sm_started = True

    def _sm_finish(self) -> None:
        self._sm_finished = True
        for w in self._sm_waiters:
            if not w.future.done():
                w.future.set_exception(
                    StateMachineError(f"{self._sm_path} finished in {self.state_path} without reaching {w.target!r}")
                )
        self._sm_waiters.clear()

    def _sm_root(self) -> StateMachine:
        m = self
        while m.parent is not None:
            m = m.parent
        return m

    def _sm_active_paths(self) -> list[str]:
        """Paths of every active state, composite and leaf."""
        if self._sm_state is None:
            return []
        paths = [f"{self._sm_path}/{self._sm_state}"]
        for child in self._sm_children:
            paths.extend(child._sm_active_paths())
        return paths

    def _sm_matches(self, target: str) -> bool:
        if self._sm_state is None:
            return False
        if target == self._sm_state:
            return True
        return any(p == target or p.endswith("/" + target) for p in self._sm_active_paths())

    @staticmethod
    def add_transition_listener(fn: TransitionListener) -> HookHandle:
        """Call ``fn(machine, record)`` for every :class:`HistoryRecord` any machine records, in any process task.

        Process-wide, like a logging handler (a recorder attached to a robot filters
        on ``machine.robot``). A listener that raises is logged and never breaks the
        machine. Returns a handle; ``handle.remove()`` unregisters.
        """
        if not callable(fn):
            raise TypeError(f"a transition listener must be callable, got {fn!r}")
        _transition_listeners.append(fn)
        return HookHandle(lambda: _transition_listeners.remove(fn), lambda: fn in _transition_listeners)

    def _sm_record(
        self, source: str | None, target: str | None, event: str | None, *, note: str = "", time: float | None = None
    ) -> None:
        rec = HistoryRecord(
            time=self.clock.now() if time is None else time,
            source=source,
            target=target,
            event=event,
            note=note,
            machine=self._sm_path,
        )
        m: StateMachine | None = self
        while m is not None:
            m.history.append(rec)
            m = m.parent
        for listener in tuple(_transition_listeners):
            try:
                listener(self, rec)
            except Exception:  # an observer must never break a behavior
                _log.exception("transition listener %r failed", listener)

    def _sm_entered(self, name: str) -> None:
        self._sm_state = name
        root = self._sm_root()
        for w in list(root._sm_waiters):
            if not w.future.done() and w.machine._sm_matches(w.target):
                w.future.set_result(None)

    def _sm_accepts(self, event: str) -> bool:
        spec = self._require_spec()
        state = self._sm_state or spec.initial
        if event in spec.by_source.get(state, {}):
            return True
        return any(c._sm_accepts(event) for c in self._sm_children)

    def _sm_handler_above(self) -> bool:
        """Whether an enclosing machine can take an error to its fault state."""
        m = self.parent
        while m is not None:
            fault = m._require_spec().fault
            if fault is not None and m._sm_state != fault:
                return True
            m = m.parent
        return False

    def _sm_make_children(self, state: State) -> list[StateMachine]:
        classes: Sequence[type[StateMachine]]
        if state.machine is not None:
            classes = (state.machine,)
        elif state.parallel is not None:
            classes = state.parallel
        else:
            return []
        children = []
        for cls in classes:
            child = cls(self.robot, clock=self.clock, strict=self.strict, stop_timeout=self.stop_timeout)
            child.parent = self
            child._sm_path = f"{self._sm_path}/{state.name}/{cls.__name__}"
            child._sm_started = True
            children.append(child)
        return children

    async def _sm_loop(self) -> str:
        spec = self._require_spec()
        name, event = spec.initial, None
        self._sm_record(None, name, None, note="initial")
        while True:
            self._sm_entered(name)
            state = spec.states[name]
            if state.final:
                self._sm_finished = True
                return name
            step = await self._sm_run_state(state, event)
            if step.error is not None:
                raise step.error
            assert step.target is not None
            self._sm_record(name, step.target, step.event, time=step.time)
            name, event = step.target, step.event

    async def _sm_run_state(self, state: State, event: str | None) -> _Step:
        assert state.name is not None
        path = f"{self._sm_path}/{state.name}"
        token = object()
        scope = MotionScope(path, clock=self.clock, stop_timeout=self.stop_timeout)
        ctx = StateContext(
            robot=self.robot,
            machine=self,
            state=path,
            clock=self.clock,
            event=event,
            error=self.last_error if state.fault else None,
            scope=scope,
        )
        body = getattr(self, f"on_{state.name}", None)
        self._sm_children = self._sm_make_children(state)
        try:
            async with asyncio.TaskGroup() as tg:
                tasks: list[asyncio.Task[None]] = []
                if body is not None or self._sm_children:
                    tasks.append(tg.create_task(self._sm_body(state, body, ctx, scope, token), name=path))
                if state.timeout is not None:
                    tasks.append(tg.create_task(self._sm_timer(state.timeout, token), name=f"{path} timeout"))
                try:
                    step = await self._sm_dispatch(state, path, token)
                finally:
                    scope.cancel_all()  # decelerate-and-hold requested before anything else
                    for task in tasks:
                        task.cancel()
        except BaseException:
            # cancelled (or a BaseException from a body): stop the motions, then propagate
            self._sm_children = []
            await self._sm_close_scope(scope, path, None)
            raise
        self._sm_children = []
        await self._sm_close_scope(scope, path, step)
        return step

    async def _sm_close_scope(self, scope: MotionScope, path: str, step: _Step | None) -> None:
        try:
            await scope.aclose()
        except MotionStopTimeoutError as exc:
            _log.error("%s: %s; e-stopping", path, exc)
            already = step is not None and step.error is not None and step.error.estopped
            if not already:
                await self._sm_estop(exc)
            if step is None:
                return  # an exception (e.g. CancelledError) is propagating: keep it
            if step.error is not None:
                step.error.exc.add_note(f"while leaving {path}: {exc}")
                step.error.estopped = step.error.fatal = True
                return
            self._sm_record(path.rsplit("/", 1)[-1], None, None, note=f"motions did not stop: {exc}")
            raise _Unhandled(exc, path, estopped=True, fatal=True) from exc

    async def _sm_body(
        self,
        state: State,
        body: Callable[[StateContext], Awaitable[object]] | None,
        ctx: StateContext,
        scope: MotionScope,
        token: object,
    ) -> None:
        scope.activate()  # this task's context is private
        put = self._sm_queue.put_nowait
        try:
            if body is not None:
                result = await body(ctx)
            else:
                result = await self._sm_run_children(state)
            if result is not None and not isinstance(result, str):
                raise TypeError(f"state body on_{state.name} returned {result!r}; expected an event name or None")
        except asyncio.CancelledError:
            task = asyncio.current_task()
            if task is not None and not task.cancelling():
                put(_Failure(token, StateMachineError(f"{ctx.state}: body raised CancelledError"), ctx.state))
            raise
        except _Unhandled as u:
            put(_Failure(token, u.exc, u.path, estopped=u.estopped, fatal=u.fatal))
        except Exception as exc:
            put(_Failure(token, exc, ctx.state))
        else:
            put(_Completion(token, result))

    async def _sm_run_children(self, state: State) -> str:
        children = list(self._sm_children)
        if state.machine is not None:
            final = await children[0]._sm_loop()
            return state.completion_event(final)
        try:
            async with asyncio.TaskGroup() as tg:
                for child in children:
                    tg.create_task(child._sm_loop(), name=child.machine_path)
        except BaseExceptionGroup as eg:
            leaf: BaseException = eg
            while isinstance(leaf, BaseExceptionGroup):
                leaf = leaf.exceptions[0]
            raise leaf from None
        return state.completion_event()

    async def _sm_timer(self, delay: float, token: object) -> None:
        await self.clock.sleep(delay)
        self._sm_queue.put_nowait(_TimerFired(token))

    async def _sm_dispatch(self, state: State, path: str, token: object) -> _Step:
        assert state.name is not None
        spec = self._require_spec()
        while True:
            item = await self._sm_queue.get()
            if isinstance(item, _External):
                event = item.event
            elif item.token is not token:
                continue  # left over from a previous visit of a state
            elif isinstance(item, _Failure):
                return await self._sm_fail(state, item)
            elif isinstance(item, _TimerFired):
                event = "timeout"
            else:
                if item.event is None:
                    continue  # body finished: wait here for an event or the timeout
                event = item.event
                if event not in spec.events:
                    err = StateMachineError(f"state body of {path} returned unknown event {event!r}")
                    return await self._sm_fail(state, _Failure(token, err, path))
            now = self.clock.now()
            try:
                edge, blocked = await self._sm_select(state.name, event)
            except Exception as exc:
                return await self._sm_fail(state, _Failure(token, exc, path))
            if edge is not None:
                return _Step(edge.target, event, now)
            if blocked:
                self._sm_record(state.name, None, event, note="blocked by guard", time=now)
            if isinstance(item, _External) and self._sm_children:
                for child in self._sm_children:
                    child._sm_queue.put_nowait(item)
            elif not blocked:
                self._sm_record(state.name, None, event, note="ignored", time=now)

    async def _sm_select(self, state: str, event: str) -> tuple[_Edge | None, bool]:
        blocked = False
        for edge in self._require_spec().by_source.get(state, {}).get(event, ()):
            if edge.guard is None or await self._sm_check(edge.guard):
                return edge, False
            blocked = True
        return None, blocked

    async def _sm_check(self, guard: Guard) -> bool:
        result = getattr(self, guard)() if isinstance(guard, str) else guard(self)
        if inspect.isawaitable(result):
            result = await result
        return bool(result)

    async def _sm_fail(self, state: State, failure: _Failure) -> _Step:
        assert state.name is not None
        spec = self._require_spec()
        self.last_error = failure.exc
        self.last_error_path = failure.path
        now = self.clock.now()
        if not failure.fatal and spec.fault is not None and state.name != spec.fault:
            _log.warning("%s: %s: %s -> %s", failure.path, type(failure.exc).__name__, failure.exc, spec.fault)
            return _Step(spec.fault, "error", now)
        estopped = failure.estopped
        if not estopped and not self._sm_handler_above():
            await self._sm_estop(failure.exc)
            estopped = True
        self._sm_record(state.name, None, "error", note=f"unhandled {type(failure.exc).__name__}", time=now)
        return _Step(None, None, now, _Unhandled(failure.exc, failure.path, estopped=estopped, fatal=failure.fatal))

    async def _sm_estop(self, cause: BaseException) -> None:
        estop = getattr(self.robot, "estop", None)
        if estop is None:
            return
        try:
            result = estop(category=1)
            if inspect.isawaitable(result):
                await result
        except Exception as exc:
            _log.exception("%s: robot.estop(category=1) failed", self._sm_path)
            cause.add_note(f"robot.estop(category=1) failed: {type(exc).__name__}: {exc}")

    # ----------------------------------------------------------------- Mermaid

    @classmethod
    def mermaid(cls) -> str:
        """A Mermaid ``stateDiagram-v2`` of the machine (nested machines as composite states)."""
        lines = ["stateDiagram-v2"]
        cls._mermaid_into(lines, "    ", "")
        return "\n".join(lines) + "\n"

    @classmethod
    def _mermaid_into(cls, lines: list[str], indent: str, prefix: str) -> None:
        spec = cls._require_spec()

        def sid(name: str) -> str:
            return f"{prefix}{name}"

        for name, st in spec.states.items():
            notes = []
            if st.timeout is not None:
                notes.append(f"timeout {st.timeout:g}s")
            if st.fault:
                notes.append("fault handler")
            if prefix:
                lines.append(f'{indent}state "{name}" as {sid(name)}')
            if st.machine is not None or st.parallel is not None:
                regions = (st.machine,) if st.machine is not None else st.parallel or ()
                lines.append(f"{indent}state {sid(name)} {{")
                seen: dict[str, int] = {}
                for i, region in enumerate(regions):
                    if i:
                        lines.append(f"{indent}    --")
                    lines.append(f"{indent}    %% {region.__name__}")
                    n = seen[region.__name__] = seen.get(region.__name__, 0) + 1
                    tag = region.__name__ if n == 1 else f"{region.__name__}{n}"
                    inner = f"{sid(name)}__" if st.machine is not None else f"{sid(name)}__{tag}__"
                    region._mermaid_into(lines, indent + "    ", inner)
                lines.append(f"{indent}}}")
            elif not prefix and not notes:
                lines.append(f"{indent}{name}")
            for note in notes:
                lines.append(f"{indent}{sid(name)} : {note}")
        lines.append(f"{indent}[*] --> {sid(spec.initial)}")
        for e in spec.edges:
            label = e.event if e.guard is None else f"{e.event} [{e.guard_label}]"
            lines.append(f"{indent}{sid(e.source)} --> {sid(e.target)} : {label}")
        for name, st in spec.states.items():
            if st.final:
                lines.append(f"{indent}{sid(name)} --> [*]")


# --------------------------------------------------------------------------- validation


def _build_spec(cls: type[StateMachine]) -> _Spec | None:
    """Collect and validate the declaration of ``cls``; ``None`` if it declares no states."""
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
        if name in _RESERVED:
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
            if not (isinstance(sub, type) and issubclass(sub, StateMachine)) or sub._spec is None:
                raise fail(f"state {name!r}: {sub!r} is not a StateMachine subclass with states")
        if isinstance(st.done, Mapping):
            if st.machine is None:
                raise fail(f"state {name!r}: a done= mapping needs machine=")
            sub_spec = st.machine._require_spec()
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
    edges: list[_Edge] = []
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
            edges.append(_Edge(source, target, event, guard))
    by_source: dict[str, dict[str, list[_Edge]]] = {n: {} for n in states}
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
        for completion in _completion_events(st):
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

    return _Spec(
        states=MappingProxyType(dict(states)),
        initial=initial[0],
        fault=faults[0] if faults else None,
        edges=tuple(edges),
        by_source=MappingProxyType(
            {n: MappingProxyType({ev: tuple(es) for ev, es in d.items()}) for n, d in by_source.items()}
        ),
        events=frozenset(e.event for e in edges),
    )


_RESERVED = frozenset(n for n in dir(StateMachine) if not n.startswith("__")) | {
    "robot",
    "clock",
    "strict",
    "stop_timeout",
    "parent",
    "history",
    "last_error",
    "last_error_path",
}


def _completion_events(st: State) -> list[str]:
    """The events a nested/parallel state can fire when its machine(s) finish."""
    if st.machine is not None:
        finals = [n for n, s in st.machine._require_spec().states.items() if s.final]
        return list(dict.fromkeys(st.completion_event(f) for f in finals))
    if st.parallel is not None:
        if all(any(s.final for s in r._require_spec().states.values()) for r in st.parallel):
            return [st.completion_event()]
    return []


# --------------------------------------------------------------------------- discovery


def find_machines(module: ModuleType | str | os.PathLike[str]) -> list[type[StateMachine]]:
    """The machine classes defined in ``module``, in definition order.

    ``module`` is a module object, a dotted module name, or a path to a ``.py``
    file (imported under a private name).  Abstract machines (no states) and
    machines merely imported into the module are left out.
    """
    if isinstance(module, os.PathLike) or (isinstance(module, str) and module.endswith(".py")):
        path = Path(module)
        mod_name = f"_agentsdk_machines_{path.stem}"
        spec = importlib.util.spec_from_file_location(mod_name, path)
        if spec is None or spec.loader is None:
            raise ConfigurationError(f"cannot import {path}")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[mod_name] = mod
        try:
            spec.loader.exec_module(mod)
        except BaseException:
            del sys.modules[mod_name]
            raise
    elif isinstance(module, str):
        mod = importlib.import_module(module)
    else:
        mod = module
    found = (
        obj
        for obj in vars(mod).values()
        if isinstance(obj, type)
        and issubclass(obj, StateMachine)
        and obj._spec is not None
        and obj.__module__ == mod.__name__
    )
    return list(dict.fromkeys(found))
