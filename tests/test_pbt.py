"""Population-based training inside a population run (``hydra/launcher=pbt``, drone_torchrl.training.pbt).

- An exploit step copies the best agents' rows of the stacked state into the worst agents' rows
  and moves or resamples the searched keys within the sweep's values; an agent keeps its seed and count.
- A killed and resumed PBT run takes the same steps (lineage) and flies the same episodes as an
  uninterrupted one.
- An agent read back from the run (drone-eval / drone-export / resume ``agent=K``) has the values
  PBT gave it.
"""

from __future__ import annotations

import csv
import os
import signal

import pytest
import torch
from tensordict import TensorDict
from test_population_run import AGENTS, COMMON, NAMES, _by_agent, _same

from drone_torchrl.config import config_dir, validate
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.training import population_record as record_module
from drone_torchrl.training.pb2 import PB2Settings
from drone_torchrl.training.pbt import FRESH, PBT, HalvingSettings, PBTSettings, ReplaySettings, schedule
from drone_torchrl.training.signals import TrainingStopped
from drone_torchrl.training.trainer import train_population

pytest.importorskip("pyarrow")

LR_SPACE = [1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1, 3e-1]


def _state(n: int) -> TensorDict:
    """A population's state of ``n`` agents whose rows all differ."""
    row = torch.arange(n, dtype=torch.float64)
    return TensorDict(
        {
            "params": row[:, None] * torch.ones(n, 5),
            "exp_avg": row[:, None] * 10 + torch.zeros(n, 5),
            "exp_avg_sq": row[:, None] * 100 + torch.zeros(n, 5),
            "adam_steps": row.float() + 1000,
            "lr": torch.tensor(LR_SPACE, dtype=torch.float64),
            "weight_decay": torch.zeros(n, dtype=torch.float64),
            "gamma": torch.full((n,), 0.99, dtype=torch.float32),
            "seed": torch.arange(n) + 50,
            "counter": torch.full((n,), 7),
        },
        batch_size=[n],
    )


def _pbt(resample: float) -> PBT:
    settings = PBTSettings(every_updates=5, quantile=0.25, resample_probability=resample)
    space = {"algo.lr": LR_SPACE, "algo.gamma": [0.99] * 8, "seed": list(range(50, 58))}
    return PBT(settings, space, {"algo.lr": (0.0, 1.0), "algo.gamma": (0.0, 1.0)}, seed=50)


def test_an_exploit_step_copies_the_best_rows_into_the_worst_and_perturbs_their_values():
    """8 agents scored 0..7 (agent 7 best), quantile 0.25: agents 0 and 1 take the rows of agents
    drawn from 6 and 7 (weights, Adam's moments and steps), keep their seed and update count, and
    get the lr next to the parent's in the sweep's list (agent 7's, the list's end: its own or the
    one below) and gamma 0.99 (the list's only value); each replacement is a lineage row. The same
    update gives the same step."""
    state, pbt = _state(8), _pbt(resample=0.0)
    pairs = pbt.step(state, [float(i) for i in range(8)], [True] * 8, update=10)
    assert sorted(agent for agent, _ in pairs) == [0, 1]
    assert all(parent in (6, 7) for _, parent in pairs)
    for agent, parent in pairs:
        for key in ("params", "exp_avg", "exp_avg_sq", "adam_steps"):
            assert torch.equal(state[key][agent], _state(8)[key][parent]), key
        assert int(state["seed"][agent]) == 50 + agent and int(state["counter"][agent]) == 7
        assert float(state["lr"][agent]) in (LR_SPACE[parent - 1], LR_SPACE[min(parent + 1, 7)])
        assert float(state["gamma"][agent]) == pytest.approx(0.99)
    for agent in range(2, 8):  # the others are left as they were
        assert torch.equal(state["params"][agent], _state(8)["params"][agent])
    assert pbt.lineage["update"] == [10, 10]
    assert sorted(pbt.lineage["agent"]) == [0, 1]
    assert [float(state["lr"][a]) for a in pbt.lineage["agent"]] == pbt.lineage["algo.lr"]
    again = _pbt(resample=0.0)
    again_state = _state(8)
    assert again.step(again_state, [float(i) for i in range(8)], [True] * 8, update=10) == pairs
    assert torch.equal(again_state["lr"], state["lr"])


