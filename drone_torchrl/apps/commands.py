"""The console commands (pyproject's ``[project.scripts]``): ``--help`` answered before the app loads.

Each app's module imports torch and the training code (seconds); its ``--help`` page needs neither
(:mod:`drone_torchrl.apps.help`), so each command checks for it first and imports its app only to
run it. Output piped into ``head`` never stops a command, its help page included
(:func:`~drone_torchrl.io.streams.guard_broken_pipes`, first).
"""

from __future__ import annotations

import functools
import importlib

from drone_torchrl.apps.help import answer_help
from drone_torchrl.io.streams import guard_broken_pipes


def start(prog: str) -> None:
    """How each command starts: broken pipes guarded, then ``prog``'s help page if asked for (exits)."""
    guard_broken_pipes()
    answer_help(prog)  # the page made from conf/ (drone_torchrl/apps/help.py), not Hydra's


def _command(prog: str, app: str) -> None:
    """``prog``: its help page if asked for, else ``drone_torchrl.apps.<app>.run()``."""
    start(prog)
    importlib.import_module(f"drone_torchrl.apps.{app}").run()


# The console scripts: ``drone-train`` runs drone_torchrl.apps.train.run(), and so on.
train = functools.partial(_command, "drone-train", "train")
evaluate = functools.partial(_command, "drone-eval", "evaluate")
export = functools.partial(_command, "drone-export", "export")
