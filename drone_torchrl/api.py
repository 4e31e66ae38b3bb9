"""The Python entry points: :func:`~drone_torchrl.api.train` and :func:`~drone_torchrl.api.evaluate`, what ``drone-train`` and ``drone-eval`` do.

For a notebook or a script (docs/python.md)::

    import drone_torchrl

    result = drone_torchrl.train("algo.lr=3e-4", seed=1, algo={"episodes": 500})
    result.final_return, result.eval_return, result.run_dir
    result.policy(observation)                      # [B, 6] -> thrust [B, 2], deterministic
    drone_torchrl.evaluate(checkpoint=result.run_dir, episodes=20).policy["return_mean"]

Both take the command line's overrides: Hydra override strings as positional arguments, and
``key=value`` keyword arguments (a dict value is a section: ``env={"max_steps": 100}`` is
``env.max_steps=100``; a dotted key goes through ``**{"algo.lr": 3e-4}``). The config is composed
by Hydra's compose API from the same ``conf/`` and checked by the same checks as the commands, so a
bad override is a one-line :class:`~drone_torchrl.checks.ConfigError` before anything is written,
and a run trains on the same code path as ``drone-train`` (the same numbers for the same config).
Training runs in the calling process; Hydra's global state, the working folder, logging, the
signal handlers, torch's thread count and its global random state are left as they were found.
"""

from __future__ import annotations

import contextlib
import numbers
import os
import re
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException

from drone_torchrl import migrations
from drone_torchrl.checks import ConfigError, as_override, first_line
from drone_torchrl.comparison import PD_NAME, PLOT_NAME, VIDEO_NAME, run_eval
from drone_torchrl.config import check_default_folder, check_overrides, config_dir, preset_notes

# The configs of drone-train and drone-eval (conf/<name>.yaml).
TRAIN_CONFIG, EVAL_CONFIG = "config", "eval"
# Where a run goes: the config's own default (outputs/<date>/<time>), or this override.
RUN_DIR_KEY = "hydra.run.dir"


@dataclass(frozen=True)
class TrainResult:
    """A finished run: its folder, its final metrics and its trained policy.

    Attributes:
        run_dir: the run folder (absolute): ``config.yaml``, ``episodes.csv``, ``checkpoints/``.
        metrics: the final metrics the last checkpoint keeps (``final_return``: the running mean of
            the last 100 episodes' returns, ``final_length``, ``eval_return``: the final
            evaluation's mean return, ``wall_clock_s``).
        config: the run's config, as it trained (a continued run: the checkpoint's, with the
            budget and process settings given).
        actor: the trained TorchRL actor (``ProbabilisticActor``, CPU, eval mode): reads
            ``"observation"`` of a ``DroneEnv`` tensordict and writes ``"action"``; deterministic
            under ``set_exploration_type(ExplorationType.DETERMINISTIC)``.
        policy: its deterministic policy as a plain module, observations ``[B, 6]`` -> the motor
            commands ``[B, 2]`` the env applies (what ``drone-export`` writes).
    """

    run_dir: Path
    metrics: dict[str, float]
    config: DictConfig = field(repr=False)
    actor: torch.nn.Module = field(repr=False)
    policy: torch.nn.Module = field(repr=False)

    @property
    def final_return(self) -> float:
        """The running mean of the last episodes' returns at the end (what sweeps optimise)."""
        return self.metrics["final_return"]

    @property
    def eval_return(self) -> float:
        """The final evaluation's mean return (``eval.episodes`` seeded deterministic episodes)."""
        return self.metrics["eval_return"]

    @property
    def checkpoint(self) -> Path:
        """The run's last checkpoint, what ``drone-eval``, ``drone-export`` and ``resume`` take."""
        from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, LAST

        return self.run_dir / CHECKPOINT_DIR / LAST