def test_a_resample_draws_from_the_sweeps_values_and_a_dead_agent_takes_no_part():
    """resample_probability=1: the new lr is one of the sweep's values. A diverged agent (here the
    worst-scored) is neither replaced nor copied from."""
    state, pbt = _state(8), _pbt(resample=1.0)
    alive = [True] * 8
    alive[0] = False
    pairs = pbt.step(state, [float(i) for i in range(8)], alive, update=5)
    assert [agent for agent, _ in pairs] == [1] and pairs[0][1] == 7  # 7 alive agents: one of each side
    assert float(state["lr"][1]) in LR_SPACE
    assert torch.equal(state["params"][0], _state(8)["params"][0])


def _cfgs(*overrides: str):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfgs = [compose("config", overrides=[*COMMON, *overrides, *agent]) for agent in AGENTS]
    for cfg in cfgs:
        validate(cfg)
    return cfgs


SEARCH = PBTSettings(every_updates=2, quantile=0.34, resample_probability=0.25)


HALVING = HalvingSettings(rungs=(2, 4), fraction=0.34)
PB2_SEARCH = PB2Settings(every_updates=2, quantile=0.34)


@pytest.mark.parametrize("search", [SEARCH, PB2_SEARCH, HALVING], ids=["pbt", "pb2", "halving"])
def test_a_killed_and_resumed_search_takes_the_steps_of_an_uninterrupted_one(tmp_path, monkeypatch, search):
    """3 agents, 12 episodes; PBT and PB2: an exploit step every 2 updates (one agent replaced each time);
    halving: rungs at ages 2 and 4, the worst third stopped and restarted. SIGTERM at update 5
    stops it with a checkpoint; resumed to 12 it writes the uninterrupted run's lineage and every
    agent's episodes once, with the same returns. PBT's read-back agent has the lr PBT gave it."""
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    train_population(_cfgs("algo.episodes=12"), NAMES, whole, search=search)
    lineage = record_module.read_table(whole / record_module.LINEAGE_TABLE)
    if search is not HALVING:
        assert lineage["update"] == [2, 4, 6, 8, 10]  # none after the last update: the budget is reached
    else:  # every agent meets rung 2 at update 2; restarted ones meet it again 2 updates later
        assert lineage["update"][0] == 2 and set(lineage["parent"]) == {FRESH}
    assert all(a != p for a, p in zip(lineage["agent"], lineage["parent"], strict=True))

    book = record_module.PopulationRecord.after_update

    def signal_at_five(self):
        book(self)
        if self.updates == 5:
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(record_module.PopulationRecord, "after_update", signal_at_five)
    with pytest.raises(TrainingStopped):
        train_population(_cfgs("algo.episodes=12"), NAMES, cut, search=search)
    monkeypatch.setattr(record_module.PopulationRecord, "after_update", book)
    stopped_at = load_checkpoint(cut / "checkpoints" / "last.pt")["episodes_done"]
    assert 5 <= stopped_at[0] < 12 and len(set(stopped_at)) == 1
    train_population(_cfgs("algo.episodes=12"), NAMES, cut, search=search)
    assert record_module.read_table(cut / record_module.LINEAGE_TABLE) == lineage
    _same(_by_agent(cut), _by_agent(whole))
    if search is not SEARCH:
        return
    last, parent = lineage["agent"][-1], lineage["parent"][-1]
    state = load_checkpoint(whole / "checkpoints" / "last.pt")
    # Replaced at update 10, the agent is scored by its parent's 10 episodes, then its own 2.
    recent = state["recent_returns"]
    assert torch.equal(recent[last][:10], recent[parent][:10])
    assert not torch.equal(recent[last][10:12], recent[parent][10:12])
    agent = record_module.agent_checkpoint(state, last, whole)
    assert agent["config"]["algo"]["lr"] == lineage["algo.lr"][-1]


