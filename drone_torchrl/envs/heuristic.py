"""A classical PD hover controller: the hand-written baseline of the Drone2D task.

Like Gymnasium LunarLander's ``heuristic``, it is a reference point for the learned policies: it
takes the drone from the floor into the target zone and holds it there, with unbounded thrust
(the paper's setting) or with each motor limited to ``[0, max_thrust]`` times the weight.

Structure (all batched over any leading shape, no Python loop over the batch):

1. **Altitude**: a PD law on ``z`` gives a desired vertical acceleration ``a_z``, limited to
   ``+-max_accel_z``; the collective thrust that produces it is ``m (g + a_z) / cos(alpha)``
   (gravity compensation, tilt-corrected). With unbounded thrust, braking near the set point asks
   for a negative collective thrust (the paper's setting allows it).
2. **Horizontal position**: a PD law on ``x`` gives a desired tilt. Since
   ``x_ddot = sin(-alpha) T / m``, accelerating towards ``+x`` needs a *negative* ``alpha``, so the
   desired tilt is minus the PD output, clipped to ``max_tilt``.
3. **Attitude**: a PD law on ``alpha`` gives a desired angular acceleration, turned into a thrust
   difference with ``alpha_ddot = r / I_yy (T_r - T_l)``.

Outputs are thrust fractions of the weight ``[a_l, a_r]``. With a thrust limit the controller clips
itself, keeping the full thrust difference (attitude) and sacrificing collective thrust first.

Use :func:`pd_action` as a plain function, :class:`PDController` as a TorchRL policy
(``env.rollout(300, PDController(env.params))``); ``drone_torchrl.evaluation.evaluate_pd`` gives seeded statistics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import torch
from tensordict.nn import TensorDictModule

from drone_torchrl.envs.dynamics import STATE_DIM, DroneParams, clamp_action

#: The collective thrust is divided by cos(alpha); below the cosine of the termination tilt
#: (params.alpha_limit, 60 deg by default) the correction is held constant so a nearly flipped drone
#: does not ask for unbounded thrust, and never below MIN_COS_ALPHA (84 deg) whatever the tilt limit.
MIN_COS_ALPHA = 0.1
# The desired tilt stays within this share of the tilt limit (a tighter limit than the paper's
# 60 deg then tightens gains.max_tilt).
MAX_TILT_SHARE = 0.5


@dataclass(frozen=True)
class PDGains:
    """Targets and gains of :func:`pd_action` (the parameters a Hydra config sets).

    Units: altitude gains in ``(m/s^2)/m`` and ``(m/s^2)/(m/s)``; position-to-tilt gains in
    ``rad/m`` and ``rad/(m/s)``; attitude gains in ``(rad/s^2)/rad`` and ``(rad/s^2)/(rad/s)``.

    Default design: the altitude and attitude loops are critically damped (``kd = 2 sqrt(kp)``),
    natural frequencies 8 rad/s and 20 rad/s; near hover the position-to-tilt loop gives
    ``x_ddot ~ -g alpha``, about 2 rad/s and critically damped. They were tuned on ``DroneEnv``
    from the floor for both ``max_thrust=None`` and ``max_thrust=1.0`` (seed 0, 100 episodes):
    returns 2757 and 2685 of 3000, first step in the zone 28 and 36, no termination. With
    ``max_thrust=1`` the climb is close to the bang-bang limit (net upward acceleration at most g).
    """

    z_target: float | None = None
    """Altitude set point (m); None for the centre height of the params' target zone (2.7 m by default)."""
    x_target: float = 0.0
    """Horizontal set point (m)."""
    kp_z: float = 64.0
    """Altitude proportional gain."""
    kd_z: float = 16.0
    """Altitude derivative (vertical-velocity damping) gain."""
    max_accel_z: float = 20.0
    """Limit of the commanded vertical acceleration magnitude (m/s^2, about 2 g). It bounds the
    collective thrust to about 3 weights when thrust is unbounded: with more, a small tilt error
    turns into a large sideways push (``x_ddot = -tan(alpha) (g + a_z)``) before the attitude loop
    has corrected it."""
    kp_x: float = 0.4
    """Horizontal position error to desired tilt."""
    kd_x: float = 0.4
    """Horizontal velocity to desired tilt (damping)."""
    max_tilt: float = 0.35
    """Limit of the desired tilt (rad), well inside the 60 deg termination bound (and never more
    than half of ``params.alpha_limit``)."""
    kp_alpha: float = 400.0
    """Attitude proportional gain."""
    kd_alpha: float = 40.0
    """Attitude derivative (roll-rate damping) gain."""


