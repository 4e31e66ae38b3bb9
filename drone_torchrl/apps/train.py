"""``drone-train``: REINFORCE on the 2D drone, configured by Hydra (``conf/``).

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

from drone_torchrl.config import ConfigError, check_command_line, config_dir
from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, LAST, CheckpointError
from drone_torchrl.io.folders import remove_if_untouched
from drone_torchrl.training.run import TrainingDiverged

# The shell's convention for a command stopped by Ctrl-C (128 + SIGINT).
EXIT_INTERRUPTED = 130


@hydra.main(config_path=config_dir(), config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    from drone_torchrl.training.trainer import train

    if HydraConfig.get().mode != RunMode.MULTIRUN:
        hydra_dir = Path(HydraConfig.get().runtime.output_dir)
        try:
            return train(cfg)
        except (ConfigError, CheckpointError) as err:
            sys.exit(f"drone-train: error: {err}")
        except TrainingDiverged as err:
            sys.exit(f"drone-train: error: {err}")
        except KeyboardInterrupt:
            run = cfg.resume or hydra_dir
            if cfg.resume or (hydra_dir / CHECKPOINT_DIR / LAST).is_file():
                hint = f"continue from the last checkpoint with: drone-train resume={run}"
            else:
                hint = "no checkpoint was written yet; start it again"
            print(f"drone-train: interrupted; {hint}", file=sys.stderr)
            sys.exit(EXIT_INTERRUPTED)
        finally:
            # Refused, or resumed in the run's own folder: Hydra's folder for this call holds nothing.
            remove_if_untouched(hydra_dir)
    job_dir = Path(HydraConfig.get().runtime.output_dir)
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
        print(f"drone-train: job failed: {type(err).__name__}: {err}", file=sys.stderr)
        raise


def run() -> None:
    """Console entry point: registers the population launcher, then runs the Hydra app."""
    from hydra.core.plugins import Plugins

    from hydra_plugins.drone_torchrl_launcher import slurm_launcher
    from hydra_plugins.drone_torchrl_launcher.fused_launcher import FusedLauncher
    from hydra_plugins.drone_torchrl_launcher.population_sweeper import PopulationSweeper

    # Hydra finds plugins by listing the hydra_plugins folders; an editable install's import hook
    # is not a folder, so register ours explicitly (harmless for a normal install).
    Plugins.instance().register(FusedLauncher)
    Plugins.instance().register(PopulationSweeper)
    if hasattr(slurm_launcher, "SlurmLauncher"):  # with the submitit extra
        Plugins.instance().register(slurm_launcher.SlurmLauncher)
        Plugins.instance().register(slurm_launcher.SlurmPopulationLauncher)
    try:
        check_command_line("drone-train", "config")
        main()
    except KeyboardInterrupt:  # before Hydra started the run (main() handles it once training runs)
        print("drone-train: interrupted before training started", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)


if __name__ == "__main__":
    run()
