"""Runs written by main at 8b4447f and stopped mid-way end as if never stopped, on today's code.

The fixtures (tests/fixtures/main_8b4447f, how they were made: its README) are a REINFORCE run, two
PPO runs (one per backend), a fused sweep of two seeds, a population of three, a PBT search and a successive-halving
search, each stopped by SIGTERM part-way through its budget; ``expected/`` holds the episodes of
the same commands run without a stop. Each test continues a copy with the run's own command and
compares every episode (all columns but the wall-clock) and the search's lineage with them.
"""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import pytest

from drone_torchrl.apps import train as train_app

# About 30 s in all: CI's slow stage.
pytestmark = pytest.mark.slow

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "main_8b4447f"
QUIET = ["env.max_steps=30", "eval.episodes=2", "eval.video=false", "progress=false"]
SWEEPS = {
    "sweep_fused": ["-m", "seed=0,1", "hydra/launcher=fused"],
    "population": ["-m", "seed=0,1,2", "hydra/launcher=population"],
    "pbt": [
        "-m",
        "hydra/launcher=pbt",
        "hydra.launcher.every_updates=5",
        "algo.lr=1e-4,3e-4,1e-3,3e-3",
        "seed=0",
    ],
    "halving": ["-m", "hydra/launcher=halving", "hydra.launcher.rungs=[10,20]", "seed=0,1,2,3"],
}


def _expected(name: str) -> list[dict[str, str]]:
    with open(FIXTURES / "expected" / f"{name}.csv", newline="") as f:
        return list(csv.DictReader(f))


def _rows(rows: list[dict], columns: list[str]) -> list[dict[str, str]]:
    """Rows as the expected CSVs hold them: those columns, each value as ``csv`` writes it."""
    return [{c: str(row[c]) for c in columns} for row in rows]


def _csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _sweep_again(drone_train, runs: Path, name: str) -> None:
    """The sweep's own command again, in its folder: it continues from the checkpoints."""
    command = [
        *SWEEPS[name],
        "algo.episodes=40",
        "eval.every_episodes=10",
        *QUIET,
        f"hydra.sweep.dir={runs / name}",
    ]
    proc = drone_train(*command, cwd=runs)
    assert proc.returncode == 0, proc.stderr


@pytest.fixture
def drone_train(command_here):
    return lambda *args, cwd: command_here(train_app.run, "drone-train", *args, cwd=cwd)


@pytest.fixture
def runs(tmp_path) -> Path:
    shutil.copytree(FIXTURES, tmp_path / "runs", ignore=shutil.ignore_patterns("expected", "*.md", "*.py"))
    return tmp_path / "runs"


@pytest.mark.parametrize("name", ["run_reinforce", "run_ppo_fast"])
def test_a_stopped_run_resumes_to_the_uninterrupted_episodes(runs, drone_train, name):
    stopped = len(_csv(runs / name / "episodes.csv"))
    expected = _expected(name)
    assert 0 < stopped < len(expected)
    proc = drone_train(f"resume={runs / name}", cwd=runs)
    assert proc.returncode == 0, proc.stderr
    assert f"continuing from episode {stopped}" in proc.stdout
    assert _rows(_csv(runs / name / "episodes.csv"), list(expected[0])) == expected


def test_a_stopped_reference_ppo_run_resumes_with_every_episode_once(runs, drone_train):
    """``backend=reference``: TorchRL's collector starts its drones afresh on resume (their episodes
    in flight were not booked), so the run goes on with other episodes than an uninterrupted one,
    none lost or booked twice, to its budget."""
    stopped = _csv(runs / "run_ppo" / "episodes.csv")
    expected = _expected("run_ppo")
    proc = drone_train(f"resume={runs / 'run_ppo'}", cwd=runs)
    assert proc.returncode == 0, proc.stderr
    assert f"continuing from episode {len(stopped)}" in proc.stdout
    resumed = _rows(_csv(runs / "run_ppo" / "episodes.csv"), list(expected[0]))
    assert resumed[: len(stopped)] == expected[: len(stopped)]
    assert [int(row["episode"]) for row in resumed] == list(range(len(resumed)))
    assert len(resumed) >= 48


def test_a_stopped_fused_sweep_resumes_to_the_uninterrupted_episodes(runs, drone_train):
    sweep = runs / "sweep_fused"
    _sweep_again(drone_train, runs, "sweep_fused")
    expected = _expected("sweep_fused")
    got = []
    for job in sorted(sweep.glob("*seed=*")):
        seed = job.name.rsplit("seed=", 1)[1]
        got += [{"seed": seed, **row} for row in _csv(job / "episodes.csv")]
    assert _rows(got, list(expected[0])) == expected


@pytest.mark.parametrize("name", ["population", "pbt", "halving"])
def test_a_stopped_population_resumes_to_the_uninterrupted_episodes(runs, drone_train, name):
    pq = pytest.importorskip("pyarrow.parquet", reason="a population's record needs the population extra")
    run = runs / name / "population_0"
    before = pq.read_table(run / "episodes").num_rows
    expected = _expected(name)
    assert 0 < before < len(expected)
    _sweep_again(drone_train, runs, name)
    episodes = sorted(pq.read_table(run / "episodes").to_pylist(), key=lambda r: (r["agent"], r["episode"]))
    assert _rows(episodes, list(expected[0])) == expected
    if (FIXTURES / "expected" / f"{name}_lineage.csv").exists():
        lineage = _expected(f"{name}_lineage")
        assert _rows(pq.read_table(run / "lineage.parquet").to_pylist(), list(lineage[0])) == lineage
