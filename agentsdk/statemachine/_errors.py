"""The state machines' exceptions."""

from __future__ import annotations

from ..errors import AgentSDKError, ConfigurationError

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



class RobotStoppedError(StateMachineError):
    """The robot was stopped while a state ran: an e-stop, a safety fault, or an aborted motion.

    The state is left through the fault path (its fault state, or out of ``run()``),
    never by the transition its body asked for, and only once the stop has brought
    the robot to rest.  ``reason`` is ``"estop"``, ``"fault"`` or ``"aborted"``.
    """

    def __init__(self, message: str, *, reason: str, path: str | None = None) -> None:
        super().__init__(message, path=path)
        self.reason = reason
