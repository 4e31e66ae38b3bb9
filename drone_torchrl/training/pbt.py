"""Population-based training (PBT) inside a population run: exploit and explore as row copies.

Every ``every_updates`` updates of a population run (``hydra/launcher=pbt``), the agents are
ranked by their running-mean return. Each agent of the worst ``quantile`` then **exploits**: it
takes the weights, Adam's moments and step count, per-agent hyper-parameters and running-mean
window of an agent drawn from the best ``quantile`` (a copy of rows of the stacked state). It then
**explores** inside the searched space, as Ray Tune's ``PopulationBasedTraining`` does:

- a key the sweep gave as a list (``algo.lr=1e-4,3e-4,1e-3``) moves from the parent's value to a
  neighbouring value of the sorted list, one step down or up with equal chance (an end stays where
  it is when the step would leave the list), or, with probability ``resample_probability``, is
  drawn again from the list. No value outside the list is ever tried.
- a key the sweep gave as a range (``interval(low,high)``, or ``tag(log,interval(low,high))``:
  :class:`Range`) is the parent's value times a factor drawn from ``perturb``, clipped to
  ``[low, high]``, or, with probability ``resample_probability``, drawn again uniformly from the
  range (log-uniformly where tagged ``log``).

The defaults are Ray Tune's (truncation quantile 0.25, factors 0.8 and 1.2, resample probability
0.25). Agents keep their own seeds, so a copy explores with noise of its own.

The draws of an exploit step come from a generator keyed by the first agent's seed and the update
number, and everything else they depend on (the windows, the state) is in the checkpoint: a killed
and resumed run takes the same steps as an uninterrupted one. Each step appends one row per
replaced agent to the run's lineage (update, agent, parent and the agent's values from then on of
every key of :data:`STATE_KEYS`, searched or not: the copy gives it the parent's values of the keys
not searched), kept in the checkpoint and written to ``lineage.parquet``
(:mod:`.population_record`). An agent that diverged takes no part.

PBT, PB2 (:mod:`.pb2`) and successive halving (:class:`Halving`) take one step (:meth:`Search.step`):
the search picks the agents replaced and their parents (``select``), rewrites their rows and draws
their values (``renew``), and the step books them in the state and the lineage; a replay
(:class:`Replay`) books its schedule's values for every agent. Every search's checkpoint entry is
its settings' record, the lineage and its own :attr:`Search.extra`.
"""

from __future__ import annotations

import functools
import itertools
import math
import sys
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import numpy as np
import torch

from drone_torchrl.checks import ConfigError, is_number
from drone_torchrl.config import per_agent_keys, schema_keys

#: Each per-agent key a search can change -> its entry in the population state (the lineage records them all).
STATE_KEYS = {"algo.lr": "lr", "algo.gamma": "gamma", "algo.weight_decay": "weight_decay"}
# The largest truncation quantile: the worst and the best quantile must not overlap.
MAX_QUANTILE = 0.5
# The largest factor of hydra.launcher.perturb (the smallest: its inverse).
MAX_FACTOR = 100.0
# Updates until a replay's next change, when it has none left.
NEVER = 2**62
# The lineage's columns besides the searched keys.
# (parent -1: a new configuration from fresh weights, successive halving's; seed: the agent's then.)
LINEAGE_COLUMNS = ("update", "agent", "parent", "seed")
#: The parent of an agent restarted from fresh weights.
FRESH = -1
#: The ``(agent, parent)`` pairs of a search step.
Pairs = list[tuple[int, int]]
#: Columns of values (a lineage, column -> one value per row, or the sweep's, key -> one per agent).
Table = Mapping[str, Sequence[Any]]
FACTORS = f"a non-empty list of factors in [{1 / MAX_FACTOR:g}, {MAX_FACTOR:g}], e.g. [0.8,1.2]"
#: ``[(update, values), ...]``: the values one agent trained with from each update on (:func:`schedule`).
Schedule = list[tuple[int, dict[str, float]]]
#: The rule of a launcher key (whether a value is allowed, what is expected instead, the value kept).
Rule = tuple[Callable[[Any], bool], str, Callable[[Any], Any]]


@dataclass(frozen=True)
class Range:
    """A key searched over a range: ``key=interval(low,high)`` (``log``: ``tag(log,interval(low,high))``).

    Attributes:
        key: the searched key.
        low: the range's lower end.
        high: the range's upper end.
        log: whether values are drawn log-uniformly (``low`` > 0).
    """

    key: str
    low: float
    high: float
    log: bool = False

    def draw(self, rng: np.random.Generator, size: int) -> np.ndarray:
        """``size`` values drawn uniformly from the range (log-uniformly where ``log``)."""
        if self.log:
            return np.exp(rng.uniform(math.log(self.low), math.log(self.high), size))
        return rng.uniform(self.low, self.high, size)

    def first_values(self, seeds: Sequence[int]) -> list[float]:
        """Each agent's first value: one draw from a generator keyed by its seed and the key.

        The same sweep gives every agent the same value again (a resumed run's), whatever the
        population's size or order.
        """
        tag = zlib.crc32(self.key.encode())
        return [float(self.draw(np.random.default_rng([int(seed), tag]), 1)[0]) for seed in seeds]


