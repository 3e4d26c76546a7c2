"""``agentsdk run`` and ``agentsdk replay``: a behavior with its recorder, plot, video, viewer and web page."""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Any

from ..errors import AgentSDKError, ConfigurationError
from ._behavior import EXIT_BEHAVIOR_FAILED, EXIT_INTERRUPTED, Interrupted, load_behavior, parse_options, run_behavior


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

        from ..loop import Phase

        backend = robot.backend  # the MuJoCo backend's public model and data
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
            from ..recording import Recorder

            rate: dict[str, Any] = {} if self.rate is None else {"rate": self.rate}  # default: recording.STATE_RATE
            self.recorder = Recorder.attach(bot, self.record, keep=bool(self.plot),
                                            metadata=self.metadata, format=self.record_format, **rate)
        if self.view and bot.backend.name == "mujoco":
            self.viewer = _MujocoView(bot)
        if self.web_port is not None:
            from ..webview import WebView

            self.web = WebView.attach(
                bot, port=self.web_port, on_ready=lambda v: print(f"web view: {v.url}", file=sys.stderr, flush=True)
            )
        if self.video:
            from ..video import VideoRecorder

            self.video_recorder = VideoRecorder.attach(bot, self.video, fps=self.video_fps, size=self.video_size)
        if self.progress_on:
            from ..progress import RunProgress

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
            from ..plot import plot_run

            plot_run(rec.data(), self.plot)
            lines.append(f"plot written to {self.plot}")
        return lines


def _video_args(args: argparse.Namespace) -> tuple[int, int]:
    if args.video is None:
        return (640, 480)
    from ..video import check_video_path

    check_video_path(args.video)
    w, sep, h = str(args.video_size).lower().partition("x")
    try:
        size = (int(w), int(h))
    except ValueError:
        sep = ""
    if not sep:
        raise ConfigurationError(f"--video-size expects WIDTHxHEIGHT (e.g. 640x480), got {args.video_size!r}")
    return size


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
    from ..realtime import set_realtime_priority

    set_realtime_priority(priority, cpu_list)


def _cmd_run(args: argparse.Namespace) -> int:
    from ..progress import progress_enabled
    from ..recording import robot_spec_for_metadata

    module = load_behavior(args.behavior)
    robot = args.robot or getattr(module, "ROBOT", "arm3")
    backend = args.backend or getattr(module, "BACKEND", "mujoco")
    options = parse_options(args.option)
    if args.update_rate is not None:
        options["update_rate"] = args.update_rate
    if not args.block_lockstep:
        options["block_lockstep"] = False  # (a connect option, like update_rate)
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
        from ..webview import WebView

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
        from .. import recording  # noqa: F401
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
    from ..progress import progress_enabled
    from ..recording import read_recording, replay

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
        from ..plot import plot_run

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
