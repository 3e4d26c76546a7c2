"""Robot descriptions: URDF and xacro files loaded into an immutable :class:`RobotDescription`.

``load_description`` expands xacro (``xacro.process_file``), checks the URDF
strictly (errors name the file, the line for plain URDF files, and the link or
joint), resolves every mesh to an absolute filesystem path, and parses the
result with ``yourdfpy``. The resolved URDF text (``urdf_xml``) can be handed
to a simulator as is, from any directory.

Mesh and ``$(find pkg)`` resolution follows ROS conventions:

* ``package://pkg/rel/path`` - ``pkg`` is searched, in order, in the
  directories given by ``package_path``, ``$AGENTSDK_PACKAGE_PATH`` and
  ``$ROS_PACKAGE_PATH`` (``os.pathsep``-separated). A directory ``D`` provides
  ``pkg`` if ``D/pkg`` exists, if ``D`` itself is named ``pkg``, if
  ``D/package.xml`` declares ``<name>pkg</name>``, or (like ``rospack``) if a
  ``package.xml`` declaring ``pkg`` is found a few levels below ``D``. Last,
  the description's own directory and its parents are tried (a parent named
  ``pkg``, declaring ``pkg`` in its ``package.xml``, or holding a ``pkg``
  directory).
* ``file:///abs/path`` and absolute paths are used as is.
* relative paths (and ``file://rel/path``) are relative to the directory of the
  URDF/xacro file.

``resolve_robot`` turns a robot name from the shipped ``robots/`` directory,
a ``robot.yaml``, or a bare ``.urdf``/``.xacro`` into a validated
``(RobotConfig, RobotDescription)`` pair; ``apply_overrides`` merges
robot.yaml ``joint_limits`` into the URDF limits.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import os
import re
import threading
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast
from urllib.parse import unquote, urlparse
from urllib.request import url2pathname
from xml.parsers.expat import ExpatError

from lxml import etree

from .config import JointLimitsOverride, RobotConfig, load_robot_config
from .errors import ConfigurationError, DescriptionError, UnknownJointError
from .types import JointInfo

if TYPE_CHECKING:
    from collections.abc import Callable

__all__ = [
    "PACKAGE_PATH_ENV_VARS",
    "JointRecord",
    "RobotDescription",
    "apply_overrides",
    "check_config",
    "find_package",
    "list_robots",
    "load_description",
    "package_search_path",
    "resolve_robot",
]

log = logging.getLogger(__name__)

#: environment variables searched (in this order) for ``package://`` URIs
PACKAGE_PATH_ENV_VARS: tuple[str, ...] = ("AGENTSDK_PACKAGE_PATH", "ROS_PACKAGE_PATH")

_ACTUATED = ("revolute", "continuous", "prismatic")
_JOINT_TYPES = (*_ACTUATED, "fixed", "floating", "planar")
_GEOMETRIES = ("box", "cylinder", "sphere", "mesh")
_CRAWL_DEPTH = 3  # how deep to look for package.xml below a search-path entry
_CRAWL_MAX_DIRS = 5000
_IGNORE_MARKERS = ("CATKIN_IGNORE", "COLCON_IGNORE", "AMENT_IGNORE")

# xacro keeps its state in module globals: one expansion at a time
_XACRO_LOCK = threading.Lock()


# --------------------------------------------------------------------------- records


@dataclass(frozen=True, slots=True)
class JointRecord:
    """One URDF ``<joint>`` of any type, as written in the file (after xacro).

    ``lower``/``upper``/``velocity``/``effort`` are ``None`` when the URDF has
    no ``<limit>`` (fixed joints); ``axis`` is normalised.
    """

    name: str
    type: str
    parent: str
    child: str
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    lower: float | None = None
    upper: float | None = None
    velocity: float | None = None
    effort: float | None = None
    damping: float = 0.0
    friction: float = 0.0
    mimic: str | None = None
    mimic_multiplier: float = 1.0
    mimic_offset: float = 0.0

    @property
    def actuated(self) -> bool:
        """True for revolute/continuous/prismatic joints that do not mimic another joint."""
        return self.type in _ACTUATED and self.mimic is None


@dataclass(frozen=True)
class RobotDescription:
    """A loaded robot description.

    ``joints`` holds the actuated joints (revolute, continuous, prismatic; not
    mimic joints) in URDF document order, with the URDF limits; use
    :func:`apply_overrides` to merge robot.yaml ``joint_limits``.
    ``urdf_xml`` is the URDF text with every mesh filename rewritten to an
    absolute path.
    """

    name: str
    source: Path
    urdf_xml: str = field(repr=False)
    joints: tuple[JointInfo, ...]
    all_joints: tuple[JointRecord, ...] = field(repr=False)
    links: tuple[str, ...]
    root_link: str
    mesh_files: tuple[Path, ...] = ()

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Names of the actuated joints, in ``joints`` order."""
        return tuple(j.name for j in self.joints)

    def joint(self, name: str) -> JointInfo:
        """The actuated joint called ``name``; raises ``UnknownJointError`` listing the known ones."""
        for j in self.joints:
            if j.name == name:
                return j
        raise UnknownJointError(
            f"robot '{self.name}' has no actuated joint '{name}'; known joints: {', '.join(self.joint_names)}"
        )

    def child_joints(self, link: str) -> tuple[JointRecord, ...]:
        """Joints (any type) whose parent is ``link``, in document order."""
        return tuple(j for j in self.all_joints if j.parent == link)

    def tree_lines(self) -> list[str]:
        """The kinematic tree in the spirit of ROS ``check_urdf``.

        A summary line, the root link, then one line per joint (type, axis,
        limits) ending with its child link, indented under its parent, e.g.
        ``└─ joint1 [revolute] z  lower=-3.140 upper=3.140 vel=2.5 effort=20 → link1``.
        """
        lines = [
            f"robot '{self.name}': root link '{self.root_link}', {len(self.links)} links, "
            f"{len(self.all_joints)} joints ({len(self.joints)} actuated)",
            self.root_link,
        ]

        def walk(link: str, indent: str) -> None:
            children = self.child_joints(link)
            for i, joint in enumerate(children):
                last = i == len(children) - 1
                lines.append(f"{indent}{'└─' if last else '├─'} {_joint_label(joint)} → {joint.child}")
                walk(joint.child, indent + ("   " if last else "│  "))

        walk(self.root_link, "")
        return lines

    def write_urdf(self, directory: str | Path, filename: str | None = None) -> Path:
        """Write ``urdf_xml`` to ``directory/filename`` (default ``<name>.urdf``) and return the path."""
        path = Path(directory) / (filename or f"{self.name}.urdf")
        path.write_text(self.urdf_xml, encoding="utf-8")
        return path


