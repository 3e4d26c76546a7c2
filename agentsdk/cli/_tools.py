"""The pass-through commands: ``emulate-can``, ``bench``, ``vcan``, ``serve``, ``security``."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ._behavior import EXIT_USER_ERROR


def _cmd_emulate_can(args: argparse.Namespace, rest: list[str]) -> int:
    from agentsdk.backends.can.emulator import main as emulator_main

    return emulator_main(rest)


def _cmd_bench(rest: list[str]) -> int:
    import ctypes.util

    if not os.environ.get("DISPLAY") and "MUJOCO_GL" not in os.environ and ctypes.util.find_library("EGL"):
        # headless: MuJoCo picks its GL when imported; left to itself it tries GLFW, whose warnings reach the user
        os.environ["MUJOCO_GL"] = "egl"
    from agentsdk.bench.__main__ import main as bench_main

    return bench_main(rest)


def _cmd_vcan(rest: list[str]) -> int:
    """Run a command inside a user-mode Linux kernel with a real SocketCAN vcan0 (the shipped runner)."""
    import subprocess

    script = Path(__file__).resolve().parent.parent / "data" / "run-in-vcan.sh"
    if rest and rest[0] == "--":
        rest = rest[1:]
    if not rest:
        print("usage: agentsdk vcan [--] COMMAND [ARGS...]   (e.g. agentsdk vcan -- pytest -m vcan)", file=sys.stderr)
        return EXIT_USER_ERROR
    return subprocess.call(["bash", str(script), *rest])


def _cmd_serve(rest: list[str]) -> int:
    from ..ros2.cli import main as serve_main

    return serve_main(rest)


def _cmd_security(rest: list[str]) -> int:
    from ..ros2.cli import security_main

    return security_main(rest)
