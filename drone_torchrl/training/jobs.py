"""From configs to runs: validation, the resume and fork rules, grouping, and how each job ended.

Hydra cannot resume a multirun by itself. Every job here is idempotent instead: its folder is named
by its overrides inside a fixed sweep folder, and a job whose folder already holds a checkpoint
continues from it (finished jobs return at once), so running the same sweep command again skips
finished jobs and resumes the rest.

Resume rules (:func:`prepare`):

- ``resume=<run folder>`` or ``resume=<run>/checkpoints/last.pt`` continues that run in its folder:
  the same CSV and TensorBoard run, the episode counter carries on.
- ``resume=<any other checkpoint>`` (``best.pt``, a copied file) continues from it as a **fork** in
  a new run folder (the Hydra job's folder): the parent's CSV rows up to the checkpoint are copied,
  and the parent run is left as it was. A folder that holds anything (another run) is refused:
  the fork would overwrite it.
- A continued run keeps its hyper-parameters. From the command line it takes only the budget
  (``algo.episodes``), logging and checkpointing options and the process settings (each key's
  ``on_resume`` in :mod:`drone_torchrl.schema`); a command line that changes any other key is refused, naming each key
  with the checkpoint's and the command line's value.
"""

from __future__ import annotations

import contextlib
import functools
import math
import shlex
import sys
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, open_dict

from drone_torchrl import migrations
from drone_torchrl.config import (
    ConfigError,
    check_networks,
    command_line_keys,
    complete,
    composed_leaves,
    group_names,
    implied_choices,
    leaves,
    per_agent_keys,
    preset_notes,
    resume_rule,
    run_config,
    validate,
)
from drone_torchrl.io import run_lock
from drone_torchrl.io.checkpoint import (
    CHECKPOINT_DIR,
    LAST,
    CheckpointError,
    is_last_of_its_run,
    is_population,
    load_checkpoint,
    run_dir_of,
)
from drone_torchrl.io.folders import HYDRA_ENTRIES, check_fork_folder
from drone_torchrl.io.streams import about, console
from drone_torchrl.schema import BUDGET, KEPT, PROCESS
from drone_torchrl.training.population_record import open_agent
from drone_torchrl.training.run import FAILED_FILE, trained_out


@dataclass
class Job:
    """A run ready to train: its config, its folder, and where it continues from."""

    cfg: DictConfig
    run_dir: Path
    checkpoint: dict[str, Any] | None = None
    parent_dir: Path | None = None
    """The run a fork continues from (its CSV rows up to the checkpoint are copied)."""

    @property
    def already_finished(self) -> bool:
        """Whether the job's checkpoint is final, with its whole budget trained or ``eval.stop_return`` reached."""
        ckpt = self.checkpoint
        return (
            ckpt is not None
            and ckpt["final"] is not None
            and trained_out(
                ckpt["episodes_done"],
                self.cfg.algo.episodes,
                ckpt.get("stopped_at_return"),
                self.cfg.eval.get("stop_return"),
            )
        )


def _hydra_run_dir() -> Path | None:
    return Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else None


def prepare(
    cfg: DictConfig,
    run_dir: str | Path | None = None,
    requested: Iterable[str] | None = None,
    validated: bool = False,
) -> Job:
    """Validate ``cfg`` and find what the run continues from; raises :class:`~.checks.ConfigError` (one line).

    ``run_dir`` defaults to the Hydra job's folder (with ``resume`` of a run's last checkpoint: that
    run's folder). A run continues from a checkpoint when ``resume`` names one, or when its own
    folder already holds ``checkpoints/last.pt``; it continues with the backend that wrote it.
    ``requested``: the keys the caller sets (default: those of the Hydra command line); a continued
    run takes those the schema lets change on resume and refuses changes to the others. Without a
    command line, only the budget (``algo.episodes``) and the process settings are taken from ``cfg``. ``validated``:
    ``cfg`` has passed :func:`~drone_torchrl.config.validate` already (a sweeper checked it).

    The job's folder is then this process's (:func:`drone_torchrl.io.run_lock.hold`) until
    :func:`~.trainer.train_jobs` is done with it; a folder another live process trains is refused
    (:class:`~drone_torchrl.io.run_lock.RunFolderBusy`).
    """
    job = _prepare(cfg, run_dir, requested, validated)
    run_lock.hold(job.run_dir)
    for note in preset_notes(HydraConfig.get().runtime.choices) if HydraConfig.initialized() else ():
        _note(note)
    return job


