"""algo=a2c: registered and composed as one plug-in, one update moves the policy the way A2C's
objective says, and its own keys (the critic's loss, the advantages' scaling and the critic's own
gradient clip), each checked against its formula on one collected batch (no learning curves; the
on-policy loop's own tests run for A2C too, in tests/test_ppo.py)."""

from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir

from drone_torchrl import algorithms
from drone_torchrl.config import config_dir
from drone_torchrl.training.jobs import Job

QUIET = ["eval.video=false", "progress=false", "eval.episodes=2"]
SMALL = ["algo.num_envs=8", "algo.steps_per_batch=8", "algo.minibatch_size=64"]


def test_a2c_is_a_registered_plug_in_with_its_own_keys():
    from drone_torchrl.algorithms.a2c import A2C
    from drone_torchrl.config import validate

    assert algorithms.get("a2c").learner is A2C
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=["algo=a2c", "experiment=bounded"])
    assert validate(cfg) is None
    assert cfg.algo.name == "a2c" and "clip_epsilon" not in cfg.algo and "loss_critic_type" in cfg.algo


def test_an_a2c_update_moves_the_policy_up_its_advantage_weighted_log_probabilities():
    """One A2C update on a collected batch, as the loop makes it: the batch's log-probabilities
    change in the direction of their standardised advantages (the first-order change of A2C's
    objective, sum of advantage x change of log-probability, is positive; a loss of the wrong
    sign makes it negative). This checks the algorithm, not a learning curve (benchmarks/algorithms.py
    measures that)."""
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=["algo=a2c", "experiment=bounded", *QUIET])
    learner = algorithms.get("a2c").learner([Job(cfg, run_dir=None)])
    batch = next(learner._batches)
    scaled = batch.clone()
    scaled.set(("next", "reward"), scaled.get(("next", "reward")) * cfg.algo.reward_scale)
    with torch.no_grad():
        learner.advantage(scaled)
        advantage = scaled.get("advantage").squeeze(-1)
        advantage = (advantage - advantage.mean()) / advantage.std()

        def log_prob():
            dist = learner.actor_module.get_dist(batch.clone())
            return dist.log_prob(batch.get("action"))

        before = log_prob()
    learner.learn(batch)
    with torch.no_grad():
        change = log_prob() - before
    learner.close()
    assert change.abs().max() > 0
    assert float((advantage * change).sum()) > 0


def _learner(*overrides: str):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=["algo=a2c", "experiment=bounded", *QUIET, *SMALL, *overrides])
    return algorithms.get("a2c").learner([Job(cfg, run_dir=None)])


def _scored_batch(learner):
    """A collected batch with GAE's advantages and value targets, as the loop gives the loss."""
    batch = next(learner._batches).reshape(-1)
    batch.set(("next", "reward"), batch.get(("next", "reward")) * learner.cfg.algo.reward_scale)
    with torch.no_grad():
        learner.advantage(batch)
    return batch


@pytest.mark.parametrize("kind", ["l2", "l1", "smooth_l1"])
def test_the_critic_loss_is_the_named_distance_to_the_value_target(kind):
    learner = _learner(f"algo.loss_critic_type={kind}", "algo.critic_coeff=0.5")
    batch = _scored_batch(learner)
    # Targets far from the fresh critic's values: L2, L1 and smooth L1 differ there.
    batch.set("value_target", batch.get("value_target") + 3.0)
    with torch.no_grad():
        value = learner.critic(batch.clone()).get("state_value")
        error = batch.get("value_target") - value
        expected = {
            "l2": error.pow(2),
            "l1": error.abs(),
            "smooth_l1": torch.where(error.abs() < 1, 0.5 * error.pow(2), error.abs() - 0.5),
        }[kind]
        loss = learner.loss(batch.clone()).get("loss_critic")
    learner.close()
    assert error.abs().min() > 1  # every error is past smooth L1's quadratic part
    torch.testing.assert_close(loss, 0.5 * expected.mean())


