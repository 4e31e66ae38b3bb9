"""Policies from a run's config: the one place that reads the ``model`` section."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from omegaconf import DictConfig
from torch import nn
from torchrl.modules import MLP, ProbabilisticActor, ValueOperator

from drone_torchrl.envs import disturbances
from drone_torchrl.envs.dynamics import ACTION_DIM, DTYPES, HOVER_THRUST
from drone_torchrl.modules.policy import ACTIVATIONS, ThreeNetPolicy, actor_from_net, init_exploration
from drone_torchrl.modules.stacked import StackedThreeNet

# How close to the TanhNormal's bounds a starting mean may be (atanh is infinite at +-1).
TANH_EDGE = 0.99
# nn.Linear.reset_parameters' kaiming_uniform_(a=sqrt(5)): build_policies repeats its draws.
LINEAR_INIT_SLOPE = math.sqrt(5)


def model_dtype(cfg: DictConfig) -> torch.dtype:
    """The precision of a run's networks: its env's (``env.dtype``).

    The whole model runs in the env's dtype rather than casting at the policy boundary, so a
    float64 run is float64 end to end: observations, actions, log-probabilities, returns, the loss,
    the gradients and the weights (its checkpoints hold float64 weights).
    """
    return DTYPES[cfg.env.dtype]


def observation_dim(cfg: Mapping[str, Any]) -> int:
    """Entries of a run's observations: :func:`~drone_torchrl.envs.disturbances.observation_names` of its ``env.disturbance``."""
    return len(disturbances.observation_names(cfg["env"].get("disturbance")))


def build_policy(cfg: DictConfig, seed: int | None = None) -> ThreeNetPolicy:
    """A fresh three-net policy on ``cfg.device`` in :func:`model_dtype`, optionally seeded.

    With ``seed``, it is initialised after ``torch.manual_seed(seed)``, in float32 and then
    converted, so a seed starts from the same weights in either precision.
    """
    if seed is not None:
        torch.manual_seed(seed)
    model = cfg.model
    net = _policy_net(cfg)
    if model.get("init_std") is not None:
        init_exploration(net, model.init_std, hover_mean(model.distribution, cfg.env.max_thrust))
    return net.to(device=cfg.device, dtype=model_dtype(cfg))


def _policy_net(cfg: DictConfig) -> ThreeNetPolicy:
    model = cfg.model
    return ThreeNetPolicy(
        list(model.hidden_sizes),
        model.activation,
        model.min_std,
        observation_dim(cfg),
        distribution_eps=model.get("distribution_eps", 0.0),
    )


def build_policies(cfg: DictConfig, seeds: Sequence[int]) -> StackedThreeNet:
    """Fresh policies of ``len(seeds)`` agents, stacked, without building a module per agent.

    Agent ``i`` starts from the weights of ``build_policy(cfg, seeds[i])``.

    Each agent's draws are those of ``torch.manual_seed(seed)`` then ``nn.Linear``'s own
    initialisation, from a generator of its own (CPU generators of one seed give one stream): per
    layer, the weight ``U(-b, b)`` with ``nn.init.kaiming_uniform_(a=sqrt(5))``'s bound, then the bias
    ``U(-1/sqrt(fan_in), 1/sqrt(fan_in))``, in ``named_parameters()`` order (the order the layers are
    made). At tens of thousands of agents a module each takes minutes; this takes seconds. torch's
    global generator is left as ``build_policy(cfg, seeds[-1])`` leaves it.
    """
    model = cfg.model
    with torch.device("meta"):  # the architecture only: a meta net draws nothing
        template = _policy_net(cfg)
    draws, start = [], 0
    for name, param in template.named_parameters():
        fan_in = template.get_submodule(name.rpartition(".")[0]).in_features
        if name.endswith("weight"):
            gain = nn.init.calculate_gain("leaky_relu", LINEAR_INIT_SLOPE)
            bound = math.sqrt(3.0) * (gain / math.sqrt(fan_in))
        else:
            bound = 1 / math.sqrt(fan_in)
        draws.append((start, start + param.numel(), bound))
        start += param.numel()
    flat = _uniform_rows(seeds, draws, start)
    if len(seeds):
        # torch's own generator as build_policy(cfg, seeds[-1]) leaves it: seeded, then one draw
        # per weight (the reference backend's collector samples from it next).
        torch.manual_seed(int(seeds[-1]))
        torch.empty(start).uniform_()
    stacked = StackedThreeNet([template], model.activation, flat=flat)
    if model.get("init_std") is not None:
        init_exploration(
            template,
            model.init_std,
            hover_mean(model.distribution, cfg.env.max_thrust),
            weights=stacked.params.flatten_keys("."),  # views of stacked.flat: set in place
        )
    return stacked.to(device=cfg.device, dtype=model_dtype(cfg))


