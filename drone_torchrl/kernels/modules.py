"""The kernels behind the interfaces the rest of the package uses.

- :class:`KernelReinforce`: one REINFORCE update's gradient through ``drone_torchrl::reinforce``.
- :class:`KernelRollout`: whole episodes through ``drone_torchrl::rollout``, as
  :class:`~drone_torchrl.envs.rollout.Episodes` (what :func:`~drone_torchrl.envs.rollout.fly_episodes`
  returns for the PyTorch code).
"""

from __future__ import annotations

import torch

from drone_torchrl.envs import dynamics
from drone_torchrl.envs.rollout import Episodes
from drone_torchrl.kernels import ops
from drone_torchrl.modules.stacked import StackedThreeNet


class KernelRollout:
    """Each agent's episodes flown to their ends by the C++ kernel, for the stochastic policy or
    the deterministic one.

    Args:
        stacked: the agents' nets (their flat parameters are read at each call).
        params: the drone.
        squash_high: the TanhNormal head's upper bound, or None for the Normal head.
        max_steps: the episode length limit.
        reset_mode: where start states drawn from ``rng`` lie (``env.reset_mode``).
    """

    def __init__(
        self,
        stacked: StackedThreeNet,
        params: dynamics.DroneParams,
        squash_high: float | None,
        max_steps: int,
        reset_mode: str = "floor",
    ) -> None:
        self.stacked = stacked
        self.hidden = list(stacked.hidden_sizes)
        self.activation = ops.ACTIVATION_CODES[stacked.activation_name]
        self.env = ops.env_constants(params, squash_high, reset_mode)
        self.max_steps = max_steps

    @torch.no_grad()
    def __call__(
        self,
        start: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
        active: torch.Tensor | None = None,
        rng: torch.Tensor | None = None,
    ) -> Episodes:
        """Each agent's episodes from ``start`` (``[N, E, 6]``) with ``noise`` (``[N, E, max_steps, 2]``;
        None: the deterministic action), or with start states and noise drawn from ``rng``
        (``[N, E, 2]``: seed and update counter, see ``drone_torchrl::rollout``). ``active``: ``[N]``
        bool (default: all). Returns ``[N, E, T]`` episodes, ``T`` the longest; inactive agents' rows are empty."""
        flat = self.stacked.flat
        n = flat.shape[0]
        if active is None:
            active = torch.ones(n, dtype=torch.bool)
        gamma = torch.ones(n, dtype=torch.float64)  # the returns-to-go are not used here
        states, action, reward, cause, length, _, _ = ops.rollout(
            flat.detach(), start, noise, rng, active, self.env, gamma, self.hidden, self.activation,
            self.stacked.min_std, self.max_steps, self.stacked.distribution_eps,
        )  # fmt: skip
        steps = max(int(length.max()), 1)  # the longest episode; the rest of the buffers is zeros
        return Episodes(
            states[..., : steps + 1, :],
            action[..., :steps, :],
            reward[..., :steps],
            cause[..., :steps],
            length,
        )


class KernelReinforce:
    """One REINFORCE update's gradient of every agent by the C++ kernel (``drone_torchrl::reinforce``).

    Args:
        rollout: the agents' :class:`KernelRollout` (network, drone, episode limit).
        episodes: episodes per agent per update.
        options: the loss options, :data:`drone_torchrl.kernels.ops.LOSS_OPTIONS` -> bool.
    """

    def __init__(self, rollout: KernelRollout, episodes: int, options: dict[str, bool]) -> None:
        self.rollout = rollout
        self.episodes = episodes
        self.options = [int(bool(options[name])) for name in ops.LOSS_OPTIONS]

    def __call__(
        self, seed: torch.Tensor, counter: torch.Tensor, gamma: torch.Tensor, active: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        """``seed``, ``counter`` (the update's RNG key), ``gamma``, ``active``: ``[N]`` each. Returns
        :func:`~drone_torchrl.kernels.ops.reinforce`'s outputs."""
        r = self.rollout
        keys = torch.stack([seed, counter], -1).unsqueeze(1).expand(-1, self.episodes, -1)
        return ops.reinforce(
            r.stacked.flat.detach(), keys, active, r.env, gamma, self.options, r.hidden, r.activation,
            r.stacked.min_std, r.max_steps, r.stacked.distribution_eps,
        )  # fmt: skip
