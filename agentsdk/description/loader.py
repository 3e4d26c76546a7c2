"""``load_description``: one entry point for URDF, xacro and MJCF files, strict or with visible repairs."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

from ..errors import DescriptionError
from .model import RobotDescription
from .urdf import load_urdf

__all__ = ["MJCF_SUFFIXES", "is_mjcf", "load_description", "repair_report"]

log = logging.getLogger("agentsdk.description")

#: file suffixes read as MuJoCo MJCF models
MJCF_SUFFIXES = (".xml", ".mjcf")
#: the largest link mass (kg) and inertia (kg·m²) a description may give; beyond, no simulator integrates it
MAX_MASS = 1e6
MAX_INERTIA = 1e6


def is_mjcf(path: Path) -> bool:
    """True when ``path`` names an MJCF model (by suffix, or an ``.xml`` whose root is ``<mujoco>``)."""
    return path.suffix.lower() in MJCF_SUFFIXES


def repair_report(description: RobotDescription, strict: bool = False) -> str:
    """The repairs as one message: a headline, then one indented line per repair."""
    n = len(description.repairs)
    what = f"{n} repair{'s' if n != 1 else ''}"
    if strict:
        head = f"{description.source}: strict mode refuses the {what} the simulators need:"
    else:
        head = (
            f"robot '{description.name}' ({description.source}): {what} so that every simulator can load it "
            "(strict: true refuses them):"
        )
    return "\n".join([head, *(f"  - {r}" for r in description.repairs)])


def _short(path: Path | str, limit: int = 120) -> str:
    """A path for a message: quoted, its middle elided when longer than ``limit`` characters."""
    text = str(path)
    return repr(text if len(text) <= limit else f"{text[: limit // 2]}...{text[-limit // 2 :]}")


def _check_physical(description: RobotDescription) -> None:
    """Refuse masses, inertias and origins no simulator can integrate (1e308, inf, NaN), naming the link."""
    for rec in description.link_records:
        inertial = rec.inertial
        if inertial is None:
            continue
        where = f"{description.source}: link '{rec.name}'"
        if not (math.isfinite(inertial.mass) and 0 <= inertial.mass <= MAX_MASS):
            raise DescriptionError(f"{where}: mass {inertial.mass:g} kg is not physical (0 to {MAX_MASS:g} kg)")
        if not all(math.isfinite(v) and abs(v) <= MAX_INERTIA for v in inertial.inertia):
            values = " ".join(f"{v:g}" for v in inertial.inertia)
            raise DescriptionError(
                f"{where}: inertia ({values}) kg·m² is not physical (each element within ±{MAX_INERTIA:g})"
            )
        if not all(math.isfinite(v) for v in (*inertial.xyz, *inertial.rpy)):
            raise DescriptionError(f"{where}: the inertial origin is not finite")


def load_description(
    path: str | Path,
    xacro_args: Mapping[str, str] | None = None,
    package_path: Sequence[Path] | None = None,
    *,
    strict: bool = False,
    warn: bool = True,
    trusted: bool = False,
    roots: Sequence[Path] = (),
) -> RobotDescription:
    """Load a ``.urdf``, ``.xacro`` or MJCF ``.xml`` file into a :class:`RobotDescription`.

    ``xacro_args`` are ``<xacro:arg>`` values (an arg the file does not use is
    an error). ``package_path`` lists extra directories searched first for
    ``package://`` URIs and ``$(find pkg)``. Parsing follows ROS's urdfdom;
    what the simulators cannot take is repaired (see
    :mod:`agentsdk.description.urdf`) and, with ``warn``, logged as one warning
    listing every repair. ``strict=True`` raises a ``DescriptionError`` listing
    the repairs instead. Broken files raise ``DescriptionError`` naming the
    file, line and element.

    Robot files are data: xacro expressions are checked before they run and
    expansion has time and memory limits (:mod:`agentsdk.description.xacro_sandbox`),
    and every file the description reaches must lie inside a package root (the
    package the file is in, the package search path, ``roots``); a refusal is a
    ``DescriptionError`` naming the file, line and construct. ``trusted=True``
    lifts the checks for a file you trust.
    """
    path = Path(path).expanduser()
    try:
        if not path.is_file():
            raise DescriptionError(
                f"robot description not found: {path}" + (" (a directory)" if path.is_dir() else "")
            )
        path = path.resolve()
    except (OSError, ValueError) as exc:  # a name too long, a NUL byte
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise DescriptionError(f"robot description {_short(path)}: cannot read: {reason}") from exc
    if is_mjcf(path):
        if xacro_args:
            raise DescriptionError(f"{path}: xacro_args {dict(xacro_args)} given, but the file is an MJCF model")
        from .mjcf import load_mjcf

        description = load_mjcf(path, trusted=trusted, roots=roots)
    else:
        description = load_urdf(path, xacro_args, package_path, trusted=trusted, roots=roots)
    _check_physical(description)
    if description.repairs:
        if strict:
            raise DescriptionError(repair_report(description, strict=True))
        if warn:
            log.warning("%s", repair_report(description))
    return description