def _fmt(v: float) -> str:
    return f"{v:g}"


def _axis_label(axis: tuple[float, float, float]) -> str:
    for i, letter in enumerate("xyz"):
        unit = [0.0, 0.0, 0.0]
        unit[i] = 1.0
        if all(math.isclose(a, u, abs_tol=1e-9) for a, u in zip(axis, unit, strict=True)):
            return letter
        if all(math.isclose(a, -u, abs_tol=1e-9) for a, u in zip(axis, unit, strict=True)):
            return "-" + letter
    return "axis=(" + " ".join(f"{a:.3g}" for a in axis) + ")"


def _joint_label(j: JointRecord) -> str:
    parts = [f"{j.name} [{j.type}]"]
    if j.type != "fixed":
        parts.append(" " + _axis_label(j.axis))
    limits: list[str] = []
    if j.type in ("revolute", "prismatic") and j.lower is not None and j.upper is not None:
        limits.append(f"lower={j.lower:.3f} upper={j.upper:.3f}")
    if j.type != "fixed" and j.velocity is not None and j.effort is not None:
        limits.append(f"vel={_fmt(j.velocity)} effort={_fmt(j.effort)}")
    if j.mimic is not None:
        limits.append(f"mimic={j.mimic} x{_fmt(j.mimic_multiplier)}{j.mimic_offset:+g}")
    if limits:
        parts.append("  " + " ".join(limits))
    return "".join(parts)


# --------------------------------------------------------------------------- packages


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
        root = etree.parse(str(manifest), _xml_parser()).getroot()
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


def _search_path_text(package_path: Sequence[str | Path] | None, near: Path) -> str:
    entries = package_search_path(package_path)
    described = ", ".join(f"{d} (from {origin})" for origin, d in entries)
    if not described:
        described = f"none ({' and '.join(PACKAGE_PATH_ENV_VARS)} are empty)"
    return f"search path: {described}; then {near} and its parents"


