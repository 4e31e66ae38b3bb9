"""What a search's record and report say (``drone_torchrl.training.pbt``, ``drone_torchrl.report``).

- The lineage holds every per-agent value an exploit or a restart changes, searched or not: an
  exploit copies the parent's whole row, so with ``hydra.launcher.keys=[algo.lr]`` the agent takes
  the parent's gamma too; a fork, a schedule and a replay follow it. An older lineage (searched
  keys only) reads as the parent's values then.
- A replay refuses a run still training, keeps its schedule in its checkpoint, and refuses to
  resume once the run replayed has changed.
- A PBT population too small for its quantile is refused in one line, nothing written.
- ``drone-report`` labels a search's agents by their final values, draws no landscape over values
  the agents did not keep, and draws every agent's schedule.
"""

from __future__ import annotations

import csv
import shutil

import pytest
import torch
from tensordict import TensorDict

from drone_torchrl.checks import ConfigError
from drone_torchrl.config import config_dir, validate
from drone_torchrl.io.checkpoint import load_checkpoint, save_checkpoint
from drone_torchrl.training import population_record as record_module
from drone_torchrl.training.pbt import PBT, PBTSettings, ReplaySettings, schedule
from drone_torchrl.training.trainer import train_population

pytest.importorskip("pyarrow")

COMMON = [
    "backend=fast",
    "env.max_steps=20",
    "eval.every_episodes=0",
    "eval.episodes=1",
    "eval.video=false",
    "progress=false",
    "logger=csv",
]
# A 2 x 2 grid of lr x gamma: with only lr searched, an exploit still copies the parent's gamma.
GRID = [("seed=0", f"algo.lr={lr}", f"algo.gamma={gamma}") for lr in (1e-4, 1e-3) for gamma in (0.9, 0.99)]
NAMES = [" ".join(agent) for agent in GRID]
LR_ONLY = PBTSettings(every_updates=2, quantile=0.25, resample_probability=0.0, keys=("algo.lr",))
LAST = ("checkpoints", "last.pt")


def _cfgs(*overrides: str):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfgs = [compose("config", overrides=[*COMMON, *overrides, *agent]) for agent in GRID]
    for cfg in cfgs:
        validate(cfg)
    return cfgs


def _copied(state: dict, lineage: dict) -> tuple[list[float], list[float]]:
    """Each agent's final gamma and lr, walking the lineage: an exploit copies the parent's gamma."""
    gammas, lrs = list(state["agents"]["algo.gamma"]), list(state["agents"]["algo.lr"])
    for agent, parent, lr in zip(lineage["agent"], lineage["parent"], lineage["algo.lr"], strict=True):
        gammas[agent], lrs[agent] = gammas[parent], lr
    return gammas, lrs


@pytest.fixture(scope="module")
def pbt_sweep(tmp_path_factory):
    """A sweep folder holding one finished PBT population run (4 agents, lr searched, 8 updates)."""
    sweep = tmp_path_factory.mktemp("pbt") / "sweep"
    run = sweep / "population_0"
    train_population(_cfgs("algo.episodes=8"), NAMES, run, lambda: (run / ".hydra").mkdir(), LR_ONLY)
    return sweep


def _state(n: int) -> TensorDict:
    """A population's state of ``n`` agents: lr 0.1 * (i + 1), gamma 0.9 + 0.01 * i, weight decay 0."""
    row = torch.arange(n, dtype=torch.float64)
    return TensorDict(
        {
            "params": row[:, None] * torch.ones(n, 3),
            "lr": 0.1 * (row + 1),
            "gamma": (0.9 + 0.01 * row).float(),
            "weight_decay": torch.zeros(n, dtype=torch.float64),
            "seed": torch.arange(n),
            "counter": torch.zeros(n, dtype=torch.int64),
        },
        batch_size=[n],
    )


VALUES = {
    "seed": [0, 1, 2, 3],
    "algo.lr": [0.1, 0.2, 0.3, 0.4],
    "algo.gamma": [0.9, 0.91, 0.92, 0.93],
    "algo.weight_decay": [0.0] * 4,
}


def test_an_exploit_records_the_parents_unsearched_gamma_and_the_schedule_follows_it():
    """keys=[algo.lr], 4 agents scored 0..3, quantile 0.25: agent 0 takes agent 3's row, gamma
    0.93 included. The lineage row says gamma 0.93 (and weight decay 0); agent 0's schedule is
    agent 3's first values, then from update 2 its explored lr with gamma 0.93."""
    state = _state(4)
    pbt = PBT(LR_ONLY, VALUES, {"algo.lr": (1e-6, 1.0)}, seed=0)
    assert pbt.step(state, [0.0, 1.0, 2.0, 3.0], [True] * 4, update=2) == [(0, 3)]
    assert pbt.lineage["algo.gamma"] == [0.93] and pbt.lineage["algo.weight_decay"] == [0.0]
    assert float(state["gamma"][0]) == pytest.approx(0.93)
    new_lr = pbt.lineage["algo.lr"][0]
    assert float(state["lr"][0]) == pytest.approx(new_lr)  # explored: whatever the exploration rule
    assert schedule(pbt.lineage, VALUES, 0) == [
        (0, {"algo.lr": 0.4, "algo.gamma": 0.93, "algo.weight_decay": 0.0}),
        (2, {"algo.lr": new_lr, "algo.gamma": 0.93, "algo.weight_decay": 0.0}),
    ]


