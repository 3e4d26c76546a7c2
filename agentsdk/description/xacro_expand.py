"""xacro expansion with ``$(find pkg)`` answered by the SDK's package search."""

from __future__ import annotations

import contextlib
import io
import logging
import re
import sys
import threading
import types
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import cast
from xml.parsers.expat import ExpatError

from ..errors import DescriptionError
from .packages import Resolver, search_path_text

__all__ = ["run_xacro"]

log = logging.getLogger("agentsdk.description")

# xacro keeps its state in module globals: one expansion at a time
_XACRO_LOCK = threading.Lock()


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
    """Answer xacro's ``$(find pkg)`` with our package search, through xacro's documented route.

    In ROS 2, xacro resolves ``$(find pkg)`` with
    ``ament_index_python.packages.get_package_share_directory`` (imported when the
    substitution is evaluated). Outside a ROS install that module does not exist, so for
    the duration of one expansion (under ``_XACRO_LOCK``) an ``ament_index_python``
    module answered by :func:`find` is registered in ``sys.modules``; the ROS one, if any,
    is put back afterwards (and ``find`` falls back to it for packages we cannot find).
    No attribute of xacro itself is touched.
    """
    names = ("ament_index_python", "ament_index_python.packages")
    saved = {name: sys.modules.get(name) for name in names}
    real = saved["ament_index_python.packages"]

    def get_package_share_directory(package_name: str, print_warning: bool = True) -> str:
        try:
            return find(package_name)
        except _PackageNotFound:
            if real is not None and hasattr(real, "get_package_share_directory"):
                try:
                    return str(real.get_package_share_directory(package_name))
                except Exception:
                    pass
            raise

    root = types.ModuleType("ament_index_python")
    packages = types.ModuleType("ament_index_python.packages")
    packages.get_package_share_directory = get_package_share_directory  # type: ignore[attr-defined]
    packages.PackageNotFoundError = _PackageNotFound  # type: ignore[attr-defined]
    root.packages = packages  # type: ignore[attr-defined]
    sys.modules["ament_index_python"] = root
    sys.modules["ament_index_python.packages"] = packages
    try:
        yield
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


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


def run_xacro(path: Path, args: Mapping[str, str], resolver: Resolver) -> str:
    """Expand ``path`` with xacro args ``args``; raises DescriptionError naming the file, macro and problem."""
    try:
        import xacro
    except ImportError as exc:  # pragma: no cover - xacro is a dependency
        raise DescriptionError(f"{path}: the 'xacro' package is needed to expand xacro files") from exc

    def find(package: str) -> str:
        root = resolver.package(package)
        if root is None:
            raise _PackageNotFound(
                f"$(find {package}): package '{package}' not found; "
                f"{search_path_text(resolver.package_path, resolver.base_dir)}"
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
