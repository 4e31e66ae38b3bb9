"""Algorithms as plug-ins: each one is a module here (or in another package) and a YAML in ``conf/algo/``.

A module registers one :class:`~drone_torchrl.registry.Algorithm`: its name (what ``algo.name`` in its YAML says), its
learner (a :class:`~drone_torchrl.registry.Learner`, which the one loop,
:class:`~drone_torchrl.training.trainer.Trainer`, drives through the update contract of
:meth:`drone_torchrl.registry.Learner.update`), the checks of its own ``algo.*`` keys and the
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
The registry and :class:`~drone_torchrl.registry.Algorithm` live in :mod:`drone_torchrl.registry`, below the config and the
training loop that look algorithms up (``from drone_torchrl.algorithms import Algorithm, Learner, register``
works too).
"""

from __future__ import annotations

from drone_torchrl.registry import ALGORITHMS, Algorithm, Learner

__all__ = ["ALGORITHMS", "Algorithm", "Learner", "get", "names", "register"]


def register(algorithm: Algorithm) -> Algorithm:
    """Add ``algorithm`` (its module calls this when imported)."""
    return ALGORITHMS.register(algorithm.name, algorithm)


def names() -> tuple[str, ...]:
    """The registered algorithms' names, sorted."""
    return ALGORITHMS.names()


def get(name: object) -> Algorithm:
    """The algorithm named ``name``; a one-line :class:`~drone_torchrl.checks.ConfigError` otherwise."""
    return ALGORITHMS.get(name)
