"""Policies from a run's config: the one place that reads the ``model`` section."""

from __future__ import annotations

import math

import torch
from omegaconf import DictConfig
from torchrl.modules import ProbabilisticActor, ValueOperator

from drone_torchrl.envs.dynamics import ACTION_DIM, DTYPES, HOVER_THRUST, STATE_DIM
from drone_torchrl.modules.policy import ThreeNetPolicy, actor_from_net, init_exploration
from drone_torchrl.modules.value import make_critic, make_q_value

# How close to the TanhNormal's bounds a starting mean may be (atanh is infinite at +-1).
TANH_EDGE = 0.99


def model_dtype(cfg: DictConfig) -> torch.dtype:
    """The precision of a run's networks: its env's (``env.dtype``).

    The whole model runs in the env's dtype rather than casting at the policy boundary, so a
    float64 run is float64 end to end: observations, actions, log-probabilities, returns, the loss,
    the gradients and the weights (its checkpoints hold float64 weights)."""
    return DTYPES[cfg.env.dtype]


def observation_dim(cfg: DictConfig) -> int:
    """Entries of the run's observations: the 6 state entries and ``env.disturbance.observed_actions``
    past commands (2 each)."""
    disturbance = cfg.env.get("disturbance")
    return STATE_DIM + ACTION_DIM * (0 if disturbance is None else disturbance.observed_actions)


def build_policy(cfg: DictConfig, seed: int | None = None) -> ThreeNetPolicy:
    """A fresh three-net policy on ``cfg.device`` in :func:`model_dtype`; with ``seed``, initialised
    after ``torch.manual_seed(seed)`` (in float32, then converted: a seed starts from the same
    weights in either precision)."""
    if seed is not None:
        torch.manual_seed(seed)
    model = cfg.model
    net = ThreeNetPolicy(
        list(model.hidden_sizes),
        model.activation,
        model.min_std,
        observation_dim(cfg),
        distribution_eps=model.get("distribution_eps", 0.0),
    )
    if model.get("init_std") is not None:
        init_exploration(net, model.init_std, hover_mean(model.distribution, cfg.env.max_thrust))
    return net.to(device=cfg.device, dtype=model_dtype(cfg))


def hover_mean(distribution: str, max_thrust: float | None) -> float:
    """The mean head's output at which both motors hover (:data:`HOVER_THRUST` x weight each).

    The Normal head's mean is the command itself; the TanhNormal head maps ``loc`` onto
    ``[0, max_thrust]`` through ``(tanh(loc) + 1) / 2``, so hovering is ``atanh(2 h / A - 1)``
    (0 at ``max_thrust=1``), kept inside the open range when ``max_thrust`` cannot hover.
    """
    if distribution == "normal":
        return HOVER_THRUST
    inside = min(max(2.0 * HOVER_THRUST / max_thrust - 1.0, -TANH_EDGE), TANH_EDGE)
    return math.atanh(inside)


def build_critic(cfg: DictConfig) -> ValueOperator:
    """PPO's value network (``algo.value_hidden_sizes``, the policy's activation) on ``cfg.device``."""
    return make_critic(
        list(cfg.algo.value_hidden_sizes),
        cfg.model.activation,
        cfg.device,
        model_dtype(cfg),
        observation_dim(cfg),
    )


def build_q_value(cfg: DictConfig) -> ValueOperator:
    """SAC's Q-network (``algo.qvalue_hidden_sizes``, the policy's activation) on ``cfg.device``."""
    return make_q_value(
        list(cfg.algo.qvalue_hidden_sizes),
        cfg.model.activation,
        cfg.device,
        model_dtype(cfg),
        observation_dim(cfg),
    )


def build_actor(
    cfg: DictConfig, net: torch.nn.Module | None = None, return_log_prob: bool = False
) -> ProbabilisticActor:
    """The config's ``ProbabilisticActor`` over ``net`` (default: a fresh :func:`build_policy`)."""
    return actor_from_net(
        build_policy(cfg) if net is None else net, cfg.model.distribution, cfg.env.max_thrust, return_log_prob
    )
