"""Algorithms as plug-ins: each one is a module here (or in another package) and a YAML in ``conf/algo/``.

A module registers one :class:`Algorithm`: its name (what ``algo.name`` in its YAML says), its
learner (the class :class:`~drone_torchrl.training.trainer.Trainer` drives through the update
contract of :mod:`drone_torchrl.training.update`, or its own loop ``train(trainer, stop)``, as
:class:`~.ppo.OnPolicy`'s), the checks of its own ``algo.*`` keys and the
entries its learner adds to every checkpoint. Everything else a run does (the run record,
evaluations, checkpoints and resume, divergence, the one-line errors, sweeps and launchers) is
the shared skeleton's and needs nothing from the algorithm.

Adding one, e.g. A2C (see :mod:`.a2c`): write ``drone_torchrl/algorithms/a2c.py`` with its learner,
``validate`` and a call of :func:`register`, and its keys' schema (a dataclass, each field with its
bounds or choices) stored with :func:`drone_torchrl.schema.store_plugin` as ``schema_algo_a2c``;
and ``conf/algo/a2c.yaml`` listing that schema first in its defaults, with ``name: a2c`` and its
keys' values (``# @package _global_`` at the top if it also sets ``model.*`` or other groups' keys);
then ``drone-train algo=a2c``. The YAML's file name is the option users type; ``algo.name`` names the
learner, so several YAMLs can share one (``algo=reinforce_plus`` is ``name: reinforce`` with other
values). Another package adds algorithms by naming a module in the ``drone_torchrl.algorithms``
entry-point group, and its YAML in ``conf/algo/`` of a Hydra search path.

Modules are imported when an algorithm is first looked up (:class:`~drone_torchrl.registry.Registry`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from drone_torchrl.registry import Registry


@dataclass(frozen=True)
class Algorithm:
    """One algorithm as the shared training loop sees it.

    Attributes:
        name: its ``algo.name``.
        learner: the learner class; ``learner(jobs)`` trains up to ``learner.max_agents`` prepared
            jobs (None: any number) behind ``update(state, k, active)`` or its own ``train``.
        validate: raises :class:`~drone_torchrl.checks.ConfigError` (one line) for values of its keys
            that do not go together; each key's own bounds and choices (its schema's) are checked
            before it is called. Gets the resolved config as nested dicts with attribute access.
        checkpoint_keys: entries its learner adds to every checkpoint (a checkpoint without one is
            refused when resumed, in one line).
        summary: one line saying what it is.
        memory: ``memory(cfg, agents)``: the bytes its learner allocates, by part
            (:mod:`drone_torchrl.training.memory_estimate` derives them); a config whose estimate
            exceeds the free memory is refused before any work. None: only the parts every run has.
    """

    name: str
    learner: type
    validate: Callable[[Mapping[str, Any]], None]
    checkpoint_keys: tuple[str, ...] = ()
    summary: str = ""
    memory: Callable[[Mapping[str, Any], int], dict[str, Any]] | None = None


ALGORITHMS: Registry[Algorithm] = Registry("algo.name", __name__, "drone_torchrl.algorithms")


def register(algorithm: Algorithm) -> Algorithm:
    """Add ``algorithm`` (its module calls this when imported)."""
    return ALGORITHMS.register(algorithm.name, algorithm)


def names() -> tuple[str, ...]:
    """The registered algorithms' names, sorted."""
    return ALGORITHMS.names()


def get(name: Any) -> Algorithm:
    """The algorithm named ``name``; a one-line :class:`~drone_torchrl.checks.ConfigError` otherwise."""
    return ALGORITHMS.get(name)
