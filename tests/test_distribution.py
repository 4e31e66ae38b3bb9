"""drone-report's seed distributions and the paper's cumulative averaging, on hand-made runs."""

import numpy as np
import pytest
from test_report import _job

from drone_torchrl.apps.report import main
from drone_torchrl.report.distribution import (
    distribution,
    paper_averaged_curves,
    paper_order,
    per_setting_curves,
    small_study_band,
)
from drone_torchrl.report.runs import ReportError, group_runs, load_runs

# Returns per run (window 1: the running mean is the raw value), 2 seeds per learning rate.
RUNS = {
    1e-3: ([10, 10], [30, 50]),
    5e-4: ([100, 200], [300, 400]),
    1e-4: ([1000, 1000], [2000, 3000]),
    5e-5: ([20, 40], [60, 80]),
}


def _settings(tmp_path, runs=RUNS):
    sweep = tmp_path / "lr"
    for lr, per_seed in runs.items():
        for seed, returns in enumerate(per_seed):
            _job(sweep, lr, seed, returns, lengths=[300, 300] if lr == 1e-4 else [5, 5])
    return group_runs(load_runs(sweep))


def test_cumulative_averaging_by_hand(tmp_path):
    key, ordered = paper_order(_settings(tmp_path))
    assert key == "algo.lr"
    assert [s.label for s in ordered] == [
        "algo.lr=5e-05",
        "algo.lr=0.0001",
        "algo.lr=0.0005",
        "algo.lr=0.001",
    ]
    own = per_setting_curves(ordered, "return", 1)
    pooled = paper_averaged_curves(ordered, "return", 1)
    # Per setting: each setting's two runs. As the paper: runs of settings 1..k (2k runs).
    np.testing.assert_allclose(own[0], [40, 60])
    np.testing.assert_allclose(own[1], [1500, 2000])
    np.testing.assert_allclose(pooled[0], [40, 60])
    np.testing.assert_allclose(pooled[1], [(20 + 60 + 1000 + 2000) / 4, (40 + 80 + 1000 + 3000) / 4])
    np.testing.assert_allclose(
        pooled[2], [(20 + 60 + 1000 + 2000 + 100 + 300) / 6, (40 + 80 + 1000 + 3000 + 200 + 400) / 6]
    )
    np.testing.assert_allclose(pooled[3], [(3480 + 10 + 30) / 8, (4720 + 10 + 50) / 8])


def test_gamma_grids_go_in_the_paper_order_and_other_sweeps_are_refused(tmp_path):
    settings = _settings(tmp_path / "a", {1e-3: ([1, 1],), 1e-4: ([1, 1],)})
    assert [s.label for s in paper_order(settings)[1]] == ["algo.lr=0.0001", "algo.lr=0.001"]
    odd = _settings(tmp_path / "b", {2e-3: ([1, 1],), 1e-4: ([1, 1],)})
    with pytest.raises(ReportError, match="--paper-averaging needs"):
        paper_order(odd)


def test_distribution_by_hand(tmp_path):
    settings = {s.label: s for s in _settings(tmp_path)}
    d = distribution(settings["algo.lr=0.0001"], 1)
    assert d.final_returns.tolist() == [1000, 3000] and d.median == 2000
    assert d.reached_full_length == 2 and d.in_zone == 1  # 3000 >= 1500, 1000 < 1500
    low, high = d.median_ci
    assert 1000 <= low <= 2000 <= high <= 3000
    d = distribution(settings["algo.lr=0.001"], 1)
    assert d.reached_full_length == 0 and d.in_zone == 0
    assert np.isnan(d.four_seed_band[0])  # fewer than 4 seeds: no 4-seed band


def test_four_seed_band_of_a_bimodal_setting():
    """8 seeds, half at 0 and half at 2000. 4 drawn without replacement hold k of the 2000s with
    probability C(4,k) C(4,4-k) / C(8,4) = 1, 16, 36, 16, 1 (/70): the mean 500 k is 0 or 2000 only
    1.4% of the time each, so the central 95% of 4-seed means spans 500 to 1500."""
    values = np.array([0.0] * 4 + [2000.0] * 4)
    low, high = small_study_band(values, np.random.default_rng(0))
    assert (low, high) == (500.0, 1500.0)
    low, high = small_study_band(np.full(8, 7.0), np.random.default_rng(0))
    assert low == high == 7.0


def test_cli_writes_the_paper_averaging_figure(tmp_path, capsys):
    _settings(tmp_path)
    main([str(tmp_path / "lr"), "--no-pd", "--window", "1", "--paper-averaging"])
    out = capsys.readouterr().out
    assert "| algo.lr=0.001 | 8 | 30 | 598 |" in out  # final: own (10 + 50) / 2, pooled 4780 / 8 = 597.5
    for name in ("finals.png", "paper_averaging.png"):
        assert (tmp_path / "lr" / "report" / name).stat().st_size > 0
