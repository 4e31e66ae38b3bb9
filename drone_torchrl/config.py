"""Where the Hydra configs live, and the checks every config passes before any work starts."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from drone_torchrl.envs.drone_env import DroneEnv, make_params
from drone_torchrl.envs.dynamics import DroneParams
from drone_torchrl.modules.policy import ACTIVATIONS, DISTRIBUTIONS
from drone_torchrl.objectives.reinforce import BASELINES

# torchrl: TorchRL env + ProbabilisticActor rollouts, the reference collector; fused: many agents
# stepped as one batch on the shared dynamics, the fast path (drone_torchrl/training/collectors.py).
ENGINES = ("torchrl", "fused")
# The DroneEnv arguments a config holds under env.*: the one list of them.
ENV_ARGS = (
    "mass",
    "motor_distance",
    "gravity",
    "dt",
    "max_steps",
    "reset_mode",
    "max_thrust",
    "floor_tolerance",
)


def config_dir() -> str:
    """Absolute path of the ``conf/`` folder.

    A wheel ships the top-level ``conf/`` as ``drone_torchrl/conf`` (pyproject's package-dir);
    a source checkout or editable install reads the top-level folder itself.
    """
    # The configs name hydra/launcher=fused and hydra/sweeper=population: their schemas must be in
    # Hydra's ConfigStore before composing, also where Hydra's plugin scan does not see them (an
    # editable install's hydra_plugins is an import hook, not a folder).
    import hydra_plugins.drone_torchrl_launcher.schemas  # noqa: F401

    package = Path(__file__).resolve().parent
    for candidate in (package / "conf", package.parent / "conf"):
        if (candidate / "config.yaml").is_file():
            return str(candidate)
    raise FileNotFoundError(f"drone_torchrl's conf/ folder is missing (looked in {package} and its parent)")


class ConfigError(ValueError):
    """A config value that is not allowed: the message names the key, the value and what is allowed."""

    @classmethod
    def of(cls, key: str, value: Any, allowed: str) -> ConfigError:
        return cls(f"{key}={value!r} is not allowed; expected {allowed}")


def _number(
    cfg: DictConfig,
    key: str,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    integer: bool = False,
) -> None:
    value = cfg
    for part in key.split("."):
        value = value[part]
    kind = "an integer" if integer else "a number"
    bounds = []
    if low is not None:
        bounds.append(f"{'>' if low_open else '>='} {low}")
    if high is not None:
        bounds.append(f"<= {high}")
    allowed = f"{kind} {' and '.join(bounds)}".strip()
    numeric = isinstance(value, int | float) and not isinstance(value, bool)
    if not numeric or (integer and not isinstance(value, int)) or not math.isfinite(value):
        raise ConfigError.of(key, value, allowed)
    if low is not None and (value < low or (low_open and value == low)):
        raise ConfigError.of(key, value, allowed)
    if high is not None and value > high:
        raise ConfigError.of(key, value, allowed)


def _choice(cfg: DictConfig, key: str, choices: tuple) -> None:
    section, name = key.split(".")
    if cfg[section][name] not in choices:
        raise ConfigError.of(key, cfg[section][name], f"one of {list(choices)}")


# Keys added after the first runs were saved, with the value those runs behaved as: a checkpoint's
# config gets them filled in, so old runs can still be evaluated and resumed.
ADDED_KEYS = {
    "engine": "torchrl",
    "compile": False,
    "logger.every_updates": 1,
    "logger.video_stride": 1,
    "algo.optimizer": "adam",
    "algo.weight_decay": 0.0,
    "logger.flush_every_s": 10,
}
OPTIMIZERS = ("adam", "adamw")


def run_config(saved: dict[str, Any]) -> DictConfig:
    """The config stored in a checkpoint, with keys added since filled in (:data:`ADDED_KEYS`)."""
    cfg = OmegaConf.create(saved)
    for key, value in ADDED_KEYS.items():
        if OmegaConf.select(cfg, key, default=_ABSENT) is _ABSENT:
            OmegaConf.update(cfg, key, value, force_add=True)
    return cfg


_ABSENT = object()


# The DroneEnv arguments that describe the episode rather than the drone.
EPISODE_ARGS = ("max_steps", "reset_mode")


def physics_params(kwargs: dict[str, Any]) -> DroneParams:
    """The validated physical parameters among ``DroneEnv`` arguments (what the dynamics need)."""
    return make_params(**{k: v for k, v in kwargs.items() if k not in EPISODE_ARGS})


def env_kwargs(cfg: DictConfig | Mapping[str, Any]) -> dict[str, Any]:
    """The ``DroneEnv`` arguments of a config (a ``DictConfig`` or the plain dict of a saved one)."""
    return {name: cfg["env"][name] for name in ENV_ARGS}


def check_device(device: Any) -> None:
    """Raise :class:`ConfigError` for a device torch does not know or this machine does not have."""
    import torch

    try:
        kind = torch.device(device).type
    except (RuntimeError, TypeError):
        raise ConfigError.of("device", device, "a torch device such as 'cpu' or 'cuda'") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise ConfigError.of("device", device, "'cpu' here (this torch build or machine has no CUDA device)")


def validate(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for the first value that is not allowed."""
    check_device(cfg.device)
    try:
        DroneEnv(batch_size=[], device=cfg.device, **env_kwargs(cfg)).close()
    except ValueError as err:
        message = str(err)
        raise ConfigError(message if message.startswith("device=") else f"env.{message}") from None
    if cfg.engine not in ENGINES:
        raise ConfigError.of("engine", cfg.engine, f"one of {list(ENGINES)}")
    _number(cfg, "env.num_workers", low=0, integer=True)
    workers = cfg.env.num_workers
    _number(cfg, "seed", low=0, integer=True)
    _number(cfg, "threads", low=1, integer=True)
    _number(cfg, "algo.lr", low=0, low_open=True)
    _number(cfg, "algo.gamma", low=0, high=1)
    _number(cfg, "algo.episodes", low=1, integer=True)
    _number(cfg, "algo.episodes_per_update", low=1, integer=True)
    if workers and cfg.engine != "torchrl":
        raise ConfigError.of(
            "env.num_workers",
            workers,
            f"0 with engine={cfg.engine!r} (only engine=torchrl runs a ParallelEnv)",
        )
    if workers and cfg.algo.episodes_per_update % workers:
        raise ConfigError.of(
            "env.num_workers",
            workers,
            f"a divisor of algo.episodes_per_update={cfg.algo.episodes_per_update} (the episodes are split over the workers)",
        )
    _number(cfg, "algo.adam_eps", low=0, low_open=True)
    _choice(cfg, "algo.optimizer", OPTIMIZERS)
    _number(cfg, "algo.weight_decay", low=0)
    if cfg.algo.max_grad_norm is not None:
        _number(cfg, "algo.max_grad_norm", low=0, low_open=True)
    _choice(cfg, "algo.baseline", BASELINES)
    for flag in ("discount_weight", "normalize_returns"):
        if not isinstance(cfg.algo[flag], bool):
            raise ConfigError.of(f"algo.{flag}", cfg.algo[flag], "true or false")
    _choice(cfg, "model.distribution", DISTRIBUTIONS)
    _choice(cfg, "model.activation", tuple(ACTIVATIONS))
    _number(cfg, "model.min_std", low=0)
    sizes = cfg.model.hidden_sizes
    if (
        not isinstance(sizes, ListConfig | list)
        or not sizes
        or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 1 for s in sizes)
    ):
        raise ConfigError.of(
            "model.hidden_sizes",
            list(sizes) if isinstance(sizes, ListConfig | list) else sizes,
            "a non-empty list of integers >= 1, e.g. [32,32]",
        )
    if cfg.model.distribution == "tanh_normal" and cfg.env.max_thrust is None:
        raise ConfigError.of(
            "model.distribution",
            "tanh_normal",
            "'normal' unless env.max_thrust is set (e.g. env.max_thrust=1.0)",
        )
    _number(cfg, "checkpoint.every_episodes", low=1, integer=True)
    _number(cfg, "eval.every_episodes", low=0, integer=True)
    _number(cfg, "eval.episodes", low=1, integer=True)
    _number(cfg, "eval.seed", low=0, integer=True)
    _number(cfg, "metrics.running_mean_window", low=1, integer=True)
    _number(cfg, "logger.video_fps", low=1, integer=True)
    _number(cfg, "logger.video_stride", low=1, integer=True)
    _number(cfg, "logger.every_updates", low=1, integer=True)
    _number(cfg, "logger.flush_every_s", low=0)
    if not isinstance(cfg.compile, bool):
        raise ConfigError.of("compile", cfg.compile, "true or false")
    if cfg.progress not in (True, False, "auto"):
        raise ConfigError.of("progress", cfg.progress, "true, false or auto")
