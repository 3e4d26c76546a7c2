"""``agentsdk teleop``: a follower following a leader, or jogging from the keyboard or a gamepad."""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
from typing import Any

from ..errors import ConfigurationError
from ._behavior import EXIT_INTERRUPTED, load_behavior


def _cmd_teleop(args: argparse.Namespace) -> int:
    """``agentsdk teleop --leader B1:R1 --follower B2:R2``: the follower follows the leader (agentsdk.teleop);
    ``--keys`` / ``--gamepad``: jog one robot from the terminal's keyboard or a gamepad (agentsdk.jog).
    """
    from ..robot import connect
    from ..teleop import follow_leader, parse_endpoint

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
    from ..robot import connect

    if args.keys and args.gamepad:
        raise ConfigurationError("choose one of --keys and --gamepad")
    if args.leader or args.follower:
        raise ConfigurationError("--keys / --gamepad jog one robot (--robot, --backend); leave out --leader/--follower")
    device: Any = None
    if args.gamepad:
        from ..gamepad import find_gamepad

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
                from ..gamepad import jog_with_gamepad

                print(f"jog {robot.name} ({backend}) from {device}: hold LB and use the sticks; Ctrl-C ends",
                      file=sys.stderr, flush=True)
                return await jog_with_gamepad(robot, device)
            from ..keyjog import jog_with_keys

            return await jog_with_keys(robot)

    try:
        steps = asyncio.run(session())
    except KeyboardInterrupt:
        print("jog interrupted; the robot held its position", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"jog ended after {steps} steps")
    return 0