class _Resolver:
    """Maps URDF resource URIs to absolute paths, caching package lookups."""

    def __init__(self, base_dir: Path, package_path: Sequence[str | Path] | None) -> None:
        self.base_dir = base_dir
        self.package_path = list(package_path or ())
        self._packages: dict[str, Path | None] = {}

    def package(self, name: str) -> Path | None:
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
            package, _, rel = rest.partition("/")
            if not package or not rel:
                return None, f"malformed {scheme}:// URI (expected {scheme}://<package>/<path>)"
            root = self.package(package)
            if root is None:
                return None, (
                    f"package '{package}' not found; {_search_path_text(self.package_path, self.base_dir)}. "
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


# --------------------------------------------------------------------------- xacro


class _TrackedArgs(dict[str, str]):
    """The xacro ``mappings`` dict, recording which arg names the document asked about."""

    def __init__(self, values: Mapping[str, str]) -> None:
        super().__init__(values)
        self.queried: set[str] = set()

    def __contains__(self, key: object) -> bool:
        if isinstance(key, str):
            self.queried.add(key)
        return super().__contains__(key)

    def __getitem__(self, key: str) -> str:
        self.queried.add(key)
        return super().__getitem__(key)


class _PackageNotFound(Exception):
    pass


@contextlib.contextmanager
def _xacro_find(find: Callable[[str], str]) -> Iterator[None]:
    """Make xacro's ``$(find pkg)`` use our package search (instead of ament_index)."""
    import xacro.substitution_args as sa

    saved_fn, saved_dict = sa._eval_find, sa._eval_dict.get("find")
    sa._eval_find = find
    sa._eval_dict["find"] = find
    try:
        yield
    finally:
        sa._eval_find = saved_fn
        sa._eval_dict["find"] = saved_dict


def _xacro_error_text(exc: BaseException) -> str:
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:  # unwrap to our own error, if any
        seen.add(id(cur))
        if isinstance(cur, _PackageNotFound):
            return str(cur)
        cur = getattr(cur, "exc", None) or cur.__cause__ or cur.__context__
    inner = getattr(exc, "exc", None)
    if isinstance(exc, ExpatError) or isinstance(inner, ExpatError):
        return f"malformed XML: {inner if isinstance(inner, ExpatError) else exc}"
    if isinstance(inner, OSError) and exc.args and exc.args[0]:
        text = str(exc.args[0])  # xacro repeats the OSError text after its own message
    else:
        text = str(exc) or repr(exc)
    text = re.sub(r"<class '[\w.]+'>: ", "", text)
    return " ".join(text.split())


def _run_xacro(path: Path, args: Mapping[str, str], resolver: _Resolver) -> str:
    try:
        import xacro
    except ImportError as exc:  # pragma: no cover - xacro is a dependency
        raise DescriptionError(f"{path}: the 'xacro' package is needed to expand xacro files") from exc

    def find(package: str) -> str:
        root = resolver.package(package)
        if root is None:
            raise _PackageNotFound(
                f"$(find {package}): package '{package}' not found; "
                f"{_search_path_text(resolver.package_path, resolver.base_dir)}"
            )
        return str(root)

    mappings = _TrackedArgs({str(k): str(v) for k, v in args.items()})
    captured = io.StringIO()
    with _XACRO_LOCK:
        try:
            with contextlib.redirect_stderr(captured), _xacro_find(find):
                doc = xacro.process_file(str(path), mappings=mappings)
                text = cast(str, doc.toxml())
        except (Exception, SystemExit) as exc:
            where = ""
            macros = [m.body.getAttribute("name") for m in (xacro.macrostack or []) if hasattr(m, "body")]
            files = [f for f in (xacro.filestack or []) if f]
            if macros:
                where += f" (in macro '{macros[-1]}')"
            if files and Path(files[-1]).resolve() != path:
                where += f" (in included file {files[-1]})"
            detail = _xacro_error_text(exc)
            hint = ""
            if "Undefined substitution argument" in detail:
                hint = "; pass it in xacro_args (robot.yaml) or give the <xacro:arg> a default"
            raise DescriptionError(f"{path}: xacro failed{where}: {detail}{hint}") from exc
        finally:
            xacro.substitution_args_context["arg"] = {}
    for line in captured.getvalue().splitlines():
        if line.strip():
            log.warning("%s: xacro: %s", path, line.strip())
    unused = sorted(set(mappings) - mappings.queried)
    if unused:
        declared = sorted(mappings.queried)
        raise DescriptionError(
            f"{path}: xacro arg(s) {', '.join(repr(a) for a in unused)} are not used by the file; "
            f"it declares: {', '.join(declared) if declared else 'no args'}"
        )
    return text


# --------------------------------------------------------------------------- URDF checks


def _xml_parser() -> etree.XMLParser:
    # comments and blank text are dropped: urdf_xml is re-serialised pretty-printed, since
    # PyBullet's tinyxml2 rejects some long single-line URDFs that contain comments
    return etree.XMLParser(
        resolve_entities=False, no_network=True, huge_tree=False, remove_comments=True, remove_blank_text=True
    )


class _Where:
    """Builds DescriptionErrors that say where the problem is."""

    def __init__(self, path: Path, expanded: bool) -> None:
        self.path = path
        self.expanded = expanded

    def __call__(self, elem: Any, msg: str) -> DescriptionError:
        if self.expanded:
            return DescriptionError(f"{self.path} (after xacro expansion): {msg}")
        line = getattr(elem, "sourceline", None)
        if line:
            return DescriptionError(f"{self.path}, line {line}: {msg}")
        return DescriptionError(f"{self.path}: {msg}")


def _numbers(
    where: _Where,
    elem: Any,
    attr: str,
    owner: str,
    count: int | tuple[int, ...],
    default: tuple[float, ...] | None = None,
) -> tuple[float, ...]:
    raw = elem.get(attr)
    if raw is None:
        if default is None:
            raise where(elem, f"{owner}: <{elem.tag}> is missing the '{attr}' attribute")
        return default
    parts = raw.replace(",", " ").split()
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise where(elem, f'{owner}: <{elem.tag} {attr}="{raw}">: not a number') from None
    counts = (count,) if isinstance(count, int) else count
    if len(values) not in counts:
        need = " or ".join(str(c) for c in counts)
        raise where(elem, f'{owner}: <{elem.tag} {attr}="{raw}"> needs {need} number(s), got {len(values)}')
    if not all(math.isfinite(v) for v in values):
        raise where(elem, f'{owner}: <{elem.tag} {attr}="{raw}"> must be finite')
    return values


def _number(where: _Where, elem: Any, attr: str, owner: str, default: float | None = None) -> float:
    return _numbers(where, elem, attr, owner, 1, None if default is None else (default,))[0]


def _origin(where: _Where, parent: Any, owner: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    origin = parent.find("origin")
    if origin is None:
        return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    xyz = _numbers(where, origin, "xyz", owner, 3, (0.0, 0.0, 0.0))
    rpy = _numbers(where, origin, "rpy", owner, 3, (0.0, 0.0, 0.0))
    return xyz, rpy


def _check_link(where: _Where, link: Any, name: str) -> None:
    owner = f"link '{name}'"
    inertial = link.find("inertial")
    if inertial is not None:
        _origin(where, inertial, owner)
        mass = inertial.find("mass")
        if mass is None:
            raise where(inertial, f"{owner}: <inertial> has no <mass>")
        if _number(where, mass, "value", owner) < 0:
            raise where(mass, f"{owner}: mass must be >= 0")
        inertia = inertial.find("inertia")
        if inertia is None:
            raise where(inertial, f"{owner}: <inertial> has no <inertia>")
        for attr in ("ixx", "iyy", "izz"):
            _number(where, inertia, attr, owner)
        for attr in ("ixy", "ixz", "iyz"):
            _number(where, inertia, attr, owner, 0.0)
    for kind in ("visual", "collision"):
        for elem in link.findall(kind):
            _origin(where, elem, owner)
            geometry = elem.find("geometry")
            if geometry is None:
                raise where(elem, f"{owner}: <{kind}> has no <geometry>")
            shapes = [c for c in geometry if isinstance(c.tag, str)]
            if len(shapes) != 1:
                raise where(geometry, f"{owner}: <{kind}><geometry> needs exactly one of box, cylinder, sphere, mesh")
            shape = shapes[0]
            if shape.tag not in _GEOMETRIES:
                raise where(
                    shape, f"{owner}: unsupported geometry <{shape.tag}> (URDF has box, cylinder, sphere, mesh)"
                )
            if shape.tag == "box":
                size = _numbers(where, shape, "size", owner, 3)
                if min(size) <= 0:
                    raise where(shape, f"{owner}: box size must be positive")
            elif shape.tag == "cylinder":
                if _number(where, shape, "radius", owner) <= 0 or _number(where, shape, "length", owner) <= 0:
                    raise where(shape, f"{owner}: cylinder radius and length must be positive")
            elif shape.tag == "sphere":
                if _number(where, shape, "radius", owner) <= 0:
                    raise where(shape, f"{owner}: sphere radius must be positive")
            else:
                if not shape.get("filename"):
                    raise where(shape, f"{owner}: <mesh> has no filename")
                if shape.get("scale") is not None:
                    _numbers(where, shape, "scale", owner, (1, 3))
            material = elem.find("material")
            if material is not None and material.find("color") is not None:
                _numbers(where, material.find("color"), "rgba", owner, 4, (1.0, 1.0, 1.0, 1.0))


def _parse_joint(where: _Where, joint: Any, name: str, links: set[str]) -> JointRecord:
    owner = f"joint '{name}'"
    jtype = joint.get("type")
    if jtype is None:
        raise where(joint, f"{owner} has no 'type' attribute")
    if jtype not in _JOINT_TYPES:
        raise where(joint, f"{owner}: unknown joint type '{jtype}' (URDF has {', '.join(_JOINT_TYPES)})")
    if jtype in ("floating", "planar"):
        raise where(
            joint, f"{owner}: joint type '{jtype}' is not supported (use revolute, continuous, prismatic or fixed)"
        )
    ends: dict[str, str] = {}
    for end in ("parent", "child"):
        elem = joint.find(end)
        if elem is None or not elem.get("link"):
            raise where(joint if elem is None else elem, f'{owner} has no <{end} link="..."/>')
        if elem.get("link") not in links:
            raise where(elem, f"{owner}: {end} link '{elem.get('link')}' is not defined")
        ends[end] = elem.get("link")
    if ends["parent"] == ends["child"]:
        raise where(joint, f"{owner} connects link '{ends['parent']}' to itself")
    xyz, rpy = _origin(where, joint, owner)

    axis_elem = joint.find("axis")
    axis: tuple[float, ...] = (1.0, 0.0, 0.0)
    if axis_elem is not None:
        axis = _numbers(where, axis_elem, "xyz", owner, 3, (1.0, 0.0, 0.0))
    norm = math.sqrt(sum(a * a for a in axis))
    if jtype != "fixed" and norm < 1e-9:
        raise where(axis_elem, f"{owner}: axis must not be zero")
    if norm >= 1e-9:
        axis = tuple(a / norm for a in axis)

    mimic_elem = joint.find("mimic")
    mimic = None
    multiplier, offset = 1.0, 0.0
    if mimic_elem is not None and jtype != "fixed":
        mimic = mimic_elem.get("joint")
        if not mimic:
            raise where(mimic_elem, f"{owner}: <mimic> has no 'joint' attribute")
        multiplier = _number(where, mimic_elem, "multiplier", owner, 1.0)
        offset = _number(where, mimic_elem, "offset", owner, 0.0)

    limit = joint.find("limit")
    lower = upper = velocity = effort = None
    if jtype in _ACTUATED:
        if limit is None:
            if jtype != "continuous":
                raise where(joint, f"{owner}: a {jtype} joint needs a <limit lower upper velocity effort/> (URDF spec)")
            if mimic is None:
                raise where(joint, f"{owner}: continuous joint has no <limit velocity=... effort=.../>")
        else:
            for attr in ("velocity", "effort"):
                if limit.get(attr) is None:
                    raise where(limit, f"{owner}: <limit> is missing the '{attr}' attribute")
            velocity = _number(where, limit, "velocity", owner)
            effort = _number(where, limit, "effort", owner)
            if mimic is None and (velocity <= 0 or effort <= 0):
                raise where(limit, f"{owner}: <limit> velocity and effort must be > 0 (got {velocity:g}, {effort:g})")
            if jtype == "continuous":
                lower, upper = -math.inf, math.inf
            else:
                lower = _number(where, limit, "lower", owner, 0.0)
                upper = _number(where, limit, "upper", owner, 0.0)
                if lower > upper:
                    raise where(limit, f"{owner}: <limit> lower={lower:g} is above upper={upper:g}")
    dynamics = joint.find("dynamics")
    damping = friction = 0.0
    if dynamics is not None:
        damping = _number(where, dynamics, "damping", owner, 0.0)
        friction = _number(where, dynamics, "friction", owner, 0.0)
        if damping < 0 or friction < 0:
            raise where(dynamics, f"{owner}: <dynamics> damping and friction must be >= 0")
    return JointRecord(
        name=name,
        type=jtype,
        parent=ends["parent"],
        child=ends["child"],
        xyz=cast(tuple[float, float, float], xyz),
        rpy=cast(tuple[float, float, float], rpy),
        axis=cast(tuple[float, float, float], axis),
        lower=lower,
        upper=upper,
        velocity=velocity,
        effort=effort,
        damping=damping,
        friction=friction,
        mimic=mimic,
        mimic_multiplier=multiplier,
        mimic_offset=offset,
    )


def _check_tree(where: _Where, root: Any, links: list[str], joints: list[JointRecord], elems: dict[str, Any]) -> str:
    parent_of: dict[str, JointRecord] = {}
    for j in joints:
        if j.child in parent_of:
            raise where(
                elems[j.name],
                f"link '{j.child}' has two parent joints ('{parent_of[j.child].name}' and '{j.name}'); "
                "a URDF must be a tree",
            )
        parent_of[j.child] = j
    roots = [name for name in links if name not in parent_of]
    if not roots:
        raise where(root, "the joints form a loop: every link has a parent joint, so there is no root link")
    if len(roots) > 1:
        raise where(
            root,
            f"more than one root link ({', '.join(repr(r) for r in roots)}); every link but one needs a parent joint",
        )
    children: dict[str, list[str]] = {}
    for j in joints:
        children.setdefault(j.parent, []).append(j.child)
    reached = {roots[0]}
    stack = [roots[0]]
    while stack:
        for child in children.get(stack.pop(), []):
            if child not in reached:
                reached.add(child)
                stack.append(child)
    unreached = [name for name in links if name not in reached]
    if unreached:
        raise where(root, f"links {', '.join(repr(n) for n in unreached)} are in a kinematic loop, not in the tree")
    return roots[0]


# --------------------------------------------------------------------------- loading


def load_description(
    path: str | Path,
    xacro_args: Mapping[str, str] | None = None,
    package_path: Sequence[Path] | None = None,
) -> RobotDescription:
    """Load a ``.urdf`` or ``.xacro`` file.

    ``xacro_args`` are ``<xacro:arg>`` values (an arg the file does not use is
    an error). ``package_path`` lists extra directories searched first for
    ``package://`` URIs and ``$(find pkg)``. Raises ``DescriptionError``
    naming the file and the problem.
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise DescriptionError(f"robot description not found: {path}" + (" (a directory)" if path.is_dir() else ""))
    path = path.resolve()
    resolver = _Resolver(path.parent, package_path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DescriptionError(f"{path}: cannot read: {exc}") from exc

    is_xacro = path.suffix.lower() == ".xacro" or b"xmlns:xacro" in raw
    if is_xacro:
        data = _run_xacro(path, xacro_args or {}, resolver).encode("utf-8")
    else:
        if xacro_args:
            raise DescriptionError(
                f"{path}: xacro_args {dict(xacro_args)} given, but the file is plain URDF (not .xacro)"
            )
        data = raw
    where = _Where(path, expanded=is_xacro)

    try:
        root = etree.fromstring(data, _xml_parser())
    except etree.XMLSyntaxError as exc:
        detail = re.sub(r" \(<string>, line \d+\)$", "", str(exc))
        raise where(None, f"malformed XML: {detail}") from exc
    if root.tag != "robot":
        raise where(root, f"the top-level element is <{root.tag}>, expected <robot>")
    name = root.get("name")
    if not name:
        raise where(root, "<robot> has no 'name' attribute")

    link_elems: dict[str, Any] = {}
    for link in root.findall("link"):
        lname = link.get("name")
        if not lname:
            raise where(link, "a <link> has no 'name' attribute")
        if lname in link_elems:
            raise where(link, f"link '{lname}' is defined twice")
        _check_link(where, link, lname)
        link_elems[lname] = link
    if not link_elems:
        raise where(root, "the robot has no <link>")

    joint_elems: dict[str, Any] = {}
    records: list[JointRecord] = []
    for joint in root.findall("joint"):
        jname = joint.get("name")
        if not jname:
            raise where(joint, "a <joint> has no 'name' attribute")
        if jname in joint_elems:
            raise where(joint, f"joint '{jname}' is defined twice")
        joint_elems[jname] = joint
        records.append(_parse_joint(where, joint, jname, set(link_elems)))
    for rec in records:
        if rec.mimic is not None:
            target = next((r for r in records if r.name == rec.mimic), None)
            if target is None or target.type not in _ACTUATED or rec.mimic == rec.name:
                raise where(
                    joint_elems[rec.name], f"joint '{rec.name}' mimics '{rec.mimic}', which is not a movable joint"
                )
    root_link = _check_tree(where, root, list(link_elems), records, joint_elems)
    if not any(r.actuated for r in records):
        raise where(root, "the robot has no actuated joints (revolute, continuous or prismatic)")

    mesh_files: list[Path] = []
    for kind, attr_owner in (("mesh", "link"), ("texture", "material")):
        for elem in root.iter(kind):
            uri = elem.get("filename")
            if uri is None:
                continue
            resolved, problem = resolver.resolve(uri)
            if resolved is None:
                owner = next((a.get("name") for a in elem.iterancestors(attr_owner)), None)
                what = f"{attr_owner} '{owner}': " if owner else ""
                raise where(elem, f"{what}cannot resolve {kind} '{uri}': {problem}")
            elem.set("filename", str(resolved))
            if kind == "mesh" and resolved not in mesh_files:
                mesh_files.append(resolved)

    urdf_xml = '<?xml version="1.0" encoding="utf-8"?>\n' + etree.tostring(root, encoding="unicode", pretty_print=True)
    model = _yourdfpy_model(where, urdf_xml)

    by_name = {r.name: r for r in records}
    joints: list[JointInfo] = []
    for j in model.robot.joints:
        rec = by_name[j.name]
        if not rec.actuated:
            continue
        assert rec.velocity is not None and rec.effort is not None and rec.lower is not None and rec.upper is not None
        joints.append(
            JointInfo(
                name=j.name,
                type=cast(Literal["revolute", "continuous", "prismatic"], j.type),
                lower=rec.lower,
                upper=rec.upper,
                max_velocity=float(j.limit.velocity),
                max_effort=float(j.limit.effort),
                parent=j.parent,
                child=j.child,
                axis=rec.axis,
            )
        )
    return RobotDescription(
        name=name,
        source=path,
        urdf_xml=urdf_xml,
        joints=tuple(joints),
        all_joints=tuple(records),
        links=tuple(link.name for link in model.robot.links),
        root_link=root_link,
        mesh_files=tuple(mesh_files),
    )


def _yourdfpy_model(where: _Where, urdf_xml: str) -> Any:
    """Parse the checked, resolved URDF with yourdfpy (no scene graph, no mesh loading)."""
    import yourdfpy

    try:
        model = yourdfpy.URDF.load(
            io.BytesIO(urdf_xml.encode("utf-8")),
            build_scene_graph=False,
            build_collision_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
            filename_handler=yourdfpy.filename_handler_null,
        )
    except Exception as exc:
        raise where(None, f"yourdfpy could not parse the URDF: {exc}") from exc
    if not model.validate(validation_fn=lambda errors: not errors):
        problems = "; ".join(str(e) for e in model.errors)
        raise where(None, f"invalid URDF: {problems}")
    return model


# --------------------------------------------------------------------------- robot.yaml


def _robot_label(config: RobotConfig, description: RobotDescription) -> str:
    return f"robot '{config.name or description.name}'"


def apply_overrides(description: RobotDescription, config: RobotConfig) -> tuple[JointInfo, ...]:
    """The description's joints with robot.yaml ``joint_limits`` applied.

    ``joint_limits["default"]`` applies to every joint: its acceleration/jerk
    values replace the built-in defaults, and its position/velocity/effort
    values can only tighten each joint's URDF limits. A per-joint entry
    replaces values for that joint; it may tighten but never widen a URDF
    limit (that would exceed what the hardware description allows).
    Raises ``ConfigurationError`` for an unknown joint name or an inconsistent
    override.
    """
    limits = config.joint_limits
    names = description.joint_names
    label = _robot_label(config, description)
    unknown = [k for k in limits if k != "default" and k not in names]
    if unknown:
        raise ConfigurationError(
            f"{label}: joint_limits names unknown joint(s) {', '.join(repr(u) for u in unknown)}; "
            f"known joints: {', '.join(names)} (or 'default')"
        )
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
                if own.min_position < j.lower:
                    raise ConfigurationError(
                        f"{where}.min_position={own.min_position:g} is below the URDF lower limit {j.lower:g}"
                    )
                lower = own.min_position
            if own.max_position is not None:
                if own.max_position > j.upper:
                    raise ConfigurationError(
                        f"{where}.max_position={own.max_position:g} is above the URDF upper limit {j.upper:g}"
                    )
                upper = own.max_position
            if own.max_velocity is not None:
                if own.max_velocity > j.max_velocity:
                    raise ConfigurationError(
                        f"{where}.max_velocity={own.max_velocity:g} is above the URDF velocity limit {j.max_velocity:g}"
                    )
                vel = own.max_velocity
            if own.max_effort is not None:
                if own.max_effort > j.max_effort:
                    raise ConfigurationError(
                        f"{where}.max_effort={own.max_effort:g} is above the URDF effort limit {j.max_effort:g}"
                    )
                eff = own.max_effort
            if own.max_acceleration is not None:
                acc = own.max_acceleration
            if own.max_jerk is not None:
                jerk = own.max_jerk
        if lower > upper:
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
    for section, keys in (("gains", config.gains), ("initial_positions", config.initial_positions)):
        unknown = [k for k in keys if k not in names and not (section == "gains" and k == "default")]
        if unknown:
            raise ConfigurationError(
                f"{label}: {section} names unknown joint(s) {', '.join(repr(u) for u in unknown)}; "
                f"known joints: {', '.join(names)}"
            )
    for j in joints:
        q = config.initial_positions.get(j.name)
        if q is not None and not j.within(q):
            raise ConfigurationError(
                f"{label}: initial_positions.{j.name}={q:g} is outside the joint limits [{j.lower:g}, {j.upper:g}]"
            )
    return joints


def _default_robots_dir() -> Path:
    import agentsdk.robots as robots

    return Path(robots.__file__).resolve().parent


def list_robots(robots_dir: Path | None = None) -> list[str]:
    """Names of the robots shipped in ``robots_dir`` (default: the ``robots`` package): dirs with a robot.yaml."""
    directory = Path(robots_dir) if robots_dir is not None else _default_robots_dir()
    if not directory.is_dir():
        return []
    return sorted(d.name for d in directory.iterdir() if (d / "robot.yaml").is_file())


_DESCRIPTION_SUFFIXES = (".urdf", ".xacro")
_CONFIG_SUFFIXES = (".yaml", ".yml")


def resolve_robot(spec: str | Path, robots_dir: Path | None = None) -> tuple[RobotConfig, RobotDescription]:
    """Turn a robot name or path into a validated ``(RobotConfig, RobotDescription)``.

    ``spec`` is a robot name from ``robots_dir`` (default: the shipped
    ``robots/`` directory), or a path to a ``.urdf``, ``.xacro``,
    ``robot.yaml`` or a directory holding a ``robot.yaml``. A bare URDF/xacro
    gets a default ``RobotConfig``. Raises ``ConfigurationError`` (or its
    subclass ``DescriptionError``) naming what is wrong.
    """
    directory = Path(robots_dir) if robots_dir is not None else _default_robots_dir()
    text = os.fspath(spec)
    bare_name = (
        isinstance(spec, str)
        and "/" not in text
        and os.sep not in text
        and not text.lower().endswith(_DESCRIPTION_SUFFIXES + _CONFIG_SUFFIXES)
    )
    path = Path(text).expanduser()
    if bare_name:
        candidate = directory / text / "robot.yaml"
        if text and candidate.is_file():
            path = candidate
        elif not path.exists():
            known = list_robots(directory)
            raise ConfigurationError(
                f"unknown robot '{text}'; available robots: {', '.join(known) if known else '(none)'} "
                f"(in {directory}), or pass a path to a .urdf, .xacro or robot.yaml"
            )
    if path.is_dir():
        if not (path / "robot.yaml").is_file():
            raise ConfigurationError(f"{path} is a directory without a robot.yaml")
        path = path / "robot.yaml"
    if not path.exists():
        raise ConfigurationError(f"robot description not found: {path}")

    lower = path.name.lower()
    if lower.endswith(_CONFIG_SUFFIXES):
        config = load_robot_config(path)
        description = load_description(config.description_path, config.xacro_args)
    elif lower.endswith(_DESCRIPTION_SUFFIXES):
        description = load_description(path)
        config = RobotConfig(name=description.name, description=path.name, base_dir=path.resolve().parent)
    else:
        raise ConfigurationError(f"{path}: expected a .urdf, .xacro or robot.yaml file")
    check_config(config, description)
    return config, description
