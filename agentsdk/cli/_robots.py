"""``agentsdk robots``, ``describe``, ``check`` and ``graph``: looking at robots and behaviors."""

from __future__ import annotations

import argparse
import sys

from ..errors import AgentSDKError, ConfigurationError
from ._behavior import EXIT_BEHAVIOR_FAILED, load_behavior

_TRUST_HELP = (
    "load a robot file you trust as code: xacro expressions unchecked, files outside its package allowed "
    "(default: robot files are data)"
)


def _cmd_robots(args: argparse.Namespace) -> int:
    from ..description import list_robots, resolve_robot

    if getattr(args, "all", False):
        from ..description.catalog import installed_robots

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
    from ..description import apply_overrides, resolve_robot

    config, desc = resolve_robot(args.robot, trusted=True if args.trusted else None)
    joints = apply_overrides(desc, config)
    print(f"robot name is: {desc.name}")
    print(f"---------- Successfully parsed {desc.source} ----------")
    for line in desc.tree_lines():
        print(line)
    print()
    from ..description.mobility import report_lines
    from ..description.start import start_pose

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
    from ..check import check_robot

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
    from ..statemachine import find_machines

    module = load_behavior(args.behavior)
    machines = find_machines(module)
    if not machines:
        raise ConfigurationError(f"{args.behavior} defines no StateMachine")
    visited: list[str] | None = None
    if args.run is not None:  # highlight the states a recorded run entered
        from ..recording import read_recording

        transitions = read_recording(args.run).transitions
        visited = [f"{t['machine']}/{t['target']}" for t in transitions if t.get("target")]
    for i, machine in enumerate(machines):
        if i:
            print()
        print(machine.mermaid(visited=visited))
    return 0