@pytest.mark.parametrize("scaling", ["standardize", "center", "none"])
def test_the_advantages_are_scaled_as_the_key_says(scaling):
    learner = _learner(f"algo.advantage_scaling={scaling}")
    raw = torch.tensor([1.0, 2.0, 4.0, 9.0])
    scaled = learner.scale_advantage(raw.clone())
    learner.close()
    centred = raw - raw.mean()
    expected = {"standardize": centred / centred.std(), "center": centred, "none": raw}[scaling]
    torch.testing.assert_close(scaled, expected, atol=1e-6, rtol=1e-6)


def test_the_loop_hands_the_loss_the_scaled_advantages(monkeypatch):
    """``learn`` runs GAE, then :meth:`scale_advantage`, then the loss on what it returned."""
    learner = _learner("algo.advantage_scaling=center")
    seen = {}
    forward = learner.loss.forward

    def spy(td):
        seen["advantage"] = td.get("advantage").clone()
        return forward(td)

    monkeypatch.setattr(learner.loss, "forward", spy)
    learner.learn(next(learner._batches))
    learner.close()
    assert abs(float(seen["advantage"].mean())) < 1e-5
    assert abs(float(seen["advantage"].std()) - 1) > 1e-3  # centred, not standardised


def _grads(learner, scale: float) -> None:
    """Gradients of ``scale`` x the loss on a batch (large: both nets' norms pass their clips)."""
    batch = _scored_batch(learner)
    losses = learner.loss(batch)
    learner.optimizer.zero_grad()
    (scale * sum(losses[k] for k in learner.loss_keys)).backward()


def _norm(net) -> float:
    return float(torch.stack([p.grad.norm() for p in net.parameters() if p.grad is not None]).norm())


def test_the_critic_has_its_own_gradient_clip():
    learner = _learner("algo.max_grad_norm=0.5", "algo.critic_max_grad_norm=3.0")
    # The loop's optimizer steps the same tensors the clips see.
    assert {id(p) for p in learner.loss.parameters()} == {
        id(p) for net in (learner.actor_module, learner.critic) for p in net.parameters()
    }
    _grads(learner, 1e4)
    actor_before, critic_before = _norm(learner.actor_module), _norm(learner.critic)
    booked = float(learner.clip_gradients())
    actor_after, critic_after = _norm(learner.actor_module), _norm(learner.critic)
    learner.close()
    assert actor_before > 0.5 and critic_before > 3.0
    assert actor_after == pytest.approx(0.5, rel=1e-4) and critic_after == pytest.approx(3.0, rel=1e-4)
    assert booked == pytest.approx((actor_before**2 + critic_before**2) ** 0.5, rel=1e-4)


def test_without_a_critic_clip_both_nets_share_max_grad_norm():
    learner = _learner("algo.max_grad_norm=0.5", "algo.critic_max_grad_norm=null")
    _grads(learner, 1e4)
    learner.clip_gradients()
    actor, critic = _norm(learner.actor_module), _norm(learner.critic)
    learner.close()
    assert (actor**2 + critic**2) ** 0.5 == pytest.approx(0.5, rel=1e-4)


def test_runs_saved_before_the_keys_existed_keep_their_updates():
    """A checkpoint's config without the keys gets their ``added`` values: smooth L1, standardised
    advantages (rounded as the loop rounds them) and one shared clip, what A2C did then."""
    from dataclasses import fields

    from drone_torchrl.algorithms.a2c import A2CConf
    from drone_torchrl.algorithms.ppo import ADVANTAGE_EPS
    from drone_torchrl.schema import RULE

    added = {f.name: f.metadata[RULE].added for f in fields(A2CConf)}
    assert (added["loss_critic_type"], added["advantage_scaling"], added["critic_max_grad_norm"]) == (
        "smooth_l1",
        "standardize",
        None,
    )
    learner = _learner(*(f"algo.{key}={'null' if added[key] is None else added[key]}" for key in
                         ("loss_critic_type", "advantage_scaling", "critic_max_grad_norm")))  # fmt: skip
    assert learner.loss.loss_critic_type == "smooth_l1"
    advantage = torch.randn(256, 1, generator=torch.Generator().manual_seed(0)) * 7 + 3
    learner.close()
    expected = (advantage - advantage.mean()) / (advantage.std() + ADVANTAGE_EPS)
    assert torch.equal(learner.scale_advantage(advantage), expected)
