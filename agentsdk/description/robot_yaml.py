"""robot.yaml on top of a description: joint-limit overrides, config checks, robot names and paths."""

from __future__ import annotations

import math
import os
from dataclasses import replace
from pathlib import Path

from ..config import JointLimitsOverride, RobotConfig, did_you_mean, load_robot_config
from ..errors import ConfigurationError, DescriptionError
from ..types import JointInfo
from .loader import load_description
from .model import RobotDescription

__all__ = ["apply_overrides", "check_config", "list_robots", "resolve_robot"]


def _robot_label(config: RobotConfig, description: RobotDescription) -> str:
    if config.source is not None:
        return str(config.source)
    return f"robot '{config.name or description.name}'"


def _unknown_joints(label: str, section: str, unknown: list[str], names: tuple[str, ...], extra: str = "") -> str:
    """One line per unknown joint name, each with a "did you mean" from the robot's joints."""
    choices = [*names, extra] if extra else list(names)
    known = ", ".join(names) + (f" (or {extra!r})" if extra else "")
    lines = []
    for u in unknown:
        hint = did_you_mean(u, choices)
        hint = hint if "did you mean" in hint else ""
        lines.append(f"{label}: {section}.{u}: unknown joint {u!r}{hint}; known joints: {known}")
    return "\n".join(lines)


def apply_overrides(description: RobotDescription, config: RobotConfig) -> tuple[JointInfo, ...]:
    """The description's joints with robot.yaml ``joint_limits`` applied.

    ``joint_limits["default"]`` applies to every joint: its acceleration/jerk
    values replace the built-in defaults, and its position/velocity/effort
    values can only tighten each joint's URDF limits. A per-joint entry
    replaces values for that joint; it may tighten but never widen a URDF
    limit (that would exceed what the hardware description allows). Every
    value must be finite (a NaN limit compares false with everything and would
    silently remove the URDF limit).
    Raises ``ConfigurationError`` for an unknown joint name or an inconsistent
    override.
    """
    limits = config.joint_limits
    names = description.joint_names
    label = _robot_label(config, description)
    unknown = [k for k in limits if k != "default" and k not in names]
    if unknown:
        raise ConfigurationError(_unknown_joints(label, "joint_limits", unknown, names, "default"))
    for key, entry in limits.items():
        for field, value in entry.model_dump(exclude_none=True).items():
            if not math.isfinite(value):  # a model built without validation (model_construct)
                raise ConfigurationError(f"{label}: joint_limits.{key}.{field}: expected a finite number, got {value}")
    default = limits.get("default", JointLimitsOverride())
    out: list[JointInfo] = []
    for j in description.joints:
        lower, upper, vel, eff = j.lower, j.upper, j.max_velocity, j.max_effort
        acc = default.max_acceleration if default.max_acceleration is not None else j.max_acceleration
        jerk = default.max_jerk if default.max_jerk is not None else j.max_jerk
        if default.min_position is not None:
            lower = max(lower, default.min_position)
        if default.max_position is not None:
            upper = min(upper, default.max_position)
        if default.max_velocity is not None:
            vel = min(vel, default.max_velocity)
        if default.max_effort is not None:
            eff = min(eff, default.max_effort)

        own = limits.get(j.name)
        if own is not None:
            where = f"{label}: joint_limits.{j.name}"
            if own.min_position is not None:
                if not own.min_position >= j.lower:
                    raise ConfigurationError(
                        f"{where}.min_position={own.min_position:g} is below the URDF lower limit {j.lower:g}"
                    )
                lower = own.min_position
            if own.max_position is not None:
                if not own.max_position <= j.upper:
                    raise ConfigurationError(
                        f"{where}.max_position={own.max_position:g} is above the URDF upper limit {j.upper:g}"
                    )
                upper = own.max_position
            if own.max_velocity is not None:
                if not own.max_velocity <= j.max_velocity:
                    raise ConfigurationError(
                        f"{where}.max_velocity={own.max_velocity:g} is above the URDF velocity limit {j.max_velocity:g}"
                    )
                vel = own.max_velocity
            if own.max_effort is not None:
                if not own.max_effort <= j.max_effort:
                    raise ConfigurationError(
                        f"{where}.max_effort={own.max_effort:g} is above the URDF effort limit {j.max_effort:g}"
                    )
                eff = own.max_effort
            if own.max_acceleration is not None:
                acc = own.max_acceleration
            if own.max_jerk is not None:
                jerk = own.max_jerk
        if not lower <= upper:
            raise ConfigurationError(
                f"{label}: joint_limits leave joint '{j.name}' an empty range "
                f"(min_position {lower:g} > max_position {upper:g})"
            )
        out.append(
            replace(
                j,
                lower=float(lower),
                upper=float(upper),
                max_velocity=float(vel),
                max_effort=float(eff),
                max_acceleration=float(acc),
                max_jerk=float(jerk),
            )
        )
    return tuple(out)


