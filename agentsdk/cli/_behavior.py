"""Running a behavior script: loading it, running ``main(robot)``, exit codes and error lines."""

from __future__ import annotations

import asyncio
import inspect
import logging
import signal
import sys
import time
import traceback
from collections.abc import Awaitable, Callable
from pathlib import Path
from types import ModuleType
from typing import Any

from ..errors import AgentSDKError, ConfigurationError

#: a user error (configuration, robot, options, arguments)
EXIT_USER_ERROR = 2


#: the behavior raised (the robot was stopped)
EXIT_BEHAVIOR_FAILED = 1


#: the behavior script cannot be used (syntax error, failing import, no async main(robot))
EXIT_BAD_BEHAVIOR = 3


EXIT_INTERRUPTED = 130


class BehaviorError(ConfigurationError):
    """A behavior script cannot be used: missing, a syntax error, an import failing, no ``async def main(robot)``.

    ``agentsdk run`` reports it in one line (file:line) and exits with :data:`EXIT_BAD_BEHAVIOR`.
    """


def load_behavior(spec: str) -> ModuleType:
    """Import a behavior script by path, or by name from the shipped ``behaviors`` package.

    Checked when the file loads, not when the robot is already running: the file
    must compile, import, and define ``main`` as an ``async def`` taking the robot.
    Raises :class:`BehaviorError` naming the file and line otherwise.
    """
    path = Path(spec)
    if not path.exists() and not spec.endswith(".py"):
        import agentsdk.behaviors as behaviors

        candidate = Path(behaviors.__file__).parent / f"{spec}.py"
        if candidate.exists():
            path = candidate
    if not path.is_file():
        raise BehaviorError(f"behavior script not found: {spec}")
    try:
        source = path.read_bytes()
        code = compile(source, str(path), "exec", dont_inherit=True)
    except SyntaxError as exc:
        where = f"{exc.filename or path}:{exc.lineno}" + (f":{exc.offset}" if exc.offset else "")
        raise BehaviorError(f"{where}: {type(exc).__name__}: {exc.msg}") from None
    except (OSError, ValueError) as exc:
        raise BehaviorError(f"cannot read behavior script {path}: {exc}") from None
    name = f"agentsdk_behavior_{path.stem}"
    module = ModuleType(name)
    module.__file__ = str(path)
    sys.modules[name] = module
    try:
        exec(code, module.__dict__)
    except Exception as exc:
        del sys.modules[name]
        tb = traceback.extract_tb(exc.__traceback__)
        frame = next((f for f in reversed(tb) if f.filename == str(path)), tb[-1] if tb else None)
        where = f"{frame.filename}:{frame.lineno}" if frame is not None else str(path)
        raise BehaviorError(f"{where}: importing the behavior failed: {type(exc).__name__}: {exc}") from exc
    main = getattr(module, "main", None)
    if main is None:
        raise BehaviorError(f"{path} does not define `async def main(robot)`")
    call = type(main).__call__ if callable(main) and not inspect.isfunction(main) else None
    if not (inspect.iscoroutinefunction(main) or (call is not None and inspect.iscoroutinefunction(call))):
        line = getattr(getattr(main, "__code__", None), "co_firstlineno", None)
        where = f"{path}:{line}" if line else str(path)
        raise BehaviorError(f"{where}: `main` must be an `async def main(robot)` coroutine function, "
                            f"got {type(main).__name__} {getattr(main, '__name__', '')}".rstrip())
    try:
        inspect.signature(main).bind(object())
    except TypeError:
        line = main.__code__.co_firstlineno if hasattr(main, "__code__") else None
        where = f"{path}:{line}" if line else str(path)
        raise BehaviorError(
            f"{where}: `main` must take exactly one argument, the robot: async def main(robot)"
        ) from None
    except ValueError:  # no signature available (a builtin): let the call decide
        pass
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


async def final_errors(robot: Any) -> dict[str, float]:
    """Position error (last position setpoint - measured) of the enabled joints in position mode."""
    from ..backend import ModeCode

    sp = robot.setpoint
    st = await robot.read()
    return {
        n: float(sp.position[i] - st.position[i])
        for i, n in enumerate(robot.joint_names)
        if sp.mode[i] == ModeCode.POSITION and sp.enabled[i]
    }


