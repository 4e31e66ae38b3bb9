"""The paper's three-net actor and our REINFORCE loss, against hand computations."""

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import IndependentNormal, ProbabilisticActor

from drone_torchrl.modules import ThreeNetPolicy, make_actor
from drone_torchrl.objectives import ReinforceLoss, discounted_returns, valid_steps


def _obs(n: int, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"observation": torch.randn(n, 6, generator=g)}, batch_size=[n])


def test_three_nets_shapes_and_std_floor():
    net = ThreeNetPolicy(hidden_sizes=(32, 32), activation="tanh", min_std=0.25)
    assert [m.out_features for m in net.shared if isinstance(m, nn.Linear)] == [32, 32]
    loc, scale = net(torch.randn(7, 6))
    assert loc.shape == scale.shape == (7, 2)
    assert bool((scale >= 0.25).all())


@pytest.mark.parametrize("eps", [1e-6, 1e-2])
def test_distribution_eps_is_normal_of_mu_plus_eps_and_sigma_plus_eps(eps):
    """model.distribution_eps: the actor's distribution is exactly the paper's code's
    ``Normal(mu + eps, sigma + eps)`` over the same net's ``mu`` and ``sigma`` (min_std 0 there: its
    std is ``softplus`` only); its log-probabilities of the same actions, and their gradients in
    the weights, are those of that Normal."""
    torch.manual_seed(0)
    plain = make_actor("normal", min_std=0.0)
    shifted = make_actor("normal", min_std=0.0, distribution_eps=eps)
    shifted.load_state_dict(plain.state_dict())
    td = _obs(64)
    net = plain.module[0].module
    mu = net.mean(net.shared(td["observation"]))
    sigma = nn.functional.softplus(net.std(net.shared(td["observation"])))
    out = shifted(td.clone())
    torch.testing.assert_close(out["loc"], mu + eps, rtol=0, atol=0)
    torch.testing.assert_close(out["scale"], sigma + eps, rtol=0, atol=0)
    reference = torch.distributions.Normal(mu + eps, sigma + eps)
    action = out["action"]
    log_prob = shifted.get_dist(out).log_prob(action)
    torch.testing.assert_close(log_prob, reference.log_prob(action).sum(-1), rtol=0, atol=0)
    # The gradient of the log-probability is that of the Normal(mu + eps, sigma + eps) reference.
    grads = torch.autograd.grad(log_prob.sum(), list(shifted.parameters()))
    expected = torch.autograd.grad(reference.log_prob(action.detach()).sum(), list(plain.parameters()))
    for got, want in zip(grads, expected, strict=True):
        torch.testing.assert_close(got, want)
    # Not the plain Normal(mu, sigma): the eps moves the density.
    assert not torch.equal(log_prob, torch.distributions.Normal(mu, sigma).log_prob(action).sum(-1))
    # eps = 0 is the plain net, bit for bit.
    assert torch.equal(plain(td.clone())["loc"], mu)


@pytest.mark.parametrize("bad", [-1e-6, 0.5, float("nan"), float("inf"), True, "x"])
def test_distribution_eps_out_of_range_is_refused(bad):
    with pytest.raises(ValueError, match="model.distribution_eps"):
        ThreeNetPolicy(distribution_eps=bad)


def test_normal_actor_is_unbounded_and_sums_log_prob_over_motors():
    actor = make_actor("normal")
    td = actor(_obs(256))
    assert td["action"].shape == (256, 2)
    assert bool((td["action"] < 0).any())  # unbounded: the paper's agent can command negative thrust
    dist = actor.get_dist(td)
    per_motor = torch.distributions.Normal(td["loc"], td["scale"]).log_prob(td["action"])
    torch.testing.assert_close(dist.log_prob(td["action"]), per_motor.sum(-1))


def test_tanh_normal_actor_stays_in_bounds_with_finite_log_prob():
    actor = make_actor("tanh_normal", max_thrust=1.5)
    td = actor(_obs(512))
    assert bool((td["action"] >= 0).all()) and bool((td["action"] <= 1.5).all())
    assert bool(torch.isfinite(actor.get_dist(td).log_prob(td["action"])).all())


def test_tanh_normal_needs_max_thrust():
    with pytest.raises(ValueError, match="env.max_thrust"):
        make_actor("tanh_normal", max_thrust=None)
    with pytest.raises(ValueError, match="model.distribution"):
        make_actor("beta")


@pytest.mark.parametrize("distribution", ["normal", "tanh_normal"])
def test_deterministic_action_is_repeatable_and_the_mean(distribution):
    actor = make_actor(distribution, max_thrust=1.0)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a1 = actor(_obs(8))["action"]
        a2 = actor(_obs(8))["action"]
    assert torch.equal(a1, a2)
    loc = actor(_obs(8))["loc"]
    expected = loc if distribution == "normal" else 0.5 * (torch.tanh(loc) + 1.0)  # tanh onto [0, 1]
    torch.testing.assert_close(a1, expected)


