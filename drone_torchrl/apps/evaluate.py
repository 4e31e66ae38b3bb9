"""``drone-eval``: fly a trained policy (or the PD controller) on seeded episodes and report.

drone-eval checkpoint=outputs/<date>/<run>          # the run's last checkpoint
drone-eval checkpoint=<run>/checkpoints/best.pt episodes=20
drone-eval                                          # the PD hover controller alone
drone-eval env.max_thrust=1.0                       # ... with bounded thrust
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from drone_torchrl import command_line
from drone_torchrl.apps.commands import start
from drone_torchrl.config import ConfigError, config_dir
from drone_torchrl.io.folders import remove_if_untouched
from drone_torchrl.io.storage import StorageError


@hydra.main(config_path=config_dir(), config_name="eval", version_base="1.3")
def main(cfg: DictConfig) -> None:
    """The Hydra app of ``drone-eval``: evaluate as ``cfg`` says; a refused config exits with one line."""
    from drone_torchrl.comparison import run_eval

    try:
        run_eval(cfg)
    except (ConfigError, StorageError) as err:
        # Refused, or its plot or video refused by the disk: the folder keeps no half of the output.
        remove_if_untouched(Path(HydraConfig.get().runtime.output_dir))
        sys.exit(f"drone-eval: error: {err}")


def run() -> None:
    """Console entry point ``drone-eval``: check the command line, then run the Hydra app.

    The command line's keys and the folder Hydra will write are checked.
    """
    start("drone-eval")
    command_line.check("drone-eval")
    main()


if __name__ == "__main__":
    run()
