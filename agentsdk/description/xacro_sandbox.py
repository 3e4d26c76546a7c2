"""xacro expansion as data: a checked expression evaluator, run in a worker process with limits.

A xacro file is a robot *description*, downloaded and loaded like data; xacro itself
evaluates every ``${...}`` and ``$(eval ...)`` with Python's ``eval``, whose
"no builtins" sandbox is escaped in one line (``python.vars``,
``().__class__.__bases__[0].__subclasses__()``). So the SDK never lets xacro
evaluate an expression it has not checked:

* **An allow-list over the expression's syntax tree.** Literals, arithmetic,
  comparisons, boolean operators, conditional expressions, names of properties,
  subscripts, tuples/lists/dicts/sets and comprehensions over them are allowed;
  lambdas, f-strings, ``:=``, attribute names starting with ``_`` and names
  starting with ``__`` are refused before anything runs.
* **Calls and attribute reads are checked when they run.** A call must reach one
  of the functions xacro documents (``math.*``, the ``python.*`` builtins except
  ``type`` and ``vars``, ``xacro.*`` such as ``load_yaml``, ``dotify``, ``arg``,
  ``tokenize``), or a pure method of a string, number, list, tuple, dict or set
  (``'a b'.split()``); functions handed to ``map``/``filter``/``key=`` are
  checked the same way. An attribute read is a key of a xacro namespace or
  ``load_yaml`` dict (``math.pi``, ``props.arm.length``) or one of those methods.
* **Sizes are bounded before they are computed.** ``**``, ``*`` and ``<<`` refuse
  a result larger than :data:`MAX_INT_BITS` bits or :data:`MAX_SEQUENCE` items
  (``${9**9**8}``, ``${'a'*10**10}``) instead of computing it.
* **Files stay inside the package roots.** ``xacro:include`` and ``load_yaml``
  open only files whose real path (symlinks followed) is inside one of the roots
  the parent process passes (the description's package, the packages found by
  ``$(find)``, the directories of the package search path).
* **Limits.** The expansion runs in this module as a separate process (``python
  -P xacro_sandbox.py``) with an address-space limit, no file writes
  (``RLIMIT_FSIZE`` 0) and no child processes; once it has started (imports
  done) it arms a wall-clock alarm and a CPU-time limit of the job's seconds, and
  the parent kills it if it has not answered a start-up allowance later.
  xacro's module state (its file and macro stacks, the
  ``ament_index_python`` module answering ``$(find)``) lives and dies with the
  worker, so nothing in the caller's process changes.

A refused expression or path is reported with the file, the line and the
construct. ``trusted=True`` runs xacro's own evaluator, without checks (the
limits still apply). This module imports only the standard library at the top
level, so that the worker starts fast; xacro is imported in the worker only.
"""

from __future__ import annotations

import ast
import contextlib
import importlib.util
import io
import json
import math
import os
import re
import signal
import sys
import types
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "MAX_INCLUDE_DEPTH",
    "MAX_INT_BITS",
    "MAX_SEQUENCE",
    "ExpressionRefused",
    "PathRefused",
    "SandboxRefusal",
    "check_expression",
]

#: the largest integer an expression may produce by ``**``, ``*`` or ``<<`` (bits)
MAX_INT_BITS = 1 << 14
#: the longest string/list/tuple an expression may produce by ``*`` (items)
MAX_SEQUENCE = 1 << 20
#: how deep ``xacro:include`` may nest
MAX_INCLUDE_DEPTH = 32

_REFUSED_NODES: dict[type[ast.AST], str] = {
    ast.Lambda: "a lambda",
    ast.JoinedStr: "an f-string",
    ast.FormattedValue: "an f-string",
    ast.NamedExpr: "an assignment expression (:=)",
    ast.Await: "await",
    ast.Yield: "yield",
    ast.YieldFrom: "yield from",
}
_ALLOWED_NODES: tuple[type[ast.AST], ...] = (
    ast.Expression,
    ast.Constant,
    ast.Name,
    ast.BinOp,
    ast.UnaryOp,
    ast.BoolOp,
    ast.Compare,
    ast.IfExp,
    ast.Call,
    ast.keyword,
    ast.Attribute,
    ast.Subscript,
    ast.Slice,
    ast.Tuple,
    ast.List,
    ast.Dict,
    ast.Set,
    ast.Starred,
    ast.ListComp,
    ast.SetComp,
    ast.DictComp,
    ast.GeneratorExp,
    ast.comprehension,
    ast.operator,
    ast.unaryop,
    ast.cmpop,
    ast.boolop,
    ast.expr_context,
)

