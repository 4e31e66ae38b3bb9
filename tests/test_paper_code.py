"""experiment=paper_code's options: the motors' log-probabilities averaged (algo.log_prob_reduction=mean)."""

import pytest
import torch
from hydra import compose, initialize_config_dir

from drone_torchrl.config import config_dir, validate
from drone_torchrl.training.jobs import prepare
from drone_torchrl.training.trainer import Trainer

COMMON = ["engine=fused", "compile=false", "eval.video=false", "progress=false", "algo.episodes=4"]


def _trainer(tmp_path, name, *overrides):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", [*COMMON, *overrides])
    return Trainer([prepare(cfg, tmp_path / name)])


def _loss_and_weights(trainer):
    batch = trainer.collector.collect([0], [0])
    loss = trainer.loss_module([0])(batch)["loss_reinforce"]
    trainer.population.zero_grad()
    loss.backward()
    params = trainer.population.policy.params
    grads = {k: v.grad.detach().clone() for k, v in params.items(True, True)}
    trainer.population.step([0])
    weights = {k: v.detach().clone() for k, v in params.items(True, True)}
    return batch, loss.detach(), weights, grads


@pytest.mark.parametrize("optimizer", ["adam", "adamw"])
def test_mean_reduction_halves_the_loss_and_adam_takes_the_same_step(tmp_path, optimizer):
    """Mean over two motors = half the joint log-probability, so half the gradient; Adam's step
    g / (|g| + eps) is then the same up to eps: the preset's optimizer, not this option, differs."""
    decay = "algo.weight_decay=0.01" if optimizer == "adamw" else "algo.weight_decay=0"
    runs = {}
    for reduction in ("sum", "mean"):
        trainer = _trainer(
            tmp_path, reduction, f"algo.optimizer={optimizer}", decay, f"algo.log_prob_reduction={reduction}"
        )
        start = {k: v.detach().clone() for k, v in trainer.population.policy.params.items(True, True)}
        runs[reduction] = (*_loss_and_weights(trainer), start)
        trainer.close()
    (batch_s, loss_s, after_s, grads, start), (batch_m, loss_m, after_m, _, _) = runs["sum"], runs["mean"]
    assert torch.equal(batch_s["action"], batch_m["action"])  # the same episode
    torch.testing.assert_close(loss_m, loss_s / 2, rtol=1e-6, atol=0)
    lr, eps = 1e-4, 1e-8
    for key in start:
        moved = (after_s[key] - start[key]).abs()
        assert moved.max() > 0.5 * lr  # Adam's first step moves each weight by about lr
        # First step: -lr g / (|g| + eps) with the sum's gradient g, -lr (g/2) / (|g|/2 + eps) with the
        # mean's: they differ by lr |g| eps / ((|g| + eps)(|g| + 2 eps)) (plus float32 rounding).
        g = grads[key].abs().double()
        bound = (
            lr * g * eps / ((g + eps) * (g + 2 * eps)) + 4 * torch.finfo(torch.float32).eps * start[key].abs()
        )
        assert ((after_m[key] - after_s[key]).abs().double() <= bound + 1e-12).all(), key


def test_paper_code_preset():
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", ["experiment=paper_code"])
    validate(cfg)
    assert (cfg.algo.optimizer, cfg.algo.weight_decay, cfg.algo.log_prob_reduction) == ("adamw", 0.01, "mean")
    assert (cfg.algo.lr, cfg.algo.gamma, cfg.model.distribution) == (1e-4, 0.99, "normal")
