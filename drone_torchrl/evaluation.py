"""The evaluator: seeded deterministic episodes, for training, ``drone-eval``, the PD baseline and reports.

Every policy evaluated with the same ``episodes`` and ``seed`` starts from the same states (those
a ``DroneEnv(batch_size=[episodes])`` seeded with ``seed`` resets to), so returns are comparable
across policies, runs and backends. A TensorDict policy (an actor, a controller) is flown by the
reference (:func:`drone_torchrl.envs.rollout.fly_reference`: ``DroneEnv`` and TorchRL's rollout);
the fast engine passes its own deterministic rollout, all agents of a population at once.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from drone_torchrl.config import physics_params
from drone_torchrl.envs import dynamics
from drone_torchrl.envs.drone_env import DroneEnv, check_env_args
from drone_torchrl.envs.heuristic import PDController, PDGains
from drone_torchrl.envs.rollout import RolloutFn, fly_reference
from drone_torchrl.episodes import cause_counts, episode_stats
from drone_torchrl.optimum import Optimum, env_optimum


@torch.no_grad()
def evaluate(
    policy: TensorDictModuleBase | RolloutFn,
    env_kwargs: dict[str, Any],
    episodes: int,
    seed: int,
    device: str = "cpu",
    agents: int | None = None,
) -> tuple[dict[str, torch.Tensor], TensorDictBase]:
    """Fly ``episodes`` seeded episodes with the policy's deterministic action.

    ``policy`` is a TensorDict module reading ``"observation"`` and writing ``"action"``, or a
    :data:`~drone_torchrl.envs.rollout.RolloutFn` flying start states to their episodes' ends with
    the deterministic action (the training engines pass their own, so evaluation uses exactly the
    arithmetic of training). With ``agents=N`` the same start states are flown by N agents at
    once (observations ``[N, episodes, 6]``). Returns the per-episode stats
    (:func:`~drone_torchrl.episodes.episode_stats`, shape ``[episodes]`` or ``[N, episodes]``)
    and the rollout.
    """
    env = DroneEnv(batch_size=[episodes], device=device, **env_kwargs)  # validates the arguments
    env.set_seed(seed)
    env.reset()
    start, keys = env.state, env.episode_keys
    env.close()
    if agents is not None:
        start = start.expand(agents, *start.shape).clone()
        keys = None if keys is None else keys.expand(agents, *keys.shape).clone()
    if isinstance(policy, TensorDictModuleBase):
        episodes = fly_reference(policy, start, keys, device, **env_kwargs)
    else:
        episodes = policy(start) if keys is None else policy(start, keys=keys)
    rollout = episodes.as_rollout(env.max_steps)
    return episode_stats(rollout), rollout


def summarize(
    stats: dict[str, torch.Tensor],
    max_return: float,
    optimum: float | None = None,
    pd_return: float | None = None,
) -> dict[str, Any]:
    """Means over the episodes of one policy's stats (1-D tensors), in drone-eval's table's order.

    ``return_mean``, ``return_std`` (population std), ``return_min``, ``pct_of_max`` (of
    ``max_return``), ``pct_of_optimum`` (of ``optimum``, the best achievable return of each of these
    episodes, :func:`reference_optimum`; NaN without one), ``pct_of_pd`` (of ``pd_return``, the PD
    controller's mean return; NaN without one or if 0), ``length_mean``, ``time_in_zone``,
    ``first_zone_step_mean`` / ``_max`` (over the episodes that end a step inside the zone; NaN if
    none), ``reached_fraction`` (those episodes), ``thrust_mean`` and ``thrust_max`` (motor commands
    as fractions of the weight), ``negative_thrust_fraction``, ``crashes`` (episodes that
    terminated), then ``terminated_fraction`` and ``causes`` (:func:`~.episodes.cause_counts`).
    """
    returns = stats["return"].float()
    mean = float(returns.mean())
    first = stats["first_zone_step"]
    reached = first > 0
    terminated = stats["termination_cause"] != int(dynamics.TerminationCause.NONE)
    return {
        "return_mean": mean,
        "return_std": float(returns.std(correction=0)),
        "return_min": float(returns.min()),
        "pct_of_max": 100.0 * mean / max_return,
        "pct_of_optimum": math.nan if optimum is None else 100.0 * mean / optimum,
        "pct_of_pd": 100.0 * mean / pd_return if pd_return else math.nan,
        "length_mean": float(stats["length"].float().mean()),
        "time_in_zone": float(stats["time_in_zone"].float().mean()),
        "first_zone_step_mean": float(first[reached].float().mean()) if reached.any() else math.nan,
        "first_zone_step_max": float(first[reached].max()) if reached.any() else math.nan,
        "reached_fraction": float(reached.float().mean()),
        "thrust_mean": float(stats["thrust_mean"].float().mean()),
        "thrust_max": float(stats["thrust_max"].float().max()),
        "negative_thrust_fraction": float(stats["negative_thrust_fraction"].float().mean()),
        "crashes": int(terminated.sum()),
        "terminated_fraction": float(terminated.float().mean()),
        "causes": cause_counts(stats["termination_cause"]),
    }


def max_return(env_kwargs: dict[str, Any]) -> float:
    """The return ceiling ``REWARD_IN_ZONE * max_steps`` (3000 for 300 steps)."""
    return dynamics.REWARD_IN_ZONE * check_env_args(**env_kwargs).max_steps


def reference_optimum(env_kwargs: dict[str, Any]) -> Optimum | None:
    """The best achievable return of the env's episodes where it is the reference: with bounded thrust.

    The bound is :func:`drone_torchrl.optimum.env_optimum`'s, the reference for returns. ``None``
    with unbounded thrust (the bound is the ceiling ``10 * max_steps``, reached only by a thrust
    pulse of hundreds of weights, so the PD controller is the practical reference), under
    disturbances (the bound is the nominal drone's) and where the bound is not derived.
    """
    args = check_env_args(**env_kwargs)
    if args.params.max_thrust is None or args.disturbance.active:
        return None
    return env_optimum(args.params, args.max_steps, args.reset_mode)


def evaluate_pd(
    env_kwargs: dict[str, Any] | None = None,
    episodes: int = 100,
    seed: int = 0,
    gains: PDGains | None = None,
    device: str = "cpu",
) -> dict[str, Any]:
    """The PD hover controller's :func:`summarize` over ``episodes`` seeded episodes."""
    env_kwargs = dict(env_kwargs or {})
    stats, _ = evaluate(PDController(physics_params(env_kwargs), gains), env_kwargs, episodes, seed, device)
    return summarize(stats, max_return(env_kwargs))
