"""Sphinx configuration of the documentation site: MyST markdown pages and an API reference from the docstrings.

Built offline (no intersphinx: nothing is fetched) with warnings as errors:
``python -m sphinx -W --keep-going -b html docs docs/_build/html``.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the checkout's package, also when it is not installed editable

project = "drone_torchrl"
author = "drone_torchrl contributors"

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
# drone-report's generated summaries are data next to their figures, not pages of the site.
exclude_patterns = ["_build", "**/summary.md"]

# GitHub-style anchors (`page.md#a-heading`), so the same links work on GitHub and here.
myst_heading_anchors = 4
myst_enable_extensions = ["dollarmath"]

autosummary_generate = True
# Members are documented where they are defined, not again where a package re-exports them.
autodoc_default_options = {"members": True, "show-inheritance": True, "ignore-module-all": True}
autodoc_typehints = "description"
autodoc_member_order = "bysource"
napoleon_google_docstring = True
napoleon_numpy_docstring = False

html_theme = "furo"
html_title = "drone_torchrl"
