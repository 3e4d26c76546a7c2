"""ROS-style ``package://`` and ``$(find pkg)`` resolution.

* ``package://pkg/rel/path`` - ``pkg`` is searched, in order, in the
  directories given by ``package_path``, ``$AGENTSDK_PACKAGE_PATH`` and
  ``$ROS_PACKAGE_PATH`` (``os.pathsep``-separated). A directory ``D`` provides
  ``pkg`` if ``D/pkg`` exists, if ``D`` itself is named ``pkg``, if
  ``D/package.xml`` declares ``<name>pkg</name>``, or (like ``rospack``) if a
  ``package.xml`` declaring ``pkg`` is found a few levels below ``D``. Last,
  the description's own directory and its parents are tried (a parent named
  ``pkg``, declaring ``pkg`` in its ``package.xml``, or holding a ``pkg``
  directory). ``package:///pkg/path`` (an extra slash, written by some
  exporters) is read as ``package://pkg/path``.
* ``file:///abs/path`` and absolute paths are used as is.
* relative paths (and ``file://rel/path``) are relative to the directory of the
  URDF/xacro file.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Sequence
from pathlib import Path
from urllib.parse import unquote, urlparse
from urllib.request import url2pathname

from lxml import etree

__all__ = ["PACKAGE_PATH_ENV_VARS", "Resolver", "find_package", "package_search_path", "search_path_text"]

log = logging.getLogger("agentsdk.description")

#: environment variables searched (in this order) for ``package://`` URIs
PACKAGE_PATH_ENV_VARS: tuple[str, ...] = ("AGENTSDK_PACKAGE_PATH", "ROS_PACKAGE_PATH")

_CRAWL_DEPTH = 3  # how deep to look for package.xml below a search-path entry
_CRAWL_MAX_DIRS = 5000
_IGNORE_MARKERS = ("CATKIN_IGNORE", "COLCON_IGNORE", "AMENT_IGNORE")


def _manifest_parser() -> etree.XMLParser:
    return etree.XMLParser(resolve_entities=False, no_network=True, remove_comments=True)


def package_search_path(extra: Sequence[str | Path] | None = None) -> list[tuple[str, Path]]:
    """The ``package://`` search path as ``(origin, directory)`` pairs, highest priority first.

    ``origin`` is ``"package_path"`` for ``extra`` entries, else the name of the
    environment variable the directory came from.
    """
    out: list[tuple[str, Path]] = [("package_path", Path(p).expanduser()) for p in (extra or ())]
    for var in PACKAGE_PATH_ENV_VARS:
        for entry in os.environ.get(var, "").split(os.pathsep):
            if entry.strip():
                out.append((var, Path(entry.strip()).expanduser()))
    return out


def _declared_package_name(directory: Path) -> str | None:
    manifest = directory / "package.xml"
    if not manifest.is_file():
        return None
    try:
        root = etree.parse(str(manifest), _manifest_parser()).getroot()
    except (OSError, etree.XMLSyntaxError):
        log.debug("ignoring unreadable %s", manifest)
        return None
    name = root.findtext("name")
    return name.strip() if name else None


def _crawl_for_package(top: Path, package: str) -> Path | None:
    """Breadth-first search below ``top`` for a package.xml declaring ``package`` (like rospack)."""
    frontier = [top]
    visited = 0
    for _depth in range(_CRAWL_DEPTH):
        next_frontier: list[Path] = []
        for directory in frontier:
            try:
                entries = sorted(p for p in directory.iterdir() if p.is_dir() and not p.name.startswith("."))
            except OSError:
                continue
            for sub in entries:
                visited += 1
                if visited > _CRAWL_MAX_DIRS:
                    return None
                if any((sub / marker).exists() for marker in _IGNORE_MARKERS):
                    continue
                declared = _declared_package_name(sub)
                if declared == package:
                    return sub
                if declared is None:  # rospack does not descend into packages
                    next_frontier.append(sub)
        frontier = next_frontier
    return None


def find_package(
    package: str,
    package_path: Sequence[str | Path] | None = None,
    near: str | Path | None = None,
) -> Path | None:
    """Directory of ROS-style package ``package``, or None.

    Searches ``package_path``, ``$AGENTSDK_PACKAGE_PATH``, ``$ROS_PACKAGE_PATH``,
    then ``near`` (a file or directory) and its parents; see the module docstring.
    """
    search = [d for _, d in package_search_path(package_path)]
    for directory in search:
        if not directory.is_dir():
            continue
        if (directory / package).is_dir():
            return (directory / package).resolve()
        if directory.name == package or _declared_package_name(directory) == package:
            return directory.resolve()
    for directory in search:
        if directory.is_dir():
            found = _crawl_for_package(directory, package)
            if found is not None:
                return found.resolve()
    if near is not None:
        start = Path(near).resolve()
        if not start.is_dir():
            start = start.parent
        for directory in (start, *start.parents):
            if directory.name == package or _declared_package_name(directory) == package:
                return directory
            if (directory / package).is_dir():
                return directory / package
    return None


def search_path_text(package_path: Sequence[str | Path] | None, near: Path) -> str:
    """The package search path in words, for error messages."""
    entries = package_search_path(package_path)
    described = ", ".join(f"{d} (from {origin})" for origin, d in entries)
    if not described:
        described = f"none ({' and '.join(PACKAGE_PATH_ENV_VARS)} are empty)"
    return f"search path: {described}; then {near} and its parents"


class Resolver:
    """Maps URDF resource URIs to absolute paths, caching package lookups."""

    def __init__(self, base_dir: Path, package_path: Sequence[str | Path] | None) -> None:
        self.base_dir = base_dir
        self.package_path = list(package_path or ())
        self._packages: dict[str, Path | None] = {}

    def package(self, name: str) -> Path | None:
        """Directory of package ``name`` (cached), or None."""
        if name not in self._packages:
            self._packages[name] = find_package(name, self.package_path, near=self.base_dir)
        return self._packages[name]

    def resolve(self, uri: str) -> tuple[Path | None, str]:
        """``(path, problem)``: path is None when the URI cannot be resolved; problem explains why."""
        uri = uri.strip()
        if not uri:
            return None, "empty filename"
        if uri.startswith(("package://", "model://")):
            scheme, _, rest = uri.partition("://")
            package, _, rel = rest.lstrip("/").partition("/")
            if not package or not rel:
                return None, f"malformed {scheme}:// URI (expected {scheme}://<package>/<path>)"
            root = self.package(package)
            if root is None:
                return None, (
                    f"package '{package}' not found; {search_path_text(self.package_path, self.base_dir)}. "
                    f"Add the directory that contains '{package}' to AGENTSDK_PACKAGE_PATH"
                )
            path = root / unquote(rel)
            if not path.is_file():
                return None, f"file not found: {path} (package '{package}' is {root})"
            return path.resolve(), ""
        if uri.startswith("file://"):
            parsed = urlparse(uri)
            text = url2pathname(parsed.path)
            if parsed.netloc and parsed.netloc != "localhost":  # file://relative/path
                text = url2pathname(parsed.netloc + parsed.path)
            candidate = Path(text)
        elif re.match(r"^[A-Za-z][A-Za-z0-9+.-]+://", uri):
            return None, f"unsupported URI scheme '{uri.split('://', 1)[0]}' (use package://, file:// or a path)"
        else:
            candidate = Path(uri).expanduser()
        path = candidate if candidate.is_absolute() else self.base_dir / candidate
        if not path.is_file():
            return None, f"file not found: {path}"
        return path.resolve(), ""
