"""PBT's explore step stays inside the searched space (``hydra/launcher=pbt``, drone_torchrl.training.pbt).

- A key searched over a list moves to a neighbouring value of the sorted list, or is drawn again
  from it: no explored value ever leaves the list (the old x0.8/x1.2 took gamma from the sweep's
  0.948-0.996 down to 0.6 within one lineage).
- A key searched over a range (``interval``) is multiplied by a ``perturb`` factor and clipped to
  the range, or drawn again from it (log-uniformly when tagged ``log``).
- The exploit step copies the parent's weights and Adam state, keeps the agent's seed and counter.
- The same seed and update give the same draws.
"""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from drone_torchrl.training.pbt import PBT, PBTSettings

GAMMAS = [0.94821, 0.97317, 0.98611, 0.99627]
LRS = [3e-5, 1.12e-4, 4.17e-4, 1.55e-3, 3e-3]
N = 8


def _state(n: int = N) -> TensorDict:
    """A population's state whose rows all differ (agent i: i in params, 10 i in exp_avg, ...)."""
    row = torch.arange(n, dtype=torch.float64)
    return TensorDict(
        {
            "params": row[:, None] * torch.ones(n, 5),
            "exp_avg": row[:, None] * 10 + torch.zeros(n, 5),
            "exp_avg_sq": row[:, None] * 100 + torch.zeros(n, 5),
            "adam_steps": row.float() + 1000,
            "lr": torch.zeros(n, dtype=torch.float64),
            "weight_decay": torch.zeros(n, dtype=torch.float64),
            "gamma": torch.zeros(n, dtype=torch.float32),
            "seed": torch.arange(n) + 50,
            "counter": torch.arange(n) + 7,
        },
        batch_size=[n],
    )


def _pbt(space: dict, resample: float, seed: int = 50, **kwargs) -> PBT:
    settings = PBTSettings(every_updates=5, quantile=0.25, resample_probability=resample, **kwargs)
    bounds = {"algo.lr": (0.0, 1.0), "algo.gamma": (0.0, 1.0)}
    return PBT(settings, {**space, "seed": list(range(seed, seed + N))}, bounds, seed=seed)


def _lists() -> dict:
    """8 agents over the 5 x 4 lists: every list value is some agent's."""
    return {"algo.lr": [LRS[i % len(LRS)] for i in range(N)], "algo.gamma": [GAMMAS[i % 4] for i in range(N)]}


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    resample=st.sampled_from([0.0, 0.25, 1.0]),
    scores=st.lists(st.lists(st.floats(-10, 10), min_size=N, max_size=N), min_size=10, max_size=30),
)
def test_explored_list_values_never_leave_the_list(seed, resample, scores):
    """Steps after steps of one population (random scores, so any agent may be a parent of any):
    every value PBT gives lr and gamma is one of the sweep's, however long the lineage."""
    pbt, state = _pbt(_lists(), resample, seed=seed), _state()
    for update, score in enumerate(scores, start=1):
        pbt.step(state, score, [True] * N, update=update * 5)
        for key, allowed in (("algo.lr", LRS), ("algo.gamma", GAMMAS)):
            assert set(pbt.current[key]) <= set(allowed), (key, pbt.current[key])
            assert set(pbt.lineage[key]) <= set(allowed), key


def _outcomes(key: str, values: list[float], start: float, resample: float, updates: int = 200) -> set:
    """The values a replaced agent got over ``updates`` steps when both parents held ``start``."""
    seen = set()
    for update in range(1, updates + 1):
        space = {"algo.lr": [LRS[0]] * N, "algo.gamma": [GAMMAS[0]] * N}
        space[key] = [*values, *[start] * (N - len(values))]  # agents 6 and 7 (the best) hold start
        pbt = _pbt(space, resample)
        pairs = pbt.step(_state(), [float(i) for i in range(N)], [True] * N, update=update)
        seen |= {pbt.current[key][agent] for agent, _ in pairs}
    return seen


@pytest.mark.parametrize("key, values", [("algo.lr", LRS), ("algo.gamma", GAMMAS)])
def test_a_list_value_moves_only_to_a_neighbour_or_is_drawn_again_from_the_list(key, values):
    """From each value of the list (unsorted on the command line: the sorted list's neighbours
    count), resample_probability=0 gives exactly the value below and the value above (an end: itself
    and its one neighbour); resample_probability=1 gives exactly the list."""
    order = sorted(values)
    shuffled = order[1::2] + order[::2]
    for i, start in enumerate(order):
        neighbours = {order[max(i - 1, 0)], order[min(i + 1, len(order) - 1)]}
        assert _outcomes(key, shuffled, start, resample=0.0) == neighbours, start
    assert _outcomes(key, shuffled, order[1], resample=1.0) == set(order)


