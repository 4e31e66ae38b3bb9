"""``algo.dual_clip`` on both engines: the reference's DualClipPPOLoss equals the fast engine's
clip_ppo_losses, binds where Ye et al. (2020) say, and experiment=hover_optimal trains on the reference;
and a fast-engine run is a function of its seed, whatever its thread count."""

from __future__ import annotations

import csv
import math
from types import SimpleNamespace

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torchrl.objectives import ClipPPOLoss

from drone_torchrl.algorithms.ppo import PPO, DualClipPPOLoss, clip_ppo_losses, pre_image
from drone_torchrl.config import config_dir
from drone_torchrl.io.episodes_csv import read_episodes
from drone_torchrl.modules.factory import build_actor, build_critic, build_policy, observation_dim
from drone_torchrl.modules.policy import distribution_head
from drone_torchrl.training.trainer import train

QUIET = ["eval.video=false", "progress=false", "eval.episodes=2"]


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def _twins(cfg, log_ratio_of, advantage_of):
    """PPO.make_loss's loss and clip_ppo_losses over one actor and critic, on one batch.

    ``log_ratio_of(frames)`` is subtracted from the batch's log-probabilities (so the current
    policy's ratio to the flying one is its exponential); ``advantage_of(frames)`` gives the
    advantages. Returns each one's ``(losses, gradients)`` and the batch's advantages.
    """
    net = build_policy(cfg, 0)
    actor, critic = build_actor(cfg, net, return_log_prob=True), build_critic(cfg)
    loss = PPO.make_loss(SimpleNamespace(cfg=cfg), actor, critic)
    frames = 512
    generator = torch.Generator().manual_seed(0)
    batch = TensorDict(
        {"observation": torch.randn(frames, observation_dim(cfg), generator=generator)}, [frames]
    )
    with torch.no_grad():
        actor(batch)
    keys = loss.tensor_keys
    batch[keys.sample_log_prob] = batch[keys.sample_log_prob] - log_ratio_of(frames, generator)
    batch["advantage"] = advantage_of(frames, generator)
    batch["value_target"] = torch.randn(frames, 1, generator=generator)
    params = [*actor.parameters(), *critic.parameters()]
    head = distribution_head(cfg.model.distribution, cfg.env.max_thrust)
    plain = [
        batch["observation"],
        *pre_image(head, batch[keys.action]),
        *(batch[key] for key in (keys.sample_log_prob, keys.advantage, keys.value_target)),
    ]
    eps, coeff = torch.tensor(cfg.algo.clip_epsilon), torch.tensor(cfg.algo.critic_coeff)
    out = {
        "reference": loss(batch.clone()),
        "fast": clip_ppo_losses(net, critic.module, plain, eps, coeff, cfg.algo.dual_clip),
    }
    results = {}
    for name, losses in out.items():
        total = losses["loss_objective"] + losses["loss_critic"]
        results[name] = (losses, torch.autograd.grad(total, params))
    return loss, results, batch["advantage"]


@pytest.mark.parametrize("preset", ["experiment=hover_optimal", "algo=ppo"])  # TanhNormal, Normal
@pytest.mark.parametrize("dual_clip", ["3.0", "1.1", "null"])  # 1.1: inside 1 + clip_epsilon
def test_the_reference_dual_clip_equals_the_fast_loss_with_its_gradients(preset, dual_clip):
    """On one batch whose log-ratios spread over +-2.5 (ratios up to 12, past either bound), with
    random advantages: DualClipPPOLoss's (or, without a dual clip, ClipPPOLoss's) losses,
    diagnostics and gradients equal clip_ppo_losses' to 1e-6 in float32; the dual clip binds on
    some frames, so the losses differ from those without it."""
    cfg = _cfg(preset, f"algo.dual_clip={dual_clip}")

    def spread(frames, generator):
        return 5 * torch.rand(frames, generator=generator) - 2.5

    def randn(frames, generator):
        return torch.randn(frames, 1, generator=generator)

    loss, twins, advantage = _twins(cfg, spread, randn)
    assert type(loss).__name__ == ("ClipPPOLoss" if dual_clip == "null" else "DualClipPPOLoss")
    (want, want_grads), (got, got_grads) = twins["reference"], twins["fast"]
    for key in ("loss_objective", "loss_critic", "clip_fraction", "kl_approx"):
        torch.testing.assert_close(got[key], want[key], rtol=1e-6, atol=1e-6)
    assert any(g.abs().max() > 0 for g in got_grads)
    for g, w in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-6, atol=1e-6)
    if dual_clip != "null":
        unbound = _twins(_cfg(preset, "algo.dual_clip=null"), spread, randn)[1]["reference"][0]
        assert abs(float((unbound["loss_objective"] - want["loss_objective"]).detach())) > 1e-3


