"""The fair classical baseline of benchmarks/disturbances.py: a PID controller whose gains are searched.

Comparing a policy trained under disturbances with the nominal PD controller would flatter it: the
PD gains were tuned for the perfect model.

**The controller** (:class:`PIDController`) is the PD controller of ``drone_torchrl.envs.heuristic``
plus integral action on ``x`` and ``z``. Under a constant disturbance the PD controller settles off
its set points: a horizontal wind ``w`` (a fraction of the weight) needs a lean ``alpha = asin(w)``,
which the position-to-tilt law ``alpha = kp_x x`` only commands at ``x = asin(w) / kp_x`` (0.76 m for
``w = 0.3`` and the default ``kp_x = 0.4``, on the edge of the 0.8 m zone); a drone heavier than the
controller believes hovers ``g (m / m0 - 1) / kp_z`` below its set point. An integrator on each
position error removes both offsets. It is written as a moving set point,
``target + (ki / kp) * integral(error dt)``, which is the same control law as adding
``ki * integral(error dt)`` to the PD output, with the integrals clamped to ``+-integral_limit``
(anti-windup). ``ki = 0`` is the PD controller exactly.

The controller keeps its integrals between calls, so it is a stateful policy: it must see every step
of its episodes in order, and flies one evaluation (``drone_torchrl.evaluation.evaluate``) from a
fresh instance or after :meth:`PIDController.reset`. Gains may be tensors (e.g. ``[C, 1]`` against
observations ``[C, E, 6]``): the tuner flies many candidate controllers in one batch.

**The tuner** (:func:`tune_pid`) searches the :class:`PIDGains` for the env settings at hand (its
disturbances included) on its own seeds, disjoint from the evaluation's: a random search over the
loops' natural frequencies and damping, the position-to-tilt gains and the two integral gains, then
a second round around the best. All candidates fly their episodes in one batch (the same start
states and disturbances for each). The nominal PD gains are always candidate 0, so the result is
never worse than PD on the tuning seeds. Altitude and attitude gains are searched as a natural
frequency ``w`` and a damping ratio ``zeta`` (``kp = w^2``, ``kd = 2 zeta w``), the form the PD
defaults were designed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from drone_torchrl.envs.dynamics import STATE_DIM, DroneParams, X, Z
from drone_torchrl.envs.heuristic import PDGains, pd_action


@dataclass(frozen=True)
class PIDGains:
    """PID gains: :class:`~drone_torchrl.envs.heuristic.PDGains` plus integral gains on ``z`` and ``x``.

    The integral gains are in ``(m/s^2)/(m s)`` on ``z`` and ``rad/(m s)`` on ``x``.
    """

    pd: PDGains = field(default_factory=PDGains)
    ki_x: float | torch.Tensor = 0.0
    ki_z: float | torch.Tensor = 0.0
    integral_limit: float | torch.Tensor = 1.0
    """Bound of each integral of the position error (m s)."""


class PIDController(TensorDictModuleBase):
    """:class:`PIDGains` as a TorchRL policy: reads ``"observation"`` (its first 6 entries), writes ``"action"``.

    Args:
        params: the drone's physical parameters and arena (as :func:`~drone_torchrl.envs.heuristic.pd_action` takes them).
        gains: the controller's gains (None: :class:`PIDGains`' defaults).
    """

    def __init__(self, params: DroneParams, gains: PIDGains | None = None) -> None:
        super().__init__()
        self.params = params
        self.gains = PIDGains() if gains is None else gains
        self.in_keys = ["observation"]
        self.out_keys = ["action"]
        self.integral: torch.Tensor | None = None

    def reset(self) -> None:
        """Forget the integrals: the next call starts new episodes."""
        self.integral = None

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write the PID commands (:meth:`act`) for the observation at ``in_keys[0]`` to ``out_keys[0]``."""
        tensordict.set(self.out_keys[0], self.act(tensordict.get(self.in_keys[0])))
        return tensordict

    def act(self, observation: torch.Tensor) -> torch.Tensor:
        """The commands for ``observation`` ``[..., >= 6]``; then the integrals take this step's error."""
        state = observation[..., :STATE_DIM]
        gains, pd = self.gains, self.gains.pd
        z_target = pd.z_target if pd.z_target is not None else self.params.zone_z_centre
        if self.integral is None:
            self.integral = state.new_zeros((*state.shape[:-1], 2))
        shift_x = gains.ki_x / pd.kp_x * self.integral[..., 0]
        shift_z = gains.ki_z / pd.kp_z * self.integral[..., 1]
        moved = replace(pd, x_target=pd.x_target + shift_x, z_target=z_target + shift_z)
        action = pd_action(state, self.params, moved)
        error = torch.stack((pd.x_target - state[..., X], z_target - state[..., Z]), -1)
        limit = torch.as_tensor(gains.integral_limit, dtype=state.dtype, device=state.device)
        limit = limit.unsqueeze(-1) if limit.dim() else limit
        self.integral = torch.minimum(torch.maximum(self.integral + error * self.params.dt, -limit), limit)
        return action