def test_halving_stops_the_worst_of_everything_a_rung_has_seen_and_restarts_their_slots():
    """4 agents of seeds 0..3, one rung at age 10, fraction 0.5. At update 10, scores 1, 2, 3, 4:
    agents 0 and 1 stop; their slots restart with seeds 4 and 5 (fresh weights: build_policies',
    fresh Adam), values drawn from the sweep's, age 0 (lineage parent -1). At update 20 they reach
    the rung: scored 2.5 and 0.5 among the rung's six scores 1, 2, 3, 4, 2.5, 0.5, the worst three
    are those below 2.5: only agent 1 (0.5) stops again."""
    from hydra import compose, initialize_config_dir

    from drone_torchrl.modules.factory import build_policies
    from drone_torchrl.training.population import Population

    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfgs = [compose("config", overrides=["backend=fast", f"seed={s}", "algo.lr=0.001"]) for s in range(4)]
    population = Population(cfgs)
    state = population.state
    with torch.no_grad():
        state["exp_avg"].fill_(1.0)
        state["adam_steps"].fill_(10.0)
    values = {"seed": [0, 1, 2, 3], "algo.lr": [1e-3, 2e-3, 3e-3, 4e-3], "algo.gamma": [0.99] * 4}
    halving = HalvingSettings(rungs=(10,), fraction=0.5).make(cfgs[0], values, None)
    assert halving.step(state, [1.0, 2.0, 3.0, 4.0], [True] * 4, 10) == [(0, FRESH), (1, FRESH)]
    assert state["seed"].tolist() == [4, 5, 2, 3]
    assert torch.equal(state["params"][:2].detach(), build_policies(cfgs[0], [4, 5]).flat.detach())
    assert state["exp_avg"][:2].abs().sum() == 0 and state["adam_steps"].tolist() == [0, 0, 10, 10]
    assert halving.lineage["parent"] == [FRESH, FRESH] and halving.lineage["seed"] == [4, 5]
    assert all(lr in values["algo.lr"] for lr in halving.lineage["algo.lr"])
    assert not halving.due(15) and halving.due(20) and halving.updates_until_due(15) == 5
    assert halving.step(state, [2.5, 0.5, 3.5, 4.5], [True] * 4, 20) == [(1, FRESH)]
    assert halving.rung_scores[10] == [1.0, 2.0, 3.0, 4.0, 2.5, 0.5]


def test_a_pbt_run_is_not_continued_with_other_settings(tmp_path):
    """Resuming with another search (or none) is refused in one line naming both."""
    from drone_torchrl.config import ConfigError

    run = tmp_path / "run"
    train_population(_cfgs("algo.episodes=4"), NAMES, run, search=SEARCH)
    with pytest.raises(ConfigError, match="hydra/launcher=pbt .* no search") as info:
        train_population(_cfgs("algo.episodes=8"), NAMES, run)
    assert "\n" not in str(info.value)


def test_the_schedule_of_an_agent_follows_its_line_of_ancestors_back():
    """Agent 0 took agent 2's weights at update 10 (lr 0.5), agent 1 took agent 0's at 20 (lr 0.7),
    agent 2 took agent 1's at 30 (lr 0.9): agent 2's weights were trained with agent 2's first lr,
    then 0.5, 0.7 and 0.9 (its own first values are not its line's after update 30)."""
    lineage = {
        "update": [10, 20, 30],
        "agent": [0, 1, 2],
        "parent": [2, 0, 1],
        "algo.lr": [0.5, 0.7, 0.9],
    }
    initial = {"algo.lr": [0.1, 0.2, 0.3]}
    assert schedule(lineage, initial, 2, ["algo.lr"]) == [
        (0, {"algo.lr": 0.3}),
        (10, {"algo.lr": 0.5}),
        (20, {"algo.lr": 0.7}),
        (30, {"algo.lr": 0.9}),
    ]
    assert schedule(lineage, initial, 0, ["algo.lr"]) == [(0, {"algo.lr": 0.3}), (10, {"algo.lr": 0.5})]
    assert schedule(lineage, initial, 1, ["algo.lr"]) == [
        (0, {"algo.lr": 0.3}),
        (10, {"algo.lr": 0.5}),
        (20, {"algo.lr": 0.7}),
    ]


