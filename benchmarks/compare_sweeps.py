"""Do two sweeps of the same settings end alike? Per setting: median final return and fraction of
seeds in the zone of each, and the difference with its bootstrap interval.

    python benchmarks/compare_sweeps.py multirun/before multirun/after
    python benchmarks/compare_sweeps.py old/lr32 new/lr32 --settings "algo.lr=0.0001" "algo.lr=0.001"
    python benchmarks/compare_sweeps.py multirun/lr32 multirun/one_lr_zone --pair "algo.lr=5e-05" all

Made to check a change of engine that is allowed to change float rounding (and so each seed's
run) but not the statistics: the sweeps' runs are read by ``drone-report``'s reader, each run's
final value is its last running mean over ``drone_torchrl.episodes.RUNNING_MEAN_WINDOW`` (100) episodes, "in the zone"
is ``drone-report``'s (final return >= 1500 of 3000), and the intervals are percentile-bootstrap
95% intervals of the difference (after - before), resampling each sweep's seeds independently
(10,000 resamples, fixed seed).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from drone_torchrl.episodes import RUNNING_MEAN_WINDOW
from drone_torchrl.report.distribution import (
    BOOTSTRAP_SAMPLES,
    BOOTSTRAP_SEED,
    distribution,
    percentile_tails,
)
from drone_torchrl.report.runs import group_runs, load_runs
from drone_torchrl.report.stats import ZONE_SHARE


def finals(sweep: Path, window: int) -> dict[str, tuple[np.ndarray, float]]:
    """Each setting's final returns and its zone threshold."""
    settings = group_runs(load_runs(sweep))
    return {s.label: (distribution(s, window).final_returns, ZONE_SHARE * s.ceiling) for s in settings}


def bootstrap_difference(before: np.ndarray, after: np.ndarray, statistic, rng) -> tuple[float, float]:
    pick = lambda values: values[rng.integers(0, values.size, (BOOTSTRAP_SAMPLES, values.size))]  # noqa: E731
    diffs = statistic(pick(after)) - statistic(pick(before))
    low, high = np.percentile(diffs, percentile_tails())
    return float(low), float(high)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--settings", nargs="*", help="setting labels to compare (default: all in both)")
    parser.add_argument(
        "--pair",
        nargs=2,
        action="append",
        metavar=("BEFORE", "AFTER"),
        help="compare setting BEFORE of the first sweep with setting AFTER of the second (labels differ: "
        "a sweep of one setting labels it 'all'); repeatable",
    )
    args = parser.parse_args()
    window = RUNNING_MEAN_WINDOW
    old, new = finals(args.before, window), finals(args.after, window)
    if args.pair:
        missing = [b for b, _ in args.pair if b not in old] + [a for _, a in args.pair if a not in new]
        if missing:
            parser.error(f"no such setting: {', '.join(missing)}")
        new = {b: new[a] for b, a in args.pair}
    labels = [label for label in old if label in new and (not args.settings or label in args.settings)]
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    median = lambda x: np.median(x, axis=-1)  # noqa: E731
    print(
        "| setting | seeds | median final return, before | after | difference [95% CI] "
        "| in the zone, before | after | difference [95% CI] |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for label in labels:
        (a, zone), (b, _) = old[label], new[label]
        in_zone = lambda x, zone=zone: (x >= zone).mean(axis=-1)  # noqa: E731
        lo, hi = bootstrap_difference(a, b, median, rng)
        zlo, zhi = bootstrap_difference(a, b, in_zone, rng)
        print(
            f"| {label} | {a.size} / {b.size} | {np.median(a):.0f} | {np.median(b):.0f} "
            f"| {np.median(b) - np.median(a):+.0f} [{lo:+.0f}, {hi:+.0f}] "
            f"| {(a >= zone).sum()}/{a.size} | {(b >= zone).sum()}/{b.size} "
            f"| {in_zone(b) - in_zone(a):+.2f} [{zlo:+.2f}, {zhi:+.2f}] |"
        )


if __name__ == "__main__":
    main()
