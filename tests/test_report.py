"""drone-report: running means, seed aggregation, grouping, crossings, verdict, files, CLI errors."""

import csv
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from drone_torchrl.metrics import CSV_COLUMNS
from drone_torchrl.report import (
    aggregate_over_seeds,
    build_report,
    first_crossing,
    main,
    running_mean,
    write_report,
)


def test_running_mean_by_hand():
    np.testing.assert_allclose(running_mean([0, 3, 6, 9], 3), [0, 1.5, 3, 6])
    np.testing.assert_allclose(running_mean([4, 2], 100), [4, 3])


def test_first_crossing():
    assert first_crossing([0, 100, 299.5, 300, 280], 300) == 3
    assert first_crossing([1, 2, 3], 10) is None


def test_aggregate_over_seeds_of_different_lengths():
    stats = aggregate_over_seeds([np.array([1.0, 3.0, 5.0]), np.array([3.0, 5.0])])
    np.testing.assert_allclose(stats.mean, [2, 4, 5])
    np.testing.assert_allclose(stats.std, [1, 1, 0])
    assert stats.count.tolist() == [2, 2, 1]


def _job(sweep, lr, seed, returns, lengths=None, finished=True, max_steps=300):
    """A job folder as drone-train writes it: .hydra/overrides.yaml, config.yaml, episodes.csv, checkpoint."""
    job = sweep / f"algo.lr={lr},seed={seed}"
    (job / ".hydra").mkdir(parents=True)
    OmegaConf.save(
        OmegaConf.create([f"algo.lr={lr}", f"seed={seed}", "+sweep=lr", "algo.episodes=4"]),
        job / ".hydra" / "overrides.yaml",
    )
    config = {
        "seed": seed,
        "algo": {"lr": lr, "gamma": 0.99},
        "env": {
            "mass": 1.0,
            "motor_distance": 1.0,
            "gravity": 9.81,
            "dt": 0.02,
            "max_steps": max_steps,
            "reset_mode": "floor",
            "max_thrust": None,
            "floor_tolerance": 0.05,
            "num_workers": 0,
        },
    }
    OmegaConf.save(OmegaConf.create(config), job / "config.yaml")
    lengths = lengths or [min(r, max_steps) for r in returns]
    with (job / "episodes.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for i, (r, n) in enumerate(zip(returns, lengths, strict=True)):
            writer.writerow(
                {
                    "episode": i,
                    "update": i + 1,
                    "return": r,
                    "length": n,
                    "time_in_zone": 0.0,
                    "negative_thrust_fraction": 0.25,
                    "termination_cause": "NONE",
                    "wall_clock_s": 10.0 * (i + 1),
                }
            )
    (job / "checkpoints").mkdir()
    state = {"episodes_done": len(returns)}
    if finished:
        state["final"] = {"final_return": float(np.mean(returns))}
    torch.save(state, job / "checkpoints" / "last.pt")
    return job


def test_report_groups_seeds_and_computes_the_table(tmp_path):
    sweep = tmp_path / "lr"
    # lr 1e-3: two seeds; window 2 running means of returns: seed 0 [0, 150, 300, 300], seed 1 [100, 200, 300, 300]
    _job(sweep, 1e-3, 0, [0, 300, 300, 300])
    _job(sweep, 1e-3, 1, [100, 300, 300, 300])
    # lr 1e-4: one finished seed, one still running (2 episodes so far)
    _job(sweep, 1e-4, 0, [0, 0, 100, 100])
    _job(sweep, 1e-4, 1, [0, 50], finished=False)
    report = build_report(sweep, window=2, return_threshold=250, pd=False)
    labels = [s.label for s in report.summaries]
    assert labels == ["algo.lr=0.0001", "algo.lr=0.001"]  # the seed is not part of a setting
    fast = report.summaries[1]
    assert fast.final_returns == [300, 300]
    assert fast.length_cap.episodes == [2, 2]  # running-mean length first reaches 300 at episode 2
    assert fast.return_threshold.episodes == [2, 2]
    assert fast.final_negative_thrust == pytest.approx(0.25)
    slow = report.summaries[0]
    assert slow.seeds_finished == 1 and slow.seeds_total == 2
    assert any("1 of 2 seeds unfinished, shortest at 2 episodes" in note for note in slow.notes)
    assert slow.final_returns == [100, 25]
    assert report.verdict.startswith("best: algo.lr=0.001 (300")
    assert "provisional" in report.verdict

    paths = write_report(report, tmp_path / "out")
    for path in paths:
        assert path.stat().st_size > 0
    rows = list(csv.DictReader((tmp_path / "out" / "summary.csv").open()))
    assert [r["setting"] for r in rows] == labels
    assert (tmp_path / "out" / "summary.md").read_text().splitlines()[0].startswith("best: algo.lr=0.001")


def test_cli_errors_are_one_line(tmp_path, capsys):
    for folder in (tmp_path / "missing", tmp_path):
        with pytest.raises(SystemExit) as exit_info:
            main([str(folder), "--no-pd"])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(folder) in err[0]


def test_report_on_a_real_tiny_sweep(tmp_path):
    sweep = tmp_path / "sweep"
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    cmd = [
        sys.executable,
        "-m",
        "drone_torchrl.train",
        "-m",
        "algo.lr=1e-3,1e-4",
        "seed=0,1",
        "algo.episodes=3",
        "env.max_steps=20",
        "eval.video=false",
        "eval.episodes=1",
        f"hydra.sweep.dir={sweep}",
    ]
    subprocess.run(cmd, check=True, capture_output=True, env=env, timeout=300)
    main([str(sweep), "--no-pd"])
    for name in ("steps.png", "returns.png", "summary.md", "summary.csv"):
        assert (sweep / "report" / name).stat().st_size > 0
    rows = list(csv.DictReader((sweep / "report" / "summary.csv").open()))
    assert len(rows) == 2