def test_an_older_lineage_of_the_searched_keys_only_reads_as_the_parents_row():
    """A lineage written before every key was recorded (update, agent, parent, seed, algo.lr):
    agent 0 copied agent 3 at update 2, then agent 1 copied agent 0 at update 4. The missing gamma
    is the parent's then: 0.93 for both; a resumed search and the final values agree."""
    from drone_torchrl.training.pbt import complete_lineage, final_values

    old = {"update": [2, 4], "agent": [0, 1], "parent": [3, 0], "seed": [0, 1], "algo.lr": [0.32, 0.25]}
    full = complete_lineage(old, VALUES)
    assert full["algo.gamma"] == [0.93, 0.93] and full["algo.weight_decay"] == [0.0, 0.0]
    assert final_values(old, VALUES)["algo.gamma"] == [0.93, 0.93, 0.92, 0.93]
    resumed = PBT(LR_ONLY, VALUES, {"algo.lr": (1e-6, 1.0)}, seed=0, lineage=old)
    assert resumed.current["algo.gamma"] == [0.93, 0.93, 0.92, 0.93]
    assert schedule(old, VALUES, 1)[-1] == (
        4,
        {"algo.lr": 0.25, "algo.gamma": 0.93, "algo.weight_decay": 0.0},
    )


def test_a_fork_and_a_replay_of_a_pbt_agent_train_with_the_gamma_it_copied(pbt_sweep, tmp_path):
    """In a real run (lr searched, gamma 0.9 or 0.99 from the sweep): each lineage row's gamma is
    its parent's, the agent read back (resume/drone-eval agent=K) has its final gamma, and a
    replay of it sets gamma as well as lr at every step of its schedule."""
    run = pbt_sweep / "population_0"
    state = load_checkpoint(run.joinpath(*LAST))
    lineage = record_module.read_table(run / record_module.LINEAGE_TABLE)
    assert lineage["update"] == [2, 4, 6]
    gammas, _ = _copied(state, lineage)
    changed = [a for a in range(4) if gammas[a] != state["agents"]["algo.gamma"][a]]
    assert changed, "the run copied no other gamma: the test shows nothing"
    for agent in range(4):
        assert float(state["state"]["gamma"][agent]) == pytest.approx(gammas[agent])
        forked = record_module.agent_checkpoint(state, agent, run)
        assert forked["config"]["algo"]["gamma"] == gammas[agent]
    assert lineage["algo.gamma"] == [gammas[a] for a in lineage["agent"]]
    agent = changed[0]
    replay = ReplaySettings.of({"run": str(run), "agent": agent})
    steps = [(u, dict(v)) for u, v in replay.schedule]
    assert steps[-1][1]["algo.gamma"] == gammas[agent]
    fresh = tmp_path / "replay"
    train_population(_cfgs("algo.episodes=8", "algo.gamma=0.5"), NAMES, fresh, search=replay)
    replayed = record_module.read_table(fresh / record_module.LINEAGE_TABLE)
    for update, values in steps:
        rows = [i for i, u in enumerate(replayed["update"]) if u == update]
        assert {replayed["algo.gamma"][i] for i in rows} == {values["algo.gamma"]}
    kept = load_checkpoint(fresh.joinpath(*LAST))["state"]["gamma"]
    assert kept.tolist() == pytest.approx([gammas[agent]] * 4)


def test_a_replay_of_a_run_still_training_is_refused(pbt_sweep, tmp_path):
    """One agent of the PBT run without a final return (still training): refused in one line
    naming hydra.launcher.run, even with an agent that has finished."""
    run = tmp_path / "running"
    shutil.copytree(pbt_sweep / "population_0", run)
    state = load_checkpoint(run.joinpath(*LAST))
    state["final"][2] = None
    save_checkpoint(state, run.joinpath(*LAST))
    with pytest.raises(ConfigError, match=r"hydra\.launcher\.run=.*still training") as info:
        ReplaySettings.of({"run": str(run), "agent": 0})
    assert "\n" not in str(info.value) and "1 of its 4 agents" in str(info.value)


