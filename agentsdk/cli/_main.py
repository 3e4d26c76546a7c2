"""The ``agentsdk`` argument parser and :func:`main`, which dispatches to one command module."""

from __future__ import annotations

import argparse
import logging
import sys

from ..errors import AgentSDKError
from ._behavior import EXIT_BAD_BEHAVIOR, EXIT_USER_ERROR, BehaviorError, print_error
from ._robots import _TRUST_HELP, _cmd_check, _cmd_describe, _cmd_graph, _cmd_robots
from ._run import _cmd_replay, _cmd_run
from ._teleop import _cmd_teleop
from ._tools import _cmd_bench, _cmd_emulate_can, _cmd_security, _cmd_serve, _cmd_vcan


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
    r.add_argument("--update-rate", type=float, metavar="HZ",
                   help="control rate (default: robot.yaml update_rate), e.g. lower for an emulated bus in a VM")
    r.add_argument("--no-block-lockstep", dest="block_lockstep", action="store_false",
                   help="in lockstep, run every tick on its own: no blocks of uneventful ticks (the same results, "
                   "bit for bit; blocks are the default where they can run: MuJoCo)")
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
