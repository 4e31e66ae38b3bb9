"""The natively batched TorchRL environment of the 2D drone."""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping, Sequence
from dataclasses import fields
from numbers import Integral
from typing import Any, NamedTuple

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from drone_torchrl.checks import INT64_MAX, as_override, check_number
from drone_torchrl.envs import disturbances, dynamics
from drone_torchrl.envs.dynamics import ACTION_DIM, DTYPES, RESET_MODES, STATE_DIM, TerminationCause
from drone_torchrl.envs.params import PARAM, PARAM_NAMES, DroneParams

RENDER_MODES = (None, "human", "rgb_array")


# The longest episode (steps): an int64 count.
MAX_STEPS = INT64_MAX


def make_params(**values: Any) -> DroneParams:
    """Validate the physical and arena arguments shared by both envs and bundle them.

    Each field of :class:`~drone_torchrl.envs.params.DroneParams` left out is its default; each is
    checked in field order against its :class:`~drone_torchrl.envs.params.Param` (a bound named by an earlier field is that field's checked
    value). A ValueError names the first argument out of range.
    """
    unknown = sorted(set(values) - set(PARAM_NAMES))
    if unknown:
        raise TypeError(f"unexpected keyword argument {unknown[0]!r}; expected one of {PARAM_NAMES}")
    checked: dict[str, Any] = {}
    for f in fields(DroneParams):
        rule, value = f.metadata[PARAM], values.get(f.name, f.default)
        if rule.choices:
            if value not in rule.choices:
                raise ValueError(
                    f"{f.name}={as_override(value)} is not allowed; expected one of {rule.choices}"
                )
        elif not (rule.optional and value is None):
            low, high = ((b, checked[b]) if isinstance(b, str) else b for b in (rule.low, rule.high))
            bounds = {"low": low, "high": high, "low_open": rule.low_open, "high_open": rule.high_open}
            value = float(check_number(f.name, value, **bounds, dtype_range=False))
        checked[f.name] = value
    return DroneParams(**checked)


def is_integer(value: object) -> bool:
    """Whether ``value`` is an integer (a bool, though an int to Python, is not)."""
    return isinstance(value, Integral) and not isinstance(value, bool)


class EnvArgs(NamedTuple):
    """:class:`DroneEnv`'s arguments, checked (:func:`check_env_args`)."""

    batch_size: torch.Size
    params: DroneParams
    dtype: torch.dtype
    disturbance: disturbances.Disturbance
    device: torch.device
    max_steps: int
    reset_mode: str
    render_mode: str | None
    render_index: int


def check_env_args(
    batch_size: Sequence[int] | torch.Size | int | None = None,
    *,
    params: DroneParams | None = None,
    max_steps: int = 300,
    reset_mode: str = "floor",
    dtype: str | torch.dtype = "float32",
    disturbance: disturbances.Disturbance | Mapping[str, Any] | None = None,
    device: torch.device | str = "cpu",
    render_mode: str | None = None,
    render_index: int = 0,
    **overrides: Any,
) -> EnvArgs:
    """Check :class:`DroneEnv`'s arguments (the same, with the same defaults) without building an env.

    Returns them checked; the first one not allowed raises a one-line ``ValueError`` naming it
    (:class:`~drone_torchrl.checks.ConfigError` for a physical or arena argument). The config's
    validation, drone-eval and the evaluator ask this, not an env built to be thrown away.
    """
    batch_size = [batch_size] if is_integer(batch_size) else [] if batch_size is None else batch_size
    if not isinstance(batch_size, Sequence | torch.Size) or not all(
        is_integer(n) and n >= 1 for n in batch_size
    ):
        raise ValueError(
            f"batch_size={as_override(batch_size)} is not allowed; expected a list of positive integers, e.g. [] or [64]"
        )
    batch_size = torch.Size(batch_size)
    given = {} if params is None else {f.name: getattr(params, f.name) for f in fields(DroneParams)}
    params = make_params(**{**given, **overrides})
    torch_dtype = next((value for name, value in DTYPES.items() if dtype == name or dtype is value), None)
    if torch_dtype is None:
        raise ValueError(f"dtype={as_override(dtype)} is not allowed; expected one of {tuple(DTYPES)}")
    dtype, disturbance = torch_dtype, disturbances.make(disturbance)
    if not is_integer(max_steps) or not 1 <= max_steps <= MAX_STEPS:
        raise ValueError(
            f"max_steps={as_override(max_steps)} is not allowed; expected an integer >= 1 and <= {MAX_STEPS}"
        )
    allowed = {"reset_mode": RESET_MODES, "render_mode": RENDER_MODES}
    for (name, choices), value in zip(allowed.items(), (reset_mode, render_mode), strict=True):
        if value not in choices:
            raise ValueError(f"{name}={as_override(value)} is not allowed; expected one of {choices}")
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise ValueError(
            f"device={as_override(device)} is not allowed; expected e.g. 'cpu' or 'cuda:0'"
        ) from err
    n_envs = math.prod(batch_size)
    if not is_integer(render_index) or not 0 <= render_index < n_envs:
        raise ValueError(
            f"render_index={as_override(render_index)} is not allowed; expected an integer in [0, {n_envs - 1}]"
        )
    steps, index = int(max_steps), int(render_index)
    return EnvArgs(batch_size, params, dtype, disturbance, device, steps, reset_mode, render_mode, index)


