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

