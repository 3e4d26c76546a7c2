"""Finding the machine classes of a behavior file or module."""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

from ..errors import ConfigurationError
from ._machine import StateMachine

# --------------------------------------------------------------------------- discovery


def find_machines(module: ModuleType | str | os.PathLike[str]) -> list[type[StateMachine]]:
    """The machine classes defined in ``module``, in definition order.

    ``module`` is a module object, a dotted module name, or a path to a ``.py``
    file (imported under a private name).  Abstract machines (no states) and
    machines merely imported into the module are left out.
    """
    if isinstance(module, os.PathLike) or (isinstance(module, str) and module.endswith(".py")):
        path = Path(module)
        mod_name = f"_agentsdk_machines_{path.stem}"
        spec = importlib.util.spec_from_file_location(mod_name, path)
        if spec is None or spec.loader is None:
            raise ConfigurationError(f"cannot import {path}")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[mod_name] = mod
        try:
            spec.loader.exec_module(mod)
        except BaseException:
            del sys.modules[mod_name]
            raise
    elif isinstance(module, str):
        mod = importlib.import_module(module)
    else:
        mod = module
    found = (
        obj
        for obj in vars(mod).values()
        if isinstance(obj, type)
        and issubclass(obj, StateMachine)
        and not obj.is_abstract()
        and obj.__module__ == mod.__name__
    )
    return list(dict.fromkeys(found))

