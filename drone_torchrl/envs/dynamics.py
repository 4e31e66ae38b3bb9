"""Pure, batched tensor functions for the 2D drone (the paper's eqs. 2.1-2.4, section 2.2).

This is the only copy of the physics: :class:`~drone_torchrl.envs.drone_env.DroneEnv` (TorchRL) and
:class:`~drone_torchrl.envs.gym_env.DroneGymEnv` (Gymnasium) both call it. Every function works on any
batch shape ``[*B, 6]`` with no Python loop over the batch.

State layout: ``[x, x_dot, z, z_dot, alpha, alpha_dot]`` in SI units, angles in radians,
``alpha`` measured from the vertical axis, positive counter-clockwise.
"""

from __future__ import annotations

from enum import IntEnum

import torch

from drone_torchrl.envs.params import DroneParams

STATE_NAMES = ("x", "x_dot", "z", "z_dot", "alpha", "alpha_dot")
ACTION_NAMES = ("a_l", "a_r")  # each motor's thrust as a fraction of the weight
STATE_DIM, ACTION_DIM = len(STATE_NAMES), len(ACTION_NAMES)
X, X_DOT, Z, Z_DOT, ALPHA, ALPHA_DOT = range(STATE_DIM)

# The precisions the physics runs in (env argument ``dtype``), by name.
DTYPES = {"float32": torch.float32, "float64": torch.float64}

#: The hover command of both motors; each carrying half the weight holds a level drone still.
HOVER_THRUST = 0.5

# Section 2.2: 0 on the terminating step, 10 per step in the zone, 1 per step elsewhere.
REWARD_TERMINATED = 0.0
REWARD_IN_ZONE = 10.0
REWARD_ALIVE = 1.0

#: The reset noise (section 2.1 item 2), x and alpha (floor) or every component (air) uniform in +-0.01.
RESET_NOISE = 0.01
RESET_MODES = ("floor", "air")


class TerminationCause(IntEnum):
    """Why an episode terminated. When several hold, the lowest non-zero code wins."""

    NONE = 0
    OUT_X = 1
    FLOOR = 2
    CEILING = 3
    TILT = 4


def clamp_action(action: torch.Tensor, max_thrust: float | None) -> torch.Tensor:
    """Clamp each motor command into ``[0, max_thrust]``; identity when unbounded (the paper)."""
    return action if max_thrust is None else action.clamp(0.0, max_thrust)


def integrate(
    state: torch.Tensor,
    action: torch.Tensor,
    params: DroneParams,
    force: torch.Tensor | None = None,
    mass_ratio: torch.Tensor | None = None,
) -> torch.Tensor:
    """One semi-implicit Euler step of eqs. 2.1-2.3.

    ``action`` is ``[a_l, a_r]``, thrust as a fraction of the nominal weight ``m0 g`` (already
    clamped). Accelerations use the state before the step; positions use the new velocities.

    Model mismatch (:mod:`.disturbances`): ``force`` ``[*B]`` is a horizontal force as a fraction of
    the nominal weight, ``mass_ratio`` ``[*B]`` the true mass over the nominal one (the inertia
    follows it, ``I = 2/5 m r^2``), both given or neither. Then ``x'' = g (sin(-alpha) (a_l + a_r) + force) / ratio``,
    ``z'' = g cos(alpha) (a_l + a_r) / ratio - g`` and ``alpha'' = (a_r - a_l) m0 g r / (I0 ratio)``.
    Without them (the paper's drone) the same equations are computed as the spec writes them, in
    thrusts ``T = a m g`` (the arithmetic the C++ kernels round alike).
    """
    alpha = state[..., ALPHA]
    if mass_ratio is None:
        thrust_left = action[..., 0] * params.weight
        thrust_right = action[..., 1] * params.weight
        total = thrust_left + thrust_right
        x_ddot = torch.sin(-alpha) * total / params.mass
        z_ddot = torch.cos(alpha) * total / params.mass - params.gravity
        alpha_ddot = (thrust_right - thrust_left) * (params.lever_arm / params.inertia)
    else:
        g = params.gravity
        total = action[..., 0] + action[..., 1]
        x_ddot = g * (torch.sin(-alpha) * total + force) / mass_ratio
        z_ddot = g * torch.cos(alpha) * total / mass_ratio - g
        alpha_ddot = (
            (action[..., 1] - action[..., 0])
            * params.weight
            * params.lever_arm
            / (params.inertia * mass_ratio)
        )
    dt = params.dt
    x, x_dot, z, z_dot, alpha, alpha_dot = state.unbind(-1)
    x_dot = x_dot + x_ddot * dt
    z_dot = z_dot + z_ddot * dt
    alpha_dot = alpha_dot + alpha_ddot * dt
    return torch.stack(
        (x + x_dot * dt, x_dot, z + z_dot * dt, z_dot, alpha + alpha_dot * dt, alpha_dot), dim=-1
    )