def _check_share(key: str, share: float, agents: int, outcome: str) -> None:
    """Refuse a population of ``agents`` whose ``share`` of it rounds down to no agent.

    ``key``: PBT's quantile or halving's fraction (``hydra.launcher.<key>``); nothing would ever be
    ``outcome``. A larger share is the advice where the key allows 1 / ``agents`` (each allows a half).
    """
    if int(agents * share) >= 1:
        return
    # 1 / share rounded up may fall short by a rounding error
    smallest = next(n for n in itertools.count(math.ceil(1 / share)) if int(n * share) >= 1)
    larger = f"at least 1/{agents} for a population of {agents} agents, or " if agents > 1 else ""
    expected = f"a population of at least {smallest} agents (int({agents} x {share:g}) = 0 agents would ever"
    raise ConfigError.of(f"hydra.launcher.{key}", share, f"{larger}{expected} be {outcome})")


def _list(value: Any) -> bool:
    """Whether ``value`` is a non-empty list (not a string)."""
    return isinstance(value, Sequence) and not isinstance(value, str | bytes) and bool(value)


def _factors(value: Any) -> bool:
    """Whether ``value`` is a non-empty list of ``hydra.launcher.perturb``'s factors."""
    # A factor past MAX_FACTOR (or below its inverse) sends any value to its range's end in one
    # step: a resample, not a perturbation (and inf or nan would be clipped into a value no agent had).
    return _list(value) and all(is_number(f) and 1 / MAX_FACTOR <= f <= MAX_FACTOR for f in value)


def _rungs(value: Any) -> bool:
    """Whether ``value`` is a list of increasing update counts >= 1 (``hydra.launcher.rungs``)."""
    counts = _list(value) and all(is_number(r) and isinstance(r, int) and r >= 1 for r in value)
    return counts and list(value) == sorted(set(value))


def _searched_keys(keys: Any, search: str) -> tuple[str, ...]:
    """``hydra.launcher.keys`` checked: per-agent keys that a search can change."""
    if not _list(keys):
        raise ConfigError.of("hydra.launcher.keys", keys, f"a non-empty list of {sorted(STATE_KEYS)}")
    for key in keys:
        if not isinstance(key, str) or key not in STATE_KEYS:
            why = "a per-agent key" if key in per_agent_keys() else "not a per-agent key"
            expected = f"keys among {sorted(STATE_KEYS)} ({key!r} is {why} {search} cannot search)"
            raise ConfigError.of("hydra.launcher.keys", list(keys), expected)
    if len(set(keys)) < len(keys):  # one lineage column per key: a repeated one has no meaning
        raise ConfigError.of("hydra.launcher.keys", list(keys), "each key once, e.g. [algo.lr,algo.gamma]")
    return tuple(keys)


class Settings:
    """What the settings of every search do: read from the launcher's keys, checked, and recorded."""

    #: The search's name in a checkpoint.
    launcher: ClassVar[str]
    #: The settings the search does not use (left out of its record).
    unused: ClassVar[tuple[str, ...]] = ()
    #: Each ``hydra.launcher`` key but ``keys``, in the order they are checked -> its :data:`Rule`
    #: (a key kept as an ``int`` or a ``float`` must be a number).
    rules: ClassVar[dict[str, Rule]] = {}
    #: The search, as the refusal of a key it cannot search names it.
    title: ClassVar[str]

    @classmethod
    def of(cls, params: Mapping[str, Any]) -> Any:
        """The settings from the launcher's parameters, each checked.

        :class:`~.checks.ConfigError` (one line, naming ``hydra.launcher.<key>``) for the first that is not
        allowed.
        """
        values = {}
        for key, (ok, expected, kept) in cls.rules.items():
            value = params.get(key, getattr(cls, key))
            if not ((is_number(value) or kept not in (int, float)) and ok(value)):
                raise ConfigError.of(f"hydra.launcher.{key}", value, expected)
            values[key] = kept(value)
        return cls(**values, keys=_searched_keys(params.get("keys", cls.keys), cls.title))  # type: ignore[call-arg]

    def record(self) -> dict[str, Any]:
        """The settings as the checkpoint keeps them (a resumed run must ask for the same)."""
        # A list-only search records no ranges: its record is the one runs made before ranges existed.
        unused = {*self.unused, *(() if getattr(self, "ranges", ()) else ("ranges",))}
        return {k: v for k, v in {"launcher": self.launcher, **asdict(self)}.items() if k not in unused}  # type: ignore[call-overload]


