"""``benchmarks/search_protocol.py``'s settings, its refusals and its goal check, without training."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def protocol():
    spec = importlib.util.spec_from_file_location(
        "search_protocol", ROOT / "benchmarks" / "search_protocol.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up while it loads
    spec.loader.exec_module(module)
    yield module
    del sys.modules[spec.name]


def test_the_default_protocol_is_the_docs_searches_on_8_tuning_and_16_test_seeds(protocol):
    plan = protocol.make_plan(protocol.parse_args([]))
    assert plan.tuning_seeds == tuple(range(110, 118)) and plan.test_seeds == tuple(range(500, 516))
    assert plan.searches == ("pbt", "halving", "pb2")
    assert len(plan.lrs) * len(plan.grid_gammas) == 64  # the landscape's cells
    assert len(plan.lrs) * len(plan.pbt_gammas) == 32  # PBT's agents
    assert set(plan.pbt_gammas) < set(plan.grid_gammas)
    # PBT spends 10% of the four-seed grid's episodes, as in docs/sweeps.md
    assert 32 * plan.pbt_episodes == 0.1 * 4 * 64 * plan.grid_episodes
    assert (plan.pbt_every_updates, plan.halving_rungs, plan.halving_fraction) == (400, (300, 900), 0.67)
    sweeps = protocol.protocol_sweeps(plan)
    assert len(sweeps) == 8 * 8 + 1  # per tuning seed: the grid and 3 searches, each with its test sweep
    assert sum(n * e for n, e in sweeps) == 7_929_600 + 8 * (32 * 4800 + 16 * 6000)  # + PB2


def test_a_smoke_plan_shrinks_agents_and_budgets(protocol):
    plan = protocol.make_plan(protocol.parse_args(["--max-values", "2", "--episodes-fraction", "0.005"]))
    assert plan.lrs == (3e-5, 3e-3) and plan.grid_gammas == (0.9, 0.999)
    assert plan.pbt_gammas == (0.94821, 0.99627)
    assert (plan.grid_episodes, plan.pbt_episodes, plan.halving_episodes, plan.test_episodes) == (
        30,
        24,
        12,
        30,
    )
    assert (plan.pbt_every_updates, plan.halving_rungs) == (2, (2, 4))


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--tuning-seeds", "1", "500"], "--tuning-seeds and --test-seeds share 500"),
        (["--tuning-seeds", "1", "1"], "--tuning-seeds 1 1: a seed is repeated"),
        (["--test-seeds", "7"], "--test-seeds 7: a bootstrap interval needs at least 2 test seeds"),
        (["--episodes-fraction", "0"], "--episodes-fraction 0.0: must be in (0, 1]"),
        (["--episodes-fraction", "1.5"], "--episodes-fraction 1.5: must be in (0, 1]"),
        (["--max-values", "1"], "--max-values 1: must be at least 2"),
        (["--searches", "pbt", "pb3"], "--searches pb3: unknown; known: pbt, halving, pb2"),
        (["seed=3"], "override seed=3: the protocol sets seed itself"),
        (["hydra.sweep.dir=x"], "override hydra.sweep.dir=x: the protocol sets hydra.sweep.dir itself"),
    ],
)
def test_a_bad_option_is_refused_in_one_line(protocol, capsys, argv, message):
    with pytest.raises(SystemExit) as exit_info:
        protocol.parse_args(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_a_search_whose_launcher_is_not_installed_is_refused(protocol, monkeypatch, capsys):
    monkeypatch.setitem(protocol.SEARCHES, "pb9", ("pb9", protocol.pbt_overrides))
    with pytest.raises(SystemExit):
        protocol.parse_args(["--searches", "pb9"])
    assert "--searches pb9: no hydra/launcher=pb9 in this installation" in capsys.readouterr().err


def test_a_folder_of_other_settings_is_refused_before_any_run(protocol, tmp_path, capsys):
    argv = ["--out", str(tmp_path), "--episodes-fraction", "0.5"]
    settings = protocol.make_plan(protocol.parse_args(argv)).as_json()
    (tmp_path / "settings.json").write_text(json.dumps({**settings, "pbt_episodes": 1}))
    with pytest.raises(SystemExit, match="holds other pbt_episodes"):
        protocol.main(argv)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["settings.json"]


def _row(protocol, seed, upper_vs_grid, vs_paper):
    return protocol.Row(
        seed, "pbt", "", 1, 1.0, False, 16, 2000.0, 1.0, (0.0, -100.0, upper_vs_grid), (vs_paper, 0.0, 0.0)
    )


@pytest.mark.parametrize(
    "uppers, vs_paper, verdict",
    [
        ([10, 0, 5, 5, 5, 5, -1, -1], [0] * 8, "Goal met"),  # 6 of 8 not worse: enough
        ([10, 0, 5, 5, 5, -1, -1, -1], [0] * 8, "Goal not met"),  # 5 of 8
        ([10] * 8, [0] * 7 + [-101], "Goal not met"),  # one tuning seed below the paper's - 100
        ([10] * 8, [0] * 7 + [-100], "Goal met"),
    ],
)
def test_the_goal_check(protocol, uppers, vs_paper, verdict):
    plan = protocol.make_plan(protocol.parse_args(["--searches", "pbt"]))
    rows = [_row(protocol, 110 + i, u, p) for i, (u, p) in enumerate(zip(uppers, vs_paper, strict=True))]
    text = protocol.summary(rows, plan)
    assert text.rstrip().endswith(f"{verdict}.")
    assert f"on >= 6/8 tuning seeds: {sum(u >= 0 for u in uppers)}/8" in text
