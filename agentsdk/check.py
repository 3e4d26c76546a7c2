"""``agentsdk check ROBOT``: check_urdf plus a doctor, the first stop with a new robot.

:func:`check_robot` loads the description (URDF, xacro, MJCF or robot.yaml)
and reports the joint tree, every repair and default, the link masses, the
start pose, the self-collision pairs left out and why, then loads the robot on
each installed simulator, each in its own process (:mod:`agentsdk.probe`), so
a simulator that crashes cannot take the check down with it. It returns the
report lines and the problems (one line each); the CLI prints them and exits 1
when there is a problem.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import AgentSDKError, BackendUnavailableError

if TYPE_CHECKING:
    from .config import RobotConfig
    from .description.model import RobotDescription
    from .types import JointInfo

__all__ = ["CheckReport", "check_robot"]

SIMULATORS = ("mujoco", "pybullet")


@dataclass
class CheckReport:
    """What ``agentsdk check`` found: ``lines`` to show, ``problems`` (one line each; any makes it fail)."""

    lines: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when nothing failed."""
        return not self.problems


def _wrap(items: Sequence[str], indent: str = "    ", width: int = 110) -> list[str]:
    out: list[str] = []
    line = indent
    for item in items:
        piece = item if line == indent else ", " + item
        if len(line) + len(piece) > width and line != indent:
            out.append(line + ",")
            line = indent + item
        else:
            line += piece
    if line != indent:
        out.append(line)
    return out


def _installed(names: Sequence[str], notes: list[str]) -> list[str]:
    """The backends among ``names`` that import here; the others are noted with their install hint."""
    from .registry import load_backend

    usable = []
    for name in names:
        try:
            load_backend(name)
        except BackendUnavailableError as exc:
            notes.append(f"  {name:9s} – {exc}")
        else:
            usable.append(name)
    return usable


def _broken_plugins() -> list[str]:
    """Third-party backends (entry points other than the project's own) that fail to import."""
    from .registry import BUILTIN_BACKENDS, broken_backends

    return [reason for name, reason in broken_backends().items() if name not in BUILTIN_BACKENDS]


def _following_problem(r: dict[str, object]) -> str | None:
    """The following error a probe's ``follow`` trial latched (the joint, its error and window), or None."""
    errors = r.get("following_errors")
    if isinstance(errors, list) and errors:
        return str(errors[0]).removeprefix("following error: ")
    return None


def _following_peak(r: dict[str, object], key: str = "following_peak") -> str:
    """The largest following error of the trial and its joint, e.g. ``0.0021 rad or m, joint2``; "" if not measured.

    ``key``: ``following_peak`` (the whole trial) or ``move_peak`` (while the move ran: the tracking error).
    """
    peak, names = r.get(key), r.get("joints")
    if not isinstance(peak, list) or not peak or not isinstance(names, list):
        return ""
    k = max(range(len(peak)), key=lambda i: float(peak[i]))
    return f"{float(peak[k]):.2g} rad or m, {names[k]}"


def _gain_source(desc: RobotDescription, config: RobotConfig, joints: Sequence[JointInfo]) -> str:
    """Where the servo gains come from (the rule of :attr:`agentsdk.backend.Backend.servo_gains`), in words."""
    explicit = [j.name for j in joints if config.gains_for(j.name) is not None]
    declared = [j.name for j in joints if j.name not in explicit and j.name in desc.declared_gains]
    model = len(joints) - len(explicit) - len(declared)
    parts = []
    if explicit:
        parts.append("robot.yaml" + ("" if len(explicit) == len(joints) else f" for {len(explicit)}"))
    if declared:
        parts.append(
            "the description's position actuators (kp, kv; lowered only where a simulator's timestep requires)"
            + ("" if len(declared) == len(joints) else f" for {len(declared)}")
        )
    if model:
        every = model == len(joints)
        parts.append("from the model, agentsdk.dynamics.model_gains" + ("" if every else f" for {model}"))
    return "; ".join(parts)


