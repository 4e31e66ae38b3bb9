"""Pure, batched tensor functions for the 2D drone (the paper's eqs. 2.1-2.4, section 2.2).

This is the only copy of the physics: :class:`~drone_torchrl.envs.drone_env.DroneEnv` (TorchRL) and
:class:`~drone_torchrl.envs.gym_env.DroneGymEnv` (Gymnasium) both call it. Every function works on any
batch shape ``[*B, 6]`` with no Python loop over the batch.

State layout: ``[x, x_dot, z, z_dot, alpha, alpha_dot]`` in SI units, angles in radians,
``alpha`` measured from the vertical axis, positive counter-clockwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from enum import IntEnum
from typing import Any

import torch

STATE_NAMES = ("x", "x_dot", "z", "z_dot", "alpha", "alpha_dot")
ACTION_NAMES = ("a_l", "a_r")  # each motor's thrust as a fraction of the weight
STATE_DIM, ACTION_DIM = len(STATE_NAMES), len(ACTION_NAMES)
X, X_DOT, Z, Z_DOT, ALPHA, ALPHA_DOT = range(STATE_DIM)

# Domain and target zone of the paper's Table 2.1 (angles converted to radians): the defaults of
# DroneParams, whose fields (the env's arguments) the dynamics read.
X_LIMIT = 2.0
Z_MIN, Z_MAX = 0.0, 4.0
ALPHA_LIMIT = math.pi / 3
ZONE_X_LIMIT = 0.8
ZONE_Z_MIN, ZONE_Z_MAX = 2.2, 3.2
ZONE_Z_CENTRE = 0.5 * (ZONE_Z_MIN + ZONE_Z_MAX)
# The arena's largest extent (|x_limit|, |z_min|, |z_max|, m): a kilometre. float32 positions there
# still resolve 0.1 mm, far below what a drone moves in one step (dt = 0.02 s); at 1e300 m they are inf.
MAX_ARENA = 1e3
# Upper bounds of the physical parameters. Past them the task stops making sense: a step longer
# than MAX_DT lets a hovering drone cross the 1 m target zone in one or two steps, gravity above
# MAX_GRAVITY (10x Earth's) makes a 300-step episode a free fall, and a floor tolerance above
# MAX_FLOOR_TOLERANCE would let the drone sink a quarter of the domain's height before "FLOOR".
MAX_DT = 0.1
MAX_GRAVITY = 100.0
MAX_FLOOR_TOLERANCE = 1.0
# The drone's size. Mass cancels out of the motion (thrust is a fraction of the weight), but the
# weight m*g and the angular acceleration's 1/(m r) are float32 numbers: at 1e300 kg or 1e-40 kg
# they overflow (a traceback, or episodes that end at their first step). A gram is lighter than
# any drone that flies, ten tonnes heavier than any built; a motor distance of 1 cm to 100 m alike.
MIN_MASS, MAX_MASS = 1e-3, 1e4
MIN_MOTOR_DISTANCE, MAX_MOTOR_DISTANCE = 1e-2, 1e2
# Thrust per motor in weights: 100 is a thrust-to-weight ratio of 200 (racing drones reach 10-20).
MAX_THRUST = 100.0

# How a state exactly on a bound counts. "inclusive" (the paper's text and the default): inside,
# both for the domain (no termination) and for the target zone. "strict" (the paper's public code,
# `-0.6 < x < 0.6` style): outside of both.
BOUNDS_MODES = ("inclusive", "strict")

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


#: The metadata key of a :class:`DroneParams` field's :class:`Param`.
PARAM = "drone_torchrl.param"

# A bound of a Param: a float (shown as Python writes it), a labelled value ("0", 0.0), or the name of
# an earlier field (its value is the bound).
Bound = float | tuple[str, float] | str


@dataclass(frozen=True)
class Param:
    """What one :class:`DroneParams` field means and allows (checked by ``drone_env.make_params``).

    Attributes:
        doc: its meaning and unit.
        low, high: its bounds (:data:`Bound`), ``low_open``/``high_open``: the bound itself excluded.
        optional: ``None`` is allowed too.
        choices: the values a string field allows (the kernels receive the value's index).
        new: came after the first runs; a saved config without it behaved as the default.
    """

    doc: str
    low: Bound | None = None
    high: Bound | None = None
    low_open: bool = False
    high_open: bool = False
    optional: bool = False
    choices: tuple[str, ...] = ()
    new: bool = False


def _param(default: Any, doc: str, **rule: Any) -> Any:
    return field(default=default, metadata={PARAM: Param(doc, **rule)})


_ZERO = ("0", 0.0)
_ARENA = (f"{MAX_ARENA:g} m", MAX_ARENA)


@dataclass(frozen=True)
class DroneParams:
    """The drone's physical parameters and its task's arena: the one home of the env's parameters.

    Each field's :class:`Param` (``dataclasses.fields(DroneParams)[i].metadata[PARAM]``) holds its
    meaning and range; from them follow :func:`~drone_torchrl.envs.drone_env.make_params` (the
    checks), :class:`~drone_torchrl.envs.drone_env.DroneEnv`'s keyword arguments, the config
    schema's ``env.*`` keys (their defaults too) and the fast engine's constants
    (:data:`drone_torchrl.kernels.ops.ENV_CONSTANTS`). The defaults are the paper's (Table 2.1);
    the arena is the domain, the target zone and how a state on a bound counts.
    """

    mass: float = _param(
        1.0, "kg; no effect on the motion (thrust is a fraction of the weight, as in the paper)",
        low=MIN_MASS, high=MAX_MASS,
    )  # fmt: skip
    motor_distance: float = _param(
        1.0, "m, diagonal motor-to-motor; the lever arm is half of it, I_yy = 2/5 m r^2",
        low=MIN_MOTOR_DISTANCE, high=MAX_MOTOR_DISTANCE,
    )  # fmt: skip
    # Thrust is a fraction of the weight m*g: with g = 0 no motor command could move the drone.
    gravity: float = _param(9.81, "m/s^2", low=0.0, high=MAX_GRAVITY, low_open=True)
    dt: float = _param(0.02, "s, the semi-implicit Euler step (50 Hz)", low=0.0, high=MAX_DT, low_open=True)
    max_thrust: float | None = _param(
        None, "per-motor thrust limit as a fraction of the weight (1.0: thrust-to-weight 2); None: unbounded (the paper)",
        low=0.0, high=MAX_THRUST, low_open=True, optional=True,
    )  # fmt: skip
    floor_tolerance: float = _param(
        0.05, "m below z_min before the floor counts as hit", low=0.0, high=MAX_FLOOR_TOLERANCE
    )
    x_limit: float = _param(
        X_LIMIT, "m, the domain is |x| <= x_limit", low=_ZERO, high=_ARENA, low_open=True, new=True
    )
    z_min: float = _param(
        Z_MIN,
        'm, the floor ("floor" resets start here)',
        low=(f"-{MAX_ARENA:g} m", -MAX_ARENA),
        high=_ARENA,
        new=True,
    )
    z_max: float = _param(Z_MAX, "m, the ceiling", low="z_min", high=_ARENA, low_open=True, new=True)
    alpha_limit: float = _param(
        ALPHA_LIMIT, "rad, the tilt bound of the domain and the zone (pi/3: 60 deg)",
        low=_ZERO, high=("pi", math.pi), low_open=True, new=True,
    )  # fmt: skip
    zone_x_limit: float = _param(
        ZONE_X_LIMIT,
        "m, the target zone is |x| <= zone_x_limit",
        low=_ZERO,
        high="x_limit",
        low_open=True,
        new=True,
    )
    zone_z_min: float = _param(
        ZONE_Z_MIN, "m, the bottom of the target zone", low="z_min", high="z_max", high_open=True, new=True
    )
    zone_z_max: float = _param(
        ZONE_Z_MAX, 'm, the top of the target zone ("air" resets start at the zone\'s centre)',
        low="zone_z_min", high="z_max", low_open=True, new=True,
    )  # fmt: skip
    bounds: str = _param(
        "inclusive", "a state exactly on a bound: inclusive = inside (the paper's text), strict = outside (its code)",
        choices=BOUNDS_MODES, new=True,
    )  # fmt: skip

    @property
    def strict(self) -> bool:
        """Whether a state exactly on a bound is outside (``bounds="strict"``).

        On the domain's bound such a state terminates; on the zone's, it is not in the zone.
        """
        return self.bounds == "strict"

    @property
    def zone_z_centre(self) -> float:
        """The target zone's centre height, where ``reset_mode="air"`` starts."""
        return 0.5 * (self.zone_z_min + self.zone_z_max)

    @property
    def floor(self) -> float:
        """The height below which (or on which, with strict bounds) the floor is hit."""
        return self.z_min - self.floor_tolerance

    @property
    def lever_arm(self) -> float:
        """``r``: half the diagonal motor-to-motor distance."""
        return 0.5 * self.motor_distance

    @property
    def inertia(self) -> float:
        """``I_yy = 2/5 m r^2`` (eq. 2.4, spherical mass distribution)."""
        return 0.4 * self.mass * self.lever_arm**2

    @property
    def arm_over_inertia(self) -> float:
        """``r / I_yy``: the angular acceleration per newton of thrust difference."""
        return self.lever_arm / self.inertia

    @property
    def weight(self) -> float:
        """The drone's weight ``m * g`` in newtons."""
        return self.mass * self.gravity


#: The env's physical and arena arguments: :class:`DroneParams`' fields, in order.
PARAM_NAMES = tuple(f.name for f in fields(DroneParams))


def clamp_action(action: torch.Tensor, max_thrust: float | None) -> torch.Tensor:
    """Clamp each motor command into ``[0, max_thrust]``; identity when unbounded (the paper)."""
    if max_thrust is None:
        return action
    return action.clamp(0.0, max_thrust)


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
    follows it, ``I = 2/5 m r^2``). Then ``x'' = g (sin(-alpha) (a_l + a_r) + force) / ratio``,
    ``z'' = g cos(alpha) (a_l + a_r) / ratio - g`` and ``alpha'' = (a_r - a_l) m0 g r / (I0 ratio)``.
    Without them (the paper's drone) the same equations are computed as the spec writes them, in
    thrusts ``T = a m g`` (the arithmetic the C++ kernels round alike).
    """
    alpha = state[..., ALPHA]
    if force is None and mass_ratio is None:
        thrust_left = action[..., 0] * params.weight
        thrust_right = action[..., 1] * params.weight
        total = thrust_left + thrust_right
        x_ddot = torch.sin(-alpha) * total / params.mass
        z_ddot = torch.cos(alpha) * total / params.mass - params.gravity
        alpha_ddot = (thrust_right - thrust_left) * (params.lever_arm / params.inertia)
    else:
        g = params.gravity
        ratio = torch.ones_like(alpha) if mass_ratio is None else mass_ratio
        push = torch.zeros_like(alpha) if force is None else force
        total = action[..., 0] + action[..., 1]
        x_ddot = g * (torch.sin(-alpha) * total + push) / ratio
        z_ddot = g * torch.cos(alpha) * total / ratio - g
        alpha_ddot = (
            (action[..., 1] - action[..., 0]) * params.weight * params.lever_arm / (params.inertia * ratio)
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
