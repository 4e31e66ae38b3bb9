"""Where the Hydra configs live, and the checks every config passes before any work starts."""

from __future__ import annotations

import difflib
import functools
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from drone_torchrl import algorithms, loggers
from drone_torchrl.checks import ConfigError, choice, number, plain_name, sizes
from drone_torchrl.envs.drone_env import DroneEnv, make_params
from drone_torchrl.envs.dynamics import DroneParams
from drone_torchrl.modules.policy import ACTIVATIONS, DISTRIBUTIONS

# torchrl: TorchRL env + ProbabilisticActor rollouts, the reference collector; fused: many agents
# stepped as one batch on the shared dynamics, the fast path (drone_torchrl/training/collectors.py).
ENGINES = ("torchrl", "fused")
# The device kinds the code runs on. Others fail deep inside (mps has no float64 for the
# population optimizer's per-agent scalars; meta holds no numbers), so they are refused up front.
DEVICE_KINDS = ("cpu", "cuda")
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


# Bounds of values that have no natural limit. A learning rate above 1 only diverges with Adam's
# unit-scale steps; seeds are signed 64-bit integers in torch.
MAX_LR = 1.0
MAX_SEED = 2**63 - 1
# Episodes flown side by side (an update's, an evaluation's, drone-eval's) live in memory together:
# about 25 kB each for 300 steps, so 10,000 take a quarter of a GB.
MAX_PARALLEL_EPISODES = 10_000
# torch's intra-op threads; far past the cores they only slow it down (and 10^5 crashes it).
MAX_THREADS = 256
# Updates per call of the update function: past a few hundred the Python loop is already negligible,
# and each call holds its updates' metrics in memory.
MAX_UPDATES_PER_CALL = 10_000
# What a run writes into its folder: logger.exp_name must not collide with one of them.
RUN_FOLDER_ENTRIES = frozenset(
    {"checkpoints", "videos", "episodes.csv", "config.yaml", "FAILED.txt", ".hydra", "train.log", ".lock"}
)
# Groups chosen with ``group=option`` (a file conf/<group>/<option>.yaml); Hydra's own groups
# (hydra/launcher, hydra/sweeper) are Hydra's to check.
_HYDRA_PREFIX = "hydra"


# Groups whose options are plug-ins, each option naming its plug-in under this key: each option
# may add keys of its own (an algorithm's hyper-parameters, a logger backend's settings).
PLUGIN_GROUPS = {"algo": "name", "logger": "backend"}


@functools.cache
def schema(name: str = "config", algo: str | None = None, logger: str | None = None) -> DictConfig:
    """Every key a ``conf/<name>.yaml`` config can hold, with its default value.

    The primary file merged with its default group options (``algo``, ``logger``: that option of
    the group instead of the default one), not Hydra's settings: what a config composed from it
    holds, whichever experiment or sweep preset is chosen, since those only set values of these keys.
    """
    chosen = {"algo": algo, "logger": logger}
    root = Path(config_dir())
    primary = OmegaConf.load(root / f"{name}.yaml")
    merged = OmegaConf.create()
    for entry in primary.get("defaults", []):
        if not isinstance(entry, Mapping):
            continue  # _self_
        for group, option in entry.items():
            if group.startswith("override") or group.startswith(_HYDRA_PREFIX):
                continue
            option = chosen.get(group) or option
            _merge_option(merged, root, group, option)
    own = {k: v for k, v in primary.items() if k not in ("defaults", _HYDRA_PREFIX)}
    merged.merge_with(OmegaConf.create(own))
    return merged


def _merge_option(merged: DictConfig, root: Path, group: str, option: str) -> None:
    """Merge ``conf/<group>/<option>.yaml`` (after the options its own defaults list names)."""
    path = root / group / f"{option}.yaml"
    node = OmegaConf.load(path)
    for parent in node.pop("defaults", []):
        if isinstance(parent, str) and parent != "_self_":
            _merge_option(merged, root, group, parent)
    if _is_global(path):
        merged.merge_with(node)
    elif group in merged:
        merged[group].merge_with(node)
    else:
        merged[group] = node