def _updates(cfg: Any) -> int:
    """The budget's updates: ``algo.episodes / algo.episodes_per_update``."""
    return int(cfg.algo.episodes) // int(cfg.algo.episodes_per_update)


@dataclass(frozen=True)
class PBTSettings(Settings):
    """``hydra/launcher=pbt``'s settings (``hydra.launcher.<field>``).

    Attributes:
        every_updates: updates between two exploit steps (every agent trains that many in between).
        quantile: the fraction of agents replaced at each step, and the fraction they copy from.
        perturb: the factors an explored value of a range key is multiplied by (one drawn per key
            and agent). A key searched over a list ignores it: it moves to a neighbouring value.
        resample_probability: the chance that a key is drawn again from its list or range instead.
        keys: the searched keys (per-agent keys other than ``seed``).
        ranges: the keys the sweep gave as a range (``interval``), set by the population sweeper
            from the command line; the other searched keys are lists.
    """

    every_updates: int = 100
    quantile: float = 0.25
    perturb: tuple[float, ...] = (0.8, 1.2)
    resample_probability: float = 0.25
    keys: tuple[str, ...] = field(default=("algo.lr", "algo.gamma"))
    ranges: tuple[Range, ...] = ()
    launcher: ClassVar[str] = "pbt"
    title: ClassVar[str] = "PBT"
    rules: ClassVar[dict[str, Rule]] = {
        "every_updates": (lambda v: isinstance(v, int) and v >= 1, "an integer >= 1", int),
        "quantile": (lambda v: 0 < v <= MAX_QUANTILE, f"a number in (0, {MAX_QUANTILE}]", float),
        "perturb": (_factors, FACTORS, lambda v: tuple(map(float, v))),
        "resample_probability": (lambda v: 0 <= v <= 1, "a number in [0, 1]", float),
    }

    def check(self, cfg: Any, agents: int) -> None:
        """A step inside the budget (``algo.episodes / algo.episodes_per_update`` updates).

        And a population of ``agents`` large enough that the quantile is at least one agent.
        """
        if self.every_updates >= (updates := _updates(cfg)):
            expected = f"fewer than the budget's {updates} updates"
            raise ConfigError.of("hydra.launcher.every_updates", self.every_updates, expected)
        _check_share("quantile", self.quantile, agents, "replaced: no exploit step, an empty lineage")

    def bounds(self, cfg: Any) -> dict[str, tuple[float, float]]:
        """Each searched key's ``(low, high)``: the values its rule allows under ``cfg``'s algorithm.

        Raises :class:`~.checks.ConfigError` (one line) for a key the algorithm does not have, or a
        range (:attr:`ranges`) that reaches outside its key's values.
        """
        rules = schema_keys("config", algo=cfg.algo.name, logger=cfg.logger.backend)
        if not set(self.keys) <= set(rules):
            expected = f"keys that algo={cfg.algo.name} has"
            raise ConfigError.of("hydra.launcher.keys", list(self.keys), expected)
        bounds = {key: (float(rules[key].low), float(rules[key].high)) for key in self.keys}
        for span in self.ranges:
            low, high = bounds[span.key]
            if not low <= span.low < span.high <= high:
                text = f"interval({span.low},{span.high})"
                raise ConfigError(
                    f"{span.key}={f'tag(log,{text})' if span.log else text} is not allowed; expected "
                    f"a range inside the values algo={cfg.algo.name} allows, [{low}, {high}]"
                )
        return bounds

    def make(self, cfg: Any, values: Mapping[str, list], saved: Mapping[str, Any] | None) -> PBT:
        """The search of a population (``saved``: what its checkpoint holds of it, or None).

        ``cfg`` is the population's group config, ``values`` what its sweep gave each agent.
        """
        bounds = self.bounds(cfg)
        if not self.ranges and self.perturb != PBTSettings.perturb:
            keys = ", ".join(self.keys)
            note = f"hydra.launcher.perturb={list(self.perturb)} is not used: every searched key ({keys}) is searched over a list, and moves to a neighbouring value of it; perturb multiplies keys searched over interval(low,high)"
            print(f"drone-train: note: {note}", file=sys.stderr)
        return PBT(self, values, bounds, int(values["seed"][0]), (saved or {}).get("lineage"))


