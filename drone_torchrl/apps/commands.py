"""The console commands (pyproject's ``[project.scripts]``): ``--help`` answered before the app loads.

Each app's module imports torch and the training code (seconds); its ``--help`` page needs neither
(:mod:`drone_torchrl.apps.help`), so each command checks for it first and imports its app only to
run it. Output piped into ``head`` never stops a command, its help page included
(:func:`~drone_torchrl.io.streams.guard_broken_pipes`, first).
"""

from __future__ import annotations

import importlib

from drone_torchrl.apps.help import answer_help
from drone_torchrl.io.streams import guard_broken_pipes


def _command(prog: str, app: str) -> None:
    """``prog``: its help page if asked for, else ``drone_torchrl.apps.<app>.run()``."""
    guard_broken_pipes()
    answer_help(prog)
    importlib.import_module(f"drone_torchrl.apps.{app}").run()


def train() -> None:
    """``drone-train`` (:func:`drone_torchrl.apps.train.run`)."""
    _command("drone-train", "train")


def evaluate() -> None:
    """``drone-eval`` (:func:`drone_torchrl.apps.evaluate.run`)."""
    _command("drone-eval", "evaluate")


def export() -> None:
    """``drone-export`` (:func:`drone_torchrl.apps.export.run`)."""
    _command("drone-export", "export")
