"""Where a batch of episodes comes from, for REINFORCE's two engines.

Both collectors give the update a ``[N, E, T]`` batch for every agent (``N`` agents, ``E`` episodes
each, one episode per row), the actor that scores it for the loss, and a policy for the evaluator.
An update call of ``k`` updates first calls :meth:`begin`, then :meth:`collect` once per update.

- :class:`TorchRLCollector` (``engine=torchrl``), the reference: ``DroneEnv.rollout`` (or a
  ``ParallelEnv`` of them) with the ``ProbabilisticActor``, sampling from torch's global RNG; its
  batches are tensordicts in ``EnvBase.rollout``'s layout. One agent.
- :class:`VectorisedCollector` (``engine=fused``): any number of agents on the same
  :mod:`~drone_torchrl.envs.dynamics`, as :class:`~drone_torchrl.envs.rollout.Episodes`. Start states
  and action noise come from the counter-based generator of :mod:`.rng` (a function of each agent's
  seed and update count), drawn for all agents and many updates at once, so an agent's run does not
  depend on which other agents share the batch. The policy forward, sampling and physics of
  ``steps_per_call`` steps are one function, ``torch.compile``-d with ``compile=true``. With
  ``compile=true`` on the CPU the update does not ask it for batches at all: the C++ kernel
  flies and differentiates the episodes itself (:class:`~drone_torchrl.kernels.modules.KernelReinforce`),
  and evaluation flies the kernel's deterministic rollout (:attr:`VectorisedCollector.kernel`).
  Under ``env.disturbance.*`` (domain randomisation) each episode also gets a counter-based key for
  its disturbances, the drones fly :mod:`~drone_torchrl.envs.disturbances` in PyTorch (compiled with
  ``compile=true``; the kernels fly the nominal drone only) and the batch keeps what the policy saw.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from drone_torchrl.config import env_kwargs, physics_params
from drone_torchrl.envs import disturbances, dynamics
from drone_torchrl.envs.factory import make_env
from drone_torchrl.envs.rollout import ChunkFn, Episodes, RolloutFn, chunked, fly_episodes
from drone_torchrl.modules.factory import build_actor, model_dtype
from drone_torchrl.modules.policy import actor_from_net
from drone_torchrl.modules.stacked import ActionSampler, StackedThreeNet
from drone_torchrl.training import rng
from drone_torchrl.training.population import Population

if TYPE_CHECKING:  # for the annotation only: kernel_rollout imports it where it is used
    from drone_torchrl.kernels.modules import KernelRollout

# The action noise of one call's updates is drawn at once, in pieces of at most this many numbers
# (4 bytes each): 100 updates of 32 agents' 300-step episodes take 1.9 M, a 1024-agent update 0.6 M.
NOISE_PER_DRAW = 1 << 22


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
        self._loss_actor = build_actor(cfg, population.policy)
        self._actor = build_actor(cfg, _OneAgent(population.policy))
        self._stop = (
            {"break_when_all_done": True}
            if workers == 0 or per_worker == 1
            else {"break_when_any_done": False}
        )

    def begin(self, state: TensorDictBase, k: int) -> None:
        pass

    def collect(self, j: int, active: torch.Tensor) -> TensorDictBase:
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            rollout = self.env.rollout(self.cfg.env.max_steps, self._actor, **self._stop)
        return rollout.reshape(1, -1, rollout.shape[-1])

    def actor(self) -> ProbabilisticActor:
        """The actor that scores ``[1, E, T]`` batches (the agent dim first)."""
        return self._loss_actor

    def eval_policy(self) -> ProbabilisticActor:
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
    """Every agent's episodes flown as one batch on the shared dynamics (``[N, E, 6]`` states)."""

    def __init__(self, cfg: DictConfig, population: Population) -> None:
        self.cfg = cfg
        self.population = population
        self.params = physics_params(env_kwargs(cfg))
        self.max_steps = cfg.env.max_steps
        self.episodes = cfg.algo.episodes_per_update
        self.device = torch.device(cfg.device)
        self.dtype = model_dtype(cfg)  # the env's: states, noise and the nets (float64 end to end)
        self.sampler = ActionSampler(cfg.model.distribution, cfg.env.max_thrust)
        self.steps_per_call = cfg.steps_per_call
        kwargs = env_kwargs(cfg)
        self.disturbance = disturbances.make(kwargs["disturbance"])
        # Nominal drones fly dynamics.step on their states; disturbed ones (domain randomisation)
        # carry their episodes' draws and fly disturbances.step on what the policy observes.
        self.disturbed = not self.disturbance.nominal
        self.kernel = (
            None
            if self.disturbed
            else kernel_rollout(cfg, population.policy, squash_bound(cfg), cfg.env.max_steps)
        )
        self.net = population.policy
        self._actor = actor_from_net(self.net, cfg.model.distribution, cfg.env.max_thrust)
        # compile=true without the kernels fuses the ~40 small kernels of each step (policy,
        # sampling, physics; ~80 with disturbances) of a chunk of steps_per_call steps into one
        # graph; it costs a one-off compilation per batch shape and changes float rounding slightly.
        compiled = cfg.compile and self.kernel is None
        self._eager = self._disturbed_steps if self.disturbed else self._steps
        self._compiled = torch.compile(self._eager) if compiled else None
        self._chunk = self._compiled_steps if compiled else self._eager
        self._draws: tuple[torch.Tensor, torch.Tensor, torch.Tensor, int, int] | None = None

    def _compiled_steps(self, *args) -> tuple[torch.Tensor, ...]:
        try:
            return self._compiled(*args)
        except Exception as err:  # noqa: BLE001  (no compiler, unsupported platform, ...)
            warnings.warn(f"compile=true failed ({type(err).__name__}: {err}); running eager", stacklevel=2)
            self._chunk = self._eager
            return self._chunk(*args)

    def _policy_and_physics(
        self, layers: list, state: torch.Tensor, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, ...]:
        return policy_step(self.population.policy, layers, self.sampler, self.params, state, noise)

    def _steps(
        self, layers: list, state: torch.Tensor, noise: torch.Tensor | None, k: int
    ) -> tuple[torch.Tensor, ...]:
        """``k`` steps (a :data:`~drone_torchrl.envs.rollout.ChunkFn`'s outputs); ``noise`` is ``[k, ...]``."""
        return chunked(lambda s, i: self._policy_and_physics(layers, s, None if noise is None else noise[i]))(
            state, 0, k
        )

    def _stepper(self, noise: torch.Tensor | None) -> ChunkFn:
        """The PyTorch path's chunks; ``noise`` ``[T, N, E, 2]`` (None: the deterministic action)."""
        with torch.no_grad():
            layers = self.population.policy.layers()
        return lambda state, t, k: self._chunk(layers, state, None if noise is None else noise[t : t + k], k)

    def _disturbed_steps(
        self,
        layers: list,
        state: torch.Tensor,
        internal: disturbances.Internal,
        noise: torch.Tensor,
        t: torch.Tensor,
        k: int,
    ) -> tuple[torch.Tensor, ...]:
        """``k`` steps of disturbed drones from step ``t`` (a tensor, so one compiled graph serves every
        chunk): the :data:`~drone_torchrl.envs.rollout.ChunkFn`'s outputs, then the observations
        ``[k, ...]`` and the internal state after the last step."""
        outputs = []
        for i in range(k):
            observation = disturbances.observe(self.disturbance, state, internal, t + i)
            loc, scale = self.population.policy.apply_stacked(layers, observation)
            action = self.sampler(loc, scale, noise[i])
            state, reward, cause, internal = disturbances.step(
                self.disturbance, state, action, internal, t + i, self.params
            )
            outputs.append((action, state, reward, cause, observation))
        return *(torch.stack(column) for column in zip(*outputs, strict=True)), internal

    def _disturbed_stepper(
        self, noise: torch.Tensor, keys: torch.Tensor
    ) -> tuple[ChunkFn, list[torch.Tensor]]:
        """Chunks of disturbed drones whose episodes have keys ``keys`` (``[N, E]``), and the list
        their chunks append the policy's observations to (``[k, N, E, 6 + 2k]`` each)."""
        with torch.no_grad():
            layers = self.population.policy.layers()
        internal = disturbances.start(self.disturbance, keys, self.dtype)
        observations: list[torch.Tensor] = []

        def chunk(state: torch.Tensor, t: int, k: int) -> tuple[torch.Tensor, ...]:
            nonlocal internal
            step = torch.tensor(t, device=state.device)
            *flown, seen, internal = self._chunk(layers, state, internal, noise[t : t + k], step, k)
            observations.append(seen)
            return tuple(flown)

        return chunk, observations

    def begin(self, state: TensorDictBase, k: int) -> None:
        """Remember the update counters the next ``k`` updates draw their start states and noise with."""
        self._seeds, self._counters, self._k = state["seed"], state["counter"].clone(), k
        self._draws = None

    def _draw(self, j: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Update ``j``'s start states ``[N, E, 6]``, noise ``[N, T, E, 2]`` and episode keys ``[N, E]``
        (the disturbances'), drawn for as many of the call's updates at once as
        :data:`NOISE_PER_DRAW` allows."""
        if self._draws is None or not self._draws[-2] <= j < self._draws[-1]:
            n = len(self._seeds)
            per_draw = max(1, NOISE_PER_DRAW // (n * self.max_steps * self.episodes * dynamics.ACTION_DIM))
            last = min(self._k, j + per_draw)
            offsets = torch.arange(j, last, device=self._counters.device).unsqueeze(1)
            seeds = self._seeds.repeat(last - j)
            counters = (self._counters + offsets).reshape(-1)
            uniform = rng.uniform(seeds, counters, rng.START_STATES, (self.episodes, dynamics.STATE_DIM))
            start = dynamics.states_from_uniform(uniform, self.cfg.env.reset_mode, self.params, self.dtype)
            start = start.unflatten(0, (-1, n))
            noise = rng.normal(seeds, counters, rng.ACTION_NOISE, (self.max_steps, self.episodes, 2))
            noise = noise.to(self.dtype)  # drawn in float32, as the C++ kernels draw it
            keys = rng.keys(seeds, counters, rng.EPISODE_KEYS, (self.episodes,))
            self._draws = (start, noise.unflatten(0, (-1, n)), keys.unflatten(0, (-1, n)), j, last)
        start, noise, keys, first, _ = self._draws
        return start[j - first], noise[j - first], keys[j - first]

    def collect(self, j: int, active: torch.Tensor) -> Episodes:
        """Update ``j`` of the call's episodes of every agent, by the PyTorch code (the C++ kernels'
        update draws and flies its own: :class:`~drone_torchrl.kernels.modules.KernelReinforce`).
        Inactive agents are flown too; the update masks them."""
        start, noise, keys = self._draw(j)
        noise = noise.transpose(0, 1)
        if not self.disturbed:
            return fly_episodes(self._stepper(noise), start, self.max_steps, self.steps_per_call)
        chunk, observations = self._disturbed_stepper(noise, keys)
        episodes = fly_episodes(chunk, start, self.max_steps, self.steps_per_call)
        seen = torch.cat(observations)[: episodes.steps].movedim(0, -2)  # the steps fly_episodes kept
        return episodes._replace(observation=torch.where(episodes.valid().unsqueeze(-1), seen, 0.0))

    def actor(self) -> ProbabilisticActor:
        """The agents' nets under the config's distribution head (scores ``[N, ...]`` batches)."""
        return self._actor

    def eval_policy(self) -> RolloutFn | ProbabilisticActor:
        """The deterministic episodes of every agent (the same arithmetic as training); under
        disturbances the agents' actor, which the evaluator flies through the disturbed env."""
        if self.kernel is not None:
            return self.kernel
        if self.disturbed:
            return self._actor
        return lambda start: fly_episodes(self._stepper(None), start, self.max_steps, self.steps_per_call)

    def rng_state(self, agent: int) -> dict[str, torch.Tensor | None]:
        # Counter-based: the update count in the checkpoint is all the state there is.
        return {"torch": None, "env": None, "agent": None}

    def set_rng_state(self, agent: int, state: dict[str, Any], episodes_done: int) -> None:
        pass

    def close(self) -> None:
        pass


def policy_step(
    policy: StackedThreeNet,
    layers: list,
    sampler: ActionSampler,
    params: dynamics.DroneParams,
    state: torch.Tensor,
    noise: torch.Tensor | None,
) -> tuple[torch.Tensor, ...]:
    """One step of every agent's every drone (``state`` ``[N, ..., 6]``) on the nominal dynamics:
    ``(action, next_state, reward, cause)``; ``noise`` None gives the deterministic action."""
    loc, scale = policy.apply_stacked(layers, state)
    action = sampler(loc, scale, noise)
    return (action, *dynamics.step(state, action, params))


_warned: set[str] = set()


def squash_bound(cfg: DictConfig) -> float | None:
    """The TanhNormal head's upper bound on the motor commands (``env.max_thrust``), or None for
    the Normal head: what the kernels squash their samples onto."""
    return cfg.env.max_thrust if cfg.model.distribution == "tanh_normal" else None


def kernel_rollout(
    cfg: DictConfig,
    policy: StackedThreeNet,
    squash_high: float | None,
    max_steps: int,
    fallback: str = "torch.compile",
) -> KernelRollout | None:
    """The C++ kernels' rollout of ``policy`` (``max_steps`` steps at most) where ``compile=true`` on
    the CPU and they cover the config, else None (with a warning, once per reason, when
    ``compile=true`` asked for them on the CPU, naming the caller's ``fallback``)."""
    if not cfg.compile or torch.device(cfg.device).type != "cpu":
        return None
    from drone_torchrl.kernels import library, unavailable_reason
    from drone_torchrl.kernels.ops import check_supported

    reason = check_supported(
        dynamics.STATE_DIM, policy.hidden_sizes, policy.activation_name, policy.flat.dtype
    )
    if reason is not None:
        reason = f"the C++ kernels do not cover {reason}"
    elif library() is None:
        reason = f"the C++ kernels could not be built ({unavailable_reason()})"
    if reason is not None:
        if reason not in _warned:
            _warned.add(reason)
            warnings.warn(f"compile=true: {reason}; using {fallback} instead", stacklevel=3)
        return None
    from drone_torchrl.kernels.modules import KernelRollout

    return KernelRollout(policy, physics_params(env_kwargs(cfg)), squash_high, max_steps, cfg.env.reset_mode)


COLLECTORS = {"torchrl": TorchRLCollector, "fused": VectorisedCollector}


def make_collector(cfg: DictConfig, population: Population) -> TorchRLCollector | VectorisedCollector:
    """The collector of ``cfg.engine``."""
    return COLLECTORS[cfg.engine](cfg, population)
