"""The plug-ins page (docs/plugins.md) lists the plug-ins the registries hold: adding an algorithm or a logger cannot leave it behind."""

from __future__ import annotations

from pathlib import Path

from drone_torchrl import algorithms, loggers
from drone_torchrl.config import group_options, options_by_plugin
from drone_torchrl.plugin_docs import BEGIN, END, plugin_table, readme_block

ROOT = Path(__file__).resolve().parents[1]
PLUGINS_PAGE = ROOT / "docs" / "plugins.md"


def test_the_readme_lists_exactly_the_registered_plugins():
    text = PLUGINS_PAGE.read_text()
    assert text.count(BEGIN) == 1 and text.count(END) == 1
    block = text[text.index(BEGIN) : text.index(END) + len(END)]
    assert block == readme_block(), (
        "docs/plugins.md's plug-in table is stale: python -m drone_torchrl.plugin_docs"
    )


def test_the_table_has_a_row_per_registered_plugin_and_every_option():
    table = plugin_table()
    for group, registered in (("algo", algorithms.names()), ("logger", loggers.BACKENDS.names())):
        assert sorted(options_by_plugin(group)) == sorted(registered)  # every plug-in has an option file
        for name in registered:
            assert f"| `{name}` |" in table
        for option in group_options(group):
            assert f"`{group}={option}`" in table


def test_the_algorithms_benchmark_takes_every_algorithm_option(monkeypatch):
    """benchmarks/algorithms.py had its own list of four: an algorithm added as a module and a YAML
    (here a stand-in option ``a3c``) is now benchmarked without an edit there."""
    import importlib.util

    from drone_torchrl import config

    real = config.group_options
    monkeypatch.setattr(
        config, "group_options", lambda group: [*real(group), *(["a3c"] if group == "algo" else [])]
    )
    path = ROOT / "benchmarks" / "algorithms.py"
    spec = importlib.util.spec_from_file_location("algorithms_benchmark", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.parse_args([]).algos == [*real("algo"), "a3c"]
    assert module.parse_args(["--algos", "sac"]).algos == ["sac"]
