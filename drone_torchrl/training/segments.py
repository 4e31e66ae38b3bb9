"""The on-policy algorithms' batches flown by the fast engine (``backend=fast``).

What :class:`torchrl.collectors.Collector` gives :class:`~drone_torchrl.algorithms.ppo.OnPolicy`
over a batched :class:`~drone_torchrl.envs.drone_env.DroneEnv`: ``num_envs`` drones flown side by side for
``steps_per_batch`` steps, each starting a new episode as soon as one ends (auto-reset) and
carrying an unfinished one over to the next batch, as a ``[num_envs, steps_per_batch]`` tensordict
with the env's keys and the actor's log-probability of each action. Here one call of the C++
engine's ``ops.segments`` flies a whole batch
(:class:`~drone_torchrl.kernels.modules.KernelSegments`, which carries each drone's state,
disturbances included, from batch to batch), where the collector steps the env and the actor
through TorchRL one step at a time (``benchmarks/ppo_collectors.py`` times both). Given the same
draws the two give the same batches (``tests/test_kernel_disturbances.py``).

The draws: each batch's action noise, and a start state (and under disturbances an episode key)
for every drone and step at which an episode may begin, from one CPU generator seeded with the
run's seed, whose state a checkpoint keeps (as ``DroneEnv`` draws its start states and keys): the
same layout and semantics as the collector's batches, from other random draws.
"""

from __future__ import annotations

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from drone_torchrl.config import env_kwargs, physics_params
from drone_torchrl.envs import disturbances, dynamics
from drone_torchrl.kernels.modules import Carried, KernelRollout, KernelSegments
from drone_torchrl.modules.factory import model_dtype
from drone_torchrl.modules.policy import ThreeNetPolicy
from drone_torchrl.modules.stacked import StackedThreeNet
from drone_torchrl.training.collectors import kernel_rollout


class FusedSegments:
    """Batches of ``[num_envs, steps_per_batch]`` steps of the actor's net, as TorchRL's collector's.

    See the module's docstring. Iterate to get the batches.

    Args:
        cfg: the run's config (``algo.num_envs``, ``algo.steps_per_batch``, the env).
        actor: the actor that scores the actions.
        net: the :class:`~drone_torchrl.modules.policy.ThreeNetPolicy` inside ``actor`` (the learner
            trains it): its weights are copied into the kernel's flat layout at every batch.
    """

    def __init__(self, cfg: DictConfig, actor: ProbabilisticActor, net: ThreeNetPolicy) -> None:
        algo = cfg.algo
        self.cfg, self.actor, self.net = cfg, actor, net
        self.num_envs, self.steps = algo.num_envs, algo.steps_per_batch
        self.reset_mode = cfg.env.reset_mode
        self.params = physics_params(env_kwargs(cfg))
        self.dtype = model_dtype(cfg)
        self.stacked = StackedThreeNet([net], cfg.model.activation)
        self.rollout = kernel_rollout(cfg, self.stacked)
        self.kernel = KernelSegments(self.rollout, self.num_envs)
        self.disturbed = not disturbances.make(env_kwargs(cfg)["disturbance"]).nominal
        self.log_prob_key = actor.log_prob_keys[0]
        self.generator = torch.Generator()
        self.generator.manual_seed(int(cfg.seed))

    def restart(self) -> None:
        """Start every drone's episode afresh (a resumed run: the interrupted episodes were not booked)."""
        self.kernel.restart()

    def carried(self) -> list[torch.Tensor]:
        """What each drone carries into the next batch (its state, step count, disturbances...)."""
        return [t.clone() for t in self.kernel.carried]

    def carry_on(self, carried: list[torch.Tensor]) -> None:
        """Fly on from :meth:`carried` (a resumed run's drones, mid-episode)."""
        self.kernel.carried = Carried(*(t.clone() for t in carried))

    def eval_policy(self) -> KernelRollout:
        """The net's deterministic episodes as they stand now, flown by the kernel (one agent's rows)."""
        self.stacked.load_agent_state_dict(0, self.net.state_dict())
        return self.rollout

    def __iter__(self) -> FusedSegments:
        return self

    @torch.no_grad()
    def __next__(self) -> TensorDictBase:
        self.stacked.load_agent_state_dict(0, self.net.state_dict())
        n, steps, generator = self.num_envs, self.steps, self.generator
        noise = torch.randn(n, steps, dynamics.ACTION_DIM, generator=generator).to(self.dtype)
        fresh = dynamics.initial_state((n, steps), self.reset_mode, generator, None, self.dtype, self.params)
        keys = disturbances.episode_keys(generator, (n, steps)) if self.disturbed else None
        flown = self.kernel(noise, fresh, keys)
        done = flown.terminated | flown.truncated
        column = lambda x: x.unsqueeze(-1)  # noqa: E731
        td = TensorDict(
            {
                "observation": flown.observation,
                "action": flown.action,
                "step_count": column(flown.step_count),
                "next": {
                    "observation": flown.next_observation,
                    "reward": column(flown.reward),
                    "terminated": column(flown.terminated),
                    "truncated": column(flown.truncated),
                    "done": column(done),
                    "termination_cause": column(flown.cause),
                },
            },
            batch_size=[n, steps],
        )
        with set_exploration_type(ExplorationType.RANDOM):
            dist = self.actor.get_dist(td.select("observation"))
        td.set(self.log_prob_key, dist.log_prob(flown.action))
        return td
