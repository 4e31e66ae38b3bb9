"""Latency of one forward pass of an exported policy: onnxruntime vs the .pt2 vs eager torch.

    python benchmarks/export_latency.py                       # fresh paper and bounded policies, batch 1
    python benchmarks/export_latency.py --checkpoint outputs/<date>/<time> --batches 1 64 4096

Each policy is written as drone-export writes it (drone_torchrl.export.program_bytes: a torch.export
program, and the ONNX model converted from it) into a temporary folder, checked against its actor,
and timed on one thread, in turns, per batch size:

* **onnxruntime**: ``InferenceSession.run`` of the ``.onnx`` (CPU provider, one intra-op thread),
  numpy in and out;
* **torch.export**: the ``.pt2`` loaded with ``torch.export.load(...).module()``;
* **eager torch**: the same policy module (drone_torchrl.export.DeterministicPolicy), not exported;
* **TorchRL actor**: the ``ProbabilisticActor`` drone-eval flies, TensorDict in and out, its
  deterministic action and the env's clamp: what the files replace.

Every figure is the median over ``--repeats`` rounds of the mean time of one call in ``--calls``
calls (the runtimes take turns within a round, so a slow spell of a shared machine falls on all of
them); the ratio is to eager torch timed in the same run. Needs the onnx extra.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from drone_torchrl import export
from drone_torchrl.config import config_dir
from drone_torchrl.envs.dynamics import STATE_DIM
from drone_torchrl.modules.factory import build_policy

# The fresh policies timed without --checkpoint: the paper's and experiment=bounded's.
PRESETS = {"paper (Normal)": [], "bounded (TanhNormal)": ["experiment=bounded"]}
EAGER = "eager torch"


def policies(checkpoint: str | None) -> dict[str, tuple[export.DeterministicPolicy, Callable]]:
    """name -> (the exported policy, the commands of its TorchRL actor on an observation batch)."""
    if checkpoint is not None:
        policy, actor, path = export.load_policy(checkpoint)
        return {path.name: (policy, lambda obs: export.actor_commands(actor, obs, policy.max_thrust))}
    out = {}
    for name, overrides in PRESETS.items():
        with initialize_config_dir(config_dir(), version_base="1.3"):
            cfg = compose("config", overrides=overrides)
        policy, actor = export.policy_and_actor(
            build_policy(cfg, seed=0), cfg.model.distribution, cfg.env.max_thrust
        )
        out[name] = (
            policy,
            lambda obs, actor=actor, a=cfg.env.max_thrust: export.actor_commands(actor, obs, a),
        )
    return out


def time_in_turns(passes: dict[str, Callable[[], object]], repeats: int, calls: int) -> dict[str, float]:
    """Median microseconds per call of each pass, the passes taking turns within each round."""
    per_call: dict[str, list[float]] = {name: [] for name in passes}
    for call in passes.values():
        for _ in range(export.LATENCY_WARMUP):
            call()
    for _ in range(repeats):
        for name, call in passes.items():
            start = time.perf_counter()
            for _ in range(calls):
                call()
            per_call[name].append((time.perf_counter() - start) / calls * export.US_PER_S)
    return {name: statistics.median(times) for name, times in per_call.items()}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--checkpoint", help="a run folder or checkpoint (default: fresh paper and bounded policies)"
    )
    parser.add_argument("--batches", type=int, nargs="+", default=[1])
    parser.add_argument("--repeats", type=int, default=export.LATENCY_REPEATS)
    parser.add_argument("--calls", type=int, default=export.LATENCY_CALLS)
    args = parser.parse_args()
    export.check_onnx_extra()
    import onnxruntime

    rows = []
    observations = export.check_observations()
    with tempfile.TemporaryDirectory() as folder:
        for name, (policy, actor_commands) in policies(args.checkpoint).items():
            files = {}
            for format in ("onnx", "pt2"):
                files[format] = Path(folder) / f"{len(rows)}.{format}"
                files[format].write_bytes(export.program_bytes(policy, format))
            expected = actor_commands(observations)
            diff = max(
                (export.load_program(path, format)(observations) - expected).abs().max().item()
                for format, path in files.items()
            )
            for batch in args.batches:
                passes = export.forward_passes(policy, files, batch)
                observation = torch.tensor([export.HOVER_OBSERVATION]).expand(batch, STATE_DIM).contiguous()
                passes["TorchRL actor"] = lambda obs=observation, run=actor_commands: run(obs)
                with export.one_thread(), torch.inference_mode():
                    times = time_in_turns(passes, args.repeats, args.calls)
                rows += [(name, batch, runtime, us, us / times[EAGER], diff) for runtime, us in times.items()]

    print(
        f"\nCPU, one thread; onnxruntime {onnxruntime.__version__}, torch {torch.__version__}; "
        f"median of {args.repeats} rounds x {args.calls} calls; max |diff|: the files against the actor "
        f"on {len(observations)} observations\n"
    )
    print("| policy | batch | runtime | us / forward pass | x eager torch | max abs diff |")
    print("|---|---|---|---|---|---|")
    for name, batch, runtime, us, ratio, diff in rows:
        print(f"| {name} | {batch} | {runtime} | {us:.1f} | {ratio:.2f} | {diff:.1e} |")


if __name__ == "__main__":
    main()
