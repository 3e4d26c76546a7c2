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
* **A state is left at rest, whatever ends it.**  An e-stop or a safety fault
  while a state runs (the robot's safety layer records it) leaves that state
  through the fault path (:class:`RobotStoppedError`: the fault state, or out of
  ``run()``), never by the transition its body or an event asked for; a body that
  returns an event although a motion it started was ``ABORTED`` (and no later one
  succeeded) goes the same way.  Every exit waits for a safety stop in progress
  to reach rest before the next state's entry action or body starts.  The fault
  state itself is not left for a stop (its body may e-stop, reset and enable).
* Entry/exit actions ``on_enter_<state>(self, ctx)`` / ``on_exit_<state>(self, ctx)``
  (sync or async) on any state, nested, parallel and final ones included; entry
  runs in the state's motion scope before the body, exit after the state's
  motions have stopped (innermost first).
* ``State(history="shallow"|"deep")``, internal transitions
  (``s.internal(action)``), transition actions (``a.to(b, action=...)``), parallel
  outcome maps and ``finish=`` (SMACH ``Concurrence``), userdata with ``remap=`` and
  ``args=``, done data (``State(final=True, data=...)``), declared outcomes
  (``outcomes=`` or a ``Literal`` return annotation, checked at class definition),
  graceful preemption (``preempt_timeout=``, ``ctx.preempt_requested()``) and
  ``event_priority = "inner"``; see the README.
"""

from ..scope import ClockLike, LoopClock
from ._declaration import State, Transition, TransitionList
from ._discovery import find_machines
from ._errors import EventNotAllowed, RobotStoppedError, StateMachineDefinitionError, StateMachineError
from ._machine import StateMachine, TransitionListener
from ._runtime import HistoryRecord, StateContext, UserData

__all__ = [
    "ClockLike",
    "EventNotAllowed",
    "HistoryRecord",
    "LoopClock",
    "RobotStoppedError",
    "State",
    "StateContext",
    "StateMachine",
    "StateMachineDefinitionError",
    "StateMachineError",
    "Transition",
    "TransitionList",
    "TransitionListener",
    "UserData",
    "find_machines",
]

for _name in __all__:
    _obj = globals()[_name]
    if getattr(_obj, "__module__", "").startswith(__name__ + "."):
        _obj.__module__ = __name__  # documented and pickled as agentsdk.statemachine.X