@dataclass(frozen=True)
class EvalResult:
    """The numbers of ``drone-eval``'s table: each policy flown, by its name in the table.

    Attributes:
        results: ``{name: summary}``, the checkpoint's row first (absent without a checkpoint),
            then the PD controller's; each summary as
            :func:`drone_torchrl.evaluation.summarize` gives it (``return_mean``, ``return_std``,
            ``length_mean``, ``time_in_zone``, ``pct_of_max``, ``pct_of_optimum``, ``causes``...).
        plot: the trajectory plot written, or None (``plot=false``).
        video: the GIF written, or None (``video=false``).
    """

    results: dict[str, dict[str, Any]]
    plot: Path | None = None
    video: Path | None = None

    @property
    def policy(self) -> dict[str, Any] | None:
        """The checkpoint's row, or None when only the PD controller flew."""
        return next((row for name, row in self.results.items() if name != PD_NAME), None)

    @property
    def pd(self) -> dict[str, Any]:
        """The PD hover controller's row, flown on the same seeded episodes."""
        return self.results[PD_NAME]


def train(*overrides: str, run_dir: str | os.PathLike | None = None, **values: Any) -> TrainResult:
    """Train one run in this process, as ``drone-train <overrides>`` would; returns its result.

    ``train("algo=ppo", "algo.lr=3e-4")``, ``train(algo="ppo", seed=1, **{"algo.lr": 3e-4})`` and
    ``train(algo="ppo", env={"max_steps": 100})`` are ``drone-train`` command lines. The run
    prints what ``drone-train`` prints; a folder that holds a run's last checkpoint continues that
    run (as ``drone-train hydra.run.dir=<folder>`` does), and so does ``resume=<run>``.

    Args:
        *overrides: Hydra override strings, as on the command line (``"algo.lr=3e-4"``,
            ``"experiment=bounded"``, ``"resume=outputs/<date>/<time>"``).
        run_dir: the run folder; the same as the override ``hydra.run.dir=<folder>``. Default: the
            config's, ``outputs/<date>/<time>`` under the working folder, with ``-1``, ``-2``...
            appended if a run of the same second has it.
        **values: ``key=value`` overrides after the strings (the last one of a key wins). Strings
            stay strings (quoted for Hydra), paths become strings, a dict is a section.

    Returns:
        The run's folder, final metrics, config and trained policy.

    Raises:
        ConfigError: a bad override, value or run folder (one line), before anything is written.
        TrainingDiverged: the training's numbers went non-finite (the run's ``FAILED.txt``).
    """
    from drone_torchrl.export import load_policy
    from drone_torchrl.training.jobs import prepare
    from drone_torchrl.training.trainer import train_job

    args = _arguments("train", overrides, values, run_dir)
    try:
        # Old keys (engine=, ...) work, each with a note naming today's (drone_torchrl.migrations).
        args, notes = migrations.legacy_arguments(args)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    with _own_hydra():
        cfg, folder = _compose(TRAIN_CONFIG, args)
        with _process_state(cfg.device):
            job = prepare(cfg, folder, requested=args)  # validated; the folder is this process's
            outcome = train_job(job)
            # One net, the actor and its deterministic policy (built from a seed: inside the block).
            policy, actor, _ = load_policy(outcome.run_dir)
    return TrainResult(outcome.run_dir.resolve(), dict(outcome.final), job.cfg, actor, policy)


