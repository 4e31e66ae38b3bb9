"""``Drone2D-v0``: a single drone as a Gymnasium env, a thin adapter over the shared dynamics."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from drone_torchrl.envs import disturbances, dynamics
from drone_torchrl.envs.drone_env import check_dtype, check_episode_args, make_params
from drone_torchrl.envs.dynamics import (
    ACTION_DIM,
    ALPHA_LIMIT,
    STATE_DIM,
    X_LIMIT,
    Z_MAX,
    Z_MIN,
    ZONE_X_LIMIT,
    ZONE_Z_MAX,
    ZONE_Z_MIN,
    TerminationCause,
)


class DroneGymEnv(gym.Env):
    """The Gymnasium twin of :class:`~drone_torchrl.envs.DroneEnv` (same arguments, same manual).

    Observations are numpy arrays of shape ``(6,)`` in ``dtype`` (float32 by default, float64 with
    ``dtype="float64"``; the spaces too); ``info["termination_cause"]`` is the
    cause's name (``"NONE"``, ``"OUT_X"``, ``"FLOOR"``, ``"CEILING"``, ``"TILT"``). Resets draw from
    a ``torch.Generator`` seeded by ``reset(seed=...)`` exactly as ``DroneEnv.set_seed`` does, and
    steps call :func:`drone_torchrl.envs.dynamics.step` in ``dtype`` with the same arena (zone,
    domain, ``bounds``), so the same seed, arguments and actions give the same trajectory as
    ``DroneEnv`` bit for bit:
    ``reset(seed=s)`` + steps + ``reset()`` + ... equals ``DroneEnv.set_seed(s)`` + a rollout.

    One rule makes this hold under TorchRL's ``GymEnv`` too: a ``reset()`` that follows
    ``reset(seed=s)`` with no step in between returns the same seeded start instead of drawing a
    new one. ``GymEnv.set_seed(s)`` calls ``reset(seed=s)`` and its rollout then calls ``reset()``;
    without the rule the seeded start would be skipped.
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 50}

    def __init__(
        self,
        *,
        mass: float = 1.0,
        motor_distance: float = 1.0,
        gravity: float = 9.81,
        dt: float = 0.02,
        max_steps: int = 300,
        reset_mode: str = "floor",
        max_thrust: float | None = None,
        floor_tolerance: float = 0.05,
        x_limit: float = X_LIMIT,
        z_min: float = Z_MIN,
        z_max: float = Z_MAX,
        alpha_limit: float = ALPHA_LIMIT,
        zone_x_limit: float = ZONE_X_LIMIT,
        zone_z_min: float = ZONE_Z_MIN,
        zone_z_max: float = ZONE_Z_MAX,
        bounds: str = "inclusive",
        dtype: str | torch.dtype = "float32",
        disturbance: disturbances.Disturbance | Mapping[str, Any] | None = None,
        render_mode: str | None = None,
    ) -> None:
        self.params = make_params(
            mass,
            motor_distance,
            gravity,
            dt,
            max_thrust,
            floor_tolerance,
            x_limit=x_limit,
            z_min=z_min,
            z_max=z_max,
            alpha_limit=alpha_limit,
            zone_x_limit=zone_x_limit,
            zone_z_min=zone_z_min,
            zone_z_max=zone_z_max,
            bounds=bounds,
        )
        self.dtype = check_dtype(dtype)
        self.disturbance = disturbances.make(disturbance)
        self._disturbed = not self.disturbance.nominal
        self._internal: disturbances.Internal | None = None
        check_episode_args(max_steps, reset_mode, render_mode)
        self.max_steps = int(max_steps)
        self.reset_mode = reset_mode
        self.render_mode = render_mode
        np_dtype = np.float64 if self.dtype == torch.float64 else np.float32
        self._np_dtype = np_dtype
        obs_dim = self.disturbance.observation_dim
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(obs_dim,), dtype=np_dtype)
        if max_thrust is None:
            self.action_space = spaces.Box(-np.inf, np.inf, shape=(ACTION_DIM,), dtype=np_dtype)
        else:
            self.action_space = spaces.Box(0.0, float(max_thrust), shape=(ACTION_DIM,), dtype=np_dtype)
        self._generator = torch.Generator()
        self._generator.seed()
        self._state = torch.zeros(STATE_DIM, dtype=self.dtype)
        self._action = torch.zeros(ACTION_DIM, dtype=self.dtype)
        self._steps = 0
        self._return = 0.0
        self._cause = TerminationCause.NONE
        self._renderer = None
        self._seeded_start: tuple[torch.Tensor, disturbances.Internal | None] | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._generator.manual_seed(int(seed))
            self._state, self._internal = self._start()
            self._seeded_start = (self._state.clone(), self._internal)
        elif self._seeded_start is not None:  # reset(seed=s) then reset(), no step: same start
            self._state, self._internal = self._seeded_start
            self._seeded_start = None
        else:
            self._state, self._internal = self._start()
        self._action = torch.zeros(ACTION_DIM, dtype=self.dtype)
        self._steps, self._return, self._cause = 0, 0.0, TerminationCause.NONE
        if self.render_mode == "human":
            self.render()
        return self._observation(), self._info()

    def _start(self) -> tuple[torch.Tensor, disturbances.Internal | None]:
        """A start state and, when disturbed, its episode's key drawn right after it (as DroneEnv)."""
        state = dynamics.initial_state((), self.reset_mode, self._generator, None, self.dtype, self.params)
        if not self._disturbed:
            return state, None
        keys = disturbances.episode_keys(self._generator, ())
        return state, disturbances.start(self.disturbance, keys, self.dtype)

    def _observation(self) -> np.ndarray:
        if self._internal is None:
            return self._state.numpy().copy()
        t = torch.tensor(self._steps)
        return disturbances.observe(self.disturbance, self._state, self._internal, t).numpy().copy()

    def step(self, action):
        action = torch.as_tensor(np.asarray(action, dtype=self._np_dtype))
        if action.shape != (ACTION_DIM,):
            raise ValueError(f"action has shape {tuple(action.shape)}; expected ({ACTION_DIM},)")
        if not bool(torch.isfinite(action).all()):
            raise ValueError(
                f"action {action.tolist()} contains NaN or inf; expected finite thrust fractions"
            )
        self._seeded_start = None
        self._action = dynamics.clamp_action(action, self.params.max_thrust)
        if self._internal is None:
            self._state, reward, cause = dynamics.step(self._state, self._action, self.params)
        else:
            t = torch.tensor(self._steps)
            self._state, reward, cause, self._internal = disturbances.step(
                self.disturbance, self._state, action, self._internal, t, self.params
            )
        self._steps += 1
        self._cause = TerminationCause(int(cause))
        terminated = self._cause != TerminationCause.NONE
        truncated = self._steps >= self.max_steps and not terminated
        self._return += float(reward)
        if self.render_mode == "human":
            self.render()
        return self._observation(), float(reward), terminated, truncated, self._info()

    def _info(self) -> dict[str, Any]:
        return {"termination_cause": self._cause.name, "step_count": self._steps}

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called with render_mode=None; pass render_mode='rgb_array' or 'human'")
            return None
        from drone_torchrl.envs.rendering import DroneRenderer

        if self._renderer is None:
            self._renderer = DroneRenderer(self.render_mode, self.params, self.metadata["render_fps"])
        return self._renderer.draw(
            state=self._state.numpy(),
            action=self._action.numpy(),
            step=self._steps,
            episode_return=self._return,
            cause=self._cause,
        )

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
