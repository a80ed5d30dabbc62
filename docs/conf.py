"""Sphinx configuration of sb3-nfq's documentation (``make docs``; warnings are errors)."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import sb3_nfq  # noqa: E402  (after the path is set)

project = "sb3-nfq"
author = "sb3-nfq contributors"
copyright = "2026, sb3-nfq contributors"  # Sphinx's name for it
release = sb3_nfq.__version__
version = release

extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.viewcode", "myst_parser"]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3
exclude_patterns = ["_build"]
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_inherit_docstrings = False
autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": True}
nitpicky = False
html_theme = "sphinx_rtd_theme"
html_title = f"sb3-nfq {release}"
# SB3's own docstrings (inherited members are not documented here) and type aliases it cannot resolve.
suppress_warnings = ["myst.header"]