def test_the_exploit_step_copies_the_parents_weights_and_adam_state_and_keeps_the_agents_seed():
    """8 agents scored 0..7, quantile 0.25: agents 0 and 1 take the params, exp_avg, exp_avg_sq and
    Adam step count of their parent (6 or 7), not their own, and keep their own seed and counter."""
    state, pbt = _state(), _pbt(_lists(), resample=0.25)
    before = _state()
    pairs = pbt.step(state, [float(i) for i in range(N)], [True] * N, update=10)
    assert sorted(agent for agent, _ in pairs) == [0, 1] and {p for _, p in pairs} <= {6, 7}
    for agent, parent in pairs:
        for key in ("params", "exp_avg", "exp_avg_sq", "adam_steps"):
            assert torch.equal(state[key][agent], before[key][parent]), key
            assert not torch.equal(state[key][agent], before[key][agent]), key
        assert int(state["seed"][agent]) == 50 + agent and int(state["counter"][agent]) == 7 + agent
        assert float(state["lr"][agent]) == pytest.approx(pbt.current["algo.lr"][agent])
    for agent in range(2, N):
        for key in before.keys():  # noqa: SIM118
            assert torch.equal(state[key][agent], before[key][agent]), key


@pytest.mark.parametrize("lr", ["list", "log range"])
def test_the_same_seed_and_update_give_the_same_step(lr):
    """Two PBTs of the same seed take the same step at the same update (a resumed run's); another
    update or another seed draws otherwise."""
    from drone_torchrl.training.pbt import Range

    ranges = () if lr == "list" else (Range("algo.lr", 1e-5, 1e-2, log=True),)

    def step(seed: int, update: int) -> tuple:
        pbt, state = _pbt(_lists(), resample=0.25, seed=seed, ranges=ranges), _state()
        pairs = pbt.step(state, [float(i) for i in range(N)], [True] * N, update=update)
        return pairs, tuple(pbt.lineage["algo.lr"]), tuple(pbt.lineage["algo.gamma"]), state["lr"].tolist()

    assert step(50, 10) == step(50, 10)
    assert len({step(50, u)[1:3] for u in range(10, 30)}) > 1
    assert len({step(s, 10)[1:3] for s in range(50, 70)}) > 1


@pytest.mark.parametrize("log", [False, True], ids=["linear", "log"])
def test_explored_range_values_stay_in_the_range(log):
    """lr searched over interval(1e-5,1e-2) (log or not): 300 steps of random scores; every value is
    in [1e-5, 1e-2]; a value not drawn again is a parent's times 0.8 or 1.2, clipped; draws cover
    the range (log: the decade 1e-5..1e-4 gets about a third, not 1%)."""
    import numpy as np

    from drone_torchrl.training.pbt import Range

    span = Range("algo.lr", 1e-5, 1e-2, log)
    first = span.first_values(range(50, 50 + N))
    assert span.first_values(range(50, 50 + N)) == first  # keyed by the agents' seeds
    assert all(1e-5 <= v <= 1e-2 for v in first)
    space = {"algo.lr": first, "algo.gamma": [GAMMAS[i % 4] for i in range(N)]}
    pbt, state = _pbt(space, resample=0.25, ranges=(span,)), _state()
    rng = np.random.default_rng(0)
    moved = drawn = 0
    for update in range(1, 301):
        parents_values = list(pbt.current["algo.lr"])
        pairs = pbt.step(state, rng.normal(size=N).tolist(), [True] * N, update=update)
        for agent, parent in pairs:
            value, old = pbt.current["algo.lr"][agent], parents_values[parent]
            assert 1e-5 <= value <= 1e-2
            candidates = [min(max(old * f, 1e-5), 1e-2) for f in (0.8, 1.2)]
            if any(value == pytest.approx(c, rel=1e-12) for c in candidates):
                moved += 1
            else:
                drawn += 1
        assert set(pbt.current["algo.gamma"]) <= set(GAMMAS)
    assert moved > drawn > 0
    draws = span.draw(np.random.default_rng(1), 3000)
    share = float(np.mean(draws < 1e-4))
    assert share == pytest.approx(1 / 3 if log else (1e-4 - 1e-5) / (1e-2 - 1e-5), abs=0.03)


TINY = [
    "algo.episodes=6",
    "env.max_steps=20",
    "eval.episodes=1",
    "eval.every_episodes=0",
    "eval.video=false",
    "progress=false",
]


