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


def test_the_same_seed_and_update_give_the_same_step():
    """Two PBTs of the same seed take the same step at the same update (a resumed run's); another
    update or another seed draws otherwise."""

    def step(seed: int, update: int) -> tuple:
        pbt, state = _pbt(_lists(), resample=0.25, seed=seed), _state()
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
