"""Headless pygame for every test (no display, no audio device), and W&B offline (nothing leaves the
machine: logger=wandb writes its run files only)."""

import os

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