@pytest.mark.parametrize("search", [SEARCH, PB2_SEARCH], ids=["pbt", "pb2"])
def test_a_replay_trains_every_agent_with_the_pbt_agents_values(tmp_path, search):
    """hydra/launcher=pbt_replay's search on fresh seeds (of a PBT or a PB2 run): every agent gets
    the schedule's values at its updates (the lineage holds one row per agent and change, and the
    state holds the last)."""
    run = tmp_path / "pbt"
    train_population(_cfgs("algo.episodes=8"), NAMES, run, search=search)
    replay = ReplaySettings.of({"run": str(run), "agent": 1})
    steps = [(u, dict(v)) for u, v in replay.schedule]
    assert steps[0][0] == 0 and all(u % SEARCH.every_updates == 0 for u, _ in steps)
    fresh = tmp_path / "fresh"
    train_population(_cfgs("algo.episodes=8"), NAMES, fresh, search=replay)
    lineage = record_module.read_table(fresh / record_module.LINEAGE_TABLE)
    assert sorted(set(lineage["update"])) == [u for u, _ in steps]
    for update, values in steps:
        rows = [i for i, u in enumerate(lineage["update"]) if u == update]
        assert sorted(lineage["agent"][i] for i in rows) == [0, 1, 2]
        assert {lineage["algo.lr"][i] for i in rows} == {values["algo.lr"]}
    state = load_checkpoint(fresh / "checkpoints" / "last.pt")["state"]
    assert state["lr"].tolist() == [steps[-1][1]["algo.lr"]] * 3


def test_drone_report_draws_the_best_agents_schedules(tmp_path):
    """drone-report on a PBT sweep writes pbt_schedules.png and .csv: the best agents by final
    return, best first, each with its line's values from update 0 (schedule())."""
    from drone_torchrl.apps.report import main as report_main
    from drone_torchrl.report.schedules import SCHEDULES_CSV, SCHEDULES_FIGURE

    sweep = tmp_path / "sweep"
    run = sweep / "population_0"
    hydra_record = lambda: (run / ".hydra").mkdir()  # noqa: E731  (what the launcher writes: a job of the sweep)
    train_population(_cfgs("algo.episodes=6"), NAMES, run, hydra_record, search=SEARCH)
    report_main([str(sweep), "--no-pd", "--out", str(tmp_path / "report")])
    assert (tmp_path / "report" / SCHEDULES_FIGURE).stat().st_size > 0
    rows = list(csv.DictReader((tmp_path / "report" / SCHEDULES_CSV).open()))
    state = load_checkpoint(sweep / "population_0" / "checkpoints" / "last.pt")
    finals = [f["final_return"] for f in state["final"]]
    order = sorted(range(3), key=lambda i: -finals[i])
    assert list(dict.fromkeys(int(r["agent"]) for r in rows)) == order
    initial = {"algo.lr": state["agents"]["algo.lr"], "algo.gamma": state["agents"]["algo.gamma"]}
    best = order[0]
    expected = schedule(state["search"]["lineage"], initial, best, ["algo.lr", "algo.gamma"])
    got = [
        (int(r["from_update"]), {"algo.lr": float(r["algo.lr"]), "algo.gamma": float(r["algo.gamma"])})
        for r in rows
        if int(r["agent"]) == best
    ]
    assert got == expected and got[0][0] == 0
