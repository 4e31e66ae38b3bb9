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


# --------------------------------------------------------------------------------------------------
# Comparing two versions: --drone-train, --grid-from, and a replay written before it kept a schedule


def _executable(path: Path) -> Path:
    path.write_text("#!/bin/sh\nexit 0\n")
    path.chmod(0o755)
    return path


def test_the_searches_executable_and_the_grids_folder_are_settings(protocol, tmp_path):
    plan = protocol.make_plan(protocol.parse_args([]))
    assert plan.drone_train == str(Path(sys.executable).parent / "drone-train") and plan.grid_from is None
    (tmp_path / "earlier").mkdir()
    (tmp_path / "earlier" / "settings.json").write_text(json.dumps(plan.as_json()))
    other = _executable(tmp_path / "drone-train")
    argv = [
        "--drone-train",
        str(other),
        "--grid-from",
        str(tmp_path / "earlier"),
        "--out",
        str(tmp_path / "o"),
    ]
    settings = protocol.make_plan(protocol.parse_args(argv)).as_json()
    assert (settings["drone_train"], settings["grid_from"]) == (str(other), str(tmp_path / "earlier"))


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--drone-train", "{tmp}/nothing"], "--drone-train {tmp}/nothing: not an executable file"),
        (["--grid-from", "{tmp}"], "--grid-from {tmp}: no settings.json there (not a protocol's folder)"),
        (["--grid-from", "{tmp}/p", "--out", "{tmp}/p"], "--grid-from {tmp}/p: is --out"),
        (["--grid-from", "{tmp}/p", "--estimate-only"], "--grid-from with --estimate-only: the estimate"),
    ],
)
def test_a_bad_drone_train_or_grid_folder_is_refused_in_one_line(protocol, tmp_path, capsys, argv, message):
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "settings.json").write_text("{}")
    with pytest.raises(SystemExit) as exit_info:
        protocol.parse_args([a.format(tmp=tmp_path) for a in argv])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert message.format(tmp=tmp_path) in err and len(err.strip().splitlines()) == 1


def _earlier(protocol, folder: Path, argv: list[str], **changes) -> None:
    """An earlier protocol's folder: its settings.json (with ``changes``), no sweeps."""
    folder.mkdir()
    settings = protocol.make_plan(protocol.parse_args(argv)).as_json()
    (folder / "settings.json").write_text(json.dumps({**settings, **changes}))


def test_a_grid_folder_of_other_settings_or_unfinished_sweeps_is_refused_before_any_run(protocol, tmp_path):
    argv = ["--out", str(tmp_path / "out"), "--tuning-seeds", "110", "--searches", "pbt"]
    _earlier(protocol, tmp_path / "other", argv, pbt_episodes=1, test_episodes=2)
    with pytest.raises(SystemExit, match=r"its settings.json holds other test_episodes, pbt_episodes "):
        protocol.main([*argv, "--grid-from", str(tmp_path / "other")])
    # the searches and tuning seeds may differ: the earlier protocol's grid is the same grid
    _earlier(protocol, tmp_path / "same", argv, searches=["halving"], tuning_seeds=[111, 112])
    (tmp_path / "same" / "paper_default").mkdir()
    (tmp_path / "same" / "paper_default" / "test.done.json").write_text("{}")
    with pytest.raises(SystemExit) as exit_info:
        protocol.main([*argv, "--grid-from", str(tmp_path / "same")])
    grid = tmp_path / "same" / "seed_110"
    assert str(exit_info.value) == (
        f"--grid-from {tmp_path / 'same'}: unfinished sweeps, no {grid / 'grid.done.json'}, "
        f"{grid / 'grid_test.done.json'}"
    )
    assert not (tmp_path / "out").exists()