def test_discounted_returns_by_hand():
    # One row holding two episodes: rewards 1, 1, 10 | done at t=2 | 1, 0 (done at t=4).
    reward = torch.tensor([1.0, 1.0, 10.0, 1.0, 0.0]).view(1, 5, 1)
    done = torch.tensor([False, False, True, False, True]).view(1, 5, 1)
    g = 0.5
    expected = [1 + g * (1 + g * 10), 1 + g * 10, 10, 1 + g * 0, 0]
    torch.testing.assert_close(discounted_returns(reward, done, g).flatten(), torch.tensor(expected))


def test_discounted_returns_matches_torchrl_reward2go():
    from torchrl.objectives.value.functional import reward2go

    g = torch.Generator().manual_seed(1)
    reward = torch.rand(4, 50, 1, generator=g)
    done = torch.rand(4, 50, 1, generator=g) < 0.1
    done[:, -1] = True
    torch.testing.assert_close(discounted_returns(reward, done, 0.97), reward2go(reward, done, 0.97))


def test_valid_steps_cut_after_first_done():
    done = torch.tensor([[0, 0, 1, 1, 1], [0, 0, 0, 0, 1]], dtype=torch.bool).unsqueeze(-1)
    assert valid_steps(done).squeeze(-1).tolist() == [[True, True, True, False, False], [True] * 5]


class _LinearGaussian(nn.Module):
    """loc = w * s (per motor), fixed sigma: small enough to differentiate by hand."""

    def __init__(self, w: float, sigma: float) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.tensor(w))
        self.sigma = sigma

    def forward(self, obs):
        loc = self.w * obs[..., :2]
        return loc, torch.full_like(loc, self.sigma)


def _tiny_batch():
    # One episode of 3 steps, then one padded step (repeat of the last) that must not count.
    obs = torch.tensor(
        [[[0.5, -1.0, 0, 0, 0, 0], [1.0, 2.0, 0, 0, 0, 0], [-0.5, 0.3, 0, 0, 0, 0], [-0.5, 0.3, 0, 0, 0, 0]]]
    )
    action = torch.tensor([[[0.2, -0.4], [1.5, 0.9], [0.1, 0.0], [0.1, 0.0]]])
    reward = torch.tensor([[1.0, 10.0, 0.0, 0.0]]).unsqueeze(-1)
    done = torch.tensor([[False, False, True, True]]).unsqueeze(-1)
    step = torch.tensor([[0, 1, 2, 2]]).unsqueeze(-1)
    return TensorDict(
        {"observation": obs, "action": action, "step_count": step, "next": {"reward": reward, "done": done}},
        batch_size=[1, 4],
    )


@pytest.mark.parametrize("discount_weight", [False, True])
def test_loss_gradient_matches_hand_derivation(discount_weight):
    w, sigma, gamma = 0.7, 0.8, 0.9
    net = _LinearGaussian(w, sigma)
    actor = ProbabilisticActor(
        TensorDictModule(net, ["observation"], ["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=IndependentNormal,
    )
    loss_module = ReinforceLoss(actor, gamma=gamma, discount_weight=discount_weight)
    batch = _tiny_batch()
    out = loss_module(batch)
    out["loss_reinforce"].backward()

    s = batch["observation"][0, :3, :2]
    a = batch["action"][0, :3]
    g = torch.tensor([1 + gamma * 10, 10.0, 0.0])  # returns-to-go of rewards 1, 10, 0
    weight = g * (gamma ** torch.arange(3.0) if discount_weight else 1.0)
    # d/dw log N(a; w s, sigma) = (a - w s) s / sigma^2, summed over the two motors.
    dlogp = ((a - w * s) * s / sigma**2).sum(-1)
    expected_grad = -(weight * dlogp).sum()
    logp = (-((a - w * s) ** 2) / (2 * sigma**2) - math.log(sigma) - 0.5 * math.log(2 * math.pi)).sum(-1)
    torch.testing.assert_close(out["loss_reinforce"], -(weight * logp).sum())
    torch.testing.assert_close(net.w.grad, expected_grad)
    assert out["episodes"].item() == 1
    assert out["return_mean"].item() == pytest.approx(1 + gamma * 10)


def test_loss_options_baseline_and_normalisation():
    actor = make_actor("normal")
    batch = _tiny_batch()
    batch["loc"] = torch.zeros(1, 4, 2)
    for kwargs in ({"baseline": "mean"}, {"normalize_returns": True}):
        out = ReinforceLoss(actor, gamma=0.9, **kwargs)(batch)
        assert torch.isfinite(out["loss_reinforce"])
    with pytest.raises(ValueError, match="algo.baseline"):
        ReinforceLoss(actor, baseline="critic")


def test_loss_scores_stored_actions_without_resampling():
    actor = make_actor("normal")
    batch = _tiny_batch()
    before = batch["action"].clone()
    loss_a = ReinforceLoss(actor)(batch)["loss_reinforce"]
    loss_b = ReinforceLoss(actor)(batch)["loss_reinforce"]
    assert torch.equal(batch["action"], before)
    assert torch.equal(loss_a, loss_b)