def recorded_keys(initial: Mapping[str, Any]) -> tuple[str, ...]:
    """The keys of :data:`STATE_KEYS` that ``initial`` (key -> every agent's value) names, in that order.

    A population's values name every per-agent key: the lineage records each of these.
    """
    return tuple(key for key in STATE_KEYS if key in initial)


def _walk(lineage: Table | None, initial: Table, keys: Sequence, cast: Callable = float) -> tuple[dict, dict]:
    """The lineage with a column for each of ``keys``, and each agent's values of them at its end (``cast``).

    A missing column's value (a float) is the one the agent's row held from that row on
    (:func:`complete_lineage`).
    """
    out = {column: list(values) for column, values in (lineage or {}).items()}
    out.update({column: out.get(column, []) for column in LINEAGE_COLUMNS})
    missing = [key for key in keys if key not in out]
    now = {key: [cast(v) for v in initial[key]] for key in keys}
    out.update({key: [] for key in missing})
    for row, (agent, parent) in enumerate(zip(out["agent"], out["parent"], strict=True)):
        for key in missing:
            out[key].append(float(now[key][agent if parent == FRESH else parent]))
        for key in keys:
            now[key][agent] = cast(out[key][row])
    return out, now


def complete_lineage(lineage: Table | None, initial: Table, keys: Sequence[str] | None = None) -> dict:
    """The lineage with a column for each of ``keys`` (default: :func:`recorded_keys` of ``initial``).

    A lineage written before it recorded every key has the searched keys' columns only. A missing
    column's value is the one the agent's row held from that row on: its parent's value then (an
    exploit copies the parent's whole row; a replay's parent is the agent itself), or the agent's
    own for a restart from fresh weights (:data:`FRESH`: the slot keeps the keys not drawn).
    """
    return _walk(lineage, initial, recorded_keys(initial) if keys is None else tuple(keys))[0]


def final_values(lineage: Table | None, initial: Table) -> dict[str, list]:
    """Each agent's values at the end of ``lineage``: ``initial``'s, then each lineage row's (as they are).

    Of :func:`recorded_keys` of ``initial``, and ``seed`` where ``initial`` has it (a restart from
    fresh weights gives the slot a new seed).
    """
    keys = (*recorded_keys(initial), *(("seed",) if "seed" in initial else ()))
    return _walk(lineage, initial, keys, lambda value: value)[1]


class Exploit(NamedTuple):
    """One search step, as the search's ``renew`` (and PBT's explore, :meth:`PBT.choose`) sees it.

    ``worst``: the agents replaced; ``parents``: each one's parent (the agent whose rows it copied,
    or :data:`FRESH`);
    ``scores``: every agent's running-mean return; ``alive``: whether each agent takes part;
    ``update``: the updates done; ``rng``: the step's generator (keyed by the first agent's seed and
    ``update``).
    """

    worst: np.ndarray
    parents: np.ndarray
    scores: Sequence[float]
    alive: Sequence[bool]
    update: int
    rng: np.random.Generator


