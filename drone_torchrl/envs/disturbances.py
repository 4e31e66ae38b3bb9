"""Disturbances and model mismatch: what the nominal model of :mod:`.dynamics` leaves out.

The paper's drone is a perfect model: no wind, the mass the controller believes, identical motors
that act at once, exact measurements. A :class:`Disturbance` adds, each drawn per drone and per
episode (all zero by default, the paper's task):

- **wind**: a constant horizontal force ``w * m0 g`` with ``w`` uniform in ``[-wind, wind]``, plus
  gusts ``v_t * m0 g``, an Ornstein-Uhlenbeck process with stationary standard deviation ``gust``
  and correlation time ``gust_time``: ``v_{t+1} = v_t e^{-dt/tau} + gust sqrt(1 - e^{-2 dt/tau})
  n_t`` (exact for an OU process sampled every ``dt``), ``v_0`` drawn from the stationary law.
  ``m0`` is the nominal mass, so ``wind=0.1`` pushes with a tenth of the nominal weight.
- **mass**: the true mass is ``m = m0 (1 + mass u)``, ``u`` uniform in ``[-1, 1]``; the moment of
  inertia follows it (``I = 2/5 m r^2``). The commands stay fractions of the *nominal* weight, so a
  heavier drone really has less thrust to spare: with ``max_thrust=1`` a drone 30% heavier has a
  thrust-to-weight ratio of ``2 / 1.3 = 1.54`` and climbs at ``0.54 g`` at most.
- **motor_gain**: each motor's thrust is its command times a gain uniform in
  ``[1 - motor_gain, 1 + motor_gain]`` (left and right drawn independently), after the command
  is clamped to ``[0, max_thrust]``: a weaker motor cannot be compensated past its limit.
- **motor_lag**: the thrust follows the command through a first-order lag of time constant
  ``tau``, ``f_{t+1} = f_t + (1 - e^{-dt/tau}) (u_t - f_t)`` (exact for a constant command over the
  step); the new ``f_{t+1}`` acts during step ``t``.
- **action_delay**: a command acts ``action_delay`` steps after it is issued.

With lag or delay the motors start at the nominal hover command (``f_0 = 0.5``, and the commands
in flight too): a drone resting on the floor is held up by it, and with motors that start from 0
a lagged or delayed drone would sink through the floor tolerance before any command of the
policy's took effect.

- **observation noise**: Gaussian noise of standard deviation ``noise_position`` (m) on the
  observed ``x`` and ``z`` and ``noise_angle`` (rad) on the observed ``alpha``, a fresh draw each
  step; velocities are observed exactly (as from a filtered estimate). Reward and termination use
  the true state.

Lag and delay make the observation non-Markov (the thrust in effect is not in it): with
``observed_actions=k`` the last ``k`` commands the policy issued are appended to the observation,
newest first (``6 + 2k`` entries).

Randomness is counter-based (:mod:`drone_torchrl.envs.rng`): each episode of each drone gets
one 64-bit key when it starts, and every number of that episode is a hash of (key, step, stream,
index). An episode's disturbances are therefore the same whatever the batch it is flown in, its
position in it, and the engine that flies it: only the key must match.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import torch

from drone_torchrl.checks import as_override, check_number
from drone_torchrl.envs import dynamics, params, rng
from drone_torchrl.envs.dynamics import ACTION_DIM, ALPHA, HOVER_THRUST, DroneParams, X, Z

# Streams of the counter-based generator (distinct from the training engine's 1 and 2).
EPISODE_STREAM = 11  # per-episode draws (wind, mass, gains, initial gust)
STEP_STREAM = 12  # per-step draws (gust innovation, observation noise)
# Per-episode uniforms: wind, mass, left gain, right gain; then one normal pair (initial gust, unused).
_EPISODE_UNIFORMS = 4
# Per-step normals: gust innovation, noise on x, z, alpha.
_STEP_NORMALS = 4


@dataclass(frozen=True)
class Disturbance:
    """Magnitudes of the disturbances (see the module docstring for each one's physics).

    ``wind`` and ``gust`` are fractions of the nominal weight; ``mass`` and ``motor_gain`` relative
    spreads; ``gust_time`` and ``motor_lag`` seconds; ``noise_position`` metres; ``noise_angle``
    radians; ``action_delay`` and ``observed_actions`` steps.
    """

    wind: float = 0.0
    gust: float = 0.0
    gust_time: float = 0.5
    mass: float = 0.0
    motor_gain: float = 0.0
    motor_lag: float = 0.0
    noise_position: float = 0.0
    noise_angle: float = 0.0
    action_delay: int = 0
    observed_actions: int = 0

    def __post_init__(self) -> None:
        for name, high in MAX_MAGNITUDES.items():
            value = getattr(self, name)
            check_number(name, value, low=0.0, high=high, low_open=name == "gust_time", dtype_range=False)
        for name in ("action_delay", "observed_actions"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_STEPS_BACK:
                raise ValueError(
                    f"{name}={as_override(value)} is not allowed; expected an integer in [0, {MAX_STEPS_BACK}]"
                )

    @property
    def active(self) -> bool:
        """Whether anything differs from the nominal model (the observation layout aside)."""
        return any(getattr(self, f.name) != f.default for f in fields(self) if f.name not in _LAYOUT)

    @property
    def nominal(self) -> bool:
        """Whether this is the nominal drone with its 6-entry observation (nothing to draw or carry)."""
        return not self.active and self.observed_actions == 0

    @property
    def observation_dim(self) -> int:
        """Entries of an observation, ``len(observation_names(self))``."""
        return len(observation_names(self))


# Upper bounds: a mass spread of 1 would allow a massless drone, a gain spread of 1 a dead motor.
MAX_MASS_SPREAD = 0.9
MAX_GAIN_SPREAD = 0.9
# Commands remembered for the delay or offered to the policy; 25 steps is half a second at 50 Hz.
MAX_STEPS_BACK = 25
# Upper bounds of the other magnitudes, past which they describe no drone that could fly (and, far
# past, overflow float32): wind and gusts of 10 weights (the strongest motors allowed, 100 weights
# each, are for benches, not wind); a gust correlation time and a motor lag of an hour (a constant
# wind, a motor that never answers within an episode); position noise of the largest arena (a
# kilometre) and angle noise of half a turn (pi: past it the noise wraps around).
MAX_FORCE = 10.0
MAX_TIME = 3600.0
MAX_MAGNITUDES = {
    "wind": MAX_FORCE,
    "gust": MAX_FORCE,
    "gust_time": MAX_TIME,
    "motor_lag": MAX_TIME,
    "noise_position": params.MAX_ARENA,
    "noise_angle": math.pi,
    # A drone lighter than nothing, or a motor with a negative gain, is not a disturbance.
    "mass": MAX_MASS_SPREAD,
    "motor_gain": MAX_GAIN_SPREAD,
}
FIELDS = tuple(f.name for f in fields(Disturbance))
# Fields that change what the policy sees, not the physics.
_LAYOUT = ("observed_actions", "gust_time")


def make(disturbance: Disturbance | Mapping[str, Any] | None) -> Disturbance:
    """Make a :class:`Disturbance` from itself, a mapping of its fields or ``None``.

    The mapping is e.g. a config's ``env.disturbance``; ``None`` is no disturbance. An unknown
    field raises a one-line ``ValueError``.
    """
    if disturbance is None:
        return Disturbance()
    if isinstance(disturbance, Disturbance):
        return disturbance
    if not isinstance(disturbance, Mapping):
        raise ValueError(
            f"disturbance={as_override(disturbance)} is not allowed; expected a mapping of {FIELDS} or None"
        )
    unknown = sorted(set(disturbance) - set(FIELDS))
    if unknown:
        raise ValueError(f"disturbance.{unknown[0]} is not a disturbance; expected one of {FIELDS}")
    try:
        return Disturbance(**disturbance)
    except ValueError as err:  # named as the env argument's field: disturbance.wind=...
        raise ValueError(f"disturbance.{err}") from None


def observation_names(disturbance: Disturbance | Mapping[str, Any] | None = None) -> tuple[str, ...]:
    """What each entry of the policy's observation is, in order: the one home of its layout.

    The state's six entries (``dynamics.STATE_NAMES``), then, with ``observed_actions=k``, the last
    ``k`` commands newest first: ``a_l[t-1], a_r[t-1], ..., a_r[t-k]``. Its length is the width the
    env's specs, the Gym twin, the networks, the memory estimate, the export and the kernels use
    (the loader compares the kernels' ``observation_dim`` with it). ``disturbance``: what
    :func:`make` takes (a config's ``env.disturbance`` too).
    """
    commands = range(1, make(disturbance).observed_actions + 1)
    return dynamics.STATE_NAMES + tuple(
        f"{motor}[t-{j}]" for j in commands for motor in dynamics.ACTION_NAMES
    )


class EpisodeDraw(NamedTuple):
    """What one episode of each drone drew at its start, shape ``[*B]`` (gains ``[*B, 2]``)."""

    wind: torch.Tensor  # constant horizontal force / nominal weight
    mass_ratio: torch.Tensor  # true mass / nominal mass
    gain: torch.Tensor  # left and right motor gains


class Internal(NamedTuple):
    """The state a disturbed drone carries besides its 6 physical numbers (all ``[*B, ...]``).

    ``key`` int64 episode keys; ``gust`` the gust force / nominal weight; ``thrust`` the motors'
    thrust fractions in effect (lag); ``pending`` the commands issued but not yet acting, oldest
    first (``[*B, action_delay, 2]``); ``issued`` the last commands the policy issued, newest first
    (``[*B, observed_actions, 2]``).
    """

    key: torch.Tensor
    draw: EpisodeDraw
    gust: torch.Tensor
    thrust: torch.Tensor
    pending: torch.Tensor
    issued: torch.Tensor


def replace_rows(internal: Internal, index: tuple[torch.Tensor, ...], fresh: Internal) -> Internal:
    """``internal`` with the rows ``index`` (integer indices of the batch) replaced by ``fresh``'s."""
    put = lambda old, new: old.index_put(index, new)  # noqa: E731
    draw = EpisodeDraw(*map(put, internal.draw, fresh.draw))
    return Internal(put(internal.key, fresh.key), draw, *map(put, internal[2:], fresh[2:]))


def draw_episode(
    disturbance: Disturbance, key: torch.Tensor, dtype: torch.dtype = torch.float32
) -> EpisodeDraw:
    """The per-episode draws of the drones whose episodes have keys ``key`` (int64 ``[*B]``)."""
    u = _uniform(key, 0, EPISODE_STREAM, _EPISODE_UNIFORMS, dtype)
    spread = 2.0 * u - 1.0  # uniform in (-1, 1)
    return EpisodeDraw(
        wind=disturbance.wind * spread[..., 0],
        mass_ratio=1.0 + disturbance.mass * spread[..., 1],
        gain=1.0 + disturbance.motor_gain * spread[..., 2:4],
    )


def start(disturbance: Disturbance, key: torch.Tensor, dtype: torch.dtype = torch.float32) -> Internal:
    """The internal state at the start of episodes with keys ``key`` (int64 ``[*B]``)."""
    shape = key.shape
    thrust = torch.full((*shape, ACTION_DIM), HOVER_THRUST, dtype=dtype, device=key.device)
    gust = disturbance.gust * _normal(key, 0, EPISODE_STREAM, 2, dtype, offset=_EPISODE_UNIFORMS)[..., 0]
    return Internal(
        key=key,
        draw=draw_episode(disturbance, key, dtype),
        gust=gust,
        thrust=thrust,
        pending=thrust.unsqueeze(-2).expand(*shape, disturbance.action_delay, ACTION_DIM).clone(),
        issued=torch.zeros(
            (*shape, disturbance.observed_actions, ACTION_DIM), dtype=dtype, device=key.device
        ),
    )


def observe(
    disturbance: Disturbance, state: torch.Tensor, internal: Internal, t: torch.Tensor | int
) -> torch.Tensor:
    """What the policy sees at step ``t`` (the step about to be taken): noisy state, then past commands."""
    obs = state
    if disturbance.noise_position or disturbance.noise_angle:
        n = _normal(internal.key, t, STEP_STREAM, _STEP_NORMALS, state.dtype)
        noise = torch.zeros_like(state)
        scale = (disturbance.noise_position, disturbance.noise_position, disturbance.noise_angle)
        noise[..., (X, Z, ALPHA)] = n[..., 1:] * state.new_tensor(scale)
        obs = state + noise
    if disturbance.observed_actions:
        obs = torch.cat((obs, internal.issued.flatten(-2)), -1)
    return obs


def step(
    disturbance: Disturbance,
    state: torch.Tensor,
    action: torch.Tensor,
    internal: Internal,
    t: torch.Tensor | int,
    params: DroneParams,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, Internal]:
    """One step of the disturbed drone: ``(next_state, reward, termination_cause, next_internal)``.

    ``action`` is the command issued at step ``t`` (as the policy gave it); the reward and the
    termination are :mod:`.dynamics`' on the true state.
    """
    issued = internal.issued
    if disturbance.observed_actions:
        issued = torch.cat((action.unsqueeze(-2), issued[..., :-1, :]), -2)
    command = action
    pending = internal.pending
    if disturbance.action_delay:
        command = pending[..., 0, :]
        pending = torch.cat((pending[..., 1:, :], action.unsqueeze(-2)), -2)
    command = dynamics.clamp_action(command, params.max_thrust)
    thrust = command
    if disturbance.motor_lag:
        thrust = internal.thrust + (1.0 - math.exp(-params.dt / disturbance.motor_lag)) * (
            command - internal.thrust
        )
    force = internal.draw.wind + internal.gust
    next_state = dynamics.integrate(
        state, thrust * internal.draw.gain, params, force, internal.draw.mass_ratio
    )
    cause = dynamics.termination_cause(next_state, params)
    reward = dynamics.reward(next_state, cause != int(dynamics.TerminationCause.NONE), params)
    gust = internal.gust
    if disturbance.gust:
        decay = math.exp(-params.dt / disturbance.gust_time)
        n = _normal(internal.key, t, STEP_STREAM, _STEP_NORMALS, state.dtype)
        gust = gust * decay + disturbance.gust * math.sqrt(1.0 - decay * decay) * n[..., 0]
    return next_state, reward, cause, Internal(internal.key, internal.draw, gust, thrust, pending, issued)


def episode_keys(
    generator: torch.Generator, shape: tuple[int, ...] | torch.Size, device: torch.device | str | None = None
) -> torch.Tensor:
    """Draw fresh int64 episode keys ``[*shape]``, independent of the batch layout.

    From a CPU generator, one draw per episode in row-major order, moved to ``device``.
    """
    keys = torch.randint(-(2**63), 2**63 - 1, tuple(shape), generator=generator, dtype=torch.int64)
    return keys if device is None else keys.to(device)


def _uniform(
    key: torch.Tensor, t: torch.Tensor | int, stream: int, n: int, dtype: torch.dtype
) -> torch.Tensor:
    flat = key.reshape(-1)
    counters = torch.as_tensor(t, dtype=torch.int64, device=flat.device)
    counters = counters.reshape(-1) if counters.dim() else counters
    return rng.uniform(flat, counters, stream, (n,)).to(dtype).reshape(*key.shape, n)


def _normal(
    key: torch.Tensor, t: torch.Tensor | int, stream: int, n: int, dtype: torch.dtype, offset: int = 0
) -> torch.Tensor:
    """``n`` standard normals per key (Box-Muller on uniforms ``offset..offset+n`` of the stream)."""
    return rng.box_muller(_uniform(key, t, stream, offset + n, dtype)[..., offset:])
