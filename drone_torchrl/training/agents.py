"""The agents of one population: the group's config and a column per per-agent key.

The agents of a population differ only in the per-agent keys (``seed``, ``algo.lr``,
``algo.gamma``, ``algo.weight_decay``: the schema's ``per_agent``; see :func:`.jobs.group_key`).
An OmegaConf config takes milliseconds to make, so at tens of thousands of agents a config per
agent is most of the set-up: an :class:`AgentTable` holds one config and each agent's values.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from omegaconf import DictConfig, OmegaConf

from drone_torchrl.config import per_agent_keys


class AgentTable:
    """N agents as one config and, per per-agent key, N values.

    Args:
        cfg: the group's validated config; its per-agent values are agent 0's.
        values: each per-agent key (every one of :func:`~drone_torchrl.config.per_agent_keys`) -> a
            list of N values, agent ``i``'s at ``i``.
        checkpoints: what each agent continues from (a run's checkpoint), or None (none does).
    """

    def __init__(
        self, cfg: DictConfig, values: dict[str, list], checkpoints: Sequence[dict | None] | None = None
    ) -> None:
        sizes = {len(column) for column in values.values()}
        if len(sizes) != 1 or set(values) != set(per_agent_keys()):
            raise ValueError(f"an agent table needs one value per agent for each of {per_agent_keys()}")
        self.cfg = cfg
        self.values = values
        (self.size,) = sizes
        self.checkpoints = list(checkpoints) if checkpoints is not None else [None] * self.size

    @classmethod
    def of(cls, agents: AgentTable | Sequence[DictConfig] | Sequence[Any]) -> AgentTable:
        """``agents`` as a table: a table itself, or a list of configs or of jobs.

        Jobs come each with its ``cfg`` and ``checkpoint``; the configs must be equal but for their
        per-agent keys.
        """
        if isinstance(agents, AgentTable):
            return agents
        jobs = [a for a in agents if not isinstance(a, DictConfig)]
        cfgs = [a if isinstance(a, DictConfig) else a.cfg for a in agents]
        values = {key: [OmegaConf.select(cfg, key) for cfg in cfgs] for key in per_agent_keys()}
        return cls(cfgs[0], values, [job.checkpoint for job in jobs] if jobs else None)

    def __len__(self) -> int:
        return self.size
