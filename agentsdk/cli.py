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
"""

from __future__ import annotations

import argparse
import asyncio
import inspect
import json
import logging
import os
import signal
import sys
import time
import traceback
from collections.abc import Awaitable, Callable
from pathlib import Path
from types import ModuleType
from typing import Any

from .errors import AgentSDKError, ConfigurationError

__all__ = ["BehaviorError", "Interrupted", "load_behavior", "main", "run_behavior"]

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
    from .backend import ModeCode

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
    from .robot import connect

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


# ----------------------------------------------------------------- commands
def _has_display() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _check_view(backend: str) -> None:
    if backend not in ("mujoco", "pybullet"):
        raise ConfigurationError(f"--view is available for the mujoco and pybullet backends, not {backend!r}")
    if not _has_display():
        raise ConfigurationError(
            "--view needs a display, but neither DISPLAY nor WAYLAND_DISPLAY is set; "
            "run without --view (use --record/--plot instead) or under a desktop session or xvfb-run"
        )


def _check_output(path: str | None, what: str) -> None:
    if path is None:
        return
    p = Path(path)
    if p.is_dir():
        raise ConfigurationError(f"{what} {path} is a directory; give a file name")
    if not p.resolve().parent.is_dir():
        raise ConfigurationError(f"cannot write {what} {path}: directory {p.resolve().parent} does not exist")


class _MujocoView:
    """MuJoCo's passive viewer, synced from a tick hook at about 60 Hz of wall time."""

    def __init__(self, robot: Any) -> None:
        import mujoco.viewer

        from .loop import Phase

        backend = robot.controller  # the MuJoCo backend's public model and data
        self._handle = mujoco.viewer.launch_passive(backend.model, backend.data)
        self._last = 0.0
        self._hook = robot.add_tick_hook(Phase.OBSERVE, self._on_tick)

    def _on_tick(self, t: float, state: Any, setpoint: Any) -> None:
        now = time.perf_counter()
        if now - self._last >= 1 / 60 and self._handle.is_running():
            self._last = now
            self._handle.sync()

    def close(self) -> None:
        self._hook.remove()
        self._handle.close()


class _RunExtras:
    """Recording, plot, progress bar and viewer around one run."""

    def __init__(
        self,
        *,
        record: str | None,
        plot: str | None,
        rate: float | None,
        progress: bool,
        view: bool,
        label: str,
        metadata: dict[str, str],
        total: float | None = None,
        video: str | None = None,
        video_fps: float = 30.0,
        video_size: tuple[int, int] = (640, 480),
        record_format: str = "mcap",
        web_port: int | None = None,
    ) -> None:
        self.web_port = web_port
        self.web: Any = None
        self.record, self.plot, self.rate = record, plot, rate
        self.record_format = record_format
        self.video, self.video_fps, self.video_size = video, video_fps, video_size
        self.video_recorder: Any = None
        self.progress_on, self.view, self.label, self.metadata, self.total = progress, view, label, metadata, total
        self.recorder: Any = None
        self.progress: Any = None
        self.viewer: Any = None
        self.robot_desc = ""

    def on_robot(self, bot: Any) -> None:
        self.robot_desc = f"{bot.name} ({bot.backend})"
        if self.record or self.plot:
            from .recording import Recorder

            rate: dict[str, Any] = {} if self.rate is None else {"rate": self.rate}  # default: recording.STATE_RATE
            self.recorder = Recorder.attach(bot, self.record, keep=bool(self.plot),
                                            metadata=self.metadata, format=self.record_format, **rate)
        if self.view and bot.backend == "mujoco":
            self.viewer = _MujocoView(bot)
        if self.web_port is not None:
            from .webview import WebView

            self.web = WebView.attach(
                bot, port=self.web_port, on_ready=lambda v: print(f"web view: {v.url}", file=sys.stderr, flush=True)
            )
        if self.video:
            from .video import VideoRecorder

            self.video_recorder = VideoRecorder.attach(bot, self.video, fps=self.video_fps, size=self.video_size)
        if self.progress_on:
            from .progress import RunProgress

            self.progress = RunProgress(bot.clock.now, label=self.label, total=self.total).start()

    def close(self) -> list[str]:
        """Stop the display, finish the recording, draw the plot; returns summary lines."""
        lines: list[str] = []
        if self.progress is not None:
            self.progress.stop()
        if self.viewer is not None:
            self.viewer.close()
        if self.web is not None:
            self.web.close()
            self.web = None
        if self.video_recorder is not None:
            video, self.video_recorder = self.video_recorder, None
            path = video.finish(progress=self.progress_on)
            lines.append(f"video written to {path} ({len(video.frames)} frames at {video.fps:g} fps)")
        rec = self.recorder
        if rec is None:
            return lines
        rec.finish()
        if self.record:
            counts = ", ".join(f"{k} {v}" for k, v in rec.counts.items())
            lines.append(f"recorded {rec.ticks} ticks to {self.record}" + (f" ({counts})" if counts else ""))
        if self.plot:
            from .plot import plot_run

            plot_run(rec.data(), self.plot)
            lines.append(f"plot written to {self.plot}")
        return lines


