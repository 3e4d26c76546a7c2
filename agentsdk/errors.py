"""One exception root, subclasses grouped by what the caller can do about them.

==============================  =============================================
exception                       what the caller can do
==============================  =============================================
``ConfigurationError``          fix the robot description / robot.yaml / args
``DescriptionError``            (a ``ConfigurationError``) fix the URDF/xacro
``BackendUnavailableError``     install the backend or pick a known name
``BackendStartError``           the backend failed to open (hardware, sim)
``BusClaimedError``             (a ``BackendStartError``) another robot in this process drives those motors
``UnsupportedModelError``       (a ``BackendStartError``) the backend cannot simulate part of the model: use another
``CommandRejected``             fix the command; the robot state is unchanged
``UnknownJointError``           (a ``CommandRejected``, ``KeyError``)
``UnknownLinkError``            (a ``CommandRejected``, ``KeyError``) no such link
``UnreachablePoseError``        (a ``CommandRejected``) IK found no solution: names the residual
``InvalidValueError``           (a ``CommandRejected``, ``ValueError``) NaN/inf, shape
``LimitViolation``              (a ``CommandRejected``) outside a joint limit
``UnsupportedModeError``        (a ``CommandRejected``) mode not offered
``AgentTimeoutError``           (also a builtin ``TimeoutError``)
``SafetyError``                 the safety layer stopped or refuses motion
``EStopActive``                 (a ``SafetyError``) e-stop latched: reset+enable
``SafetyFault``                 (a ``SafetyError``) a fault (divergence, bus)
``SensorFault``                 (a ``SafetyFault``) a reading the physics cannot explain
``BackendFault``                the backend failed while running
``SimulationDiverged``          (a ``BackendFault``) physics became unstable
``BusConflict``                 (a ``BackendFault``) another controller or responder on the bus
``RobotClosedError``            the connection is closed; reconnect
==============================  =============================================
"""

from __future__ import annotations

__all__ = [
    "AgentSDKError",
    "AgentTimeoutError",
    "BackendFault",
    "BackendStartError",
    "BackendUnavailableError",
    "BusClaimedError",
    "BusConflict",
    "CommandRejected",
    "ConfigurationError",
    "DescriptionError",
    "EStopActive",
    "InvalidValueError",
    "LimitViolation",
    "RobotClosedError",
    "SafetyError",
    "SafetyFault",
    "SensorFault",
    "SimulationDiverged",
    "UnknownJointError",
    "UnknownLinkError",
    "UnreachablePoseError",
    "UnsupportedModeError",
    "UnsupportedModelError",
]


class AgentSDKError(Exception):
    """Root of every error raised by agentsdk."""


class ConfigurationError(AgentSDKError):
    """A robot.yaml, connect() option or robot name is invalid."""


class DescriptionError(ConfigurationError):
    """A URDF/xacro robot description could not be loaded or is malformed."""


class BackendUnavailableError(ConfigurationError):
    """The backend name is unknown or its optional dependency is not installed."""


class BackendStartError(AgentSDKError):
    """The backend could not be opened (simulator build failed, motor silent...)."""


class BusClaimedError(BackendStartError):
    """The bus channel and motor ids are already driven by another open robot in this process."""


class UnsupportedModelError(BackendStartError):
    """The backend cannot simulate part of the robot model (e.g. MJCF tendons on PyBullet); the message names it."""


class CommandRejected(AgentSDKError):
    """A command was refused before anything was applied; robot state is unchanged."""


class UnknownJointError(CommandRejected, KeyError):
    """A joint name is not part of the robot."""

    def __str__(self) -> str:  # KeyError would repr() the message
        return str(self.args[0]) if self.args else ""


class UnknownLinkError(CommandRejected, KeyError):
    """A link (frame) name is not part of the robot."""

    def __str__(self) -> str:  # KeyError would repr() the message
        return str(self.args[0]) if self.args else ""


class UnreachablePoseError(CommandRejected):
    """Inverse kinematics found no joint positions within the limits that reach the pose.

    The message names the link, the residual (position error in m, orientation error in
    rad) of the best attempt and the tolerances; ``result`` holds that best attempt
    (an :class:`agentsdk.kinematics.IKResult` with ``ok == False``), never to be used as
    a solution without checking.
    """

    def __init__(self, message: str, result: object = None) -> None:
        super().__init__(message)
        self.result = result


class InvalidValueError(CommandRejected, ValueError):
    """A value is NaN/inf, of the wrong length, or otherwise malformed."""


class LimitViolation(CommandRejected):
    """A value is outside a joint limit and the policy is to reject."""


class UnsupportedModeError(CommandRejected):
    """The command mode is unknown or not supported by this backend."""


class AgentTimeoutError(AgentSDKError, TimeoutError):
    """An operation did not complete in time."""


class SafetyError(AgentSDKError):
    """The safety layer refuses motion."""


class EStopActive(SafetyError):
    """The emergency stop is latched: ``await robot.reset()`` then ``await robot.enable()``."""


class SafetyFault(SafetyError):
    """The safety layer is in FAULT (e.g. simulator divergence, motor error)."""


class SensorFault(SafetyFault):
    """A measured value the physics cannot explain (a jump, NaN, a leap past the limits).

    ``joint`` names the joint, ``source`` where it is measured (e.g. ``"motor id 2 on
    socketcan:vcan0"``, None on simulators), ``quantity`` and ``value`` what was read.
    """

    def __init__(
        self, message: str, *, joint: str = "", source: str | None = None, quantity: str = "", value: float = 0.0
    ) -> None:
        super().__init__(message)
        self.joint = joint
        self.source = source
        self.quantity = quantity
        self.value = value


class BackendFault(AgentSDKError):
    """The backend failed while running."""


class SimulationDiverged(BackendFault):
    """The physics simulation became unstable (NaN, huge accelerations)."""


class BusConflict(BackendFault):
    """Another controller commands our motors, or a second device answers with one of their ids."""


class RobotClosedError(AgentSDKError):
    """The robot connection was closed; every call after close() raises this."""
