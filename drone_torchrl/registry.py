"""Plug-in registries: algorithms and logger backends are found by name the same way.

The algorithms are :mod:`drone_torchrl.algorithms` (the registry :data:`ALGORITHMS`, :class:`Algorithm`,
the :class:`Learner` protocol and its update's :class:`UpdateOutput` are here, below the config and the training loop that look them
up), the logger backends :mod:`drone_torchrl.loggers`.

A plug-in module calls :meth:`Registry.register` when imported. A registry imports the modules of
its own package, and those another package names in its entry-point group, when a name is first
looked up, not when it is created: plug-ins use the config helpers, which look them up.
"""

from __future__ import annotations

import importlib
import pkgutil
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib import metadata
from typing import TYPE_CHECKING, Any, Generic, NamedTuple, Protocol, TypeVar

from drone_torchrl.checks import ConfigError

if TYPE_CHECKING:
    import torch

#: The type of the plug-ins a :class:`Registry` holds.
T = TypeVar("T")
# What a plug-in may be called.
NAME = re.compile(r"[a-z][a-z0-9_]*")


class Registry(Generic[T]):
    """Named plug-ins of one kind.

    Args:
        key: the config key that names one (``algo.name``), for error messages.
        package: the package whose modules are the built-in plug-ins.
        entry_points: the entry-point group through which other packages add theirs.
    """

    def __init__(self, key: str, package: str, entry_points: str) -> None:
        self.key, self.package, self.entry_points = key, package, entry_points
        self._items: dict[str, T] = {}
        self._discovered = False

    def register(self, name: str, item: T) -> T:
        """Add ``item`` as ``name``; a duplicate or a malformed name is refused.

        A duplicate is another item of the same name; a well-formed name is lowercase letters,
        digits and ``_``, starting with a letter (it is typed on command lines and names folders and
        config keys).
        """
        if not isinstance(name, str) or not NAME.fullmatch(name):
            raise ValueError(f"{self.key}={name!r} cannot be registered: a name is {NAME.pattern}")
        known = self._items.get(name)
        if known is not None and known != item:
            raise ValueError(f"two plug-ins are registered as {self.key}={name}: {known!r} and {item!r}")
        self._items[name] = item
        return item

    def _discover(self) -> None:
        if self._discovered:
            return
        self._discovered = True
        package = importlib.import_module(self.package)
        for module in pkgutil.iter_modules(package.__path__):
            importlib.import_module(f"{self.package}.{module.name}")
        for entry in metadata.entry_points(group=self.entry_points):
            importlib.import_module(entry.value)

    def names(self) -> tuple[str, ...]:
        """The registered names, sorted."""
        self._discover()
        return tuple(sorted(self._items))

    def get(self, name: object) -> T:
        """The plug-in called ``name``; else a one-line :class:`~.checks.ConfigError` naming the choices."""
        self._discover()
        if not isinstance(name, str) or name not in self._items:
            raise ConfigError.of(
                self.key,
                name,
                f"one of {list(self.names())} (registered in {self.package} or '{self.entry_points}')",
            )
        return self._items[name]


@dataclass(frozen=True)
class Algorithm:
    """One algorithm as the shared training loop sees it.

    Attributes:
        name: its ``algo.name``.
        learner: the :class:`Learner` subclass the training loop drives.
        validate: raises :class:`~drone_torchrl.checks.ConfigError` (one line) for values of its keys
            that do not go together; each key's own bounds and choices (its schema's) are checked
            before it is called. Gets the resolved config as nested dicts with attribute access.
        checkpoint_keys: entries its learner adds to every checkpoint (a checkpoint without one is
            refused when resumed, in one line).
        summary: one line saying what it is.
        memory: ``memory(cfg, agents)``: the bytes its learner allocates, by part
            (:mod:`drone_torchrl.memory_estimate` derives them); a config whose estimate
            exceeds the free memory is refused before any work. None: only the parts every run has.
    """

    name: str
    learner: type[Learner]
    validate: Callable[[Mapping[str, Any]], None]
    checkpoint_keys: tuple[str, ...] = ()
    summary: str = ""
    memory: Callable[[Mapping[str, Any], int], dict[str, Any]] | None = None


