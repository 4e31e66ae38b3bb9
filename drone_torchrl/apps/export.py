"""``drone-export``: a checkpoint's deterministic policy as a standalone file.

The file is a ``torch.export`` program (``.pt2``) or an ONNX model (``.onnx``, the ``onnx`` extra).

drone-export checkpoint=outputs/<date>/<run>                     # <run>/export/last.pt2
drone-export checkpoint=outputs/<date>/<run> format=onnx         # <run>/export/last.onnx
drone-export checkpoint=<run>/checkpoints/best.pt                # <run>/export/best.pt2
drone-export checkpoint=<population run> agent=3                 # <run>/export/last_agent3.pt2
drone-export checkpoint=outputs/<date>/<run> output=policy.onnx  # anywhere else: output=<file>

Load a .pt2 with plain torch: ``torch.export.load("policy.pt2").module()(observation)``; an .onnx
with onnxruntime: ``InferenceSession("policy.onnx").run(None, {"observation": observation})``.
It prints the file's largest difference from the actor (checked before it is written) and the
latency of one forward pass (batch 1) in its runtime and in eager torch.
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from drone_torchrl import command_line
from drone_torchrl.apps.commands import start
from drone_torchrl.config import ConfigError, config_dir
from drone_torchrl.io.storage import StorageError
from drone_torchrl.training.signals import Interrupted, interrupt_on_signals


@hydra.main(config_path=config_dir(), config_name="export", version_base="1.3")
def main(cfg: DictConfig) -> None:
    """The Hydra app of ``drone-export``: export, check and time the policy; refusals exit in one line."""
    from drone_torchrl import export

    try:
        with interrupt_on_signals():  # SIGTERM while writing: no partial or temporary file left
            exported = export.run_export(cfg)
    except (ConfigError, export.ExportError, StorageError) as err:
        sys.exit(f"drone-export: error: {err}")
    except Interrupted as stop:
        print(f"drone-export: {stop}; nothing written", file=sys.stderr)
        sys.exit(stop.exit_code)
    print(f"wrote {exported.path}")
    print(
        f"checked: largest difference from the actor {exported.max_abs_diff:.2g} on {exported.checked} "
        f"observations (tolerance {export.TOLERANCE:g})"
    )
    times = export.latencies(export.forward_passes(exported.policy, {exported.format: exported.path}))
    figures = ", ".join(f"{name} {us:.1f} us" for name, us in times.items())
    runtime = export.RUNTIMES[exported.format]
    print(
        f"latency of one forward pass, batch 1, one thread (median of {export.LATENCY_REPEATS} x "
        f"{export.LATENCY_CALLS} calls): {figures}; {runtime} / eager {times[runtime] / times['eager torch']:.2f}"
    )


def run() -> None:
    """Console entry point: checks the command line's keys, then runs the Hydra app."""
    start("drone-export")
    command_line.check("drone-export")
    main()


if __name__ == "__main__":
    run()