class Search:
    """What every search shares: the lineage, each agent's values now, and the step that books them.

    The lineage records every key of :data:`STATE_KEYS` that ``initial`` names, searched or not:
    an exploit copies the parent's whole row, so a key not searched changes too.

    Args:
        initial: each key -> every agent's value from the sweep (every recorded key: the searched
            keys and the others of :data:`STATE_KEYS`).
        lineage: the rows written so far (a resumed run's, from its checkpoint), column -> values.
    """

    settings: Any
    #: The key of a step's random draws, with the update number.
    seed = 0
    #: What else the checkpoint keeps of the search (name -> the search's own record, kept up to date).
    extra: Mapping[str, Any] = {}

    def __init__(self, initial: Table, lineage: Table | None) -> None:
        self.recorded = recorded_keys(initial)
        # An older checkpoint's lineage may lack the keys that were not searched: filled in. Each
        # agent's value of each recorded key now is exact (the state holds gamma in the network's
        # precision): the sweep's, then each lineage row's.
        complete, self.current = _walk(lineage, initial, self.recorded)
        self.lineage: dict[str, list] = {key: complete[key] for key in (*LINEAGE_COLUMNS, *self.recorded)}

    def start(self, state: Any) -> None:
        """A fresh run's state before its first update (a resumed one has its checkpoint's)."""

    def due(self, updates_done: int) -> bool:
        """Whether the search takes a step after ``updates_done`` (>= 1) updates."""
        return self.updates_until_due(updates_done - 1) == 1

    def step(self, state: Any, scores: Sequence[float], alive: Sequence[bool], update: int) -> Pairs:
        """The search's step after ``update`` updates; returns the ``(agent, parent)`` pairs it replaced.

        Rewrites rows of ``state`` (the population's stacked state) in place and books them in the
        lineage. ``scores``: each agent's running-mean return; ``alive``: the agents that take part.
        The caller copies the agents' own records for the pairs returned. A search tells which agents
        are replaced (``select``), and gives their rows and values (``renew``).
        """
        rng = np.random.default_rng([self.seed, update])
        agents, parents = self.select(scores, alive, update, rng)
        if not agents:
            return []
        new = self.renew(state, Exploit(np.array(agents), np.array(parents), scores, alive, update, rng))
        return self._set(state, update, agents, parents, new)

    def _set(self, state: Any, update: int, agents: list[int], parents: list[int], new: Mapping) -> Pairs:
        """Give ``agents`` the ``new`` values (key -> one per agent) in ``state`` and book them in the lineage.

        A recorded key that ``new`` leaves out keeps the value the agent's row holds: its parent's
        (the exploit copied it), or its own after a restart from fresh weights (:data:`FRESH`).
        Returns the ``(agent, parent)`` pairs.
        """
        source = [agent if parent == FRESH else parent for agent, parent in zip(agents, parents, strict=True)]
        values = {key: [self.current[key][i] for i in source] for key in self.recorded}
        values.update({key: [float(v) for v in new[key]] for key in new})
        rows = torch.as_tensor(list(agents))
        with torch.no_grad():
            for key in self.recorded:
                entry = state[STATE_KEYS[key]]
                entry[rows] = torch.as_tensor(np.asarray(values[key], dtype=np.float64), dtype=entry.dtype)
        booked = ([update] * len(source), agents, parents, state["seed"][rows].tolist())
        for column, column_values in zip(LINEAGE_COLUMNS, booked, strict=True):
            self.lineage[column] += [int(v) for v in column_values]
        for key in self.recorded:
            self.lineage[key] += values[key]
            for agent, value in zip(agents, values[key], strict=True):
                self.current[key][agent] = value
        return list(zip(agents, parents, strict=True))

    def checkpoint(self) -> dict[str, Any]:
        """What a checkpoint keeps of the search: its settings, the lineage, and its :attr:`extra`."""
        return {"settings": self.settings.record(), "lineage": self.lineage, **self.extra}


