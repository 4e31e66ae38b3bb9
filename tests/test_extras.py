"""A choice that needs a missing extra is refused before Hydra starts: one line, nothing written.

``hydra/launcher=pbt`` without pyarrow made a sweep folder and printed two lines naming
``hydra/launcher=population``; ``logger=mlflow`` without MLflow was refused only once Hydra had made
the run's folder (and, in a sweep, with the job's overrides appended). The extras are hidden here as
an install without them would be: the modules cannot be found nor imported.
"""

from __future__ import annotations

import importlib.abc
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from drone_torchrl.apps import train as train_app

TINY = ["algo.episodes=2", "env.max_steps=20", "eval.episodes=1", "eval.video=false", "progress=false"]
# A PBT run's perturbation interval within the tiny budget (the default, 100 updates, is refused).
PBT_TINY = [*TINY, "hydra.launcher.every_updates=1"]
POPULATION_LINE = "drone-train: error: {choice} needs pyarrow: pip install 'drone_torchrl[population]'"

# A sitecustomize that hides the modules named in $HIDE_MODULES from the whole process (an install
# without them): every finder answers "not here" for them and their submodules.
SITECUSTOMIZE = textwrap.dedent(
    """
    import os, sys

    HIDDEN = tuple(filter(None, os.environ.get("HIDE_MODULES", "").split(",")))

    class Hide:
        def __init__(self, finder):
            self.finder = finder

        def find_spec(self, name, path=None, target=None):
            if any(name == m or name.startswith(m + ".") for m in HIDDEN):
                return None
            find = getattr(self.finder, "find_spec", None)
            return None if find is None else find(name, path, target)

        def __getattr__(self, attr):
            return getattr(self.finder, attr)

    sys.meta_path[:] = [Hide(finder) for finder in sys.meta_path]
    """
)


class _Hide(importlib.abc.MetaPathFinder):
    """In this process: the finders of ``sys.meta_path``, blind to ``hidden`` (see SITECUSTOMIZE)."""

    def __init__(self, finder, hidden: tuple[str, ...]) -> None:
        self.finder, self.hidden = finder, hidden

    def find_spec(self, name, path=None, target=None):
        if any(name == m or name.startswith(m + ".") for m in self.hidden):
            return None
        find = getattr(self.finder, "find_spec", None)
        return None if find is None else find(name, path, target)


@pytest.fixture
def hide(monkeypatch):
    """``hide("pyarrow")``: this process cannot find nor import it until the test ends."""

    def hide(*modules: str) -> None:
        for name in [n for n in sys.modules if any(n == m or n.startswith(m + ".") for m in modules)]:
            monkeypatch.delitem(sys.modules, name)
        monkeypatch.setattr(sys, "meta_path", [_Hide(f, modules) for f in sys.meta_path])

    return hide


def test_pbt_without_pyarrow_is_one_line_naming_it_and_writes_nothing(tmp_path):
    """The real command, in an install without pyarrow: exit 1, one line, no multirun/ nor outputs/."""
    site, work = tmp_path / "site", tmp_path / "work"
    site.mkdir()
    work.mkdir()
    (site / "sitecustomize.py").write_text(SITECUSTOMIZE)
    path = os.pathsep.join(p for p in (str(site), os.environ.get("PYTHONPATH")) if p)
    proc = subprocess.run(
        [sys.executable, "-m", "drone_torchrl.apps.train", "-m", "seed=0,1", "hydra/launcher=pbt", *PBT_TINY],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=work,
        env={**os.environ, "PYTHONPATH": path, "HIDE_MODULES": "pyarrow"},
    )
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr == POPULATION_LINE.format(choice="hydra/launcher=pbt") + "\n"
    assert proc.stdout == ""
    assert not (work / "multirun").exists() and not (work / "outputs").exists()
    assert list(work.iterdir()) == []


@pytest.mark.parametrize(
    ("launcher", "hidden", "needs"),
    [
        ("population", "pyarrow", "pyarrow: pip install 'drone_torchrl[population]'"),
        ("halving", "pyarrow", "pyarrow: pip install 'drone_torchrl[population]'"),
        ("pbt_replay", "pyarrow", "pyarrow: pip install 'drone_torchrl[population]'"),
        (
            "local_parallel",
            "hydra_plugins.hydra_joblib_launcher",
            "Hydra's joblib launcher plug-in: pip install 'drone_torchrl[joblib]'",
        ),
        (
            "slurm_population",
            "hydra_plugins.hydra_submitit_launcher",
            "Hydra's submitit launcher plug-in: pip install 'drone_torchrl[submitit]'",
        ),
    ],
    ids=["population", "halving", "pbt_replay", "local_parallel", "slurm_population"],
)
def test_a_launcher_without_its_extra_is_refused_naming_itself(
    launcher, hidden, needs, hide, tmp_path, command_here
):
    hide(hidden)
    proc = command_here(
        train_app.run, "drone-train", "-m", "seed=0,1", f"hydra/launcher={launcher}", *TINY, cwd=tmp_path
    )
    assert (proc.returncode, proc.stderr) == (
        1,
        f"drone-train: error: hydra/launcher={launcher} needs {needs}\n",
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("args", "hidden", "line"),
    [
        (["logger=mlflow"], "mlflow", "logger=mlflow needs mlflow: pip install 'drone_torchrl[mlflow]'"),
        (
            ["-m", "seed=0,1", "logger=mlflow"],
            "mlflow",
            "logger=mlflow needs mlflow: pip install 'drone_torchrl[mlflow]'",
        ),
        (["logger=wandb"], "wandb", "logger=wandb needs wandb: pip install 'drone_torchrl[wandb]'"),
        # A swept logger: each option is checked.
        (["-m", "logger=csv,wandb"], "wandb", "logger=wandb needs wandb: pip install 'drone_torchrl[wandb]'"),
    ],
    ids=["mlflow", "mlflow-sweep", "wandb", "swept-wandb"],
)
def test_a_logger_without_its_extra_is_refused_before_hydra_starts(
    args, hidden, line, hide, tmp_path, command_here
):
    hide(hidden)
    proc = command_here(train_app.run, "drone-train", *args, *TINY, cwd=tmp_path)
    assert (proc.returncode, proc.stderr) == (1, f"drone-train: error: {line}\n")
    assert list(tmp_path.iterdir()) == []  # Hydra never started: no outputs/, no multirun/


def test_launchers_that_need_no_pyarrow_are_not_refused_for_it(hide):
    """fused and slurm_population train a folder per job (no Parquet): pyarrow is not theirs to need."""
    from drone_torchrl import command_line, extras

    hide("pyarrow")
    command_line.check_extras({"hydra/launcher": "fused"})
    assert extras.LAUNCHERS["slurm_population"].module == "hydra_plugins.hydra_submitit_launcher"
    assert {k for k, v in extras.LAUNCHERS.items() if v == extras.POPULATION} == {
        "population",
        "pbt",
        "pb2",
        "halving",
        "pbt_replay",
    }


def test_the_population_record_names_the_same_extra_when_reached_another_way(hide):
    """A population launcher chosen in a config file reaches the record: the same extra, in one line."""
    from drone_torchrl.checks import ConfigError
    from drone_torchrl.training import population_record

    hide("pyarrow")
    with pytest.raises(ConfigError) as info:
        population_record.read_table(Path("agents.parquet"))
    message = str(info.value)
    assert "\n" not in message and message.endswith("needs pyarrow: pip install 'drone_torchrl[population]'")
    assert "hydra/launcher=population|pbt|pb2|halving|pbt_replay" in message
