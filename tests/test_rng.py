"""The counter-based generator: an agent's numbers depend on its own key only, and are standard."""

import torch

from drone_torchrl.envs import rng


def test_an_agents_numbers_do_not_depend_on_the_others():
    alone = rng.normal(torch.tensor([11]), torch.tensor([4]), rng.ACTION_NOISE, (20, 1, 2))
    crowd = rng.normal(torch.arange(16), torch.full((16,), 4), rng.ACTION_NOISE, (20, 1, 2))
    assert torch.equal(crowd[11], alone[0])
    assert not torch.equal(crowd[10], alone[0])


def test_normals_are_standard():
    x = rng.normal(torch.arange(64), torch.zeros(64, dtype=torch.int64), rng.ACTION_NOISE, (1000, 2))
    # 128,000 draws: the standard error of the mean is 0.0028, of the variance 0.004.
    assert abs(x.mean().item()) < 0.015
    assert abs(x.var().item() - 1.0) < 0.02
    u = rng.uniform(torch.arange(64), torch.zeros(64, dtype=torch.int64), rng.START_STATES, (1000,))
    assert u.min().item() > 0.0 and u.max().item() < 1.0
    assert abs(u.mean().item() - 0.5) < 0.005