class PBT(Search):
    """The exploit and explore steps of one population run.

    Args:
        settings: what to search and how.
        space: each searched key -> the values the sweep gave it, one per agent (the agents' first
            values; a list key's distinct values are its list).
        bounds: each searched key -> its ``(low, high)``, the values its rule allows (a range key's
            explored values are kept inside these as well as inside its range).
        seed: the key of the steps' random draws (with the update number).
        lineage: the rows written so far (a resumed run's, from its checkpoint), column -> values.
    """

    def __init__(
        self, settings: PBTSettings, space: Table, bounds: Mapping, seed: int, lineage: Table | None = None
    ) -> None:
        super().__init__(space, lineage)
        self.settings, self.bounds, self.seed = settings, dict(bounds), int(seed)
        self.ranges = {r.key: r for r in settings.ranges}
        self.space = {key: sorted(set(space[key])) for key in settings.keys if key not in self.ranges}

    def updates_until_due(self, updates_done: int) -> int:
        """Updates from ``updates_done`` until the next exploit-and-explore step."""
        return self.settings.every_updates - updates_done % self.settings.every_updates

    def select(self, scores: Sequence, alive: Sequence, update: int, rng: Any) -> tuple[list, list]:
        """The worst ``quantile`` of the agents that take part, and a parent for each drawn from the best."""
        candidates = [i for i, a in enumerate(alive) if a and not math.isnan(scores[i])]
        ranked = sorted(candidates, key=lambda i: (scores[i], i))
        if (count := int(len(ranked) * self.settings.quantile)) < 1:
            return [], []
        return ranked[:count], np.array(ranked[-count:])[rng.integers(count, size=count)].tolist()

    def renew(self, state: Any, step: Exploit) -> dict[str, np.ndarray]:
        """The exploit: the parents' rows copied into the replaced agents' (who keep their own seed and update count)."""
        copied = state.exclude("seed", "counter")
        with torch.no_grad():
            copied[torch.as_tensor(step.worst)] = copied[torch.as_tensor(step.parents)]
        return self.choose(step)

    def choose(self, step: Exploit) -> dict[str, np.ndarray]:
        """The values the replaced agents train with next (key -> one per agent): each explored from its parent's."""
        parents = step.parents
        return {k: self.explore(k, np.array(self.current[k])[parents], step.rng) for k in self.settings.keys}

    def explore(self, key: str, values: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The explored values of ``key`` from the parents' ``values``, with ``rng``'s draws.

        A list key: a neighbouring value of the sorted list, or a value drawn from the list. A
        range key: the value times a ``perturb`` factor clipped to the range, or a value drawn from it.
        """
        s, count = self.settings, len(values)
        resampled = rng.random(count) < s.resample_probability
        if span := self.ranges.get(key):
            factors = np.array(s.perturb)[rng.integers(len(s.perturb), size=count)]
            moved = np.clip(values * factors, span.low, span.high)
            return np.clip(np.where(resampled, span.draw(rng, count), moved), *self.bounds[key])
        space = np.array(self.space[key])
        # The parent's place in the list: its nearest value (a run resumed from before lists kept
        # their values may hold one off the list).
        place = np.abs(space[None, :] - values[:, None]).argmin(axis=1)
        moved = space[np.clip(place + rng.choice(np.array([-1, 1]), size=count), 0, len(space) - 1)]
        return np.where(resampled, space[rng.integers(len(space), size=count)], moved)


@dataclass(frozen=True)
class ReplaySettings(Settings):
    """``hydra/launcher=pbt_replay``: every agent follows the values one agent of a PBT run had.

    The run may also be a successive halving run; it must have finished (every agent at its budget
    or diverged).

    Attributes:
        run: the PBT population run (its folder).
        agent: the agent whose line of ancestors' values is replayed (default: the one with the
            best final return).
        schedule: ``(update, ((key, value), ...))`` from update 0: that agent's values of every
            key the run's lineage records (:func:`schedule`). The replay's checkpoint keeps it.
    """

    run: str
    agent: int
    schedule: tuple[tuple[int, tuple[tuple[str, float], ...]], ...]
    launcher: ClassVar[str] = "pbt_replay"

    @classmethod
    def of(cls, params: Mapping[str, Any]) -> ReplaySettings:
        """The settings from the launcher's parameters, checked against the PBT run replayed.

        Raises :class:`~.checks.ConfigError` (one line) for a run that is not a finished PBT
        population run, or for an agent it does not have.
        """
        from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, LAST, CheckpointError, load_checkpoint
        from drone_torchrl.io.storage import name_too_long

        run = params.get("run")
        path = Path(str(run)) / CHECKPOINT_DIR / LAST
        refused = functools.partial(ConfigError.of, "hydra.launcher.run", run)
        if (too_long := name_too_long(path)) is not None:  # is_file() would raise ENAMETOOLONG
            raise refused(f"a folder name this file system takes ({too_long})")
        try:
            state = load_checkpoint(path) if run is not None and path.is_file() else None
        except CheckpointError as err:
            raise refused(f"a PBT population run ({err})") from None
        search = (state or {}).get("search")
        if not search or search["settings"].get("launcher") not in ("pbt", "pb2", "halving"):
            raise refused("the folder of a PBT, PB2 or halving run (hydra/launcher=pbt, pb2 or halving)")
        count = len(state["episodes_done"])
        training = sum(f is None and e is None for f, e in zip(state["final"], state["failure"], strict=True))
        if training:  # its lineage and final returns are not yet the run's
            raise refused(
                f"a finished PBT or halving run ({training} of its {count} agents are still training: run its command again to finish it first)"
            )
        agent = params.get("agent")
        if agent is None:  # the best final return
            finals = [-math.inf if f is None else f["final_return"] for f in state["final"]]
            agent = max(range(count), key=finals.__getitem__)
        if isinstance(agent, bool) or not isinstance(agent, int) or not 0 <= agent < count:
            expected = f"an agent of {run}: an integer 0..{count - 1}"
            raise ConfigError.of("hydra.launcher.agent", agent, expected)
        steps = schedule(search["lineage"], state["agents"], agent)
        return cls(str(Path(str(run)).resolve()), agent, tuple((u, tuple(v.items())) for u, v in steps))

    def record(self) -> dict[str, Any]:
        """What a checkpoint keeps of these settings: the launcher, run and agent, and the schedule."""
        return {**super().record(), "schedule": [[update, dict(values)] for update, values in self.schedule]}

    def check(self, cfg: Any, agents: int) -> None:
        """Any budget and population: the last values hold past the PBT run's."""

    def check_resume(self, saved: Mapping[str, Any]) -> None:
        """A resumed replay follows the schedule its checkpoint keeps (``saved``: its settings' record).

        :class:`~.checks.ConfigError` (one line) when the run replayed has changed since (another
        run written in its folder): its agent's schedule is no longer the one this replay follows.
        """
        if [saved.get(key) for key in ("launcher", "run", "agent")] != ["pbt_replay", self.run, self.agent]:
            return  # another search: the caller's comparison names both
        if "schedule" in saved and saved["schedule"] != self.record()["schedule"]:
            expected = (
                f"the run this replay started from, unchanged: agent {self.agent}'s schedule there is "
                f"now {_schedule_text(self.record()['schedule'])}, this replay follows "
                f"{_schedule_text(saved['schedule'])}; replay the new run in another hydra.sweep.dir"
            )
            raise ConfigError.of("hydra.launcher.run", self.run, expected)

    def make(self, cfg: Any, values: Mapping[str, list], saved: Mapping[str, Any] | None) -> Replay:
        """The :class:`Replay` of a population of ``len(values["seed"])`` agents."""
        return Replay(self, len(values["seed"]), None if saved is None else saved["lineage"])


