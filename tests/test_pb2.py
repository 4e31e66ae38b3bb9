"""Population-based bandits (``hydra/launcher=pb2``, drone_torchrl.training.pb2).

- The Gaussian process sends a replaced agent to the values whose return grew most.
- No chosen value leaves the searched space (a list's values; a range, in log space where tagged).
- The exploit step copies the parent's weights and Adam state (PBT's), keeps the agent's seed.
- A PB2 run is replayed by ``pbt_replay``; its model's data is in the checkpoint (the killed and
  resumed run: tests/test_pbt.py's parametrised test).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from test_pbt_explore import _state

from drone_torchrl.training.pb2 import PB2, Model, PB2Settings
from drone_torchrl.training.pbt import Range

LRS = [3e-5, 5.79e-5, 1.12e-4, 2.16e-4, 4.17e-4, 8.05e-4, 1.55e-3, 3e-3]
GAMMAS = [0.94821, 0.97317, 0.98611, 0.99627]
N = 8
BOUNDS = {"algo.lr": (0.0, 1.0), "algo.gamma": (0.0, 1.0)}


def _pb2(lr: list[float], gamma: list[float], ranges: tuple[Range, ...] = (), seed: int = 50) -> PB2:
    space = {"algo.lr": lr, "algo.gamma": gamma, "seed": list(range(seed, seed + N))}
    return PB2(PB2Settings(every_updates=5, quantile=0.25, ranges=ranges), space, BOUNDS, seed=seed)


def _fly(pb2: PB2, growth, steps: int) -> list[dict[str, list[float]]]:
    """``steps`` exploit steps where an agent's return grows by ``growth(lr index)`` an interval.

    Returns each step's choice: the replaced agents' new values.
    """
    state = _state()
    scores = [0.0] * N
    chosen = []
    for k in range(1, steps + 1):
        scores = [s + growth(LRS.index(pb2.current["algo.lr"][i])) for i, s in enumerate(scores)]
        pairs = pb2.step(state, scores, [True] * N, update=5 * k)
        for agent, parent in pairs:
            scores[agent] = scores[parent]  # the copied running-mean window
        chosen.append({key: [pb2.current[key][a] for a, _ in pairs] for key in ("algo.lr", "algo.gamma")})
    return chosen


def test_the_model_sends_a_replaced_agent_to_the_rate_whose_return_grew_most():
    """8 agents, one per learning rate; an agent's return grows by -(i - 5)^2 an interval at rate
    index i (the best: index 5, 8.05e-4). After three intervals of data the first agent replaced
    takes rate 8.05e-4: the model's mean peaks there, and every rate has been seen (similar
    variances). The mirrored growth (best at index 2) sends it to 1.12e-4."""
    for best in (5, 2):
        pb2 = _pb2(LRS, [0.99] * N)
        chosen = _fly(pb2, lambda i, best=best: -float((i - best) ** 2), steps=3)
        assert chosen[-1]["algo.lr"][0] == LRS[best]


def test_the_second_agent_replaced_in_a_step_goes_elsewhere_when_the_first_took_the_best():
    """The variance knows where the population trains next: two agents replaced in one step are
    not both sent to a value the kept agents and the first choice already cover when nothing is
    known yet (no data: every candidate's mean is 0, only the variance tells them apart)."""
    model = Model.fit(np.zeros(0), np.zeros((0, 1)), np.zeros(0))
    options = np.linspace(0, 1, 8)[:, None]
    first = model.upper_bound(options, 1, np.array([[0.0], [1 / 7]]))
    assert np.argmax(first) == 7  # the farthest from the kept agents at 0 and 1/7
    second = model.upper_bound(options, 1, np.array([[0.0], [1 / 7], [1.0]]))
    assert np.argmax(second) in (3, 4)  # the middle of the gap between 1/7 and 1


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), scores=st.lists(st.floats(-1e3, 1e3), min_size=N, max_size=N))
def test_no_chosen_value_leaves_the_searched_lists(seed, scores):
    """Over any scores, the values PB2 gives are values of the sweep's lists."""
    pb2 = _pb2([LRS[i] for i in range(N)], [GAMMAS[i % 4] for i in range(N)], seed=seed % 1000)
    state = _state()
    for k in range(1, 4):
        pb2.step(state, [s * k for s in scores], [True] * N, update=5 * k)
        assert set(pb2.current["algo.lr"]) <= set(LRS)
        assert set(pb2.current["algo.gamma"]) <= set(GAMMAS)