def test_a_folder_written_before_the_two_settings_existed_is_continued(protocol, tmp_path, monkeypatch):
    argv = ["--out", str(tmp_path), "--episodes-fraction", "0.5"]
    settings = protocol.make_plan(protocol.parse_args(argv)).as_json()
    del settings["drone_train"], settings["grid_from"]  # it ran this venv's drone-train, its own grid
    (tmp_path / "settings.json").write_text(json.dumps(settings))

    def first_sweep(folder, overrides, plan, drone_train=None):
        raise RuntimeError(f"run {folder.relative_to(tmp_path)}")

    monkeypatch.setattr(protocol, "run_sweep", first_sweep)
    with pytest.raises(RuntimeError, match="run paper_default/test"):
        protocol.main(argv)
    with pytest.raises(SystemExit, match="holds other drone_train: use another --out"):
        protocol.main([*argv, "--drone-train", str(_executable(tmp_path / "drone-train"))])


def test_an_earlier_protocols_sweep_is_read_where_it_ran(protocol, tmp_path, capsys):
    plan = protocol.make_plan(protocol.parse_args(["--tuning-seeds", "110"]))
    folder = tmp_path / "seed_110" / "grid"
    folder.parent.mkdir()
    overrides = protocol.grid_overrides(plan, 110)
    # that protocol ran with a relative --out, from its own working directory
    command = protocol.sweep_arguments(Path("benchmarks/out/p/seed_110/grid"), overrides, plan)
    done = tmp_path / "seed_110" / "grid.done.json"
    done.write_text(json.dumps({"command": command, "wall_clock_s": 49.8, "resumed": False}))
    sweep = protocol.read_sweep(folder, overrides, plan)
    assert (sweep.folder, sweep.wall_clock_s, sweep.resumed) == (folder, 49.8, False)
    assert f"{folder}: read (49.8 s)" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="grid.done.json was written by another command"):
        protocol.read_sweep(folder, protocol.grid_overrides(plan, 111), plan)


def _population(folder: Path, **state) -> None:
    """A population run's checkpoint holding ``state`` besides the keys every one has."""
    from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, FORMAT_VERSION, LAST, save_checkpoint

    (folder / CHECKPOINT_DIR).mkdir(parents=True)
    keys = {"kind": "population", "format_version": FORMAT_VERSION, "backend": "torchrl", "state": {}}
    keys |= {"config": {}, "episodes_done": [6, 6], "updates_done": [6, 6], "failure": [None, None]}
    keys |= {"parts": [], "agents": {}, "final": [None, None]}
    save_checkpoint({**keys, **state}, folder / CHECKPOINT_DIR / LAST)


def test_a_replay_without_a_schedule_in_its_checkpoint_reads_it_from_its_runs_lineage(protocol, tmp_path):
    run = tmp_path / "pbt" / "population_0"
    lineage = {
        "update": [4],
        "agent": [1],
        "parent": [0],
        "seed": [7],
        "algo.lr": [1.2e-3],
        "algo.gamma": [0.99],
    }
    _population(
        run,
        agents={"algo.lr": [1e-3, 2e-3], "algo.gamma": [0.99, 0.95]},
        final=[{"final_return": 2000.0}, {"final_return": 2500.0}],
        search={"settings": {"launcher": "pbt", "keys": ["algo.lr", "algo.gamma"]}, "lineage": lineage},
    )
    record = {"launcher": "pbt_replay", "run": str(run), "agent": 1}  # as the replay wrote it before
    _population(tmp_path / "old_test" / "population_0", search={"settings": record})
    # agent 1 was a copy of agent 0 from update 4: agent 0's values before, its own from then on
    assert protocol.replayed(tmp_path / "old_test") == (
        "agent 1 (final 2500): 0: lr 0.001, gamma 0.99; 4: lr 0.0012, gamma 0.99"
    )
    # a replay's own schedule, when its checkpoint keeps one, is the one it followed
    record["schedule"] = [[0, {"algo.lr": 3e-3, "algo.gamma": 0.9}]]
    _population(tmp_path / "new_test" / "population_0", search={"settings": record})
    assert protocol.replayed(tmp_path / "new_test") == "agent 1 (final 2500): 0: lr 0.003, gamma 0.9"
