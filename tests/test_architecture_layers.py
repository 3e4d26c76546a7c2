"""Architecture guards (issue 21): the import direction of agentsdk/ and the one limiter.

* No import cycle between the modules of ``agentsdk/``: module-level imports, the ones under
  ``if TYPE_CHECKING:`` included (a type-only circle hides real two-way calls), apart from a
  short allowlist, each with its reason.
* The core layers (see docs/architecture.md) import only downward, lazy imports inside
  functions included.
* Inside the packages split by objects (``agentsdk.motion``, ``agentsdk.safety``, ``agentsdk.cli``) each module
  imports only the modules listed before it (the package ``__init__`` only re-exports).
* A module over ~600 lines is named, with its reason, in docs/architecture.md, and a module named
  there is still long (the list of exceptions stays true).
* The position limiting math exists once: the safety filter and the trajectory executor call
  the same :class:`agentsdk.limits.StepLimiter` methods.
* Inside a package split by objects no class extends another class of its package (value types,
  enums, exceptions and pydantic models excepted): its objects are separate, each built with its
  collaborators, not layers of one ``self``.
* The host-side model is compiled in one place (:func:`agentsdk.hostmodel.compile_spec`): the
  kinematics, the dynamics and the core build no MuJoCo model of their own.
"""

from __future__ import annotations

import ast
import inspect
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk.limits import StepLimiter
from agentsdk.motion._executor import _Executor
from agentsdk.safety._filter import CommandFilter
from agentsdk.trajectory import Trajectory, TrajectoryPoint

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "agentsdk"

#: type-only import edges allowed inside a cycle, and why
TYPE_ONLY_ALLOWED = {
    # the state machine's private helpers annotate their parameters with the StateMachine class that
    # imports them (one package, one class): the helpers never call back into _machine at import time
    ("agentsdk.statemachine._declaration", "agentsdk.statemachine._machine"),
    ("agentsdk.statemachine._mermaid", "agentsdk.statemachine._machine"),
    ("agentsdk.statemachine._runtime", "agentsdk.statemachine._machine"),
    ("agentsdk.statemachine._validation", "agentsdk.statemachine._machine"),
}

#: the core layers, lowest first: a module may import (at any level, lazily too) only from its own
#: layer or a lower one. The diagram and the reasons are in docs/architecture.md.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("agentsdk.errors", "agentsdk.types"),
    ("agentsdk.backendspec",),
    ("agentsdk.backend",),
    ("agentsdk.loop",),
    ("agentsdk.limits", "agentsdk.commands", "agentsdk.checks", "agentsdk.stall"),
    ("agentsdk.safety", "agentsdk.following"),
    ("agentsdk.motion",),
    ("agentsdk.robot",),
)

#: the modules of a package split by objects, lowest first: a module may import (at any level, lazily
#: too) only the modules before it; the package ``__init__`` re-exports and nothing inside imports it
PACKAGE_ORDER: dict[str, tuple[str, ...]] = {
    "agentsdk.motion": (
        "_types", "_handle", "_envelope", "_records", "_ownership", "_stops", "_admission", "_executor", "_block",
        "_manager",
    ),
    "agentsdk.safety": ("_config", "_state", "_filter", "_stops", "_watchdogs", "_block", "_layer"),
    "agentsdk.cli": ("_behavior", "_run", "_robots", "_teleop", "_tools", "_main", "__main__"),
}

#: longest module without a reason in docs/architecture.md (lines)
MAX_LINES = 600


