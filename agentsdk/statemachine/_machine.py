"""The engine: one task per state body, one event queue per machine."""

from __future__ import annotations

import asyncio
import functools
import inspect
import logging
from collections.abc import Awaitable, Callable, Sequence
from typing import Any, ClassVar

from ..loop import HookHandle
from ..scope import DEFAULT_STOP_TIMEOUT, ClockLike, LoopClock, MotionScope, MotionStopTimeoutError
from ._declaration import Edge, Guard, Spec, State
from ._errors import EventNotAllowed, StateMachineDefinitionError, StateMachineError
from ._runtime import (
    Completion,
    External,
    Failure,
    HistoryRecord,
    Item,
    StateContext,
    Step,
    TimerFired,
    Unhandled,
    Waiter,
    merge_region_failures,
)
from ._validation import build_spec

_log = logging.getLogger("agentsdk.statemachine")

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

    _spec: ClassVar[Spec | None] = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls._spec = build_spec(cls, _reserved())

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
        self._sm_queue: asyncio.Queue[Item] = asyncio.Queue()
        self._sm_started = False
        self._sm_finished = False
        self._sm_waiters: list[Waiter] = []

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
    def is_abstract(cls) -> bool:
        """True for a machine class that declares no states (a base for shared methods)."""
        return cls._spec is None

    @classmethod
    def definition(cls) -> Spec:
        """The validated declaration (states, transitions by source and event, the fault state)."""
        return cls._require_spec()

    @classmethod
    def _require_spec(cls) -> Spec:
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
        except Unhandled as u:
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
        self._sm_queue.put_nowait(External(event))

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
        waiter = Waiter(self, target, asyncio.get_running_loop().create_future())
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

    async def _sm_run_state(self, state: State, event: str | None) -> Step:
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

    async def _sm_close_scope(self, scope: MotionScope, path: str, step: Step | None) -> None:
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
            raise Unhandled(exc, path, estopped=True, fatal=True) from exc

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
                put(Failure(token, StateMachineError(f"{ctx.state}: body raised CancelledError"), ctx.state))
            raise
        except Unhandled as u:
            put(Failure(token, u.exc, u.path, estopped=u.estopped, fatal=u.fatal))
        except Exception as exc:
            put(Failure(token, exc, ctx.state))
        else:
            put(Completion(token, result))

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
            raise merge_region_failures(eg, f"{self._sm_path}/{state.name}") from None
        return state.completion_event()

    async def _sm_timer(self, delay: float, token: object) -> None:
        await self.clock.sleep(delay)
        self._sm_queue.put_nowait(TimerFired(token))

    async def _sm_dispatch(self, state: State, path: str, token: object) -> Step:
        assert state.name is not None
        spec = self._require_spec()
        while True:
            item = await self._sm_queue.get()
            if isinstance(item, External):
                event = item.event
            elif item.token is not token:
                continue  # left over from a previous visit of a state
            elif isinstance(item, Failure):
                return await self._sm_fail(state, item)
            elif isinstance(item, TimerFired):
                event = "timeout"
            else:
                if item.event is None:
                    continue  # body finished: wait here for an event or the timeout
                event = item.event
                if event not in spec.events:
                    err = StateMachineError(f"state body of {path} returned unknown event {event!r}")
                    return await self._sm_fail(state, Failure(token, err, path))
            now = self.clock.now()
            try:
                edge, blocked = await self._sm_select(state.name, event)
            except Exception as exc:
                return await self._sm_fail(state, Failure(token, exc, path))
            if edge is not None:
                return Step(edge.target, event, now)
            if blocked:
                self._sm_record(state.name, None, event, note="blocked by guard", time=now)
            if isinstance(item, External) and self._sm_children:
                for child in self._sm_children:
                    child._sm_queue.put_nowait(item)
            elif not blocked:
                self._sm_record(state.name, None, event, note="ignored", time=now)

    async def _sm_select(self, state: str, event: str) -> tuple[Edge | None, bool]:
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

    async def _sm_fail(self, state: State, failure: Failure) -> Step:
        assert state.name is not None
        spec = self._require_spec()
        self.last_error = failure.exc
        self.last_error_path = failure.path
        now = self.clock.now()
        if not failure.fatal and spec.fault is not None and state.name != spec.fault:
            _log.warning("%s: %s: %s -> %s", failure.path, type(failure.exc).__name__, failure.exc, spec.fault)
            return Step(spec.fault, "error", now)
        estopped = failure.estopped
        if not estopped and not self._sm_handler_above():
            await self._sm_estop(failure.exc)
            estopped = True
        self._sm_record(state.name, None, "error", note=f"unhandled {type(failure.exc).__name__}", time=now)
        return Step(None, None, now, Unhandled(failure.exc, failure.path, estopped=estopped, fatal=failure.fatal))

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


@functools.cache
def _reserved() -> frozenset[str]:
    """Names a state or event may not take: they would shadow the machine's own attributes."""
    return frozenset(n for n in dir(StateMachine) if not n.startswith("__")) | {
        "robot",
        "clock",
        "strict",
        "stop_timeout",
        "parent",
        "history",
        "last_error",
        "last_error_path",
    }

