"""Where REINFORCE's episodes come from, one collector per backend.

- :class:`TorchRLCollector` (``backend=reference``): ``DroneEnv.rollout`` (or a ``ParallelEnv`` of
  them) with the ``ProbabilisticActor``, sampling from torch's global RNG; its batches are
  tensordicts in ``EnvBase.rollout``'s layout, scored by ``ReinforceLoss``. One agent.
- :class:`FastCollector` (``backend=fast``): any number of agents on the C++ engine
  (:mod:`drone_torchrl.kernels`). It hands out no batches: each update's episodes are flown and
  differentiated inside one kernel call
  (:class:`~drone_torchrl.kernels.modules.KernelReinforce`, :meth:`drone_torchrl.algorithms.reinforce.Reinforce.update`), with start states and
  action noise from the counter-based generator of :mod:`.rng` (a function of each agent's seed and
  update count; under disturbances each episode's key too), so an agent's run does not depend on
  which other agents share the batch; the evaluator flies the kernel's deterministic rollout.

The reference's update calls ``collect`` once per update (the fast engine's update does not ask
for batches).
"""

from __future__ import annotations

from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from drone_torchrl.config import env_kwargs, physics_params
from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.envs.factory import make_env
from drone_torchrl.kernels.modules import KernelRollout
from drone_torchrl.modules.factory import build_actor
from drone_torchrl.modules.stacked import StackedThreeNet
from drone_torchrl.training.population import Population


class _OneAgent(nn.Module):
    """The only agent of a population, for observations without the agent dim (TorchRL rollouts)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc, scale = self.net(observation.unsqueeze(0))
        return loc.squeeze(0), scale.squeeze(0)


class TorchRLCollector:
    """``env.rollout`` of a TorchRL env with the agent's ``ProbabilisticActor`` (one agent).

    ``algo.episodes_per_update`` episodes per batch, split over ``env.num_workers`` processes
    when that is set. ``break_when_all_done`` stops when the last episode ends; a ``ParallelEnv``
    whose workers hold several drones cannot step part of a worker, so it flies the full
    ``max_steps`` and the steps after each row's first episode are masked like the repeats.
    Actions are sampled from torch's global RNG, the env's start states from its own generator.

    Args:
        cfg: the run's validated config.
        population: the population of one agent whose policy flies.
    """

    def __init__(self, cfg: DictConfig, population: Population) -> None:
        workers = cfg.env.num_workers
        per_worker = cfg.algo.episodes_per_update // max(workers, 1)
        self.env = make_env(num_envs=per_worker, num_workers=workers, device=cfg.device, **env_kwargs(cfg))
        self.env.set_seed(cfg.seed)
        self.cfg = cfg
        #: The actor that scores ``[1, E, T]`` batches (the agent dim first).
        self.loss_actor = build_actor(cfg, population.policy)
        self._actor = build_actor(cfg, _OneAgent(population.policy))
        self._stop = (
            {"break_when_all_done": True}
            if workers == 0 or per_worker == 1
            else {"break_when_any_done": False}
        )

    def collect(self, active: torch.Tensor) -> TensorDictBase:
        """Fly one update's episodes; returns the rollout as a ``[1, E, T]`` tensordict (agent dim first)."""
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            rollout = self.env.rollout(self.cfg.env.max_steps, self._actor, **self._stop)
        return rollout.reshape(1, -1, rollout.shape[-1])

    def eval_policy(self) -> ProbabilisticActor:
        """The policy the evaluator flies (the collector's actor)."""
        return self._actor

    def rng_state(self, agent: int) -> dict[str, torch.Tensor | None]:
        """What a checkpoint keeps of the random state: torch's global generator and the env's."""
        generator = self.env._generator if isinstance(self.env, DroneEnv) else None
        return {
            "torch": torch.get_rng_state(),
            "env": None if generator is None else generator.get_state(),
            "agent": None,
        }

    def set_rng_state(self, agent: int, state: dict[str, Any], episodes_done: int) -> None:
        """Restore the random state of :meth:`rng_state` (a parallel env is reseeded instead)."""
        torch.set_rng_state(state["torch"])
        if isinstance(self.env, DroneEnv):
            self.env._generator.set_state(state["env"])
        else:  # ParallelEnv workers own their generators: reseed deterministically instead.
            self.env.set_seed(self.cfg.seed + episodes_done)

    def close(self) -> None:
        """Close the env (and its worker processes, if parallel)."""
        self.env.close(raise_if_closed=False)


class FastCollector:
    """Every agent's policy on the C++ engine (``[N, ...]`` agents; see the module's docstring).

    Args:
        cfg: the group's validated config.
        population: the agents whose stacked policy flies.
    """

    def __init__(self, cfg: DictConfig, population: Population) -> None:
        self.kernel = kernel_rollout(cfg, population.policy)

    def eval_policy(self) -> KernelRollout:
        """The deterministic episodes of every agent, flown by the kernel (the arithmetic of training)."""
        return self.kernel

    def rng_state(self, agent: int) -> dict[str, torch.Tensor | None]:
        """No random state to keep: the generator is counter-based (seed and update count)."""
        return {"torch": None, "env": None, "agent": None}

    def set_rng_state(self, agent: int, state: dict[str, Any], episodes_done: int) -> None:
        """Nothing to restore: the update count in the checkpoint is the generator's whole state."""

    def close(self) -> None:
        """Nothing to close: the kernels hold no resources."""


def kernel_rollout(cfg: DictConfig, policy: StackedThreeNet) -> KernelRollout:
    """The C++ engine's rollout of ``policy`` (``env.max_steps`` steps at most) for the config's drone.

    The TanhNormal head's samples are squashed onto ``env.max_thrust``. The config passed
    :func:`drone_torchrl.config.validate`, which refuses what the kernels do not fly
    (:func:`drone_torchrl.kernels.coverage.fast_refusal`).
    """
    kwargs = env_kwargs(cfg)
    squash_high = cfg.env.max_thrust if cfg.model.distribution == "tanh_normal" else None
    return KernelRollout(
        policy,
        physics_params(kwargs),
        squash_high,
        cfg.env.max_steps,
        cfg.env.reset_mode,
        kwargs["disturbance"],
    )