def pd_action(observation: torch.Tensor, params: DroneParams, gains: PDGains | None = None) -> torch.Tensor:
    """Thrust fractions ``[a_l, a_r]`` (shape ``[..., 2]``) for observations ``[..., 6]``.

    Args:
        observation: ``[x, x_dot, z, z_dot, alpha, alpha_dot]`` with any leading batch shape.
        params: the drone's physical parameters (mass, gravity, lever arm, inertia, thrust limit)
            and arena (the zone's centre is the default set point; the tilt limit).
        gains: targets and gains; ``PDGains()`` when omitted.

    When ``params.max_thrust`` is set, each motor's command is clipped into ``[0, max_thrust]``
    with priority to the thrust difference (attitude) over the collective thrust (altitude).
    """
    if observation.shape[-1] != STATE_DIM:
        raise ValueError(f"observation has shape {tuple(observation.shape)}; expected [..., {STATE_DIM}]")
    gains = PDGains() if gains is None else gains
    x, x_dot, z, z_dot, alpha, alpha_dot = observation.unbind(-1)

    # 1. Altitude: desired vertical acceleration, then the collective thrust (fraction of weight).
    z_target = params.zone_z_centre if gains.z_target is None else gains.z_target
    accel_z = gains.kp_z * (z_target - z) - gains.kd_z * z_dot
    accel_z = accel_z.clamp(-gains.max_accel_z, gains.max_accel_z)
    cos_alpha = torch.cos(alpha).clamp_min(max(math.cos(params.alpha_limit), MIN_COS_ALPHA))
    collective = (1.0 + accel_z / params.gravity) / cos_alpha

    # 2. Horizontal position -> desired tilt. x_ddot = -sin(alpha) T/m: tilt the opposite way.
    push = gains.kp_x * (gains.x_target - x) - gains.kd_x * x_dot
    # torch.clamp: the gains may be tensors (a batch of candidate controllers, benchmarks/pid_tuning.py).
    max_tilt = torch.as_tensor(gains.max_tilt, dtype=push.dtype, device=push.device).clamp(
        max=MAX_TILT_SHARE * params.alpha_limit
    )
    alpha_target = torch.maximum(torch.minimum(-push, max_tilt), -max_tilt)

    # 3. Attitude: desired angular acceleration -> thrust difference a_r - a_l (fraction of weight).
    accel_alpha = gains.kp_alpha * (alpha_target - alpha) - gains.kd_alpha * alpha_dot
    difference = accel_alpha * (params.inertia / (params.lever_arm * params.weight))

    if params.max_thrust is not None:
        limit = params.max_thrust
        # Keep the attitude command whole if possible, then fit the collective around it:
        # a_l, a_r = base -+ difference/2 lie in [0, limit] iff base lies in [|d|/2, limit - |d|/2].
        difference = difference.clamp(-limit, limit)
        half = 0.5 * difference.abs()
        base = torch.minimum(torch.maximum(0.5 * collective, half), limit - half)
    else:
        base = 0.5 * collective
    action = torch.stack((base - 0.5 * difference, base + 0.5 * difference), dim=-1)
    return clamp_action(action, params.max_thrust)  # only rounding can reach beyond the limit


class PDController(TensorDictModule):
    """:func:`pd_action` as a TorchRL policy: reads ``"observation"``, writes ``"action"``.

    >>> from drone_torchrl.envs import DroneEnv
    >>> env = DroneEnv(batch_size=[16], max_thrust=1.0)
    >>> td = env.rollout(300, PDController(env.params))

    Args:
        params: the drone's physical parameters and arena (as :func:`pd_action` takes them).
        gains: the controller's gains (None: :class:`PDGains`' defaults).
        observation_key: the key it reads the ``[*B, 6]`` observation from.
        action_key: the key it writes the ``[*B, 2]`` action to.
    """

    def __init__(
        self,
        params: DroneParams,
        gains: PDGains | None = None,
        observation_key: str = "observation",
        action_key: str = "action",
    ) -> None:
        self.params, self.gains = params, PDGains() if gains is None else gains
        act = partial(_pd_on_state, params=params, gains=self.gains)
        super().__init__(act, in_keys=[observation_key], out_keys=[action_key])


def _pd_on_state(observation: torch.Tensor, params: DroneParams, gains: PDGains) -> torch.Tensor:
    # Past the 6 state entries an observation may carry the last commands (observed_actions).
    return pd_action(observation[..., :STATE_DIM], params, gains)


__all__ = ["MIN_COS_ALPHA", "PDController", "PDGains", "pd_action"]
