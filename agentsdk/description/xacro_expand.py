"""xacro expansion in a sandboxed worker process (see :mod:`.xacro_sandbox`).

The caller's process never runs xacro: each expansion starts ``python -P
xacro_sandbox.py`` with the job as JSON on its stdin, under a time limit
(:data:`XACRO_TIME_LIMIT`, wall clock and CPU time, counted once the worker has started:
starting a Python process is the machine's cost, seconds in a loaded VM) and an
address-space limit (:data:`XACRO_MEMORY_LIMIT`). The parent kills a worker that has not
answered :data:`XACRO_START_ALLOWANCE` seconds after that limit.
The worker answers ``$(find pkg)`` with the SDK's package search, checks every
expression and every file it opens unless the file is ``trusted``, and returns the
expanded XML or a one-line error, which becomes a :class:`DescriptionError`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import signal
import subprocess
import sys
import threading
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..errors import DescriptionError
from .packages import Resolver

__all__ = ["TRUST_HINT", "XACRO_MEMORY_LIMIT", "XACRO_START_ALLOWANCE", "XACRO_TIME_LIMIT", "run_xacro"]

log = logging.getLogger("agentsdk.description")

#: seconds one xacro expansion may take (wall clock, and about as much CPU time), from the moment its
#: worker process has started and imported xacro
XACRO_TIME_LIMIT = 20.0
#: seconds a worker process may take to start (interpreter and imports) before its expansion's own limit
#: runs; the parent's backstop for a worker that never gets as far as arming that limit
XACRO_START_ALLOWANCE = 60.0
#: bytes of address space the expansion worker may use
XACRO_MEMORY_LIMIT = 1 << 30
#: how to lift the checks, appended to a refusal
TRUST_HINT = (
    "robot files are loaded as data; for a file you trust, pass trusted=True "
    "(robot.yaml `trusted: true`, CLI --trusted)"
)

_WORKER = Path(__file__).with_name("xacro_sandbox.py")

# Expansions are cached in this process (a worker process costs a few hundred ms, seconds in a slow
# VM, and a test suite connects to the same xacro robot hundreds of times): an entry is used only
# while the job (file, args, search path, trust, limits), the working directory and the variables
# that shape the worker's interpreter (_PROCESS_ENV) are the same, every environment variable the
# worker read (its $(env)/$(optenv), the package search path) has the same value, and every file the
# expansion read has the same content (SHA-256). Other variables, such as the PYTEST_CURRENT_TEST
# that changes with every test, do not make a connect expand the same file again.
_CACHE_SIZE = 32
_MAX_CACHED_FILE = 1 << 24
#: prefixes of the environment variables read before the worker's code runs (interpreter, loader, libxml2)
_PROCESS_ENV = ("PYTHON", "LD_", "XML_")
_cache: OrderedDict[str, tuple[dict[str, Any], tuple[tuple[str, str], ...], dict[str, str | None]]] = OrderedDict()
_cache_lock = threading.Lock()


def _stamps(files: Sequence[str]) -> tuple[tuple[str, str], ...] | None:
    out = []
    for name in files:
        try:
            with open(name, "rb") as f:
                digest = hashlib.sha256(f.read(_MAX_CACHED_FILE + 1)).hexdigest()
        except (OSError, ValueError):
            return None
        out.append((name, digest))
    return tuple(out)


def _cache_key(job: Mapping[str, Any]) -> str:
    process_env = sorted((k, v) for k, v in os.environ.items() if k.startswith(_PROCESS_ENV))
    return json.dumps([job, process_env, os.getcwd()], sort_keys=True)


def _cached(key: str) -> dict[str, Any] | None:
    with _cache_lock:
        entry = _cache.get(key)
        if entry is not None:
            _cache.move_to_end(key)
    if entry is None:
        return None
    result, stamps, environ = entry
    if any(os.environ.get(name) != value for name, value in environ.items()):
        return None
    if _stamps([name for name, _ in stamps]) != stamps:
        return None
    return result


def _remember(key: str, result: dict[str, Any]) -> None:
    stamps = _stamps([str(f) for f in result.get("files", ())])
    if stamps is None:
        return
    read = result.get("environ")
    if read is None:  # the worker listed the whole environment: any change may change its answer
        return
    environ: dict[str, str | None] = {str(k): v for k, v in read.items()}
    with _cache_lock:
        _cache[key] = (result, stamps, environ)
        _cache.move_to_end(key)
        while len(_cache) > _CACHE_SIZE:
            _cache.popitem(last=False)


def _worker_result(path: Path, job: Mapping[str, Any], seconds: float) -> dict[str, Any]:
    """Run one worker; its own limits count from its start-up, the parent's backstop adds the start-up."""
    try:
        proc = subprocess.Popen(
            [sys.executable, "-P", str(_WORKER)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
    except OSError as exc:
        raise DescriptionError(f"{path}: cannot start the xacro worker: {exc}") from exc
    try:
        out, err = proc.communicate(json.dumps(job).encode("utf-8"), timeout=seconds + XACRO_START_ALLOWANCE)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        raise DescriptionError(
            f"{path}: the xacro worker did not answer within {seconds + XACRO_START_ALLOWANCE:g} s "
            f"({XACRO_START_ALLOWANCE:g} s to start and {seconds:g} s to expand) and was stopped"
        ) from None
    if proc.returncode == -getattr(signal, "SIGALRM", 0) != 0:
        raise DescriptionError(
            f"{path}: xacro expansion took longer than {seconds:g} s and was stopped (an expression too costly "
            "to evaluate, or an include that never ends)"
        )
    if proc.returncode == -getattr(signal, "SIGXCPU", 0) != 0:
        raise DescriptionError(f"{path}: xacro expansion used more than {seconds:g} s of CPU time and was stopped")
    try:
        result: dict[str, Any] = json.loads(out.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        tail = " ".join(err.decode("utf-8", "replace").strip().splitlines()[-1:])
        if "MemoryError" in tail:
            return {"ok": False, "limit": "memory", "error": "", "warnings": ""}
        raise DescriptionError(
            f"{path}: the xacro worker failed (exit status {proc.returncode}){': ' + tail if tail else ''}"
        ) from None
    return result


def run_xacro(
    path: Path,
    args: Mapping[str, str],
    resolver: Resolver,
    *,
    trusted: bool = False,
    seconds: float | None = None,
    memory: int | None = None,
) -> str:
    """Expand ``path`` with xacro args ``args``; raises DescriptionError naming the file, macro and problem.

    Unless ``trusted``, expressions are checked against the allow-list and files stay inside
    ``resolver``'s package roots (a refusal names the file, the line and the construct).
    ``seconds``/``memory`` default to :data:`XACRO_TIME_LIMIT` and :data:`XACRO_MEMORY_LIMIT`.
    """
    seconds = XACRO_TIME_LIMIT if seconds is None else seconds
    job = {
        "path": str(path),
        "args": {str(k): str(v) for k, v in args.items()},
        "package_path": [str(p) for p in resolver.package_path],
        "roots": [str(p) for p in resolver.extra_roots],
        "trusted": trusted,
        "seconds": seconds,
        "memory": XACRO_MEMORY_LIMIT if memory is None else memory,
    }
    key = _cache_key(job)
    result = _cached(key)
    if result is None:
        result = _worker_result(path, job, seconds)
        if result.get("ok"):
            _remember(key, result)
    for line in str(result.get("warnings", "")).splitlines():
        if line.strip():
            log.warning("%s: xacro: %s", path, line.strip())
    if not result.get("ok"):
        if result.get("refused"):
            raise DescriptionError(f"{result['error']} ({TRUST_HINT})")
        if result.get("limit") == "memory":
            raise DescriptionError(f"{path}: xacro expansion ran out of its memory limit and was stopped")
        detail = str(result.get("error", ""))
        hint = ""
        if "Undefined substitution argument" in detail:
            hint = "; pass it in xacro_args (robot.yaml) or give the <xacro:arg> a default"
        raise DescriptionError(f"{path}: xacro failed{result.get('where', '')}: {detail}{hint}")
    queried = set(result.get("queried", ()))
    unused = sorted(set(args) - queried)
    if unused:
        declared = sorted(queried)
        raise DescriptionError(
            f"{path}: xacro arg(s) {', '.join(repr(a) for a in unused)} are not used by the file; "
            f"it declares: {', '.join(declared) if declared else 'no args'}"
        )
    return str(result["xml"])
