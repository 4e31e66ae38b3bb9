"""Sweep reports: figures and a summary table of hyper-parameter sweeps (the ``drone-report`` CLI).

A report reads only the files a sweep job leaves on disk (``episodes.csv``, ``config.yaml``,
``.hydra/overrides.yaml`` and ``checkpoints/last.pt``), so it works on sweeps that are still
running and on jobs trained by any engine writing those files. Modules: :mod:`.runs` (job
folders, settings), :mod:`.stats` (the numbers, one sweep's report), :mod:`.tables` (the files
written, its curves' figures too), :mod:`.distribution`, :mod:`.landscape` and :mod:`.schedules`.

Method:

1. **Settings.** Jobs are grouped by their command-line overrides minus the seed and minus keys
   that do not change what is trained (``NON_SETTING_KEYS``, ``NON_SETTING_PREFIXES`` of
   :mod:`.runs`). Values are read back from the job's resolved ``config.yaml`` when the key is
   there, so ``algo.lr=1e-3`` and ``algo.lr=0.001`` are the same setting. A setting's label keeps
   only the overrides that differ between settings (``algo.lr=0.001``); a single setting is
   labelled ``all``.
2. **Curves.** Per run, the running mean over ``window`` episodes (default
   :data:`drone_torchrl.episodes.RUNNING_MEAN_WINDOW`, the paper's 100) of the episode length,
   return and negative-thrust fraction. The window is *trailing*, and over the first
   ``window - 1`` episodes it averages the episodes available so far (pandas'
   ``rolling(window, min_periods=1)``), which is also what ``drone-train`` logs as its running
   mean. Consequence: a threshold can be crossed early by a short lucky start; the crossing
   episodes below are read off exactly these curves. Then, per episode index (0-based, as in
   ``episodes.csv``), the mean, population std (``ddof=0``), min and max over the seeds that have
   reached that episode: runs of different lengths (unfinished, failed) contribute where they have
   data, and the report says how many seeds are unfinished and how far the shortest got.
3. **Table.** Per setting: seeds finished/total, the final running-mean return (each run's last
   value; mean +- std over seeds, and as a percentage of the ``10 * max_steps`` ceiling), the first
   episode at which the running-mean length reaches ``max_steps`` and the running-mean return
   reaches ``return_threshold`` (mean over the seeds that reach it, and how many do), the final
   running-mean negative-thrust fraction, and the wall-clock time (each run's last
   ``wall_clock_s``; mean per run and total). The verdict names the setting with the best mean
   final running-mean return; none when the runs mix budgets (``algo.episodes``): a run given
   more episodes ends further along, so each budget is then a setting of its own in the table.
4. **Figures.** ``steps.png`` and ``returns.png`` like the paper's figures 4.2 and 4.4: one curve per
   setting with a mean +- std band, the ``max_steps`` cap and the ``10 * max_steps`` ceiling as
   dashed lines, and the PD hover controller's mean return
   (:func:`drone_torchrl.evaluation.evaluate_pd`, 100 episodes, seed 0, on the jobs' env settings)
   as a dotted reference line.
"""

from __future__ import annotations

from drone_torchrl.lazy import lazy_getattr

#: The return whose first crossing by the running mean the report gives (drone-report --return-threshold).
DEFAULT_RETURN_THRESHOLD = 2000.0

# Loaded on first use (PEP 562): drone-report's command line (drone_torchrl/apps/report.py) and its
# --help need none of them, and they import torch.
_LAZY = {
    name: f"drone_torchrl.report.{module}"
    for module, names in {
        "runs": "ReportError Run Setting group_runs load_runs setting_of",
        "stats": "Crossing SeedStats SettingSummary SweepReport aggregate_over_seeds build_report first_crossing "
        "running_mean setting_curve summarize verdict",
        "tables": "format_report format_table write_report",
    }.items()
    for name in names.split()
}

__all__ = sorted(_LAZY)


__getattr__ = lazy_getattr(__name__, _LAZY)