def test_the_dual_clip_bounds_a_negative_advantage_s_term_by_c_times_it():
    """By hand, hover_optimal's loss (dual_clip 3, clip 0.3) on 3 frames of log-ratios 100, 0 and
    -0.1 and advantages -1, 2, -1 (standardised: -1, 2, -1 over sqrt(3)): the first term is 3 x its
    advantage, the others ClipPPOLoss's; the gradient is finite. Without the bound (algo.dual_clip
    null: ClipPPOLoss) e^100 overflows float32 and the loss is inf; a bound from below would
    change the other two terms."""
    losses = {}
    for dual_clip in ("3.0", "null"):
        cfg = _cfg("experiment=hover_optimal", f"algo.dual_clip={dual_clip}")
        assert cfg.algo.clip_epsilon == 0.3
        net = build_policy(cfg, 0)
        actor, critic = build_actor(cfg, net, return_log_prob=True), build_critic(cfg)
        loss = PPO.make_loss(SimpleNamespace(cfg=cfg), actor, critic)
        batch = TensorDict({"observation": torch.randn(3, observation_dim(cfg))}, [3])
        with torch.no_grad():
            actor(batch)
        log_prob = loss.tensor_keys.sample_log_prob
        batch[log_prob] = batch[log_prob] - torch.tensor([100.0, 0.0, -0.1])
        batch["advantage"] = torch.tensor([[-1.0], [2.0], [-1.0]])
        batch["value_target"] = torch.zeros(3, 1)
        losses[dual_clip] = loss(batch)["loss_objective"]
        if dual_clip != "null":
            gradients = torch.autograd.grad(losses[dual_clip], list(net.parameters()))
    assert isinstance(loss, ClipPPOLoss) and not isinstance(loss, DualClipPPOLoss)
    a = torch.tensor([-1.0, 2.0, -1.0]) / math.sqrt(3)
    expected = -(3 * a[0] + a[1] + math.exp(-0.1) * a[2]) / 3
    assert float(losses["3.0"].detach()) == pytest.approx(float(expected), rel=1e-6)
    assert all(bool(torch.isfinite(g).all()) for g in gradients)
    assert float(losses["null"].detach()) == math.inf


def test_hover_optimal_trains_on_the_reference_engine(tmp_path):
    """experiment=hover_optimal backend=reference (its dual clip: DualClipPPOLoss) trains a
    budget smaller than a batch and books its episodes."""
    run = tmp_path / "run"
    train(_cfg("experiment=hover_optimal", "backend=reference", "algo.episodes=8", *QUIET), run)
    assert len(read_episodes(run / "episodes.csv")[0]["return"]) >= 8


def _episodes(run) -> list[dict[str, str]]:
    """episodes.csv's rows without their wall-clock column."""
    with open(run / "episodes.csv", newline="") as f:
        return [{k: v for k, v in row.items() if k != "wall_clock_s"} for row in csv.DictReader(f)]


def test_a_fast_engine_run_is_a_function_of_its_seed_on_one_thread_or_two(tmp_path):
    """experiment=hover_optimal (the fast engine's PPO, dual-clipped) on 100 episodes, about 4 batches
    of 10 epochs: the same seed gives the same episodes.csv, but for its wall clock, twice on one
    thread and once on two (the C++ engine splits its drones over threads, torch its matmuls)."""
    runs, threads_before = {}, torch.get_num_threads()
    try:  # a run sets torch's threads and leaves them: the next tests' are put back
        for name, threads in (("first", 1), ("again", 1), ("two threads", 2)):
            overrides = ["experiment=hover_optimal", "algo.episodes=100", f"threads={threads}", *QUIET]
            train(_cfg(*overrides), tmp_path / name)
            runs[name] = _episodes(tmp_path / name)
    finally:
        torch.set_num_threads(threads_before)
    assert len(runs["first"]) >= 100
    assert runs["again"] == runs["first"]
    assert runs["two threads"] == runs["first"]
