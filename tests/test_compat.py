"""Private APIs of other packages live in drone_torchrl/compat.py only, and each still exists."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from drone_torchrl import compat

ROOT = Path(__file__).resolve().parent.parent
# How the private names this project uses are spelled in code.
PRIVATE = re.compile(r"hydra\._internal|omegaconf\._utils|_EXECUTOR|torch\._fused_adam")


def test_private_apis_are_used_in_compat_only():
    sources = [*ROOT.joinpath("drone_torchrl").rglob("*.py"), *ROOT.joinpath("hydra_plugins").rglob("*.py")]
    users = sorted(
        str(path.relative_to(ROOT))
        for path in sources
        if path.name != "compat.py" and PRIVATE.search(path.read_text(encoding="utf-8"))
    )
    assert users == []


def test_every_private_name_resolves_on_the_installed_versions():
    compat.check_versions()
    assert compat.basic_sweeper_class().__name__ == "BasicSweeper"
    assert {"max_batch_size", "params"} <= set(compat.basic_sweeper_conf().__dataclass_fields__)
    assert callable(compat.omegaconf_str_representer())
    assert callable(compat.fused_adam(True)) and compat.fused_adam(True) is not compat.fused_adam(False)


def test_overrides_dirname_is_hydras():
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(["seed=3", "algo.lr=1e-3", "threads=2"])
    assert compat.overrides_dirname(parsed, ["threads"], ",", "=") == "algo.lr=1e-3,seed=3"


def test_a_version_outside_the_checked_range_is_one_line():
    with pytest.raises(RuntimeError) as error:
        compat.check_versions({"hydra-core": ("9.0", "10.0")})
    message = str(error.value)
    assert "\n" not in message
    assert message.startswith("hydra-core 1.3.") and ">=9.0,<10.0" in message
    compat.check_versions({"no-such-distribution": ("1", "2")})  # not installed: skipped


@pytest.mark.parametrize(
    ("version", "release"), [("2.13.0+cpu", (2, 13, 0)), ("1.3.2", (1, 3, 2)), ("2.4.0rc1", (2, 4, 0))]
)
def test_release_numbers(version, release):
    assert compat._release(version) == release
