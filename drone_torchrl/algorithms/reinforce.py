"""REINFORCE (``algo=reinforce``, the paper's; ``algo=reinforce_plus``, with variance reductions).

Both are the same learner (``reinforce_plus`` adds the variance reductions): a group of jobs
trained as one population, with either engine.

The update itself, the population engine's, is :meth:`Reinforce.update`;
its loss, in Python, is :class:`~drone_torchrl.objectives.reinforce.ReinforceLoss` (the arithmetic in
:func:`~drone_torchrl.objectives.reinforce.reinforce_terms`), and the fast engine's loss and gradient
are one call of :class:`~drone_torchrl.kernels.modules.KernelReinforce` (the C++ engine's ``ops.reinforce``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from tensordict import TensorDictBase

from drone_torchrl import schema
from drone_torchrl.algorithms import Algorithm, Learner, register
from drone_torchrl.checks import ConfigError
from drone_torchrl.envs.rollout import Episodes
from drone_torchrl.episodes import EPISODE_KEYS, counted_metrics, episode_stats
from drone_torchrl.kernels.modules import KernelReinforce
from drone_torchrl.memory_estimate import reinforce_parts
from drone_torchrl.migrations import FAST
from drone_torchrl.objectives.reinforce import BASELINES, LOG_PROB_REDUCTIONS, ReinforceLoss
from drone_torchrl.registry import UpdateOutput
from drone_torchrl.training.agents import AgentTable
from drone_torchrl.training.collectors import FastCollector, TorchRLCollector
from drone_torchrl.training.optim import clip_grad_norms
from drone_torchrl.training.population import Population

#: What the finite checks test, in their row order (then the weights after the step).
CHECKS = ("actions", "loss", "gradients", "weights")


class Gradient(NamedTuple):
    """One update's gradient of every agent and what the loop books of it (``[N]`` unless noted)."""

    grad: torch.Tensor  # [N, P]
    loss: torch.Tensor
    std: torch.Tensor
    actions_finite: torch.Tensor
    episodes: dict[str, torch.Tensor]  # EPISODE_KEYS -> [N, E]


