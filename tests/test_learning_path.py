"""The learning path, number by number: REINFORCE weights, gradient signs, the std floor, stacked nets.

Every expected value here is derived by hand (the derivation is in the comments) and computed with
plain ``math``, so a flipped sign, an ignored option or a clamp instead of an offset makes a test fail.
"""

import math

import pytest
import torch
from tensordict import TensorDict

from drone_torchrl.modules import StackedThreeNet, ThreeNetPolicy, actor_from_net, make_actor
from drone_torchrl.objectives import ReinforceLoss

LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


def _softplus(x: float) -> float:
    return math.log1p(math.exp(x))


def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def _log_normal(a: float, mu: float, s: float) -> float:
    """log N(a; mu, s) = -(a - mu)^2 / (2 s^2) - log s - log sqrt(2 pi)."""
    return -((a - mu) ** 2) / (2 * s * s) - math.log(s) - LOG_SQRT_2PI


def _policy_of(actor) -> ThreeNetPolicy:
    return next(m for m in actor.modules() if isinstance(m, ThreeNetPolicy))


def _constant_actor(mu, std_bias, min_std):
    """A ``make_actor`` policy whose weights are all zero: loc = mu, scale = softplus(std_bias) + min_std.

    With zero trunk weights and biases the features are tanh(0) = 0, so both heads output their bias
    whatever the observation. Float64 so hand values can be compared tightly.
    """
    actor = make_actor("normal", hidden_sizes=(4,), activation="tanh", min_std=min_std)
    net = _policy_of(actor).double()
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
        net.mean.bias.copy_(torch.tensor(mu, dtype=torch.float64))
        net.std.bias.copy_(torch.tensor(std_bias, dtype=torch.float64))
    return actor, net


# ---------------------------------------------------------------------------------------------------
# The hand-made rollout: E = 2 episodes (rows), T = 3 steps, gamma = 0.5.
#   episode 0: rewards 1, 2, 4, done at t = 2;
#   episode 1: rewards 2, -1, done at t = 1; t = 2 is padding (done again, junk reward and action that
#              would change every number below if they were not masked).
# Returns-to-go G_t = r_t + gamma * G_{t+1}:
#   episode 0: G_2 = 4, G_1 = 2 + 0.5 * 4 = 4, G_0 = 1 + 0.5 * 4 = 3
#   episode 1: G_1 = -1, G_0 = 2 + 0.5 * (-1) = 1.5
# Valid steps (row-major): G = [3, 4, 4, 1.5, -1]; sum 11.5 over 5 steps, mean 2.3.
# G - mean = [0.7, 1.7, 1.7, -0.8, -3.3]; squares 0.49 + 2.89 + 2.89 + 0.64 + 10.89 = 17.8,
# population variance 17.8 / 5 = 3.56, std = sqrt(3.56).
# Policy: loc = MU = (0.2, -0.3), scale = softplus(B) + MIN_STD with B = (0, 0.5), MIN_STD = 0.1:
#   scale = (log 2 + 0.1, log(1 + e^0.5) + 0.1) = (0.79315, 1.07408).
# ---------------------------------------------------------------------------------------------------
GAMMA = 0.5
MU = (0.2, -0.3)
B = (0.0, 0.5)
MIN_STD = 0.1
ACTIONS = [
    [(0.5, 0.1), (-0.4, 0.7), (1.2, -1.0)],
    [(0.0, 0.3), (0.9, -0.8), (7.0, -7.0)],  # last one: padding
]
REWARDS = [[1.0, 2.0, 4.0], [2.0, -1.0, 100.0]]  # 100: padding
DONE = [[False, False, True], [False, True, True]]
STEP = [[0, 1, 2], [0, 1, 1]]  # a rollout's padding repeats the last step's counter
VALID = [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1)]
G_VALID = [3.0, 4.0, 4.0, 1.5, -1.0]
N_EPISODES = 2


def _rollout() -> TensorDict:
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(2, 3, 6, generator=g, dtype=torch.float64)  # irrelevant: zero weights
    done = torch.tensor(DONE).unsqueeze(-1)
    return TensorDict(
        {
            "observation": obs,
            "action": torch.tensor(ACTIONS, dtype=torch.float64),
            "step_count": torch.tensor(STEP).unsqueeze(-1),
            "next": {
                "reward": torch.tensor(REWARDS, dtype=torch.float64).unsqueeze(-1),
                "done": done,
                "terminated": done.clone(),
                "truncated": torch.zeros_like(done),
            },
        },
        batch_size=[2, 3],
    )


