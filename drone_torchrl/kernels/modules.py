"""The kernels behind the interfaces the rest of the package uses.

- :class:`KernelReinforce`: one REINFORCE update's gradient through ``ops.reinforce``.
- :class:`KernelRollout`: whole episodes through ``ops.rollout``, as
  :class:`~drone_torchrl.envs.rollout.Episodes` (what :func:`~drone_torchrl.envs.rollout.fly_reference`
  returns for the PyTorch code).
- :class:`KernelSegments`: PPO/A2C's auto-resetting batches through ``ops.segments``,
  the drones' state carried from call to call.

Each flies the drone with the env's disturbances (:mod:`drone_torchrl.envs.disturbances`).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from functools import partial
from typing import Any

import torch

from drone_torchrl.envs import disturbances, dynamics
from drone_torchrl.envs.params import DroneParams
from drone_torchrl.envs.rollout import Episodes
from drone_torchrl.kernels import ops
from drone_torchrl.kernels.ops import Carried, Segment
from drone_torchrl.modules.stacked import StackedThreeNet

#: A disturbance as the modules take it (a :class:`~drone_torchrl.envs.disturbances.Disturbance`, its
#: config section, or None for the nominal drone).
DisturbanceArg = disturbances.Disturbance | Mapping[str, Any] | None


class KernelRollout:
    """Each agent's episodes flown to their ends by the C++ kernel.

    The policy flown is the stochastic one or the deterministic one.

    Args:
        stacked: the agents' nets (their flat parameters are read at each call).
        params: the drone.
        squash_high: the TanhNormal head's upper bound, or None for the Normal head.
        max_steps: the episode length limit.
        reset_mode: where start states drawn from ``rng`` lie (``env.reset_mode``).
        disturbance: the env's disturbances (``env.disturbance``; None: the nominal drone).
    """

    def __init__(
        self,
        stacked: StackedThreeNet,
        params: DroneParams,
        squash_high: float | None,
        max_steps: int,
        reset_mode: str = "floor",
        disturbance: DisturbanceArg = None,
    ) -> None:
        self.stacked = stacked
        self.hidden = list(stacked.hidden_sizes)
        self.activation = ops.ACTIVATION_CODES[stacked.activation_name]
        self.env = ops.env_constants(params, squash_high, reset_mode)
        self.max_steps = max_steps
        self.nominal = disturbances.make(disturbance).nominal
        self.disturbance = None if self.nominal else ops.disturbance_constants(disturbance)
        self.agents = slice(None)

    def rows(self, agents: slice) -> KernelRollout:
        """The same rollout for the ``agents`` rows of the population only."""
        part = copy.copy(self)
        part.agents = agents
        return part

    @torch.no_grad()
    def __call__(
        self,
        start: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
        active: torch.Tensor | None = None,
        rng: torch.Tensor | None = None,
        keys: torch.Tensor | None = None,
    ) -> Episodes:
        """Fly each agent's episodes ``[N, E, T]`` from start states (or ``rng``) by the C++ kernel.

        Each agent's episodes from ``start`` (``[N, E, 6]``) with ``noise`` (``[N, E, max_steps, 2]``;
        None: the deterministic action), or with start states and noise drawn from ``rng``
        (``[N, E, 2]``: seed and update counter, see ``ops.rollout``). ``keys``: ``[N, E]``
        the episodes' disturbance keys (None: drawn from ``rng``). ``active``: ``[N]`` bool (default:
        all). Returns ``[N, E, T]`` episodes, ``T`` the longest; inactive agents' rows are empty.
        Under disturbances their ``observation`` is what the policy saw.
        """
        flat = self.stacked.flat[self.agents]
        active = torch.ones(flat.shape[0], dtype=torch.bool) if active is None else active
        gamma = torch.ones(flat.shape[0], dtype=torch.float64)  # the returns-to-go are not used here
        states, action, reward, cause, length, _, _, seen = ops.rollout(
            flat.detach(), start, noise, rng, active, self.env, gamma, self.hidden, self.activation,
            self.stacked.min_std, self.max_steps, self.stacked.distribution_eps, self.disturbance, keys,
            not self.nominal,
        )  # fmt: skip
        steps = max(int(length.max()), 1)  # the longest episode; the rest of the buffers is zeros
        cut = (states[..., : steps + 1, :], action[..., :steps, :], reward[..., :steps], cause[..., :steps])
        return Episodes(*cut, length, None if self.nominal else seen[..., :steps, :])


class KernelReinforce:
    """One REINFORCE update's gradient of every agent by the C++ kernel (``ops.reinforce``).

    Args:
        rollout: the agents' :class:`KernelRollout` (network, drone, disturbances, episode limit).
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
        """One REINFORCE update of every active agent by the C++ kernel (all inputs ``[N]``).

        ``seed`` and ``counter``: the update's RNG key. Returns
        :func:`~drone_torchrl.kernels.ops.reinforce`'s outputs.
        """
        r = self.rollout
        keys = torch.stack([seed, counter], -1).unsqueeze(1).expand(-1, self.episodes, -1)
        return ops.reinforce(
            r.stacked.flat.detach(), keys, active, r.env, gamma, self.options, r.hidden, r.activation,
            r.stacked.min_std, r.max_steps, r.stacked.distribution_eps, r.disturbance,
        )  # fmt: skip


class KernelSegments:
    """``n`` drones of one agent flown by the C++ kernel with auto-reset, ``steps`` steps a call.

    The function is ``ops.segments``; it matches TorchRL's collector over a batched
    :class:`~drone_torchrl.envs.drone_env.DroneEnv`, given the same draws.

    Args:
        rollout: the agent's :class:`KernelRollout` (one agent: network, drone, disturbances;
            its ``max_steps`` truncates the episodes).
        n: the drones.
    """

    def __init__(self, rollout: KernelRollout, n: int) -> None:
        self.rollout = rollout
        self.n = n
        self.delay, self.observed = ops.steps_back(rollout.disturbance)
        self.restart()

    def restart(self) -> None:
        """Every drone starts a new episode at the next call."""
        dtype, n, a, i64 = self.rollout.stacked.flat.dtype, self.n, dynamics.ACTION_DIM, torch.int64
        zeros, hover = partial(torch.zeros, dtype=dtype), dynamics.HOVER_THRUST
        self.carried = Carried(
            zeros(n, dynamics.STATE_DIM), torch.full((n,), -1, dtype=i64), torch.zeros(n, dtype=i64), zeros(n),
            torch.full((n, a), hover, dtype=dtype), torch.full((n, self.delay, a), hover, dtype=dtype),
            zeros(n, self.observed, a),
        )  # fmt: skip

    @torch.no_grad()
    def __call__(
        self, noise: torch.Tensor, fresh: torch.Tensor, fresh_keys: torch.Tensor | None = None
    ) -> Segment:
        """Fly the next ``steps`` steps of every drone; returns them as a :class:`Segment`.

        ``noise`` ``[n, steps, 2]``: standard normals of the actions; ``fresh`` ``[n, steps, 6]`` and
        ``fresh_keys`` ``[n, steps]``: the start state and episode key of a drone that starts a new
        episode at that step (keys: None for the nominal drone).
        """
        r = self.rollout
        segment, self.carried = ops.segments(
            r.stacked.flat.detach()[0], self.carried, noise, fresh, fresh_keys, r.max_steps, r.env,
            r.disturbance, r.hidden, r.activation, r.stacked.min_std, r.stacked.distribution_eps,
        )  # fmt: skip
        return segment