def check_config(config: RobotConfig, description: RobotDescription) -> tuple[JointInfo, ...]:
    """Check that robot.yaml joint names exist and initial positions are within limits.

    Returns the joints with overrides applied (see :func:`apply_overrides`).
    """
    joints = apply_overrides(description, config)
    names = description.joint_names
    label = _robot_label(config, description)
    problems = []
    gravity = config.gravity_compensation if isinstance(config.gravity_compensation, dict) else {}
    for section, keys in (
        ("gains", config.gains),
        ("initial_positions", config.initial_positions),
        ("gravity_compensation", gravity),
    ):
        unknown = [k for k in keys if k not in names and not (section != "initial_positions" and k == "default")]
        if unknown:
            extra = "default" if section != "initial_positions" else ""
            problems.append(_unknown_joints(label, section, unknown, names, extra))
    if problems:
        raise ConfigurationError("\n".join(problems))
    urdf = {j.name: j for j in description.joints}
    for j in joints:
        q = config.initial_positions.get(j.name)
        if q is not None and not (math.isfinite(q) and j.within(q)):
            raise ConfigurationError(
                f"{label}: initial_positions.{j.name}={q:g} is outside the joint limits [{j.lower:g}, {j.upper:g}]"
            )
        # the implicit start (the description's default pose, else 0) must not be outside limits that
        # robot.yaml narrowed: the robot would start outside them and be driven in by the safety layer
        start = description.default_positions.get(j.name, 0.0)
        own = urdf.get(j.name)
        if q is None and own is not None and own.within(start) and not j.within(start):
            raise ConfigurationError(
                f"{label}: joint {j.name!r} starts at {start:g} rad, outside its joint_limits "
                f"[{j.lower:g}, {j.upper:g}]; set initial_positions.{j.name} inside them"
            )
    return joints


def default_robots_dir() -> Path:
    import agentsdk.robots as robots

    return Path(robots.__file__).resolve().parent


def list_robots(robots_dir: Path | None = None) -> list[str]:
    """Names of the robots shipped in ``robots_dir`` (default: the ``robots`` package): dirs with a robot.yaml."""
    directory = Path(robots_dir) if robots_dir is not None else default_robots_dir()
    if not directory.is_dir():
        return []
    return sorted(d.name for d in directory.iterdir() if (d / "robot.yaml").is_file())


def _installed_robot(name: str, directory: Path) -> Path:
    """The description of robot ``name`` from an installed package (see :mod:`.catalog`), or raise."""
    from .catalog import installed_robots

    entries = installed_robots(directory)
    for entry in entries:
        if entry.name == name:
            if entry.path is None:
                raise ConfigurationError(f"robot '{name}' (entry point of {entry.provider or '?'}) is broken: "
                                         f"{entry.problem}")
            return entry.path
    shipped = [e.name for e in entries if e.source == "shipped"]
    others = sorted((e.name for e in entries if e.source != "shipped"), key=str.lower)
    hint = did_you_mean(name, [e.name for e in entries])
    hint = f"{hint} " if "did you mean" in hint else "; "
    installed = f"; installed: {', '.join(others)}" if others else ""
    raise ConfigurationError(
        f"unknown robot '{name}'{hint}shipped robots: {', '.join(shipped) if shipped else '(none)'} "
        f"(in {directory}){installed} (`agentsdk robots --all` shows where each comes from); "
        "or pass a path to a .urdf, .xacro, MJCF .xml or robot.yaml"
    )


