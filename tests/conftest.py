"""Shared fixtures: every test fails on leaked asyncio tasks or threads; backends from the registry."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator, Iterable, Iterator
from typing import Any

import pytest
import pytest_asyncio

import agentsdk


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