_NUMBER_METHODS = frozenset({"real", "imag", "conjugate", "bit_length", "is_integer"})
_SAFE_METHODS: dict[type, frozenset[str]] = {
    str: frozenset(
        {
            "upper", "lower", "title", "capitalize", "casefold", "swapcase", "strip", "lstrip", "rstrip",
            "split", "rsplit", "splitlines", "startswith", "endswith", "replace", "find", "rfind", "index",
            "rindex", "count", "isdigit", "isalpha", "isalnum", "isspace", "isupper", "islower", "isnumeric",
            "isdecimal", "join", "partition", "rpartition", "removeprefix", "removesuffix",
        }
    ),
    list: frozenset({"index", "count", "copy"}),
    tuple: frozenset({"index", "count"}),
    dict: frozenset({"keys", "values", "items", "get", "copy"}),
    set: frozenset({"union", "intersection", "difference", "symmetric_difference", "issubset", "issuperset",
                    "isdisjoint", "copy"}),
    frozenset: frozenset({"union", "intersection", "difference", "symmetric_difference", "issubset",
                          "issuperset", "isdisjoint", "copy"}),
    bool: _NUMBER_METHODS,
    int: _NUMBER_METHODS,
    float: _NUMBER_METHODS,
    complex: _NUMBER_METHODS,
}
#: builtins xacro exposes in its ``python`` namespace that reach object internals
_UNSAFE_BUILTINS = (type, vars)


class SandboxRefusal(Exception):
    """Base of what the sandbox refuses; ``where`` is filled in with the file and line when known."""

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message
        self.where = ""

    def __str__(self) -> str:
        return f"{self.where}: {self.message}" if self.where else self.message


class ExpressionRefused(SandboxRefusal):
    """A ``${...}`` or ``$(eval ...)`` expression uses a construct outside the allow-list."""


class PathRefused(SandboxRefusal):
    """A file the expansion would open lies outside the package roots."""


# --------------------------------------------------------------------------- the static check


def _describe_node(node: ast.AST) -> str:
    try:
        return ast.unparse(node)
    except Exception:  # pragma: no cover - unparse handles every expression node
        return type(node).__name__


def check_expression(expr: str) -> ast.Expression:
    """Parse ``expr`` and check it against the allow-list; raises :class:`ExpressionRefused`."""
    try:
        tree = ast.parse(expr.strip(), mode="eval")
    except SyntaxError as exc:
        raise ExpressionRefused(f"is not a valid expression ({exc.msg})") from None
    except (ValueError, MemoryError, RecursionError) as exc:
        raise ExpressionRefused(f"cannot be parsed ({type(exc).__name__})") from None
    for node in ast.walk(tree):
        refused = _REFUSED_NODES.get(type(node))
        if refused is not None:
            raise ExpressionRefused(f"uses {refused} ({_describe_node(node)!r})")
        if not isinstance(node, _ALLOWED_NODES):
            raise ExpressionRefused(f"uses {type(node).__name__} ({_describe_node(node)!r}), not allowed")
        if isinstance(node, ast.Name) and node.id.startswith("__"):
            raise ExpressionRefused(f"uses the name {node.id!r} (names starting with '__' are refused)")
        if isinstance(node, ast.Attribute):
            if node.attr.startswith("_"):
                raise ExpressionRefused(
                    f"reads the attribute {node.attr!r} ({_describe_node(node)!r}); "
                    "attributes starting with '_' are refused"
                )
            if not isinstance(node.ctx, ast.Load):
                raise ExpressionRefused(f"assigns the attribute {node.attr!r}")
        if isinstance(node, ast.Subscript) and not isinstance(node.ctx, ast.Load):
            raise ExpressionRefused(f"assigns to a subscript ({_describe_node(node)!r})")
    return tree


_BINOPS = {ast.Pow: "pow", ast.Mult: "mul", ast.LShift: "lshift"}