@functools.cache  # once per process, not once per job of a sweep
def _note(note: str) -> None:
    console.warning(f"note: {note}")


def _prepare(
    cfg: DictConfig,
    run_dir: str | Path | None,
    requested: Iterable[str] | None,
    validated: bool,
) -> Job:
    migrations.apply_legacy(cfg)  # old keys from the command line, as today's
    complete(cfg)  # env.disturbance's keys left out, nominal: the run and its saved config see them all
    run_dir = Path(run_dir) if run_dir is not None else _hydra_run_dir()
    keys = command_line_keys() if requested is None else {k.split("=", 1)[0].lstrip("+~") for k in requested}
    if keys is not None:  # an old key that picked the implementation asks for a backend
        legacy = {k for k in keys if k.startswith(f"{migrations.LEGACY}.")}
        picked = {f"{migrations.LEGACY}.{k}" for k in migrations.REPLACED} & legacy
        keys = (keys - legacy) | ({"backend"} if picked else set())
    location = cfg.resume
    if location is None:
        if run_dir is None:
            raise ConfigError("no run folder: pass run_dir or run inside a Hydra app")
        if not (run_dir / CHECKPOINT_DIR / LAST).is_file():
            if not validated:
                validate(cfg)
            return Job(cfg, run_dir)
        location = run_dir
    path, checkpoint = open_agent("resume", location, cfg.agent)
    # An agent of a population run (open_agent refuses agent=K for any other checkpoint) continues
    # in a folder of its own: a fork of the population.
    of_population = cfg.agent is not None
    saved = run_config(checkpoint["config"])
    requested = cfg.backend if keys is not None and "backend" in keys else None
    if requested is not None and requested != checkpoint["backend"]:
        raise ConfigError(
            f"backend={requested!r} cannot continue {path}: it was written by backend={checkpoint['backend']!r}"
        )
    _refuse_changes(cfg, saved, keys, path)
    with open_dict(saved):
        for key, value in leaves(cfg).items():
            rule = resume_rule(key)
            if rule == PROCESS or (rule == BUDGET if keys is None else rule != KEPT and _on(key, keys)):
                OmegaConf.update(saved, key, value, force_add=True)
        saved.backend = checkpoint["backend"]
    validate(saved)
    check_networks("resume", path, checkpoint, saved)
    done = checkpoint["episodes_done"]
    if checkpoint["final"] is None and saved.algo.episodes < done:
        raise ConfigError.of(
            "algo.episodes", saved.algo.episodes, f">= {done}: {path} has already trained {done} episodes"
        )
    if is_last_of_its_run(path) and not of_population:
        return Job(saved, run_dir_of(path), checkpoint)
    # A fork: continue from an earlier point of the parent run, in a folder of its own.
    fork_dir, parent = run_dir, run_dir_of(path)
    if fork_dir is None:
        raise ConfigError(
            f"resume={cfg.resume!r} is not the run's {LAST}: it continues as a fork and needs a new run folder"
        )
    # A new or empty folder (the Hydra job's holds its record, log and lock): never another run's,
    # nor the parent's.
    check_fork_folder(fork_dir, cfg.resume, HYDRA_ENTRIES)
    console.info(
        f"resume: {path.name} (episode {checkpoint['episodes_done']}) is not the last checkpoint of {parent}; "
        f"continuing as a fork in {fork_dir} (the original run is left as it is)",
        **about(fork_dir),
    )
    # A fork has not finished, whatever its parent did after the checkpoint, and its best.pt is the
    # best of its own evaluations (its folder has none of the parent's checkpoints). A population's
    # episodes are not copied (they are in its Parquet parts, not an episodes.csv).
    forked = {**checkpoint, "final": None, "best_eval_return": -math.inf}
    return Job(saved, fork_dir, forked, None if of_population else parent)