def test_a_replay_resumed_after_its_run_changed_is_refused(pbt_sweep, tmp_path):
    """A replay keeps its schedule in its checkpoint. Its source folder then holds another run
    (its lineage's lr differ): continuing the replay to a larger budget is refused in one line
    naming hydra.launcher.run; the unchanged source continues."""
    source = tmp_path / "source"
    shutil.copytree(pbt_sweep / "population_0", source)
    agent = record_module.read_table(source / record_module.LINEAGE_TABLE)["agent"][-1]  # one replaced
    replay = ReplaySettings.of({"run": str(source), "agent": agent})
    fresh = tmp_path / "replay"
    train_population(_cfgs("algo.episodes=4"), NAMES, fresh, search=replay)
    state = load_checkpoint(source.joinpath(*LAST))
    state["search"]["lineage"]["algo.lr"] = [lr * 2 for lr in state["search"]["lineage"]["algo.lr"]]
    save_checkpoint(state, source.joinpath(*LAST))
    changed = ReplaySettings.of({"run": str(source), "agent": agent})
    assert changed.schedule != replay.schedule
    with pytest.raises(ConfigError, match=r"hydra\.launcher\.run=.*schedule") as info:
        train_population(_cfgs("algo.episodes=6"), NAMES, fresh, search=changed)
    assert "\n" not in str(info.value)
    saved = load_checkpoint(fresh.joinpath(*LAST))
    assert saved["episodes_done"] == [4] * 4
    steps = saved["search"]["settings"]["schedule"]
    assert [(u, dict(v)) for u, v in steps] == [(u, dict(v)) for u, v in replay.schedule]


def test_a_replay_whose_checkpoint_predates_saved_schedules_still_continues(pbt_sweep, tmp_path):
    """A replay checkpoint whose settings hold no schedule (written before they did) continues to a
    larger budget, now with the schedule saved."""
    replay = ReplaySettings.of({"run": str(pbt_sweep / "population_0"), "agent": 0})
    fresh = tmp_path / "replay"
    train_population(_cfgs("algo.episodes=4"), NAMES, fresh, search=replay)
    state = load_checkpoint(fresh.joinpath(*LAST))
    del state["search"]["settings"]["schedule"]
    save_checkpoint(state, fresh.joinpath(*LAST))
    train_population(_cfgs("algo.episodes=6"), NAMES, fresh, search=replay)
    state = load_checkpoint(fresh.joinpath(*LAST))
    assert state["episodes_done"] == [6] * 4 and "schedule" in state["search"]["settings"]


def test_a_pbt_population_too_small_for_its_quantile_is_refused_before_anything_is_written(tmp_path):
    """2 agents at quantile 0.25: int(2 x 0.25) = 0 agents would ever be replaced. Refused in one
    line naming hydra.launcher.quantile and the smallest population that works (4)."""
    run = tmp_path / "run"
    with pytest.raises(ConfigError, match=r"hydra\.launcher\.quantile=0\.25.*at least 4 agents") as info:
        train_population(_cfgs("algo.episodes=8")[:2], NAMES[:2], run, search=LR_ONLY)
    assert "\n" not in str(info.value)
    assert not run.exists()


def test_drone_report_labels_a_pbt_runs_agents_by_their_final_values(pbt_sweep, tmp_path, capsys):
    """A PBT run over a 2 x 2 lr x gamma grid: each agent's setting is its final values (the
    lineage's last row for a replaced agent, with the gamma it copied), a note names the values it
    started with, no landscape.png is drawn over the starting grid (one line says why), and
    pbt_schedules.csv has every agent's schedule."""
    from drone_torchrl.apps.report import main as report_main
    from drone_torchrl.report.runs import load_runs, setting_of
    from drone_torchrl.report.schedules import SCHEDULES_CSV

    run = pbt_sweep / "population_0"
    state = load_checkpoint(run.joinpath(*LAST))
    lineage = record_module.read_table(run / record_module.LINEAGE_TABLE)
    gammas, lrs = _copied(state, lineage)
    replaced = sorted(set(lineage["agent"]))
    assert lrs[replaced[0]] != state["agents"]["algo.lr"][replaced[0]]
    runs = load_runs(pbt_sweep)
    assert len(runs) == 4
    for k, found in enumerate(runs):
        pairs = dict(setting_of(found.overrides, found.config))
        assert (float(pairs["algo.lr"]), float(pairs["algo.gamma"])) == (lrs[k], gammas[k])
        assert bool(found.notes) == (k in replaced)
    out = tmp_path / "report"
    report_main([str(pbt_sweep), "--no-pd", "--out", str(out)])
    assert not (out / "landscape.png").exists()
    assert "no landscape.png" in capsys.readouterr().out
    rows = list(csv.DictReader((out / SCHEDULES_CSV).open()))
    assert sorted({int(r["agent"]) for r in rows}) == [0, 1, 2, 3]
    assert {"algo.lr", "algo.gamma", "algo.weight_decay"} <= set(rows[0])