def _schedule_text(steps: Sequence[Sequence[Any]]) -> str:
    """A schedule in one short line: ``update 0: algo.lr=0.001 algo.gamma=0.99; update 4: ...``."""
    return "; ".join(
        f"update {update}: " + " ".join(f"{key}={value:.4g}" for key, value in dict(values).items())
        for update, values in steps
    )


def schedule(lineage: Table, initial: Table, agent: int, keys: Sequence[str] | None = None) -> Schedule:
    """The values ``agent``'s weights were trained with, as ``[(update, values), ...]``.

    The list is ``[(0, the first values), (update, the values from then on), ...]``, following the
    agent's line of ancestors back through the lineage (an agent replaced at update ``u`` by a copy
    of ``parent`` had ``parent``'s line before ``u``). ``keys``: the values given (default: every
    key of :data:`STATE_KEYS` that ``initial`` names; a column an older lineage lacks is filled by
    :func:`complete_lineage`).
    """
    keys = recorded_keys(initial) if keys is None else tuple(keys)
    lineage = complete_lineage(lineage, initial, keys)
    steps = []
    current = agent
    for row in range(len(lineage["agent"]) - 1, -1, -1):
        if lineage["agent"][row] == current:
            values = {key: float(lineage[key][row]) for key in keys}
            current = int(lineage["parent"][row])
            if current == FRESH:  # the line began here from fresh weights: its updates count from here
                start = int(lineage["update"][row])
                return [(0, values), *((update - start, later) for update, later in steps[::-1])]
            steps.append((int(lineage["update"][row]), values))
    steps.append((0, {key: float(initial[key][current]) for key in keys}))
    return steps[::-1]


class Replay(Search):
    """Every agent of a population trained with the values of one PBT agent's line.

    The line is a schedule of ``(update, values)``: the found configuration, retrained on fresh seeds.

    Args:
        settings: the launcher's settings, with the schedule replayed.
        agents: the population's size.
        lineage: the lineage a resumed run had (None: a new run).
    """

    def __init__(self, settings: ReplaySettings, agents: int, lineage: Table | None = None) -> None:
        self.settings, self.agents = settings, agents
        self.steps = {update: dict(values) for update, values in settings.schedule}
        super().__init__({key: [value] * agents for key, value in self.steps[0].items()}, lineage)

    def start(self, state: Any) -> None:
        """Give every agent the replayed line's first values."""
        self.step(state, (), (), 0)

    def updates_until_due(self, updates_done: int) -> int:
        """Updates from ``updates_done`` until the replayed line's next change of values."""
        return min((u - updates_done for u in self.steps if u > updates_done), default=NEVER)

    def step(self, state: Any, scores: Sequence[float], alive: Sequence[bool], update: int) -> Pairs:
        """Give every agent the line's values from ``update`` on; replaces no agent (returns ``[]``)."""
        everyone = list(range(self.agents))
        new = {key: [value] * self.agents for key, value in self.steps[update].items()}
        self._set(state, update, everyone, everyone, new)
        return []


@dataclass(frozen=True)
class HalvingSettings(Settings):
    """``hydra/launcher=halving``'s settings: successive halving inside a population run.

    Attributes:
        rungs: the updates after which the worst agents stop (increasing, below the budget).
        fraction: the fraction of the agents stopped at each rung; their slots go to new
            configurations (values drawn from the sweep's, fresh weights, a new seed).
        keys: the keys a new configuration draws.
    """

    rungs: tuple[int, ...] = (500, 1500)
    fraction: float = 0.5
    keys: tuple[str, ...] = ("algo.lr", "algo.gamma")
    launcher: ClassVar[str] = "halving"
    title: ClassVar[str] = "successive halving"
    rules: ClassVar[dict[str, Rule]] = {
        "rungs": (_rungs, "increasing update counts >= 1, e.g. [500,1500]", lambda v: tuple(map(int, v))),
        "fraction": (lambda v: 0 < v < 1, "a number in (0, 1)", float),
    }

    def check(self, cfg: Any, agents: int) -> None:
        """Every rung inside the budget (``algo.episodes / algo.episodes_per_update`` updates).

        And a population of ``agents`` large enough that ``fraction`` of it is at least one agent.
        """
        if self.rungs[-1] >= (updates := _updates(cfg)):
            algo = cfg.algo
            expected = f"rungs below the budget of {updates} updates (algo.episodes={algo.episodes} / algo.episodes_per_update={algo.episodes_per_update})"
            raise ConfigError.of("hydra.launcher.rungs", list(self.rungs), expected)
        _check_share("fraction", self.fraction, agents, "stopped at a rung: no halving")

    def make(self, cfg: Any, values: Mapping[str, list], saved: Mapping[str, Any] | None) -> Halving:
        """The :class:`Halving` of a population whose sweep gave ``values``."""
        return Halving(self, cfg, values, saved)