class _Guard(ast.NodeTransformer):
    """Route calls, attribute reads and size-amplifying operators through the runtime guards."""

    @staticmethod
    def _call(name: str, node: ast.AST, args: list[ast.expr], keywords: list[ast.keyword] | None = None) -> ast.Call:
        call = ast.Call(func=ast.Name(id=name, ctx=ast.Load()), args=args, keywords=keywords or [])
        return ast.copy_location(call, node)

    def visit_Call(self, node: ast.Call) -> ast.AST:
        self.generic_visit(node)
        return self._call("__sb_call", node, [node.func, *node.args], node.keywords)

    def visit_Attribute(self, node: ast.Attribute) -> ast.AST:
        self.generic_visit(node)
        return self._call("__sb_getattr", node, [node.value, ast.Constant(node.attr)])

    def visit_BinOp(self, node: ast.BinOp) -> ast.AST:
        self.generic_visit(node)
        op = _BINOPS.get(type(node.op))
        if op is None:
            return node
        return self._call("__sb_binop", node, [ast.Constant(op), node.left, node.right])


def _int_bits(value: int) -> int:
    return abs(value).bit_length()


def _checked_binop(op: str, a: Any, b: Any) -> Any:
    ints = isinstance(a, int) and isinstance(b, int)
    if op == "pow":
        if ints and b > 0 and abs(a) > 1 and b * math.log2(abs(a)) > MAX_INT_BITS:
            raise ExpressionRefused(f"computes {a}**{b}, an integer of more than {MAX_INT_BITS} bits")
        return a**b
    if op == "lshift":
        if ints and b > 0 and _int_bits(a) + b > MAX_INT_BITS:
            raise ExpressionRefused(f"computes {a} << {b}, an integer of more than {MAX_INT_BITS} bits")
        return a << b
    seq, count = (a, b) if isinstance(b, int) else (b, a)
    if isinstance(seq, str | bytes | list | tuple) and isinstance(count, int):
        if len(seq) * max(count, 0) > MAX_SEQUENCE:
            raise ExpressionRefused(
                f"repeats a sequence of {len(seq)} items {count} times (more than {MAX_SEQUENCE} items)"
            )
    elif ints and _int_bits(a) + _int_bits(b) > MAX_INT_BITS:
        raise ExpressionRefused(f"multiplies integers into more than {MAX_INT_BITS} bits")
    return a * b


def _callable_name(f: Any) -> str:
    name = getattr(f, "__qualname__", None) or getattr(f, "__name__", None)
    return str(name) if name else type(f).__name__


