"""The suite's guard against CPython 3.11's nested-parse bug (python/cpython#106905, see conftest.py).

A finalizer that parses (like asyncio's "exception was never retrieved" log formatting a traceback)
run by a garbage collection inside another parse made the outer ``ast.parse`` raise
``SystemError: AST constructor recursion depth mismatch`` on 3.11.7.
"""

from __future__ import annotations

import ast
import gc
from pathlib import Path


class _ParsesWhenCollected:
    """An object in a reference cycle (only the collector frees it) whose finalizer parses."""

    parsed = 0

    def __init__(self) -> None:
        self.me = self

    def __del__(self) -> None:
        ast.parse("x + 1")
        type(self).parsed += 1


def test_a_collection_inside_a_parse_leaves_the_parse_intact() -> None:
    source = Path(ast.__file__).read_text()  # big enough for the collector to run inside one parse
    threshold = gc.get_threshold()
    gc.set_threshold(10)  # a collection every few allocations: inside the parse, unless the guard holds it off
    try:
        for _ in range(5):
            for _ in range(50):
                _ParsesWhenCollected()
            assert isinstance(ast.parse(source), ast.Module)
    finally:
        gc.set_threshold(*threshold)
    gc.collect()
    assert _ParsesWhenCollected.parsed >= 250  # the finalizers ran (after the parses)
