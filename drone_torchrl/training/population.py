"""The agents being trained together, as one stacked structure. A run is a population of one.

All agents' policy weights live in one :class:`~drone_torchrl.modules.StackedThreeNet` (``[N, ...]``
parameters), their optimizer state in one :class:`~.optim.PopulationAdam` with per-agent learning
rate and weight decay, and their discounts and seeds in ``[N]`` tensors. Agent ``i`` starts from
the weights a single run of its seed starts from (``torch.manual_seed(seed_i)`` then a fresh
:class:`~drone_torchrl.modules.ThreeNetPolicy`). Learning rates, weight decays, discounts and seeds
may differ between agents; everything else is the group's (see :func:`.jobs.group_key`).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from omegaconf import DictConfig
from torch import nn

from drone_torchrl.modules.factory import build_actor, build_policy
from drone_torchrl.modules.stacked import StackedThreeNet
from drone_torchrl.training.optim import PopulationAdam, clip_grad_norms


class _Subset(nn.Module):
    """Some agents of a :class:`StackedThreeNet` (a gather of the stacked weights; gradients flow back)."""

    def __init__(self, stacked: StackedThreeNet, agents: list[int]) -> None:
        super().__init__()
        self.stacked = stacked
        self.register_buffer("index", torch.tensor(agents, device=stacked.params.device), persistent=False)

    def layers(self):
        return self.stacked.stacked(self.stacked.params[self.index])

    def apply_stacked(self, layers, observation: torch.Tensor):
        return self.stacked.apply_stacked(layers, observation)

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.apply_stacked(self.layers(), observation)


class Population:
    def __init__(self, cfgs: list[DictConfig]) -> None:
        self.cfgs = cfgs
        base = cfgs[0]
        device = base.device
        self.policy = StackedThreeNet(
            [build_policy(cfg, seed=cfg.seed) for cfg in cfgs], base.model.activation
        )
        self.optimizer = PopulationAdam(
            self.policy.params,
            lr=torch.tensor([cfg.algo.lr for cfg in cfgs], dtype=torch.float64),
            eps=base.algo.adam_eps,
            weight_decay=torch.tensor([cfg.algo.weight_decay for cfg in cfgs], dtype=torch.float64),
            decoupled_weight_decay=base.algo.optimizer == "adamw",
        )
        self.gamma = torch.tensor([cfg.algo.gamma for cfg in cfgs], device=device)
        self.seeds = torch.tensor([cfg.seed for cfg in cfgs], dtype=torch.int64, device=device)
        max_norm = base.algo.max_grad_norm
        self.max_grad_norm = math.inf if max_norm is None else float(max_norm)
        self._subset: tuple[tuple[int, ...], nn.Module] | None = None
        self._actor_layout: dict[str, str | None] | None = None
        self._actor_extras: dict[str, torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.cfgs)

    def net(self, agents: list[int]) -> nn.Module:
        """The agents' policies as one module over a leading agent dim (all of them: the stacked net)."""
        if len(agents) == len(self):
            return self.policy
        key = tuple(agents)
        if self._subset is None or self._subset[0] != key:
            self._subset = (key, _Subset(self.policy, agents))
        return self._subset[1]

    def zero_grad(self) -> None:
        self.optimizer.zero_grad()

    def clip(self, agents: list[int]) -> torch.Tensor:
        """Clip each agent's gradient norm to ``algo.max_grad_norm``; returns the ``agents``' norms before."""
        return clip_grad_norms(self.policy.params, self.max_grad_norm)[agents]

    def step(self, agents: list[int], ok: torch.Tensor | None = None) -> None:
        """The Adam step of ``agents`` where ``ok`` (``[len(agents)]`` bool, on the device) allows."""
        if len(agents) == len(self) and ok is None:
            self.optimizer.step()
            return
        mask = torch.zeros(len(self), dtype=torch.bool, device=self.seeds.device)
        mask[agents] = True if ok is None else ok
        self.optimizer.step(mask)

    @torch.no_grad()
    def finite(self, agents: list[int]) -> torch.Tensor:
        """``[len(agents)]`` bool: whether every weight of each agent is finite."""
        leaves = [p.flatten(1).isfinite().all(1) for p in self.policy.params.values(True, True)]
        return torch.stack(leaves).all(0)[agents]

    def state(self, agent: int) -> dict[str, Any]:
        """The agent's checkpoint entries: its actor (``make_actor``'s layout) and optimizer (``torch.optim.Adam``'s)."""
        if self._actor_layout is None:
            # Building a ProbabilisticActor per checkpoint costs ~2 ms an agent; its state-dict
            # layout is the same for every agent of the group, so learn it once.
            net = self.policy.agent_net(0)
            names = {id(p): name for name, p in net.named_parameters()}
            entries = build_actor(self.cfgs[0], net).state_dict(keep_vars=True)
            self._actor_layout = {key: names.get(id(value)) for key, value in entries.items()}
            self._actor_extras = {
                k: v.detach().clone() for k, v in entries.items() if self._actor_layout[k] is None
            }
        weights = self.policy.agent_state_dict(agent)
        actor = {
            key: weights[name] if name is not None else self._actor_extras[key].clone()
            for key, name in self._actor_layout.items()
        }
        return {"actor": actor, "optimizer": self.optimizer.agent_state(agent, self.policy.names)}

    def load(self, agent: int, checkpoint: dict[str, Any]) -> None:
        actor = build_actor(self.cfgs[agent], self.policy.agent_net(agent))  # make_actor's key layout
        actor.load_state_dict(checkpoint["actor"], assign=True)
        self.policy.load_agent_state_dict(agent, actor.module[0].module.state_dict())
        self.optimizer.load_agent_state(agent, self.policy.names, checkpoint["optimizer"])

    def actor(self, agent: int):
        """A standalone actor of one agent (a copy of its weights: for videos)."""
        return build_actor(self.cfgs[agent], self.policy.agent_net(agent))
