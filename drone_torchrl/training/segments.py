"""The on-policy algorithms' batches flown by the fast engine (``backend=fast``).

What :class:`torchrl.collectors.Collector` gives :class:`~drone_torchrl.algorithms.ppo.OnPolicy`
over a batched :class:`~drone_torchrl.envs.DroneEnv`: ``num_envs`` drones flown side by side for
``steps_per_batch`` steps, each starting a new episode as soon as one ends (auto-reset) and
carrying an unfinished one over to the next batch, as a ``[num_envs, steps_per_batch]`` tensordict
with the env's keys and the actor's log-probability of each action. Here the drones are flown by
the C++ engine's rollout, a few calls of a few milliseconds each, where the collector steps the env
and the actor through TorchRL one step at a time (``benchmarks/ppo_collectors.py`` times both).

Why written here: TorchRL's collectors step an ``EnvBase``, whose fixed cost per step is larger
than the whole step of 64 drones; the kernel flies many steps per call but not an ``EnvBase``. The
layout, the keys and the semantics (``done`` = ``terminated | truncated``, truncation at
``env.max_steps``, auto-reset) are the collector's, so GAE, the loss, the episode tracker and the
budget read both alike. Start states come from the env's own sampler
(:func:`~drone_torchrl.envs.dynamics.initial_state`) and the action noise from one generator seeded
with the run's seed, whose state a checkpoint keeps: the same layout and semantics as the
collector's batches, from different random draws.
"""

from __future__ import annotations

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from drone_torchrl.config import env_kwargs, physics_params
from drone_torchrl.envs import dynamics
from drone_torchrl.envs.dynamics import TerminationCause
from drone_torchrl.envs.rollout import Episodes
from drone_torchrl.modules.factory import model_dtype
from drone_torchrl.modules.policy import ThreeNetPolicy
from drone_torchrl.modules.stacked import StackedThreeNet
from drone_torchrl.training.collectors import kernel_rollout, squash_bound


class FusedSegments:
    """Batches of ``[num_envs, steps_per_batch]`` steps of the actor's net, as TorchRL's collector
    gives them (see the module's docstring). Iterate to get the batches.

    ``net`` is the :class:`ThreeNetPolicy` inside ``actor`` (the learner trains it): its weights
    are copied into the kernel's flat layout at every batch, and ``actor`` scores the actions."""

    def __init__(self, cfg: DictConfig, actor: ProbabilisticActor, net: ThreeNetPolicy) -> None:
        algo = cfg.algo
        self.cfg, self.actor, self.net = cfg, actor, net
        self.num_envs, self.steps = algo.num_envs, algo.steps_per_batch
        self.max_steps = cfg.env.max_steps
        self.reset_mode = cfg.env.reset_mode
        self.params = physics_params(env_kwargs(cfg))
        self.dtype = model_dtype(cfg)
        self.device = torch.device(cfg.device)
        self.stacked = StackedThreeNet([net], cfg.model.activation).to(self.device)
        self.kernel = kernel_rollout(cfg, self.stacked, squash_bound(cfg), self.steps)
        self.log_prob_key = actor.log_prob_keys[0]
        # Start states and action noise, drawn on the CPU as DroneEnv draws its start states.
        self.generator = torch.Generator()
        self.generator.manual_seed(int(cfg.seed))
        self.state = self._starts(self.num_envs)
        self.t = torch.zeros(self.num_envs, dtype=torch.int64, device=self.device)  # each drone's step

    def _starts(self, n: int) -> torch.Tensor:
        return dynamics.initial_state(
            (n,), self.reset_mode, self.generator, self.device, self.dtype, self.params
        )

    def restart(self) -> None:
        """Start every drone's episode afresh (a resumed run: the interrupted episodes were not booked)."""
        self.state = self._starts(self.num_envs)
        self.t.zero_()

    def _fly(self, start: torch.Tensor, noise: torch.Tensor) -> Episodes:
        """Each row from ``start`` ``[E, 6]`` with ``noise`` ``[E, steps, 2]`` until it terminates or
        ``steps`` steps pass."""
        flown = self.kernel(start.unsqueeze(0), noise.unsqueeze(0))  # the one agent's dim
        return Episodes(*(x[0] for x in flown[:5]))

    def __iter__(self) -> FusedSegments:
        return self

    @torch.no_grad()
    def __next__(self) -> TensorDictBase:
        self.stacked.load_agent_state_dict(0, self.net.state_dict())
        n, steps = self.num_envs, self.steps
        rows = torch.arange(n, device=self.device)
        obs = torch.zeros(n, steps, dynamics.STATE_DIM, dtype=self.dtype, device=self.device)
        next_obs, action = torch.zeros_like(obs), obs.new_zeros(n, steps, dynamics.ACTION_DIM)
        reward = obs.new_zeros(n, steps)
        cause = torch.zeros(n, steps, dtype=torch.int64, device=self.device)
        terminated = torch.zeros(n, steps, dtype=torch.bool, device=self.device)
        truncated = torch.zeros_like(terminated)
        step_count = torch.zeros_like(cause)
        filled = torch.zeros(n, dtype=torch.int64, device=self.device)
        while int(filled.min()) < steps:
            # Every call flies a whole batch's steps (the kernel's buffers have one length).
            noise = torch.randn(n, steps, dynamics.ACTION_DIM, generator=self.generator, dtype=torch.float32)
            flown = self._fly(self.state, noise.to(self.device, self.dtype))
            # Each drone keeps the steps it needs, up to its episode's end or its time limit.
            used = torch.minimum(torch.minimum(flown.length, self.max_steps - self.t), steps - filled)
            j = torch.arange(flown.steps, device=self.device)
            keep = j < used.unsqueeze(-1)  # [n, T]
            r, c = keep.nonzero(as_tuple=True)
            col = filled[r] + c
            obs[r, col] = flown.states[r, c]
            next_obs[r, col] = flown.states[r, c + 1]
            action[r, col] = flown.action[r, c]
            reward[r, col] = flown.reward[r, c]
            cause[r, col] = flown.cause[r, c]
            step_count[r, col] = self.t[r] + c
            last = (used - 1).clamp_min(0)
            ends = flown.cause[rows, last] != int(TerminationCause.NONE)
            ended_here = (used == flown.length) & ends  # never for a drone whose batch is full (used 0)
            timed_out = ~ended_here & (self.t + used >= self.max_steps)
            at = filled + last
            terminated[rows[ended_here], at[ended_here]] = True
            truncated[rows[timed_out], at[timed_out]] = True
            done = ended_here | timed_out
            after = flown.states[rows, used]
            fresh = self._starts(int(done.sum()))
            after[done] = fresh
            self.state = after
            self.t = torch.where(done, 0, self.t + used)
            filled = filled + used
        td = TensorDict(
            {
                "observation": obs,
                "action": action,
                "step_count": step_count.unsqueeze(-1),
                "next": {
                    "observation": next_obs,
                    "reward": reward.unsqueeze(-1),
                    "terminated": terminated.unsqueeze(-1),
                    "truncated": truncated.unsqueeze(-1),
                    "done": (terminated | truncated).unsqueeze(-1),
                    "termination_cause": cause.unsqueeze(-1),
                },
            },
            batch_size=[n, steps],
            device=self.device,
        )
        with set_exploration_type(ExplorationType.RANDOM):
            dist = self.actor.get_dist(td.select("observation"))
        td.set(self.log_prob_key, dist.log_prob(action))
        return td
