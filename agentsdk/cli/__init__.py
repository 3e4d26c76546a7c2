"""The ``agentsdk`` command line.

``agentsdk run BEHAVIOR``       run ``async def main(robot)`` from a behavior script
                                (``--record run.mcap``, ``--plot out.png``, ``--view``)
``agentsdk replay RUN.mcap``    replay a recording's commands and report the divergence
``agentsdk robots``             list the shipped robots
``agentsdk describe ROBOT``     print the joint tree with types and limits (like check_urdf; URDF, xacro, MJCF)
``agentsdk check ROBOT``        check_urdf plus a doctor: repairs, masses, start pose, self-collision,
                                and a load on each installed simulator (each in its own process)
``agentsdk graph BEHAVIOR``     print the Mermaid diagram of the behavior's state machines
                                (``--run run.mcap``: the states that run entered highlighted)
``agentsdk emulate-can ...``    run the MIT motor emulator on a CAN bus
``agentsdk bench ...``          run the benchmarks, each figure beside its raw baseline
``agentsdk vcan -- CMD``        run CMD inside user-mode Linux with a SocketCAN vcan0
``agentsdk serve ...``          serve a robot as a ROS 2 node (DDS) until SIGINT/SIGTERM
``agentsdk security ...``       create a keystore of roles (operator, viewer) for ``serve --keystore``

User errors print one line and exit non-zero; ``--debug`` shows tracebacks.

One module per command group, each importing only the ones above it: ``_behavior`` (loading and
running a behavior, exit codes), ``_run`` (run, replay), ``_robots`` (robots, describe, check,
graph), ``_teleop`` (teleop), ``_tools`` (emulate-can, bench, vcan, serve, security) and ``_main``
(the parser and :func:`main`, the ``agentsdk`` entry point).
"""

from __future__ import annotations

# the modules the commands use, reachable as attributes as when the CLI was one module
import sys as sys
import time as time

from ._behavior import EXIT_BAD_BEHAVIOR as EXIT_BAD_BEHAVIOR
from ._behavior import EXIT_BEHAVIOR_FAILED as EXIT_BEHAVIOR_FAILED
from ._behavior import EXIT_INTERRUPTED as EXIT_INTERRUPTED
from ._behavior import EXIT_USER_ERROR as EXIT_USER_ERROR
from ._behavior import BehaviorError, Interrupted, load_behavior, run_behavior
from ._behavior import RunSummary as RunSummary
from ._behavior import final_errors as final_errors
from ._behavior import parse_options as parse_options
from ._behavior import print_error as print_error
from ._main import _parser as _parser
from ._main import main

__all__ = ["BehaviorError", "Interrupted", "load_behavior", "main", "run_behavior"]
