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

# Every cross-reference must resolve (`-n`), except to the packages below: the build is offline, so
# their intersphinx inventories are never loaded and their names can only stay plain text.
nitpicky = True
_ANY_ROLE = r"py:.*"
nitpick_ignore_regex = [
    # PyTorch (also as the `nn` alias a docstring may use).
    (_ANY_ROLE, r"(torch|nn)(\..*)?"),
    # NumPy, under its name and its `np` alias.
    (_ANY_ROLE, r"(numpy|np)(\..*)?"),
    # OmegaConf and Hydra (Hydra's own `hydra.*`; the package's plug-ins under `hydra_plugins` stay checked).
    (_ANY_ROLE, r"(omegaconf|hydra)(\..*)?"),
    # TensorDict and TorchRL.
    (_ANY_ROLE, r"(tensordict|torchrl)(\..*)?"),
    # Gymnasium, PyArrow, MLflow: the optional extras' packages.
    (_ANY_ROLE, r"(gymnasium|pyarrow|mlflow)(\..*)?"),
    # The standard library: Python's own inventory is not loaded either.
    (
        _ANY_ROLE,
        r"(abc|typing|collections\.abc|pathlib|os|enum|ctypes|argparse|csv|logging|contextlib)(\..*)?",
    ),
    # The same classes unqualified: autodoc leaves a class's ``__init__`` annotations as written
    # (``from __future__ import annotations``), so they name the imports above by their short names.
    ("py:class", r"Path|DictConfig|ProbabilisticActor|ProbabilisticTensorDictSequential|LossModule"),
    # Hydra's submitit plug-in (the `submitit` extra), which the SLURM launchers extend, and the
    # `Dict[str, ...]` it annotates with (typing's old alias).
    (_ANY_ROLE, r"hydra_plugins\.hydra_submitit_launcher(\..*)?"),
    ("py:class", r"Dict\[str"),
    # Private bases and nested classes that autodoc names (show-inheritance, annotations) but that are
    # not documented, being private.
    ("py:class", r"drone_torchrl\.objectives\.reinforce\.ReinforceLoss\._AcceptedKeys"),
]
