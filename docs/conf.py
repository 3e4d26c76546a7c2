"""Sphinx configuration: the API reference is built from the docstrings (``sphinx -W``: warnings are errors)."""

from __future__ import annotations

import agentsdk

project = "agentsdk"
author = "agentsdk contributors"
copyright = "2026, agentsdk contributors"  # the footer: "Copyright © 2026, agentsdk contributors"
release = agentsdk.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
    "myst_parser",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build"]
myst_heading_anchors = 3

autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_default_options = {"members": True, "show-inheritance": True}
autoclass_content = "both"
# the conformance kit (agentsdk.testing) is pytest code; the docs extra does not install pytest
autodoc_mock_imports = ["pytest"]
# pydantic models document their fields through their docstrings and comments
autodoc_pydantic_model_show_json = False
suppress_warnings = ["myst.header", "myst.xref_missing"]

html_theme = "furo"
html_title = f"agentsdk {release}"