def test_a_range_sweep_draws_each_agents_first_value_by_its_seed_and_pbt_stays_in_it(tmp_path, command_here):
    """drone-train -m seed=range(0,8) hydra/launcher=pbt 'algo.lr=tag(log,interval(1e-4,1e-2))'
    algo.gamma=0.95,0.99: 16 agents; each agent's first lr is the range's draw keyed by its seed;
    every lr PBT gives (5 steps) is in [1e-4, 1e-2] and every gamma is 0.95 or 0.99. The same
    command again finds the run finished (the same values and settings)."""
    pytest.importorskip("pyarrow")
    from drone_torchrl.apps import train as train_app
    from drone_torchrl.training import population_record as record_module
    from drone_torchrl.training.pbt import Range

    sweep = tmp_path / "sweep"
    argv = [
        "-m", "seed=range(0,8)", "hydra/launcher=pbt", "hydra.launcher.every_updates=1",
        "algo.lr=tag(log,interval(1e-4,1e-2))", "algo.gamma=0.95,0.99", *TINY, f"hydra.sweep.dir={sweep}",
    ]  # fmt: skip
    proc = command_here(train_app.run, "drone-train", *argv, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    run = sweep / "population_0"
    agents = record_module.read_table(run / "agents.parquet")
    assert agents["seed"] == [s for s in range(8) for _ in range(2)]
    assert agents["algo.lr"] == Range("algo.lr", 1e-4, 1e-2, log=True).first_values(agents["seed"])
    lineage = record_module.read_table(run / record_module.LINEAGE_TABLE)
    assert sorted(set(lineage["update"])) == [1, 2, 3, 4, 5]
    assert all(1e-4 <= lr <= 1e-2 for lr in lineage["algo.lr"])
    assert set(lineage["algo.gamma"]) <= {0.95, 0.99}
    again = command_here(train_app.run, "drone-train", *argv, cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert record_module.read_table(run / record_module.LINEAGE_TABLE) == lineage


@pytest.mark.parametrize(
    "overrides, line",
    [
        (
            ["hydra/launcher=population", "algo.lr=interval(1e-5,1e-2)"],
            "algo.lr=interval(1e-5,1e-2) is not allowed; expected a list of values (e.g. "
            "algo.lr=1e-4,3e-4,1e-3): a range is searched only by hydra/launcher=pbt or pb2",
        ),
        (
            ["hydra/launcher=pbt", "hydra.launcher.every_updates=1", "algo.weight_decay=interval(0,0.1)"],
            "algo.weight_decay=interval(0,0.1) is not allowed; expected a list of values: a range is "
            "allowed only for a key PBT searches (hydra.launcher.keys=['algo.lr', 'algo.gamma'])",
        ),
        (
            ["hydra/launcher=pbt", "hydra.launcher.every_updates=1", "algo.lr=tag(log,interval(0,0.1))"],
            "algo.lr=tag(log,interval(0,0.1)) is not allowed; expected interval(low,high) with "
            "0 < low < high (a log range)",
        ),
        (
            ["hydra/launcher=pbt", "hydra.launcher.every_updates=1", "algo.gamma=interval(0.5,1.5)"],
            "algo.gamma=interval(0.5,1.5) is not allowed; expected a range inside the values "
            "algo=reinforce allows, [0.0, 1.0]",
        ),
    ],
    ids=["not-pbt", "not-searched", "log-from-0", "past-bounds"],
)
def test_a_range_pbt_cannot_search_is_refused_in_one_line(tmp_path, command_here, overrides, line):
    """Before any folder is made, with the key, the value and what is allowed."""
    pytest.importorskip("pyarrow")  # without it the extras check refuses first (tests/test_extras.py)
    from drone_torchrl.apps import train as train_app

    proc = command_here(
        train_app.run, "drone-train", "-m", "seed=0,1", *overrides, *TINY,
        f"hydra.sweep.dir={tmp_path / 'sweep'}", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 1
    assert proc.stderr == f"drone-train: error: {line}\n"
    assert not (tmp_path / "sweep").exists()


def test_perturb_set_for_a_search_of_lists_only_is_a_one_line_note(capsys):
    """perturb multiplies range keys only: a search whose keys are all lists and that asks for other
    factors is told on stderr (one line) that they go unused; the default factors say nothing."""
    from hydra import compose, initialize_config_dir

    from drone_torchrl.config import config_dir

    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=["algo.episodes=6"])
    values = {"algo.lr": [1e-4, 1e-3], "algo.gamma": [0.99, 0.99], "seed": [0, 1]}
    PBTSettings(every_updates=1).make(cfg, values, None)
    assert capsys.readouterr().err == ""
    PBTSettings(every_updates=1, perturb=(0.5, 2.0)).make(cfg, values, None)
    assert capsys.readouterr().err == (
        "drone-train: note: hydra.launcher.perturb=[0.5, 2.0] is not used: every searched key "
        "(algo.lr, algo.gamma) is searched over a list, and moves to a neighbouring value of it; "
        "perturb multiplies keys searched over interval(low,high)\n"
    )