def _is_global(path: Path) -> bool:
    return any(line.strip() == "# @package _global_" for line in path.read_text().splitlines()[:3])


def leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    """``{"algo.lr": 0.0001, ...}``: every leaf of a config (lists are leaves), Hydra's node left out."""
    if not isinstance(node, DictConfig | Mapping):
        return {prefix: OmegaConf.to_container(node) if isinstance(node, ListConfig) else node}
    out: dict[str, Any] = {}
    for key in node:
        if not prefix and key == _HYDRA_PREFIX:
            continue
        out.update(leaves(node[key], f"{prefix}.{key}" if prefix else str(key)))
    return out


def command_line_keys() -> set[str] | None:
    """Keys (and group names) set on the command line of this Hydra job; None outside a Hydra app."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    # Unresolved: an override's value may be an interpolation that does not resolve (reported later).
    task = OmegaConf.to_container(HydraConfig.get().overrides.task, resolve=False)
    return {str(o).split("=", 1)[0].lstrip("+~") for o in task}


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (Path(config_dir()) / group).glob("*.yaml"))


def group_names() -> list[str]:
    return sorted(p.name for p in Path(config_dir()).iterdir() if p.is_dir() and p.name != _HYDRA_PREFIX)


def _unknown(key: str, known: Iterable[str]) -> ConfigError:
    group = key.split(".")[0]
    if group in PLUGIN_GROUPS:  # another plug-in's key: say whose, not a look-alike of this one's
        owners = [o for o in _options(group) if key in _schema_leaves("config", **{group: o})]
        if owners:
            return ConfigError(
                f"{key} is not a key of this {group}; it belongs to {group}={f' or {group}='.join(owners)}"
            )
    close = difflib.get_close_matches(key, list(known), n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]}?" if close else " (see conf/ or drone-train --cfg job for the keys)"
    return ConfigError(f"{key} is not a config key{hint}")


def _resolved(cfg: DictConfig | Mapping) -> Mapping:
    """The config as plain data, resolved (a ``???`` value raises), Hydra's own node left out.

    At once (~0.2 ms) rather than node by node through OmegaConf (~0.5 ms)."""
    if not isinstance(cfg, DictConfig):
        return cfg
    out: dict[str, Any] = {}
    for key in cfg:
        if key == _HYDRA_PREFIX:
            continue
        value = cfg[key]
        if isinstance(value, DictConfig | ListConfig):
            try:
                value = OmegaConf.to_container(value, resolve=True, throw_on_missing=True)
            except OmegaConfBaseException:
                leaves(value)  # read node by node: the error then names the key from the root
                raise
        out[str(key)] = value
    return out


def check_keys(cfg: DictConfig, name: str = "config") -> Mapping:
    """Refuse keys the config files do not define (e.g. added with ``+``), and non-booleans for
    boolean options (``off``, ``no`` or ``1`` are strings or numbers here, not ``false``/``true``).
    Returns the config as resolved plain data (``???`` and interpolations to nothing are refused)."""

    try:
        known = _schema_leaves(name, **_plugin_options(cfg))
        resolved = _resolved(cfg)
        given = leaves(resolved)
    except OmegaConfBaseException as err:  # e.g. algo.lr=${oops}: an interpolation that resolves to nothing
        key = getattr(err, "full_key", None) or "a config value"
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"{key} cannot be read: {first}") from None
    missing = [k for k in known if k not in given and not any(g.startswith(f"{k}.") for g in given)]
    if missing:
        raise ConfigError(f"{missing[0]} is missing (deleted with ~?); every config key needs a value")
    for key, value in given.items():
        if key in known:
            if isinstance(known[key], bool) and not isinstance(value, bool):
                raise ConfigError.of(key, value, "true or false")
            continue
        # A list or dict default (e.g. model.hidden_sizes) may hold any shape of its own.
        if not any(key.startswith(f"{k}.") or key.startswith(f"{k}[") for k in known):
            raise _unknown(key, known)
    return resolved


@functools.cache
def _schema_leaves(name: str, algo: str | None = None, logger: str | None = None) -> dict[str, Any]:
    return leaves(schema(name, algo, logger))


def _plugin_options(cfg: Any) -> dict[str, str | None]:
    """``{"algo": option, "logger": option}``: the group options whose keys ``cfg`` holds, found by
    the plug-in each names (``algo.name``, ``logger.backend``): the option of that file name, or else
    the first that names it (file names are free: several options may share a plug-in, as
    reinforce_plus shares reinforce's learner)."""
    out: dict[str, str | None] = {}
    for group, key in PLUGIN_GROUPS.items():
        plugin = (
            OmegaConf.select(cfg, f"{group}.{key}", default=None) if isinstance(cfg, DictConfig) else None
        )
        out[group] = _plugin_files(group).get(plugin) if isinstance(plugin, str) else None
    return out


@functools.cache
def _plugin_files(group: str) -> dict[str, str]:
    """``{plug-in name: group option}`` of a plug-in group, an option named like its plug-in first."""
    key = f"{group}.{PLUGIN_GROUPS[group]}"
    named = {option: _schema_leaves("config", **{group: option}).get(key) for option in _options(group)}
    files: dict[str, str] = {}
    for option in sorted(named, key=lambda o: o != named[o]):
        files.setdefault(named[option], option)
    return files


def check_overrides(overrides: Iterable[str], name: str = "config") -> None:
    """One-line errors for command-line overrides Hydra would reject with several lines, or accept
    though they make no sense: an unknown key (with or without ``+``), an unknown group option, and
    a run folder that is a file, and an override Hydra cannot parse (its grammar error in one line)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    parsed = []
    for override in overrides:
        try:
            parsed += parser.parse_overrides([override])
        except HydraException as err:
            lines = [
                line
                for line in str(err).splitlines()
                if line.strip() and not line.startswith("Error parsing")
            ]
            reason = lines[0] if lines else type(err).__name__
            raise ConfigError(
                f"{override} cannot be parsed: {reason} (Hydra's override syntax: key=value, "
                "key=[a,b] for a list, quote values with special characters)"
            ) from None
    chosen: dict[str, str | None] = {}
    for group in PLUGIN_GROUPS:
        picked = [o.value() for o in parsed if o.key_or_group == group and not o.is_sweep_override()]
        chosen[group] = picked[-1] if picked and picked[-1] in _options(group) and name == "config" else None
    known = _schema_leaves(name, **chosen)
    groups = group_names()
    for override in parsed:
        key = override.key_or_group
        if override.is_delete():
            continue
        values = (
            list(override.sweep_string_iterator()) if override.is_sweep_override() else [override.value()]
        )
        if key.split(".")[0].split("/")[0] == _HYDRA_PREFIX:
            if key in ("hydra.run.dir", "hydra.sweep.dir"):
                for value in values:
                    _check_folder(key, value)
            continue
        if key == "sweep_name":  # names the multirun folder, which Hydra makes before any job runs
            for value in values:
                if not plain_name(value):
                    raise ConfigError.of(key, value, "a folder name (no '/' or '..'), e.g. lr")
            continue
        if key in groups:
            options = _options(key)
            for value in values:
                if value not in options:
                    raise ConfigError.of(key, value, f"one of {options}")
            continue
        if key not in known and not any(k.startswith(f"{key}.") for k in known):
            raise _unknown(key, known)


def _check_folder(key: str, value: Any) -> None:
    """A folder the run can create or write into: not empty, not a file, under a writable folder."""
    import os

    if not isinstance(value, str) or "${" in value:
        return  # Hydra's own interpolations (${now:...}) resolve later
    if not value.strip():
        raise ConfigError.of(key, value, "a folder path, not an empty string")
    path = Path(value).expanduser()
    existing = next(p for p in (path, *path.parents) if p.exists() or p == Path(p.anchor or "."))
    if existing.exists() and not existing.is_dir():
        raise ConfigError.of(key, value, f"a folder ({existing} is a file)")
    if not os.access(existing if existing.exists() else Path.cwd(), os.W_OK):
        raise ConfigError.of(key, value, f"a folder this user can write ({existing} is not writable)")


def check_command_line(prog: str, name: str) -> None:
    """:func:`check_overrides` on ``sys.argv``; exits with ``<prog>: error: <message>`` on a bad one.

    Skipped when the command line picks another config (``--config-name``/``--config-dir``...),
    whose keys the ``conf/`` files do not describe.
    """
    import sys

    args = sys.argv[1:]
    if any(a.startswith(("--config", "-cn", "-cp", "-cd")) for a in args):
        return
    try:
        check_overrides([a for a in args if not a.startswith("-") and "=" in a], name)
    except ConfigError as err:
        sys.exit(f"{prog}: error: {err}")


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
    "algo.name": "reinforce",
    "model.init_std": None,
    "steps_per_call": 1,
    "algo.log_prob_reduction": "sum",
    "updates_per_call": 1,
    "logger.backend": "tensorboard",
}
# An initial exploration std past this is no longer "near the mean": thrusts are fractions of the weight.
MAX_INIT_STD = 10.0


def run_config(saved: dict[str, Any]) -> DictConfig:
    """The config stored in a checkpoint, with keys added since filled in (:data:`ADDED_KEYS`;
    only those its algorithm has: a PPO run has no REINFORCE optimizer keys)."""
    cfg = OmegaConf.create(saved)
    if OmegaConf.select(cfg, "algo.name", default=_ABSENT) is _ABSENT:
        OmegaConf.update(cfg, "algo.name", ADDED_KEYS["algo.name"], force_add=True)
    known = _schema_leaves("config", **_plugin_options(cfg))
    for key, value in ADDED_KEYS.items():
        if key in known and OmegaConf.select(cfg, key, default=_ABSENT) is _ABSENT:
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


def open_checkpoint(key: str, location: Any) -> tuple[Path, dict[str, Any]]:
    """The checkpoint that config value ``key`` (``resume``, ``checkpoint``) names: a checkpoint file or
    a run folder. Raises :class:`ConfigError` naming the key for anything that is not a readable one."""
    from drone_torchrl.io.checkpoint import CheckpointError, load_checkpoint, resolve_checkpoint

    if not isinstance(location, str | Path) or not str(location).strip():
        raise ConfigError.of(key, location, "a run folder or a checkpoint file (a path)")
    try:
        path = resolve_checkpoint(location)
    except FileNotFoundError as err:
        raise ConfigError(f"{key}={str(location)!r} is not allowed; {err}") from None
    try:
        state = load_checkpoint(path)
    except CheckpointError as err:
        raise ConfigError(f"{key}={str(path)!r} cannot be used: {err}") from None
    name = OmegaConf.select(run_config(state["config"]), "algo.name")
    try:
        algorithm = algorithms.get(name)
    except ConfigError:
        raise ConfigError(
            f"{key}={str(path)!r} cannot be used: it was written by algo.name={name!r}, which is not installed "
            f"(known: {list(algorithms.names())})"
        ) from None
    missing = [entry for entry in algorithm.checkpoint_keys if entry not in state]
    if missing:
        raise ConfigError(
            f"{key}={str(path)!r} cannot be used: it lacks {', '.join(missing)} (algo.name={name} writes it): "
            "a damaged or foreign checkpoint"
        )
    return path, state


def check_device(device: Any) -> None:
    """Raise :class:`ConfigError` for a device torch does not know or this machine does not have."""
    import torch

    try:
        kind = torch.device(device).type
    except (RuntimeError, TypeError):
        raise ConfigError.of("device", device, "a torch device such as 'cpu' or 'cuda'") from None
    if kind not in DEVICE_KINDS:
        raise ConfigError.of("device", device, "'cpu' or 'cuda' ('cuda:N' for GPU number N)")
    if kind == "cuda" and not torch.cuda.is_available():
        raise ConfigError.of("device", device, "'cpu' here (this torch build or machine has no CUDA device)")


@functools.lru_cache(maxsize=64)
def _env_error(device: Any, kwargs: tuple[tuple[str, type, Any], ...]) -> str | None:
    """What ``DroneEnv`` says of these arguments (``(name, type, value)``: the type is part of the
    key, since ``1``, ``1.0`` and ``True`` are equal keys but not equally allowed), or None.
    Cached: a sweep's jobs mostly share them, and building the env is most of a job's validation
    (2 ms)."""
    try:
        DroneEnv(batch_size=[], device=device, **{name: value for name, _, value in kwargs}).close()
    except ValueError as err:
        message = str(err)
        return message if message.startswith("device=") else f"env.{message}"
    return None


class _Plain(dict):
    """A resolved config as nested dicts with attribute access (``cfg.algo.lr``), for validation:
    it reads about 150 values, ~7 us each through OmegaConf, and a population validates every job.
    (A key named like a dict method, ``items`` say, must be read as ``cfg["items"]``.)"""

    def __getattr__(self, name: str) -> Any:
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None


def _plain(node: Any) -> Any:
    if isinstance(node, dict):
        return _Plain((key, _plain(value)) for key, value in node.items())
    return node


def validate(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for the first value that is not allowed."""
    cfg = _plain(check_keys(cfg))  # also refuses ??? and interpolations to nothing, in one line
    check_device(cfg.device)
    kwargs = tuple((name, type(value), value) for name, value in env_kwargs(cfg).items())
    try:
        error = _env_error(cfg.device, kwargs)
    except TypeError:  # an unhashable value (a list where a number belongs): no cache
        error = _env_error.__wrapped__(cfg.device, kwargs)
    if error is not None:
        raise ConfigError(error)
    if cfg.engine not in ENGINES:
        raise ConfigError.of("engine", cfg.engine, f"one of {list(ENGINES)}")
    number(cfg, "env.num_workers", low=0, integer=True)
    number(cfg, "seed", low=0, high=MAX_SEED, integer=True)
    number(cfg, "threads", low=1, high=MAX_THREADS, integer=True)
    number(cfg, "steps_per_call", low=1, high=cfg.env.max_steps, integer=True)
    number(cfg, "updates_per_call", low=1, high=MAX_UPDATES_PER_CALL, integer=True)
    number(cfg, "algo.lr", low=0, low_open=True, high=MAX_LR)
    number(cfg, "algo.gamma", low=0, high=1)
    number(cfg, "algo.episodes", low=1, integer=True)
    algorithms.get(cfg.algo.name).validate(cfg)
    loggers.get(cfg.logger.backend).validate(cfg)
    choice(cfg, "model.distribution", DISTRIBUTIONS)
    choice(cfg, "model.activation", tuple(ACTIVATIONS))
    number(cfg, "model.min_std", low=0)
    sizes(cfg, "model.hidden_sizes")
    if cfg.model.init_std is not None:
        number(cfg, "model.init_std", low=cfg.model.min_std, low_open=True, high=MAX_INIT_STD)
    if cfg.model.distribution == "tanh_normal" and cfg.env.max_thrust is None:
        raise ConfigError.of(
            "model.distribution",
            "tanh_normal",
            "'normal' unless env.max_thrust is set (e.g. env.max_thrust=1.0)",
        )
    number(cfg, "checkpoint.every_episodes", low=1, integer=True)
    number(cfg, "eval.every_episodes", low=0, integer=True)
    number(cfg, "eval.episodes", low=1, high=MAX_PARALLEL_EPISODES, integer=True)
    number(cfg, "eval.seed", low=0, high=MAX_SEED, integer=True)
    number(cfg, "metrics.running_mean_window", low=1, integer=True)
    number(cfg, "logger.video_fps", low=1, integer=True)
    number(cfg, "logger.video_stride", low=1, integer=True)
    number(cfg, "logger.every_updates", low=1, integer=True)
    number(cfg, "logger.flush_every_s", low=0)
    name = cfg.logger.exp_name
    if not plain_name(name) or name in RUN_FOLDER_ENTRIES:
        raise ConfigError.of(
            "logger.exp_name",
            name,
            f"a new folder name inside the run folder (no '/' or '..', none of {sorted(RUN_FOLDER_ENTRIES)}), "
            "e.g. tensorboard",
        )
    if not plain_name(cfg.sweep_name):
        raise ConfigError.of("sweep_name", cfg.sweep_name, "a folder name (no '/' or '..'), e.g. lr")
    if cfg.progress not in (True, False, "auto"):
        raise ConfigError.of("progress", cfg.progress, "true, false or auto")
