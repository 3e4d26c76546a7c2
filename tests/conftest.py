"""Shared fixtures: every test fails on leaked asyncio tasks or threads; backends from the registry."""

from __future__ import annotations

import ast
import asyncio
import functools
import gc
import os
import sys
import threading
from collections.abc import AsyncIterator, Iterable, Iterator
from typing import Any

import pytest
import pytest_asyncio
from ros_domains import share

import agentsdk


def pytest_configure(config: pytest.Config) -> None:
    """A parallel worker (pytest-xdist) gets its own share of the ROS 2 domains its DDS tests pick from."""
    worker, count = os.environ.get("PYTEST_XDIST_WORKER", ""), os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if worker.startswith("gw") and count:
        lo, hi = share(int(worker[2:]), int(count))
        os.environ["AGENTSDK_TEST_DOMAINS"] = f"{lo}-{hi}"

if sys.version_info < (3, 12):
    # CPython 3.11 keeps ast.parse's recursion-depth count in one per-interpreter state
    # (python/cpython#106905): a parse nested inside another one - a garbage collection during the
    # outer parse runs a finalizer that parses, e.g. an asyncio task's "exception was never retrieved"
    # log, whose traceback formatting parses the source line for its carets, or a thread switch from
    # that finalizer to a thread that parses - makes the outer one raise "SystemError: AST constructor
    # recursion depth mismatch" (seen in pytest's own report code at the end of a loaded run). No
    # collection during a parse, so no finalizer (and no other Python code) runs inside one.
    _ast_parse = ast.parse

    @functools.wraps(_ast_parse)
    def _parse_without_collection(*args: Any, **kwargs: Any) -> Any:
        if not gc.isenabled():
            return _ast_parse(*args, **kwargs)
        gc.disable()
        try:
            return _ast_parse(*args, **kwargs)
        finally:
            gc.enable()

    ast.parse = _parse_without_collection


def lockstep_backends(*, deterministic: bool = False, modes: Iterable[str] = ()) -> list[Any]:
    """Every registered backend that runs in lockstep (simulated time), as pytest params.

    Chosen from the registry and gated on declared capabilities (``deterministic``: bit-identical
    reruns; ``modes``: command modes it must accept), never on names, so a new backend is tested
    without editing a list. One that cannot load here (a missing extra, a broken plugin) is a
    skipped param that says why.
    """
    need = frozenset(modes)
    params: list[Any] = []
    for name in agentsdk.available_backends():
        try:
            cls = agentsdk.load_backend(name)
        except Exception as exc:  # a missing extra or a broken third-party plugin: skipped, named
            reason = f"backend {name!r} unavailable: {type(exc).__name__}: {exc}"
            params.append(pytest.param(name, id=name, marks=pytest.mark.skip(reason=reason)))
            continue
        caps = cls.capabilities
        # (a backend that drives a robot elsewhere, e.g. ros2, needs the fixtures of its own tests)
        if (not caps.lockstep or not caps.standalone or (deterministic and not caps.deterministic)
                or not need <= caps.modes):
            continue
        params.append(pytest.param(name, id=name))
    return params


@pytest.fixture(autouse=True)
def _no_leaked_threads() -> Iterator[None]:
    before = set(threading.enumerate())
    yield
    leaked = [t for t in threading.enumerate() if t not in before and t.is_alive()]
    for t in leaked:
        t.join(timeout=2.0)
    leaked = [t for t in leaked if t.is_alive()]
    assert not leaked, f"test leaked threads: {[t.name for t in leaked]}"


@pytest.fixture(autouse=True)
def _async_leak_check(request: pytest.FixtureRequest) -> None:
    if request.node.get_closest_marker("asyncio") is not None:
        request.getfixturevalue("_no_leaked_tasks")


@pytest_asyncio.fixture
async def _no_leaked_tasks() -> AsyncIterator[None]:
    yield
    me = asyncio.current_task()
    # give cancelled tasks a moment to finish unwinding
    for _ in range(5):
        await asyncio.sleep(0)
    leaked = [t for t in asyncio.all_tasks() if t is not me and not t.done()]
    assert not leaked, f"test leaked tasks: {leaked}"


@pytest_asyncio.fixture
async def mock_arm() -> AsyncIterator[agentsdk.Robot]:
    async with agentsdk.connect("mock", robot="arm3") as robot:
        yield robot