class Halving(Search):
    """Successive halving inside a population run, asynchronous as ASHA's (Li et al. 2020).

    The rungs are ages: updates since an agent's configuration started. When an agent reaches a
    rung, its running-mean return joins the scores every agent had at that rung so far; if it is
    among the worst ``fraction`` of them, the agent stops and its slot starts a new configuration:
    each key drawn from the sweep's values, fresh weights from a new seed (after the sweep's and
    the earlier new ones), a fresh optimizer, age 0. Agents past the last rung train to the end. A
    slot's episodes after a restart are its new configuration's; each restart is a lineage row with
    parent -1 (:data:`FRESH`). The scores at each rung are in the checkpoint; draws keyed as PBT's.

    Args:
        settings: the launcher's settings (searched keys, rungs, ``fraction``).
        cfg: the group's config (fresh configurations are built from it).
        values: the sweep's values of each key, one per agent (``"seed"`` among them).
        saved: the search's checkpoint entry of a resumed run (None: a new run).
    """

    def __init__(self, settings: HalvingSettings, cfg: Any, values: Table, saved: Mapping | None) -> None:
        saved = saved or {}
        super().__init__(values, saved.get("lineage"))
        self.settings, self.cfg, self.seed = settings, cfg, int(values["seed"][0])
        self.space = {key: sorted(set(values[key])) for key in settings.keys}
        self.next_seed = max([*values["seed"], *self.lineage["seed"]]) + 1
        started = dict(zip(self.lineage["agent"], self.lineage["update"], strict=True))
        # The update each agent's configuration started at.
        self.started = [started.get(i, 0) for i in range(len(values["seed"]))]
        rungs = saved.get("rung_scores", {})
        self.rung_scores: dict[int, list[float]] = {r: list(rungs.get(r, [])) for r in settings.rungs}
        self.extra = {"rung_scores": self.rung_scores}

    def updates_until_due(self, updates_done: int) -> int:
        """Updates from ``updates_done`` until an agent next reaches a rung."""
        later = [s + r - updates_done for s in set(self.started) for r in self.settings.rungs]
        return min((d for d in later if d > 0), default=NEVER)

    def select(self, scores: Sequence, alive: Sequence, update: int, rng: Any) -> tuple[list, list]:
        """The agents at a rung that score in its worst ``fraction``, each restarted (:data:`FRESH`)."""
        stopped = []
        for rung, history in self.rung_scores.items():
            arrived = [i for i in range(len(scores)) if alive[i] and update - self.started[i] == rung]
            score = {i: -math.inf if math.isnan(scores[i]) else float(scores[i]) for i in arrived}
            history.extend(score.values())
            # The worst `fraction` of every score this rung has seen: below the k-th smallest.
            k = int(len(history) * self.settings.fraction)
            threshold = sorted(history)[k] if k else -math.inf
            stopped += [i for i in arrived if score[i] < threshold]
        return sorted(stopped), [FRESH] * len(stopped)

    def renew(self, state: Any, step: Exploit) -> dict[str, np.ndarray]:
        """Fresh weights from new seeds and a fresh optimizer in the stopped agents' rows; values drawn from the sweep's."""
        from drone_torchrl.modules.factory import build_policies

        count, rows = len(step.worst), torch.as_tensor(step.worst)
        seeds = list(range(self.next_seed, self.next_seed + count))
        self.next_seed += count
        with torch.no_grad():
            state["params"][rows] = build_policies(self.cfg, seeds).flat.detach().to(state["params"])
            for key in ("exp_avg", "exp_avg_sq", "adam_steps"):  # a fresh optimizer (optim.adam_state's)
                state[key][rows] = 0
            state["seed"][rows] = torch.as_tensor(seeds, dtype=state["seed"].dtype)
        for agent in step.worst.tolist():
            self.started[agent] = step.update
        draw = step.rng.integers
        return {key: np.array(space)[draw(len(space), size=count)] for key, space in self.space.items()}


#: What a population run's search is asked for (PBT, successive halving, or a replay of one agent's values).
SearchSettings = PBTSettings | HalvingSettings | ReplaySettings