class Interrupted(Exception):
    """The run was stopped by a signal (SIGINT/SIGTERM): the robot was brought to a category 1 stop.

    ``exit_code`` follows the shell convention ``128 + signal number`` (130, 143).
    """

    def __init__(self, signum: int, detail: str) -> None:
        self.signum = signum
        self.signame = signal.Signals(signum).name
        self.detail = detail
        super().__init__(f"{self.signame}: {detail}")

    @property
    def exit_code(self) -> int:
        """``128 + signum``: 130 for SIGINT, 143 for SIGTERM."""
        return 128 + self.signum


async def _awaited(awaitable: Awaitable[Any]) -> Any:
    """``await awaitable`` as a coroutine (``create_task`` takes coroutines, ``main`` may return any awaitable)."""
    return await awaitable


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

    An exception in the behavior triggers a category-1 stop before it propagates.
    SIGINT/SIGTERM (when handlers are installed) start a category-1 stop at once;
    the stop runs to completion (decelerate to rest, then torque off) while the
    behavior is cancelled, then :class:`Interrupted` is raised. A second signal
    escalates to category 0 (torque off at once).
    """
    from ..robot import connect

    async with connect(backend, robot=robot, realtime=realtime, **(options or {})) as bot:
        if on_robot is not None:
            on_robot(bot)
        aloop = asyncio.get_running_loop()
        # the real-time factor covers the behavior only: not the connect (description load,
        # simulator build), the viewer/recorder setup, nor the stop and close after it
        t_sim, t_wall = bot.clock.now(), time.perf_counter()
        task: asyncio.Task[Any] = aloop.create_task(_awaited(main_fn(bot)), name="agentsdk-behavior")
        stop_task: asyncio.Task[None] | None = None
        signals: list[int] = []

        def _on_signal(signum: int) -> None:
            nonlocal stop_task
            signals.append(signum)
            if len(signals) > 1:  # pressed again: no more waiting for the controlled stop
                bot.estop_threadsafe(0)
                task.cancel()
                return
            stop_task = aloop.create_task(bot.estop(category=1), name="agentsdk-signal-stop")
            task.cancel()

        if install_signal_handlers:
            for sig in (signal.SIGINT, signal.SIGTERM):
                aloop.add_signal_handler(sig, _on_signal, sig)
        try:
            try:
                await task
            except asyncio.CancelledError:
                if not signals:
                    raise
            except BaseException:
                if not signals:
                    if not bot.closed and bot.safety.state.name not in ("ESTOP", "FAULT"):
                        try:
                            await bot.estop(category=1)
                        except AgentSDKError:
                            pass
                    raise
                # after a signal, whatever the behavior raised while being stopped is part of the stop
                logging.getLogger("agentsdk").debug("behavior ended while stopping", exc_info=True)
            if stop_task is not None:
                try:
                    await stop_task  # the stop completes (to rest, then torque off) before close
                except AgentSDKError as exc:
                    logging.getLogger("agentsdk").debug("signal stop: %s", exc)
        finally:
            if install_signal_handlers:
                for sig in (signal.SIGINT, signal.SIGTERM):
                    aloop.remove_signal_handler(sig)
        if signals:
            events = [e.detail for e in bot.safety.events if e.kind == "estop"]
            detail = events[-1] if events else "robot stopped"
            raise Interrupted(signals[0], detail)
        wall = time.perf_counter() - t_wall
        summary = RunSummary(bot.clock.now() - t_sim, wall, await final_errors(bot), bot.realtime)
    return summary


def _parse_value(text: str) -> Any:
    import yaml

    return yaml.safe_load(text)


def parse_options(items: list[str] | None) -> dict[str, Any]:
    """``--option KEY=VALUE`` items as a dict of backend options (values parsed like YAML scalars)."""
    options: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigurationError(f"--option expects KEY=VALUE, got {item!r}")
        options[key] = _parse_value(value)
    return options


def print_error(exc: BaseException) -> None:
    """``error: ...`` on stderr, one line per problem (indented continuation lines stay as they are)."""
    for line in str(exc).splitlines() or [type(exc).__name__]:
        print(line if line[:1].isspace() else f"error: {line}", file=sys.stderr)