def _hand_logp() -> list[float]:
    """log pi(A_t | S_t) of the valid steps: the sum of the two motors' log N(a; loc, scale).

    = [-1.818471, -2.397134, -2.684772, -1.865412, -2.175401] for the rollout above; e.g. the first,
    a = (0.5, 0.1): -(0.3^2 / (2 * 0.79315^2)) - log 0.79315 - 0.91894
                    -(0.4^2 / (2 * 1.07408^2)) - log 1.07408 - 0.91894 = -1.818471.
    """
    scale = [_softplus(b) + MIN_STD for b in B]
    return [sum(_log_normal(ACTIONS[e][t][i], MU[i], scale[i]) for i in range(2)) for e, t in VALID]


def _hand_loss(weights: list[float]) -> float:
    """loss = -(sum over valid steps of w_t * log pi(A_t | S_t)) / number of episodes."""
    return -sum(w * lp for w, lp in zip(weights, _hand_logp(), strict=True)) / N_EPISODES


def _loss(**kwargs) -> TensorDict:
    actor, _ = _constant_actor(MU, B, MIN_STD)
    return ReinforceLoss(actor, gamma=GAMMA, **kwargs)(_rollout())


def test_hand_rollout_policy_is_the_constant_one():
    actor, _ = _constant_actor(MU, B, MIN_STD)
    td = actor(_rollout().select("observation"))
    loc = torch.tensor(MU, dtype=torch.float64).expand(2, 3, 2)
    scale = torch.tensor([math.log(2) + 0.1, math.log(1 + math.exp(0.5)) + 0.1], dtype=torch.float64)
    torch.testing.assert_close(td["loc"], loc)
    torch.testing.assert_close(td["scale"], scale.expand(2, 3, 2))


def test_no_baseline_loss_by_hand():
    # w_t = G_t = [3, 4, 4, 1.5, -1].
    out = _loss(baseline="none")
    assert out["loss_reinforce"].item() == pytest.approx(_hand_loss(G_VALID), abs=1e-9)
    assert out["loss_reinforce"].item() == pytest.approx(13.202875, abs=1e-6)
    assert out["episodes"].item() == N_EPISODES
    assert out["return_mean"].item() == pytest.approx((3.0 + 1.5) / 2)  # mean G_0 per episode
    assert out["log_prob_mean"].item() == pytest.approx(sum(_hand_logp()) / 5)


def test_mean_baseline_loss_by_hand():
    # w_t = G_t - mean(G) = [0.7, 1.7, 1.7, -0.8, -3.3].
    weights = [0.7, 1.7, 1.7, -0.8, -3.3]
    assert [g - 2.3 for g in G_VALID] == pytest.approx(weights)
    out = _loss(baseline="mean")
    expected = _hand_loss(weights)
    assert out["loss_reinforce"].item() == pytest.approx(expected, abs=1e-9)
    # The option is not ignored: without the baseline the loss is its own, different hand value.
    no_baseline = _loss(baseline="none")["loss_reinforce"].item()
    assert no_baseline == pytest.approx(_hand_loss(G_VALID), abs=1e-9)
    assert abs(no_baseline - expected) > 1.0  # 13.2029 vs 0.6205
    # A flipped sign on the weights would give -expected: far enough from expected to be caught.
    assert expected == pytest.approx(0.620508, abs=1e-6)


def test_padding_is_masked_by_done():
    # Changing the padded step (ep 1, t = 2) changes nothing: neither its reward, action nor its counter.
    actor, _ = _constant_actor(MU, B, MIN_STD)
    loss = ReinforceLoss(actor, gamma=GAMMA, baseline="mean")
    batch = _rollout()
    ref = loss(batch)
    batch["next", "reward"][1, 2] = -55.0
    batch["action"][1, 2] = torch.tensor([-3.0, 9.0], dtype=torch.float64)
    batch["step_count"][1, 2] = 0  # would count a third episode if the padding were not masked
    out = loss(batch)
    assert out["loss_reinforce"].item() == pytest.approx(ref["loss_reinforce"].item(), abs=1e-12)
    assert out["episodes"].item() == N_EPISODES
    # The collector's mask, when present, gives the same answer as the done-derived one.
    batch["collector", "mask"] = torch.tensor([[True, True, True], [True, True, False]])
    assert loss(batch)["loss_reinforce"].item() == pytest.approx(ref["loss_reinforce"].item(), abs=1e-12)


