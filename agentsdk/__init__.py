"""agentsdk: an asyncio SDK for robot agents with pluggable backends.

Write a behavior once::

    import agentsdk
    from agentsdk import JointCommand

    async def main(robot):
        await robot.command(JointCommand("position", {"joint1": 0.4}))
        await robot.clock.sleep(1.0)

and run it on MuJoCo, PyBullet, a CAN motor bus or the mock backend:
``agentsdk run behavior.py --backend mujoco --robot arm3``.
"""

from __future__ import annotations

import os as _os


def _source_checkout_subpackages() -> None:
    """Make ``agentsdk.backends`` & co. importable from a source checkout that is not installed.

    The repository keeps ``backends/``, ``robots/``, ``behaviors/`` and ``bench/`` at its root; an
    install (editable or not) maps them to ``agentsdk.backends`` etc. (``[tool.setuptools.package-dir]``).
    When this package is imported straight from a checkout (``python -m agentsdk`` in the repository
    after a non-editable install, or with ``PYTHONPATH`` pointing at it), the package path is extended
    with the repository root, as ``pkgutil.extend_path`` does for split packages.
    """
    here = _os.path.dirname(_os.path.abspath(__file__))
    root = _os.path.dirname(here)
    if _os.path.isfile(_os.path.join(root, "pyproject.toml")) and _os.path.isfile(
        _os.path.join(root, "backends", "__init__.py")
    ):
        if root not in __path__:
            __path__.append(root)


_source_checkout_subpackages()

from .backend import Backend, Capabilities, JointReading, ModeCode, SetpointView
from .clock import Clock, LockstepClock, RealtimeClock
from .config import RobotConfig, load_robot_config
from .errors import (
    AgentSDKError,
    AgentTimeoutError,
    BackendFault,
    BackendStartError,
    BackendUnavailableError,
    BusClaimedError,
    BusConflict,
    CommandRejected,
    ConfigurationError,
    DescriptionError,
    EStopActive,
    InvalidValueError,
    LimitViolation,
    RobotClosedError,
    SafetyError,
    SafetyFault,
    SensorFault,
    SimulationDiverged,
    UnknownJointError,
    UnknownLinkError,
    UnreachablePoseError,
    UnsupportedModeError,
    UnsupportedModelError,
)
from .feedback import FeedbackAgent, FeedbackState, LoopStats, run_feedback
from .loop import HookHandle, Phase, Setpoint, StateView
from .motion import Feedback, Motion, MotionResult, ResultCode, Tolerances
from .pose import Pose
from .registry import available_backends, load_backend, register_backend, unregister_backend
from .robot import Robot, connect
from .safety import SafetyCheck, SafetyConfig, SafetyEvent, SafetyState, SafetyViolation
from .trajectory import Trajectory, TrajectoryPoint
from .types import MODES, AppliedCommand, CommandMode, JointCommand, JointInfo, JointState

#: deprecated former name of :class:`Backend` (the base class backends subclass): use ``Backend``
Controller = Backend

__version__ = "0.1.0"

__all__ = [
    "MODES",
    "AgentSDKError",
    "AgentTimeoutError",
    "AppliedCommand",
    "Backend",
    "BackendFault",
    "BackendStartError",
    "BackendUnavailableError",
    "BusClaimedError",
    "BusConflict",
    "Capabilities",
    "Clock",
    "CommandMode",
    "CommandRejected",
    "ConfigurationError",
    "Controller",
    "DescriptionError",
    "EStopActive",
    "Feedback",
    "FeedbackAgent",
    "FeedbackState",
    "HookHandle",
    "InvalidValueError",
    "JointCommand",
    "JointInfo",
    "JointReading",
    "JointState",
    "LimitViolation",
    "LockstepClock",
    "LoopStats",
    "ModeCode",
    "Motion",
    "MotionResult",
    "Phase",
    "Pose",
    "RealtimeClock",
    "ResultCode",
    "Robot",
    "RobotClosedError",
    "RobotConfig",
    "SafetyCheck",
    "SafetyConfig",
    "SafetyError",
    "SafetyEvent",
    "SafetyFault",
    "SafetyState",
    "SafetyViolation",
    "SensorFault",
    "Setpoint",
    "SetpointView",
    "SimulationDiverged",
    "StateView",
    "Tolerances",
    "Trajectory",
    "TrajectoryPoint",
    "UnknownJointError",
    "UnknownLinkError",
    "UnreachablePoseError",
    "UnsupportedModeError",
    "UnsupportedModelError",
    "__version__",
    "available_backends",
    "connect",
    "load_backend",
    "load_robot_config",
    "register_backend",
    "run_feedback",
    "unregister_backend",
]