class Reinforce(Learner):
    """REINFORCE as the training loop drives it: a group of jobs trained as one population.

    The group is the jobs of one :func:`~drone_torchrl.training.jobs.group_key`, on either backend;
    ``state`` is the population's, :meth:`eval_policy` flies all ``eval_agents`` at once. Its
    :meth:`update` gets each update's gradient (:meth:`gradient`) two ways, tested equal
    (tests/test_kernels.py):

    - ``backend=fast``: one ``ops.reinforce`` call flies the episodes and returns every
      agent's loss and gradient (:class:`~drone_torchrl.kernels.modules.KernelReinforce`);
    - ``backend=reference``: the collector's ``EnvBase.rollout`` tensordicts, scored by
      :class:`~drone_torchrl.objectives.reinforce.ReinforceLoss` through the ``ProbabilisticActor``, and
      autograd.

    Args:
        jobs: the jobs of one group, or a population's :class:`~drone_torchrl.training.agents.AgentTable`.
    """

    # Why an agent stops (UpdateOutput's checks, in order) and what to do about it.
    checks = CHECKS
    advice = "lower algo.lr (or set algo.max_grad_norm)"

    @staticmethod
    def max_agents(cfg) -> int | None:
        """The jobs of one group trained together: any number on the fast engine, one on the reference."""
        return None if cfg.backend == FAST else 1

    def __init__(self, jobs) -> None:
        agents = AgentTable.of(jobs)
        cfg, algo = agents.cfg, agents.cfg.algo
        self.population = Population(agents)
        #: The population's stacked state (:attr:`~drone_torchrl.training.population.Population.state`).
        self.state = self.population.state
        self.episodes_per_update = int(algo.episodes_per_update)
        #: The agents :meth:`eval_policy` flies at once: all of them.
        self.eval_agents = len(jobs)
        self.kernel = self.loss = None
        if cfg.backend == FAST:
            self.collector = FastCollector(cfg, self.population)
            flags = {
                "baseline_mean": algo.baseline == "mean",
                "normalize_returns": algo.normalize_returns,
                "discount_weight": algo.discount_weight,
                "mean_log_prob": algo.log_prob_reduction == "mean",
            }
            self.kernel = KernelReinforce(self.collector.kernel, algo.episodes_per_update, flags)
        else:
            self.collector = TorchRLCollector(cfg, self.population)
            self.loss = ReinforceLoss(  # over [N, ...] batches, one discount per agent
                self.collector.loss_actor,
                gamma=self.state["gamma"],
                agent_dims=1,
                discount_weight=algo.discount_weight,
                normalize_returns=algo.normalize_returns,
                baseline=algo.baseline,
                log_prob_reduction=algo.log_prob_reduction,
            )
        for i, checkpoint in enumerate(agents.checkpoints):
            if checkpoint is not None:
                self.population.load(i, checkpoint)
                self.collector.set_rng_state(i, checkpoint["rng"], checkpoint["episodes_done"])

    def gradient(self, state: TensorDictBase, counters: torch.Tensor, active: torch.Tensor) -> Gradient:
        """One update's episodes and gradient, without a step; its random numbers keyed by ``counters`` ``[N]``."""
        if self.kernel is None:
            return self._autograd_gradient(state, active)
        grad, loss, std, finite, length, counts = self.kernel(state["seed"], counters, state["gamma"], active)
        return Gradient(
            grad, loss.to(grad.dtype), std.to(grad.dtype), finite, counted_metrics(length, counts)
        )

    def _autograd_gradient(self, state: TensorDictBase, active: torch.Tensor) -> Gradient:
        """The TorchRL rollout's (``[N, E, T]``) loss terms, episodes and mean policy std, and autograd."""
        params, batch = state["params"], self.collector.collect(active)
        terms = self.loss(batch)
        episodes = Episodes.from_rollout(batch)
        valid = episodes.valid().unsqueeze(-1)
        scale = batch.get("scale").detach()  # written by the actor while the loss scored the batch
        std = (scale * valid).sum((1, 2, 3)) / (valid.sum((1, 2, 3)) * scale.shape[-1])
        params.grad = None
        terms["loss_reinforce"].backward()
        grad, params.grad = params.grad, None
        finite = ~(~episodes.action.isfinite() & valid).flatten(1).any(1)
        stats = episode_stats(episodes)
        return Gradient(grad, terms["loss_per_agent"], std, finite, {key: stats[key] for key in EPISODE_KEYS})

    def update(
        self, state: TensorDictBase, k: int, active: torch.Tensor
    ) -> tuple[TensorDictBase, UpdateOutput]:
        """Run ``k`` updates of the ``active`` agents (``[N]`` bool); returns ``state`` and their output.

        Each: every agent's gradient, its norm clipped; an agent whose actions, loss or gradient are
        not finite does not step and drops out of the rest of the call, the others take their Adam step.
        """
        params, counter, adam = state["params"], state["counter"], self.population.adam
        start = counter.clone()  # the updates' random numbers are keyed by the counters they start from
        metrics: list[dict[str, torch.Tensor]] = []
        stats: list[dict[str, torch.Tensor]] = []
        for j in range(k):
            g = self.gradient(state, start + j, active)
            grad_norms = clip_grad_norms(g.grad, self.population.max_grad_norm)
            checks = torch.stack([g.actions_finite, g.loss.isfinite(), grad_norms.isfinite()])
            adam.step(state, g.grad, active & checks.all(0))
            with torch.no_grad():
                checks = torch.cat([checks, params.isfinite().all(1).unsqueeze(0)])
            counter += active
            stats.append(g.episodes)
            metrics.append(
                {
                    "train/loss": g.loss,
                    "train/grad_norm": grad_norms,
                    "policy/std_mean": g.std,
                    "active": active,
                    "checks": checks.T,
                }
            )
            active = active & checks.all(0)
        stack = lambda rows: {key: torch.stack([row[key] for row in rows]) for key in rows[0]}  # noqa: E731
        return state, UpdateOutput(stack(metrics), stack(stats))

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