def test_discount_weight_with_mean_baseline_by_hand():
    # w_t = (G_t - 2.3) * gamma^t with t = step_count: [0.7, 1.7 * 0.5, 1.7 * 0.25, -0.8, -3.3 * 0.5].
    weights = [0.7, 0.85, 0.425, -0.8, -1.65]
    out = _loss(baseline="mean", discount_weight=True)
    assert out["loss_reinforce"].item() == pytest.approx(_hand_loss(weights), abs=1e-9)
    assert out["loss_reinforce"].item() == pytest.approx(-0.315110, abs=1e-6)
    assert out["loss_reinforce"].item() != pytest.approx(_loss(baseline="mean")["loss_reinforce"].item())


def test_normalized_returns_loss_by_hand():
    # w_t = (G_t - 2.3) / (sqrt(3.56) + eps), population std over the 5 valid steps.
    eps = torch.finfo(torch.float64).eps
    std = math.sqrt(17.8 / 5)
    weights = [d / (std + eps) for d in (0.7, 1.7, 1.7, -0.8, -3.3)]
    out = _loss(normalize_returns=True)
    expected = _hand_loss(weights)
    assert out["loss_reinforce"].item() == pytest.approx(expected, abs=1e-9)
    # Not ignored: differs from the merely centred weights (std = 1.89, far from 1).
    assert expected == pytest.approx(0.328868, abs=1e-6)
    assert abs(expected - _loss(baseline="mean")["loss_reinforce"].item()) > 0.1  # 0.3289 vs 0.6205
    # Normalisation implies centring: with baseline="mean" on top nothing changes.
    both = _loss(normalize_returns=True, baseline="mean")["loss_reinforce"].item()
    assert both == pytest.approx(expected, abs=1e-9)


def test_normalized_loss_is_invariant_to_reward_scale():
    # Rewards x k (k > 0) scale every G_t, its mean and its std by k: normalised weights are unchanged,
    # centred weights scale by k.
    actor, _ = _constant_actor(MU, B, MIN_STD)
    batch = _rollout()
    scaled = batch.clone()
    scaled["next", "reward"] = 7.0 * batch["next", "reward"]
    norm = ReinforceLoss(actor, gamma=GAMMA, normalize_returns=True)
    centred = ReinforceLoss(actor, gamma=GAMMA, baseline="mean")
    assert norm(scaled)["loss_reinforce"].item() == pytest.approx(norm(batch)["loss_reinforce"].item())
    assert centred(scaled)["loss_reinforce"].item() == pytest.approx(
        7.0 * centred(batch)["loss_reinforce"].item()
    )


# ---------------------------------------------------------------------------------------------------
# Gradient direction on one step.
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ret", [2.0, -2.0])
def test_gradient_moves_mean_toward_rewarded_action(ret):
    # One step, one episode, G_0 = r. loss = -G * log N(a; mu, s) (summed over motors), so
    #   d loss / d mu = -G * (a - mu) / s^2,
    #   d loss / d b  = -G * ((a - mu)^2 / s^3 - 1 / s) * sigmoid(b)   (s = softplus(b) + min_std).
    # With a - mu = 0.5 > 0 per motor and G > 0 the mean-bias gradient is negative: a descent step
    # moves mu toward a. With G < 0 it moves mu away.
    mu, b, a = (0.1, -0.2), (0.0, 0.0), (0.6, 0.3)
    actor, net = _constant_actor(mu, b, MIN_STD)
    batch = TensorDict(
        {
            "observation": torch.zeros(1, 1, 6, dtype=torch.float64),
            "action": torch.tensor([[a]], dtype=torch.float64),
            "step_count": torch.zeros(1, 1, 1, dtype=torch.int64),
            "next": {
                "reward": torch.full((1, 1, 1), ret, dtype=torch.float64),
                "done": torch.ones(1, 1, 1, dtype=torch.bool),
            },
        },
        batch_size=[1, 1],
    )
    ReinforceLoss(actor, gamma=0.9)(batch)["loss_reinforce"].backward()
    s = math.log(2) + MIN_STD
    grad_mu = [-ret * (a[i] - mu[i]) / s**2 for i in range(2)]
    grad_b = [-ret * ((a[i] - mu[i]) ** 2 / s**3 - 1 / s) * _sigmoid(b[i]) for i in range(2)]
    torch.testing.assert_close(net.mean.bias.grad, torch.tensor(grad_mu, dtype=torch.float64))
    torch.testing.assert_close(net.std.bias.grad, torch.tensor(grad_b, dtype=torch.float64))
    if ret > 0:
        assert bool((net.mean.bias.grad < 0).all())
    else:
        assert bool((net.mean.bias.grad > 0).all())
    # One SGD step on the loss.
    before = (net.mean.bias.detach() - torch.tensor(a, dtype=torch.float64)).abs()
    torch.optim.SGD(net.parameters(), lr=0.05).step()
    after = (net.mean.bias.detach() - torch.tensor(a, dtype=torch.float64)).abs()
    if ret > 0:
        assert bool((after < before).all())
    else:
        assert bool((after > before).all())


