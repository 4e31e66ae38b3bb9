"""Policies from a run's config: the one place that reads the ``model`` section."""

from __future__ import annotations

import torch
from omegaconf import DictConfig
from torchrl.modules import ProbabilisticActor

from drone_torchrl.modules.policy import ThreeNetPolicy, actor_from_net


def build_policy(cfg: DictConfig, seed: int | None = None) -> ThreeNetPolicy:
    """A fresh three-net policy on ``cfg.device``; with ``seed``, initialised after ``torch.manual_seed(seed)``."""
    if seed is not None:
        torch.manual_seed(seed)
    model = cfg.model
    return ThreeNetPolicy(list(model.hidden_sizes), model.activation, model.min_std).to(cfg.device)


def build_actor(cfg: DictConfig, net: torch.nn.Module | None = None) -> ProbabilisticActor:
    """The config's ``ProbabilisticActor`` over ``net`` (default: a fresh :func:`build_policy`)."""
    return actor_from_net(
        build_policy(cfg) if net is None else net, cfg.model.distribution, cfg.env.max_thrust
    )
