"""Population-based bandits (PB2): PBT whose explore step is chosen by a Gaussian process.

``hydra/launcher=pb2`` exploits as :class:`~.pbt.PBT` does (every ``every_updates`` updates the worst
``quantile`` of the agents copy the weights, Adam state and values of agents drawn from the best
``quantile``), but explores as Parker-Holder et al. (NeurIPS 2020) and Ray Tune's ``PB2`` do: the
new values are the ones a time-varying Gaussian process expects to improve the return most, by an
upper confidence bound, rather than the parent's moved at random.

- **Data.** At each step, every agent that takes part adds one point: the positions of the values
  it trained with over the interval and the step's number, and its return's change over the
  interval (the running-mean return now minus just after the previous step; an exploited agent's
  "before" is its parent's, whose window it copied). Each step's changes are centred on their mean:
  an agent is measured against the population in the same interval, which also makes the first
  interval (every agent from fresh weights) usable. Ray Tune's PB2 conditions on the return before
  the interval instead. The changes are then standardised and clipped to [-2, 2], as Ray Tune does.
- **Model.** Squared-exponential in the values' positions times ``(1 - epsilon) ** (|i - j| / 2)``
  in the steps' numbers (Bogunovic et al., 2016, the TV-GP-UCB kernel PB2 uses: older intervals
  count less). Its length scale, ``epsilon`` and noise are the grid point of :data:`LENGTH_SCALES`,
  :data:`EPSILONS`, :data:`NOISES` with the highest marginal likelihood (Ray Tune fits them with
  GPy's optimiser; a grid needs no extra dependency and is deterministic).
- **Choice.** Each replaced agent takes the candidate with the highest ``mean + kappa * variance``
  at the next step, ``kappa = sqrt(0.2 log(0.4 n))`` for ``n`` points (Ray Tune's; 0 below 3
  points; with no point at all, the highest variance). The variance
  is the model's given also the values the population trains with next (the agents kept, and the
  ones chosen before in the same step), so that two replaced agents are not sent to the same place.
- **Space.** A key searched over a list is a position ``index / (len - 1)`` on the sorted list and
  only the list's values are candidates (every combination while there are at most
  :data:`CANDIDATES`, else that many drawn); a key searched over a range
  (``interval``/``tag(log,interval)``) is its place in the range (in log space where tagged), with
  :data:`CANDIDATES` drawn values. Nothing outside the searched space is ever tried.

The draws (parents, candidates) come from a generator keyed by the first agent's seed and the
update, and the data is in the checkpoint: a killed and resumed run takes the same steps.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch

from drone_torchrl.training.pbt import PBT, Exploit, PBTSettings, Table

#: The grid of the model's length scale (in positions in [0, 1]).
LENGTH_SCALES = (0.05, 0.1, 0.2, 0.5, 1.0, 2.0)
#: The grid of the model's forgetting per step.
EPSILONS = (0.0, 0.05, 0.1, 0.2, 0.5)
#: The grid of the model's noise variance (the standardised signal's is 1).
NOISES = (0.01, 0.1, 0.3, 1.0)
#: The most candidates scored for one choice.
CANDIDATES = 1024
# Ray Tune's clip of the standardised changes.
CLIP = 2.0


@dataclass(frozen=True)
class PB2Settings(PBTSettings):
    """``hydra/launcher=pb2``'s settings: PBT's ``every_updates``, ``quantile``, ``keys`` (and ranges).

    ``perturb`` and ``resample_probability`` are PBT's random explore: PB2 has none.
    """

    launcher: ClassVar[str] = "pb2"
    unused: ClassVar[tuple[str, ...]] = ("perturb", "resample_probability")

    def make(self, cfg: Any, values: Mapping[str, list], saved: Mapping[str, Any] | None) -> PB2:
        """The search of a population (``saved``: what its checkpoint holds of it, or None)."""
        lineage, data = ((saved or {}).get(key) for key in ("lineage", "data"))
        return PB2(self, values, self.bounds(cfg), int(values["seed"][0]), lineage, data)


class PB2(PBT):
    """PBT with PB2's explore step (the module's docstring).

    Args:
        settings: what to search.
        space: each searched key -> the values the sweep gave it, one per agent.
        bounds: each searched key -> the values its rule allows.
        seed: the key of the steps' random draws (with the update number).
        lineage: the rows written so far (a resumed run's), column -> values.
        data: the model's data so far (a resumed run's, ``checkpoint()``'s ``data``).
    """

    def __init__(
        self,
        settings: PB2Settings,
        space: Table,
        bounds: Mapping,
        seed: int,
        lineage: Table | None = None,
        data: Mapping | None = None,
    ) -> None:
        super().__init__(settings, space, bounds, seed, lineage)
        # The model's points (each step, positions and return change) and each agent's running-mean
        # return just after the last step (None before the first).
        data = {"steps": [], "points": [], "changes": [], "before": None, **(data or {})}
        self.data: dict[str, Any] = copy.deepcopy(data)
        self.extra = {"data": self.data}

    def position(self, key: str, value: float) -> float:
        """``value``'s place in ``key``'s searched space, in [0, 1]."""
        if span := self.ranges.get(key):
            scale = math.log if span.log else float
            return (scale(value) - scale(span.low)) / (scale(span.high) - scale(span.low))
        space = self.space[key]
        return int(np.abs(np.array(space) - value).argmin()) / (len(space) - 1) if len(space) > 1 else 0.5

    def value(self, key: str, position: float) -> float:
        """The value at ``position`` of ``key``'s searched space (a list key: a value of the list)."""
        if span := self.ranges.get(key):
            scale, back = (math.log, math.exp) if span.log else (float, float)
            return back(scale(span.low) + position * (scale(span.high) - scale(span.low)))
        space = self.space[key]
        return space[round(position * (len(space) - 1))]

    def candidates(self, rng: np.random.Generator) -> np.ndarray:
        """Positions to score (rows), every one a point of the searched space."""
        keys = self.settings.keys
        grids = [np.linspace(0, 1, len(self.space[k])) if k in self.space else None for k in keys]
        if all(g is not None for g in grids) and math.prod(len(g) for g in grids) <= CANDIDATES:
            return np.array(list(itertools.product(*grids)), dtype=np.float64).reshape(-1, len(keys))
        columns = [
            rng.uniform(0, 1, CANDIDATES) if g is None else g[rng.integers(len(g), size=CANDIDATES)]
            for g in grids
        ]
        return np.stack(columns, axis=1)

    def observe(self, scores: Sequence[float], alive: Sequence[bool], step: int) -> None:
        """Add each taking-part agent's point of the interval that ends at ``step``."""
        data, before = self.data, self.data["before"] or [0.0] * len(scores)
        finite = [alive[i] and before[i] is not None and math.isfinite(before[i]) for i in range(len(scores))]
        rows = [i for i in range(len(scores)) if finite[i] and math.isfinite(scores[i])]
        if rows:
            changes = np.array([scores[i] - before[i] for i in rows])
            data["steps"] += [step] * len(rows)
            data["points"] += [self.point(i) for i in rows]
            data["changes"] += (changes - changes.mean()).tolist()

    def point(self, agent: int) -> list[float]:
        """The agent's values now as a point of the searched space (its position on each key)."""
        return [self.position(key, self.current[key][agent]) for key in self.settings.keys]

    def choose(self, step: Exploit) -> dict[str, np.ndarray]:
        """Each replaced agent's next values: the candidate of the highest upper confidence bound."""
        worst, scores, alive = step.worst, step.scores, step.alive
        number = step.update // self.settings.every_updates
        self.observe(scores, alive, number)
        after = [float(s) if math.isfinite(s) else math.nan for s in scores]
        for agent, parent in zip(worst.tolist(), step.parents.tolist(), strict=True):
            after[agent] = after[parent]  # the copied window: the agent goes on from its parent's return
        self.data["before"] = after
        keys = self.settings.keys
        kept = [i for i in range(len(scores)) if alive[i] and i not in worst and math.isfinite(scores[i])]
        pending = [self.point(i) for i in kept]
        threads = torch.get_num_threads()
        # Matrices of a few hundred rows: one thread is fastest, and several beside a busy
        # trainer's were 12x slower on 2 cores (a 350-point fit: 10.5 s on 2 threads, 0.85 s on 1).
        torch.set_num_threads(1)
        try:
            data = (np.array(self.data[k], dtype=np.float64) for k in ("steps", "points", "changes"))
            model = Model.fit(*data)
            options = self.candidates(step.rng)
            chosen = []
            for _ in worst:
                score = model.upper_bound(options, number + 1, np.array(pending).reshape(-1, len(keys)))
                chosen.append(options[int(np.argmax(score))])
                pending.append(chosen[-1].tolist())
        finally:
            torch.set_num_threads(threads)
        return {key: np.array([self.value(key, float(p[j])) for p in chosen]) for j, key in enumerate(keys)}


@dataclass
class Model:
    """The time-varying Gaussian process of PB2's choice, fitted to standardised changes.

    The linear algebra runs in torch (float64; :meth:`PB2.choose` runs it on one thread): numpy's
    OpenBLAS starts threads of its own beside torch's, and a 350-point fit took 32 s instead of 1 s
    on 2 cores.

    Attributes:
        steps: each point's step.
        points: each point's positions (rows).
        targets: the standardised, clipped changes.
        length: the squared-exponential's length scale.
        epsilon: the forgetting per step.
        noise: the noise variance (the signal's is 1).
    """

    steps: np.ndarray
    points: np.ndarray
    targets: np.ndarray
    length: float
    epsilon: float
    noise: float

    @classmethod
    def fit(cls, steps: np.ndarray, points: np.ndarray, changes: np.ndarray) -> Model:
        """The grid point of highest marginal likelihood for ``changes`` (no data: a prior)."""
        if changes.size == 0:
            return cls(steps, points.reshape(0, 0), changes, LENGTH_SCALES[0], 0.0, 1.0)
        targets = np.clip((changes - changes.mean()) / (changes.std() + 1e-8), -CLIP, CLIP)
        squared, apart = _distances(steps, points, steps, points)
        y, eye = torch.as_tensor(targets, dtype=torch.float64), torch.eye(len(targets), dtype=torch.float64)
        best, best_fit = (LENGTH_SCALES[0], EPSILONS[0], NOISES[0]), -math.inf
        for length, epsilon, noise in itertools.product(LENGTH_SCALES, EPSILONS, NOISES):
            factor = torch.linalg.cholesky(_covariance(squared, apart, length, epsilon) + noise * eye)
            alpha = torch.linalg.solve_triangular(factor, y[:, None], upper=False)
            fit = float(-0.5 * (alpha**2).sum() - torch.log(torch.diagonal(factor)).sum())
            if fit > best_fit:
                best, best_fit = (length, epsilon, noise), fit
        return cls(steps, points, targets, *best)

    def kernel(self, steps_a: np.ndarray, a: np.ndarray, steps_b: np.ndarray, b: np.ndarray) -> torch.Tensor:
        """The covariance of two sets of points: squared-exponential times the forgetting in time."""
        return _covariance(*_distances(steps_a, a, steps_b, b), self.length, self.epsilon)

    def upper_bound(self, options: np.ndarray, step: int, pending: np.ndarray) -> np.ndarray:
        """``mean + kappa * variance`` of each option at ``step``, the variance given ``pending`` too."""
        at = np.full(len(options), float(step))
        # The variance also knows where the population trains next (no target needed for it).
        steps = np.concatenate([self.steps, np.full(len(pending), float(step))])
        points = np.concatenate([self.points.reshape(-1, options.shape[1]), pending])
        if len(steps):
            factor = self._factor(steps, points)
            v = torch.linalg.solve_triangular(factor, self.kernel(steps, points, at, options), upper=False)
            variance = torch.clamp(1.0 - (v**2).sum(dim=0), min=0.0).numpy()
        else:
            variance = np.ones(len(options))
        if self.targets.size == 0:  # nothing known yet: as far as possible from where agents train
            return variance
        factor = self._factor(self.steps, self.points)
        weights = torch.cholesky_solve(torch.as_tensor(self.targets, dtype=torch.float64)[:, None], factor)
        mean = (self.kernel(self.steps, self.points, at, options).T @ weights)[:, 0].numpy()
        kappa = math.sqrt(max(0.0, 0.2 * math.log(0.4 * self.targets.size)))
        return mean + kappa * variance

    def _factor(self, steps: np.ndarray, points: np.ndarray) -> torch.Tensor:
        """The Cholesky factor of the points' covariance with the noise on its diagonal."""
        noise = self.noise * torch.eye(len(steps), dtype=torch.float64)
        return torch.linalg.cholesky(self.kernel(steps, points, steps, points) + noise)


def _distances(steps_a: np.ndarray, a: np.ndarray, steps_b: np.ndarray, b: np.ndarray) -> tuple:
    """Squared distances of the positions and steps apart, of every pair (a row of ``a``, of ``b``)."""
    ta, tb = (torch.as_tensor(np.asarray(x, dtype=np.float64)) for x in (a, b))
    sa, sb = (torch.as_tensor(x, dtype=torch.float64) for x in (steps_a, steps_b))
    return ((ta[:, None, :] - tb[None, :, :]) ** 2).sum(dim=-1), (sa[:, None] - sb[None, :]).abs()


def _covariance(squared: torch.Tensor, apart: torch.Tensor, length: float, epsilon: float) -> torch.Tensor:
    """``exp(-d^2 / length) * (1 - epsilon) ** (|i - j| / 2)`` (Ray Tune's TV_SquaredExp)."""
    return torch.exp(-squared / length) * (1.0 - epsilon) ** (0.5 * apart)