def evaluate(*overrides: str, out_dir: str | os.PathLike | None = None, **values: Any) -> EvalResult:
    """Fly a checkpoint and the PD controller on seeded episodes, as ``drone-eval <overrides>`` would.

    ``evaluate(checkpoint=result.run_dir, episodes=20, video=False)``; without ``checkpoint`` the
    PD controller flies alone. Prints ``drone-eval``'s table and returns its numbers.

    Args:
        *overrides: Hydra override strings of ``conf/eval.yaml`` (``"checkpoint=outputs/..."``).
        out_dir: where the plot and video go; the same as the override ``hydra.run.dir=<folder>``.
            Default: the config's, ``outputs/eval/<date>/<time>`` under the working folder; made
            only when ``plot`` or ``video`` is on.
        **values: ``key=value`` overrides after the strings, as for :func:`train`.

    Returns:
        Each policy's row of the table, and the plot and video written.

    Raises:
        ConfigError: a bad override or value, or a checkpoint that cannot be flown (one line).
    """
    args = _arguments("evaluate", overrides, values, out_dir)
    with _own_hydra():
        cfg, folder = _compose(EVAL_CONFIG, args)
        with _process_state(cfg.device):
            results = run_eval(cfg, folder, _keys(args))
    folder = folder.resolve()
    return EvalResult(
        results, folder / PLOT_NAME if cfg.plot else None, folder / VIDEO_NAME if cfg.video else None
    )


def _arguments(prog: str, overrides: Sequence[Any], values: Mapping[str, Any], folder: Any) -> list[str]:
    """The command line of a call: the override strings, then ``values`` and the folder (``hydra.run.dir``)."""
    for override in overrides:
        if not isinstance(override, str):
            raise ConfigError(
                f"{prog}() takes Hydra override strings such as 'algo.lr=3e-4' as positional arguments, "
                f"not {override!r}: pass values as keywords (seed=1)"
            )
        if override.startswith("-"):
            raise ConfigError(
                f"{override} is a command-line flag; {prog}() takes overrides (key=value) only: one run, "
                "in this process (a sweep is drone-train -m)"
            )
    args = list(overrides)
    for key, value in _flatten(values):
        if "=" in key or not key.strip():
            raise ConfigError(
                f"{key!r} is not a config key: a keyword is a key (seed=1), its value the value"
            )
        args.append(f"{key}={_hydra_value(key, value)}")
    if folder is not None:
        if not isinstance(folder, str | os.PathLike):
            raise ConfigError(f"{prog}() takes a folder path (a str or a Path), not {folder!r}")
        if any(a.split("=", 1)[0].lstrip("+") == RUN_DIR_KEY for a in args):
            raise ConfigError(f"the folder is given twice, as {RUN_DIR_KEY}= and as a keyword; give one")
        args.append(f"{RUN_DIR_KEY}={_hydra_value(RUN_DIR_KEY, os.fspath(folder))}")
    return args


