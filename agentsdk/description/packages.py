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

Robot files are data: every file a description reaches (meshes, ``xacro:include``,
``load_yaml``) must lie inside a *package root* (:meth:`Resolver.roots`): the package
the description is in (the nearest directory at or above it holding a
``package.xml``, else the description's own directory), the directories of the
package search path, and the packages found in them or declared by a ``package.xml``.
Real paths are compared, so neither ``..`` nor a symlink leaves a root.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Sequence
from pathlib import Path
from urllib.parse import unquote, urlparse

from lxml import etree

__all__ = [
    "PACKAGE_PATH_ENV_VARS",
    "Resolver",
    "description_root",
    "find_package",
    "package_search_path",
    "path_inside",
    "search_path_text",
]

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
    try:
        return _find_package(package, package_path, near)
    except (OSError, ValueError):  # a package name too long for the filesystem, a NUL byte
        return None


def _find_package(
    package: str, package_path: Sequence[str | Path] | None, near: str | Path | None
) -> Path | None:
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


def path_inside(path: str | os.PathLike[str], roots: Sequence[str | os.PathLike[str]]) -> bool:
    """True when the real path of ``path`` (symlinks and ``..`` resolved) lies inside one of ``roots``."""
    try:
        real = Path(os.path.realpath(path))
    except (OSError, ValueError):
        return False
    for root in roots:
        try:
            top = Path(os.path.realpath(root))
        except (OSError, ValueError):
            continue
        if real == top or top in real.parents:
            return True
    return False


def description_root(directory: Path) -> Path:
    """The package a description in ``directory`` belongs to: the nearest directory at or above it
    holding a ``package.xml``, else ``directory`` itself.
    """
    start = Path(os.path.realpath(directory))
    for candidate in (start, *start.parents):
        try:
            if (candidate / "package.xml").is_file():
                return candidate
        except OSError:
            continue
    return start


class Resolver:
    """Maps URDF resource URIs to absolute paths, caching package lookups."""

    def __init__(
        self,
        base_dir: Path,
        package_path: Sequence[str | Path] | None,
        extra_roots: Sequence[Path] = (),
        *,
        trusted: bool = False,
    ) -> None:
        self.base_dir = base_dir
        self.package_path = list(package_path or ())
        self.extra_roots = list(extra_roots)
        #: a trusted description may reach files outside its package roots
        self.trusted = trusted
        self._packages: dict[str, Path | None] = {}

    def roots(self) -> list[Path]:
        """The package roots known before any lookup: the description's package and the search path."""
        search = [d for _, d in package_search_path(self.package_path)]
        return [description_root(self.base_dir), *self.extra_roots, *search]

    def is_package_root(self, root: Path) -> bool:
        """True when a found package directory may be read: it has a package.xml or is on the search path."""
        try:
            if (root / "package.xml").is_file():
                return True
        except OSError:
            return False
        return path_inside(root, [d for _, d in package_search_path(self.package_path)])

    def allowed_roots(self) -> list[Path]:
        """:meth:`roots` and every package found so far that :meth:`is_package_root` accepts."""
        found = [p for p in self._packages.values() if p is not None and self.is_package_root(p)]
        return [*self.roots(), *found]

    def escape(self, path: Path) -> str | None:
        """Why ``path`` may not be read (outside every package root), or None (inside one, or trusted)."""
        if self.trusted:
            return None
        roots = self.allowed_roots()
        if path_inside(path, roots):
            return None
        listed = ", ".join(str(r) for r in dict.fromkeys(roots))
        return f"{os.path.realpath(path)} is outside the package roots ({listed})"

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
            problem = _not_a_file(path)
            if problem:
                return None, f"{problem}: {path} (package '{package}' is {root})"
            return path.resolve(), ""
        if uri.startswith("file://"):
            from urllib.request import url2pathname  # imported here: slow to import, rarely needed

            parsed = urlparse(uri)
            text = url2pathname(parsed.path)
            if parsed.netloc and parsed.netloc != "localhost":  # file://relative/path
                text = url2pathname(parsed.netloc + parsed.path)
            candidate = Path(text)
        elif re.match(r"^[A-Za-z][A-Za-z0-9+.-]+://", uri):
            return None, f"unsupported URI scheme '{uri.split('://', 1)[0]}' (use package://, file:// or a path)"
        else:
            try:
                candidate = Path(uri).expanduser()
            except RuntimeError:  # ~user that does not exist
                candidate = Path(uri)
        path = candidate if candidate.is_absolute() else self.base_dir / candidate
        problem = _not_a_file(path)
        if problem:
            return None, f"{problem}: {path}"
        return path.resolve(), ""


def _not_a_file(path: Path) -> str:
    """Why ``path`` is not a readable regular file ("" when it is); OSErrors become the reason."""
    try:
        if path.is_file():
            return ""
        return "file not found"
    except (OSError, ValueError) as exc:  # a name too long, a NUL byte, permissions
        return f"cannot read ({exc.strerror if isinstance(exc, OSError) and exc.strerror else exc})"
