"""Pure, batched tensor functions for the 2D drone (the paper's eqs. 2.1-2.4, section 2.2).

This is the only copy of the physics: :class:`~drone_torchrl.envs.DroneEnv` (TorchRL) and
:class:`~drone_torchrl.envs.DroneGymEnv` (Gymnasium) both call it. Every function works on any
batch shape ``[*B, 6]`` with no Python loop over the batch.

State layout: ``[x, x_dot, z, z_dot, alpha, alpha_dot]`` in SI units, angles in radians,
``alpha`` measured from the vertical axis, positive counter-clockwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import torch

STATE_DIM = 6
ACTION_DIM = 2
STATE_NAMES = ("x", "x_dot", "z", "z_dot", "alpha", "alpha_dot")
X, X_DOT, Z, Z_DOT, ALPHA, ALPHA_DOT = range(STATE_DIM)

# Domain and target zone of the paper's Table 2.1 (angles converted to radians). They define the
# task, not the agent, so they live here rather than in the configs.
X_LIMIT = 2.0
Z_MIN, Z_MAX = 0.0, 4.0
ALPHA_LIMIT = math.pi / 3
ZONE_X_LIMIT = 0.8
ZONE_Z_MIN, ZONE_Z_MAX = 2.2, 3.2
ZONE_Z_CENTRE = 0.5 * (ZONE_Z_MIN + ZONE_Z_MAX)

# Each motor carrying half the weight holds a level drone still: the hover command of both motors.
HOVER_THRUST = 0.5

# Section 2.2: 0 on the terminating step, 10 per step in the zone, 1 per step elsewhere.
REWARD_TERMINATED = 0.0
REWARD_IN_ZONE = 10.0
REWARD_ALIVE = 1.0

# Section 2.1 item 2: x and alpha (floor) or every component (air) uniform in +-0.01.
RESET_NOISE = 0.01
RESET_MODES = ("floor", "air")


class TerminationCause(IntEnum):
    """Why an episode terminated. When several hold, the lowest non-zero code wins."""

    NONE = 0
    OUT_X = 1
    FLOOR = 2
    CEILING = 3
    TILT = 4


@dataclass(frozen=True)
class DroneParams:
    """Physical parameters of one drone; see :class:`~drone_torchrl.envs.DroneEnv` for meaning."""

    mass: float = 1.0
    motor_distance: float = 1.0
    gravity: float = 9.81
    dt: float = 0.02
    max_thrust: float | None = None
    floor_tolerance: float = 0.05

    @property
    def lever_arm(self) -> float:
        """``r``: half the diagonal motor-to-motor distance."""
        return 0.5 * self.motor_distance

    @property
    def inertia(self) -> float:
        """``I_yy = 2/5 m r^2`` (eq. 2.4, spherical mass distribution)."""
        return 0.4 * self.mass * self.lever_arm**2

    @property
    def weight(self) -> float:
        return self.mass * self.gravity


def clamp_action(action: torch.Tensor, max_thrust: float | None) -> torch.Tensor:
    """Clamp each motor command into ``[0, max_thrust]``; identity when unbounded (the paper)."""
    if max_thrust is None:
        return action
    return action.clamp(0.0, max_thrust)


def integrate(state: torch.Tensor, action: torch.Tensor, params: DroneParams) -> torch.Tensor:
    """One semi-implicit Euler step of eqs. 2.1-2.3.

    ``action`` is ``[a_l, a_r]``, thrust as a fraction of the weight (already clamped).
    Accelerations use the state before the step; positions use the new velocities.
    """
    x, x_dot, z, z_dot, alpha, alpha_dot = state.unbind(-1)
    thrust_left = action[..., 0] * params.weight
    thrust_right = action[..., 1] * params.weight
    total = thrust_left + thrust_right
    x_ddot = torch.sin(-alpha) * total / params.mass
    z_ddot = torch.cos(alpha) * total / params.mass - params.gravity
    alpha_ddot = (thrust_right - thrust_left) * (params.lever_arm / params.inertia)
    dt = params.dt
    x_dot = x_dot + x_ddot * dt
    z_dot = z_dot + z_ddot * dt
    alpha_dot = alpha_dot + alpha_ddot * dt
    return torch.stack(
        (x + x_dot * dt, x_dot, z + z_dot * dt, z_dot, alpha + alpha_dot * dt, alpha_dot), dim=-1
    )


def termination_cause(state: torch.Tensor, floor_tolerance: float) -> torch.Tensor:
    """Cause code (int64, shape ``[*B]``) for each state; ``0`` when inside the domain.

    Bounds are inclusive; the floor is hit only below ``-floor_tolerance``. Checks are applied
    from the highest code to the lowest so that the lowest non-zero code wins.
    """
    x, z, alpha = state[..., X], state[..., Z], state[..., ALPHA]
    cause = torch.zeros(state.shape[:-1], dtype=torch.int64, device=state.device)
    cause = torch.where(alpha.abs() > ALPHA_LIMIT, int(TerminationCause.TILT), cause)
    cause = torch.where(z > Z_MAX, int(TerminationCause.CEILING), cause)
    cause = torch.where(z < Z_MIN - floor_tolerance, int(TerminationCause.FLOOR), cause)
    cause = torch.where(x.abs() > X_LIMIT, int(TerminationCause.OUT_X), cause)
    return cause


def in_target_zone(state: torch.Tensor) -> torch.Tensor:
    """True where the state is inside the target zone (all three bounds, inclusive)."""
    x, z, alpha = state[..., X], state[..., Z], state[..., ALPHA]
    return (x.abs() <= ZONE_X_LIMIT) & (z >= ZONE_Z_MIN) & (z <= ZONE_Z_MAX) & (alpha.abs() <= ALPHA_LIMIT)


def reward(state: torch.Tensor, terminated: torch.Tensor) -> torch.Tensor:
    """Section 2.2 reward for the state after a step (float, shape ``[*B]``)."""
    alive = torch.where(in_target_zone(state), REWARD_IN_ZONE, REWARD_ALIVE)
    return torch.where(terminated, REWARD_TERMINATED, alive).to(state.dtype)


def step(
    state: torch.Tensor, action: torch.Tensor, params: DroneParams
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Advance ``state`` by one step: returns ``(next_state, reward, termination_cause)``.

    The action is clamped into ``[0, max_thrust]`` when the drone's thrust is bounded.
    """
    next_state = integrate(state, clamp_action(action, params.max_thrust), params)
    cause = termination_cause(next_state, params.floor_tolerance)
    # int(): TorchDynamo turns a comparison with the IntEnum member into a Python bool.
    return next_state, reward(next_state, cause != int(TerminationCause.NONE)), cause