def _modules() -> dict[str, Path]:
    out = {}
    for p in PACKAGE.rglob("*.py"):
        if "__pycache__" in p.parts:
            continue
        parts = list(p.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


MODULES = _modules()


def _target(name: str) -> str | None:
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _imports(module: str, path: Path) -> Iterator[tuple[str, str]]:
    """``(imported module, kind)`` of every project import of ``module``: kind is "runtime",
    "type" (under ``if TYPE_CHECKING:``) or "lazy" (inside a function)."""
    is_pkg = path.name == "__init__.py"
    tree = ast.parse(path.read_text(), filename=str(path))

    def visit(node: ast.AST, kind: str) -> Iterator[tuple[str, str]]:
        for child in ast.iter_child_nodes(node):
            k = kind
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                k = "lazy"
            elif isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test) and kind == "runtime":
                k = "type"
            if isinstance(child, ast.Import):
                for alias in child.names:
                    t = _target(alias.name)
                    if t is not None and t != module:
                        yield t, k
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = module.split(".") if is_pkg else module.split(".")[:-1]
                    base = base[: len(base) - (child.level - 1)]
                    name = ".".join([*base, child.module] if child.module else base)
                else:
                    name = child.module or ""
                if not name.startswith("agentsdk"):
                    continue
                subs = [f"{name}.{a.name}" for a in child.names if f"{name}.{a.name}" in MODULES]
                for t in subs if len(subs) == len(child.names) else [name, *subs]:
                    tt = _target(t)
                    if tt is not None and tt != module:
                        yield tt, k
            yield from visit(child, k)

    yield from visit(tree, "runtime")


