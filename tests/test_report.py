"""drone-report: running means, seed aggregation, grouping, crossings, verdict, files, CLI errors."""

import csv

import numpy as np
import pytest
from omegaconf import OmegaConf

from drone_torchrl.apps import train as train_app
from drone_torchrl.apps.report import main
from drone_torchrl.config import ENV_ADDED
from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, FORMAT_VERSION, LAST, REQUIRED_KEYS, save_checkpoint
from drone_torchrl.io.episodes_csv import CSV_COLUMNS
from drone_torchrl.report import (
    aggregate_over_seeds,
    build_report,
    first_crossing,
    running_mean,
    setting_curve,
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


def _save_last_checkpoint(job, config, episodes, final):
    """checkpoints/last.pt with every key load_checkpoint requires; ``final`` is None while unfinished."""
    state = dict.fromkeys(REQUIRED_KEYS)
    state.update(
        format_version=FORMAT_VERSION,
        backend="reference",
        actor={},
        optimizer={},
        episodes_done=episodes,
        updates_done=episodes,  # a counter load_checkpoint checks (an integer >= 0)
        config=config,
        final=final,
    )
    save_checkpoint(state, job / CHECKPOINT_DIR / LAST)


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
    final = {"final_return": float(np.mean(returns))} if finished else None
    _save_last_checkpoint(job, config, len(returns), final)
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


def test_report_on_a_real_tiny_sweep(tmp_path, command_here):
    """The sweep is drone-train's, run in this process (tests/conftest.py's command_here)."""
    sweep = tmp_path / "sweep"
    argv = [
        "-m",
        "algo.lr=1e-3,1e-4",
        "seed=0,1",
        "algo.episodes=3",
        "env.max_steps=20",
        "eval.video=false",
        "eval.episodes=1",
        f"hydra.sweep.dir={sweep}",
    ]
    trained = command_here(train_app.run, "drone-train", *argv, cwd=tmp_path)
    assert trained.returncode == 0, trained.stderr
    main([str(sweep), "--no-pd"])
    for name in ("steps.png", "returns.png", "summary.md", "summary.csv"):
        assert (sweep / "report" / name).stat().st_size > 0
    rows = list(csv.DictReader((sweep / "report" / "summary.csv").open()))
    assert len(rows) == 2


# --- settings, partial runs, verdict, PD reference, several sweeps, errors -------------------------

ENV = {
    "mass": 1.0,
    "motor_distance": 1.0,
    "gravity": 9.81,
    "dt": 0.02,
    "max_steps": 10,
    "reset_mode": "floor",
    "max_thrust": None,
    "floor_tolerance": 0.05,
    "num_workers": 0,
}


def _write_job(job, overrides, config, returns, lengths, negative=None, clock=None, finished=True):
    """A job folder with arbitrary overrides and config (values as Hydra and drone-train write them)."""
    (job / ".hydra").mkdir(parents=True)
    OmegaConf.save(OmegaConf.create(list(overrides)), job / ".hydra" / "overrides.yaml")
    OmegaConf.save(OmegaConf.create(config), job / "config.yaml")
    negative = negative or [0.5] * len(returns)
    clock = clock or [float(i + 1) for i in range(len(returns))]
    with (job / "episodes.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for i, row in enumerate(zip(returns, lengths, negative, clock, strict=True)):
            r, n, neg, t = row
            writer.writerow(
                {
                    "episode": i,
                    "update": i + 1,
                    "return": r,
                    "length": n,
                    "time_in_zone": 0.0,
                    "negative_thrust_fraction": neg,
                    "termination_cause": "NONE",
                    "wall_clock_s": t,
                }
            )
    final = {"final_return": float(returns[-1])} if finished else None
    _save_last_checkpoint(job, config, len(returns), final)
    return job


def _config(lr, seed, gamma=0.99, max_steps=10):
    return {"seed": seed, "algo": {"lr": lr, "gamma": gamma}, "env": {**ENV, "max_steps": max_steps}}


def test_settings_normalise_values_and_ignore_non_setting_keys(tmp_path):
    sweep = tmp_path / "lr"
    extra = [
        "+sweep=lr",
        "algo.episodes=3",
        "env.max_steps=10",
        "eval.video=False",
        "checkpoint.every_episodes=5",
        "hydra.launcher.n_jobs=2",
        "progress=false",
    ]
    # "1e-3" and "0.001" are the same learning rate: the value is read back from config.yaml
    for i, (raw, lr) in enumerate([("1e-3", 1e-3), ("0.001", 1e-3), ("1e-4", 1e-4), ("0.0001", 1e-4)]):
        seed = i % 2
        _write_job(
            sweep / f"job{i}",
            [f"algo.lr={raw}", f"seed={seed}", *extra],
            _config(lr, seed),
            [1, 2, 3],
            [1, 2, 3],
        )
    report = build_report(sweep, window=2, pd=False)
    assert [s.label for s in report.settings] == ["algo.lr=0.0001", "algo.lr=0.001"]
    assert [[r.seed for r in s.runs] for s in report.settings] == [[0, 1], [0, 1]]


def test_labels_keep_only_differing_overrides(tmp_path):
    grid = tmp_path / "grid"
    for lr in (1e-3, 1e-4):
        for gamma in (0.9, 0.99):
            overrides = [f"algo.lr={lr}", f"algo.gamma={gamma}", "env.max_steps=10", "seed=0"]
            _write_job(grid / f"{lr}-{gamma}", overrides, _config(lr, 0, gamma), [1.0], [1])
    labels = [s.label for s in build_report(grid, window=2, pd=False).settings]
    assert labels == [
        "algo.lr=0.0001, algo.gamma=0.9",
        "algo.lr=0.0001, algo.gamma=0.99",
        "algo.lr=0.001, algo.gamma=0.9",
        "algo.lr=0.001, algo.gamma=0.99",
    ]
    seeds = tmp_path / "seeds"
    for seed in (0, 1):
        _write_job(seeds / f"s{seed}", ["algo.lr=0.001", f"seed={seed}"], _config(1e-3, seed), [1.0], [1])
    assert [s.label for s in build_report(seeds, window=2, pd=False).settings] == ["all"]


def test_runs_of_different_lengths_and_a_run_in_progress(tmp_path):
    sweep = tmp_path / "lr"
    # window 3. seed 0 (finished): returns [0, 3, 6, 9] -> [0, 1.5, 3, 6]; lengths [4, 10, 10, 10] -> [4, 7, 8, 10]
    _write_job(
        sweep / "s0",
        ["algo.lr=0.001", "seed=0"],
        _config(1e-3, 0),
        [0, 3, 6, 9],
        [4, 10, 10, 10],
        negative=[0.5] * 4,
        clock=[1, 2, 3, 4],
    )
    # seed 1 (in progress, no final checkpoint): returns [2, 4, 6] -> [2, 3, 4]; lengths all 10
    job = _write_job(
        sweep / "s1",
        ["algo.lr=0.001", "seed=1"],
        _config(1e-3, 1),
        [2, 4, 6],
        [10, 10, 10],
        negative=[0.1, 0.2, 0.3],
        clock=[1, 2, 5],
        finished=False,
    )
    with (job / "episodes.csv").open("a") as f:
        f.write("3,4,12")  # a row still being written is skipped, with a note
    report = build_report(sweep, window=3, return_threshold=3, pd=False)
    (setting,) = report.settings
    curve = setting_curve(setting, "return", 3)
    np.testing.assert_allclose(curve.mean, [1, 2.25, 3.5, 6])  # episode 3: only seed 0 has it
    np.testing.assert_allclose(curve.std, [1, 0.75, 0.5, 0])
    np.testing.assert_allclose(curve.min, [0, 1.5, 3, 6])
    np.testing.assert_allclose(curve.max, [2, 3, 4, 6])
    assert curve.count.tolist() == [2, 2, 2, 1]
    (row,) = report.summaries
    assert (row.seeds_finished, row.seeds_total, row.episodes_min, row.episodes_max) == (1, 2, 3, 4)
    assert row.final_returns == [6, 4]
    assert (row.final_return_mean, row.final_return_std) == (5, 1)
    assert row.final_return_pct == pytest.approx(5.0)  # of 10 * 10 steps
    assert row.length_cap.episodes == [3, 0] and row.length_cap.text() == "2 (2/2 seeds)"
    assert row.return_threshold.episodes == [2, 1] and row.return_threshold.mean == 1.5
    assert row.final_negative_thrust == pytest.approx((0.5 + 0.2) / 2)
    assert (row.wall_clock_mean_s, row.wall_clock_total_s) == (4.5, 9)
    assert row.notes[0] == "1 of 2 seeds unfinished, shortest at 3 episodes"
    assert row.notes[1:] == [f"{job / 'episodes.csv'}: line 5 is not a complete row; skipped"]
    assert report.verdict == "best: all (5.0 +- 1.0, 5.0% of 100); provisional: 1 of 2 runs not finished"


def test_verdict_names_the_best_mean_final_return(tmp_path):
    sweep = tmp_path / "lr"
    steps = [300] * 4
    for seed, level in enumerate((2060, 2360)):  # final running means 2060 and 2360: 2210 +- 150
        _write_job(
            sweep / f"a{seed}",
            ["algo.lr=0.0001", f"seed={seed}"],
            _config(1e-4, seed, max_steps=300),
            [level] * 4,
            steps,
        )
        _write_job(
            sweep / f"b{seed}",
            ["algo.lr=0.001", f"seed={seed}"],
            _config(1e-3, seed, max_steps=300),
            [1000] * 4,
            steps,
        )
    report = build_report(sweep, window=2, pd=False)
    assert report.verdict == "best: algo.lr=0.0001 (2210 +- 150, 73.7% of 3000)"
    assert [s.length_cap.episodes for s in report.summaries] == [[0, 0], [0, 0]]
    assert [s.return_threshold.text() for s in report.summaries] == ["0 (2/2 seeds)", "never (0/2 seeds)"]


def test_pd_reference_once_per_env_setting_and_several_sweeps(tmp_path, monkeypatch, capsys):
    from drone_torchrl.report import stats

    calls = []
    real = stats.evaluate_pd

    def counting(env_kwargs, episodes, seed):
        calls.append((env_kwargs, episodes, seed))
        return real(env_kwargs, episodes=episodes, seed=seed)

    monkeypatch.setattr(stats, "evaluate_pd", counting)
    stats._pd_return.cache_clear()
    sweeps = []
    for name in ("lr", "gamma"):
        for lr in (1e-3, 1e-4):
            _write_job(
                tmp_path / name / f"{lr}", [f"algo.lr={lr}", "seed=0"], _config(lr, 0), [5.0, 7.0], [5, 7]
            )
        sweeps.append(str(tmp_path / name))
    out = tmp_path / "out"
    try:
        main([*sweeps, "--out", str(out), "--window", "2"])
    finally:
        stats._pd_return.cache_clear()
    # Run folders from before the arena, bounds and dtype keys: evaluated with the values they ran with.
    expected_env = {**{k: v for k, v in ENV.items() if k != "num_workers"}, **ENV_ADDED}
    assert calls == [(expected_env, 100, 0)]  # two sweeps, one env setting: evaluated once
    for name in ("lr", "gamma"):
        for figure in ("steps.png", "returns.png"):
            assert (out / name / figure).read_bytes().startswith(b"\x89PNG")
        assert len(list(csv.DictReader((out / name / "summary.csv").open()))) == 2
        md = (out / name / "summary.md").read_text()
        assert md.startswith("best: algo.lr=") and "PD controller: mean return" in md
    printed = capsys.readouterr().out
    assert printed.count("best: algo.lr=") == 2 and "| algo.lr=0.0001 | 1/1 | 2 |" in printed


def test_default_output_folder_is_inside_the_sweep(tmp_path):
    sweep = tmp_path / "lr"
    _write_job(sweep / "a", ["algo.lr=0.001", "seed=0"], _config(1e-3, 0), [1.0], [1])
    main([str(sweep), "--no-pd"])
    assert sorted(p.name for p in (sweep / "report").iterdir()) == [
        "finals.png",
        "returns.png",
        "steps.png",
        "summary.csv",
        "summary.md",
    ]


def test_cli_error_for_jobs_without_episodes(tmp_path, capsys):
    good, empty = tmp_path / "good", tmp_path / "empty"
    _write_job(good / "a", ["seed=0"], _config(1e-3, 0), [1.0], [1])
    (empty / "job" / ".hydra").mkdir(parents=True)  # a job that never wrote episodes.csv
    with pytest.raises(SystemExit) as exit_info:
        main([str(good), str(empty), "--no-pd"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(empty) in err and "Traceback" not in err
    assert not (good / "report").exists()  # every folder is checked before any report is written


def test_landscape_of_a_two_key_grid(tmp_path):
    """2 learning rates x 2 discounts x 2 seeds, 300-step episodes (ceiling 3000, "in the zone" from
    1500): hand-computed cells."""
    from drone_torchrl.report.landscape import landscape, write_landscape

    sweep = tmp_path / "landscape"
    # final running mean over the default window = the mean of each run's returns (fewer than 100)
    runs = {
        (1e-3, 0.9): ([2000.0, 2000.0], [1000.0, 1000.0]),  # seed means 2000 and 1000
        (1e-3, 0.99): ([1600.0, 1600.0], [1400.0, 1600.0]),  # 1600 and 1500
        (1e-4, 0.9): ([100.0, 100.0], [100.0, 300.0]),  # 100 and 200
        (1e-4, 0.99): ([3000.0, 3000.0], [3000.0, 3000.0]),  # 3000 and 3000
    }
    lengths = {
        (1e-3, 0.9): [300, 300],
        (1e-3, 0.99): [150, 300],
        (1e-4, 0.9): [90, 120],
        (1e-4, 0.99): [300, 300],
    }
    for (lr, gamma), per_seed in runs.items():
        for seed, returns in enumerate(per_seed):
            _write_job(
                sweep / f"algo.gamma={gamma},algo.lr={lr},seed={seed}",
                [f"algo.lr={lr}", f"algo.gamma={gamma}", f"seed={seed}"],
                _config(lr, seed, gamma=gamma, max_steps=300),
                returns,
                lengths[(lr, gamma)],
            )
    grid = landscape(build_report(sweep, pd=False))
    assert grid is not None and (grid.x_key, grid.y_key) == ("algo.lr", "algo.gamma")
    assert grid.x_values == [1e-4, 1e-3] and grid.y_values == [
        0.9,
        0.99,
    ]  # gamma by its horizon -log(1 - gamma)
    # rows: gamma 0.9, 0.99; columns: lr 1e-4, 1e-3
    np.testing.assert_allclose(grid.median_return, [[150.0, 1500.0], [3000.0, 1550.0]])
    np.testing.assert_allclose(grid.zone_fraction, [[0.0, 0.5], [1.0, 1.0]])
    # running-mean length reaches 300: episode 0 at (1e-3, 0.9) and (1e-4, 0.99); lengths [150, 300]
    # never (running mean 225); [90, 120] never
    np.testing.assert_array_equal(grid.full_length_episode, [[np.inf, 0.0], [0.0, np.inf]])
    paths = write_landscape(grid, tmp_path / "out")
    assert paths[0].stat().st_size > 0
    rows = list(csv.DictReader(paths[1].open()))
    assert len(rows) == 4 and {r["median_full_length_episode"] for r in rows} == {"0", "never"}


def test_a_one_key_sweep_has_no_landscape(tmp_path):
    from drone_torchrl.report.landscape import landscape

    sweep = tmp_path / "lr"
    for i, lr in enumerate([1e-3, 1e-4]):
        _write_job(sweep / f"job{i}", [f"algo.lr={lr}", "seed=0"], _config(lr, 0), [1.0, 2.0], [1, 2])
    assert landscape(build_report(sweep, pd=False)) is None


def test_bounded_thrust_returns_show_their_share_of_the_optimum(tmp_path):
    """With max_thrust=1 the table, the CSV, the verdict and summary.md give each final return as a
    percentage of the best achievable return (2694, drone_torchrl.optimum); unbounded settings do not."""
    sweep = tmp_path / "thrust"
    for seed in (0, 1):
        for thrust in (1.0, None):
            config = _config(1e-3, seed, max_steps=300)
            config["env"]["max_thrust"] = thrust
            _write_job(
                sweep / f"{thrust},{seed}",
                [f"env.max_thrust={thrust}", f"seed={seed}"],
                config,
                [2000.0 + 694.0 * seed] * 3,
                [300] * 3,
            )
    report = build_report(sweep, window=2, pd=False)
    bounded, unbounded = sorted(report.summaries, key=lambda s: s.optimum is None)
    assert bounded.optimum == 2694.0 and unbounded.optimum is None
    assert bounded.final_return_pct_of_optimum == pytest.approx(100 * 2347 / 2694)
    assert list(report.optima) == ["optimum (env.max_thrust=1.0)"]
    assert report.verdict.startswith("best: ")
    paths = write_report(report, tmp_path / "out")
    md = next(p for p in paths if p.name == "summary.md").read_text()
    assert "| % of optimum |" in md and f"| {100 * 2347 / 2694:.1f}% of 2694 |" in md
    assert (
        "optimum (env.max_thrust=1.0): 2694, the best achievable return of every episode from these starts (in the zone from step 35, 266 of 300 steps;"
        in md
    )
    assert (
        "| median, % of optimum |" in md and f"| {100 * 2347 / 2694:.1f}% of 2694 |\n" in md
    )  # the seeds' table
    rows = list(csv.DictReader(next(p for p in paths if p.name == "summary.csv").open()))
    by_label = {row["setting"]: row for row in rows}
    assert float(by_label["env.max_thrust=1.0"]["optimum_return"]) == 2694.0
    assert by_label["env.max_thrust=null"]["final_return_pct_of_optimum"] == ""
