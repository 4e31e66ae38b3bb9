"""Sweep bookkeeping: each job records how it ended, and the sweep ends with a summary of all jobs.

Hydra cannot resume a multirun by itself. Every job here is idempotent instead: its folder is named
by its overrides inside a fixed sweep folder, and a job whose folder already holds a checkpoint
continues from it (finished jobs return at once), so running the same sweep command again skips
finished jobs and resumes the rest.
"""

from __future__ import annotations

import traceback
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from drone_torchrl.checkpoint import CHECKPOINT_DIR, LAST, load_checkpoint

FAILED_FILE = "FAILED.txt"


def record_failure(run_dir: Path, error: BaseException) -> str:
    """Write the traceback into ``<run>/FAILED.txt``; returns the one-line reason."""
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / FAILED_FILE).write_text("".join(traceback.format_exception(error)))
    return f"{type(error).__name__}: {error}"


def clear_failure(run_dir: Path) -> None:
    (run_dir / FAILED_FILE).unlink(missing_ok=True)


def job_status(job_dir: Path) -> tuple[str, str]:
    """``("finished" | "failed" | "unfinished", detail)`` of one job folder."""
    failed = job_dir / FAILED_FILE
    if failed.is_file():
        lines = [line for line in failed.read_text().splitlines() if line.strip()]
        return "failed", lines[-1] if lines else "unknown error"
    last = job_dir / CHECKPOINT_DIR / LAST
    if not last.is_file():
        return "unfinished", "no checkpoint"
    ckpt = load_checkpoint(last)
    episodes = ckpt["episodes_done"]
    if "final" in ckpt:
        return (
            "finished",
            f"{episodes} episodes, final running-mean return {ckpt['final']['final_return']:.1f}",
        )
    return "unfinished", f"{episodes} episodes so far"


def sweep_jobs(sweep_dir: Path) -> list[Path]:
    """Job folders of a sweep: those holding Hydra's ``.hydra/`` record."""
    return sorted(
        p.parent for p in Path(sweep_dir).glob("**/.hydra") if p.is_dir() and p.parent != Path(sweep_dir)
    )


class SweepSummary(Callback):
    """Prints, at the end of a multirun, which jobs finished, which failed and why."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        rows = [(job.relative_to(sweep_dir), *job_status(job)) for job in sweep_jobs(sweep_dir)]
        counts = {
            s: sum(1 for _, status, _ in rows if status == s) for s in ("finished", "failed", "unfinished")
        }
        print(f"\nsweep {sweep_dir}: " + ", ".join(f"{n} {s}" for s, n in counts.items()))
        for name, status, detail in rows:
            print(f"  [{status}] {name}: {detail}")
        if counts["failed"]:
            print(
                f"  failed jobs keep their traceback in <job>/{FAILED_FILE}; re-run the same command to retry them"
            )
