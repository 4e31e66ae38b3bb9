"""REINFORCE (``algo=reinforce``, the paper's; ``algo=reinforce_plus``, with variance reductions).

Both are the same learner (``reinforce_plus`` adds the variance reductions): a group of jobs
trained as one population, with either engine.

The update itself, the population engine's, is :class:`~drone_torchrl.training.update.ReinforceUpdate`;
its loss, in Python, is :class:`~drone_torchrl.objectives.reinforce.ReinforceLoss` (the arithmetic in
:func:`~drone_torchrl.objectives.reinforce.reinforce_terms`), and the fast engine's loss and gradient
are one call of :class:`~drone_torchrl.kernels.modules.KernelReinforce` (the C++ engine's ``ops.reinforce``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from drone_torchrl import schema
from drone_torchrl.algorithms import Algorithm, Learner, register
from drone_torchrl.checks import ConfigError
from drone_torchrl.memory_estimate import reinforce_parts
from drone_torchrl.migrations import FAST
from drone_torchrl.objectives.reinforce import BASELINES, LOG_PROB_REDUCTIONS
from drone_torchrl.training.agents import AgentTable
from drone_torchrl.training.collectors import make_collector
from drone_torchrl.training.population import Population
from drone_torchrl.training.update import CHECKS, ReinforceUpdate


class Reinforce(Learner):
    """REINFORCE as the training loop drives it: a group of jobs trained as one population.

    The group is the jobs of one :func:`~drone_torchrl.training.jobs.group_key`, on either backend;
    ``state`` is the population's, :meth:`eval_policy` flies all ``eval_agents`` at once.
    """

    # Why an agent stops (UpdateOutput's checks, in order) and what to do about it.
    checks = CHECKS
    advice = "lower algo.lr (or set algo.max_grad_norm)"

    @staticmethod
    def max_agents(cfg) -> int | None:
        """The jobs of one group trained together: any number on the fast engine, one on the reference."""
        return None if cfg.backend == FAST else 1

    def __init__(self, jobs) -> None:
        """``jobs``: the jobs of one group, or a population's :class:`~drone_torchrl.training.agents.AgentTable`."""
        agents = AgentTable.of(jobs)
        cfg = agents.cfg
        self.population = Population(agents)
        self.collector = make_collector(cfg, self.population)
        for i, checkpoint in enumerate(agents.checkpoints):
            if checkpoint is not None:
                self.population.load(i, checkpoint)
                self.collector.set_rng_state(i, checkpoint["rng"], checkpoint["episodes_done"])
        #: ``update(state, k, active)``: ``k`` updates of the active agents
        #: (:mod:`drone_torchrl.training.update`).
        self.update = ReinforceUpdate(cfg, self.population, self.collector)
        #: The population's stacked state (:attr:`~drone_torchrl.training.population.Population.state`).
        self.state = self.population.state
        self.episodes_per_update = int(cfg.algo.episodes_per_update)
        #: The agents :meth:`eval_policy` flies at once: all of them.
        self.eval_agents = len(jobs)

    def eval_policy(self):
        """The policy that evaluations fly, every agent at once."""
        return self.collector.eval_policy()

    def checkpoint_entries(self, agent: int) -> dict:
        """The agent's checkpoint entries that the run record does not own: policy, optimizer, RNG."""
        return {**self.population.checkpoint_entries(agent), "rng": self.collector.rng_state(agent)}

    def actor(self, agent: int):
        """Agent ``agent``'s actor on its own (for videos)."""
        return self.population.actor(agent)

    def close(self) -> None:
        """Close the collector (and its env)."""
        self.collector.close()


def validate(cfg: Mapping[str, Any]) -> None:
    """REINFORCE's rules that relate keys, and those of the engine options it alone uses.

    Each key's own bounds are not checked here: they are its schema's (ReinforceConf above).
    """
    workers = cfg.env.num_workers
    if cfg.algo.episodes % cfg.algo.episodes_per_update:
        raise ConfigError.of(
            "algo.episodes",
            cfg.algo.episodes,
            f"a multiple of algo.episodes_per_update={cfg.algo.episodes_per_update} (every update trains on that many)",
        )
    if workers and cfg.backend == FAST:
        raise ConfigError.of(
            "env.num_workers",
            workers,
            "0 with backend=fast (only backend=reference runs a ParallelEnv)",
        )
    if workers and cfg.algo.episodes_per_update % workers:
        raise ConfigError.of(
            "env.num_workers",
            workers,
            f"a divisor of algo.episodes_per_update={cfg.algo.episodes_per_update} (the episodes are split over the workers)",
        )


@dataclass
class ReinforceConf:
    """``algo.*`` of ``algo.name=reinforce`` (``algo=reinforce``, ``algo=reinforce_plus``)."""

    name: Any = schema.free()
    lr: Any = schema.LR.field()
    gamma: Any = schema.GAMMA.field()
    episodes: Any = schema.EPISODES.field()
    episodes_per_update: Any = schema.an_integer(low=1, high=schema.MAX_PARALLEL_EPISODES)
    adam_eps: Any = schema.ADAM_EPS.field()
    max_grad_norm: Any = schema.MAX_GRAD_NORM.field()
    discount_weight: Any = schema.a_flag()
    normalize_returns: Any = schema.a_flag()
    baseline: Any = schema.one_of(BASELINES)
    optimizer: Any = schema.one_of(schema.OPTIMIZERS, added="adam")
    log_prob_reduction: Any = schema.one_of(LOG_PROB_REDUCTIONS, added="sum")
    weight_decay: Any = schema.a_number(low=0, high=1, per_agent=True, added=0.0)


schema.store_plugin("algo", "reinforce", ReinforceConf)

register(
    Algorithm(
        "reinforce",
        Reinforce,
        validate,
        summary="Monte-Carlo REINFORCE (the paper; `reinforce_plus`: with its usual variance reductions), a population of agents per process",
        memory=reinforce_parts,
    )
)