class Evaluator:
    """The checked evaluator: compiles an expression after :func:`check_expression` and runs it guarded.

    ``allowed`` are the callables an expression may call (by identity); ``special`` maps some of
    them to a wrapper that checks their arguments first (``load_yaml``'s path); ``namespaces`` are
    the types whose attributes are their keys (xacro's namespaces and ``load_yaml`` dicts).
    """

    def __init__(
        self,
        allowed: Iterable[Any],
        special: Mapping[int, Callable[..., Any]],
        namespaces: tuple[type, ...],
    ) -> None:
        self._allowed = {id(f): f for f in allowed if callable(f) and not any(f is u for u in _UNSAFE_BUILTINS)}
        self._special = dict(special)
        self._namespaces = namespaces
        self._takes_function = {id(f) for f in (map, filter)}
        self.guards: dict[str, Any] = {
            "__builtins__": {},
            "__sb_call": self.call,
            "__sb_getattr": self.getattr,
            "__sb_binop": _checked_binop,
        }

    def compile(self, expr: str) -> types.CodeType:
        """Check ``expr`` and compile it with its calls, attributes and operators guarded."""
        tree = _Guard().visit(check_expression(expr))
        ast.fix_missing_locations(tree)
        return compile(tree, "<expression>", "eval")

    def _safe_method(self, f: Any) -> bool:
        owner = getattr(f, "__self__", None)
        if not isinstance(f, types.BuiltinMethodType) or owner is None or isinstance(owner, types.ModuleType):
            return False
        for kind, names in _SAFE_METHODS.items():
            if isinstance(owner, kind) and f.__name__ in names:
                return True
        return False

    def checked(self, f: Any) -> Any:
        """``f`` wrapped so that calling it goes through :meth:`call` (for ``map``, ``key=``)."""
        if not callable(f):
            return f  # let the builtin raise its own TypeError (or take None, as filter does)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            return self.call(f, *args, **kwargs)

        return wrapper

    def call(self, f: Any, *args: Any, **kwargs: Any) -> Any:
        """Call ``f`` if it is an allowed function or a pure method; else refuse."""
        special = self._special.get(id(f))
        if special is not None and self._allowed.get(id(f)) is f:
            return special(*args, **kwargs)
        if self._allowed.get(id(f)) is not f and not self._safe_method(f):
            raise ExpressionRefused(
                f"calls {_callable_name(f)!r}, which is not one of the math/builtin/xacro functions xacro documents"
            )
        if id(f) in self._takes_function and args:
            args = (self.checked(args[0]), *args[1:])
        if "key" in kwargs:
            kwargs["key"] = self.checked(kwargs["key"])
        return f(*args, **kwargs)

    def getattr(self, obj: Any, name: str) -> Any:
        """``obj.name`` for a namespace key or a pure method; else refuse."""
        if isinstance(obj, self._namespaces):
            space: Any = obj
            if name in space:
                value = space[name]
                if any(value is unsafe for unsafe in _UNSAFE_BUILTINS):
                    raise ExpressionRefused(f"reads {name!r}, which reaches object internals and is not allowed")
                return value
            if isinstance(obj, dict) and name in _SAFE_METHODS[dict]:
                return getattr(obj, name)
            raise NameError(f"name '{name}' is not defined")
        for kind, names in _SAFE_METHODS.items():
            if isinstance(obj, kind) and name in names:
                return getattr(obj, name)
        raise ExpressionRefused(f"reads the attribute {name!r} of a {type(obj).__name__}, which is not allowed")

    def eval(self, expr: str, names: Mapping[str, Any], *, as_globals: bool = False) -> Any:
        """Evaluate ``expr`` with ``names`` as its names.

        ``as_globals``: ``names`` is a dict used as the globals (xacro's property table, so that
        comprehensions see the properties too, as in xacro); the guards are added to it.
        """
        code = self.compile(expr)
        if as_globals:
            assert isinstance(names, dict)
            dict.update(names, self.guards)
            return eval(code, names)
        return eval(code, self.guards, names)


# --------------------------------------------------------------------------- paths


def _line_of(file: str | None, needle: str) -> int | None:
    if not file or not needle:
        return None
    try:
        text = Path(file).read_text(encoding="utf-8", errors="replace")
    except (OSError, ValueError):
        return None
    index = text.find(needle)
    return None if index < 0 else text.count("\n", 0, index) + 1


# --------------------------------------------------------------------------- error text


def xacro_error_text(exc: BaseException, own: tuple[type[BaseException], ...] = ()) -> str:
    """One line for a failed expansion: our own error if one is in the chain, else xacro's text."""
    from xml.parsers.expat import ExpatError

    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:  # unwrap to our own error, if any
        seen.add(id(cur))
        if isinstance(cur, own):
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