def _video_args(args: argparse.Namespace) -> tuple[int, int]:
    if args.video is None:
        return (640, 480)
    from .video import check_video_path

    check_video_path(args.video)
    w, sep, h = str(args.video_size).lower().partition("x")
    try:
        size = (int(w), int(h))
    except ValueError:
        sep = ""
    if not sep:
        raise ConfigurationError(f"--video-size expects WIDTHxHEIGHT (e.g. 640x480), got {args.video_size!r}")
    return size


def parse_options(items: list[str] | None) -> dict[str, Any]:
    """``--option KEY=VALUE`` items as a dict of backend options (values parsed like YAML scalars)."""
    options: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigurationError(f"--option expects KEY=VALUE, got {item!r}")
        options[key] = _parse_value(value)
    return options


def _apply_scheduling(priority: int | None, cpus: str | None) -> None:
    """``--rt-priority`` / ``--cpus``: SCHED_FIFO and CPU affinity for this process (agentsdk.realtime)."""
    if priority is None and cpus is None:
        return
    cpu_list: list[int] | None = None
    if cpus is not None:
        try:
            cpu_list = [int(c) for c in cpus.split(",") if c.strip()]
        except ValueError as exc:
            raise ConfigurationError(f"--cpus must be a comma-separated list of CPU numbers, got {cpus!r}") from exc
        if not cpu_list:
            raise ConfigurationError("--cpus needs at least one CPU number")
    if priority is None:
        assert cpu_list is not None
        try:
            os.sched_setaffinity(0, cpu_list)
        except (AttributeError, OSError, ValueError) as exc:
            raise ConfigurationError(f"cannot pin the process to CPUs {cpu_list}: {exc}") from exc
        return
    from .realtime import set_realtime_priority

    set_realtime_priority(priority, cpu_list)


