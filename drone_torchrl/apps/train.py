"""``drone-train``: train an agent (REINFORCE, REINFORCE+, PPO, A2C or SAC) on the 2D drone, with Hydra (``conf/``).

drone-train                                  # the paper: alpha 1e-4, gamma 0.99, 6000 episodes
drone-train algo.lr=3e-4 seed=1              # any key from the command line
drone-train experiment=bounded               # positive thrust only (TanhNormal, max_thrust 1)
drone-train resume=outputs/<date>/<run>      # continue an interrupted run
drone-train -m seed=0,1,2,3 hydra/launcher=fused   # four agents trained as one population
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from drone_torchrl import command_line
from drone_torchrl.apps.commands import start
from drone_torchrl.config import ConfigError, config_dir
from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, LAST, CheckpointError
from drone_torchrl.io.folders import remove_if_untouched
from drone_torchrl.io.storage import StorageError
from drone_torchrl.io.streams import console, guard_broken_pipes, keep_run_logs
from drone_torchrl.training.population_record import AGENTS_TABLE
from drone_torchrl.training.run import TrainingDiverged
from drone_torchrl.training.signals import TrainingStopped

# The shell's convention for a command stopped by Ctrl-C (128 + SIGINT).
EXIT_INTERRUPTED = 130


@hydra.main(config_path=config_dir(), config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    """The Hydra app of ``drone-train``: train a run or a sweep's job; returns the job's final metric."""
    from drone_torchrl.training.trainer import train

    guard_broken_pipes()  # also in a launcher's worker process
    job_dir = Path(HydraConfig.get().runtime.output_dir)
    if HydraConfig.get().mode != RunMode.MULTIRUN:
        try:
            return train(cfg, show_next_steps=True)
        except (ConfigError, CheckpointError, TrainingDiverged) as err:
            sys.exit(f"drone-train: error: {err}")
        except StorageError as err:
            sys.exit(f"drone-train: error: {err}; {_continue_hint(cfg, job_dir)}")
        except KeyboardInterrupt:
            console.warning(f"drone-train: interrupted; {_continue_hint(cfg, job_dir)}")
            sys.exit(EXIT_INTERRUPTED)
        finally:
            # Refused, or resumed in the run's own folder: Hydra's folder for this call holds nothing.
            remove_if_untouched(job_dir)
    try:
        return train(cfg)
    except Exception as err:
        # The job is recorded in <job>/FAILED.txt and reported to Hydra as FAILED (its callbacks and
        # launchers see the real status). The default sweeper (hydra/sweeper=population) goes on
        # with the other jobs; the end-of-sweep summary (training.jobs.SweepSummary) lists it and
        # exits non-zero.
        from drone_torchrl.training.jobs import FAILED_FILE, record_failure

        if not (job_dir / FAILED_FILE).is_file():
            record_failure(job_dir, err)
        console.error(f"drone-train: job failed: {type(err).__name__}: {err}")
        raise


def _continue_hint(cfg: DictConfig, job_dir: Path) -> str:
    """How to go on with the run: ``resume``'s (a run folder or a checkpoint), else ``job_dir``."""
    run = Path(cfg.resume) if cfg.resume else job_dir
    if run.is_file() or (run / CHECKPOINT_DIR / LAST).is_file():
        return f"the last checkpoint is intact; continue with: drone-train resume={run}"
    return "no checkpoint was written yet; start it again"


def _stopped(stop: TrainingStopped) -> None:
    """The one line of a run stopped by SIGTERM/SIGUSR1, and its exit code (128 + the signal)."""
    name = stop.args[0]
    if len(stop.run_dirs) == 1 and not (Path(stop.run_dirs[0]) / AGENTS_TABLE).is_file():
        hint = f"continue with: drone-train resume={stop.run_dirs[0]}"
    else:
        # Several runs, or a population run (hydra/launcher=population): the sweep's command again.
        hint = "run the same command again to continue them (each job resumes from its checkpoint)"
    print(f"drone-train: {name}; checkpoint written for {len(stop.run_dirs)} run(s); {hint}", file=sys.stderr)
    sys.exit(stop.exit_code)


def register_plugins() -> None:
    """Register our Hydra launchers and sweeper with Hydra.

    Hydra finds plugins by listing the hydra_plugins folders; an editable install's import hook is
    not a folder, so ours are registered explicitly (harmless for a normal install).
    """
    from hydra.core.plugins import Plugins

    from hydra_plugins.drone_torchrl_launcher import slurm_launcher
    from hydra_plugins.drone_torchrl_launcher.population_launcher import PopulationLauncher
    from hydra_plugins.drone_torchrl_launcher.population_sweeper import PopulationSweeper

    # The SLURM ones come with the submitit extra.
    for plugin in [PopulationLauncher, PopulationSweeper, *slurm_launcher.PLUGINS]:
        Plugins.instance().register(plugin)


def run() -> None:
    """Console entry point: registers our Hydra plug-ins, then runs the Hydra app."""
    start("drone-train")  # output piped into `head` never stops training
    keep_run_logs()  # each run's lines in its train.log, whichever launcher trains it
    register_plugins()
    claimed = command_line.check("drone-train")  # before Hydra writes anything
    try:
        main()
    except KeyboardInterrupt:  # before Hydra started the run (main() handles it once training runs)
        print("drone-train: interrupted before training started", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)
    except TrainingStopped as stop:
        _stopped(stop)
    finally:
        for folder in claimed:  # a refused command leaves no folder of its own behind
            remove_if_untouched(folder)


if __name__ == "__main__":
    run()
