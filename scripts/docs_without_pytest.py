"""Build the API reference as with the docs extra alone (no pytest), warnings as errors; check its pages.

    python3 scripts/docs_without_pytest.py OUTDIR

``agentsdk.testing`` (the conformance kit) is pytest code: with pytest hidden, Sphinx mocks it and the
"Conformance kit" page must still document ``BackendConformance``; the footer names the copyright holder
(issue 27). ``scripts/test.sh``'s sphinx suite is this build; ``tests/test_docs_build.py`` runs it too.
Exit status: Sphinx's, or 1 when a page check fails.
"""

from __future__ import annotations

import importlib.abc
import sys
from importlib.machinery import ModuleSpec
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


class NoPytest(importlib.abc.MetaPathFinder):
    def find_spec(
        self, name: str, path: object = None, target: ModuleType | None = None
    ) -> ModuleSpec | None:
        if name == "pytest" or name.startswith(("pytest.", "_pytest")):
            raise ModuleNotFoundError(f"No module named {name!r}")
        return None


def check(out_dir: Path) -> list[str]:
    """What is wrong with the built pages (empty: nothing)."""
    problems = []
    page = (out_dir / "api" / "testing.html").read_text()
    if "BackendConformance" not in page:
        problems.append("api/testing.html does not document BackendConformance")
    if "No module named" in page:
        problems.append("api/testing.html shows an import error ('No module named')")
    footer = (out_dir / "index.html").read_text()
    if "Copyright &#169; 2026, agentsdk contributors" not in footer:
        problems.append("index.html's footer does not name the copyright holder")
    return problems


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        sys.stderr.write("usage: docs_without_pytest.py OUTDIR\n")
        return 2
    out_dir = Path(argv[0])
    sys.meta_path.insert(0, NoPytest())  # as installed with the docs extra alone
    sys.path.insert(0, str(ROOT))
    from sphinx.cmd.build import main as sphinx_main

    rc = sphinx_main(["-W", "--keep-going", "-q", "-b", "html", str(ROOT / "docs"), str(out_dir)])
    if rc != 0:
        return rc
    problems = check(out_dir)
    for p in problems:
        sys.stderr.write(f"docs_without_pytest: {p}\n")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
