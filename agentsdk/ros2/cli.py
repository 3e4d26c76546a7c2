"""``agentsdk serve``: run a robot as a ROS 2 node until SIGINT/SIGTERM.

::

    agentsdk serve --robot arm3 --backend mujoco [--namespace /arm1] [--domain-id N]
    agentsdk serve --robot arm3 --namespace /left --robot arm3 --namespace /right   # two robots, one process

Time model: simulators run in **realtime** by default (paced to the wall clock, stamps in wall
time, like a ros2_control hardware driver or Gazebo at real-time factor 1). ``--lockstep`` runs
the robot in simulated time instead: it publishes ``clock`` for ``use_sim_time`` nodes and robot
time then advances only while something moves the robot (a trajectory, a goal, a stop ramp),
as fast as the CPU allows, and stands still in between (joint_states pause with it).
SIGINT/SIGTERM bring the robot to a category 1 stop (a second signal: category 0), then the
node leaves the graph; the exit code is 130/143.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import sys
from typing import Any

__all__ = ["main"]

log = logging.getLogger(__name__)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="agentsdk serve", description="Serve a robot on the ROS 2 graph (DDS) until "
                                "SIGINT/SIGTERM: joint_states, tf, robot_description, diagnostics, e-stop services, "
                                "a JointTrajectoryController with its FollowJointTrajectory action.")
    p.add_argument("--robot", action="append", help="robot name or path to .urdf/.xacro/MJCF/robot.yaml "
                   "(default arm3); repeat it, each with its own --namespace, to serve several robots")
    p.add_argument("--backend", action="append",
                   help="mujoco (default), pybullet, mock, can; one for all robots or one per --robot")
    p.add_argument("--namespace", action="append", help="ROS namespace, e.g. /arm1 (default: none); one per --robot")
    p.add_argument("--domain-id", type=int, default=None, help="DDS domain (default: $ROS_DOMAIN_ID, else 0)")
    p.add_argument("--rate", type=float, default=None,
                   help="joint_states rate in Hz, up to the control rate (default: min(control rate, 100))")
    p.add_argument("--tf-rate", type=float, default=50.0, help="tf and controller_state rate in Hz (default 50)")
    p.add_argument("--sensor-qos", action="store_true", help="publish joint_states best effort (SensorDataQoS)")
    p.add_argument("--lockstep", action="store_true",
                   help="simulated time (publishes clock); robot time advances only while the robot moves")
    p.add_argument("--interface", default=None, metavar="ADDR|NAME",
                   help="network interface to serve on (default: loopback 127.0.0.1 only)")
    p.add_argument("--peer", action="append", default=None, metavar="ADDR",
                   help="unicast discovery peer (repeatable); without it discovery uses multicast on --interface")
    p.add_argument("--lease", type=float, default=1.0,
                   help="dead-man lease in seconds: a commanding client silent this long stops the robot (default 1)")
    p.add_argument("--lease-category", type=int, default=1, choices=(0, 1),
                   help="stop category when a lease lapses (default 1: to rest, then torque off)")
    p.add_argument("--require-lease", action="store_true",
                   help="refuse commands unless a client holds a live lease (heartbeats)")
    p.add_argument("--keystore", default=None, metavar="DIR",
                   help="serve to the roles of this keystore only (agentsdk security create DIR): operators "
                   "command on its operator domain, viewers read on its viewer domain; nobody else sees the robot")
    p.add_argument("--no-deadman", action="store_true", help="turn the dead-man off (heartbeats are ignored)")
    p.add_argument("--option", "-o", action="append", metavar="KEY=VALUE", help="backend option")
    p.add_argument("--web", action="store_true", help="also serve the live web view of the (first) robot on "
                   "http://127.0.0.1:PORT: 3D, plots, safety state, an e-stop button (needs agentsdk[web])")
    p.add_argument("--port", type=int, default=8080, help="port of the --web page (default 8080)")
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    return p


def main(argv: list[str]) -> int:
    """Run ``agentsdk serve`` with ``argv``; returns the exit code."""
    from .. import cli
    from ..errors import AgentSDKError, ConfigurationError

    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        from .server import expose  # checks that cyclonedds is installed

        options = cli.parse_options(args.option)
        robots = args.robot or ["arm3"]
        backends = args.backend or ["mujoco"]
        namespaces = args.namespace or [""]
        if len(backends) not in (1, len(robots)):
            raise ConfigurationError(f"give one --backend for all robots or one per --robot ({len(robots)})")
        if len(robots) > 1 and (len(namespaces) != len(robots) or len(set(namespaces)) != len(namespaces)):
            raise ConfigurationError("serving several robots needs one distinct --namespace per --robot")
        if len(namespaces) != len(robots):
            raise ConfigurationError("give one --namespace per --robot")
        backends = backends * len(robots) if len(backends) == 1 else backends
        if args.lockstep and "can" in backends:
            raise ConfigurationError("--lockstep: a CAN robot always runs in realtime")
        realtime = None if args.lockstep else True
        if args.keystore is not None:
            from .security import load_keystore

            load_keystore(args.keystore)  # a bad keystore is a one-line error before the robot starts
            if args.domain_id is not None:
                raise ConfigurationError("--keystore sets the domains: leave out --domain-id")
        elif args.interface is not None or args.peer:
            import os

            from .dds import network_config, resolve_domain_id

            if os.environ.get("CYCLONEDDS_URI"):
                raise ConfigurationError("give either --interface/--peer or CYCLONEDDS_URI, not both")
            os.environ["CYCLONEDDS_URI"] = network_config(
                resolve_domain_id(args.domain_id), args.interface or "127.0.0.1", args.peer or [])
        lease = None if args.no_deadman else args.lease
        if args.web:
            from ..webview import WebView

            WebView.prepare()  # seconds of imports: before the robot's loop and its stall watchdog run

        async def serve(first: Any) -> None:
            from ..robot import connect

            async with contextlib.AsyncExitStack() as stack:
                served = [first]
                if args.web:
                    from ..webview import WebView

                    view = WebView.attach(first, port=args.port, on_ready=lambda v: print(
                        f"web view: {v.url}", file=sys.stderr, flush=True))
                    stack.callback(view.close)
                    await view.wait_ready()
                for robot_spec, backend in zip(robots[1:], backends[1:], strict=True):
                    served.append(await stack.enter_async_context(
                        connect(backend, robot=robot_spec, realtime=realtime, **options)))
                try:
                    for robot, ns in zip(served, namespaces, strict=True):
                        if args.keystore is not None:
                            from .security import expose_secured

                            secured = await stack.enter_async_context(expose_secured(
                                robot, args.keystore, ns, interface=args.interface or "127.0.0.1",
                                peers=args.peer or [], rate=args.rate, tf_rate=args.tf_rate,
                                sensor_qos=args.sensor_qos, lease=lease, lease_category=args.lease_category,
                                require_lease=args.require_lease))
                            print(f"serving {robot.name} ({robot.backend}) as ROS 2 node namespace "
                                  f"{secured.operator.namespace or '/'} to operators on domain "
                                  f"{secured.operator.domain_id} and viewers on domain {secured.viewer.domain_id} "
                                  "(keystore roles only); Ctrl-C stops", file=sys.stderr, flush=True)
                            continue
                        face = await stack.enter_async_context(expose(
                            robot, ns, domain_id=args.domain_id, rate=args.rate, tf_rate=args.tf_rate,
                            sensor_qos=args.sensor_qos, lease=lease, lease_category=args.lease_category,
                            require_lease=args.require_lease))
                        mode = "realtime" if robot.realtime else "lockstep"
                        print(f"serving {robot.name} ({robot.backend}, {mode}) as ROS 2 node namespace "
                              f"{face.namespace or '/'} on domain {face.domain_id}; Ctrl-C stops",
                              file=sys.stderr, flush=True)
                    await asyncio.Event().wait()
                finally:
                    # the first robot gets run_behavior's safe stop; the others the same category 1 stop here
                    for robot in served[1:]:
                        with contextlib.suppress(AgentSDKError):
                            await asyncio.shield(robot.estop(1))

        asyncio.run(cli.run_behavior(serve, backend=backends[0], robot=robots[0], realtime=realtime,
                                     options=options, install_signal_handlers=True))
    except cli.Interrupted as exc:
        print(f"stopped by {exc.signame}: {exc.detail}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130
    except AgentSDKError as exc:
        if args.debug:
            raise
        cli.print_error(exc)
        return cli.EXIT_USER_ERROR
    return 0


def _security_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="agentsdk security", description="Keystores for `agentsdk serve --keystore`: "
                                "operators command, viewers read, nobody else sees the robot (Cyclone DDS domain "
                                "tags: shared secrets, sent in clear text in discovery; see the README).")
    sub = p.add_subparsers(dest="command", required=True)
    create = sub.add_parser("create", help="create a keystore DIR with operator.json and viewer.json identities")
    create.add_argument("dir")
    create.add_argument("--domain-id", type=int, default=None, help="operators' domain (default $ROS_DOMAIN_ID or 0)")
    create.add_argument("--viewer-domain-id", type=int, default=None, help="viewers' domain (default: the next id)")
    create.add_argument("--force", action="store_true", help="replace an existing keystore's secrets")
    config = sub.add_parser("config", help="print the CYCLONEDDS_URI configuration of an identity file")
    config.add_argument("identity", help="operator.json or viewer.json of a keystore")
    config.add_argument("--interface", default="127.0.0.1", help="this host's interface (default loopback)")
    config.add_argument("--peer", action="append", default=None, help="the robot host's address (repeatable)")
    return p


def security_main(argv: list[str]) -> int:
    """Run ``agentsdk security`` with ``argv``; returns the exit code."""
    from .. import cli
    from ..errors import AgentSDKError

    args = _security_parser().parse_args(argv)
    try:
        from .security import create_keystore, identity_config, load_identity

        if args.command == "create":
            ids = create_keystore(args.dir, domain_id=args.domain_id, viewer_domain_id=args.viewer_domain_id,
                                  overwrite=args.force)
            for role, ident in ids.items():
                print(f"{role}: {args.dir}/{role}.json (domain {ident.domain_id})")
            print(f"serve with: agentsdk serve --keystore {args.dir} ...; give each client only its own identity file")
        else:
            ident = load_identity(args.identity)
            print(identity_config(ident, args.interface, args.peer or []))
            print(f"# export CYCLONEDDS_URI=<the line above> ROS_DOMAIN_ID={ident.domain_id} "
                  f"({ident.role})", file=sys.stderr)
    except AgentSDKError as exc:
        cli.print_error(exc)
        return cli.EXIT_USER_ERROR
    return 0
