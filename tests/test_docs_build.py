"""The API reference builds with warnings as errors from the docs extra alone (no pytest), issue 27.

``agentsdk.testing`` (the conformance kit) is pytest code: without pytest, Sphinx mocks it and the
"Conformance kit" page must still document ``BackendConformance``; the footer names the copyright holder.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

BLOCKER = '''
import importlib.abc
import sys


class NoPytest(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "pytest" or name.startswith(("pytest.", "_pytest")):
            raise ModuleNotFoundError(f"No module named {name!r}")
        return None


sys.meta_path.insert(0, NoPytest())  # as installed with the docs extra alone
from sphinx.cmd.build import main

sys.exit(main(sys.argv[1:]))
'''


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_docs_build_without_pytest(tmp_path: Path) -> None:
    pytest.importorskip("sphinx")
    pytest.importorskip("furo")
    pytest.importorskip("myst_parser")
    script = tmp_path / "sphinx_without_pytest.py"
    script.write_text(BLOCKER)
    out_dir = tmp_path / "html"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, str(script), "-W", "--keep-going", "-q", "-b", "html", str(ROOT / "docs"),
                          str(out_dir)], capture_output=True, text=True, env=env, timeout=1100, check=False)
    assert out.returncode == 0, out.stderr
    page = (out_dir / "api" / "testing.html").read_text()
    assert "BackendConformance" in page and "No module named" not in page
    footer = (out_dir / "index.html").read_text()
    assert "Copyright &#169; 2026, agentsdk contributors" in footer
