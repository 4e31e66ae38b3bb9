"""``drone-export``: a checkpoint's deterministic policy as a standalone ``torch.export`` file.

drone-export checkpoint=outputs/<date>/<run> output=policy.pt2
drone-export checkpoint=<run>/checkpoints/best.pt output=best.pt2

Load it with plain torch: ``torch.export.load("policy.pt2").module()(observation)``.
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from drone_torchrl import command_line
from drone_torchrl.config import ConfigError, check_command_line, check_keys, config_dir


@hydra.main(config_path=config_dir(), config_name="export", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from drone_torchrl.export import export_policy

    try:
        check_keys(cfg, "export")
        if cfg.checkpoint is None:
            raise ConfigError.of("checkpoint", None, "a checkpoint file or a run folder")
        if not isinstance(cfg.output, str) or not cfg.output:
            raise ConfigError.of("output", cfg.output, "a file path such as policy.pt2")
        print(f"wrote {export_policy(cfg.checkpoint, cfg.output)}")
    except ConfigError as err:
        sys.exit(f"drone-export: error: {err}")


def run() -> None:
    """Console entry point: checks the command line's keys, then runs the Hydra app."""
    command_line.check_flags("drone-export")
    check_command_line("drone-export", "export")
    main()


if __name__ == "__main__":
    run()
