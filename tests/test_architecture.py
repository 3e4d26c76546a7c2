"""Architecture guards (issue 11): no reaching into other modules' internals, no monkey-patching.

Static checks over the shipped code (agentsdk/, backends/, behaviors/, bench/):

* ``from x import _name`` of another module's private name;
* ``obj._name`` where ``_name`` is not defined in the same module (so it belongs to another
  module's object), apart from a short allowlist, each with its documented reason;
* inside a subpackage of agentsdk (``agentsdk.motion``, ``agentsdk.safety``, ...) the package is the
  unit of privacy: its modules may use each other's private names (``from ._types import _POS``,
  ``motion._settle(...)``), never those of another package or of a top-level module;
* assignments to attributes of imported modules or classes (monkey-patching).
"""

from __future__ import annotations

import ast
import functools
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted(
    p
    for d in ("agentsdk", "backends", "behaviors", "bench")
    for p in (ROOT / d).rglob("*.py")
    if "__pycache__" not in p.parts
)

#: (file, attribute) pairs that read a private name of another module's object, and why
ALLOWED = {
    # asyncio exposes no public "is any task ready?": lockstep time needs it (documented in loop._settle)
    ("agentsdk/loop.py", "_ready"),
    # sys._current_frames is documented in the Python library reference (the stall watchdog's stack dump)
    ("agentsdk/stall.py", "_current_frames"),
}


def _defined_private_names(tree: ast.AST) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef) and node.name.startswith("_"):
            names.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) and node.attr.startswith("_"):
            names.add(node.attr)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store) and node.id.startswith("_"):
            names.add(node.id)
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        elif isinstance(node, ast.Assign):
            for t in node.targets:
                if isinstance(t, ast.Name) and t.id == "__slots__" and isinstance(node.value, ast.Tuple):
                    names.update(e.value for e in node.value.elts if isinstance(e, ast.Constant))
    return names


def _imported_names(tree: ast.AST) -> set[str]:
    """Names bound to the project's own modules and classes (what monkey-patching would target)."""
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update((a.asname or a.name).split(".")[0] for a in node.names if a.name.startswith("agentsdk"))
        elif isinstance(node, ast.ImportFrom) and (node.level > 0 or (node.module or "").startswith("agentsdk")):
            out.update(a.asname or a.name for a in node.names)
    return out


@functools.cache
def _parsed(path: Path) -> ast.Module:
    """A source file's syntax tree, parsed once per session (each file's check reads its whole package)."""
    return ast.parse(path.read_text(), filename=path.relative_to(ROOT).as_posix())


@functools.cache
def _private_names_of(path: Path) -> frozenset[str]:
    return frozenset(_defined_private_names(_parsed(path)))


def _package_private_names(path: Path) -> set[str]:
    """The private names defined by the other modules of ``path``'s package (none at the top level)."""
    if path.parent in (ROOT / "agentsdk", ROOT):
        return set()
    names: set[str] = set()
    for other in path.parent.glob("*.py"):
        if other != path:
            names |= _private_names_of(other)
    return names


def _problems(path: Path) -> list[str]:
    rel = path.relative_to(ROOT).as_posix()
    tree = _parsed(path)
    package = _package_private_names(path)
    own = _defined_private_names(tree) | package
    imported = _imported_names(tree)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level > 0 and node.module is None:
                continue  # ``from . import _part``: a package importing its own private submodule
            if node.level == 1 and package and (path.parent / f"{node.module}.py").is_file():
                continue  # ``from ._types import _POS``: a private name shared inside one subpackage
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    out.append(f"{rel}:{node.lineno}: imports private {alias.name!r} from {node.module}")
        elif isinstance(node, ast.Attribute):
            attr = node.attr
            if not attr.startswith("_") or (attr.startswith("__") and attr.endswith("__")):
                continue
            if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
                continue
            if attr not in own and (rel, attr) not in ALLOWED:
                out.append(f"{rel}:{node.lineno}: uses {attr!r}, private to another module")
        if isinstance(node, ast.Assign | ast.AugAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for t in targets:
                if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id in imported:
                    out.append(f"{rel}:{node.lineno}: assigns {t.value.id}.{t.attr} (monkey-patching)")
    return out


@pytest.mark.parametrize("path", SOURCES, ids=[p.relative_to(ROOT).as_posix() for p in SOURCES])
def test_no_private_access_across_modules_and_no_monkey_patching(path: Path) -> None:
    problems = _problems(path)
    assert not problems, "\n".join(problems)


def test_no_merge_conflict_markers_are_committed() -> None:
    """A half-resolved merge once left ``<<<<<<<`` blocks in the README: no tracked text file has any."""
    listed = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=False)
    files = listed.stdout.split()
    if not files:
        pytest.skip("not a git checkout")
    markers = re.compile(r"^(<{7} |>{7} |={7}$)", re.M)
    text_suffixes = {".py", ".md", ".toml", ".yaml", ".yml", ".rst", ".sh", ".txt", ".cfg", ".urdf", ".xacro"}
    bad = []
    for name in files:
        path = ROOT / name
        if path.suffix not in text_suffixes:
            continue
        if path.is_file() and markers.search(path.read_text(errors="replace")):
            bad.append(name)
    assert not bad, f"merge conflict markers in {bad}"


def test_every_package_is_installed() -> None:
    """pyproject lists packages explicitly (the backends/ → agentsdk.backends mapping needs it): every
    folder with an ``__init__.py`` must be in the list, or a wheel install silently lacks it."""
    import tomllib

    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(cfg["packages"])
    folders = {"agentsdk": ROOT / "agentsdk"}
    folders.update({name: ROOT / path for name, path in cfg["package-dir"].items()})
    found = set()
    for name, folder in folders.items():
        for init in folder.rglob("__init__.py"):
            rel = init.parent.relative_to(folder).parts
            if "__pycache__" not in rel:
                found.add(".".join((name, *rel)))
    missing = sorted(found - listed)
    assert not missing, f"packages missing from [tool.setuptools] packages: {missing}"


def test_package_privacy_stops_at_the_package() -> None:
    """Private names are shared inside one subpackage only: not with top-level modules or other packages."""
    motion = _package_private_names(ROOT / "agentsdk" / "motion" / "_executor.py")
    assert {"_settle", "_POS", "_Exec"} <= motion
    assert _package_private_names(ROOT / "agentsdk" / "robot.py") == set()
    assert "_settle" not in _package_private_names(ROOT / "agentsdk" / "safety" / "_filter.py")