def _cmd_run(args: argparse.Namespace) -> int:
    from .progress import progress_enabled
    from .recording import robot_spec_for_metadata

    module = load_behavior(args.behavior)
    robot = args.robot or getattr(module, "ROBOT", "arm3")
    backend = args.backend or getattr(module, "BACKEND", "mujoco")
    options = parse_options(args.option)
    _check_output(args.record, "recording")
    _check_output(args.plot, "plot")
    video_size = _video_args(args)
    if args.record_rate is not None and not (args.record or args.plot):
        raise ConfigurationError("--record-rate needs --record or --plot")
    if args.record_rate is not None and not args.record_rate > 0:
        raise ConfigurationError(f"--record-rate must be > 0 Hz, got {args.record_rate:g}")
    _apply_scheduling(args.rt_priority, args.cpus)
    if args.record_format != "mcap" and not args.record:
        raise ConfigurationError("--record-format needs --record")
    if args.view:
        _check_view(backend)
        if backend == "pybullet":
            options.setdefault("gui", True)
    if args.web:
        from .webview import WebView

        WebView.prepare()  # imports take seconds: before the robot's loop and its stall watchdog run
    behavior_name = Path(module.__file__ or args.behavior).name
    extras = _RunExtras(
        record=args.record,
        plot=args.plot,
        rate=args.record_rate,
        progress=progress_enabled(args.quiet),
        view=args.view,
        video=args.video,
        video_fps=args.video_fps,
        video_size=video_size,
        record_format=args.record_format,
        web_port=args.port if args.web else None,
        label=f"{behavior_name} on {robot} ({backend})",
        metadata={
            "robot": robot_spec_for_metadata(robot),
            "behavior": str(Path(module.__file__ or args.behavior).resolve()),
            "backend_options": json.dumps(options, sort_keys=True, default=str),
        },
    )
    main_fn = module.main
    if args.web_wait:
        if not args.web:
            raise ConfigurationError("--web-wait needs --web")
        behavior_main = module.main

        async def main_fn(bot: Any) -> Any:
            await extras.web.wait_ready()
            print(f"press Start on {extras.web.url} to run the behavior", file=sys.stderr, flush=True)
            await extras.web.wait_for_start()
            return await behavior_main(bot)

    if args.record or args.plot:
        # import the recorder (mcap, zstandard, its encoders) before the robot connects: attaching it
        # then runs on the control loop, where a realtime robot's stall watchdog allows 0.25 s
        from . import recording  # noqa: F401
    try:
        summary = asyncio.run(
            run_behavior(
                main_fn,
                backend=backend,
                robot=robot,
                realtime=True if (args.realtime or args.view) else None,
                options=options,
                on_robot=extras.on_robot,
                install_signal_handlers=True,
            )
        )
    except Interrupted as exc:
        _close_extras(extras, args.quiet)
        print(f"interrupted by {exc.signame}: {exc.detail}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:  # a signal before the handlers were installed (while connecting)
        _close_extras(extras, args.quiet)
        print("interrupted while connecting", file=sys.stderr)
        return EXIT_INTERRUPTED
    except AgentSDKError:
        _close_extras(extras, args.quiet)
        raise
    except Exception as exc:
        _close_extras(extras, args.quiet)
        if args.debug:
            raise
        tb = traceback.extract_tb(exc.__traceback__)
        where = next((f"{f.filename}:{f.lineno} in {f.name}" for f in reversed(tb) if "agentsdk" not in f.filename),
                     f"{tb[-1].filename}:{tb[-1].lineno}" if tb else "?")
        print(f"behavior failed: {type(exc).__name__}: {exc} (at {where}); robot stopped (category 1)",
              file=sys.stderr)
        return EXIT_BEHAVIOR_FAILED
    except BaseException:
        _close_extras(extras, True)
        raise
    lines = extras.close()
    if not args.quiet:
        print(f"ran {behavior_name} on {robot} ({backend})")
        for line in [*summary.lines(), *lines]:
            print(line)
    return 0


def _close_extras(extras: _RunExtras, quiet: bool) -> None:
    """Finish recording/plot after a failed run too (that is when they are most useful)."""
    try:
        lines = extras.close()
    except AgentSDKError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return
    if not quiet:
        for line in lines:
            print(line, file=sys.stderr)


def _cmd_replay(args: argparse.Namespace) -> int:
    from .progress import progress_enabled
    from .recording import read_recording, replay

    _check_output(args.record, "recording")
    _check_output(args.plot, "plot")
    data = read_recording(args.recording)
    if data.truncated and not args.quiet:
        print(f"warning: {args.recording} was not finished (the recording process was killed?); "
              f"replaying the {data.duration:.3f} s recovered from it", file=sys.stderr)
    backend = args.backend or data.backend or "mujoco"
    robot = args.robot or data.robot
    if args.tolerance is not None and not args.tolerance >= 0:
        raise ConfigurationError(f"--tolerance must be >= 0, got {args.tolerance:g}")
    extras = _RunExtras(
        record=None,
        plot=None,
        rate=None,
        progress=progress_enabled(args.quiet),
        view=False,
        label=f"replay {Path(args.recording).name}",
        metadata={},
        total=data.duration,
    )
    t_wall = time.perf_counter()
    try:
        result = asyncio.run(
            replay(data, backend=backend, robot=robot, options=parse_options(args.option), record=args.record,
                   on_robot=extras.on_robot)
        )
    finally:
        extras.close()
    wall = time.perf_counter() - t_wall
    if args.plot:
        from .plot import plot_run

        result.replayed.metadata.setdefault("behavior", data.metadata.get("behavior", ""))
        plot_run(result.replayed, args.plot, reference=data,
                 title=f"replay of {Path(args.recording).name} into {robot} on {backend} (dashed: recorded)")
    failed = args.tolerance is not None and result.worst > args.tolerance
    if not args.quiet or failed:
        source = Path(data.metadata.get("behavior") or "?").name
        print(f"replayed {args.recording} ({source} on {data.robot or '?'}, {data.backend or '?'}, "
              f"{data.duration:.3f} s) into {robot} ({backend}) in {wall:.2f} s wall time")
        if result.config_changed:
            print("warning: the robot configuration differs from the recorded one")
        for line in result.lines():
            print(line)
        if args.record:
            print(f"replay recorded to {args.record}")
        if args.plot:
            print(f"plot written to {args.plot}")
    if failed:
        print(f"divergence {result.worst:.3e} exceeds --tolerance {args.tolerance:g}", file=sys.stderr)
        return EXIT_BEHAVIOR_FAILED
    return 0


def _parse_value(text: str) -> Any:
    import yaml

    return yaml.safe_load(text)


def _cmd_robots(args: argparse.Namespace) -> int:
    from .description import list_robots, resolve_robot

    if getattr(args, "all", False):
        from .description.catalog import installed_robots

        entries = installed_robots()
        width = max((len(e.name) for e in entries), default=4)
        for e in entries:
            where = f"broken: {e.problem}" if e.path is None else str(e.path)
            source = f"{e.source} ({e.provider})" if e.provider else e.source
            print(f"{e.name:{width}s}  {source:22s} {where}")
        return 0
    for name in list_robots():
        try:
            _, desc = resolve_robot(name)
            print(f"{name:12s} {len(desc.joints)} joints: {', '.join(j.name for j in desc.joints)}")
        except AgentSDKError as exc:
            print(f"{name:12s} (broken: {exc})")
    return 0


def _cmd_describe(args: argparse.Namespace) -> int:
    from .description import apply_overrides, resolve_robot

    config, desc = resolve_robot(args.robot, trusted=True if args.trusted else None)
    joints = apply_overrides(desc, config)
    print(f"robot name is: {desc.name}")
    print(f"---------- Successfully parsed {desc.source} ----------")
    for line in desc.tree_lines():
        print(line)
    print()
    from .description.mobility import report_lines
    from .description.start import start_pose

    try:
        start = start_pose(desc, config, joints)
    except AgentSDKError:  # a named start pose that does not exist: `agentsdk check` reports it
        start = None
    for line in report_lines(desc, config, start):
        print(line)
    overrides = f" (after {config.source.name} overrides)" if config.source is not None else ""
    print(f"{len(joints)} actuated joints{overrides}, control rate {config.update_rate:g} Hz:")
    for j in joints:
        print(
            f"  {j.name:22s} {j.type:10s} [{j.lower:+.3f}, {j.upper:+.3f}]  vel {j.max_velocity:g}  "
            f"acc {j.max_acceleration:g}  effort {j.max_effort:g}"
        )
    return 0


def _cmd_check(args: argparse.Namespace) -> int:
    from .check import check_robot

    report = check_robot(
        args.robot,
        backends=args.backend,
        strict=True if args.strict else None,
        timeout=args.timeout,
        trusted=True if args.trusted else None,
    )
    for line in report.lines:
        print(line)
    if report.problems:
        if report.lines:
            print()
        for problem in report.problems:
            print(f"error: {problem}", file=sys.stderr)
        return EXIT_BEHAVIOR_FAILED
    print()
    print("ok")
    return 0


def _cmd_graph(args: argparse.Namespace) -> int:
    from .statemachine import find_machines

    module = load_behavior(args.behavior)
    machines = find_machines(module)
    if not machines:
        raise ConfigurationError(f"{args.behavior} defines no StateMachine")
    visited: list[str] | None = None
    if args.run is not None:  # highlight the states a recorded run entered
        from .recording import read_recording

        transitions = read_recording(args.run).transitions
        visited = [f"{t['machine']}/{t['target']}" for t in transitions if t.get("target")]
    for i, machine in enumerate(machines):
        if i:
            print()
        print(machine.mermaid(visited=visited))
    return 0


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

    script = Path(__file__).resolve().parent / "data" / "run-in-vcan.sh"
    if rest and rest[0] == "--":
        rest = rest[1:]
    if not rest:
        print("usage: agentsdk vcan [--] COMMAND [ARGS...]   (e.g. agentsdk vcan -- pytest -m vcan)", file=sys.stderr)
        return EXIT_USER_ERROR
    return subprocess.call(["bash", str(script), *rest])


_TRUST_HELP = (
    "load a robot file you trust as code: xacro expressions unchecked, files outside its package allowed "
    "(default: robot files are data)"
)


def _cmd_teleop(args: argparse.Namespace) -> int:
    """``agentsdk teleop --leader B1:R1 --follower B2:R2``: the follower follows the leader (agentsdk.teleop);
    ``--keys`` / ``--gamepad``: jog one robot from the terminal's keyboard or a gamepad (agentsdk.jog).
    """
    from .robot import connect
    from .teleop import follow_leader, parse_endpoint

    if args.keys or args.gamepad:
        return _cmd_jog(args)
    if not (args.leader and args.follower):
        raise ConfigurationError("teleop needs --leader BACKEND:ROBOT and --follower BACKEND:ROBOT, or --keys / "
                                 "--gamepad with --robot NAME to jog one robot")
    lb, lr = parse_endpoint(args.leader, "leader")
    fb, fr = parse_endpoint(args.follower, "follower")
    driver = load_behavior(args.leader_behavior) if args.leader_behavior else None

    async def session() -> Any:
        async with (connect(lb, robot=lr, realtime=True) as leader,
                    connect(fb, robot=fr, realtime=True) as follower):
            print(f"teleop: {leader.name} ({lb}) -> {follower.name} ({fb}), scale {args.scale:g}; "
                  "Ctrl-C ends (the follower holds)", file=sys.stderr, flush=True)
            async with asyncio.TaskGroup() as tg:
                follow = tg.create_task(follow_leader(leader, follower, scale=args.scale, duration=args.duration))
                if driver is not None:  # a scripted leader (a demo without a leader arm)
                    await driver.main(leader)
                    await leader.close()  # the leader stops: the follower holds and the session ends
                return await follow

    try:
        report = asyncio.run(session())
    except KeyboardInterrupt:
        print("teleop interrupted; the follower held its position", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"teleop ended ({report.ended}) after {report.commands} commands; largest tracking error "
          f"{report.max_tracking_error:.4f}; joints: {', '.join(f'{a}->{b}' for a, b in report.pairs)}")
    return 0


def _cmd_jog(args: argparse.Namespace) -> int:
    """``agentsdk teleop --keys|--gamepad [DEVICE] --robot R [--backend B]``."""
    from .robot import connect

    if args.keys and args.gamepad:
        raise ConfigurationError("choose one of --keys and --gamepad")
    if args.leader or args.follower:
        raise ConfigurationError("--keys / --gamepad jog one robot (--robot, --backend); leave out --leader/--follower")
    device: Any = None
    if args.gamepad:
        from .gamepad import find_gamepad

        device = find_gamepad() if args.gamepad == "auto" else args.gamepad
        if device is None:
            raise ConfigurationError("no gamepad found (no /dev/input/js*): plug one in, or jog with --keys")
    elif not os.isatty(sys.stdin.fileno()):
        raise ConfigurationError("--keys reads the keyboard of a terminal, but stdin is not one; run it in a "
                                 "terminal (over ssh: ssh -t), or jog from the web page (agentsdk run --web)")
    backend = args.backend or "mujoco"

    async def session() -> int:
        async with connect(backend, robot=args.robot or "arm3", realtime=True) as robot:
            if args.gamepad:
                from .gamepad import jog_with_gamepad

                print(f"jog {robot.name} ({backend}) from {device}: hold LB and use the sticks; Ctrl-C ends",
                      file=sys.stderr, flush=True)
                return await jog_with_gamepad(robot, device)
            from .keyjog import jog_with_keys

            return await jog_with_keys(robot)

    try:
        steps = asyncio.run(session())
    except KeyboardInterrupt:
        print("jog interrupted; the robot held its position", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"jog ended after {steps} steps")
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="agentsdk", description="Run robot behaviors on any backend.")
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run a behavior script's `async def main(robot)`")
    r.add_argument("behavior", help="path to a behavior .py (or a name from behaviors/)")
    r.add_argument("--backend", default=None, help="mujoco (default), pybullet, mock, can")
    r.add_argument("--robot", default=None,
                   help="robot name (`agentsdk robots --all`) or path to a .urdf, .xacro, MJCF .xml or robot.yaml")
    r.add_argument("--realtime", action="store_true", help="pace the simulation to the wall clock")
    r.add_argument("--rt-priority", type=int, metavar="N",
                   help="run with the SCHED_FIFO real-time policy at priority N (1..99; Linux, needs CAP_SYS_NICE "
                   "or an rtprio limit; a clear error says what to change where it is not permitted)")
    r.add_argument("--cpus", metavar="LIST",
                   help="pin the process to these CPUs, e.g. 2,3 (with or without --rt-priority)")
    r.add_argument("--option", "-o", action="append", metavar="KEY=VALUE", help="backend option")
    r.add_argument("--quiet", "-q", action="store_true", help="no summary, no progress bar")
    r.add_argument("--debug", action="store_true", help="show tracebacks")
    r.add_argument("--record", metavar="RUN.mcap", help="record joint states, commands, safety events and "
                   "state-machine transitions to an MCAP file (Foxglove-readable)")
    r.add_argument("--record-format", choices=("mcap", "ros2"), default="mcap",
                   help="mcap: CDR with ros2msg schemas, every agentsdk channel, replayable (default); "
                   "ros2: standard ROS 2 message types only, fully indexed, for ros2 bag play")
    r.add_argument("--record-rate", type=float, metavar="HZ",
                   help="record joint states at HZ of robot time (default 50; the control rate or more: "
                   "every tick); commands are always complete")
    r.add_argument("--plot", metavar="OUT.png", help="plot desired vs actual position per joint and the error")
    r.add_argument("--video", metavar="RUN.mp4",
                   help="render the run offscreen (no display needed) to an .mp4 or .gif file")
    r.add_argument("--video-fps", type=float, default=30.0, metavar="FPS", help="video frame rate (robot time)")
    r.add_argument("--video-size", default="640x480", metavar="WxH", help="video size in pixels")
    r.add_argument("--view", action="store_true",
                   help="show the simulation (MuJoCo viewer / PyBullet GUI; needs a display; implies --realtime)")

    r.add_argument("--web", action="store_true",
                   help="serve a live page on http://127.0.0.1:PORT: the robot in 3D, joint plots, safety state, "
                        "an e-stop button (needs agentsdk[web])")
    r.add_argument("--port", type=int, default=8080, help="port of the --web page (default 8080)")
    r.add_argument("--web-wait", action="store_true",
                   help="with --web: run the behavior when the page's Start button is pressed")
    rp = sub.add_parser("replay", help="replay a recording's commands into a fresh robot and report divergence")
    rp.add_argument("recording", help="an MCAP file written by `agentsdk run --record`")
    rp.add_argument("--backend", default=None, help="backend to replay into (default: the recorded one)")
    rp.add_argument("--robot", default=None, help="robot (default: the recorded one)")
    rp.add_argument("--option", "-o", action="append", metavar="KEY=VALUE", help="backend option")
    rp.add_argument("--record", metavar="OUT.mcap", help="record the replayed run")
    rp.add_argument("--plot", metavar="OUT.png", help="plot the replayed run over the recorded one")
    rp.add_argument("--tolerance", type=float, metavar="RAD",
                    help="exit with status 1 if any joint diverges by more than RAD")
    rp.add_argument("--quiet", "-q", action="store_true", help="no report, no progress bar")
    rp.add_argument("--debug", action="store_true", help="show tracebacks")

    rb = sub.add_parser("robots", help="list the shipped robots (--all: every robot known by name)")
    rb.add_argument("--all", action="store_true",
                    help="also list the robots of installed packages (example-robot-data, Menagerie, "
                         "agentsdk.robots entry points) with their source")
    d = sub.add_parser("describe", help="print a robot's joint tree and limits (URDF, xacro, MJCF, robot.yaml)")
    d.add_argument("robot")
    d.add_argument("--trusted", action="store_true", help=_TRUST_HELP)
    c = sub.add_parser("check", help="check a robot description and load it on each installed simulator")
    c.add_argument("robot", help="robot name, or a .urdf, .xacro, MJCF .xml or robot.yaml")
    c.add_argument("--backend", action="append", metavar="NAME",
                   help="simulator(s) to load on (default: every installed one of mujoco, pybullet)")
    c.add_argument("--strict", action="store_true", help="treat every repair as an error")
    c.add_argument("--trusted", action="store_true", help=_TRUST_HELP)
    c.add_argument("--timeout", type=float, default=300.0, help="seconds allowed per simulator load")
    t = sub.add_parser("teleop", help="teleoperation: a follower robot follows a leader's joints, or jog one robot "
                       "from the keyboard (--keys) or a gamepad (--gamepad)")
    t.add_argument("--leader", metavar="BACKEND:ROBOT", help="e.g. can:my_arm, mock:arm3")
    t.add_argument("--follower", metavar="BACKEND:ROBOT", help="e.g. mujoco:arm3")
    t.add_argument("--keys", action="store_true",
                   help="jog --robot from this terminal's keyboard (I/K J/L U/O: x y z; 1-9: joints; q quits)")
    t.add_argument("--gamepad", nargs="?", const="auto", metavar="DEVICE",
                   help="jog --robot from a gamepad (default: the first /dev/input/js*; hold LB, move the sticks)")
    t.add_argument("--robot", default=None, help="with --keys/--gamepad: the robot to jog (default arm3)")
    t.add_argument("--backend", default=None, help="with --keys/--gamepad: its backend (default mujoco)")
    t.add_argument("--scale", type=float, default=1.0, help="follower motion = scale x leader motion (default 1)")
    t.add_argument("--duration", type=float, default=None, help="end after this many seconds")
    t.add_argument("--leader-behavior", metavar="BEHAVIOR.py",
                   help="drive the leader with a behavior script (a demo without a leader arm)")
    g = sub.add_parser("graph", help="print the Mermaid diagram of a behavior's state machines")
    g.add_argument("behavior")
    g.add_argument("--run", metavar="RECORDING", default=None,
                   help="a recording (--record) of the behavior: highlight the states the run entered")
    sub.add_parser("emulate-can", help="run the MIT motor emulator (see `agentsdk emulate-can --help`)",
                   add_help=False)
    sub.add_parser("bench", help="run the benchmarks against their raw baselines (see `agentsdk bench --help`)",
                   add_help=False)
    sub.add_parser("vcan", help="run a command inside user-mode Linux with a SocketCAN vcan0 (root, Debian)",
                   add_help=False)
    sub.add_parser("serve", help="serve a robot as a ROS 2 node over DDS (see `agentsdk serve --help`)",
                   add_help=False)
    sub.add_parser("security", help="keystores for serving to operators and viewers only "
                   "(see `agentsdk security --help`)", add_help=False)
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the ``agentsdk`` command line with ``argv`` (default ``sys.argv[1:]``) and return its exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _parser()
    passthrough = {"emulate-can": lambda rest: _cmd_emulate_can(argparse.Namespace(), rest),
                   "bench": _cmd_bench, "vcan": _cmd_vcan, "serve": _cmd_serve,
                   "security": _cmd_security}
    head = argv[1:2] if argv[:1] == ["--debug"] else argv[:1]
    if head and head[0] in passthrough:
        rest = argv[argv.index(head[0]) + 1:]
        return passthrough[head[0]](rest)
    args = parser.parse_args(argv)
    debug = args.debug
    logging.basicConfig(level=logging.DEBUG if debug else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    handlers = {
        "run": _cmd_run,
        "replay": _cmd_replay,
        "robots": _cmd_robots,
        "describe": _cmd_describe,
        "check": _cmd_check,
        "graph": _cmd_graph,
        "teleop": _cmd_teleop,
    }
    try:
        return handlers[args.command](args)
    except AgentSDKError as exc:
        if debug:
            raise
        print_error(exc)
        return EXIT_BAD_BEHAVIOR if isinstance(exc, BehaviorError) else EXIT_USER_ERROR


def _cmd_serve(rest: list[str]) -> int:
    from .ros2.cli import main as serve_main

    return serve_main(rest)


def _cmd_security(rest: list[str]) -> int:
    from .ros2.cli import security_main

    return security_main(rest)


def print_error(exc: BaseException) -> None:
    """``error: ...`` on stderr, one line per problem (indented continuation lines stay as they are)."""
    for line in str(exc).splitlines() or [type(exc).__name__]:
        print(line if line[:1].isspace() else f"error: {line}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
