"""The agents being trained together: their policies, optimizers and discounts. A run is a population of one.

Agent ``i`` owns ``nets[i]`` (a :class:`~drone_torchrl.modules.ThreeNetPolicy` initialised after
``torch.manual_seed(seed_i)``, so exactly the weights a single run of that seed starts from) and
``optimizers[i]`` (Adam at its own learning rate). Learning rates, discounts and seeds may differ
between agents; everything else is the group's (see :func:`drone_torchrl.training.jobs.group_key`).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from omegaconf import DictConfig

from drone_torchrl.modules.factory import build_actor, build_policy
from drone_torchrl.modules.stacked import StackedThreeNet


class Population:
    def __init__(self, cfgs: list[DictConfig]) -> None:
        self.cfgs = cfgs
        base = cfgs[0]
        self.activation = base.model.activation
        self.nets = [build_policy(cfg, seed=cfg.seed) for cfg in cfgs]
        self.optimizers = [
            torch.optim.Adam(net.parameters(), lr=cfg.algo.lr, eps=cfg.algo.adam_eps)
            for net, cfg in zip(self.nets, cfgs, strict=True)
        ]
        self.gamma = torch.tensor([cfg.algo.gamma for cfg in cfgs], device=base.device)
        max_norm = base.algo.max_grad_norm
        self.max_grad_norm = math.inf if max_norm is None else float(max_norm)
        self._stacked: dict[tuple[int, ...], StackedThreeNet] = {}

    def __len__(self) -> int:
        return len(self.nets)

    def stacked(self, agents: list[int]) -> StackedThreeNet:
        """The agents' nets as one module over a leading agent dim (the agents' own parameters).

        Kept per set of agents: the set changes only when an agent finishes."""
        key = tuple(agents)
        if key not in self._stacked:
            self._stacked = {key: StackedThreeNet([self.nets[i] for i in agents], self.activation)}
        return self._stacked[key]

    def zero_grad(self, agents: list[int]) -> None:
        for i in agents:
            self.optimizers[i].zero_grad(set_to_none=True)

    def clip_and_step(self, agents: list[int]) -> torch.Tensor:
        """Clip each agent's gradient norm to ``algo.max_grad_norm`` and take its Adam step.

        Returns the agents' gradient norms before clipping (``[A]``, on the device).
        """
        norms = [
            torch.nn.utils.clip_grad_norm_(self.nets[i].parameters(), self.max_grad_norm) for i in agents
        ]
        for i in agents:
            self.optimizers[i].step()
        return torch.stack(norms)

    def state(self, agent: int) -> dict[str, Any]:
        """The agent's checkpoint entries: its actor (``make_actor``'s layout) and optimizer."""
        actor = build_actor(self.cfgs[agent], self.nets[agent])
        return {"actor": actor.state_dict(), "optimizer": self.optimizers[agent].state_dict()}

    def load(self, agent: int, checkpoint: dict[str, Any]) -> None:
        build_actor(self.cfgs[agent], self.nets[agent]).load_state_dict(checkpoint["actor"])
        self.optimizers[agent].load_state_dict(checkpoint["optimizer"])