def check_robot(
    robot: str | Path,
    *,
    backends: Sequence[str] | None = None,
    strict: bool | None = None,
    timeout: float = 300.0,
    trusted: bool | None = None,
) -> CheckReport:
    """Check ``robot`` (see the module docstring); ``backends`` defaults to the installed simulators."""
    from .description import apply_overrides, resolve_robot
    from .description.collision import for_robot, from_mjcf

    report = CheckReport()
    out = report.lines
    try:
        config, desc = resolve_robot(robot, strict=strict, trusted=trusted)
        joints = apply_overrides(desc, config)
    except AgentSDKError as exc:
        report.problems.append(" ".join(str(exc).split()) if "\n" not in str(exc) else str(exc).splitlines()[0])
        report.problems.extend(line.strip() for line in str(exc).splitlines()[1:] if line.strip())
        return report

    try:
        collision = from_mjcf(desc, config) if desc.format == "mjcf" else for_robot(desc, config)
    except AgentSDKError as exc:
        report.problems.append(f"self-collision model: {' '.join(str(exc).split())}")
        collision = None
    repairs = [*desc.repairs, *(collision.repairs if collision is not None else ())]

    kind = {"urdf": "URDF", "mjcf": "MJCF"}[desc.format]
    out.append(f"robot '{desc.name}' ({kind}): {desc.source}")
    out.append("")
    out.append("joint tree:")
    out.extend("  " + line for line in desc.tree_lines())
    out.append("")
    if repairs:
        out.append(f"repairs ({len(repairs)}, so that every simulator can load it; strict: true refuses them):")
        out.extend(f"  - {r}" for r in repairs)
    else:
        out.append("repairs: none")
    if desc.defaults:
        out.append("defaults (values the description leaves out):")
        out.extend(f"  - {r}" for r in desc.defaults)
    out.append("")

    moving = [rec for rec in desc.link_records if rec.mass > 0]
    out.append(f"masses: {desc.total_mass():.4g} kg in {len(moving)} of {len(desc.link_records)} links (kg):")
    out.extend(_wrap([f"{rec.name} {rec.mass:.4g}" for rec in moving]))
    out.append("")

    from .description.start import start_pose

    try:
        pose = start_pose(desc, config, joints)
    except AgentSDKError as exc:
        report.problems.append(f"start pose: {' '.join(str(exc).split())}")
        pose = None
    if pose is not None:
        out.append(f"start pose ({pose.summary()}):")
        entries = [
            f"{j.name}={pose.positions[j.name]:g}"
            + (f" (clipped from {pose.clipped[j.name]:g})" if j.name in pose.clipped else "")
            for j in joints
        ]
        out.extend(_wrap(entries) or ["    (no commanded joints)"])
        if pose.clipped:
            out.append(f"  note: {', '.join(pose.clipped)} start clipped into their limits; "
                       "set initial_positions or initial_group_state in robot.yaml")
        out.append("")
    from .description.mobility import report_lines

    out.extend(report_lines(desc, config, pose))
    gc = [j.name for j in joints if not config.gravity_compensation_for(j.name)]
    out.append("gravity compensation: " + ("on for every joint" if not gc else f"off for {', '.join(gc)}"))
    out.append("inverse-dynamics feed-forward of the motion: " + (
        "on" if config.inverse_dynamics else "off (robot.yaml inverse_dynamics: false)"))
    out.append("")

    if collision is not None:
        mode = "the model's own contact settings" if desc.format == "mjcf" else collision.mode
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(collision.reasons().items())) or "none"
        out.append(
            f"self-collision ({mode}): {len(collision.pairs)} link pairs collide; "
            f"{len(collision.excluded)} left out ({reasons})"
        )
        if collision.srdf is not None:
            out.append(f"  SRDF: {collision.srdf}")
        by_reason: dict[str, list[str]] = {}
        for (a, b), reason in sorted(collision.excluded.items()):
            by_reason.setdefault(reason, []).append(f"{a}–{b}")
        for reason, pairs in sorted(by_reason.items()):
            out.append(f"  left out, {reason} ({len(pairs)}):")
            out.extend(_wrap(pairs, indent="    "))
        out.append("")

    from .probe import ProbePool

    not_installed: list[str] = []
    chosen = list(backends) if backends else _installed(SIMULATORS, not_installed)
    out.append("simulators (each in its own process):")
    if not chosen:
        out.append("  none installed")
    out.extend(not_installed)
    report.problems.extend(_broken_plugins())
    jobs = [{"robot": str(robot), "backend": b, "duration": 0.05, "options": {}, "behavior": "follow"}
            for b in chosen]
    options = {k: v for k, v in (("strict", strict), ("trusted", trusted)) if v is not None}
    for job in jobs:
        job["options"] = dict(options)
    with ProbePool(workers=min(2, max(1, len(jobs))), timeout=timeout) as pool:
        results = pool.run(jobs)
    for backend, r in zip(chosen, results, strict=True):
        if r.get("loaded"):
            n, seconds = len(r["joints"]), r.get("seconds", math.nan)
            size = f"({n} joint{'s' if n != 1 else ''}, {seconds:.2f} s)"
            lag = _following_problem(r)
            if lag is not None:
                # a joint that does not follow its command is never a pass, whatever else ran
                out.append(f"  {backend:9s} ✗ loads, but does not follow: {lag} {size}")
                report.problems.append(f"{backend}: does not follow its commands: {lag}")
                continue
            if not r.get("ok"):
                # a run that ended in a fault or e-stop (a sensor fault: a joint running away) is never a pass
                run_error = " ".join(str(r.get("run_error")).split())
                out.append(f"  {backend:9s} ✗ loads, then {run_error} {size}")
                report.problems.append(f"{backend}: {run_error}")
                continue
            note = "loads, holds and moves"
            peak, in_motion = _following_peak(r), _following_peak(r, "move_peak")
            if peak:
                note += f" (following error ≤ {peak}" + (f"; while moving ≤ {in_motion})" if in_motion else ")")
            out.append(f"  {backend:9s} ✓ {note} {size}")
        else:
            out.append(f"  {backend:9s} ✗ {r.get('error_type')}")
            report.problems.append(f"{backend}: {' '.join(str(r.get('error')).split())}")
    source = _gain_source(desc, config, joints)
    for backend, r in zip(chosen, results, strict=True):
        if not r.get("gains"):
            continue
        out.append("")
        out.append(f"servo gains on {backend} ({source}; p N·m/rad, d N·m·s/rad):")
        gain_pairs = zip(r["joints"], r["gains"], strict=True)
        out.extend(_wrap([f"{name} p={g[0]:.4g} d={g[1]:.4g}" for name, g in gain_pairs]))
    return report