def _flatten(values: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``(dotted key, value)`` of keyword overrides; a mapping is a section (its keys one by one)."""
    for key, value in values.items():
        full = f"{prefix}{key}"
        if isinstance(value, Mapping):
            yield from _flatten(value, f"{full}.")
        else:
            yield full, value


# Backslashes right before a quote (and at the end) are escapes in Hydra's quoted strings; the
# others are themselves (Hydra's override grammar).
_BEFORE_QUOTE = re.compile(r"(\\*)'")
_AT_END = re.compile(r"(\\+)$")


def _hydra_value(key: str, value: Any) -> str:
    """A Python value as Hydra's override grammar writes it; a string stays a string (quoted)."""
    if value is None or isinstance(value, bool):
        return as_override(value)  # null, true, false
    if isinstance(value, numbers.Integral):
        return str(int(value))
    if isinstance(value, numbers.Real):
        return repr(float(value))  # inf, -inf and nan read back as floats
    if isinstance(value, str | os.PathLike):
        text = _AT_END.sub(lambda m: 2 * m[1], os.fspath(value))
        return "'" + _BEFORE_QUOTE.sub(lambda m: 2 * m[1] + "\\'", text) + "'"
    if isinstance(value, Sequence):
        return "[" + ",".join(_hydra_value(key, item) for item in value) + "]"
    if isinstance(value, Mapping):
        return "{" + ",".join(f"{k}:{_hydra_value(key, v)}" for k, v in value.items()) + "}"
    raise ConfigError.of(key, value, "a number, string, bool, None, path, list or dict")


def _keys(args: Sequence[str]) -> set[str]:
    """The keys (and group names) an override list sets, as the command line's are read."""
    return {a.split("=", 1)[0].lstrip("+~") for a in args}


def _compose(name: str, args: list[str]) -> tuple[DictConfig, Path]:
    """The config ``conf/<name>.yaml`` composed with ``args``, checked as its command's, and its folder.

    The checks before composing are those of the command line (``drone_torchrl.command_line``):
    each bad override is one line. Hydra's node is taken off the config, as a Hydra app gets it.
    """
    from hydra import compose
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    check_overrides(args, name)
    for override in OverridesParser.create().parse_overrides(args):
        key = override.key_or_group
        if override.is_sweep_override():
            raise ConfigError(
                f"{override.input_line} is a sweep: one call trains or flies one config (call it once per "
                "value, or sweep with drone-train -m)"
            )
        if key == RUN_DIR_KEY and not isinstance(override.value(), str):  # Hydra's merge: several lines
            raise ConfigError.of(key, override.value(), "a folder path")
        if key.split(".")[0].split("/")[0] == "hydra" and key != RUN_DIR_KEY:
            raise ConfigError(
                f"{override.input_line} is a Hydra setting; in Python only {RUN_DIR_KEY} (the folder) applies"
            )
    given = RUN_DIR_KEY in _keys(args)
    if not given:
        check_default_folder(name, args)
    try:
        cfg = compose(name, overrides=args, return_hydra_config=True)
        folder = OmegaConf.select(cfg, RUN_DIR_KEY)
        choices = OmegaConf.to_container(cfg.hydra.runtime.choices)
    except (HydraException, OmegaConfBaseException) as err:
        first = first_line(err)
        raise ConfigError(f"Hydra cannot compose conf/{name}.yaml with {' '.join(args)}: {first}") from None
    if not isinstance(folder, str):
        raise ConfigError.of(RUN_DIR_KEY, folder, "a folder path")
    folder = Path(folder).expanduser()
    with open_dict(cfg):
        del cfg["hydra"]
    for note in preset_notes(choices, name):
        print(f"note: {note}", file=sys.stderr)
    if not given:  # the default folder is named by the second: a second call that second gets its own
        stem, n = folder, 0
        while folder.exists():
            n += 1
            folder = stem.with_name(f"{stem.name}-{n}")
    return cfg, folder.absolute()


@contextlib.contextmanager
def _own_hydra() -> Iterator[None]:
    """Hydra initialised on our ``conf/`` for the block, its global state put back as found after.

    ``GlobalHydra`` (also a caller's own, e.g. inside its Hydra app or ``initialize``),
    ``HydraConfig`` (cleared meanwhile: the call has no Hydra job, so the code reads the overrides
    given, not an enclosing app's command line) and Hydra's version base.
    """
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig
    from hydra.initialize import get_gh_backup, restore_gh_from_backup
    from hydra.version import VersionBase

    outer = get_gh_backup()
    job, version = HydraConfig.instance().cfg, VersionBase.instance().version_base
    GlobalHydra.instance().clear()
    HydraConfig.instance().cfg = None
    try:
        with initialize_config_dir(config_dir(), version_base="1.3"):
            yield
    finally:
        restore_gh_from_backup(outer)
        HydraConfig.instance().cfg = job
        VersionBase.instance().version_base = version


@contextlib.contextmanager
def _process_state(device: str) -> Iterator[None]:
    """Torch's thread count and global random state put back after the block.

    A run sets its threads (``threads``) and seeds its networks through torch's global generator;
    the caller's later work keeps its own.
    """
    threads = torch.get_num_threads()
    try:
        where = torch.device(device)
    except (RuntimeError, TypeError, ValueError):  # not a device: the config's checks say so in one line
        where = torch.device("cpu")
    cuda = []
    if where.type == "cuda" and torch.cuda.is_available():  # CUDA is initialised only for a run on it
        cuda = [torch.cuda.current_device() if where.index is None else where.index]
    try:
        with torch.random.fork_rng(devices=cuda):
            yield
    finally:
        torch.set_num_threads(threads)
