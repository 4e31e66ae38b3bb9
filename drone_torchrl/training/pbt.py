"""Population-based training (PBT) inside a population run: exploit and explore as row copies.

Every ``every_updates`` updates of a population run (``hydra/launcher=pbt``), the agents are
ranked by their running-mean return. Each agent of the worst ``quantile`` then **exploits**: it
takes the weights, Adam's moments and step count, per-agent hyper-parameters and running-mean
window of an agent drawn from the best ``quantile`` (a copy of rows of the stacked state). It then
**explores**: each searched key is, with probability ``resample_probability``, drawn again from
the values the sweep gave that key, and otherwise is the parent's value times a factor drawn from
``perturb``, kept inside the key's bounds. The defaults are Ray Tune's (``PopulationBasedTraining``:
truncation quantile 0.25, factors 0.8 and 1.2, resample probability 0.25). Agents keep their own
seeds, so a copy explores with noise of its own.

The draws of an exploit step come from a generator keyed by the first agent's seed and the update
number, and everything else they depend on (the windows, the state) is in the checkpoint: a killed
and resumed run takes the same steps as an uninterrupted one. Each step appends one row per
replaced agent to the run's lineage (update, agent, parent and the new values), kept in the
checkpoint and written to ``lineage.parquet`` (:mod:`.population_record`). An agent that diverged
takes no part.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch

from drone_torchrl.checks import ConfigError
from drone_torchrl.config import per_agent_keys, schema_keys

# The population state's entry of each key PBT can search.
STATE_KEYS = {"algo.lr": "lr", "algo.gamma": "gamma", "algo.weight_decay": "weight_decay"}
# The largest truncation quantile: the worst and the best quantile must not overlap.
MAX_QUANTILE = 0.5
# The lineage's columns besides the searched keys.
LINEAGE_COLUMNS = ("update", "agent", "parent")


@dataclass(frozen=True)
class PBTSettings:
    """``hydra/launcher=pbt``'s settings (``hydra.launcher.<field>``).

    Attributes:
        every_updates: updates between two exploit steps (every agent trains that many in between).
        quantile: the fraction of agents replaced at each step, and the fraction they copy from.
        perturb: the factors an explored value is multiplied by (one drawn per key).
        resample_probability: the chance that a key is drawn again from the sweep's values instead.
        keys: the searched keys (per-agent keys other than ``seed``).
    """

    every_updates: int = 100
    quantile: float = 0.25
    perturb: tuple[float, ...] = (0.8, 1.2)
    resample_probability: float = 0.25
    keys: tuple[str, ...] = field(default=("algo.lr", "algo.gamma"))

    @classmethod
    def of(cls, params: Mapping[str, Any]) -> PBTSettings:
        """The settings from the launcher's parameters, each checked: :class:`ConfigError` (one
        line, naming ``hydra.launcher.<key>``) for the first that is not allowed."""

        def refuse(key: str, value: Any, allowed: str) -> ConfigError:
            return ConfigError.of(f"hydra.launcher.{key}", value, allowed)

        every = params.get("every_updates", cls.every_updates)
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise refuse("every_updates", every, "an integer >= 1")
        quantile = params.get("quantile", cls.quantile)
        if (
            isinstance(quantile, bool)
            or not isinstance(quantile, int | float)
            or not 0 < quantile <= MAX_QUANTILE
        ):
            raise refuse("quantile", quantile, f"a number in (0, {MAX_QUANTILE}]")
        perturb = params.get("perturb", cls.perturb)
        if (
            isinstance(perturb, str | bytes)
            or not isinstance(perturb, Sequence)
            or not perturb
            or not all(isinstance(f, int | float) and not isinstance(f, bool) and f > 0 for f in perturb)
        ):
            raise refuse("perturb", perturb, "a non-empty list of factors > 0, e.g. [0.8,1.2]")
        resample = params.get("resample_probability", cls.resample_probability)
        if isinstance(resample, bool) or not isinstance(resample, int | float) or not 0 <= resample <= 1:
            raise refuse("resample_probability", resample, "a number in [0, 1]")
        keys = params.get("keys", cls.keys)
        if isinstance(keys, str | bytes) or not isinstance(keys, Sequence) or not keys:
            raise refuse("keys", keys, f"a non-empty list of {sorted(STATE_KEYS)}")
        for key in keys:
            if key not in STATE_KEYS:
                why = "a per-agent key" if key in per_agent_keys() else "not a per-agent key"
                raise refuse(
                    "keys",
                    list(keys),
                    f"keys among {sorted(STATE_KEYS)} ({key!r} is {why} PBT cannot search)",
                )
        return cls(
            int(every), float(quantile), tuple(float(f) for f in perturb), float(resample), tuple(keys)
        )


class PBT:
    """The exploit and explore steps of one population run.

    Args:
        settings: what to search and how.
        space: each searched key -> the values the sweep gave it (what a resample draws from).
        bounds: each searched key -> its ``(low, high)`` (explored values are kept inside).
        seed: the key of the steps' random draws (with the update number).
        lineage: the rows written so far (a resumed run's, from its checkpoint), column -> values.
    """

    def __init__(
        self,
        settings: PBTSettings,
        space: Mapping[str, Sequence[float]],
        bounds: Mapping[str, tuple[float, float]],
        seed: int,
        lineage: Mapping[str, list] | None = None,
    ) -> None:
        self.settings = settings
        self.space = {key: sorted(set(space[key])) for key in settings.keys}
        self.bounds = dict(bounds)
        self.seed = int(seed)
        columns = (*LINEAGE_COLUMNS, *settings.keys)
        self.lineage: dict[str, list] = {key: list((lineage or {}).get(key, [])) for key in columns}
        # Each agent's value of each searched key now, exactly (the state holds gamma in the
        # network's precision): the sweep's, then each lineage row's.
        self.current = {key: [float(v) for v in space[key]] for key in settings.keys}
        for row, agent in enumerate(self.lineage["agent"]):
            for key in settings.keys:
                self.current[key][agent] = float(self.lineage[key][row])

    @classmethod
    def for_population(cls, settings: PBTSettings, cfg: Any, values: Mapping[str, list], lineage=None) -> PBT:
        """The PBT of a population whose group config is ``cfg`` and whose sweep gave ``values``."""
        rules = schema_keys("config", algo=cfg.algo.name, logger=cfg.logger.backend)
        bounds = {}
        for key in settings.keys:
            rule = rules.get(key)
            if rule is None:
                raise ConfigError.of(
                    "hydra.launcher.keys", list(settings.keys), f"keys that algo={cfg.algo.name} has"
                )
            bounds[key] = (float(rule.low), float(rule.high))
        return cls(settings, values, bounds, int(values["seed"][0]), lineage)

    def updates_until_due(self, updates_done: int) -> int:
        every = self.settings.every_updates
        return every - updates_done % every

    def step(
        self, state: Any, scores: Sequence[float], alive: Sequence[bool], update: int
    ) -> list[tuple[int, int]]:
        """One exploit-and-explore step after ``update`` updates: rewrites rows of ``state`` (the
        population's stacked state) in place and appends the lineage. ``scores``: each agent's
        running-mean return; ``alive``: the agents that take part. Returns ``(agent, parent)``
        pairs (the caller copies the agents' own records)."""
        s = self.settings
        candidates = [i for i in range(len(scores)) if alive[i] and not math.isnan(scores[i])]
        count = int(len(candidates) * s.quantile)
        if count < 1:
            return []
        ranked = sorted(candidates, key=lambda i: (scores[i], i))
        worst, best = np.array(ranked[:count]), np.array(ranked[-count:])
        rng = np.random.default_rng([self.seed, update])
        parents = best[rng.integers(count, size=count)]
        rows, sources = torch.as_tensor(worst), torch.as_tensor(parents)
        with torch.no_grad():
            for key in state.keys():  # noqa: SIM118  (a TensorDict iterates over its rows)
                if key not in ("seed", "counter"):  # an agent keeps its own noise and update count
                    state[key][rows] = state[key][sources]
        new = {}
        for key in s.keys:
            space = np.array(self.space[key])
            resampled = rng.random(count) < s.resample_probability
            drawn = space[rng.integers(len(space), size=count)]
            factors = np.array(s.perturb)[rng.integers(len(s.perturb), size=count)]
            values = np.where(resampled, drawn, np.array(self.current[key])[parents] * factors)
            low, high = self.bounds[key]
            new[key] = np.clip(values, low, high)
            with torch.no_grad():
                state[STATE_KEYS[key]][rows] = torch.as_tensor(new[key], dtype=state[STATE_KEYS[key]].dtype)
        for i, (agent, parent) in enumerate(zip(worst.tolist(), parents.tolist(), strict=True)):
            self._append(update, agent, parent, {key: float(new[key][i]) for key in s.keys})
        return list(zip(worst.tolist(), parents.tolist(), strict=True))

    def _append(self, update: int, agent: int, parent: int, values: Mapping[str, float]) -> None:
        for key, value in zip(LINEAGE_COLUMNS, (update, agent, parent), strict=True):
            self.lineage[key].append(value)
        for key, value in values.items():
            self.lineage[key].append(value)
            self.current[key][agent] = value

    def checkpoint(self) -> dict[str, Any]:
        return {"settings": asdict(self.settings), "lineage": self.lineage}