def _uniform_rows(seeds: Sequence[int], draws: list[tuple[int, int, float]], width: int) -> torch.Tensor:
    """Seeded uniform draws ``[len(seeds), width]``: each row from its own seed's generator.

    Row ``i`` holds ``U(-b, b)`` for each ``(first, last, b)`` of ``draws`` in turn (float32).

    One ``uniform_(0, 1)`` per row, then ``lo + u * (hi - lo)`` per column, is 8x faster than a call
    per layer and gives the same numbers where this build's ``uniform_`` computes that expression
    as one fused multiply-add: checked on the first row, which is also drawn layer by layer;
    otherwise every row is drawn layer by layer.
    """

    def by_layer(seed: int, row: torch.Tensor, generator: torch.Generator) -> None:
        generator.manual_seed(int(seed))
        for first, last, bound in draws:
            row[first:last].uniform_(-bound, bound, generator=generator)

    generator = torch.Generator()
    rows = torch.empty(len(seeds), width)
    lo, hi = torch.empty(width), torch.empty(width)
    for first, last, bound in draws:
        lo[first:last], hi[first:last] = -bound, bound  # rounded to float32, as uniform_ rounds them
    for row, seed in zip(rows, seeds, strict=True):
        generator.manual_seed(int(seed))
        row.uniform_(0.0, 1.0, generator=generator)
    rows = torch.addcmul(lo, rows, hi - lo)
    if len(seeds):
        first = torch.empty(width)
        by_layer(seeds[0], first, generator)
        if not torch.equal(first, rows[0]):
            for row, seed in zip(rows, seeds, strict=True):
                by_layer(seed, row, generator)
    return rows


def hover_mean(distribution: str, max_thrust: float | None) -> float:
    """The mean head's output at which both motors hover (:data:`~.dynamics.HOVER_THRUST` x weight each).

    The Normal head's mean is the command itself; the TanhNormal head maps ``loc`` onto
    ``[0, max_thrust]`` through ``(tanh(loc) + 1) / 2``, so hovering is ``atanh(2 h / A - 1)``
    (0 at ``max_thrust=1``), kept inside the open range when ``max_thrust`` cannot hover.
    """
    if distribution == "normal":
        return HOVER_THRUST
    inside = min(max(2.0 * HOVER_THRUST / max_thrust - 1.0, -TANH_EDGE), TANH_EDGE)
    return math.atanh(inside)


def build_critic(cfg: DictConfig, q_value: bool = False) -> ValueOperator:
    """PPO's value network (``algo.value_hidden_sizes``): ``"observation"`` in, ``"state_value"`` out.

    ``q_value``: SAC's Q-network (``algo.qvalue_hidden_sizes``), the observation and action in,
    ``"state_action_value"`` out. A one-output MLP with the policy's activation, made in float32 on
    ``cfg.device``, then in :func:`model_dtype`.
    """
    in_keys = ["observation", "action"] if q_value else ["observation"]
    net = MLP(
        in_features=observation_dim(cfg) + (ACTION_DIM if q_value else 0),
        out_features=1,
        num_cells=list(cfg.algo.qvalue_hidden_sizes if q_value else cfg.algo.value_hidden_sizes),
        activation_class=ACTIVATIONS[cfg.model.activation],
        device=cfg.device,
    )
    out_keys = ["state_action_value" if q_value else "state_value"]
    return ValueOperator(net.to(model_dtype(cfg)), in_keys=in_keys, out_keys=out_keys)


def build_actor(
    cfg: DictConfig, net: torch.nn.Module | None = None, return_log_prob: bool = False
) -> ProbabilisticActor:
    """The config's ``ProbabilisticActor`` over ``net`` (default: a fresh :func:`build_policy`)."""
    return actor_from_net(
        build_policy(cfg) if net is None else net, cfg.model.distribution, cfg.env.max_thrust, return_log_prob
    )
