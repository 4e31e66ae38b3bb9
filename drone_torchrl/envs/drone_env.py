"""The natively batched TorchRL environment of the 2D drone."""

from __future__ import annotations

import math
from collections.abc import Sequence
from numbers import Integral, Real

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from drone_torchrl.envs import dynamics
from drone_torchrl.envs.dynamics import (
    ACTION_DIM,
    RESET_MODES,
    STATE_DIM,
    DroneParams,
    TerminationCause,
)

RENDER_MODES = (None, "human", "rgb_array")


# Upper bounds of the physical arguments. Past them the task stops making sense: a step longer
# than MAX_DT lets a hovering drone cross the 1 m target zone in one or two steps, gravity above
# MAX_GRAVITY (10x Earth's) makes a 300-step episode a free fall, and a floor tolerance above
# MAX_FLOOR_TOLERANCE would let the drone sink a quarter of the domain's height before "FLOOR".
MAX_DT = 0.1
MAX_GRAVITY = 100.0
MAX_FLOOR_TOLERANCE = 1.0


def _check_real(
    name: str, value: object, *, minimum: float, inclusive: bool, maximum: float | None = None
) -> float:
    """Return ``value`` as float, or raise a ValueError naming the argument and the allowed range."""
    allowed = f"a finite number {'>=' if inclusive else '>'} {minimum}"
    if maximum is not None:
        allowed += f" and <= {maximum}"
    if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value):
        raise ValueError(f"{name}={value!r} is not allowed; expected {allowed}")
    if value < minimum or (value == minimum and not inclusive) or (maximum is not None and value > maximum):
        raise ValueError(f"{name}={value!r} is not allowed; expected {allowed}")
    return float(value)


def make_params(
    mass: float = 1.0,
    motor_distance: float = 1.0,
    gravity: float = 9.81,
    dt: float = 0.02,
    max_thrust: float | None = None,
    floor_tolerance: float = 0.05,
) -> DroneParams:
    """Validate the physical arguments shared by both envs and bundle them."""
    return DroneParams(
        mass=_check_real("mass", mass, minimum=0.0, inclusive=False),
        motor_distance=_check_real("motor_distance", motor_distance, minimum=0.0, inclusive=False),
        # Thrust is a fraction of the weight m*g: with g = 0 no motor command could move the drone.
        gravity=_check_real("gravity", gravity, minimum=0.0, inclusive=False, maximum=MAX_GRAVITY),
        dt=_check_real("dt", dt, minimum=0.0, inclusive=False, maximum=MAX_DT),
        max_thrust=None
        if max_thrust is None
        else _check_real("max_thrust", max_thrust, minimum=0.0, inclusive=False),
        floor_tolerance=_check_real(
            "floor_tolerance", floor_tolerance, minimum=0.0, inclusive=True, maximum=MAX_FLOOR_TOLERANCE
        ),
    )


def check_episode_args(max_steps: object, reset_mode: object, render_mode: object) -> None:
    """Validate the episode arguments shared by both envs."""
    if isinstance(max_steps, bool) or not isinstance(max_steps, Integral) or max_steps < 1:
        raise ValueError(f"max_steps={max_steps!r} is not allowed; expected an integer >= 1")
    if reset_mode not in RESET_MODES:
        raise ValueError(f"reset_mode={reset_mode!r} is not allowed; expected one of {RESET_MODES}")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode={render_mode!r} is not allowed; expected one of {RENDER_MODES}")


def _check_batch_size(batch_size: object) -> torch.Size:
    if isinstance(batch_size, Integral) and not isinstance(batch_size, bool):
        batch_size = [batch_size]
    if batch_size is None:
        batch_size = []
    ok = isinstance(batch_size, Sequence | torch.Size) and all(
        isinstance(n, Integral) and not isinstance(n, bool) and n >= 1 for n in batch_size
    )
    if not ok:
        raise ValueError(
            f"batch_size={batch_size!r} is not allowed; expected a list of positive integers, e.g. [] or [64]"
        )
    return torch.Size(batch_size)


