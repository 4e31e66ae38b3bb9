"""The agents being trained together, as one stacked state. A run is a population of one.

Everything an update reads and writes is one ``TensorDict`` with batch size ``[N]``
(:attr:`Population.state`), so any slice of it is one agent's part:

- ``"params"``: every agent's policy weights, ``[N, P]`` (the
  :class:`~drone_torchrl.modules.stacked.StackedThreeNet`'s flat parameter: the same tensor);
- Adam's ``"exp_avg"``, ``"exp_avg_sq"`` ``[N, P]`` and ``"adam_steps"`` ``[N]``, and the per-agent
  hyper-parameters ``"lr"``, ``"weight_decay"``, ``"gamma"``;
- ``"seed"`` and ``"counter"`` (updates done): the key of the counter-based random numbers
  (:mod:`.rng`), so the RNG has no other state.

Agent ``i`` starts from the weights a single run of its seed starts from (``torch.manual_seed(seed_i)``
then a fresh :class:`~drone_torchrl.modules.policy.ThreeNetPolicy`). Learning rates, weight decays,
discounts and seeds may differ between agents; everything else is the group's (see :func:`.jobs.group_key`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDict

from drone_torchrl.modules.factory import build_actor, build_policies
from drone_torchrl.training.agents import AgentTable
from drone_torchrl.training.optim import Adam, adam_state


class Population:
    """The stacked state of a population's agents (see the module's docstring).

    Args:
        agents: the agents (an :class:`~.agents.AgentTable`, or a list of configs equal but for the
            per-agent keys).
    """

    def __init__(self, agents: AgentTable | Sequence[DictConfig]) -> None:
        self.agents = agents = AgentTable.of(agents)
        self.cfg = base = agents.cfg
        device = torch.device(base.device)
        self.policy = build_policies(base, agents.values["seed"])
        params = self.policy.flat
        decays = torch.tensor(agents.values["algo.weight_decay"], dtype=torch.float64)
        decoupled = base.algo.optimizer == "adamw"
        coupled = not decoupled and bool(decays.any())
        self.adam = Adam(eps=base.algo.adam_eps, decoupled_weight_decay=decoupled, coupled_decay=coupled)
        #: Everything an update reads and writes, batch size ``[N]`` (the module's description lists it).
        self.state = TensorDict(
            {
                "params": params,
                **adam_state(params, torch.tensor(agents.values["algo.lr"], dtype=torch.float64), decays),
                "gamma": torch.tensor(agents.values["algo.gamma"], dtype=params.dtype, device=device),
                "seed": torch.tensor(agents.values["seed"], dtype=torch.int64, device=device),
                "counter": torch.zeros(len(agents), dtype=torch.int64, device=device),
            },
            batch_size=[len(agents)],
        )
        self.max_grad_norm = math.inf if base.algo.max_grad_norm is None else float(base.algo.max_grad_norm)

    def __len__(self) -> int:
        return len(self.agents)

    @functools.cached_property
    def _actor_entries(self) -> dict[str, str | torch.Tensor]:
        """Each entry of ``make_actor``'s state dict: the agent net's parameter it holds, or a tensor of its own.

        Building a ProbabilisticActor per agent per checkpoint is slow at thousands of agents; its
        state-dict layout is the same for every agent of the group, so it is learnt once.
        """
        net = self.policy.agent_net(0)
        names = {id(p): name for name, p in net.named_parameters()}
        entries = build_actor(self.cfg, net).state_dict(keep_vars=True)
        return {key: names.get(id(value)) or value.detach().clone() for key, value in entries.items()}

    def checkpoint_entries(self, agent: int) -> dict[str, Any]:
        """The agent's checkpoint entries: its actor (``make_actor``'s layout) and optimizer (``torch.optim.Adam``'s)."""
        weights = self.policy.agent_state_dict(agent)
        actor = {
            key: weights[e] if isinstance(e, str) else e.clone() for key, e in self._actor_entries.items()
        }
        optimizer = self.adam.agent_state(self.state, agent, self.policy.names, self.policy.views)
        return {"actor": actor, "optimizer": optimizer}

    def load(self, agent: int, checkpoint: dict[str, Any]) -> None:
        """Continue agent ``agent`` from a checkpoint: weights, optimizer and update counter."""
        actor = build_actor(self.cfg, self.policy.agent_net(agent))  # make_actor's key layout
        actor.load_state_dict(checkpoint["actor"], assign=True)
        self.policy.load_agent_state_dict(agent, actor.module[0].module.state_dict())
        self.adam.load_agent_state(
            self.state, agent, self.policy.names, self.policy.views, checkpoint["optimizer"]
        )
        self.state["counter"][agent] = checkpoint["updates_done"]

    def actor(self, agent: int):
        """A standalone actor of one agent (a copy of its weights: for videos)."""
        return build_actor(self.cfg, self.policy.agent_net(agent))
