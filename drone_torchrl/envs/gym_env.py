"""``Drone2D-v0``: a single drone as a Gymnasium env.

An adapter over :class:`~drone_torchrl.envs.drone_env.DroneEnv`.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDict

from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.envs.dynamics import ACTION_DIM, TerminationCause


class DroneGymEnv(gym.Env):
    """The Gymnasium twin of :class:`~drone_torchrl.envs.drone_env.DroneEnv` (same arguments, same manual).

    It holds a ``DroneEnv`` of one drone (``batch_size=[]``) and calls its reset and step: the same
    code flies both, so the same seed, arguments and actions give the same trajectory bit for bit:
    ``reset(seed=s)`` + steps + ``reset()`` + ... equals ``DroneEnv.set_seed(s)`` + a rollout.
    Observations are numpy arrays of shape ``(6,)`` (``6 + 2k`` with ``observed_actions=k``) in
    ``dtype`` (float32 by default, float64 with ``dtype="float64"``; the spaces too);
    ``info["termination_cause"]`` is the cause's name (``"NONE"``, ``"OUT_X"``, ``"FLOOR"``,
    ``"CEILING"``, ``"TILT"``) and ``info["step_count"]`` the steps of the episode so far.

    One rule makes this hold under TorchRL's ``GymEnv`` too: a ``reset()`` that follows
    ``reset(seed=s)`` with no step in between returns the same seeded start instead of drawing a
    new one. ``GymEnv.set_seed(s)`` calls ``reset(seed=s)`` and its rollout then calls ``reset()``;
    without the rule the seeded start would be skipped.
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 50}

    def __init__(self, *, render_mode: str | None = None, **env_kwargs: Any) -> None:
        # DroneEnv's keyword arguments, but those of a batch: one drone, on the CPU (numpy's).
        for batch_only in ("batch_size", "device", "render_index"):
            if batch_only in env_kwargs:
                raise TypeError(f"DroneGymEnv.__init__() got an unexpected keyword argument '{batch_only}'")
        env = self.env = DroneEnv(batch_size=[], render_mode=render_mode, **env_kwargs)
        self.params, self.dtype, self.disturbance = env.params, env.dtype, env.disturbance
        self.max_steps, self.reset_mode, self.render_mode = env.max_steps, env.reset_mode, render_mode
        self._np_dtype = np.float64 if self.dtype == torch.float64 else np.float32
        obs_dim = self.disturbance.observation_dim
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(obs_dim,), dtype=self._np_dtype)
        max_thrust = self.params.max_thrust
        low, high = (-np.inf, np.inf) if max_thrust is None else (0.0, float(max_thrust))
        self.action_space = spaces.Box(low, high, shape=(ACTION_DIM,), dtype=self._np_dtype)
        self._out: TensorDict | None = None  # the env's last output (Gymnasium resets before stepping)
        self._seeded = False

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """A new episode: ``(observation, info)``, as Gymnasium's API; ``seed`` seeds its start state."""
        super().reset(seed=seed)
        if seed is not None:
            self.env.set_seed(int(seed))
        if seed is not None or not self._seeded:  # reset(seed=s) then reset(), no step: the same start
            self._out = self.env._reset()
        self._seeded = seed is not None
        return self._observation(), self._info()

    def _observation(self) -> np.ndarray:
        return self._out.get("observation").numpy().copy()

    def step(self, action):
        """One step of the drone: ``(observation, reward, terminated, truncated, info)`` as Gymnasium's API.

        ``info`` holds the ``termination_cause`` (its name) and the ``step_count``.
        """
        action = torch.as_tensor(np.asarray(action, dtype=self._np_dtype))
        if action.shape != (ACTION_DIM,):
            raise ValueError(f"action has shape {tuple(action.shape)}; expected ({ACTION_DIM},)")
        if not bool(torch.isfinite(action).all()):
            raise ValueError(
                f"action {action.tolist()} contains NaN or inf; expected finite thrust fractions"
            )
        self._seeded = False
        out = self._out = self.env._step(TensorDict({"action": action}, batch_size=[]))
        terminated, truncated = bool(out.get("terminated")), bool(out.get("truncated"))
        return self._observation(), float(out.get("reward")), terminated, truncated, self._info()

    def _info(self) -> dict[str, Any]:
        cause = TerminationCause(int(self._out.get("termination_cause")))
        return {"termination_cause": cause.name, "step_count": int(self._out.get("step_count"))}

    def render(self):
        """Draw the current state in the env's render mode (an RGB array for ``"rgb_array"``); None without one."""
        if self.render_mode is None:
            gym.logger.warn("render() called with render_mode=None; pass render_mode='rgb_array' or 'human'")
            return None
        return self.env.render()

    def close(self) -> None:
        """Close the underlying :class:`~drone_torchrl.envs.drone_env.DroneEnv`."""
        self.env.close(raise_if_closed=False)
