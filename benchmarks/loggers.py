"""TensorBoard writers timed against each other: the hand-written one, SummaryWriter, TorchRL's logger.

    python benchmarks/loggers.py                                   # under a minute on 2 cores
    python benchmarks/loggers.py --updates 6000 --runs 32 --sweep-updates 6000 --repeats 5

Writes the same scalars, at the same steps and with the same flushes, through

- ``hand-written``: :class:`drone_torchrl.loggers.tb_logger.RunLogger` (``logger=tensorboard``):
  buffered ``log_scalars``, the events encoded by hand, written at each flush;
- ``SummaryWriter``: ``torch.utils.tensorboard.SummaryWriter.add_scalar`` per scalar (its writer
  thread, the file held open), ``flush()`` at the same points, ``close()`` at the end;
- ``TorchRL``: ``torchrl.record.loggers.tensorboard.TensorboardLogger.log_scalar`` per scalar (a
  ``SummaryWriter`` inside), flushed and closed alike;

for three cases, the shapes the run records log (drone_torchrl/loggers/__init__.py:log_update,
drone_torchrl/training/population_record.py:PopulationRecord.after_update):

- ``single run``: a default ``drone-train`` run, one episode an update: per update its episode's 4
  scalars, the 5 termination-cause counts, 3 training metrics and 2 running means (14 scalars),
  flushed at every checkpoint (``checkpoint.every_episodes=250``);
- ``population``: a population run (``hydra/launcher=population``) writes one event file for all
  its agents, the summary of each update (agents alive, 3 return quantiles, the best return and
  agent: 6 scalars), whatever the number of agents (their rows go to Parquet); flushed alike;
- ``fused sweep``: ``hydra/launcher=fused`` trains ``--runs`` jobs in one process, each with its own
  run folder and logger, each logging as the single run does.

The writers alternate within each repeat (their order rotates); the table has the median seconds
over the repeats, the ratio to the hand-written writer's median, and the event files' size. After
the timed repeats, every writer's files are read back with tensorboard's ``EventAccumulator`` and
compared: the same tags, steps and values (float32) as the hand-written writer's. Last, the import
time of each writer's modules, in a fresh ``python -c`` each (median of ``--import-repeats``), after
:data:`BASE_IMPORT` (what every ``drone-train`` imports anyway, timed too).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from drone_torchrl.envs.dynamics import TerminationCause
from drone_torchrl.loggers import EPISODE_SCALARS

WRITERS = ("hand-written", "SummaryWriter", "TorchRL")
CASES = ("single run", "population", "fused sweep")

SINGLE_TAGS = (
    *(f"episode/{k}" for k in EPISODE_SCALARS),
    *(f"episode/termination_cause/{c.name}" for c in TerminationCause),
    "train/loss",
    "train/grad_norm",
    "policy/std_mean",
    "train/running_mean_return",
    "train/running_mean_length",
)
POPULATION_TAGS = (
    "population/alive",
    "population/return_q10",
    "population/return_q50",
    "population/return_q90",
    "population/best_return",
    "population/best_agent",
)
# What each writer imports, timed after what every ``drone-train`` imports anyway: the run record,
# which makes the loggers (torch, tensordict and torchrl with it).
BASE_IMPORT = "import drone_torchrl.training.run"
IMPORTS = {
    "hand-written": "import drone_torchrl.loggers.tb_logger, tensorboard.compat.proto.event_pb2",
    "SummaryWriter": "import torch.utils.tensorboard",
    "TorchRL": "import torchrl.record.loggers.tensorboard",
}

# One update's scalars: (tag, value) pairs; the step is the update's count of episodes.
Update = list[tuple[str, float]]


def updates(tags: tuple[str, ...], count: int, seed: int) -> list[Update]:
    """``count`` updates of ``tags``, values drawn once so every writer logs the same numbers."""
    values = np.random.default_rng(seed).normal(size=(count, len(tags))).astype(np.float32)
    return [list(zip(tags, row.tolist(), strict=True)) for row in values]


class Writer:
    """One run's logger of one kind: ``log`` an update, ``flush``, ``close``."""

    def __init__(self, kind: str, folder: Path) -> None:
        if kind == "hand-written":
            from drone_torchrl.loggers.tb_logger import RunLogger

            logger = RunLogger("tensorboard", folder)
            self.log = lambda scalars, step: logger.log_scalars((t, v, step) for t, v in scalars)
            self.flush = self.close = logger.flush
        elif kind == "SummaryWriter":
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(str(folder / "tensorboard"))

            def log(scalars: Update, step: int) -> None:
                for tag, value in scalars:
                    writer.add_scalar(tag, value, step)

            self.log, self.flush, self.close = log, writer.flush, writer.close
        elif kind == "TorchRL":
            from torchrl.record.loggers.tensorboard import TensorboardLogger

            torchrl = TensorboardLogger("tensorboard", str(folder))

            def log(scalars: Update, step: int) -> None:
                for tag, value in scalars:
                    torchrl.log_scalar(tag, value, step)

            self.log, self.flush, self.close = log, torchrl.experiment.flush, torchrl.experiment.close
        else:
            raise ValueError(f"writer {kind!r}: one of {', '.join(WRITERS)}")


def write(kind: str, folders: list[Path], data: list[Update], flush_every: int) -> None:
    """Each of ``folders`` a run logging ``data`` (one update a step, a flush every ``flush_every``), interleaved."""
    writers = [Writer(kind, folder) for folder in folders]
    for n, scalars in enumerate(data, 1):
        for writer in writers:
            writer.log(scalars, n)
        if n % flush_every == 0:
            for writer in writers:
                writer.flush()
    for writer in writers:
        writer.close()