@pytest.mark.parametrize("log", [False, True])
def test_no_chosen_value_leaves_a_searched_range(log):
    """gamma searched over interval(0.95,0.999) (log-tagged or not), lr over the list: every
    chosen gamma is inside the range, every lr a list value."""
    span = Range("algo.gamma", 0.95, 0.999, log)
    first = span.first_values(range(50, 50 + N))
    pb2 = _pb2(LRS, first, ranges=(span,))
    chosen = _fly(pb2, lambda i: float(i), steps=4)
    gammas = [g for step in chosen for g in step["algo.gamma"]]
    assert gammas and all(0.95 <= g <= 0.999 for g in gammas)
    assert all(lr in LRS for step in chosen for lr in step["algo.lr"])


def test_pb2_exploits_as_pbt_does_copying_the_parents_weights_and_adam_state():
    """8 agents scored 0..7, quantile 0.25: agents 0 and 1 take the weights, Adam moments and step
    count of a parent among 6 and 7, keep their own seed and counter; the state's lr is the
    agent's new value."""
    state, before = _state(), _state()
    pb2 = _pb2(LRS, [0.99] * N)
    pairs = pb2.step(state, [float(i) for i in range(N)], [True] * N, update=5)
    assert sorted(a for a, _ in pairs) == [0, 1] and {p for _, p in pairs} <= {6, 7}
    for agent, parent in pairs:
        for key in ("params", "exp_avg", "exp_avg_sq", "adam_steps"):
            assert torch.equal(state[key][agent], before[key][parent]), key
        assert int(state["seed"][agent]) == 50 + agent and int(state["counter"][agent]) == 7 + agent
        assert float(state["lr"][agent]) == pytest.approx(pb2.current["algo.lr"][agent])


def test_the_model_data_round_trips_through_the_checkpoint():
    """A PB2 made from its checkpoint's record takes the same next step as the one that wrote it."""
    pb2 = _pb2(LRS, [0.99] * N)
    _fly(pb2, lambda i: -float((i - 5) ** 2), steps=2)
    saved = pb2.checkpoint()
    assert len(saved["data"]["changes"]) == 2 * N
    again = PB2(
        pb2.settings,
        {"algo.lr": LRS, "algo.gamma": [0.99] * N, "seed": list(range(50, 58))},
        BOUNDS,
        50,
        saved["lineage"],
        saved["data"],
    )
    scores = [float(i) for i in range(N)]
    a, b = _state(), _state()
    assert pb2.step(a, scores, [True] * N, update=15) == again.step(b, scores, [True] * N, update=15)
    assert torch.equal(a["lr"], b["lr"])


def test_the_kernel_forgets_older_intervals():
    """The time factor is (1 - epsilon) ** (|i - j| / 2): 0.9 ** 1 two steps apart."""
    model = Model(np.zeros(1), np.zeros((1, 1)), np.zeros(1), length=1.0, epsilon=0.1, noise=0.1)
    k = model.kernel(np.array([1.0]), np.array([[0.3]]), np.array([3.0]), np.array([[0.3]]))
    assert float(k[0, 0]) == pytest.approx(0.9)
    k = model.kernel(np.array([1.0]), np.array([[0.0]]), np.array([1.0]), np.array([[0.5]]))
    assert float(k[0, 0]) == pytest.approx(math.exp(-0.25))