class DroneEnv(EnvBase):
    """A 2D quadcopter that must take off from the floor and hover in a target zone.

    ## Description

    The drone of "Training a 2D Drone Model to Fly Using Reinforcement Learning" (M. Neumark):
    a rigid body in the vertical X-Z plane driven by a left and a right motor (eqs. 2.1-2.4).
    It starts on the floor and must fly into the target zone ``|x| <= 0.8 m``,
    ``2.2 <= z <= 3.2 m`` and hover there without leaving the 4 m x 4 m domain or tilting past
    60 degrees. The environment is natively batched: ``batch_size=[N]`` simulates N independent
    drones with one tensor operation per step, and done sub-environments are reset on their own
    through TorchRL's ``"_reset"`` mask. The physics lives in
    :mod:`drone_torchrl.envs.dynamics`, shared with the Gymnasium twin ``Drone2D-v0``.

    ## Action space

    ``"action"``, float32, shape ``[*batch, 2]``: ``[a_l, a_r]``, each motor's thrust as a
    fraction of the drone's weight, ``T = a * m * g``; ``a_l = a_r = 0.5`` hovers level.

    - ``max_thrust=None`` (the paper): unbounded; negative thrust is applied as is.
    - ``max_thrust=A``: bounded to ``[0, A]`` per motor; out-of-range actions are clamped.

    A NaN or infinite action raises ``ValueError`` naming the offending batch indices; it never
    reaches the state.

    ## Observation space

    ``"observation"``, float32, shape ``[*batch, 6]``, SI units, angles in radians:

    | index | name        | meaning                                         | termination bound |
    |-------|-------------|-------------------------------------------------|-------------------|
    | 0     | ``x``         | horizontal position (m, right positive)        | ``[-2, 2]``          |
    | 1     | ``x_dot``     | horizontal velocity (m/s)                      | none              |
    | 2     | ``z``         | altitude (m, up positive)                      | ``[-floor_tolerance, 4]`` |
    | 3     | ``z_dot``     | vertical velocity (m/s)                        | none              |
    | 4     | ``alpha``     | roll from the vertical (rad, counter-clockwise)| ``[-pi/3, pi/3]``     |
    | 5     | ``alpha_dot`` | roll rate (rad/s)                              | none              |

    Also in every reset and step output: ``"termination_cause"`` (int64, ``[*batch, 1]``, a
    :class:`TerminationCause` code) and ``"step_count"`` (int64, ``[*batch, 1]``).

    ## Rewards

    On the state after each step: ``0`` if the step terminated the episode, ``10`` inside the
    target zone (all bounds inclusive), ``1`` anywhere else. An episode's return is at most
    ``10 * max_steps`` (3000 by default). From the floor with bounded thrust the best achievable
    return is lower (2694 with ``max_thrust=1``: :mod:`drone_torchrl.optimum`); with unbounded
    thrust only a pulse of hundreds of weights on the first step reaches 3000.

    ## Starting state

    ``reset_mode="floor"``: ``z`` and all velocities are 0; ``x`` and ``alpha`` are uniform in
    +-0.01. ``reset_mode="air"``: every component uniform in +-0.01 around ``x=0, z=2.7 m``.

    ## Episode end

    Termination (``"terminated"``), checked on the state after the step, with
    ``"termination_cause"`` (lowest code wins when several hold): ``1 OUT_X`` ``|x| > 2``;
    ``2 FLOOR`` ``z < -floor_tolerance``; ``3 CEILING`` ``z > 4``; ``4 TILT`` ``|alpha| > pi/3``.
    Bounds are inclusive; the floor alone has a tolerance so a drone spooling up on the ground is
    not ended at once. Truncation (``"truncated"``): the step that brings the episode's step count
    to ``max_steps``, unless that step also terminated. ``"done" = terminated | truncated``.

    ## Arguments

    - ``batch_size`` (list of int, default ``[]``): number of drones simulated together.
    - ``mass`` (float > 0, default 1.0 kg). It has no effect on the motion: as in the paper, the
      actions are thrusts as fractions of the weight ``m g`` and ``I_yy`` is proportional to ``m``,
      so the mass cancels out of all three accelerations. It is an argument because the paper
      lists it.
    - ``motor_distance`` (float > 0, default 1.0 m): diagonal motor-to-motor distance; the lever
      arm is half of it and ``I_yy = 2/5 m r^2``.
    - ``gravity`` (float in (0, 100], default 9.81 m/s^2): not 0, since the thrust is a fraction
      of the weight.
    - ``dt`` (float in (0, 0.1], default 0.02 s): semi-implicit Euler step (50 Hz).
    - ``max_steps`` (int >= 1, default 300): truncation length.
    - ``reset_mode`` (``"floor"`` or ``"air"``, default ``"floor"``).
    - ``max_thrust`` (float > 0 or None, default None): per-motor thrust limit as a fraction of the
      weight; ``1.0`` is a thrust-to-weight ratio of 2.
    - ``floor_tolerance`` (float in [0, 1], default 0.05 m).
    - ``device`` (default ``"cpu"``). Start states are drawn from the env's own CPU generator
      (``set_seed``) and then moved to the device, so a seed gives the same start states on any device.
    - ``render_mode`` (``None``, ``"human"`` or ``"rgb_array"``): pygame drawing of sub-env
      ``render_index`` (default 0); ``"human"`` draws after every step, ``render()`` returns an
      ``H x W x 3`` uint8 frame in ``"rgb_array"`` mode.

    Each argument is validated; a bad value raises ``ValueError`` naming it.

    ## Example

    >>> from drone_torchrl.envs import DroneEnv
    >>> env = DroneEnv(batch_size=[64])
    >>> env.set_seed(0)
    >>> td = env.rollout(300, break_when_any_done=False)
    >>> td["next", "reward"].shape
    torch.Size([64, 300, 1])

    ## Version history

    - v0: first release, the environment this docstring specifies.
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 50}
    batch_locked = True

    def __init__(
        self,
        batch_size: Sequence[int] | torch.Size | int | None = None,
        *,
        mass: float = 1.0,
        motor_distance: float = 1.0,
        gravity: float = 9.81,
        dt: float = 0.02,
        max_steps: int = 300,
        reset_mode: str = "floor",
        max_thrust: float | None = None,
        floor_tolerance: float = 0.05,
        device: torch.device | str = "cpu",
        render_mode: str | None = None,
        render_index: int = 0,
    ) -> None:
        batch_size = _check_batch_size(batch_size)
        self.params = make_params(mass, motor_distance, gravity, dt, max_thrust, floor_tolerance)
        check_episode_args(max_steps, reset_mode, render_mode)
        try:
            device = torch.device(device)
        except (RuntimeError, TypeError) as err:
            raise ValueError(f"device={device!r} is not allowed; expected e.g. 'cpu' or 'cuda:0'") from err
        n_envs = math.prod(batch_size)
        if (
            isinstance(render_index, bool)
            or not isinstance(render_index, Integral)
            or not 0 <= render_index < n_envs
        ):
            raise ValueError(
                f"render_index={render_index!r} is not allowed; expected an integer in [0, {n_envs - 1}]"
            )
        super().__init__(device=device, batch_size=batch_size)
        self.max_steps = int(max_steps)
        self.reset_mode = reset_mode
        self.render_mode = render_mode
        self.render_index = int(render_index)
        self._renderer = None
        # On the CPU whatever the env's device: a seed then gives the same start states on a GPU
        # as on the CPU (evaluations stay comparable), and a checkpoint's generator state loads on both.
        self._generator = torch.Generator()
        self._generator.seed()
        self._make_specs()
        shape = tuple(batch_size)
        self._state = torch.zeros((*shape, STATE_DIM), device=device)
        self._step_count = torch.zeros(shape, dtype=torch.int64, device=device)
        self._cause = torch.zeros(shape, dtype=torch.int64, device=device)
        # Kept only for the render overlay: the last applied action and the return so far.
        self._last_action = torch.zeros((*shape, ACTION_DIM), device=device)
        self._episode_return = torch.zeros(shape, device=device)

    # Convenience views of the parameters, named like the constructor arguments.
    mass = property(lambda self: self.params.mass)
    motor_distance = property(lambda self: self.params.motor_distance)
    gravity = property(lambda self: self.params.gravity)
    dt = property(lambda self: self.params.dt)
    max_thrust = property(lambda self: self.params.max_thrust)
    floor_tolerance = property(lambda self: self.params.floor_tolerance)

    def _make_specs(self) -> None:
        bs = self.batch_size
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*bs, STATE_DIM), dtype=torch.float32, device=self.device),
            termination_cause=Bounded(
                low=0, high=max(TerminationCause), shape=(*bs, 1), dtype=torch.int64, device=self.device
            ),
            step_count=Bounded(
                low=0, high=self.max_steps, shape=(*bs, 1), dtype=torch.int64, device=self.device
            ),
            shape=bs,
            device=self.device,
        )
        if self.max_thrust is None:
            self.action_spec = Unbounded(shape=(*bs, ACTION_DIM), dtype=torch.float32, device=self.device)
        else:
            self.action_spec = Bounded(
                low=0.0,
                high=self.max_thrust,
                shape=(*bs, ACTION_DIM),
                dtype=torch.float32,
                device=self.device,
            )
        self.reward_spec = Unbounded(shape=(*bs, 1), dtype=torch.float32, device=self.device)
        flag = Categorical(n=2, shape=(*bs, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(
            done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=bs, device=self.device
        )

    @property
    def state(self) -> torch.Tensor:
        """A copy of the physical state, shape ``[*batch, 6]``."""
        return self._state.clone()

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            self._generator.seed()
        else:
            self._generator.manual_seed(int(seed))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict:
            mask = tensordict.get("_reset").reshape(self.batch_size)
        # One count decides between a full and a partial reset (cheaper than mask.all() at large batch).
        n_reset = None if mask is None or self.batch_size == () else int(mask.sum())
        if n_reset is None or n_reset == mask.numel():
            self._state = dynamics.initial_state(
                self.batch_size, self.reset_mode, self._generator, self.device
            )
            # The counters are replaced, never written in place, so _output can hand them out
            # without a copy (the last action may even be the caller's own tensor, see _step).
            self._step_count = torch.zeros_like(self._step_count)
            self._cause = torch.zeros_like(self._cause)
            if self.render_mode is not None:
                self._episode_return = torch.zeros_like(self._episode_return)
                self._last_action = torch.zeros_like(self._last_action)
        else:
            # Integer indices found once (same rows, same row-major order as boolean-mask writes,
            # which would search the mask again for every tensor).
            index = mask.nonzero(as_tuple=True)
            self._state[index] = dynamics.initial_state(
                (n_reset,), self.reset_mode, self._generator, self.device
            )
            # Out of place, for the same reason as above.
            self._step_count = self._step_count.index_put(index, self._step_count.new_zeros(()))
            self._cause = self._cause.index_put(index, self._cause.new_zeros(()))
            if self.render_mode is not None:
                self._episode_return = self._episode_return.index_put(
                    index, self._episode_return.new_zeros(())
                )
                self._last_action = self._last_action.index_put(index, self._last_action.new_zeros(()))
        if self.render_mode == "human":
            self.render()
        return self._output(done=torch.zeros_like(self._step_count, dtype=torch.bool))

    def _output(self, done: torch.Tensor, terminated=None, truncated=None, reward=None) -> TensorDictBase:
        out = {
            "observation": self._state.clone(),
            "termination_cause": self._cause.unsqueeze(-1),
            "step_count": self._step_count.unsqueeze(-1),
            "done": done.unsqueeze(-1),
            "terminated": (done if terminated is None else terminated).unsqueeze(-1),
            "truncated": (done if truncated is None else truncated).unsqueeze(-1),
        }
        if reward is not None:
            out["reward"] = reward.unsqueeze(-1)
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        # Screen with one sum (any NaN/inf entry makes it non-finite); only then find the culprits.
        if not bool(torch.isfinite(action.sum())):
            finite = torch.isfinite(action).all(-1)
            if not bool(finite.all()):
                bad = (~finite).nonzero().tolist()
                raise ValueError(
                    f"action contains NaN or inf at batch indices {bad}; expected finite thrust fractions"
                )
        action = dynamics.clamp_action(action, self.max_thrust)
        self._state, reward, self._cause = dynamics.step(self._state, action, self.params)
        self._step_count = self._step_count + 1
        terminated = self._cause != int(TerminationCause.NONE)
        truncated = (self._step_count >= self.max_steps) & ~terminated
        if self.render_mode is not None:  # the overlay's return so far and arrows
            self._episode_return = self._episode_return + reward
            self._last_action = action
            if self.render_mode == "human":
                self.render()
        return self._output(terminated | truncated, terminated, truncated, reward)

    # ------------------------------------------------------------------ rendering
    def render(self, index: int | None = None) -> np.ndarray | None:
        """Draw sub-env ``index`` (default ``render_index``) with pygame.

        Returns an ``H x W x 3`` uint8 array in ``"rgb_array"`` mode, ``None`` in ``"human"`` mode.
        """
        if self.render_mode is None:
            raise ValueError(
                "render() needs render_mode='human' or 'rgb_array'; this env was built with render_mode=None"
            )
        from drone_torchrl.envs.rendering import DroneRenderer

        if self._renderer is None:
            self._renderer = DroneRenderer(self.render_mode, self.params, self.metadata["render_fps"])
        i = self.render_index if index is None else index
        flat = lambda t: t.reshape(-1, *t.shape[len(self.batch_size) :])[i]  # noqa: E731
        return self._renderer.draw(
            state=flat(self._state).cpu().numpy(),
            action=flat(self._last_action).cpu().numpy(),
            step=int(flat(self._step_count)),
            episode_return=float(flat(self._episode_return)),
            cause=TerminationCause(int(flat(self._cause))),
        )

    def close(self, *, raise_if_closed: bool = True) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close(raise_if_closed=raise_if_closed)