def _in_chain(exc: BaseException, kind: type[BaseException]) -> BaseException | None:
    """The first exception of type ``kind`` in ``exc``'s chain (xacro's ``.exc``, causes, contexts)."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        if isinstance(cur, kind):
            return cur
        cur = getattr(cur, "exc", None) or cur.__cause__ or cur.__context__
    return None


def _refusal_in(exc: BaseException) -> SandboxRefusal | None:
    found = _in_chain(exc, SandboxRefusal)
    return found if isinstance(found, SandboxRefusal) else None


# --------------------------------------------------------------------------- the worker


class _PackageNotFound(Exception):
    pass


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


#: environment variables the worker read through ``os.environ`` (name -> value, None if unset)
_ENV_READ: dict[str, str | None] = {}
#: set when the worker iterated the whole environment (then every variable counts as read)
_ENV_READ_ALL: list[bool] = []


class _TrackedEnviron(type(os.environ)):  # type: ignore[misc]  # os._Environ is private
    """``os.environ`` recording what the worker reads, so that the parent caches on exactly that."""

    def __getitem__(self, key: str) -> str:
        try:
            value: str = super().__getitem__(key)
        except KeyError:
            _ENV_READ.setdefault(key, None)
            raise
        _ENV_READ.setdefault(key, value)
        return value

    def __iter__(self) -> Iterator[str]:
        _ENV_READ_ALL.append(True)
        return super().__iter__()  # type: ignore[no-any-return]


def _set_limits(seconds: float, memory: int) -> None:
    """Limit what the expansion may use from now on: CPU time, memory, files, processes, and wall time.

    Called once the worker has started (interpreter, xacro, lxml imported): the start-up of a
    process is the machine's cost, not the document's, and takes seconds in a slow VM. The wall
    clock runs out by ``SIGALRM``, whose default action ends the process even inside a long C call.
    """
    if hasattr(signal, "setitimer"):
        signal.signal(signal.SIGALRM, signal.SIG_DFL)
        signal.setitimer(signal.ITIMER_REAL, max(seconds, 1e-3))
    try:
        import resource
    except ImportError:  # pragma: no cover - not a POSIX system: the parent's deadline still applies
        return
    usage = resource.getrusage(resource.RUSAGE_SELF)
    used = usage.ru_utime + usage.ru_stime
    limits = [
        (resource.RLIMIT_CPU, math.ceil(used) + max(1, math.ceil(seconds)) + 1),
        (resource.RLIMIT_FSIZE, 0),
    ]
    if memory > 0:
        limits.append((resource.RLIMIT_AS, memory))
    if hasattr(resource, "RLIMIT_NPROC"):
        limits.append((resource.RLIMIT_NPROC, 0))
    for which, value in limits:
        with contextlib.suppress(ValueError, OSError):
            _soft, hard = resource.getrlimit(which)
            if hard != resource.RLIM_INFINITY and value > hard:
                value = hard
            resource.setrlimit(which, (value, hard))


def _load_packages_module() -> Any:
    """The SDK's package search (``packages.py``, stdlib and lxml only), loaded by path."""
    spec = importlib.util.spec_from_file_location("_agentsdk_packages", Path(__file__).with_name("packages.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _install_find(find: Callable[[str], str]) -> None:
    """Answer xacro's ``$(find pkg)`` (``ament_index_python``) with ``find``, in this worker process."""
    real: Any = None
    with contextlib.suppress(Exception):
        real = importlib.import_module("ament_index_python.packages")

    def get_package_share_directory(package_name: str, print_warning: bool = True) -> str:
        try:
            return find(package_name)
        except _PackageNotFound:
            if real is not None and hasattr(real, "get_package_share_directory"):
                with contextlib.suppress(Exception):
                    return str(real.get_package_share_directory(package_name))
            raise

    root = types.ModuleType("ament_index_python")
    packages = types.ModuleType("ament_index_python.packages")
    packages.get_package_share_directory = get_package_share_directory  # type: ignore[attr-defined]
    packages.PackageNotFoundError = _PackageNotFound  # type: ignore[attr-defined]
    root.packages = packages  # type: ignore[attr-defined]
    sys.modules["ament_index_python"] = root
    sys.modules["ament_index_python.packages"] = packages


class _ArgNames(Mapping[str, Any]):
    """``$(eval ...)``'s names: the functions, then the xacro args (converted like roslaunch does)."""

    def __init__(self, args: Mapping[str, str], functions: Mapping[str, Any], convert: Callable[..., Any]) -> None:
        self._args = args
        self._functions = functions
        self._convert = convert

    def __getitem__(self, key: str) -> Any:
        if key in self._functions:
            return self._functions[key]
        return self._convert(self._args[key], "auto")

    def __iter__(self) -> Iterator[str]:
        return iter({**self._functions, **self._args})

    def __len__(self) -> int:
        return len({**self._functions, **self._args})


def _expand(job: Mapping[str, Any]) -> dict[str, Any]:
    """Expand one xacro file as the job describes; the result (or error) as a JSON-able dict."""
    import xacro
    import xacro.substitution_args as substitution_args

    path = Path(job["path"])
    trusted = bool(job.get("trusted"))
    packages = _load_packages_module()
    resolver = packages.Resolver(
        path.parent, [Path(p) for p in job.get("package_path", [])], [Path(p) for p in job.get("roots", [])]
    )
    roots: list[Path] = resolver.roots()

    def find(package: str) -> str:
        root = resolver.package(package)
        if root is None:
            raise _PackageNotFound(
                f"$(find {package}): package '{package}' not found; "
                f"{packages.search_path_text(resolver.package_path, resolver.base_dir)}"
            )
        if not trusted and not resolver.is_package_root(root):
            raise PathRefused(
                f"$(find {package}) found {root}, a directory named like the package but without a "
                "package.xml, outside the package roots"
            )
        roots.append(root)
        return str(root)

    _install_find(find)

    def current_file() -> str | None:
        stack = xacro.filestack or []
        return str(stack[-1]) if stack and stack[-1] else None

    def place(refusal: SandboxRefusal, needle: str) -> SandboxRefusal:
        if not refusal.where:
            file = current_file() or str(path)
            line = _line_of(file, needle)
            refusal.where = f"{file}:{line}" if line else file
        return refusal

    def roots_text() -> str:
        return ", ".join(str(r) for r in dict.fromkeys(roots))

    def check_path(spec: str, what: str) -> None:
        target = xacro.abs_filename_spec(spec)
        if not packages.path_inside(target, roots):
            raise PathRefused(
                f"{what} '{spec}' refused: {os.path.realpath(target)} is outside the package roots ({roots_text()})"
            )

    if not trusted:
        evaluators: dict[int, Evaluator] = {}

        def evaluator_for(root: dict[str, Any]) -> Evaluator:
            found = evaluators.get(id(root))
            if found is not None:
                return found
            namespaces = (*{type(v) for v in root.values() if isinstance(v, dict)}, xacro.YamlDictWrapper)
            allowed: list[Any] = []
            for value in root.values():
                allowed.extend(value.values() if isinstance(value, dict) else [value])

            def load_yaml_checked(original: Callable[..., Any]) -> Callable[..., Any]:
                def checked(filename: Any, *args: Any, **kwargs: Any) -> Any:
                    try:
                        check_path(str(filename), "load_yaml of")
                    except PathRefused as exc:
                        raise place(exc, str(filename)) from None
                    return original(filename, *args, **kwargs)

                return checked

            xacro_ns = root.get("xacro")
            loaders = [root.get("load_yaml"), xacro_ns.get("load_yaml") if isinstance(xacro_ns, dict) else None]
            special = {id(f): load_yaml_checked(f) for f in loaders if f is not None}
            found = evaluators[id(root)] = Evaluator(allowed, special, namespaces)
            return found

        def safe_eval(expr: str, globals: dict[str, Any], locals: Mapping[str, Any] | None = None) -> Any:
            root = getattr(globals, "root", globals)  # xacro's Table keeps its global symbols in .root
            try:
                if locals is not None:
                    return evaluator_for(root).eval(expr, locals)
                return evaluator_for(root).eval(expr, globals, as_globals=True)
            except SandboxRefusal as exc:
                if not exc.where:
                    exc.message = f"xacro expression '${{{expr.strip()}}}' refused: it {exc.message}"
                raise place(exc, expr.strip()) from None

        def substitution_eval(expr: str, context: dict[str, Any]) -> str:
            arg_values: dict[str, str] = context.setdefault("arg", {})

            def arg(name: str) -> Any:
                if name not in arg_values:
                    raise substitution_args.ArgException(name)
                return substitution_args.convert_value(arg_values[name], "auto")

            def dirname() -> str:
                filename = context.get("filename")
                if not filename:
                    raise substitution_args.SubstitutionException("$(dirname) has no file information")
                return os.path.abspath(os.path.dirname(str(filename)))

            def env(name: str) -> str:
                if name not in os.environ:
                    raise substitution_args.SubstitutionException(f"environment variable {name} is not set")
                return os.environ[name]

            def optenv(name: str, default: str = "") -> str:
                return os.environ.get(name, default)

            functions: dict[str, Any] = {k: v for k, v in vars(math).items() if not k.startswith("_")}
            functions.update(arg=arg, dirname=dirname, env=env, optenv=optenv, find=find)
            local = Evaluator(functions.values(), {}, ())
            try:
                return str(local.eval(expr, _ArgNames(arg_values, functions, substitution_args.convert_value)))
            except SandboxRefusal as exc:
                if not exc.where:
                    exc.message = f"$(eval {expr.strip()}) refused: it {exc.message}"
                raise place(exc, expr.strip()) from None

        original_parse = xacro.parse

        def parse(inp: Any, filename: str | None = None) -> Any:
            if inp is None and filename is not None and len(xacro.filestack) > 1:
                stack = [os.path.realpath(f) for f in xacro.filestack[:-1] if f]
                problem = ""
                if os.path.realpath(filename) in stack:
                    problem = f"xacro:include of '{filename}' refused: an include cycle (the file includes itself)"
                elif len(stack) >= MAX_INCLUDE_DEPTH:
                    problem = (
                        f"xacro:include of '{filename}' refused: includes nested more than {MAX_INCLUDE_DEPTH} deep"
                    )
                if problem:
                    xacro.filestack.pop()
                    raise place(PathRefused(problem), os.path.basename(filename))
            if inp is None and filename is not None and not packages.path_inside(filename, roots):
                exc = PathRefused(
                    f"xacro:include of '{filename}' refused: {os.path.realpath(filename)} is outside the package "
                    f"roots ({roots_text()})"
                )
                if len(xacro.filestack) > 1:
                    xacro.filestack.pop()  # the include pushed it: report the including file
                raise place(exc, os.path.basename(filename))
            return original_parse(inp, filename)

        # this worker process exists for this one expansion: its xacro evaluates through the checks
        xacro.safe_eval = safe_eval
        xacro.parse = parse
        substitution_args._eval = substitution_eval

    mappings = _TrackedArgs({str(k): str(v) for k, v in dict(job.get("args", {})).items()})
    captured = io.StringIO()
    printed = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured), contextlib.redirect_stdout(printed):
            doc = xacro.process_file(str(path), mappings=mappings)
            text = str(doc.toxml())
    except (Exception, SystemExit) as exc:
        warnings = captured.getvalue()
        refusal = _refusal_in(exc)
        if refusal is not None:
            return {"ok": False, "refused": True, "error": str(refusal), "warnings": warnings}
        if _in_chain(exc, MemoryError):
            return {"ok": False, "limit": "memory", "error": "", "warnings": warnings}
        if _in_chain(exc, RecursionError):
            return {"ok": False, "where": "", "error": "nested too deeply (RecursionError)", "warnings": warnings}
        where = ""
        macros = [m.body.getAttribute("name") for m in (xacro.macrostack or []) if hasattr(m, "body")]
        files = [f for f in (xacro.filestack or []) if f]
        if macros:
            where += f" (in macro '{macros[-1]}')"
        if files and Path(files[-1]).resolve() != path:
            where += f" (in included file {files[-1]})"
        detail = xacro_error_text(exc, (_PackageNotFound,))
        return {"ok": False, "where": where, "error": detail, "warnings": warnings}
    files = [str(path), *(str(f) for f in getattr(xacro, "all_includes", []) if f)]
    return {
        "ok": True,
        "xml": text,
        "queried": sorted(mappings.queried),
        "warnings": captured.getvalue(),
        "files": files,
    }


def main() -> int:
    """Worker entry point: a JSON job on stdin, a JSON result on stdout."""
    os.environ.__class__ = _TrackedEnviron  # what the imports and the expansion read decides the cache
    job = json.loads(sys.stdin.buffer.read().decode("utf-8"))
    import xacro  # noqa: F401 - imported before the memory limit, like the rest of the worker's code
    import yaml  # noqa: F401
    from lxml import etree  # noqa: F401

    _set_limits(float(job.get("seconds", 10.0)), int(job.get("memory", 0)))
    try:
        result = _expand(job)
    except MemoryError:
        result = {"ok": False, "limit": "memory", "error": "", "warnings": ""}
    except RecursionError:
        result = {"ok": False, "error": "nesting too deep (RecursionError)", "where": "", "warnings": ""}
    if hasattr(signal, "setitimer"):
        signal.setitimer(signal.ITIMER_REAL, 0.0)  # done: writing the answer is not the document's time
    result["environ"] = None if _ENV_READ_ALL else dict(_ENV_READ)
    out = json.dumps(result).encode("utf-8")
    sys.stdout.buffer.write(out)
    sys.stdout.buffer.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
