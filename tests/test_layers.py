"""The package's layers (pyproject.toml's ``[tool.importlinter]``, docs/engines.md): ``lint-imports``
keeps both contracts, so an import from a layer above fails the default tests, not only CI."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _lint_imports() -> str:
    found = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which(
        "lint-imports"
    )
    if found is None:
        pytest.skip("import-linter is not installed (the test extra has it)")
    return found


def test_every_import_follows_the_layers():
    done = subprocess.run(
        [_lint_imports(), "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "Contracts: 2 kept, 0 broken." in done.stdout


def test_the_contract_places_every_module_and_excuses_no_import():
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    layers = next(c for c in contracts if c["id"] == "layers")
    assert layers["exhaustive"] is True and layers["containers"] == ["drone_torchrl"]
    assert len(layers["layers"]) >= 6
    assert not any("ignore_imports" in contract for contract in contracts)
    # The Hydra plug-ins sit between the commands and every other layer of the package.
    plugins = next(c for c in contracts if c["id"] == "hydra-plugins")
    below = {name.strip() for name in plugins["layers"][2].split(":")}
    package = {name.strip() for line in layers["layers"] for name in line.split("|")}
    assert below == {f"drone_torchrl.{name}" for name in package - {"apps"}}