# ---------------------------------------------------------------------------------------------------
# min_std is an offset, not a clamp.
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bias", [-20.0, 0.0])
def test_min_std_is_added_not_clamped(bias):
    # scale = softplus(b) + 0.5 with zero weights; d scale / d b = softplus'(b) = sigmoid(b).
    #   b = -20: scale = 0.5 + log1p(e^-20) = 0.5 + 2.06e-9, gradient sigmoid(-20) = 2.06e-9 (a clamp
    #            at 0.5 would give scale exactly 0.5 and gradient exactly 0);
    #   b = 0:   scale = 0.5 + log 2, gradient 0.5.
    net = ThreeNetPolicy(hidden_sizes=(3,), min_std=0.5).double()
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
        net.std.bias.fill_(bias)
    loc, scale = net(torch.randn(1, 6, dtype=torch.float64))
    expected = 0.5 + _softplus(bias)
    torch.testing.assert_close(scale, torch.full((1, 2), expected, dtype=torch.float64), rtol=0, atol=1e-12)
    assert bool((scale > 0.5).all())
    scale.sum().backward()
    grad = net.std.bias.grad
    torch.testing.assert_close(grad, torch.full((2,), _sigmoid(bias), dtype=torch.float64), rtol=1e-9, atol=0)
    assert bool((grad > 0).all())
    if bias == 0.0:
        assert expected == pytest.approx(0.5 + math.log(2))
        assert _sigmoid(bias) == 0.5


# ---------------------------------------------------------------------------------------------------
# Stacked nets: same outputs and same gradients as each net alone.
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("hidden_sizes", [(8, 5), (7,)])
@pytest.mark.parametrize("activation", ["relu", "elu"])
def test_stacked_nets_match_each_net_with_grads(activation, hidden_sizes):
    min_std = 0.3
    nets = []
    for seed in range(3):
        torch.manual_seed(seed)
        nets.append(ThreeNetPolicy(hidden_sizes, activation, min_std))
    with torch.no_grad():
        nets[1].std.bias.fill_(-15.0)  # one agent right at its floor: scale ~ 0.3
    g = torch.Generator().manual_seed(42)
    obs = torch.randn(3, 4, 6, generator=g)
    c1, c2 = torch.randn(3, 4, 2, generator=g), torch.randn(3, 4, 2, generator=g)

    stacked = StackedThreeNet(nets, activation)
    loc, scale = stacked(obs)
    assert loc.shape == scale.shape == (3, 4, 2)
    assert bool((scale >= min_std).all())
    torch.testing.assert_close(scale[1], torch.full((4, 2), min_std), rtol=0, atol=1e-5)
    (loc * c1 + scale * c2).sum().backward()
    stacked_grads = _agent_grads(stacked, nets)

    for k, net in enumerate(nets):
        ref_loc, ref_scale = net(obs[k])
        torch.testing.assert_close(loc[k], ref_loc)
        torch.testing.assert_close(scale[k], ref_scale)
        (ref_loc * c1[k] + ref_scale * c2[k]).sum().backward()
        for (name, p), g_stacked in zip(net.named_parameters(), stacked_grads[k], strict=True):
            assert p.grad.abs().sum() > 0 or name.startswith("std"), name  # not trivially zero
            torch.testing.assert_close(
                g_stacked, p.grad, msg=lambda m, k=k, name=name: f"net {k} {name}: {m}"
            )