_DESCRIPTION_SUFFIXES = (".urdf", ".xacro", ".xml", ".mjcf")
_CONFIG_SUFFIXES = (".yaml", ".yml")


def resolve_robot(
    spec: str | Path, robots_dir: Path | None = None, *, strict: bool | None = None, trusted: bool | None = None
) -> tuple[RobotConfig, RobotDescription]:
    """Turn a robot name or path into a validated ``(RobotConfig, RobotDescription)``.

    ``spec`` is a robot name from ``robots_dir`` (default: the shipped
    ``robots/`` directory), or a path to a ``.urdf``, ``.xacro``, MJCF
    ``.xml``, ``robot.yaml`` or a directory holding a ``robot.yaml``. A bare
    description gets a default ``RobotConfig``. ``strict`` (default: robot.yaml
    ``strict``) turns the loader's repairs into a ``DescriptionError``; without
    it they are logged as one warning. ``trusted`` (default: robot.yaml
    ``trusted``) lifts the checks that load a robot file as data (see
    :func:`load_description`); a robot named from ``robots_dir`` may reach the
    files in that directory. Raises ``ConfigurationError`` (or its subclass
    ``DescriptionError``) naming what is wrong.
    """
    directory = Path(robots_dir) if robots_dir is not None else default_robots_dir()
    text = os.fspath(spec)
    bare_name = (
        isinstance(spec, str)
        and "/" not in text
        and os.sep not in text
        and not text.lower().endswith(_DESCRIPTION_SUFFIXES + _CONFIG_SUFFIXES)
    )
    path = Path(text).expanduser()
    roots: list[Path] = []
    if bare_name:
        candidate = directory / text / "robot.yaml"
        if text and candidate.is_file():
            path = candidate
            roots.append(directory)
        elif not path.exists():
            path = _installed_robot(text, directory)
    try:
        if path.is_dir():
            if not (path / "robot.yaml").is_file():
                raise ConfigurationError(f"{path} is a directory without a robot.yaml")
            path = path / "robot.yaml"
        if not path.exists():
            raise ConfigurationError(f"robot description not found: {path}")
    except (OSError, ValueError) as exc:  # a name too long for the filesystem, a NUL byte
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        shown = text if len(text) <= 120 else f"{text[:60]}...{text[-60:]}"
        raise ConfigurationError(f"robot {shown!r}: cannot read: {reason}") from exc

    lower = path.name.lower()
    if lower.endswith(_CONFIG_SUFFIXES):
        config = load_robot_config(path)
        if strict is not None and strict != config.strict:
            config = config.model_copy(update={"strict": strict})
        if trusted is not None and trusted != config.trusted:
            config = config.model_copy(update={"trusted": trusted})
        try:
            config.description_path.is_file()
        except (OSError, ValueError) as exc:  # a name too long for the filesystem: say which file named it
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            shown = config.description if len(config.description) <= 120 else f"{config.description[:60]}..."
            raise DescriptionError(f"{path}: description: {shown!r}: cannot read: {reason}") from exc
        description = load_description(
            config.description_path, config.xacro_args, strict=config.strict, trusted=config.trusted, roots=roots
        )
    elif lower.endswith(_DESCRIPTION_SUFFIXES):
        description = load_description(path, strict=bool(strict), trusted=bool(trusted))
        config = RobotConfig(
            name=description.name,
            description=path.name,
            base_dir=path.resolve().parent,
            strict=bool(strict),
            trusted=bool(trusted),
        )
    else:
        raise ConfigurationError(f"{path}: expected a .urdf, .xacro, MJCF .xml or robot.yaml file")
    check_config(config, description)
    return config, description