_UNSET = object()


def _on(key: str, keys: set[str]) -> bool:
    """Whether the command line sets ``key`` (directly, or a list/dict above it)."""
    return any(key == k or key.startswith(f"{k}.") for k in keys)


def _refuse_changes(cfg: DictConfig, saved: DictConfig, keys: set[str] | None, path: Path) -> None:
    """Raise :class:`~.checks.ConfigError` naming every key the command line changes in a continued run.

    Only keys set on the command line count (the config's defaults are not a request). A group
    choice such as ``experiment=...`` or ``logger=csv`` may set any key: then also each key whose
    value differs from the config composed without the command line's overrides (with the run's
    own plug-ins, :func:`~drone_torchrl.command_line.resumed_plugins`), the keys the choice set.
    """
    if keys is None:
        return
    by_groups: set[str] = set()
    if any(k in group_names() for k in keys):
        baseline = composed_leaves(implied_choices())
        by_groups = {key for key, value in leaves(cfg).items() if baseline.get(key, _UNSET) != value}
    changed = kept_changes(saved, cfg, lambda key: key != "backend" and (key in by_groups or _on(key, keys)))
    if changed:
        raise ConfigError(
            f"resume: {path} was trained with other values ({'; '.join(changed)}); a continued run keeps its "
            "hyper-parameters and logger (only algo.episodes, logger.* but logger.backend, exp_name, project and entity, checkpoint.*, "
            "eval.every_episodes, eval.video, eval.stop_return, eval.rollback_drop "
            "and process settings may change): drop those overrides or start a new run"
        )


def kept_changes(saved: Any, cfg: DictConfig, asked: Callable[[str], bool]) -> list[str]:
    """``key saved -> now`` of each key that ``asked`` picks, a continued run keeps and ``cfg`` changes.

    ``saved``: the checkpoint's config; the keys kept are the schema's ``on_resume`` KEPT ones.
    """
    old = leaves(saved)
    return [
        f"{key} {old.get(key)!r} -> {value!r}"
        for key, value in leaves(cfg).items()
        if asked(key) and resume_rule(key) == KEPT and old.get(key) != value
    ]


def group_key(cfg: DictConfig) -> str:
    """The key that groups jobs into one population: their configs but for per-agent keys.

    The per-agent keys are the schema's ``per_agent`` ones.
    """
    skip = {*per_agent_keys(), "resume", "progress"}
    return repr([(key, value) for key, value in leaves(cfg).items() if key not in skip])


# ---------------------------------------------------------------------------------------- job status


def record_failure(run_dir: Path, error: BaseException) -> str:
    """Write the traceback into ``<run>/FAILED.txt``; returns the one-line reason.

    Nothing is written into a folder another process owns (:class:`~drone_torchrl.io.run_lock.RunFolderBusy`),
    and a disk that refuses ``FAILED.txt`` too leaves the reason to the caller's one line.
    """
    reason = f"{type(error).__name__}: {error}"
    if isinstance(error, run_lock.RunFolderBusy):
        return reason
    with contextlib.suppress(OSError):
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / FAILED_FILE).write_text("".join(traceback.format_exception(error)))
    return reason