def initial_state(
    shape: tuple[int, ...] | torch.Size,
    mode: str,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Sample start states of shape ``[*shape, 6]`` (section 2.1 item 2).

    ``"floor"``: ``x`` and ``alpha`` uniform in +-0.01, everything else zero.
    ``"air"``: every component uniform in +-0.01 around ``(x=0, z=zone centre)``.
    Exactly ``numel(shape) * 6`` numbers are drawn from ``generator`` in both modes, so the same
    seed gives the same draws whatever the batch layout. They are drawn on the generator's device
    and then moved to ``device``: a CPU generator gives the same start states on every device.
    """
    if mode not in RESET_MODES:
        raise ValueError(f"reset_mode={mode!r} is not allowed; expected one of {RESET_MODES}")
    draw_on = device if generator is None else generator.device
    uniform = torch.rand((*shape, STATE_DIM), generator=generator, device=draw_on, dtype=dtype)
    return states_from_uniform(uniform if device is None else uniform.to(device), mode)


def states_from_uniform(uniform: torch.Tensor, mode: str) -> torch.Tensor:
    """Start states ``[*B, 6]`` from uniforms in [0, 1) of the same shape (see :func:`initial_state`)."""
    noise = (2.0 * uniform - 1.0) * RESET_NOISE
    device, dtype = uniform.device, uniform.dtype
    if mode == "air":
        centre = torch.zeros(STATE_DIM, device=device, dtype=dtype)
        centre[Z] = ZONE_Z_CENTRE
        return noise + centre
    keep = torch.zeros(STATE_DIM, device=device, dtype=dtype)
    keep[X] = keep[ALPHA] = 1.0
    return noise * keep
