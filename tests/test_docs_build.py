"""The API reference builds with warnings as errors from the docs extra alone (no pytest), issue 27.

The build is ``scripts/docs_without_pytest.py`` (pytest hidden from imports; it checks the pages
too), which is also ``scripts/test.sh``'s sphinx suite: test.sh's main suite therefore leaves this
test out (marker ``docs_build``) instead of building the same reference twice. Plain ``pytest`` runs it.

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

SCRIPT = ROOT / "scripts" / "docs_without_pytest.py"  # the build of scripts/test.sh's sphinx suite


@pytest.mark.slow
@pytest.mark.docs_build
@pytest.mark.timeout(1200)
def test_docs_build_without_pytest(tmp_path: Path) -> None:
    pytest.importorskip("sphinx")
    pytest.importorskip("furo")
    pytest.importorskip("myst_parser")
    out_dir = tmp_path / "html"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, str(SCRIPT), str(out_dir)], capture_output=True, text=True, env=env,
                         timeout=1100, check=False)
    assert out.returncode == 0, out.stderr
    page = (out_dir / "api" / "testing.html").read_text()
    assert "BackendConformance" in page and "No module named" not in page
    footer = (out_dir / "index.html").read_text()
    assert "Copyright &#169; 2026, agentsdk contributors" in footer