def job_status(job_dir: Path) -> tuple[str, str]:
    """``("finished" | "failed" | "unfinished", detail)`` of one job folder (never raises for a bad file)."""
    failed = job_dir / FAILED_FILE
    if failed.is_file():
        text = failed.read_text(encoding="utf-8", errors="replace")  # a damaged file still says failed
        lines = [line for line in text.splitlines() if line.strip()]
        return "failed", lines[-1] if lines else "unknown error"
    last = job_dir / CHECKPOINT_DIR / LAST
    if not last.is_file():
        return "unfinished", "no checkpoint"
    try:
        ckpt = load_checkpoint(last)
    except CheckpointError as err:
        return "unfinished", f"unreadable checkpoint: {err}"
    if is_population(ckpt):
        finished = sum(final is not None for final in ckpt["final"])
        failed = sum(failure is not None for failure in ckpt["failure"])
        detail = f"population of {len(ckpt['final'])} agents: {finished} finished, {failed} failed"
        return ("finished" if finished + failed == len(ckpt["final"]) else "unfinished"), detail
    episodes = ckpt["episodes_done"]
    if ckpt["final"] is not None:
        return (
            "finished",
            f"{episodes} episodes, final running-mean return {ckpt['final']['final_return']:.1f}",
        )
    return "unfinished", f"{episodes} episodes so far"


def this_command() -> str:
    """This ``drone-train`` command line, for the shell: a sweep's is what continues it."""
    return shlex.join(["drone-train", *sys.argv[1:]])


def sweep_jobs(sweep_dir: Path) -> list[Path]:
    """Job folders of a sweep: those holding Hydra's ``.hydra/`` record."""
    return sorted(
        p.parent for p in Path(sweep_dir).glob("**/.hydra") if p.is_dir() and p.parent != Path(sweep_dir)
    )


def next_steps(folder: Path, sweep: bool = False) -> str:
    """The commands that look at what a finished command made in ``folder``, one per line.

    A run: TensorBoard on its folder (when it holds event files) and ``drone-eval`` on its last
    checkpoint; a sweep (``sweep``): ``drone-report`` and TensorBoard on the sweep's folder. The
    paths are relative to the current folder when inside it, quoted for the shell where needed.
    """
    folder = Path(folder).absolute()
    shown = folder.relative_to(Path.cwd()) if folder.is_relative_to(Path.cwd()) else folder
    lines = ["next steps:"]
    if sweep:
        lines.append(f"  drone-report {shlex.quote(str(shown))}")
    if next(folder.rglob("events.out.tfevents.*"), None) is not None:
        lines.append(f"  tensorboard --logdir {shlex.quote(str(shown))}")
    if not sweep:
        lines.append(f"  drone-eval {shlex.quote(f'checkpoint={shown / CHECKPOINT_DIR / LAST}')}")
    return "\n".join(lines)


def sweep_summary(sweep_dir: Path) -> str:
    """Which jobs of a sweep finished, failed (and why) or are unfinished, and the next steps: the end-of-sweep text."""
    sweep_dir = Path(sweep_dir)
    rows = [(job.relative_to(sweep_dir), *job_status(job)) for job in sweep_jobs(sweep_dir)]
    counts = {s: sum(1 for _, status, _ in rows if status == s) for s in ("finished", "failed", "unfinished")}
    lines = [f"\nsweep {sweep_dir}: " + ", ".join(f"{n} {s}" for s, n in counts.items())]
    lines += [f"  [{status}] {name}: {detail}" for name, status, detail in rows]
    if counts["failed"]:
        lines.append(
            f"  failed jobs keep their traceback in <job>/{FAILED_FILE}; re-run the same command to retry them"
        )
    lines.append(next_steps(sweep_dir, sweep=True))
    return "\n".join(lines)


class SweepSummary(Callback):
    """Prints the sweep summary and next steps at the end of a multirun, and exits non-zero if a job failed.

    Launchers that report a failed job to Hydra as failed (``hydra/launcher=fused``) make Hydra stop
    before this callback; that launcher prints the summary itself.
    """

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Print the sweep's summary; exit non-zero naming how many jobs failed."""
        sweep_dir = Path(config.hydra.sweep.dir)
        print(sweep_summary(sweep_dir))
        failed = [job for job in sweep_jobs(sweep_dir) if (job / FAILED_FILE).is_file()]
        if failed:
            sys.exit(f"drone-train: {len(failed)} job(s) failed")
