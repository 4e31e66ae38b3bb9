"""Headless pygame for every test (no display, no audio device), and W&B offline (nothing leaves the
machine: logger=wandb writes its run files only); ``command_here``, a console command run in-process."""

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")


def pytest_ignore_collect(collection_path, config):
    """The JAX peer's tests import jax, whose thread pools would then share the whole test process:
    they are collected only when the slow checks are selected (``-m slow``, CI's second stage)."""
    if collection_path.name != "test_jax_peer.py":
        return None
    expression = config.getoption("markexpr") or ""
    return not ("slow" in expression and "not slow" not in expression)


@pytest.fixture
def command_here(monkeypatch, capfd):
    """Run a console command's entry point (``drone_torchrl.apps.<module>.run``/``main``) in this
    process, as ``name args...`` from ``cwd``; returns what its process would have ended with.

    For commands refused before any work (a new process would spend seconds importing torch only
    to print one line): ``sys.exit("...")`` becomes exit status 1 with the message on stderr, as
    the interpreter does. Output is captured at the file descriptors, as a process's pipes would
    be. Hydra configures the root logger (handlers on the captured stdout and on each job's log
    file); it is put back as it was, for the tests after this one.
    """

    def call(entry, name: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
        monkeypatch.chdir(cwd)
        monkeypatch.setattr(sys, "argv", [name, *args])
        capfd.readouterr()
        root = logging.getLogger()
        handlers, level = list(root.handlers), root.level
        # The run's lines have a logger of their own, which Hydra's job logging gives the log file too.
        console = logging.getLogger("drone_torchrl.console")
        console_handlers = list(console.handlers)
        try:
            entry()
            code = 0
        except SystemExit as stop:
            code = stop.code
        finally:
            for handler in set(root.handlers) - set(handlers):
                handler.close()  # a job's log file (Hydra's job logging)
            root.handlers[:] = handlers
            root.setLevel(level)
            for handler in set(console.handlers) - set(console_handlers):
                handler.close()
            console.handlers[:] = console_handlers
        out, err = capfd.readouterr()
        if isinstance(code, str):
            err, code = err + code + "\n", 1
        return subprocess.CompletedProcess([name, *args], 0 if code is None else code, out, err)

    return call