def _agent_grads(stacked: StackedThreeNet, nets: list[ThreeNetPolicy]) -> list[list[torch.Tensor]]:
    """Each agent's slice of the stacked parameters' gradients, in its own net's parameter order."""
    grads = stacked.views(stacked.flat.grad)
    return [
        [grads.get(tuple(name.split(".")))[k].clone() for name, _ in net.named_parameters()]
        for k, net in enumerate(nets)
    ]


# ---------------------------------------------------------------------------------------------------
# Per-agent loss of a fused batch = the agent's solo loss.
# ---------------------------------------------------------------------------------------------------
def _random_rollout(lengths: list[int], T: int, seed: int) -> TensorDict:
    """Rows of one episode each (length L <= T), padded by repeating the last step (done stays True)."""
    g = torch.Generator().manual_seed(seed)
    E = len(lengths)
    obs = torch.randn(E, T, 6, generator=g)
    action = torch.randn(E, T, 2, generator=g)
    reward = torch.randn(E, T, 1, generator=g)
    done = torch.zeros(E, T, 1, dtype=torch.bool)
    step = torch.zeros(E, T, 1, dtype=torch.int64)
    for e, n in enumerate(lengths):
        done[e, n - 1 :] = True
        step[e, :, 0] = torch.arange(T).clamp_max(n - 1)
        obs[e, n:], action[e, n:], reward[e, n:] = obs[e, n - 1], action[e, n - 1], reward[e, n - 1]
    return TensorDict(
        {
            "observation": obs,
            "action": action,
            "step_count": step,
            "next": {
                "reward": reward,
                "done": done,
                "terminated": done.clone(),
                "truncated": torch.zeros_like(done),
            },
        },
        batch_size=[E, T],
    )


@pytest.mark.parametrize(
    "options",
    [{}, {"baseline": "mean"}, {"normalize_returns": True}, {"discount_weight": True, "baseline": "mean"}],
)
def test_per_agent_loss_equals_solo_loss(options):
    torch.manual_seed(0)
    nets = [ThreeNetPolicy((16, 16), "tanh"), ThreeNetPolicy((16, 16), "tanh")]
    gamma = torch.tensor([0.9, 0.5])
    batch = torch.stack([_random_rollout([5, 3, 2], 5, seed=1), _random_rollout([4, 5, 1], 5, seed=2)])
    assert batch.batch_size == (2, 3, 5)

    stacked = StackedThreeNet(nets, "tanh")
    fused_actor = actor_from_net(stacked, "normal", None)
    out = ReinforceLoss(fused_actor, gamma=gamma, agent_dims=1, **options)(batch)
    assert out["loss_per_agent"].shape == (2,)
    torch.testing.assert_close(out["loss_reinforce"], out["loss_per_agent"].sum())
    out["loss_reinforce"].backward()
    fused_grads = _agent_grads(stacked, nets)

    for k, net in enumerate(nets):
        net.zero_grad(set_to_none=True)
        solo = ReinforceLoss(actor_from_net(net, "normal", None), gamma=float(gamma[k]), **options)(batch[k])
        torch.testing.assert_close(out["loss_per_agent"][k], solo["loss_reinforce"].detach())
        torch.testing.assert_close(out["return_mean"][k], solo["return_mean"])
        torch.testing.assert_close(out["log_prob_mean"][k], solo["log_prob_mean"])
        assert out["episodes"][k].item() == solo["episodes"].item() == 3
        solo["loss_reinforce"].backward()
        for g_fused, p in zip(fused_grads[k], net.parameters(), strict=True):
            torch.testing.assert_close(g_fused, p.grad)
    # The two discounts are really used: agent 0 with gamma 0.5 would give another loss.
    other = ReinforceLoss(actor_from_net(nets[0], "normal", None), gamma=0.5, **options)(batch[0])
    assert not torch.allclose(other["loss_reinforce"], out["loss_per_agent"][0])
