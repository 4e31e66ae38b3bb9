"""A sweep's folder holds that sweep: an ad-hoc multirun (no ``sweep_name``) is named by its overrides.

The same command finds its folder again (finished jobs are skipped), another command never shares
it, so the end-of-sweep summary and ``drone-report`` see one command's jobs; a folder that mixes
budgets names no best. An old ``multirun/adhoc`` is reached with ``sweep_name=adhoc``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.types import RunMode

from drone_torchrl.apps import report as report_app
from drone_torchrl.apps import train as train_app
from drone_torchrl.config import config_dir
from drone_torchrl.io.episodes_csv import CSV_NAME

TINY = ["algo.episodes=2", "env.max_steps=20", "eval.episodes=1", "eval.video=false", "progress=false"]
OLD_SWEEP = Path(__file__).resolve().parent / "fixtures" / "main_8718978" / "sweep"


@pytest.fixture
def drone_train(command_here):
    """``drone-train -m args...`` in ``cwd``, in this process (the runs are tiny)."""

    def run(*args: str, cwd: Path):
        proc = command_here(train_app.run, "drone-train", "-m", *args, cwd=cwd)
        assert proc.returncode == 0, proc.stderr
        return proc

    return run


def _sweeps(cwd: Path) -> list[Path]:
    return sorted(p for p in (cwd / "multirun").iterdir() if p.is_dir())


def _summary(stdout: str) -> str:
    """The summary's first line, ``sweep <folder>: 2 finished, 0 failed, 0 unfinished``."""
    (line,) = [line for line in stdout.splitlines() if line.startswith("sweep ")]
    return line


def _sweep_dir(*overrides: str) -> str:
    """``hydra.sweep.dir`` as Hydra resolves it for ``drone-train -m overrides...``."""
    with initialize_config_dir(config_dir(), version_base="1.3"):
        loader = GlobalHydra.instance().config_loader()
        cfg = loader.load_configuration("config", list(overrides), run_mode=RunMode.MULTIRUN)
    return str(cfg.hydra.sweep.dir)


def test_two_adhoc_sweeps_land_in_two_folders_each_summary_counting_its_own(tmp_path, drone_train):
    first = drone_train("seed=0,1", *TINY, cwd=tmp_path)
    second = drone_train("algo.lr=1e-3,1e-4", "seed=0,1", *TINY, cwd=tmp_path)
    one, two = _sweeps(tmp_path)  # two folders, not multirun/adhoc shared
    by_name = {p.name.rsplit("-", 1)[0]: p for p in (one, two)}
    assert sorted(by_name) == ["algo.lr,seed", "seed"]  # the readable prefix: the swept keys
    assert (
        _summary(first.stdout) == f"sweep multirun/{by_name['seed'].name}: 2 finished, 0 failed, 0 unfinished"
    )
    assert _summary(second.stdout) == (
        f"sweep multirun/{by_name['algo.lr,seed'].name}: 4 finished, 0 failed, 0 unfinished"
    )
    assert len(list(by_name["seed"].glob(f"*/{CSV_NAME}"))) == 2
    assert len(list(by_name["algo.lr,seed"].glob(f"*/{CSV_NAME}"))) == 4


def test_the_same_command_again_finds_its_folder_and_retrains_nothing(tmp_path, drone_train):
    drone_train("seed=0,1", *TINY, cwd=tmp_path)
    drone_train("seed=2", *TINY, cwd=tmp_path)  # another command in between
    (sweep,) = [p for p in _sweeps(tmp_path) if p.name.startswith("seed-")]
    csvs = {p: p.read_bytes() for p in sweep.glob(f"*/{CSV_NAME}")}
    # The same command, its overrides in another order and a process-only setting added.
    again = drone_train("progress=false", *reversed(TINY[:-1]), "seed=0,1", "threads=2", cwd=tmp_path)
    assert _summary(again.stdout) == f"sweep multirun/{sweep.name}: 2 finished, 0 failed, 0 unfinished"
    assert again.stdout.count("already finished (2 episodes)") == 2
    assert {p: p.read_bytes() for p in sweep.glob(f"*/{CSV_NAME}")} == csvs
    assert len(_sweeps(tmp_path)) == 2


