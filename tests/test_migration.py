"""Runs written before ``backend`` replaced ``engine``, ``compile`` and ``algo.collector`` still resume, a
sweep started then runs again in its folders, and the old keys typed on a command line still work.

The fixtures (tests/fixtures/main_8718978, how they were made: its README) are a REINFORCE run, a
PPO run with ``algo.collector=fused`` and a two-seed fused sweep started with ``compile=true``,
written by main at 8718978. Each test works on a copy.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from drone_torchrl import migrations
from drone_torchrl.apps import train as train_app
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.io.episodes_csv import read_episodes

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "main_8718978"


@pytest.fixture
def drone_train(command_here):
    """``drone-train args...`` from ``cwd``, in this process (tests/conftest.py's command_here): the
    runs are tiny, a new process would mostly import torch."""
    return lambda *args, cwd: command_here(train_app.run, "drone-train", *args, cwd=cwd)


@pytest.fixture
def runs(tmp_path) -> Path:
    shutil.copytree(FIXTURES, tmp_path / "runs")
    return tmp_path / "runs"


def test_old_checkpoints_load_with_their_backend(runs):
    """Format 2 named the implementation ``engine`` (``fused`` for every run) and PPO's batches
    ``algo.collector``: read as backend=fast for both fixtures (REINFORCE on the fused engine, PPO with
    the fused collector); the removed keys are gone from the config a run continues with."""
    from drone_torchrl.config import run_config

    for name in ("run_reinforce", "run_ppo"):
        state = load_checkpoint(runs / name / "checkpoints" / "last.pt")
        assert state["backend"] == migrations.FAST and "engine" not in state
        cfg = run_config(state["config"])
        assert cfg.backend == migrations.FAST
        assert not {"engine", "compile", "steps_per_call", "updates_per_call"} & set(cfg)
        assert "collector" not in cfg.algo


@pytest.mark.parametrize(
    ("engine", "collector", "backend"),
    [("fused", None, "fast"), ("torchrl", None, "reference"), (None, None, "reference"),
     ("fused", "torchrl", "reference"), ("fused", "fused", "fast")],
)  # fmt: skip
def test_an_old_config_names_its_backend(engine, collector, backend):
    """engine=torchrl (or none: the first runs) was the reference; PPO's collector decided its batches."""
    config = {"algo": {"name": "ppo" if collector else "reinforce"}, "compile": True, "steps_per_call": 10}
    if engine is not None:
        config["engine"] = engine
    if collector is not None:
        config["algo"]["collector"] = collector
    migrated = migrations.migrate_config(config)
    assert migrated["backend"] == backend and "collector" not in migrated["algo"]
    assert not {"engine", "compile", "steps_per_call"} & set(migrated)


def test_old_runs_resume(runs, drone_train):
    """Both fixtures continue from their checkpoints at episode 4: the episode counter carries on,
    the CSV grows, and the checkpoint now says backend."""
    for name, budget in (("run_reinforce", 6), ("run_ppo", 8)):
        proc = drone_train(f"resume={runs / name}", f"algo.episodes={budget}", cwd=runs)
        assert proc.returncode == 0, proc.stderr
        assert "continuing from episode 4" in proc.stdout
        state = load_checkpoint(runs / name / "checkpoints" / "last.pt")
        assert state["format_version"] == 4 and state["episodes_done"] >= budget
        rows, _ = read_episodes(runs / name / "episodes.csv")
        assert rows["episode"].tolist() == list(range(len(rows["episode"])))
        assert len(rows["episode"]) >= budget


def test_the_old_sweep_runs_again_in_its_folders(runs, drone_train):
    """The sweep's own command again (with compile=true, a key that is gone): a note names what it
    became, no "key differs" refusal, the finished jobs are found in their folders (named after
    compile=True as before) and skipped; with a larger budget they continue in them."""
    sweep = runs / "sweep"
    task = yaml.safe_load((sweep / "multirun.yaml").read_text())["hydra"]["overrides"]["task"]
    assert "compile=true" in task
    folders = sorted(p.name for p in sweep.iterdir() if p.is_dir())
    command = ["-m", "hydra/launcher=fused", *task, f"hydra.sweep.dir={sweep}"]
    again = drone_train(*command, cwd=runs)
    assert again.returncode == 0, again.stderr
    assert "note: compile=true is ignored" in again.stderr
    assert again.stdout.count("already finished (4 episodes)") == 2
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == folders
    longer = [a if not a.startswith("algo.episodes=") else "algo.episodes=6" for a in command]
    proc = drone_train(*longer, cwd=runs)
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == folders
    for folder in folders:
        assert load_checkpoint(sweep / folder / "checkpoints" / "last.pt")["episodes_done"] == 6


@pytest.mark.parametrize(
    ("old", "note", "backend"),
    [
        ("engine=torchrl", "engine=torchrl is now backend=reference", "reference"),
        # In this process (drone_train), under a second each: all in the default run.
        ("engine=fused", "engine=fused is now backend=fast", "fast"),
        ("compile=false", "compile=false is ignored", "fast"),
        ("steps_per_call=5", "steps_per_call=5 is ignored", "fast"),
        ("updates_per_call=7", "updates_per_call=7 is ignored", "fast"),
    ],
)
def test_old_keys_on_the_command_line_work_with_a_note(tmp_path, old, note, backend, drone_train):
    proc = drone_train(
        old, "algo.episodes=2", "env.max_steps=20", "eval.video=false", f"hydra.run.dir={tmp_path / 'run'}",
        cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    notes = [line for line in proc.stderr.splitlines() if "note:" in line]
    assert len(notes) == 1 and note in notes[0] and "Traceback" not in proc.stderr
    assert load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")["backend"] == backend
    config = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    assert config["backend"] == backend and migrations.LEGACY not in config
