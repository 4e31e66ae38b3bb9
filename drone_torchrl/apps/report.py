"""``drone-report``: figures and a summary table of hyper-parameter sweeps (:mod:`drone_torchrl.report`).

drone-report multirun/lr                      # figures + table into multirun/lr/report/
drone-report multirun/lr multirun/gamma       # one report per sweep, each in <sweep>/report/
drone-report multirun/lr --out /tmp/lr --window 50 --return-threshold 2500 --no-pd
drone-report multirun/lr32 multirun/gamma32 --paper-averaging   # also the paper's cumulative averaging
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

from drone_torchrl.io.storage import StorageError, unwritable
from drone_torchrl.io.streams import guard_broken_pipes
from drone_torchrl.report import DEFAULT_RETURN_THRESHOLD

PROG = "drone-report"
EXIT_ERROR = 2


def _checked(kind: type, good: Callable[[Any], bool], expected: str) -> Callable[[str], Any]:
    """An argparse type: ``kind(text)`` if it is ``good``; else argparse's error, in one line."""

    def parse(text: str) -> Any:
        with contextlib.suppress(ValueError):
            if good(value := kind(text)):
                return value
        raise argparse.ArgumentTypeError(f"{text!r} is not allowed; expected {expected}")

    return parse


def _folder(text: str) -> Path:
    # Path("") is the current folder: an empty --out would scatter the report where the command runs.
    if not text.strip():
        raise argparse.ArgumentTypeError(f"{text!r} is not allowed; expected a folder path")
    if (refused := unwritable(text)) is not None:  # before the sweeps are read
        raise argparse.ArgumentTypeError(
            f"{text!r} is not allowed; expected a folder this user can write ({refused})"
        )
    return Path(text)


class _Parser(argparse.ArgumentParser):
    """argparse, with a usage error on one line (like the other commands' errors)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_ERROR, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """``drone-report``'s options from ``argv`` (the command line's if None); bad ones exit 2 in one line."""
    parser = _Parser(
        prog=PROG,
        description="Figures (steps.png, returns.png) and a summary table (summary.md, summary.csv) of sweeps.",
    )
    parser.add_argument("sweeps", nargs="+", type=Path, help="sweep folders, e.g. multirun/lr multirun/gamma")
    parser.add_argument(
        "--out",
        type=_folder,
        help="output folder (default: <sweep>/report; with several sweeps: <out>/<sweep name>)",
    )
    parser.add_argument(
        "--window",
        type=_checked(int, lambda value: value >= 1, "an integer >= 1"),
        help="running-mean window in episodes (default: a run's, the paper's 100)",
    )
    parser.add_argument(
        "--return-threshold",
        type=_checked(float, math.isfinite, "a finite number"),
        default=DEFAULT_RETURN_THRESHOLD,
        help=f"report the first episode the running-mean return reaches this (default {DEFAULT_RETURN_THRESHOLD:g})",
    )
    parser.add_argument("--no-pd", action="store_true", help="skip the PD controller reference line")
    parser.add_argument(
        "--paper-averaging",
        action="store_true",
        help="also redraw the paper's figures as its code averages them (cumulatively over the settings "
        "in the paper's order), next to the per-setting curves: paper_averaging.png",
    )
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    """``drone-report``: one report per sweep folder; exit code 2 with a one-line error if unusable."""
    guard_broken_pipes()  # output piped into `head` is not an unwritable report
    args = parse_args(argv)
    # Imported once the command line is read: they import torch (seconds), which --help does without.
    from drone_torchrl.report import distribution, runs, stats, tables

    try:
        loaded = [runs.load_runs(d) for d in args.sweeps]  # check every folder before any work
        out_dirs = tables.output_dirs(args.sweeps, args.out)
        for out_dir in out_dirs:  # before any figure is drawn
            if (refused := unwritable(out_dir)) is not None:
                raise runs.ReportError(f"cannot write the report into {out_dir}: {refused}")
        if args.paper_averaging:  # every sweep must be one of the paper's grids, before any work
            for sweep_runs in loaded:
                distribution.paper_order(runs.group_runs(sweep_runs))
        for sweep_dir, sweep_runs, out_dir in zip(args.sweeps, loaded, out_dirs, strict=True):
            report = stats.build_report(
                sweep_dir, args.window, args.return_threshold, not args.no_pd, sweep_runs
            )
            paths = tables.write_report(report, out_dir, args.paper_averaging)
            print(tables.format_report(report, figures=False))
            for job, reason in runs.failed_without_episodes(sweep_dir):
                print(f"failed before its first episode (not in the report): {job}: {reason}")
            if args.paper_averaging:
                print(tables.format_paper_averaging_section(report))
            print(f"wrote {', '.join(str(p) for p in paths)}\n")
    except (
        runs.ReportError,
        OSError,
    ) as err:  # StorageError: a figure or table the disk refused, in one line
        # Another OSError: an output folder that cannot be made or written.
        plain = isinstance(err, OSError) and not isinstance(err, StorageError)
        print(f"{PROG}: error: {f'{err.filename}: {err.strerror}' if plain else err}", file=sys.stderr)
        sys.exit(EXIT_ERROR)


if __name__ == "__main__":
    main()
