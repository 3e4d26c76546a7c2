"""Robots by name: the shipped robots, then descriptions found in installed packages.

``agentsdk run --robot NAME`` and ``connect(robot=NAME)`` look a bare name up, in
this order (the first source that has it wins):

1. ``shipped``: a directory with a ``robot.yaml`` in the ``robots`` package (``arm3``, ...);
2. ``entry point``: any installed distribution declaring an ``agentsdk.robots``
   entry point. Its name is the robot's name; it loads to a path (``str`` or
   :class:`~pathlib.Path`) of a ``.urdf``, ``.xacro``, MJCF ``.xml`` or
   ``robot.yaml``, or to a callable returning one. A broken plugin is reported,
   never breaks the others;
3. ``example-robot-data``: every URDF it ships, named after the file without a
   ``_robot`` suffix (``ur5``, ``ur10``, ``panda``, ``z1``, ``so100``...);
4. ``menagerie``: MuJoCo Menagerie models under ``$MENAGERIE_ROOT`` or in
   robot_descriptions' cache (``$ROBOT_DESCRIPTIONS_CACHE``, default
   ``~/.cache/robot_descriptions/mujoco_menagerie``): every top-level model XML
   of a robot directory except the ``scene*`` files, named after the file
   (``ur5e``, ``panda``...).

Two files of one source with the same name are told apart by the directory
they come from: ``<directory>_<name>`` (``anymal_b_simple_description`` ->
``anymal_b_simple_anymal``). Looking up walks directories and reads nothing
else, so listing is cheap; a description is only loaded when it is used.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

__all__ = ["ENTRY_POINT_GROUP", "RobotEntry", "find_robot", "installed_robots"]

log = logging.getLogger("agentsdk.description")

#: the entry-point group third-party packages declare robots in
ENTRY_POINT_GROUP = "agentsdk.robots"
_SOURCES_ORDER = ("shipped", "entry point", "example-robot-data", "menagerie")


@dataclass(frozen=True)
class RobotEntry:
    """One robot known by name: where its description (or robot.yaml) is and where it came from."""

    name: str
    #: ``shipped``, ``entry point``, ``example-robot-data`` or ``menagerie``
    source: str
    #: the robot.yaml, URDF, xacro or MJCF file (None when an entry point failed to load)
    path: Path | None
    #: why the entry could not be loaded ("" when it can)
    problem: str = ""
    #: the distribution that declared it (entry points)
    provider: str = ""


def _shipped(robots_dir: Path) -> Iterator[RobotEntry]:
    if not robots_dir.is_dir():
        return
    for d in sorted(robots_dir.iterdir()):
        if (d / "robot.yaml").is_file():
            yield RobotEntry(d.name, "shipped", d / "robot.yaml")


def _entry_points() -> Iterator[RobotEntry]:
    for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        provider = ep.dist.name if ep.dist is not None else ""
        try:
            target = ep.load()
            value = target() if callable(target) else target
            if not isinstance(value, str | os.PathLike):
                raise TypeError(f"expected a path, got {type(value).__name__}")
            path = Path(os.fspath(value)).expanduser()
            if not path.exists():
                raise FileNotFoundError(f"{path} does not exist")
        except Exception as exc:  # one broken plugin must not break the others
            log.debug("robot entry point %s is broken", ep.value, exc_info=True)
            yield RobotEntry(ep.name, "entry point", None, f"{ep.value}: {type(exc).__name__}: {exc}", provider)
            continue
        yield RobotEntry(ep.name, "entry point", path, "", provider)


def example_robot_data_dir() -> Path | None:
    """The ``robots`` directory of the installed example-robot-data distribution, or None."""
    try:
        dist = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError:
        return None
    root = Path(str(dist.locate_file("cmeel.prefix/share/example-robot-data/robots")))
    return root if root.is_dir() else None


def _dedupe(found: list[tuple[str, str, Path]], source: str) -> Iterator[RobotEntry]:
    """``(name, directory, path)`` triples to entries with unique names.

    A short name (``ur3`` for ``ur3_robot.urdf``) clashing with another file falls back to the file's
    stem; names still clashing (the same file name in two directories) get the directory as prefix.
    """

    def clashes(names: list[str]) -> set[str]:
        return {n for n in names if names.count(n) > 1}

    names = [name for name, _, _ in found]
    twice = clashes(names)
    names = [path.stem if name in twice and path.stem != name else name for (name, _, path) in found]
    twice = clashes(names)
    for name, (_, directory, path) in zip(names, found, strict=True):
        if name in twice:
            name = f"{directory.removesuffix('_description')}_{name}"
        yield RobotEntry(name, source, path)


def _example_robot_data() -> Iterator[RobotEntry]:
    root = example_robot_data_dir()
    if root is None:
        return
    found: list[tuple[str, str, Path]] = []
    for pkg in sorted(root.iterdir()):
        if not pkg.is_dir():
            continue
        for sub in ("urdf", "robots"):
            for urdf in sorted((pkg / sub).glob("*.urdf")):
                found.append((urdf.stem.removesuffix("_robot"), pkg.name, urdf))
    yield from _dedupe(found, "example-robot-data")


def menagerie_roots() -> list[Path]:
    """Directories searched for MuJoCo Menagerie models (existing ones only)."""
    candidates = []
    if os.environ.get("MENAGERIE_ROOT"):
        candidates.append(Path(os.environ["MENAGERIE_ROOT"]).expanduser())
    cache = os.environ.get("ROBOT_DESCRIPTIONS_CACHE", "~/.cache/robot_descriptions")
    candidates.append(Path(cache).expanduser() / "mujoco_menagerie")
    return [c for c in candidates if c.is_dir()]


def _menagerie() -> Iterator[RobotEntry]:
    found: list[tuple[str, str, Path]] = []
    for root in menagerie_roots():
        for robot_dir in sorted(root.iterdir()):
            if not robot_dir.is_dir() or robot_dir.name.startswith("."):
                continue
            for xml in sorted(robot_dir.glob("*.xml")):
                if not xml.stem.startswith("scene"):
                    found.append((xml.stem, robot_dir.name, xml))
    yield from _dedupe(found, "menagerie")


def installed_robots(robots_dir: Path | None = None) -> list[RobotEntry]:
    """Every robot known by name, in lookup order; a name hidden by an earlier source is left out."""
    from .robot_yaml import default_robots_dir

    directory = Path(robots_dir) if robots_dir is not None else default_robots_dir()
    sources: list[Callable[[], Iterator[RobotEntry]]] = [
        lambda: _shipped(directory), _entry_points, _example_robot_data, _menagerie,
    ]
    seen: set[str] = set()
    out: list[RobotEntry] = []
    for source in sources:
        for entry in source():
            if entry.name not in seen:
                seen.add(entry.name)
                out.append(entry)
    return out


def find_robot(name: str, robots_dir: Path | None = None) -> RobotEntry | None:
    """The entry named ``name`` (the first source that has it), or None."""
    return next((e for e in installed_robots(robots_dir) if e.name == name), None)