def test_the_folder_is_named_by_what_the_command_searches():
    base = _sweep_dir("seed=0,1", "algo.lr=1e-3", *TINY)
    assert base.startswith("multirun/seed-") and len(base.rsplit("-", 1)[1]) == 8
    # The same overrides in another order, and settings of this process only: the same folder.
    assert _sweep_dir(*reversed(TINY), "algo.lr=1e-3", "seed=0,1") == base
    assert _sweep_dir("seed=0,1", "algo.lr=1e-3", *TINY, "threads=2", "device=cpu", "progress=true") == base
    # A launcher that trains the same jobs into the same job folders: the same sweep, continued there.
    assert _sweep_dir("seed=0,1", "algo.lr=1e-3", *TINY, "hydra/launcher=fused") == base
    # Anything that changes the search: another folder each.
    others = [
        _sweep_dir("seed=0,1", "algo.lr=1e-3", *TINY[1:], "algo.episodes=3"),  # the budget
        _sweep_dir("seed=0,1,2", "algo.lr=1e-3", *TINY),
        _sweep_dir("seed=0,1", "algo.lr=1e-4", *TINY),
        _sweep_dir("seed=0,1", "algo.lr=1e-3", *TINY, "hydra/launcher=population"),
        _sweep_dir("seed=0,1", "algo.lr=1e-3", *TINY, "hydra/launcher=pbt", "hydra.launcher.quantile=0.25"),
        _sweep_dir("seed=0,1", "algo.lr=1e-3", *TINY, "hydra/launcher=pbt", "hydra.launcher.quantile=0.5"),
    ]
    assert len({base, *others}) == len(others) + 1
    # A name given, or a preset's: that fixed folder.
    assert _sweep_dir("seed=0,1", *TINY, "sweep_name=adhoc") == "multirun/adhoc"
    assert _sweep_dir("+sweep=lr", *TINY) == "multirun/lr"


def test_report_of_a_folder_mixing_budgets_names_no_best(tmp_path, drone_train, command_here):
    drone_train("algo.lr=1e-4", "seed=0,1", *TINY, "sweep_name=mixed", cwd=tmp_path)
    longer = [a if a != "algo.episodes=2" else "algo.episodes=3" for a in TINY]
    drone_train("algo.lr=1e-3", "seed=0,1", *longer, "sweep_name=mixed", cwd=tmp_path)
    proc = command_here(report_app.main, "drone-report", "multirun/mixed", "--no-pd", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert (
        lines[0] == "best: none named: its runs mix budgets (algo.episodes=2, 3); compare runs of one budget"
    )
    assert not any(line.startswith("best: ") for line in lines[1:])
    # The table still has one row per setting, each labelled with its budget.
    rows = [line for line in lines if line.startswith("| algo.")]
    assert [row.split(" | ")[0] for row in rows] == [
        "| algo.lr=0.0001, algo.episodes=2",
        "| algo.lr=0.001, algo.episodes=3",
    ]
    summary = (tmp_path / "multirun" / "mixed" / "report" / "summary.md").read_text()
    assert summary.splitlines()[0] == lines[0]


def test_an_old_adhoc_folder_is_reached_with_sweep_name_adhoc(tmp_path, drone_train):
    """The folder every ad-hoc sweep shared before: its command with ``sweep_name=adhoc`` runs again in it."""
    shutil.copytree(OLD_SWEEP, tmp_path / "multirun" / "adhoc")
    task = yaml.safe_load((OLD_SWEEP / "multirun.yaml").read_text())["hydra"]["overrides"]["task"]
    again = drone_train("hydra/launcher=fused", *task, "sweep_name=adhoc", cwd=tmp_path)
    assert _summary(again.stdout) == "sweep multirun/adhoc: 2 finished, 0 failed, 0 unfinished"
    assert again.stdout.count("already finished (4 episodes)") == 2
    assert [p.name for p in _sweeps(tmp_path)] == ["adhoc"]


@pytest.mark.parametrize("launcher", ["basic", "fused"])
def test_re_running_an_old_finished_sweep_keeps_each_job_s_hydra_record(tmp_path, drone_train, launcher):
    """The old sweep's jobs are finished: its command again (today's keys for compile=true) skips them,
    and their ``.hydra/`` records, how they were started (``engine: fused``, ``compile: true``), are
    left byte for byte. A new sweep's jobs still get theirs."""
    shutil.copytree(OLD_SWEEP, tmp_path / "multirun" / "adhoc")
    task = yaml.safe_load((OLD_SWEEP / "multirun.yaml").read_text())["hydra"]["overrides"]["task"]
    records = {p: p.read_bytes() for p in (tmp_path / "multirun" / "adhoc").glob("*/.hydra/*.yaml")}
    assert len(records) == 6 and all(
        b"compile: true" in records[p] for p in records if p.name == "config.yaml"
    )
    again = drone_train(f"hydra/launcher={launcher}", *task, "sweep_name=adhoc", cwd=tmp_path)
    assert again.stdout.count("already finished (4 episodes)") == 2
    assert {p: p.read_bytes() for p in (tmp_path / "multirun" / "adhoc").glob("*/.hydra/*.yaml")} == records
    drone_train(f"hydra/launcher={launcher}", "seed=0,1", *TINY, "sweep_name=new", cwd=tmp_path)
    assert len(list((tmp_path / "multirun" / "new").glob("*/.hydra/overrides.yaml"))) == 2
