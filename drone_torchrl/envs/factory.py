"""``make_env``: one entry point that builds a single, natively batched or process-parallel env."""

from __future__ import annotations

import multiprocessing as mp
from functools import partial
from typing import Any

from torchrl.envs import EnvBase, ParallelEnv, SerialEnv

from drone_torchrl.envs.drone_env import DroneEnv, check_env_args, is_integer

PARALLEL_MODES = ("process", "serial")


def make_env(
    num_envs: int | None = None,
    num_workers: int = 0,
    parallel: str = "process",
    **env_kwargs: Any,
) -> EnvBase:
    """Build a Drone2D environment from plain arguments.

    Args:
        num_envs: drones simulated together in each ``DroneEnv``; ``None`` gives an unbatched env
            (batch size ``[]``), an integer ``N`` gives batch size ``[N]``.
        num_workers: ``0`` (default) returns the natively batched ``DroneEnv`` itself, the fastest
            path on a few cores. ``k >= 1`` wraps ``k`` copies in a ``ParallelEnv`` (``parallel=
            "process"``) or ``SerialEnv`` (``parallel="serial"``), batch size ``[k, *batch]``.
        parallel: ``"process"`` or ``"serial"``, used only when ``num_workers >= 1``.
        **env_kwargs: any ``DroneEnv`` argument (``mass``, ``max_thrust``, ``device``, ...).

    ``ParallelEnv`` workers are always started with the ``"spawn"`` method: TorchRL's default, and
    the one that works under Hydra's joblib launcher, whose processes report ``"loky"``.
    """
    if num_envs is not None and (not is_integer(num_envs) or num_envs < 1):
        raise ValueError(f"num_envs={num_envs!r} is not allowed; expected None or an integer >= 1")
    if not is_integer(num_workers) or num_workers < 0:
        raise ValueError(f"num_workers={num_workers!r} is not allowed; expected an integer >= 0")
    if parallel not in PARALLEL_MODES:
        raise ValueError(f"parallel={parallel!r} is not allowed; expected one of {PARALLEL_MODES}")
    batch_size = [] if num_envs is None else [int(num_envs)]
    if num_workers == 0:
        return DroneEnv(batch_size=batch_size, **env_kwargs)
    check_env_args(batch_size, **env_kwargs)  # bad arguments fail here, not in a worker
    factory = partial(DroneEnv, batch_size=batch_size, **env_kwargs)
    if parallel == "serial":
        return SerialEnv(num_workers, factory)
    # A spawned child first re-applies its parent's *global* start method, whatever context started
    # it. Inside a worker of Hydra's joblib launcher that method is "loky", which the child cannot
    # find ("cannot find context for 'loky'"), so each ParallelEnv worker would die at start-up:
    # the process-wide method becomes "spawn" when it is not one Python itself knows.
    if mp.get_start_method(allow_none=True) not in (None, *mp.get_all_start_methods()):
        mp.set_start_method("spawn", force=True)
    return ParallelEnv(num_workers, factory, mp_start_method="spawn")