EDGES: dict[str, set[tuple[str, str]]] = {m: set(_imports(m, p)) for m, p in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            strong(v)
    return out


def test_no_import_cycles() -> None:
    graph = {
        m: {t for t, kind in edges if kind == "runtime" or (kind == "type" and (m, t) not in TYPE_ONLY_ALLOWED)}
        for m, edges in EDGES.items()
    }
    cycles = _cycles(graph)
    detail = [" <-> ".join(c) + ": " + "; ".join(f"{m} -> {sorted(graph[m] & set(c))}" for m in c) for c in cycles]
    assert not cycles, "import cycles in agentsdk/:\n" + "\n".join(detail)


def test_the_guard_finds_a_cycle() -> None:
    """The cycle finder is not vacuous."""
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def _layer_of() -> dict[str, int]:
    """The layer of every module of a core layer, the modules inside a layer's package included."""
    named = {m: i for i, layer in enumerate(LAYERS) for m in layer}
    assert set(named) <= set(MODULES), "a layer names a module that does not exist"
    return {m: i for m in MODULES for n, i in named.items() if m == n or m.startswith(n + ".")}


def test_core_layers_import_downward() -> None:
    layer_of = _layer_of()
    bad = []
    for m, i in layer_of.items():
        for t, kind in sorted(EDGES[m]):
            j = layer_of.get(t)
            if j is not None and j > i:
                bad.append(f"{m} (layer {i}) imports {t} (layer {j}, {kind})")
    assert not bad, "imports that point upward:\n" + "\n".join(bad)


def _package_violations(order: dict[str, tuple[str, ...]], edges: dict[str, set[tuple[str, str]]]) -> list[str]:
    """Imports inside an ordered package that point at a later module or at the package itself."""
    bad = []
    for pkg, names in order.items():
        rank = {f"{pkg}.{n}": k for k, n in enumerate(names)}
        for m, k in rank.items():
            for t, kind in sorted(edges.get(m, ())):
                if t == pkg:
                    bad.append(f"{m} imports its package {pkg} ({kind}): import the module that defines the name")
                elif t in rank and rank[t] > k:
                    bad.append(f"{m} imports {t}, listed after it in {pkg} ({kind})")
    return bad


def test_split_packages_import_in_order() -> None:
    """Inside agentsdk.motion, agentsdk.safety and agentsdk.cli every import points at a module listed earlier."""
    for pkg, names in PACKAGE_ORDER.items():
        inside = {m for m in MODULES if m.startswith(pkg + ".")}
        listed = {f"{pkg}.{n}" for n in names}
        assert inside == listed, f"{pkg}: unlisted {sorted(inside - listed)}, gone {sorted(listed - inside)}"
    bad = _package_violations(PACKAGE_ORDER, EDGES)
    assert not bad, "imports against the package order:\n" + "\n".join(bad)


def test_the_package_order_guard_finds_an_upward_import() -> None:
    """The package-order check is not vacuous."""
    order = {"p": ("_a", "_b")}
    assert _package_violations(order, {"p._a": {("p._b", "type")}, "p._b": {("p._a", "runtime")}}) == [
        "p._a imports p._b, listed after it in p (type)"
    ]
    assert _package_violations(order, {"p._a": {("p", "lazy")}}) != []


def _private_state(source: str, cls: str) -> set[str]:
    """The private attributes class ``cls`` of ``source`` assigns on ``self`` (its state)."""
    node = next(n for n in ast.parse(source).body if isinstance(n, ast.ClassDef) and n.name == cls)
    return {
        a.attr for a in ast.walk(node)
        if isinstance(a, ast.Attribute) and isinstance(a.ctx, ast.Store) and isinstance(a.value, ast.Name)
        and a.value.id == "self" and a.attr.startswith("_")
    }


def _reach_ins(state: set[str], sources: dict[str, str]) -> list[str]:
    """``module:line expr`` of every read or write of one of the ``state`` attributes on another object
    than ``self`` in ``sources`` (another module's classes may name their own ``self._future``)."""
    return [
        f"{m}:{a.lineno} {ast.unparse(a)}"
        for m, src in sorted(sources.items())
        for a in ast.walk(ast.parse(src))
        if isinstance(a, ast.Attribute) and a.attr in state
        and not (isinstance(a.value, ast.Name) and a.value.id in ("self", "cls"))
    ]


def test_the_motion_handle_keeps_its_state() -> None:
    """Nobody outside motion/_handle.py reads or writes a Motion's private state (its future, feedback
    snapshot, pose streams): the executor resolves and publishes through the handle's own methods."""
    state = _private_state(MODULES["agentsdk.motion._handle"].read_text(), "Motion")
    assert {"_future", "_snap", "_feedback_q", "_pose_streams"} <= state
    others = {m: p.read_text() for m, p in MODULES.items() if m != "agentsdk.motion._handle"}
    bad = _reach_ins(state, others)
    assert not bad, "reach-ins into a Motion's private state:\n" + "\n".join(bad)


def test_the_reach_in_guard_finds_one() -> None:
    """The reach-in check is not vacuous."""
    state = _private_state("class M:\n    def __init__(self):\n        self._future = 1\n        self.x = 2\n", "M")
    assert state == {"_future"}
    src = "class E:\n    def tick(self, m):\n        self._future = m._future\n        m.x = 1\n"
    assert _reach_ins(state, {"e": src}) == ["e:3 m._future"]


def _long_modules() -> dict[str, int]:
    lines = {p.relative_to(ROOT).as_posix(): len(p.read_text().splitlines()) for p in MODULES.values()}
    return {path: n for path, n in lines.items() if n > MAX_LINES}


def _documented_exceptions(doc: str) -> set[str]:
    """The module paths listed under the "Modules over ~600 lines" heading of docs/architecture.md."""
    section = doc.split("## Modules over ~600 lines", 1)[1].split("\n## ", 1)[0]
    return {line.split("`")[1] for line in section.splitlines() if line.startswith("* `")}


def test_long_modules_say_why() -> None:
    doc = (ROOT / "docs" / "architecture.md").read_text()
    listed = _documented_exceptions(doc)
    long = {path: n for path, n in _long_modules().items() if path not in listed}
    assert not long, f"modules over {MAX_LINES} lines that docs/architecture.md does not explain: {long}"


def test_documented_long_modules_are_long() -> None:
    """An exception in docs/architecture.md names a module that exists and is still over the limit."""
    listed = _documented_exceptions((ROOT / "docs" / "architecture.md").read_text())
    assert listed, "docs/architecture.md lists no long modules: the parser of its list is broken"
    stale = sorted(listed - set(_long_modules()))
    assert not stale, f"docs/architecture.md explains modules that are not over {MAX_LINES} lines (any more): {stale}"


@pytest.mark.parametrize("method", [CommandFilter.tick, _Executor._limited], ids=["filter", "executor"])
def test_filter_and_executor_do_not_clip_themselves(method: Any) -> None:
    """Neither the safety filter nor the executor's limiter check does clipping arithmetic of its own."""
    fn = ast.parse(textwrap.dedent(inspect.getsource(method))).body[0]
    cls, name = method.__qualname__.split(".")
    clipping = [
        f"line {node.lineno}: {ast.unparse(node.func)}"
        for node in ast.walk(fn)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and node.func.attr in ("maximum", "minimum", "clip", "fmax", "fmin")
    ]
    assert not clipping, f"{cls}.{name} clips by itself (use agentsdk.limits.StepLimiter): {clipping}"


async def test_filter_and_executor_limit_through_the_same_limiter(monkeypatch: pytest.MonkeyPatch) -> None:
    """The safety filter and the trajectory executor both call StepLimiter (no second copy of the math)."""
    callers: set[tuple[str, str]] = set()
    for name in ("clamp_bounds", "clamp_step"):
        original = getattr(StepLimiter, name)

        def spy(self: StepLimiter, *args: Any, _original: Any = original) -> np.ndarray:
            frame = sys._getframe(1)
            callers.add((frame.f_globals["__name__"], frame.f_code.co_name))
            result: np.ndarray = _original(self, *args)
            return result

        monkeypatch.setattr(StepLimiter, name, spy)
    async with agentsdk.connect("mock", "arm3") as robot:
        names = robot.joint_names
        start = (await robot.read()).position
        goal = [float(q) + 0.05 for q in start]
        result = await robot.follow(Trajectory(names, [TrajectoryPoint(0.2, goal)]))
        assert result.ok, result
        await robot.command(agentsdk.JointCommand("position", [float(q) + 0.02 for q in goal]))
        await robot.clock.sleep(0.05)
    assert (_Executor._limited.__module__, "_limited") in callers, callers
    assert (CommandFilter.tick.__module__, "tick") in callers, callers


#: packages whose classes are separate objects: none extends another class of its package
OBJECT_PACKAGES = ["agentsdk.motion", "agentsdk.safety"]

#: bases that make a class a value type, an enum, an exception or a pydantic model (last name of the base)
_VALUE_BASES = frozenset({
    "Enum", "IntEnum", "StrEnum", "Flag", "IntFlag", "BaseException", "Exception", "BaseModel",
    "NamedTuple", "TypedDict", "Protocol",
})


def _package_sources(package: str) -> dict[str, str]:
    return {m: p.read_text() for m, p in MODULES.items() if m == package or m.startswith(package + ".")}


def _subclass_chains(package: str, sources: dict[str, str]) -> list[str]:
    """``module: Class(Base)`` for every class in ``sources`` (module -> source text of ``package``) that
    extends a class defined in the package, unless that base is a value type (a frozen dataclass), an
    enum, an exception or a pydantic model, itself or through its own bases."""
    trees = {m: ast.parse(src, filename=m) for m, src in sources.items()}
    classes = {
        (m, node.name): node for m, tree in trees.items() for node in tree.body if isinstance(node, ast.ClassDef)
    }

    def absolute(module: str, node: ast.ImportFrom) -> str:
        if not node.level:
            return node.module or ""
        is_pkg = any(other.startswith(module + ".") for other in sources)
        base = module.split(".") if is_pkg else module.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        return ".".join([*base, node.module] if node.module else base)

    # per module: a local name -> the package class or package module it stands for
    names: dict[str, dict[str, tuple[str, str] | str]] = {}
    for m, tree in trees.items():
        local: dict[str, tuple[str, str] | str] = {name: (m, name) for mm, name in classes if mm == m}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                src = absolute(m, node)
                for a in node.names:
                    if f"{src}.{a.name}" in sources:
                        local[a.asname or a.name] = f"{src}.{a.name}"
                    elif (src, a.name) in classes:
                        local[a.asname or a.name] = (src, a.name)
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name in sources and a.asname:
                        local[a.asname] = a.name
        names[m] = local

    def resolve(m: str, expr: ast.expr) -> tuple[str, str] | None:
        """The package class a base expression names (None: not one of the package)."""
        if isinstance(expr, ast.Name):
            hit = names[m].get(expr.id)
            return hit if isinstance(hit, tuple) else None
        if isinstance(expr, ast.Attribute):
            if isinstance(expr.value, ast.Name):
                mod = names[m].get(expr.value.id)
            else:
                mod = ast.unparse(expr.value)
            if isinstance(mod, str) and (mod, expr.attr) in classes:
                return mod, expr.attr
        return None

    def is_value(key: tuple[str, str], seen: frozenset[tuple[str, str]] = frozenset()) -> bool:
        node = classes[key]
        for dec in node.decorator_list:
            if isinstance(dec, ast.Call) and "dataclass" in ast.unparse(dec.func) and any(
                k.arg == "frozen" and isinstance(k.value, ast.Constant) and k.value.value is True for k in dec.keywords
            ):
                return True
        for base in node.bases:
            if ast.unparse(base).rpartition(".")[2] in _VALUE_BASES:
                return True
            inner = resolve(key[0], base)
            if inner is not None and inner not in seen and is_value(inner, seen | {key}):
                return True
        return False

    found = []
    for (m, name), node in classes.items():
        for base in node.bases:
            target = resolve(m, base)
            if target is not None and not is_value(target):
                found.append(f"{m}: {name}({ast.unparse(base)})")
    return sorted(found)


@pytest.mark.parametrize("package", OBJECT_PACKAGES)
def test_no_class_extends_another_of_its_package(package: str) -> None:
    """The objects of a package split by objects are separate (no inheritance chain of one ``self``)."""
    sources = _package_sources(package)
    assert len(sources) > 1, f"{package} is not a package of agentsdk"
    found = _subclass_chains(package, sources)
    assert not found, (
        f"classes of {package} extending another class of the package (build a separate object and pass "
        "it in the constructor):\n" + "\n".join(found)
    )


def test_the_subclass_guard_finds_a_chain() -> None:
    """The subclass guard is not vacuous: a chain of layers is found, value types pass."""
    sources = {
        "p": "from ._c import C\n",
        "p._a": "class _Core:\n    pass\n",
        "p._b": "from ._a import _Core\n\n\nclass _Filter(_Core):\n    pass\n",
        "p._c": textwrap.dedent("""
            import enum
            from dataclasses import dataclass
            from . import _b
            from ._b import _Filter as F


            class C(_b._Filter): ...
            class D(F): ...
            class E(enum.Enum):
                A = 1
            class Err(Exception): ...
            class SubErr(Err): ...
            @dataclass(frozen=True)
            class V: ...
            class W(V): ...
            class Local: ...
            class Same(Local): ...
        """),
    }
    assert _subclass_chains("p", sources) == [
        "p._b: _Filter(_Core)", "p._c: C(_b._Filter)", "p._c: D(F)", "p._c: Same(Local)",
    ]
    del sources["p._b"], sources["p._c"]
    assert _subclass_chains("p", sources) == []


#: MuJoCo calls that compile or load a model
_COMPILES = ("compile", "from_xml_path", "from_xml_string", "from_binary_path", "from_file", "from_string")
#: the model stack and the core modules, which use the robot's one host model
_HOST_MODEL_USERS = ("agentsdk.kinematics", "agentsdk.ik", "agentsdk.dynamics", "agentsdk.feedforward",
                     "agentsdk.backendspec", "agentsdk.backend", "agentsdk.robot", "agentsdk.cartesian",
                     "agentsdk.arm")


def _compile_calls(source: str, label: str) -> list[str]:
    """``label:line name`` of every call of a MuJoCo compile/load method in ``source`` (``HostModel.compile``,
    the shared model's own constructor, excepted)."""
    return [
        f"{label}:{node.lineno} {ast.unparse(node.func)}"
        for node in ast.walk(ast.parse(source, filename=label))
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in _COMPILES
        and ast.unparse(node.func.value) != "HostModel"
    ]


def _module_compiles(module: str) -> list[str]:
    path = MODULES[module]
    return _compile_calls(path.read_text(), str(path.relative_to(ROOT)))


def test_the_host_model_is_compiled_in_one_place() -> None:
    found = [c for m in _HOST_MODEL_USERS for c in _module_compiles(m)]
    assert not found, f"compile the host model with agentsdk.hostmodel.compile_spec (HostModel), not: {found}"
    in_hostmodel = _module_compiles("agentsdk.hostmodel")
    assert len(in_hostmodel) == 1 and in_hostmodel[0].endswith(" spec.compile"), in_hostmodel


def test_the_compile_guard_finds_a_compile() -> None:
    """The compile finder is not vacuous."""
    src = "import mujoco\nm = mujoco.MjModel.from_xml_path('x')\nn = spec.compile()\nk = HostModel.compile(d)\n"
    assert _compile_calls(src, "probe") == ["probe:2 mujoco.MjModel.from_xml_path", "probe:3 spec.compile"]
