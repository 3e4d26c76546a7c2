"""The ``agentsdk`` command line.

``agentsdk run BEHAVIOR``       run ``async def main(robot)`` from a behavior script
``agentsdk robots``             list the shipped robots
``agentsdk describe ROBOT``     print the joint tree with types and limits (like check_urdf)
``agentsdk graph BEHAVIOR``     print the Mermaid diagram of the behavior's state machines
``agentsdk emulate-can ...``    run the MIT motor emulator on a CAN bus

User errors print one line and exit non-zero; ``--debug`` shows tracebacks.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
import logging
import signal
import sys
import time
import traceback
from collections.abc import Awaitable, Callable
from pathlib import Path
from types import ModuleType
from typing import Any

from .errors import AgentSDKError, ConfigurationError

__all__ = ["load_behavior", "main", "run_behavior"]

EXIT_USER_ERROR = 2
EXIT_BEHAVIOR_FAILED = 1
EXIT_INTERRUPTED = 130


def load_behavior(spec: str) -> ModuleType:
    """Import a behavior script by path, or by name from the shipped ``behaviors`` package."""
    path = Path(spec)
    if not path.exists() and not spec.endswith(".py"):
        import behaviors

        candidate = Path(behaviors.__file__).parent / f"{spec}.py"
        if candidate.exists():
            path = candidate
    if not path.is_file():
        raise ConfigurationError(f"behavior script not found: {spec}")
    name = f"agentsdk_behavior_{path.stem}"
    module_spec = importlib.util.spec_from_file_location(name, path)
    if module_spec is None or module_spec.loader is None:
        raise ConfigurationError(f"cannot import behavior script {path}")
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[name] = module
    module_spec.loader.exec_module(module)
    if not callable(getattr(module, "main", None)):
        raise ConfigurationError(f"{path} does not define `async def main(robot)`")
    return module


class RunSummary:
    def __init__(self, sim_time: float, wall_time: float, errors: dict[str, float], realtime: bool) -> None:
        self.sim_time = sim_time
        self.wall_time = wall_time
        self.errors = errors
        self.realtime = realtime

    @property
    def real_time_factor(self) -> float:
        return self.sim_time / self.wall_time if self.wall_time > 0 else float("inf")

    def lines(self) -> list[str]:
        out = [
            f"simulated time {self.sim_time:.3f} s, wall time {self.wall_time:.3f} s, "
            f"real-time factor {self.real_time_factor:.1f}x"
        ]
        if self.errors:
            worst = max(abs(e) for e in self.errors.values())
            errs = ", ".join(f"{k}={v:+.4f}" for k, v in self.errors.items())
            out.append(f"final joint errors (target - actual, rad): {errs}  (max {worst:.4f})")
        return out


def final_errors(robot: Any) -> dict[str, float]:
    """Position error (last position target - measured) of joints in position mode."""
    ctl = robot.controller
    sp, st = ctl.setpoint, ctl.state
    return {
        n: float(sp.position[i] - st.position[i])
        for i, n in enumerate(ctl.names)
        if sp.mode[i] == 0 and sp.enabled[i]
    }


async def run_behavior(
    main_fn: Callable[[Any], Awaitable[Any]],
    *,
    backend: str,
    robot: str,
    realtime: bool | None = None,
    options: dict[str, Any] | None = None,
    on_robot: Callable[[Any], Any] | None = None,
    install_signal_handlers: bool = False,
) -> RunSummary:
    """Connect, run ``main_fn(robot)`` and stop safely.

    An exception in the behavior triggers a category-1 stop before it propagates;
    SIGINT/SIGTERM (when handlers are installed) trigger a category-1 stop, then
    the behavior is cancelled.
    """
    from .robot import connect

    t_wall = time.perf_counter()
    async with connect(backend, robot=robot, realtime=realtime, **(options or {})) as bot:
        if on_robot is not None:
            on_robot(bot)
        loop = asyncio.get_running_loop()
        task = loop.create_task(main_fn(bot), name="agentsdk-behavior")
        stop_task: asyncio.Task[None] | None = None
        interrupted = False

        def _on_signal(signame: str) -> None:
            nonlocal stop_task, interrupted
            if interrupted:
                return
            interrupted = True
            logging.getLogger("agentsdk").warning("%s: category-1 stop, then exit", signame)

            async def _stop_then_cancel() -> None:
                try:
                    await bot.estop(category=1)
                finally:
                    task.cancel()

            stop_task = loop.create_task(_stop_then_cancel())

        if install_signal_handlers:
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, _on_signal, sig.name)
        try:
            await task
        except asyncio.CancelledError:
            if not interrupted:
                raise
            if stop_task is not None:
                await stop_task
            raise KeyboardInterrupt from None
        except BaseException:
            if not bot.closed and bot.safety.state.name not in ("ESTOP", "FAULT"):
                try:
                    await bot.estop(category=1)
                except AgentSDKError:
                    pass
            raise
        finally:
            if install_signal_handlers:
                for sig in (signal.SIGINT, signal.SIGTERM):
                    loop.remove_signal_handler(sig)
        summary = RunSummary(bot.clock.now(), time.perf_counter() - t_wall, final_errors(bot), bot.realtime)
    return summary


# ----------------------------------------------------------------- commands
def _cmd_run(args: argparse.Namespace) -> int:
    module = load_behavior(args.behavior)
    robot = args.robot or getattr(module, "ROBOT", "arm3")
    backend = args.backend or getattr(module, "BACKEND", "mujoco")
    options: dict[str, Any] = {}
    for item in args.option or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigurationError(f"--option expects KEY=VALUE, got {item!r}")
        options[key] = _parse_value(value)
    try:
        summary = asyncio.run(
            run_behavior(
                module.main,
                backend=backend,
                robot=robot,
                realtime=True if args.realtime else None,
                options=options,
                install_signal_handlers=True,
            )
        )
    except KeyboardInterrupt:
        print("interrupted: robot stopped (category 1)", file=sys.stderr)
        return EXIT_INTERRUPTED
    except AgentSDKError:
        raise
    except Exception as exc:
        if args.debug:
            raise
        tb = traceback.extract_tb(exc.__traceback__)
        where = next((f"{f.filename}:{f.lineno} in {f.name}" for f in reversed(tb) if "agentsdk" not in f.filename),
                     f"{tb[-1].filename}:{tb[-1].lineno}" if tb else "?")
        print(f"behavior failed: {type(exc).__name__}: {exc} (at {where}); robot stopped (category 1)",
              file=sys.stderr)
        return EXIT_BEHAVIOR_FAILED
    if not args.quiet:
        print(f"ran {Path(module.__file__ or args.behavior).name} on {robot} ({backend})")
        for line in summary.lines():
            print(line)
    return 0


def _parse_value(text: str) -> Any:
    import yaml

    return yaml.safe_load(text)


def _cmd_robots(args: argparse.Namespace) -> int:
    from .description import list_robots, resolve_robot

    for name in list_robots():
        try:
            _, desc = resolve_robot(name)
            print(f"{name:12s} {len(desc.joints)} joints: {', '.join(j.name for j in desc.joints)}")
        except AgentSDKError as exc:
            print(f"{name:12s} (broken: {exc})")
    return 0


def _cmd_describe(args: argparse.Namespace) -> int:
    from .description import apply_overrides, resolve_robot

    config, desc = resolve_robot(args.robot)
    joints = apply_overrides(desc, config)
    print(f"robot name is: {desc.name}")
    print(f"---------- Successfully parsed {desc.source} ----------")
    for line in desc.tree_lines():
        print(line)
    print()
    print(f"{len(joints)} actuated joints (after robot.yaml overrides), control rate {config.update_rate:g} Hz:")
    for j in joints:
        print(
            f"  {j.name:22s} {j.type:10s} [{j.lower:+.3f}, {j.upper:+.3f}]  vel {j.max_velocity:g}  "
            f"acc {j.max_acceleration:g}  effort {j.max_effort:g}"
        )
    return 0


def _cmd_graph(args: argparse.Namespace) -> int:
    from .statemachine import find_machines

    module = load_behavior(args.behavior)
    machines = find_machines(module)
    if not machines:
        raise ConfigurationError(f"{args.behavior} defines no StateMachine")
    for i, machine in enumerate(machines):
        if i:
            print()
        print(machine.mermaid())
    return 0


def _cmd_emulate_can(args: argparse.Namespace, rest: list[str]) -> int:
    from backends.can.emulator import main as emulator_main

    return emulator_main(rest)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="agentsdk", description="Run robot behaviors on any backend.")
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run a behavior script's `async def main(robot)`")
    r.add_argument("behavior", help="path to a behavior .py (or a name from behaviors/)")
    r.add_argument("--backend", default=None, help="mujoco (default), pybullet, mock, can")
    r.add_argument("--robot", default=None, help="robot name or path to .urdf/.xacro/robot.yaml")
    r.add_argument("--realtime", action="store_true", help="pace the simulation to the wall clock")
    r.add_argument("--option", "-o", action="append", metavar="KEY=VALUE", help="backend option")
    r.add_argument("--quiet", "-q", action="store_true", help="no summary")
    r.add_argument("--debug", action="store_true", help="show tracebacks")

    sub.add_parser("robots", help="list the shipped robots")
    d = sub.add_parser("describe", help="print a robot's joint tree and limits")
    d.add_argument("robot")
    g = sub.add_parser("graph", help="print the Mermaid diagram of a behavior's state machines")
    g.add_argument("behavior")
    sub.add_parser("emulate-can", help="run the MIT motor emulator (see `agentsdk emulate-can --help`)",
                   add_help=False)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _parser()
    if (argv and argv[0] == "emulate-can") or (len(argv) > 1 and argv[0] == "--debug" and argv[1] == "emulate-can"):
        rest = argv[argv.index("emulate-can") + 1:]
        return _cmd_emulate_can(argparse.Namespace(), rest)
    args = parser.parse_args(argv)
    debug = args.debug
    logging.basicConfig(level=logging.DEBUG if debug else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    handlers = {"run": _cmd_run, "robots": _cmd_robots, "describe": _cmd_describe, "graph": _cmd_graph}
    try:
        return handlers[args.command](args)
    except AgentSDKError as exc:
        if debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR


