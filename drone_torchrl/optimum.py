"""The best achievable return of an episode, computed exactly, and an optimal thrust sequence.

The reward counts the steps that end inside the target zone (10 each) and the other steps the
drone survives (1 each). Only the vertical motion decides when the drone can be in the zone, and
the vertical motion is linear in the *vertical thrust* ``c = cos(alpha) (a_l + a_r)`` (thrust as a
multiple of the weight): ``z_dot += (c - 1) g dt; z += z_dot dt`` (semi-implicit Euler, the
env's own recursion). With each motor in ``[0, max_thrust]`` and ``|alpha| <= pi/3`` while alive,
``c`` lies in ``[0, 2 max_thrust]``, so the vertical problem with ``c`` free in that interval is
a relaxation: the most zone steps it allows bounds every policy. ``docs/optimum.md`` derives it.

- :func:`zone_margin` solves one linear program (SciPy's HiGHS): the largest margin by which a
  vertical plan can stay inside the zone from a given step to the end, surviving the steps before.
- :func:`earliest_zone_step` finds the first step from which the drone can be in the zone for the
  rest of the episode (a sequence of those LPs, bisected: the margin only grows with the step).
- :func:`max_zone_steps` is one mixed-integer program that counts the zone steps of any thrust
  sequence, without assuming the drone stays once in: the upper bound.
- :func:`optimum` puts them together (:class:`Optimum`); :func:`env_optimum` does it for the
  starts an env resets to (``"floor"``: all share ``z = z_dot = 0``; ``"air"``: a box of starts).
- :func:`fly_plan` replays a vertical plan on the full 2D dynamics (:func:`dynamics.step <.dynamics.step>`)
  and then hands over to the PD controller, which levels the drone and holds it in the zone.
"""

from __future__ import annotations

import bisect
import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy import sparse
from scipy.optimize import Bounds, LinearConstraint, linprog, milp
from tensordict.nn import TensorDictModule

from drone_torchrl.envs import dynamics
from drone_torchrl.envs.dynamics import ACTION_DIM, ALPHA, HOVER_THRUST, Z_DOT, DroneParams, Z
from drone_torchrl.envs.heuristic import PDGains, pd_action
from drone_torchrl.envs.rollout import Episodes, fly_reference

# The reward of a step in the zone beyond that of any other surviving step (10 - 1).
ZONE_BONUS = dynamics.REWARD_IN_ZONE - dynamics.REWARD_ALIVE
FLOOR_START = (0.0, 0.0)  # (z, z_dot) of every floor start
# HiGHS solves to about 1e-9 here; a margin above -this counts as feasible (m).
MARGIN_TOLERANCE = 1e-7
MILP_TIME_LIMIT_S = 60.0

Start = tuple[float, float]
"""A vertical start state ``(z, z_dot)``."""


@dataclass(frozen=True)
class VerticalPlan:
    """A vertical thrust sequence and the vertical states it flies through (arrays of ``steps``).

    ``collective[t - 1]`` is the vertical thrust ``c`` of step ``t`` (multiple of the weight);
    ``z[t - 1]`` and ``z_dot[t - 1]`` the state after step ``t``. ``margin``: the least distance (m)
    between the zone's limits and ``z`` over the steps from ``first_zone_step`` on.
    """

    first_zone_step: int
    collective: np.ndarray
    z: np.ndarray
    z_dot: np.ndarray
    margin: float

    @property
    def apex_step(self) -> int:
        """The first step, from the zone entry on, that ends with ``z_dot <= 0`` (the top of the climb)."""
        after = np.flatnonzero(self.z_dot[self.first_zone_step - 1 :] <= 0.0)
        return self.first_zone_step + int(after[0]) if after.size else len(self.z)


@dataclass(frozen=True)
class Optimum:
    """The best achievable return of an episode of ``steps`` steps (see :func:`optimum`)."""

    steps: int
    zone_steps: int
    """The most steps that can end in the zone (the upper bound)."""
    first_zone_step: int
    """The earliest step from which the drone can stay in the zone to the end (0 if never)."""
    plan: VerticalPlan | None
    """A vertical plan that enters at ``first_zone_step`` and stays (the largest margin), or ``None``."""

    @property
    def best_return(self) -> float:
        """``steps`` rewards of at least 1, ``zone_steps`` of them 10: the bound on any episode's return."""
        return dynamics.REWARD_ALIVE * self.steps + ZONE_BONUS * self.zone_steps

    @property
    def exact(self) -> bool:
        """Whether the bound is reached in the vertical problem from ``first_zone_step`` on.

        Entering the zone at ``first_zone_step`` and staying gives ``zone_steps`` steps in it (for a
        drone that can hover).
        """
        if self.first_zone_step == 0:
            return self.zone_steps == 0  # the zone is out of reach; hovering earns the 1s
        return self.steps - self.first_zone_step + 1 == self.zone_steps

    def describe(self) -> str:
        """How the bound is made up, e.g. ``"in the zone from step 35, 266 of 300 steps"``."""
        if self.zone_steps == 0:
            return f"the zone is out of reach in {self.steps} steps: surviving them is the best"
        if not self.exact:
            return (
                f"at most {self.zone_steps} of {self.steps} steps in the zone, "
                "an upper bound no plan staying there reaches"
            )
        return f"in the zone from step {self.first_zone_step}, {self.zone_steps} of {self.steps} steps"


def collective_limit(params: DroneParams, tilt: float = 0.0) -> float | None:
    """The largest vertical thrust ``c`` (multiple of the weight), or ``None`` when unbounded.

    It is ``2 max_thrust cos(tilt)``, ``None`` when the thrust is unbounded; ``tilt`` is a roll
    angle that the drone keeps.
    """
    if params.max_thrust is None:
        return None
    return ACTION_DIM * params.max_thrust * math.cos(tilt)


def _recursion(
    params: DroneParams, steps: int, start: Start, extra: int
) -> tuple[sparse.csr_array, np.ndarray]:
    """The semi-implicit Euler recursion as ``2 steps`` linear equalities ``A x = b``.

    Variables ``x = [c_1..c_T, z_dot_1..z_dot_T, z_1..z_T, extra...]``:
    ``z_dot_t - z_dot_{t-1} - g dt c_t = -g dt`` and ``z_t - z_{t-1} - dt z_dot_t = 0``, with the
    start's ``(z_0, z_dot_0)`` moved to the right-hand side of the rows of step 1.
    """
    g, dt, n = params.gravity, params.dt, steps
    eye = sparse.eye_array(n, format="csr")
    previous = sparse.eye_array(n, k=-1, format="csr")
    zero = sparse.csr_array((n, n))
    pad = sparse.csr_array((n, extra))
    velocity = sparse.hstack([-g * dt * eye, eye - previous, zero, pad])
    position = sparse.hstack([zero, -dt * eye, eye - previous, pad])
    b_velocity = np.full(n, -g * dt)
    b_position = np.zeros(n)
    b_velocity[0] += start[1]
    b_position[0] += start[0]
    return sparse.vstack([velocity, position], format="csr"), np.concatenate([b_velocity, b_position])


def _zone_rows(held: sparse.csr_array, low: sparse.csr_array, high: sparse.csr_array) -> sparse.csr_array:
    """The rows ``-z_t + low x' <= .`` then ``z_t + high x' <= .`` of the steps ``held`` picks.

    ``x'`` are the variables after ``z`` (:func:`_recursion`'s ``extra``), ``low`` and ``high`` their columns.
    """
    zero = sparse.csr_array(held.shape)
    return sparse.vstack(
        [sparse.hstack([zero, zero, -held, low]), sparse.hstack([zero, zero, held, high])], format="csr"
    )


def zone_margin(
    params: DroneParams,
    steps: int,
    first_zone_step: int,
    start: Start = FLOOR_START,
    thrust_cap: float | None = None,
) -> VerticalPlan | None:
    """The vertical plan that stays in the zone from ``first_zone_step`` with the largest margin.

    The plan runs through ``steps``; it is one LP, and the margin is negative where the zone cannot
    be held from that step.

    Every step keeps ``z`` inside the domain (the floor with its tolerance); the steps from
    ``first_zone_step`` on keep ``zone_z_min + margin <= z <= zone_z_max - margin`` (``params``' zone); ``c`` lies in
    ``[0, thrust_cap]`` (``thrust_cap=None``: :func:`collective_limit`, and free when the thrust is
    unbounded). Returns ``None`` if even the domain cannot be kept.
    """
    if not 1 <= first_zone_step <= steps:
        raise ValueError(f"first_zone_step={first_zone_step} is not allowed; expected 1..{steps}")
    n = steps
    cap = collective_limit(params) if thrust_cap is None else thrust_cap
    a_eq, b_eq = _recursion(params, n, start, extra=1)
    # Zone rows for t >= first_zone_step:  -z_t + margin <= -z_min  and  z_t + margin <= z_max.
    held = sparse.eye_array(n, format="csr")[first_zone_step - 1 :]  # picks those z_t
    margin = sparse.csr_array(np.ones((held.shape[0], 1)))
    a_ub = _zone_rows(held, margin, margin)
    b_ub = np.concatenate(
        [np.full(held.shape[0], -params.zone_z_min), np.full(held.shape[0], params.zone_z_max)]
    )
    low, high = params.z_min - params.floor_tolerance, params.z_max  # the floor counts as hit only below it
    bounds = [(0.0, cap) if cap is not None else (None, None)] * n + [(None, None)] * n + [(low, high)] * n
    bounds.append((None, None))
    objective = np.zeros(3 * n + 1)
    objective[-1] = -1.0  # maximise the margin
    result = linprog(objective, A_ub=a_ub, b_ub=b_ub, A_eq=a_eq, b_eq=b_eq, bounds=bounds, method="highs")
    if result.status != 0:
        return None
    x = result.x
    return VerticalPlan(first_zone_step, x[:n], x[2 * n : 3 * n], x[n : 2 * n], float(x[-1]))


def earliest_zone_step(
    params: DroneParams, steps: int, start: Start = FLOOR_START, thrust_cap: float | None = None
) -> VerticalPlan | None:
    """The largest-margin plan of the earliest step from which the drone can stay in the zone.

    Staying means being in the zone at every step from ``k`` through ``steps``; ``None`` if no
    step ``k`` allows it.

    A sequence of :func:`zone_margin` LPs, bisected on ``k``: holding the zone from ``k`` asks for
    more than holding it from ``k + 1``, so the margin never decreases with ``k``.
    """

    @functools.cache
    def holds(k: int) -> VerticalPlan | None:
        plan = zone_margin(params, steps, k, start, thrust_cap)
        return plan if plan is not None and plan.margin >= -MARGIN_TOLERANCE else None

    if holds(steps) is None:
        return None
    # The smallest k in 1..steps that holds (steps does), bisected; each LP is solved once (cached).
    return holds(bisect.bisect_left(range(steps), True, lo=1, key=lambda k: holds(k) is not None))


def _height_range(params: DroneParams, steps: int, start: Start, cap: float) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and highest ``z`` after each step over all ``c`` in ``[0, cap]`` (``z`` grows with every ``c_t``)."""

    def fly(collective: float) -> np.ndarray:
        # np.cumsum adds in order, as the env's recursion does: the same floats.
        z_dot = np.cumsum([start[1], *[(collective - 1.0) * params.gravity * params.dt] * steps])[1:]
        return np.cumsum([start[0], *(z_dot * params.dt)])[1:]

    return fly(0.0), fly(cap)


def max_zone_steps(params: DroneParams, steps: int, start: Start = FLOOR_START) -> int:
    """The most steps whose end state can lie in the zone, over every vertical thrust sequence.

    The sequences have ``c`` in ``[0, 2 max_thrust]``; one MILP, bounded thrust only.

    Nothing else is assumed: the drone may leave the zone and come back, and the domain is not
    enforced (so trajectories that end in a crash are counted too). One binary per step says "in
    the zone"; big-M rows with each step's reachable height range switch the zone bounds on.
    """
    cap = collective_limit(params)
    if cap is None:
        raise ValueError(
            "max_zone_steps needs bounded thrust (max_thrust); with unbounded thrust every step can be in the zone"
        )
    n = steps
    a_eq, b_eq = _recursion(params, n, start, extra=n)
    z_low, z_high = _height_range(params, n, start, cap)
    big_low = np.maximum(params.zone_z_min - z_low, 0.0)  # -z_t + M b_t <= -z_min + M
    big_high = np.maximum(z_high - params.zone_z_max, 0.0)  # z_t + M b_t <= z_max + M
    rows = _zone_rows(
        sparse.eye_array(n, format="csr"), sparse.diags_array(big_low), sparse.diags_array(big_high)
    )
    upper = np.concatenate([big_low - params.zone_z_min, big_high + params.zone_z_max])
    inf = np.inf
    lower_bounds = np.concatenate([np.zeros(n), np.full(2 * n, -inf), np.zeros(n)])
    upper_bounds = np.concatenate([np.full(n, cap), np.full(2 * n, inf), np.ones(n)])
    objective = np.concatenate([np.zeros(3 * n), -np.ones(n)])
    result = milp(
        objective,
        constraints=[LinearConstraint(a_eq, b_eq, b_eq), LinearConstraint(rows, -inf, upper)],
        integrality=np.concatenate([np.zeros(3 * n), np.ones(n)]),
        bounds=Bounds(lower_bounds, upper_bounds),
        options={"mip_rel_gap": 0.0, "time_limit": MILP_TIME_LIMIT_S},
    )
    if result.status == 0:
        return round(-result.fun)
    # Out of time: HiGHS's dual bound still bounds the count from above.
    bound = getattr(result, "mip_dual_bound", None)
    if bound is None or not math.isfinite(bound):
        raise RuntimeError(f"the zone-step MILP failed: {result.message}")
    return min(n, math.floor(-bound + MARGIN_TOLERANCE))


def optimum(params: DroneParams, steps: int, start: Start = FLOOR_START) -> Optimum:
    """The best achievable return from the vertical start ``start`` (see :class:`Optimum`).

    Bounded thrust: the count of :func:`max_zone_steps` (MILP) bounds the return; the earliest
    entry to stay (:func:`earliest_zone_step`, LPs) shows which plan reaches it. Unbounded thrust:
    no limit on ``c``, so the zone is held from the first step (a thrust pulse of several hundred
    weights); the bound is then the ceiling ``10 * steps``.
    """
    plan = earliest_zone_step(params, steps, start)
    if params.max_thrust is None:
        # c_1 alone puts z_1 anywhere and c_2 stops the drone there: the LPs find k* = 1, N = steps.
        zone_steps = 0 if plan is None else steps - plan.first_zone_step + 1
    else:
        zone_steps = max_zone_steps(params, steps, start)
    first = 0 if plan is None else plan.first_zone_step
    return Optimum(steps, zone_steps, first, plan)


@functools.cache
def env_optimum(params: DroneParams, max_steps: int, reset_mode: str) -> Optimum | None:
    """The best achievable return of every episode that starts as ``reset_mode`` resets.

    ``None`` where it is not derived.

    ``"floor"``: every start has ``z = z_dot = 0`` (``x`` and ``alpha`` do not enter the vertical
    problem), so one :func:`optimum` serves all. ``"air"``: the set of vertical starts from which the
    zone can be held from step 1 on is convex (the projection of the LP's feasible set), so if every
    corner of the start box holds it, every air start does, and the bound is the ceiling
    ``10 * max_steps``; otherwise ``None``. ``None`` too when ``max_thrust`` is below the hover
    thrust (the drone cannot stay up, and how long it survives is outside this model). The zone
    and the domain are ``params``' (the env's arguments). With ``bounds="strict"`` the LPs still
    allow a height exactly on a bound, so the number bounds the return from above but may not be
    reached (the zone is open then). Cached: computed once per argument set in a process.
    """
    if params.max_thrust is not None and params.max_thrust < HOVER_THRUST:
        return None
    if reset_mode == "floor":
        return optimum(params, max_steps, (params.z_min, FLOOR_START[1]))
    if reset_mode != "air":
        raise ValueError(f"reset_mode={reset_mode!r} is not allowed; expected one of {dynamics.RESET_MODES}")
    # The air box: z and z_dot within RESET_NOISE of the zone's centre and of rest; its corners.
    noise, centre = dynamics.RESET_NOISE, params.zone_z_centre
    corners = [(centre + dz, dv) for dz in (-noise, noise) for dv in (-noise, noise)]
    plans = [zone_margin(params, max_steps, 1, corner) for corner in corners]
    if any(plan is None or plan.margin < -MARGIN_TOLERANCE for plan in plans):
        return None
    return Optimum(max_steps, max_steps, 1, None)


def fly_plan(
    start: torch.Tensor, params: DroneParams, max_steps: int, gains: PDGains | None = None
) -> tuple[Episodes, VerticalPlan]:
    """Replay an optimal vertical plan from the floor starts ``start`` ``[B, 6]``.

    The plan is flown through :func:`dynamics.step <.dynamics.step>`; returns the episodes
    (:func:`~drone_torchrl.episodes.episode_stats` reads them) and the plan.

    Up to the top of the climb (:attr:`VerticalPlan.apex_step`) both motors get ``c_t / (2 cos
    alpha)``: with equal thrusts and ``alpha_dot = 0`` the roll angle stays at its start value, so
    the vertical motion is the plan's exactly. The plan is solved with ``c`` at most ``2 max_thrust
    cos(max |alpha_0|)``, so that command never exceeds ``max_thrust``. Afterwards the PD controller
    (``gains``) levels the drone, brings ``x`` back and holds the zone. The first zone step is
    :func:`earliest_zone_step`'s for the tilted limit; where it differs from the level one the
    bound is not reached (and the caller sees it in the returns).
    """
    if not torch.all(start[..., Z] == FLOOR_START[0]) or not torch.all(start[..., Z_DOT] == FLOOR_START[1]):
        raise ValueError("fly_plan replays floor starts (z = z_dot = 0)")
    tilt = float(start[..., ALPHA].abs().max())
    plan = earliest_zone_step(params, max_steps, FLOOR_START, thrust_cap=collective_limit(params, tilt))
    if plan is None:
        raise ValueError("the zone cannot be held from any step with these parameters")
    collective = torch.as_tensor(plan.collective, dtype=start.dtype)

    def act(state: torch.Tensor, step_count: torch.Tensor) -> torch.Tensor:
        # The plan's commands until the top of its climb, then the PD controller.
        t = step_count.squeeze(-1)
        motor = collective[t.clamp_max(len(collective) - 1)] / (ACTION_DIM * torch.cos(state[..., ALPHA]))
        planned = motor.unsqueeze(-1).expand(*motor.shape, ACTION_DIM)
        return torch.where((t < plan.apex_step).unsqueeze(-1), planned, pd_action(state, params, gains))

    policy = TensorDictModule(act, in_keys=["observation", "step_count"], out_keys=["action"])
    dtype = "float64" if start.dtype == torch.float64 else "float32"
    episodes = fly_reference(policy, start, max_steps=max_steps, dtype=dtype, **dataclasses.asdict(params))
    return episodes, plan