#: The algorithms (:mod:`drone_torchrl.algorithms` and the ``drone_torchrl.algorithms`` entry points).
ALGORITHMS: Registry[Algorithm] = Registry(
    "algo.name", "drone_torchrl.algorithms", "drone_torchrl.algorithms"
)


class UpdateOutput(NamedTuple):
    """``k`` updates of ``N`` agents (:meth:`Learner.update`): their ``metrics`` and finished ``episodes``.

    ``metrics``: ``[k, N]`` each (REINFORCE's ``"train/loss"``, ``"train/grad_norm"``,
    ``"policy/std_mean"``); ``"active"`` ``[k, N]`` bool, who was trained in each update;
    ``"checks"`` ``[k, N, C]`` bool, the learner's ``checks`` (REINFORCE's :data:`~drone_torchrl.algorithms.reinforce.CHECKS`).
    ``episodes``: ``[k, N, E]`` each, :data:`~drone_torchrl.episodes.EPISODE_KEYS`, and where the
    updates end a varying number of episodes a ``"valid"`` mask (:meth:`~drone_torchrl.algorithms.ppo.OneRun.update`'s).
    The loop copies them to the host once per call (one sync, however many updates and agents).
    """

    metrics: dict[str, torch.Tensor]
    episodes: dict[str, torch.Tensor]


class Learner(Protocol):
    """What the training loop (:class:`~drone_torchrl.training.trainer.Trainer`) asks of an algorithm's learner.

    An algorithm's learner subclasses it (its defaults: the attributes' values, one agent, no-op
    hooks). ``learner(jobs)`` trains up to :meth:`max_agents` prepared jobs (their checkpoints restored).
    The loop calls :meth:`update` until every agent is done; after each evaluation
    :meth:`after_evaluation`; at a checkpoint :meth:`checkpoint_entries`; for an evaluation
    :meth:`eval_policy`, and :meth:`actor` for a video.

    Attributes:
        state: the agents' stacked state, handed to :meth:`update` (None: the learner keeps its own).
        episodes_per_update: the episodes each update ends per agent; None where they vary (the
            update's episodes then come padded, with a ``"valid"`` mask, one update per call).
        eval_agents: the agents :meth:`eval_policy` flies at once (None: one, a plain actor).
        checks: the names of the update's finite checks, in the order of its ``"checks"``.
        advice: what a divergence's message suggests.
        takes_rollback_drop: whether :meth:`after_evaluation` acts on ``eval.rollback_drop`` (the
            key is refused in one line for another learner).
    """

    state: Any = None
    episodes_per_update: int | None = None
    eval_agents: int | None = None
    checks: tuple[str, ...] = ()
    advice: str = ""
    takes_rollback_drop: bool = False

    @staticmethod
    def max_agents(cfg: Any) -> int | None:
        """The jobs one learner trains together (None: any number)."""
        return 1

    def update(self, state: Any, k: int, active: Any) -> tuple[Any, Any]:
        """``k`` updates of the ``active`` agents: ``(state, UpdateOutput)``.

        ``state``: the population's stacked ``TensorDict`` (batch size ``[N]``), updated in place
        (None for a learner that keeps its own, PPO's, A2C's, SAC's); ``k``: capped by the loop at
        the next evaluation, checkpoint or end of budget of any agent, so nothing falls due inside
        a call; ``active``: ``[N]`` bool, the agents to train (finished and failed ones sit out).
        """

    def eval_policy(self) -> Any:
        """The policy the evaluator flies, :attr:`eval_agents` agents at once."""

    def checkpoint_entries(self, agent: int) -> dict[str, Any]:
        """The agent's checkpoint entries that the run record does not own."""

    def actor(self, agent: int) -> Any:
        """The agent's actor on its own (for videos)."""

    def after_evaluation(self, run: Any, best_before: float) -> None:
        """After each evaluation of ``run`` (its best return before it ``best_before``): nothing by default."""

    def close(self) -> None:
        """Let go of what the learner holds (an env's workers): nothing by default."""