class DroneEnv(EnvBase):
    """A 2D quadcopter that must take off from the floor and hover in a target zone.

    ## Description

    The drone of "Training a 2D Drone Model to Fly Using Reinforcement Learning" (M. Neumark):
    a rigid body in the vertical X-Z plane driven by a left and a right motor (eqs. 2.1-2.4).
    It starts on the floor and must fly into the target zone ``|x| <= 0.8 m``,
    ``2.2 <= z <= 3.2 m`` and hover there without leaving the 4 m x 4 m domain or tilting past
    60 degrees (the paper's text; every one of these numbers is an argument, see "Arena" below).
    The environment is natively batched: ``batch_size=[N]`` simulates N independent
    drones with one tensor operation per step, and done sub-environments are reset on their own
    through TorchRL's ``"_reset"`` mask. The physics lives in
    :mod:`drone_torchrl.envs.dynamics`, shared with the Gymnasium twin ``Drone2D-v0``.

    ## Action space

    ``"action"``, float32 (``dtype``), shape ``[*batch, 2]``: ``[a_l, a_r]``, each motor's thrust as a
    fraction of the drone's weight, ``T = a * m * g``; ``a_l = a_r = 0.5`` hovers level.

    - ``max_thrust=None`` (the paper): unbounded; negative thrust is applied as is.
    - ``max_thrust=A``: bounded to ``[0, A]`` per motor; out-of-range actions are clamped.

    A NaN or infinite action raises ``ValueError`` naming the offending batch indices; it never
    reaches the state.

    ## Observation space

    ``"observation"``, float32 (``dtype``), shape ``[*batch, 6]``, SI units, angles in radians:

    =====  =============  ===============================================  =====================================================
    index  name           meaning                                          termination bound (default)
    =====  =============  ===============================================  =====================================================
    0      ``x``          horizontal position (m, right positive)          ``[-x_limit, x_limit]`` (``[-2, 2]``)
    1      ``x_dot``      horizontal velocity (m/s)                        none
    2      ``z``          altitude (m, up positive)                        ``[z_min - floor_tolerance, z_max]`` (``[-0.05, 4]``)
    3      ``z_dot``      vertical velocity (m/s)                          none
    4      ``alpha``      roll from the vertical (rad, counter-clockwise)  ``[-alpha_limit, alpha_limit]`` (``[-pi/3, pi/3]``)
    5      ``alpha_dot``  roll rate (rad/s)                                none
    =====  =============  ===============================================  =====================================================

    Its layout, the observed commands included: :func:`~.disturbances.observation_names`.
    Also in every reset and step output: ``"termination_cause"`` (int64, ``[*batch, 1]``, a
    :class:`~.dynamics.TerminationCause` code) and ``"step_count"`` (int64, ``[*batch, 1]``).

    ## Rewards

    On the state after each step: ``0`` if the step terminated the episode, ``10`` inside the
    target zone (``|x| <= zone_x_limit``, ``zone_z_min <= z <= zone_z_max``,
    ``|alpha| <= alpha_limit``; ``<`` each with ``bounds="strict"``), ``1`` anywhere else. Rewards
    are in ``dtype``. An episode's return is at most ``10 * max_steps`` (3000 by default). From the
    floor with bounded thrust the best achievable return is lower (2694 with ``max_thrust=1`` and
    the default arena: :mod:`drone_torchrl.optimum`); with unbounded thrust only a pulse of hundreds
    of weights on the first step reaches 3000.

    ## Starting state

    ``reset_mode="floor"``: ``z = z_min`` (0, the floor) and all velocities are 0; ``x`` and
    ``alpha`` are uniform in +-0.01. ``reset_mode="air"``: every component uniform in +-0.01 around
    ``x=0`` and the zone's centre height (2.7 m). The uniforms are drawn in float32 whatever
    ``dtype``, so a seed gives the same start states in float32 and float64 (up to the float64
    centre).

    ## Episode end

    Termination (``"terminated"``), checked on the state after the step, with
    ``"termination_cause"`` (lowest code wins when several hold): ``1 OUT_X`` ``|x| > x_limit``;
    ``2 FLOOR`` ``z < z_min - floor_tolerance``; ``3 CEILING`` ``z > z_max``; ``4 TILT``
    ``|alpha| > alpha_limit`` (defaults: 2, -0.05, 4, pi/3). Bounds are inclusive by default (a
    state on a bound is inside); with ``bounds="strict"`` each ``>`` is ``>=`` and the floor's
    ``<`` is ``<=``. The floor alone has a tolerance so a drone spooling up on the ground is not
    ended at once. Truncation (``"truncated"``): the step that brings the episode's step count
    to ``max_steps``, unless that step also terminated. ``"done" = terminated | truncated``.

    ## Disturbances and model mismatch

    ``disturbance`` (a :class:`~drone_torchrl.envs.disturbances.Disturbance` or a mapping of its
    fields; none by default) adds wind with gusts, a true mass off the nominal one, motor gain
    asymmetry, first-order motor lag, an action delay and observation noise, each drawn per drone
    and per episode (see :mod:`drone_torchrl.envs.disturbances` for each one's physics). Rewards
    and terminations use the true state; ``"observation"`` is what the drone measures (with
    ``observed_actions=k`` followed by its last ``k`` commands, ``6 + 2k`` entries). Each episode
    draws one key from the env's generator right after its start state, and all its disturbances
    follow from that key: the same seed gives the same disturbances wherever an episode sits in the
    batch and on every engine that flies it (the evaluator's included).

    ## Arguments

    - ``batch_size`` (list of int, default ``[]``): number of drones simulated together.
    - ``params`` (a :class:`~drone_torchrl.envs.params.DroneParams`, default the paper's) and any of its fields as
      keywords (``max_thrust=1.0``, ``zone_x_limit=0.6``; a keyword overrides ``params``' field):
      the drone's physics (``mass``, ``motor_distance``, ``gravity``, ``dt``, ``max_thrust``,
      ``floor_tolerance``) and the arena (the domain, the target zone and ``bounds``). Their
      defaults, units and ranges are the fields' (:class:`~drone_torchrl.envs.params.DroneParams`, the one home).
      Bounds are compared in ``dtype``: in float32 the nearest float32 to 0.8 is "on" the bound
      0.8. The paper's public code differs from its text: ``zone_x_limit=0.6 bounds=strict dtype=float64``.
    - ``max_steps`` (int >= 1, default 300): truncation length.
    - ``reset_mode`` (``"floor"`` or ``"air"``, default ``"floor"``).
    - ``dtype`` (``"float32"`` or ``"float64"``, or the torch dtype; default ``"float32"``): the
      precision of the state, the physics, the observations, the rewards and the specs. float64
      integrates the same equations in double precision (the paper's public code computes in
      numpy's float64); actions of another dtype are converted to it. Trajectories agree with
      float32's to float32 rounding over short horizons and drift apart later (chaotic flights).

    More:

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

    - v0: first release, the environment this docstring specifies. The arena arguments, ``bounds``
      and ``dtype`` came later; their defaults are the first release's behaviour.
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 50}
    batch_locked = True

    def __init__(self, batch_size: Sequence[int] | torch.Size | int | None = None, **options: Any) -> None:
        # The keywords and their defaults are check_env_args' (their one list; __signature__ below
        # shows them): params=, max_steps=, reset_mode=, dtype=, disturbance=, device=,
        # render_mode=, render_index= and DroneParams' fields.
        args = check_env_args(batch_size, **options)
        batch_size, device = args.batch_size, args.device
        self.params, self.dtype, self.disturbance = args.params, args.dtype, args.disturbance
        # Nominal envs keep the plain step (and draw nothing more from the generator than before).
        self._disturbed = not self.disturbance.nominal
        super().__init__(device=device, batch_size=batch_size)
        self.max_steps, self.reset_mode = args.max_steps, args.reset_mode
        self.render_mode, self.render_index = args.render_mode, args.render_index
        self._renderer = None
        # On the CPU whatever the env's device: a seed then gives the same start states on a GPU
        # as on the CPU (evaluations stay comparable), and a checkpoint's generator state loads on both.
        self._generator = torch.Generator()
        self._generator.seed()
        self._make_specs()
        shape = tuple(batch_size)
        self._state = torch.zeros((*shape, STATE_DIM), device=device, dtype=self.dtype)
        self._step_count = torch.zeros(shape, dtype=torch.int64, device=device)
        self._cause = torch.zeros(shape, dtype=torch.int64, device=device)
        # Kept only for the render overlay: the last applied action and the return so far.
        self._last_action = torch.zeros((*shape, ACTION_DIM), device=device, dtype=self.dtype)
        self._episode_return = torch.zeros(shape, device=device, dtype=self.dtype)
        # Drawn for a step before any reset (the generator is reseeded by set_seed before any seeded work).
        keys = disturbances.episode_keys(self._generator, shape, device)
        self._internal = disturbances.start(self.disturbance, keys, self.dtype) if self._disturbed else None

    __init__.__signature__ = inspect.Signature(  # help(), IDEs and Sphinx show check_env_args' keywords
        [
            inspect.Parameter("self", inspect.Parameter.POSITIONAL_OR_KEYWORD),
            *inspect.signature(check_env_args).parameters.values(),
        ],
        return_annotation=None,
    )

    def _make_specs(self) -> None:
        bs = self.batch_size
        real = {"dtype": self.dtype, "device": self.device}  # the state's, the actions' and the rewards'
        count = {"low": 0, "shape": (*bs, 1), "dtype": torch.int64, "device": self.device}
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*bs, self.disturbance.observation_dim), **real),
            termination_cause=Bounded(high=max(TerminationCause), **count),
            step_count=Bounded(high=self.max_steps, **count),
            shape=bs,
            device=self.device,
        )
        if self._disturbed:  # the observation is a measurement: the true state too, for the record
            self.observation_spec["state"] = Unbounded(shape=(*bs, STATE_DIM), **real)
        if self.max_thrust is None:
            self.action_spec = Unbounded(shape=(*bs, ACTION_DIM), **real)
        else:
            self.action_spec = Bounded(low=0.0, high=self.max_thrust, shape=(*bs, ACTION_DIM), **real)
        self.reward_spec = Unbounded(shape=(*bs, 1), **real)
        flag = Categorical(n=2, shape=(*bs, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(
            done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=bs, device=self.device
        )

    @property
    def state(self) -> torch.Tensor:
        """A copy of the physical state, shape ``[*batch, 6]``."""
        return self._state.clone()

    @property
    def episode_keys(self) -> torch.Tensor | None:
        """The current episodes' disturbance keys (int64 ``[*batch]``), ``None`` without disturbances."""
        return None if self._internal is None else self._internal.key.clone()

    def reset_to(self, state: torch.Tensor, keys: torch.Tensor | None = None) -> TensorDictBase:
        """Start every drone's episode from the given states ``[*batch, 6]`` instead of drawing starts.

        Under disturbances ``keys`` (int64 ``[*batch]``) are the episodes' disturbance keys. Returns
        the reset output: give it to ``rollout(..., auto_reset=False, tensordict=...)``. What the
        evaluator uses to fly one set of start states under several policies, and tests to fly another
        engine's draws.
        """
        shape = tuple(self.batch_size)
        if tuple(state.shape) != (*shape, STATE_DIM):
            raise ValueError(f"state has shape {tuple(state.shape)}; expected {(*shape, STATE_DIM)}")
        if self._disturbed and (keys is None or tuple(keys.shape) != shape):
            raise ValueError(f"a disturbed env needs int64 episode keys of shape {shape}")
        return self._start(state.to(self.device, self.dtype).clone(), keys)

    def _start(
        self, state: torch.Tensor, keys: torch.Tensor | None, index: tuple | None = None
    ) -> TensorDict:
        """Start episodes from ``state`` (with disturbance ``keys``): every drone's, or the rows ``index``.

        ``index`` holds a partial reset's integer indices, found once (same rows, same row-major order
        as boolean-mask writes, which would search the mask again for every tensor). The counters are
        replaced, never written in place, so :meth:`_output` can hand them out without a copy (the
        last action may even be the caller's own tensor, see :meth:`_step`).
        """
        zero = torch.zeros_like if index is None else lambda t: t.index_put(index, t.new_zeros(()))
        if index is None:
            self._state = state
        else:
            self._state[index] = state
        self._step_count, self._cause = zero(self._step_count), zero(self._cause)
        if self._disturbed:
            new = disturbances.start(self.disturbance, keys.to(self.device), self.dtype)
            self._internal = new if index is None else disturbances.replace_rows(self._internal, index, new)
        if self.render_mode is not None:
            self._episode_return, self._last_action = zero(self._episode_return), zero(self._last_action)
        if self.render_mode == "human":
            self.render()
        return self._output(done=torch.zeros_like(self._step_count, dtype=torch.bool))

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
        full = n_reset is None or n_reset == mask.numel()
        shape = tuple(self.batch_size) if full else (n_reset,)
        start = dynamics.initial_state(
            shape, self.reset_mode, self._generator, self.device, self.dtype, self.params
        )
        # Each episode's disturbance key is drawn right after its start state.
        keys = disturbances.episode_keys(self._generator, shape, self.device) if self._disturbed else None
        return self._start(start, keys, None if full else mask.nonzero(as_tuple=True))

    def _output(self, done: torch.Tensor, terminated=None, truncated=None, reward=None) -> TensorDictBase:
        observation = self._state
        if self._disturbed:  # what the policy sees: noisy positions, past commands
            observation = disturbances.observe(
                self.disturbance, observation, self._internal, self._step_count
            )
        if observation is self._state:  # nothing added: a partial reset writes into the state
            observation = observation.clone()
        out = {
            "observation": observation,
            "termination_cause": self._cause.unsqueeze(-1),
            "step_count": self._step_count.unsqueeze(-1),
            "done": done.unsqueeze(-1),
            "terminated": (done if terminated is None else terminated).unsqueeze(-1),
            "truncated": (done if truncated is None else truncated).unsqueeze(-1),
        }
        if self._disturbed:
            out["state"] = self._state.clone()
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
        action = action.to(self.dtype)
        if self._disturbed:
            self._state, reward, self._cause, self._internal = disturbances.step(
                self.disturbance, self._state, action, self._internal, self._step_count, self.params
            )
        else:
            self._state, reward, self._cause = dynamics.step(self._state, action, self.params)
        self._step_count = self._step_count + 1
        terminated = self._cause != int(TerminationCause.NONE)
        truncated = (self._step_count >= self.max_steps) & ~terminated
        if self.render_mode is not None:  # the overlay's return so far and arrows
            self._episode_return = self._episode_return + reward
            self._last_action = dynamics.clamp_action(action, self.max_thrust)
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
        state, action = flat(self._state).cpu().numpy(), flat(self._last_action).cpu().numpy()
        step, episode_return = int(flat(self._step_count)), float(flat(self._episode_return))
        return self._renderer.draw(
            state, action, step, episode_return, TerminationCause(int(flat(self._cause)))
        )

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Close the env and its render window, if one is open."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close(raise_if_closed=raise_if_closed)


# Views of the parameters, named like the constructor arguments (env.max_thrust, env.zone_x_limit...).
for _name in PARAM_NAMES:
    setattr(DroneEnv, _name, property(lambda self, name=_name: getattr(self.params, name)))
