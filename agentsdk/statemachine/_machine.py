"""The engine: one task per state body, one event queue per machine."""

from __future__ import annotations

import asyncio
import functools
import inspect
import logging
from collections.abc import AsyncIterator, Awaitable, Callable, Iterable, Mapping, MutableMapping, Sequence
from types import MappingProxyType
from typing import Any, ClassVar, Literal

from ..loop import HookHandle
from ..scope import DEFAULT_STOP_TIMEOUT, ClockLike, LoopClock, MotionScope, MotionStopTimeoutError
from ._declaration import Action, Edge, Guard, Spec, State
from ._errors import EventNotAllowed, RobotStoppedError, StateMachineDefinitionError, StateMachineError
from ._mermaid import render_mermaid
from ._rest import ignored_abort, safety_cursor, stop_since, wait_rest, watch_safety
from ._runtime import (
    EMPTY,
    Completion,
    External,
    Failure,
    HistoryRecord,
    Item,
    Poke,
    StateContext,
    Step,
    TimerFired,
    Unhandled,
    UserData,
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

    ``event_priority`` (class attribute): ``"outer"`` (default) offers an external
    event to this machine's state first, so an enclosing ``stop`` always wins over a
    nested machine; ``"inner"`` offers it to the active nested machine(s) first and
    this machine takes it only if none of them has an enabled transition for it
    (SCXML's document order, transitions' nested-first).
    """

    _spec: ClassVar[Spec | None] = None
    event_priority: ClassVar[Literal["outer", "inner"]] = "outer"

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
        #: SMACH-style userdata; a nested machine's remapped keys live in its parent's
        self.userdata: MutableMapping[str, Any] = UserData()
        #: the data of the final state reached (``State(final=True, data=...)``)
        self.done_data: Mapping[str, Any] = EMPTY
        self._sm_token: object | None = None
        self._sm_baseline = 0  # safety event count when the current state was entered
        self._sm_entered_at = 0.0
        self._sm_left_in: str | None = None  # where the last run of this machine was left (history)
        self._sm_kept: dict[str, list[StateMachine]] = {}  # composite state -> its last nested machines
        self._sm_start: str | None = None  # history: the state a nested machine resumes in
        self._sm_deep = False
        self._sm_subscribers: list[asyncio.Queue[HistoryRecord | None]] = []
        self._sm_preempt = asyncio.Event()

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
    def configuration(self) -> tuple[str, ...]:
        """Every active state's full path, outermost first (SCXML's active configuration)."""
        return tuple(self._sm_active_paths())

    def visited(self) -> tuple[str, ...]:
        """The full paths of every state entered so far, in first-entry order (nested ones included)."""
        return tuple(dict.fromkeys(f"{r.machine}/{r.target}" for r in self.history if r.target is not None))

    async def transitions(self) -> AsyncIterator[HistoryRecord]:
        """Every :class:`HistoryRecord` of this machine (and its nested ones) from now on, as it happens.

        ``async for rec in machine.transitions(): ...`` ends when the root machine
        finishes.  Each transition's record carries ``duration`` (time spent in the
        state left) and ``configuration`` (the active configuration after it).
        """
        root = self._sm_root()
        if root._sm_finished:
            return
        queue: asyncio.Queue[HistoryRecord | None] = asyncio.Queue()
        root._sm_subscribers.append(queue)
        try:
            while (rec := await queue.get()) is not None:
                if rec.machine == self._sm_path or rec.machine.startswith(self._sm_path + "/"):
                    yield rec
        finally:
            root._sm_subscribers.remove(queue)

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
        watch = self._sm_watch_safety()
        try:
            return await self._sm_loop()
        except Unhandled as u:
            raise StateMachineError(
                f"unhandled {type(u.exc).__name__} in state {u.path}: {u.exc}", path=u.path
            ) from u.exc
        finally:
            for handle in watch:
                handle.remove()
            self._sm_finish()

    def send(self, event: str, data: Mapping[str, Any] | None = None) -> None:
        """Queue an external event (synchronous; call from any task on the machine's loop).

        It is offered to the current state first, then to nested machines (the
        other way round with ``event_priority = "inner"``).  If a transition takes
        it, the running state body is cancelled (after its ``preempt_timeout``
        grace).  ``data`` reaches the entered state as ``ctx.data``.
        """
        if not isinstance(event, str) or not event:
            raise TypeError(f"event must be a non-empty str, not {event!r}")
        if data is not None and not isinstance(data, Mapping):
            raise TypeError(f"event data must be a mapping, not {data!r}")
        if self._sm_finished:
            if self.strict:
                raise EventNotAllowed(f"{self._sm_path} has finished; event {event!r} not allowed")
            self._sm_record(self._sm_state, None, event, note="ignored (machine finished)")
            return
        if self.strict and not self._sm_accepts(event):
            raise EventNotAllowed(f"no transition for event {event!r} in {self.state_path}")
        self._sm_queue.put_nowait(External(event, MappingProxyType(dict(data)) if data else EMPTY))

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
        for queue in self._sm_subscribers:
            queue.put_nowait(None)
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
        self,
        source: str | None,
        target: str | None,
        event: str | None,
        *,
        note: str = "",
        time: float | None = None,
        duration: float | None = None,
    ) -> None:
        root = self._sm_root()
        rec = HistoryRecord(
            time=self.clock.now() if time is None else time,
            source=source,
            target=target,
            event=event,
            note=note,
            machine=self._sm_path,
            duration=duration,
            configuration=root.state_path,
        )
        m: StateMachine | None = self
        while m is not None:
            m.history.append(rec)
            m = m.parent
        for queue in root._sm_subscribers:
            queue.put_nowait(rec)
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

    def _sm_make_children(self, state: State, resume_deep: bool) -> list[StateMachine]:
        classes: Sequence[type[StateMachine]]
        if state.machine is not None:
            classes = (state.machine,)
        elif state.parallel is not None:
            classes = state.parallel
        else:
            return []
        assert state.name is not None
        kept = self._sm_kept.get(state.name)
        deep = state.history == "deep" or resume_deep
        if kept is not None and (state.history is not None or resume_deep):
            children = kept  # history: the same instances resume where they were left
            for child in children:
                child._sm_start = child._sm_left_in
                child._sm_deep = deep and child._sm_left_in is not None
                child._sm_queue = asyncio.Queue()
                child._sm_finished = False
                child._sm_state = None
        else:
            children = []
            for cls in classes:
                child = cls(self.robot, clock=self.clock, strict=self.strict, stop_timeout=self.stop_timeout)
                child.parent = self
                child._sm_path = f"{self._sm_path}/{state.name}/{cls.__name__}"
                child._sm_started = True
                child.userdata = UserData(self.userdata, state.remap) if state.remap else UserData()
                children.append(child)
            self._sm_kept[state.name] = children
        if state.args is not None:
            args = state.args(self) if callable(state.args) else state.args
            for child in children:
                child.userdata.update(args)
        return children

    async def _sm_loop(self, start: str | None = None, deep: bool = False) -> str:
        spec = self._require_spec()
        name, event, data = start or spec.initial, None, EMPTY
        resume_deep = deep and start is not None
        self._sm_left_in = None
        self.done_data = EMPTY
        self._sm_entered(name)
        self._sm_record(None, name, None, note="initial" if start is None else "history")
        while True:
            state = spec.states[name]
            if state.final:
                step = await self._sm_reach_final(state, event, data)
                if step is None:
                    self._sm_finished = True
                    return name
            else:
                try:
                    step = await self._sm_run_state(state, event, data, resume_deep)
                except BaseException:
                    self._sm_left_in = name
                    raise
                resume_deep = False
                if step.error is None and step.edge is not None and step.edge.action is not None:
                    step = await self._sm_transition_action(state, step)
            if step.error is not None:
                self._sm_left_in = name
                raise step.error
            assert step.target is not None
            left_at = self._sm_entered_at
            self._sm_entered(step.target)
            self._sm_record(name, step.target, step.event, time=step.time, duration=step.time - left_at)
            name, event, data = step.target, step.event, step.data

    async def _sm_reach_final(self, state: State, event: str | None, data: Mapping[str, Any]) -> Step | None:
        """Enter a final state: entry/exit actions, done data. A Step (to the fault path) if they fail."""
        assert state.name is not None
        path = f"{self._sm_path}/{state.name}"
        self._sm_entered_at = self.clock.now()
        ctx = StateContext(robot=self.robot, machine=self, state=path, clock=self.clock, event=event, data=data)
        try:
            await self._sm_call_action("enter", state, ctx)
            if self.parent is None:  # the machine ends here: its final state exits (SCXML §3.13 exitInterpreter)
                await self._sm_call_action("exit", state, ctx)
            if state.data is not None:
                if callable(state.data):
                    values = state.data(self)
                else:
                    missing = [k for k in state.data if k not in self.userdata]
                    if missing:
                        raise StateMachineError(f"{path}: done data key(s) {missing} not in userdata", path=path)
                    values = {k: self.userdata[k] for k in state.data}
                self.done_data = MappingProxyType(dict(values))
        except Exception as exc:
            return await self._sm_fail(state, Failure(None, exc, path))
        return None

    async def _sm_transition_action(self, state: State, step: Step) -> Step:
        assert step.edge is not None and step.edge.action is not None
        try:
            await _maybe_await(self._sm_resolve_action(step.edge.action)(self, step.event, step.data))
        except Exception as exc:
            return await self._sm_fail(state, Failure(None, exc, f"{self._sm_path}/{state.name}"))
        return step

    def _sm_resolve_action(self, action: Action) -> Callable[..., Any]:
        if isinstance(action, str):
            method = getattr(type(self), action)
            return lambda machine, event, data: method(machine, event, data)
        return action

    async def _sm_call_action(self, kind: str, state: State, ctx: StateContext) -> None:
        """Run ``on_enter_<state>`` / ``on_exit_<state>`` (sync or async) if declared."""
        fn = getattr(self, f"on_{kind}_{state.name}", None)
        if fn is not None and f"{kind}_{state.name}" not in self._require_spec().states:
            await _maybe_await(fn(ctx))

    def _sm_watch_safety(self) -> list[HookHandle]:
        """Wake the active states whenever the robot's safety layer records something (an e-stop, a fault)."""
        return watch_safety(self.robot, self._sm_poke)

    def _sm_request_preempt(self) -> None:
        """SMACH ``request_preempt``: the active state and its nested machines' active states."""
        self._sm_preempt.set()
        for child in self._sm_children:
            child._sm_request_preempt()

    def _sm_poke(self) -> None:
        self._sm_queue.put_nowait(Poke())
        for child in self._sm_children:
            child._sm_poke()

    def _sm_stopped(self, path: str) -> RobotStoppedError | None:
        """The e-stop / safety fault recorded since the current state was entered, if any."""
        return stop_since(self.robot, self._sm_baseline, path)

    async def _sm_run_state(self, state: State, event: str | None, data: Mapping[str, Any], resume_deep: bool) -> Step:
        assert state.name is not None
        path = f"{self._sm_path}/{state.name}"
        token = object()
        self._sm_token = token
        self._sm_baseline = safety_cursor(self.robot)
        self._sm_entered_at = self.clock.now()
        scope = MotionScope(path, clock=self.clock, stop_timeout=self.stop_timeout)
        preempt = self._sm_preempt = asyncio.Event()
        ctx = StateContext(
            robot=self.robot,
            machine=self,
            state=path,
            clock=self.clock,
            event=event,
            error=self.last_error if state.fault else None,
            scope=scope,
            data=data,
            preempt=preempt,
        )
        body = getattr(self, f"on_{state.name}", None)
        has_enter = (
            getattr(self, f"on_enter_{state.name}", None) is not None
            and f"enter_{state.name}" not in self._require_spec().states
        )
        self._sm_children = self._sm_make_children(state, resume_deep)
        try:
            async with asyncio.TaskGroup() as tg:
                tasks: list[asyncio.Task[None]] = []
                body_task: asyncio.Task[None] | None = None
                entered = asyncio.Event()
                if body is not None or self._sm_children or has_enter:
                    body_task = tg.create_task(self._sm_body(state, body, ctx, scope, token, entered), name=path)
                    tasks.append(body_task)
                if state.timeout is not None:
                    tasks.append(tg.create_task(self._sm_timer(state.timeout, token), name=f"{path} timeout"))
                try:
                    if has_enter:
                        await entered.wait()  # no event is handled before the entry action has run
                    step = await self._sm_dispatch(state, path, token, scope)
                    if step.preemptive and state.preempt_timeout is not None and body_task is not None:
                        await self._sm_grace(state, body_task, step)
                finally:
                    scope.cancel_all()  # decelerate-and-hold requested before anything else
                    for task in tasks:
                        task.cancel()
        except BaseException:
            # cancelled (or a BaseException from a body): stop the motions, then propagate
            children, self._sm_children = self._sm_children, []
            await self._sm_close_scope(scope, path, None)
            await wait_rest(self.robot)
            try:
                await self._sm_exit_finished_children(children)
                await self._sm_call_action("exit", state, ctx)
            except Exception:
                _log.exception("%s: exit action failed while the state was cancelled", path)
            raise
        children, self._sm_children = self._sm_children, []
        await self._sm_close_scope(scope, path, step)
        await wait_rest(self.robot)  # a state is left at rest, whatever ends it
        try:
            await self._sm_exit_finished_children(children)
            await self._sm_call_action("exit", state, ctx)
        except Exception as exc:
            if step.error is not None:
                step.error.exc.add_note(f"while leaving {path}, on_exit_{state.name} raised {exc!r}")
            else:
                step = await self._sm_fail(state, Failure(token, exc, path))
        return step

    async def _sm_exit_finished_children(self, children: list[StateMachine]) -> None:
        """Exit actions of nested machines' final states: they stay active until their parent exits."""
        for child in children:
            final = child._sm_state
            if child._sm_finished and final is not None:
                ctx = StateContext(robot=self.robot, machine=child, state=f"{child._sm_path}/{final}", clock=self.clock)
                await child._sm_call_action("exit", child._require_spec().states[final], ctx)

    async def _sm_grace(self, state: State, body: asyncio.Task[None], step: Step) -> None:
        """Graceful preemption: the body (or the nested machines' active states) see
        ``ctx.preempt_requested()`` and get ``preempt_timeout`` to end by themselves.
        """
        assert state.preempt_timeout is not None
        if body.done():
            return
        self._sm_request_preempt()
        timer = asyncio.ensure_future(self.clock.sleep(state.preempt_timeout))
        try:
            await asyncio.wait((body, timer), return_when=asyncio.FIRST_COMPLETED)
        finally:
            timer.cancel()
            await asyncio.gather(timer, return_exceptions=True)
        if not body.done():
            self._sm_record(
                state.name, None, step.event, note=f"preempted: body cancelled after {state.preempt_timeout:g} s"
            )

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
        entered: asyncio.Event,
    ) -> None:
        scope.activate()  # this task's context is private
        put = self._sm_queue.put_nowait
        data: Mapping[str, Any] = EMPTY
        try:
            try:
                await self._sm_call_action("enter", state, ctx)  # in the state's scope, before its body
            finally:
                entered.set()
            result: object = None
            if body is not None:
                result = await body(ctx)
            elif self._sm_children:
                result, data = await self._sm_run_children(state)
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
            put(Completion(token, result, data))

    async def _sm_run_children(self, state: State) -> tuple[str, Mapping[str, Any]]:
        children = list(self._sm_children)
        if state.machine is not None:
            child = children[0]
            final = await child._sm_loop(child._sm_start, child._sm_deep)
            return state.completion_event(final), child.done_data
        assert state.name is not None
        names = self._require_spec().regions[state.name]
        results: dict[str, str | None] = dict.fromkeys(names)
        try:
            async with asyncio.TaskGroup() as tg:
                tasks = {
                    tg.create_task(child._sm_loop(child._sm_start, child._sm_deep), name=child.machine_path): key
                    for key, child in zip(names, children, strict=True)
                }
                pending = set(tasks)
                while pending:
                    done, pending = await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
                    for task in done:
                        if not task.cancelled() and task.exception() is None:
                            results[tasks[task]] = task.result()
                    if pending and self._sm_parallel_ends(state, results):
                        for task in pending:
                            task.cancel()  # the remaining regions are preempted (their states exit at rest)
                        preempted = ", ".join(sorted(tasks[t] for t in pending))
                        self._sm_record(state.name, None, None, note=f"regions preempted: {preempted}")
                        break
        except BaseExceptionGroup as eg:
            raise merge_region_failures(eg, f"{self._sm_path}/{state.name}") from None
        outcome = state.completion_event()
        for event, conditions in (state.outcome_map or {}).items():
            if all(results.get(region) == final for region, final in conditions.items()):
                outcome = event
                break
        return outcome, MappingProxyType(results)

    @staticmethod
    def _sm_parallel_ends(state: State, results: Mapping[str, str | None]) -> bool:
        """Whether a parallel state ends before all its regions are final (``finish=``)."""
        if state.finish == "first":
            return True
        if callable(state.finish):
            return bool(state.finish(MappingProxyType(dict(results))))
        return False

    async def _sm_timer(self, delay: float, token: object) -> None:
        await self.clock.sleep(delay)
        self._sm_queue.put_nowait(TimerFired(token))

    async def _sm_dispatch(self, state: State, path: str, token: object, scope: MotionScope) -> Step:
        assert state.name is not None
        # a composite state's nested machines answer for their own states; the fault state is where
        # stops are handled (its body may e-stop or reset the robot itself), so it is not left for one
        leaf = not self._sm_children and not state.fault
        while True:
            item = await self._sm_queue.get()
            data: Mapping[str, Any] = EMPTY
            if isinstance(item, Poke):
                stop = self._sm_stopped(path) if leaf else None
                if stop is None:
                    continue
                return await self._sm_fail(state, Failure(token, stop, path, estopped=True))
            if isinstance(item, External):
                event, data = item.event, item.data
            elif item.token is not token:
                continue  # left over from a previous visit of a state
            elif isinstance(item, Failure):
                return await self._sm_fail(state, item)
            elif isinstance(item, TimerFired):
                event = "timeout"
            else:
                if item.event is None:
                    continue  # body finished: wait here for an event or the timeout
                event, data = item.event, item.data
            stop = self._sm_stopped(path) if leaf else None
            if stop is not None:  # stopped meanwhile: never the transition the body or an event asked for
                return await self._sm_fail(state, Failure(token, stop, path, estopped=True))
            if isinstance(item, Completion):
                error = self._sm_check_outcome(state, path, event, scope if leaf else None)
                if error is not None:
                    return await self._sm_fail(state, Failure(token, error, path))
            now = self.clock.now()
            try:
                if isinstance(item, External) and self.event_priority == "inner" and self._sm_children:
                    if any([await c._sm_takes(event) for c in self._sm_children]):
                        for child in self._sm_children:
                            child._sm_queue.put_nowait(item)
                        continue
                edge, blocked = await self._sm_select(state.name, event)
                if edge is not None and edge.internal:
                    if edge.action is not None:
                        await _maybe_await(self._sm_resolve_action(edge.action)(self, event, data))
                    self._sm_record(state.name, state.name, event, note="internal", time=now)
                    continue
            except Exception as exc:
                return await self._sm_fail(state, Failure(token, exc, path))
            if edge is not None:
                return Step(edge.target, event, now, data=data, edge=edge, preemptive=not isinstance(item, Completion))
            if blocked:
                self._sm_record(state.name, None, event, note="blocked by guard", time=now)
            if isinstance(item, External) and self._sm_children:
                for child in self._sm_children:
                    child._sm_queue.put_nowait(item)
            elif not blocked:
                self._sm_record(state.name, None, event, note="ignored", time=now)

    def _sm_check_outcome(self, state: State, path: str, event: str, scope: MotionScope | None) -> Exception | None:
        """What is wrong with a body's returned event: unknown, undeclared, or a motion it ignored was aborted."""
        spec = self._require_spec()
        if event not in spec.events:
            return StateMachineError(f"state body of {path} returned unknown event {event!r}")
        declared = spec.outcomes.get(state.name or "")
        if declared and event not in declared:
            return StateMachineError(
                f"state body of {path} returned {event!r}, not one of its declared outcomes {sorted(declared)}"
            )
        if scope is not None:
            aborted = ignored_abort(scope)
            if aborted is not None:
                message = f"{path}: body returned {event!r} but its motion was aborted ({aborted})"
                return RobotStoppedError(message, reason="aborted", path=path)
        return None

    async def _sm_takes(self, event: str) -> bool:
        """Whether the active configuration below and at this machine has an enabled transition for ``event``."""
        for child in self._sm_children:
            if await child._sm_takes(event):
                return True
        if self._sm_state is None or self._sm_finished:
            return False
        edge, _ = await self._sm_select(self._sm_state, event)
        return edge is not None

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
    def mermaid(cls, visited: Iterable[str] | None = None) -> str:
        """A Mermaid ``stateDiagram-v2`` of the machine (nested machines as composite states).

        ``visited``: full state paths (``"Patrol/moving"``, ``"Patrol/picking/Approach/grasp"``,
        e.g. :meth:`visited` of a run, or ``machine/target`` of a recording's transitions)
        are highlighted with the ``visited`` class; paths of other machines are ignored.
        """
        return render_mermaid(cls, visited)

    def mermaid_run(self) -> str:
        """The diagram of this machine with every state this run has entered highlighted."""
        return render_mermaid(type(self), self.visited())


async def _maybe_await(result: object) -> None:
    if inspect.isawaitable(result):
        await result


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
        "userdata",
        "done_data",
    }

