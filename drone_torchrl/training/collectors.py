"""Where a batch of episodes comes from. The two engines differ here and only here.

Both collectors give the loop the same thing for the agents it asks for: a ``[A, E, T]``
tensordict in the layout of ``EnvBase.rollout`` (``A`` agents, ``E`` episodes each, one episode
per row, steps after a row's end masked by ``valid_steps``), the actor that scores it for the loss,
and a policy for the evaluator.

- :class:`TorchRLCollector` (``engine=torchrl``), the reference: ``DroneEnv.rollout`` (or a
  ``ParallelEnv`` of them) with the ``ProbabilisticActor``, sampling from torch's global RNG.
  One agent.
- :class:`VectorisedCollector` (``engine=fused``), the fast path: any number of agents on the
  same :mod:`~drone_torchrl.envs.dynamics`, the policy forward + sampling + physics of one step
  as one function (optionally ``torch.compile``-d). Start states and the whole update's action noise
  come from the counter-based generator of :mod:`.rng` (a function of each agent's seed and update
  count), drawn for all agents at once, so an agent's run does not depend on which other agents
  share the batch.
"""

from __future__ import annotations

import warnings
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from drone_torchrl.config import env_kwargs, physics_params
from drone_torchrl.envs import dynamics
from drone_torchrl.envs.factory import make_env
from drone_torchrl.envs.rollout import ChunkFn, chunked, fly
from drone_torchrl.modules.factory import build_actor
from drone_torchrl.modules.policy import actor_from_net
from drone_torchrl.modules.stacked import ActionSampler
from drone_torchrl.training import rng
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
    """

    def __init__(self, cfg: DictConfig, population: Population) -> None:
        if len(population) != 1:
            raise ValueError(f"engine='torchrl' trains one agent at a time, got {len(population)}")
        workers = cfg.env.num_workers
        per_worker = cfg.algo.episodes_per_update // max(workers, 1)
        self.env = make_env(num_envs=per_worker, num_workers=workers, device=cfg.device, **env_kwargs(cfg))
        self.env.set_seed(cfg.seed)
        self.cfg = cfg
        self._loss_actor = build_actor(cfg, population.net([0]))
        self._actor = build_actor(cfg, _OneAgent(population.net([0])))
        self._stop = (
            {"break_when_all_done": True}
            if workers == 0 or per_worker == 1
            else {"break_when_any_done": False}
        )

    def collect(self, agents: list[int], counters: list[int]) -> TensorDictBase:
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            rollout = self.env.rollout(self.cfg.env.max_steps, self._actor, **self._stop)
        return rollout.reshape(1, -1, rollout.shape[-1])

    def actor(self, agents: list[int]) -> ProbabilisticActor:
        """The actor that scores ``[1, E, T]`` batches (the agent dim first)."""
        return self._loss_actor

    def eval_policy(self, agents: list[int]) -> ProbabilisticActor:
        return self._actor

    def rng_state(self, agent: int) -> dict[str, torch.Tensor | None]:
        generator = getattr(self.env, "_generator", None)
        return {
            "torch": torch.get_rng_state(),
            "env": None if generator is None else generator.get_state(),
            "agent": None,
        }

    def set_rng_state(self, agent: int, state: dict[str, Any], episodes_done: int) -> None:
        torch.set_rng_state(state["torch"])
        if hasattr(self.env, "_generator"):
            self.env._generator.set_state(state["env"])
        else:  # ParallelEnv workers own their generators: reseed deterministically instead.
            self.env.set_seed(self.cfg.seed + episodes_done)

    def close(self) -> None:
        self.env.close(raise_if_closed=False)


class VectorisedCollector:
    """Every agent's episodes flown as one batch on the shared dynamics (``[A, E, 6]`` states)."""

    def __init__(self, cfg: DictConfig, population: Population) -> None:
        self.cfg = cfg
        self.population = population
        self.params = physics_params(env_kwargs(cfg))
        self.max_steps = cfg.env.max_steps
        self.episodes = cfg.algo.episodes_per_update
        self.device = torch.device(cfg.device)
        self.sampler = ActionSampler(cfg.model.distribution, cfg.env.max_thrust)
        self.steps_per_call = cfg.steps_per_call
        self._actor: ProbabilisticActor | None = None
        # compile=true fuses the ~40 small kernels of each step (policy, sampling, physics) of a
        # chunk of steps_per_call steps into one graph; it costs a one-off compilation per batch
        # shape and changes float rounding slightly.
        self._compiled = torch.compile(self._steps) if cfg.compile else None
        self._chunk = self._compiled_steps if cfg.compile else self._steps

    def _compiled_steps(self, *args) -> tuple[torch.Tensor, ...]:
        try:
            return self._compiled(*args)
        except Exception as err:  # noqa: BLE001  (no compiler, unsupported platform, ...)
            warnings.warn(f"compile=true failed ({type(err).__name__}: {err}); running eager", stacklevel=2)
            self._chunk = self._steps
            return self._chunk(*args)

    def _policy_and_physics(
        self, net: nn.Module, layers: list, state: torch.Tensor, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, ...]:
        """One step of every agent's every episode: ``(action, next_state, reward, cause)``."""
        loc, scale = net.apply_stacked(layers, state)
        action = self.sampler(loc, scale, noise)
        return (action, *dynamics.step(state, action, self.params))

    def _steps(
        self, net: nn.Module, layers: list, state: torch.Tensor, noise: torch.Tensor | None, k: int
    ) -> tuple[torch.Tensor, ...]:
        """``k`` steps (a :data:`~drone_torchrl.envs.rollout.ChunkFn`'s outputs); ``noise`` is ``[k, ...]``."""
        return chunked(
            lambda s, i: self._policy_and_physics(net, layers, s, None if noise is None else noise[i])
        )(state, 0, k)

    def _stepper(self, agents: list[int], noise: torch.Tensor | None) -> ChunkFn:
        net = self.population.net(agents)
        with torch.no_grad():
            layers = net.layers()
        return lambda state, t, k: self._chunk(
            net, layers, state, None if noise is None else noise[t : t + k], k
        )

    def collect(self, agents: list[int], counters: list[int]) -> TensorDictBase:
        """The agents' episodes of this update; ``counters`` are their update counts (the noise key)."""
        seeds = self.population.seeds[agents]
        counters = torch.tensor(counters, dtype=torch.int64, device=self.device)
        uniform = rng.uniform(seeds, counters, rng.START_STATES, (self.episodes, dynamics.STATE_DIM))
        start = dynamics.states_from_uniform(uniform, self.cfg.env.reset_mode)
        noise = rng.normal(seeds, counters, rng.ACTION_NOISE, (self.max_steps, self.episodes, 2))
        return fly(self._stepper(agents, noise.transpose(0, 1)), start, self.max_steps, self.steps_per_call)

    def actor(self, agents: list[int]) -> ProbabilisticActor:
        """The agents' stacked nets under the config's distribution head (scores ``[A, ...]`` batches)."""
        net = self.population.net(agents)
        if self._actor is None or self._actor.module[0].module is not net:
            self._actor = actor_from_net(net, self.cfg.model.distribution, self.cfg.env.max_thrust)
        return self._actor

    def eval_policy(self, agents: list[int]) -> ChunkFn:
        """The deterministic steps of the agents (the same arithmetic as training, compiled or not)."""
        return self._stepper(agents, None)

    def rng_state(self, agent: int) -> dict[str, torch.Tensor | None]:
        # Counter-based: the update count in the checkpoint is all the state there is.
        return {"torch": None, "env": None, "agent": None}

    def set_rng_state(self, agent: int, state: dict[str, Any], episodes_done: int) -> None:
        pass

    def close(self) -> None:
        pass


COLLECTORS = {"torchrl": TorchRLCollector, "fused": VectorisedCollector}


def make_collector(cfg: DictConfig, population: Population) -> TorchRLCollector | VectorisedCollector:
    """The collector of ``cfg.engine``."""
    return COLLECTORS[cfg.engine](cfg, population)
