"""Backend registry: entry-point group ``agentsdk.backends``, imported lazily by name.

An unknown name lists the known ones; a backend whose optional dependency is
missing gives an install hint; one broken plugin cannot break the others.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import TYPE_CHECKING

from .errors import BackendUnavailableError

if TYPE_CHECKING:
    from .backend import Backend

__all__ = ["available_backends", "broken_backends", "load_backend", "register_backend", "unregister_backend"]

GROUP = "agentsdk.backends"

#: backends registered in-process (tests, notebooks); take precedence over entry points
_local: dict[str, type[Backend]] = {}

#: install commands hinted at when a backend's optional dependency is missing (the extras in pyproject.toml)
_HINTS = {
    "mujoco": "pip install 'agentsdk[mujoco]'",
    "pybullet": "pip install 'agentsdk[pybullet]'",
    "can": "pip install 'agentsdk[can]'",
    "ros2": "pip install 'agentsdk[ros2]'",
}

# Fallback when the distribution metadata is not installed (e.g. running from a
# source tree without `pip install -e .`): our own backends by module path.
BUILTIN_BACKENDS = {
    "mock": "agentsdk.backends.mock:MockBackend",
    "mujoco": "agentsdk.backends.mujoco:MujocoBackend",
    "pybullet": "agentsdk.backends.pybullet:PybulletBackend",
    "can": "agentsdk.backends.can:CanBackend",
    "ros2": "agentsdk.backends.ros2:Ros2Backend",
}


#: the distribution a missing module comes from, where their names differ (``import can``: python-can)
_DISTRIBUTIONS = {"can": "python-can"}

def _entry_points() -> dict[str, str]:
    found = {ep.name: ep.value for ep in entry_points(group=GROUP)}
    return {**BUILTIN_BACKENDS, **found}


def available_backends() -> list[str]:
    """Names of every registered backend (importable or not)."""
    return sorted({*_entry_points(), *_local})


def register_backend(name: str, cls: type[Backend]) -> None:
    """Register a backend class in-process under ``name``."""
    _local[name] = cls


def unregister_backend(name: str) -> None:
    """Remove a backend registered with :func:`register_backend` (no error when absent)."""
    _local.pop(name, None)


def broken_backends() -> dict[str, str]:
    """Registered backends that cannot be imported here, each with the reason (an install hint or the error).

    Imports every registered backend (the simulators and bus libraries included): meant for
    diagnostics (``agentsdk check``, ``agentsdk backends``), not for the hot path.
    """
    broken: dict[str, str] = {}
    for name in available_backends():
        try:
            load_backend(name)
        except BackendUnavailableError as exc:
            broken[name] = str(exc)
    return broken


def load_backend(name: str) -> type[Backend]:
    """Import and return the backend class registered as ``name``."""
    from .backend import Backend

    if name in _local:
        return _local[name]
    eps = _entry_points()
    if name not in eps:
        raise BackendUnavailableError(
            f"unknown backend {name!r}; known backends: {', '.join(available_backends())}"
        )
    module_name, _, attr = eps[name].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        hint = _HINTS.get(name, f"install the package that provides {module_name!r}")
        missing = _DISTRIBUTIONS.get(exc.name or "", exc.name or str(exc))
        raise BackendUnavailableError(
            f"backend {name!r} is not available: {missing} is not installed ({hint})"
        ) from exc
    except Exception as exc:
        # a broken plugin (any error while importing it) is isolated and named; the others still load
        raise BackendUnavailableError(
            f"backend {name!r} ({eps[name]}) failed to import: {type(exc).__name__}: {exc}"
        ) from exc
    cls = getattr(module, attr, None)
    if not (isinstance(cls, type) and issubclass(cls, Backend)):
        raise BackendUnavailableError(f"entry point {name!r} -> {eps[name]!r} is not an agentsdk.Backend subclass")
    return cls