@dataclass(frozen=True)
class SearchSpace:
    """Ranges of the random search (log-uniform unless said), and its size."""

    altitude_frequency: tuple[float, float] = (3.0, 12.0)  # rad/s (PD: 8)
    attitude_frequency: tuple[float, float] = (6.0, 30.0)  # rad/s (PD: 20)
    damping: tuple[float, float] = (0.5, 1.5)  # both loops (PD: 1, critical)
    kp_x: tuple[float, float] = (0.1, 1.2)  # rad/m (PD: 0.4)
    kd_x: tuple[float, float] = (0.1, 1.2)  # rad/(m/s) (PD: 0.4)
    max_tilt: tuple[float, float] = (0.2, 0.6)  # rad (PD: 0.35); at most half the tilt limit
    ki_x: tuple[float, float] = (0.01, 1.0)  # rad/(m s); 0 in a quarter of the candidates
    ki_z: tuple[float, float] = (0.5, 40.0)  # (m/s^2)/(m s); 0 in a quarter of the candidates
    candidates: int = 64  # per round
    rounds: int = 2  # each after the first samples around the best so far
    narrowing: float = 0.25  # the next round's log-range, as a share of the previous one's
    seed: int = 1000  # of the tuning episodes (evaluations use seed 0 by default)
    episodes: int = 100


SEARCHED = ("altitude_frequency", "attitude_frequency", "damping", "kp_x", "kd_x", "max_tilt", "ki_x", "ki_z")


def _log_uniform(low: float, high: float, n: int, generator: torch.Generator) -> torch.Tensor:
    u = torch.rand(n, generator=generator, dtype=torch.float64)
    return torch.exp(math.log(low) + u * (math.log(high) - math.log(low)))


def _sample(space: SearchSpace, centre: dict[str, float] | None, generator: torch.Generator) -> dict:
    """``space.candidates`` values of each searched quantity; around ``centre`` after the first round."""
    n = space.candidates
    out = {}
    for name in SEARCHED:
        low, high = getattr(space, name)
        if centre is not None and centre[name] > 0:
            half = space.narrowing * 0.5 * math.log(high / low)
            low, high = centre[name] * math.exp(-half), centre[name] * math.exp(half)
        values = _log_uniform(low, high, n, generator)
        if name in ("ki_x", "ki_z"):
            off = torch.rand(n, generator=generator) < 0.25
            values = torch.where(off, torch.zeros_like(values), values)
        out[name] = values
    return out


def _gains(values: dict[str, torch.Tensor]) -> PIDGains:
    """Candidate gains as ``[C, 1]`` tensors (broadcast against observations ``[C, E, 6]``)."""
    col = lambda v: v.to(torch.float32).unsqueeze(-1)  # noqa: E731
    wz, wa, zeta = values["altitude_frequency"], values["attitude_frequency"], values["damping"]
    pd = replace(
        PDGains(),
        kp_z=col(wz**2),
        kd_z=col(2 * zeta * wz),
        kp_alpha=col(wa**2),
        kd_alpha=col(2 * zeta * wa),
        kp_x=col(values["kp_x"]),
        kd_x=col(values["kd_x"]),
        max_tilt=col(values["max_tilt"]),
    )
    return PIDGains(pd=pd, ki_x=col(values["ki_x"]), ki_z=col(values["ki_z"]))


def _nominal() -> dict[str, float]:
    pd = PDGains()
    return {
        "altitude_frequency": math.sqrt(pd.kp_z),
        "attitude_frequency": math.sqrt(pd.kp_alpha),
        "damping": pd.kd_z / (2 * math.sqrt(pd.kp_z)),
        "kp_x": pd.kp_x,
        "kd_x": pd.kd_x,
        "max_tilt": pd.max_tilt,
        "ki_x": 0.0,
        "ki_z": 0.0,
    }


def pick(values: dict[str, torch.Tensor], i: int) -> PIDGains:
    """Candidate ``i``'s gains as plain numbers."""
    one = {k: v[i : i + 1] for k, v in values.items()}
    gains = _gains(one)
    scalar = lambda v: float(v.reshape(-1)[0]) if isinstance(v, torch.Tensor) else v  # noqa: E731
    pd = replace(gains.pd, **{f: scalar(getattr(gains.pd, f)) for f in PDGains.__dataclass_fields__})
    return PIDGains(pd=pd, ki_x=scalar(gains.ki_x), ki_z=scalar(gains.ki_z))


def tune_pid(
    env_kwargs: dict[str, Any], space: SearchSpace | None = None, device: str = "cpu"
) -> tuple[PIDGains, dict]:
    """Search PID gains for ``env_kwargs`` (a ``DroneEnv``'s arguments, disturbances included).

    Returns the best gains (highest mean return over ``space.episodes`` episodes of ``space.seed``)
    and a record: each round's best mean return and the nominal PD's.
    """
    from drone_torchrl.config import physics_params
    from drone_torchrl.evaluation import evaluate

    space = SearchSpace() if space is None else space
    generator = torch.Generator().manual_seed(space.seed)
    params = physics_params(env_kwargs)
    best, best_return, record = _nominal(), -math.inf, {"rounds": []}
    for round_ in range(space.rounds):
        values = _sample(space, None if round_ == 0 else best, generator)
        # Candidate 0: the best so far (the nominal PD in the first round).
        for name, value in best.items():
            values[name][0] = value
        controller = PIDController(params, _gains(values))
        stats, _ = evaluate(
            controller, env_kwargs, space.episodes, space.seed, device, agents=space.candidates
        )
        returns = stats["return"].float().mean(-1)
        if round_ == 0:
            record["nominal_return"] = float(returns[0])
        i = int(returns.argmax())
        if float(returns[i]) > best_return:
            best_return = float(returns[i])
            best = {name: float(v[i]) for name, v in values.items()}
        record["rounds"].append(best_return)
    record["gains"] = best
    chosen = {k: torch.tensor([v], dtype=torch.float64) for k, v in best.items()}
    return pick(chosen, 0), record