def read_back(folder: Path) -> dict[str, list[tuple[int, float]]]:
    """``{tag: [(step, value), ...]}`` of the event files in ``folder/tensorboard``."""
    from tensorboard.backend.event_processing.event_accumulator import SCALARS, EventAccumulator

    events = EventAccumulator(str(folder / "tensorboard"), size_guidance={SCALARS: 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()[SCALARS]}


def size(folders: list[Path]) -> int:
    """Bytes of the event files in ``folders``."""
    return sum(f.stat().st_size for folder in folders for f in (folder / "tensorboard").glob("events.*"))


def import_time(statement: str, repeats: int) -> tuple[float, float]:
    """Median seconds of :data:`BASE_IMPORT` and then of ``statement``, each in a fresh interpreter."""
    code = (
        f"import time; t0 = time.perf_counter(); {BASE_IMPORT}; t1 = time.perf_counter(); {statement}; "
        "print(t1 - t0, time.perf_counter() - t1)"
    )
    runs = [
        [
            float(x)
            for x in subprocess.run(
                [sys.executable, "-c", code], check=True, capture_output=True, text=True
            ).stdout.split()
        ]
        for _ in range(repeats)
    ]
    return statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--updates", type=int, default=1000, help="updates of the single run and population")
    parser.add_argument("--runs", type=int, default=8, help="runs of the fused sweep")
    parser.add_argument("--sweep-updates", type=int, default=250, help="updates of each sweep run")
    # checkpoint.every_episodes' default: the run records flush at every checkpoint.
    parser.add_argument("--flush-every", type=int, default=250, help="updates between flushes")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (median)")
    parser.add_argument(
        "--import-repeats", type=int, default=3, help="fresh interpreters per import (0: none)"
    )
    parser.add_argument("--writers", nargs="+", default=list(WRITERS), choices=WRITERS)
    args = parser.parse_args(argv)
    for key in ("updates", "runs", "sweep_updates", "flush_every", "repeats", "import_repeats"):
        least = 0 if key == "import_repeats" else 1
        if getattr(args, key) < least:
            parser.error(f"--{key.replace('_', '-')} {getattr(args, key)}: at least {least}")
    if "hand-written" not in args.writers:
        parser.error("--writers: the hand-written writer is the baseline the ratios need")

    single = updates(SINGLE_TAGS, args.updates, seed=0)
    cases: dict[str, tuple[int, list[Update]]] = {
        "single run": (1, single),
        "population": (1, updates(POPULATION_TAGS, args.updates, seed=1)),
        "fused sweep": (args.runs, single[: args.sweep_updates]),
    }
    times: dict[tuple[str, str], list[float]] = {}
    sizes: dict[tuple[str, str], int] = {}
    with tempfile.TemporaryDirectory(prefix="loggers-") as scratch:
        root = Path(scratch)
        for kind in args.writers:  # imports and first calls out of the timing (imports: timed below)
            write(kind, [root / "warm-up" / kind], single[:1], args.flush_every)
        for repeat in range(args.repeats):
            order = args.writers[repeat % len(args.writers) :] + args.writers[: repeat % len(args.writers)]
            for case, (runs, data) in cases.items():
                for kind in order:
                    out = root / f"{repeat}" / case.replace(" ", "_") / kind
                    folders = [out / f"run_{i}" for i in range(runs)]
                    start = time.perf_counter()
                    write(kind, folders, data, args.flush_every)
                    times.setdefault((kind, case), []).append(time.perf_counter() - start)
                    sizes[kind, case] = size(folders)
        # The last repeat's files, every writer's against the hand-written writer's.
        last = root / f"{args.repeats - 1}"
        same: dict[tuple[str, str], bool] = {}
        for case, (runs, data) in cases.items():
            expected_tags = {tag for tag, _ in data[0]}
            for i in range(runs):
                base = read_back(last / case.replace(" ", "_") / "hand-written" / f"run_{i}")
                assert set(base) == expected_tags and all(len(v) == len(data) for v in base.values()), (
                    f"{case}, run {i}: the hand-written writer's events read back incomplete"
                )
                for kind in args.writers:
                    got = read_back(last / case.replace(" ", "_") / kind / f"run_{i}")
                    same[kind, case] = same.get((kind, case)) is not False and got == base

    print("| writer | case | scalars | median s | ratio to hand-written | file size KiB | reads back equal |")
    print("|---|---|---|---|---|---|---|")
    for case, (runs, data) in cases.items():
        scalars = runs * len(data) * len(data[0])
        base = statistics.median(times["hand-written", case])
        for kind in args.writers:
            median = statistics.median(times[kind, case])
            print(
                f"| {kind} | {case} | {scalars:,} | {median:.3g} | {median / base:.1f}x | "
                f"{sizes[kind, case] / 1024:.0f} | {'yes' if same[kind, case] else 'NO'} |"
            )
    if args.import_repeats:
        print()
        print(f"| import, after `{BASE_IMPORT}` | median s | the base import's median s |")
        print("|---|---|---|")
        for kind in args.writers:
            base_s, own_s = import_time(IMPORTS[kind], args.import_repeats)
            print(f"| {kind}: `{IMPORTS[kind]}` | {own_s:.2f} | {base_s:.2f} |")
    if not all(same.values()):
        sys.exit("some writer's events did not read back equal to the hand-written writer's")


if __name__ == "__main__":
    main()
