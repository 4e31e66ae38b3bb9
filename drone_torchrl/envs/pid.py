"""A PID hover controller: the PD controller of :mod:`.heuristic` plus integral action on ``x`` and ``z``.

Under a constant disturbance the PD controller settles off its set points: a horizontal wind ``w``
(a fraction of the weight) needs a lean ``alpha = asin(w)``, which the position-to-tilt law
``alpha = kp_x x`` only commands at ``x = asin(w) / kp_x`` (0.76 m for ``w = 0.3`` and the default
``kp_x = 0.4``, on the edge of the 0.8 m zone); a drone heavier than the controller believes hovers
``g (m / m0 - 1) / kp_z`` below its set point. An integrator on each position error removes both
offsets. It is written as a moving set point, ``target + (ki / kp) * integral(error dt)``, which
is the same control law as adding ``ki * integral(error dt)`` to the PD output, with the
integrals clamped to ``+-integral_limit`` (anti-windup). ``ki = 0`` is the PD controller exactly.

The controller keeps its integrals between calls, so it is a stateful policy: :meth:`PIDController.reset`
starts new episodes (the evaluator calls it before flying), and it must see every step of its
episodes in order. Gains may be tensors (e.g. ``[C, 1]`` against observations ``[C, E, 6]``): the
tuner flies many candidate controllers in one batch.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from drone_torchrl.envs.dynamics import STATE_DIM, DroneParams, X, Z
from drone_torchrl.envs.heuristic import PDGains, pd_action


@dataclass(frozen=True)
class PIDGains:
    """PID gains: :class:`~.heuristic.PDGains` plus integral gains on ``z`` and ``x``.

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
        params: the drone's physical parameters and arena (as :func:`~.heuristic.pd_action` takes them).
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