def termination_cause(state: torch.Tensor, params: DroneParams) -> torch.Tensor:
    """Cause code (int64, shape ``[*B]``) for each state; ``0`` when inside the domain.

    Inclusive bounds: a state on a bound is inside; strict bounds (``params.bounds``): it is out.
    The floor is hit only below ``z_min - floor_tolerance`` (or on it, strict). Checks are applied
    from the highest code to the lowest so that the lowest non-zero code wins. A bound is compared
    in the state's dtype (the nearest float32 to 0.8 is "on" 0.8 in float32).
    """
    x, z, alpha = state[..., X], state[..., Z], state[..., ALPHA]
    # above(v, b): v beyond the upper bound b; below(v, b): v beyond the lower bound b.
    above, below = (torch.ge, torch.le) if params.strict else (torch.gt, torch.lt)
    cause = torch.zeros(state.shape[:-1], dtype=torch.int64, device=state.device)
    cause = torch.where(above(alpha.abs(), params.alpha_limit), int(TerminationCause.TILT), cause)
    cause = torch.where(above(z, params.z_max), int(TerminationCause.CEILING), cause)
    cause = torch.where(below(z, params.floor), int(TerminationCause.FLOOR), cause)
    cause = torch.where(above(x.abs(), params.x_limit), int(TerminationCause.OUT_X), cause)
    return cause


def in_target_zone(state: torch.Tensor, params: DroneParams) -> torch.Tensor:
    """True where the state ``[*B, 6]`` is inside the target zone (``[*B]`` bool).

    Inside means ``|x| <= zone_x_limit``, ``zone_z_min <= z <= zone_z_max`` and
    ``|alpha| <= alpha_limit`` (``<`` each with strict bounds).
    """
    x, z, alpha = state[..., X], state[..., Z], state[..., ALPHA]
    within, over = (torch.lt, torch.gt) if params.strict else (torch.le, torch.ge)
    return (
        within(x.abs(), params.zone_x_limit)
        & over(z, params.zone_z_min)
        & within(z, params.zone_z_max)
        & within(alpha.abs(), params.alpha_limit)
    )


def reward(state: torch.Tensor, terminated: torch.Tensor, params: DroneParams) -> torch.Tensor:
    """Section 2.2 reward for the state after a step (the state's dtype, shape ``[*B]``)."""
    alive = torch.where(in_target_zone(state, params), REWARD_IN_ZONE, REWARD_ALIVE)
    return torch.where(terminated, REWARD_TERMINATED, alive).to(state.dtype)


def step(
    state: torch.Tensor, action: torch.Tensor, params: DroneParams
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Advance ``state`` by one step: returns ``(next_state, reward, termination_cause)``.

    The action is clamped into ``[0, max_thrust]`` when the drone's thrust is bounded.
    """
    next_state = integrate(state, clamp_action(action, params.max_thrust), params)
    cause = termination_cause(next_state, params)
    # int(): TorchDynamo turns a comparison with the IntEnum member into a Python bool.
    return next_state, reward(next_state, cause != int(TerminationCause.NONE), params), cause


def initial_state(
    shape: tuple[int, ...] | torch.Size,
    mode: str,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
    params: DroneParams | None = None,
) -> torch.Tensor:
    """Sample start states of shape ``[*shape, 6]`` (section 2.1 item 2) in ``dtype``.

    ``"floor"``: ``x`` and ``alpha`` uniform in +-0.01, ``z = z_min`` (the floor), the rest zero.
    ``"air"``: every component uniform in +-0.01 around ``(x=0, z=zone centre)``.
    ``params`` gives the floor and the zone (default: the paper's).
    Exactly ``numel(shape) * 6`` float32 uniforms are drawn from ``generator`` in both modes and
    in either dtype, so the same seed gives the same draws whatever the batch layout, and float64
    start states are the float32 ones up to the exact centre (:func:`states_from_uniform`). They are
    drawn on the generator's device and then moved to ``device``: a CPU generator gives the same
    start states on every device.
    """
    if mode not in RESET_MODES:
        raise ValueError(f"reset_mode={mode!r} is not allowed; expected one of {RESET_MODES}")
    draw_on = device if generator is None else generator.device
    uniform = torch.rand((*shape, STATE_DIM), generator=generator, device=draw_on, dtype=torch.float32)
    return states_from_uniform(uniform if device is None else uniform.to(device), mode, params, dtype)


def states_from_uniform(
    uniform: torch.Tensor, mode: str, params: DroneParams | None = None, dtype: torch.dtype | None = None
) -> torch.Tensor:
    """Start states ``[*B, 6]`` from uniforms in [0, 1) of the same shape (see :func:`initial_state`).

    The +-0.01 noise is computed in the uniforms' dtype (float32: what the C++ kernels compute),
    then converted to ``dtype`` (default: the uniforms') and added to the start point in ``dtype``:
    ``z = z_min`` ("floor") or the zone's centre ("air") of ``params`` (default: the paper's).
    """
    params = _PAPER if params is None else params
    dtype = uniform.dtype if dtype is None else dtype
    device = uniform.device
    noise = ((2.0 * uniform - 1.0) * RESET_NOISE).to(dtype)
    base = torch.zeros(STATE_DIM, device=device, dtype=dtype)
    if mode == "air":
        base[Z] = params.zone_z_centre
        return noise + base
    keep = torch.zeros(STATE_DIM, device=device, dtype=dtype)
    keep[X] = keep[ALPHA] = 1.0
    base[Z] = params.z_min
    return noise * keep + base


_PAPER = DroneParams()
