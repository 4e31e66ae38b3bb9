"""The C++ kernels as ``torch.library`` custom ops (CPU): the fast engine's rollout and network.

- ``drone_torchrl::rollout``: whole episodes of many agents' stochastic (or deterministic) policies
  on the drone's dynamics, each row until its episode ends: what
  :func:`drone_torchrl.envs.rollout.fly` computes with :mod:`~drone_torchrl.envs.dynamics` and
  :class:`~drone_torchrl.modules.StackedThreeNet`, in one call.
- ``drone_torchrl::reinforce``: one REINFORCE update's episodes (the rollout above) and each
  agent's loss and gradient, the arithmetic of :class:`~drone_torchrl.objectives.ReinforceLoss`
  (tested against it), back-propagated through the hidden outputs the rollout kept.

Being ``torch.library`` ops, they have fake (meta) implementations and trace as single opaque
nodes under ``torch.compile(fullgraph=True)``. Parameters are each agent's flat vector
(:attr:`StackedThreeNet.flat <drone_torchrl.modules.StackedThreeNet.flat>`).
"""

from __future__ import annotations

import ctypes
from collections.abc import Sequence

import torch

from drone_torchrl.envs import dynamics
from drone_torchrl.kernels.build import library, unavailable_reason

ACTIVATION_CODES = {"tanh": 0, "relu": 1, "elu": 2}
# The rollout's per-row counts (drone_kernels.cpp: Stat), from which the episode metrics follow.
STAT_NAMES = ("return", "zone_steps", "negative_commands", "termination_cause")
STATS = len(STAT_NAMES)
# The kernel's fixed limits (drone_kernels.cpp: kMaxLayers, kMaxWidth).
MAX_LAYERS = 16
MAX_WIDTH = 1024
DTYPES = (torch.float32, torch.float64)

_i64 = ctypes.c_int64
_ptr = ctypes.c_void_p


def _p(tensor: torch.Tensor | None) -> ctypes.c_void_p:
    return _ptr(None if tensor is None else tensor.data_ptr())


def _sizes(hidden: Sequence[int]) -> ctypes.Array:
    return (_i64 * max(len(hidden), 1))(*hidden)


def _lib(dtype: torch.dtype = torch.float32) -> ctypes.CDLL:
    lib = library(double=dtype == torch.float64)
    if lib is None:
        raise RuntimeError(f"the drone_torchrl C++ kernels are not available: {unavailable_reason()}")
    return lib


# The drone's constants, in the kernels' order (drone_kernels.cpp: EnvConst).
ENV_CONSTANTS = (
    "weight",
    "mass",
    "gravity",
    "dt",
    "arm_over_inertia",
    "max_thrust",  # < 0: unbounded
    "x_limit",
    "z_min",
    "z_max",
    "alpha_limit",
    "floor",  # z_min - floor_tolerance: below it the floor is hit
    "zone_x",
    "zone_z_min",
    "zone_z_max",
    "reward_zone",
    "reward_alive",
    "reward_terminated",
    "squash_high",  # the TanhNormal head's upper bound; < 0: the Normal head
    "reset_air",  # 1: start states drawn around the zone's centre, 0: on the floor
    "reset_noise",
    "zone_z_centre",
    "strict",  # 1: a state exactly on a bound is outside (the domain and the zone); 0: inside
)


def env_constants(
    params: dynamics.DroneParams,
    squash_high: float | None,
    reset_mode: str = "floor",
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """The drone's constants (:data:`ENV_CONSTANTS`), float64: its physics and its arena (domain,
    target zone, ``bounds``) from ``params``.

    ``squash_high``: the TanhNormal head's upper bound (actions in ``[0, squash_high]``), or None
    for the Normal head. ``reset_mode``: where the start states drawn in the kernel lie.
    """
    values = {
        "weight": params.weight,
        "mass": params.mass,
        "gravity": params.gravity,
        "dt": params.dt,
        "arm_over_inertia": params.lever_arm / params.inertia,
        "max_thrust": -1.0 if params.max_thrust is None else params.max_thrust,
        "x_limit": params.x_limit,
        "z_min": params.z_min,
        "z_max": params.z_max,
        "alpha_limit": params.alpha_limit,
        "floor": params.floor,
        "zone_x": params.zone_x_limit,
        "zone_z_min": params.zone_z_min,
        "zone_z_max": params.zone_z_max,
        "reward_zone": dynamics.REWARD_IN_ZONE,
        "reward_alive": dynamics.REWARD_ALIVE,
        "reward_terminated": dynamics.REWARD_TERMINATED,
        "squash_high": -1.0 if squash_high is None else float(squash_high),
        "reset_air": float(reset_mode == "air"),
        "reset_noise": dynamics.RESET_NOISE,
        "zone_z_centre": params.zone_z_centre,
        "strict": float(params.strict),
    }
    return torch.tensor([values[name] for name in ENV_CONSTANTS], dtype=torch.float64, device=device)


# ---------------------------------------------------------------------------------------- the ops
# Defined with torch.library's low-level API: a call costs ~20 us, a third of what the
# torch.library.custom_op decorator's checks cost, and each op is called once or twice per update.

_LIB = torch.library.Library("drone_torchrl", "DEF")
_LIB.define(
    "rollout(Tensor params, Tensor? start, Tensor? noise, Tensor? rng, Tensor active, Tensor env, Tensor gamma, "
    "int[] hidden, int activation, float min_std, int steps, float dist_eps=0.0) "
    "-> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)"
)
_LIB.define(
    "reinforce(Tensor params, Tensor rng, Tensor active, Tensor env, Tensor gamma, int[] options, int[] hidden, "
    "int activation, float min_std, int steps, float dist_eps=0.0) -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)"
)


def _rollout(
    params: torch.Tensor,
    start: torch.Tensor | None,
    noise: torch.Tensor | None,
    rng: torch.Tensor | None,
    active: torch.Tensor,
    env: torch.Tensor,
    gamma: torch.Tensor,
    hidden: Sequence[int],
    activation: int,
    min_std: float,
    steps: int,
    dist_eps: float = 0.0,
) -> tuple[torch.Tensor, ...]:
    n, episodes = _rows(start, rng, active)
    states = torch.zeros(n, episodes, steps + 1, dynamics.STATE_DIM, dtype=params.dtype)
    action = torch.zeros(n, episodes, steps, dynamics.ACTION_DIM, dtype=params.dtype)
    reward = torch.zeros(n, episodes, steps, dtype=params.dtype)
    cause = torch.zeros(n, episodes, steps, dtype=torch.int64)
    length = torch.zeros(n, episodes, dtype=torch.int64)
    returns = torch.zeros(n, episodes, steps, dtype=params.dtype)
    stats = torch.empty(n, episodes, STATS, dtype=torch.float64)
    params = params.contiguous()
    start = None if start is None else start.to(params.dtype).contiguous()
    noise = None if noise is None else noise.to(params.dtype).contiguous()
    rng = None if rng is None else rng.to(torch.int64).contiguous()
    active = active.to(torch.uint8).contiguous()
    env = env.to(torch.float64).contiguous()
    gamma = gamma.to(torch.float64).contiguous()
    _lib(params.dtype).dk_rollout(
        _i64(torch.get_num_threads()),
        _i64(dynamics.STATE_DIM),
        _i64(len(hidden)),
        _sizes(hidden),
        _i64(activation),
        ctypes.c_double(min_std),
        ctypes.c_double(dist_eps),
        _i64(n * episodes),
        _i64(episodes),
        _i64(steps),
        *(_p(t) for t in (params, start, noise, rng, active, env, gamma)),
        *(_p(t) for t in (states, action, reward, cause, length, returns, stats)),
    )
    return states, action, reward, cause, length, returns, stats


def _rows(start: torch.Tensor | None, rng: torch.Tensor | None, active: torch.Tensor) -> tuple[int, int]:
    """Agents and episodes per agent: from ``start`` ``[N, E, 6]``, or ``rng`` ``[N, E, 2]`` (only its
    shape is read for ``E``; the keys are per agent)."""
    if start is not None:
        return start.shape[0], start.shape[1]
    if rng is None:
        raise ValueError("drone_torchrl::rollout needs start states or rng keys")
    return active.shape[0], rng.shape[1]


def _rollout_fake(
    params, start, noise, rng, active, env, gamma, hidden, activation, min_std, steps, dist_eps=0.0
):
    n, episodes = _rows(start, rng, active)
    new = params.new_empty
    return (
        new(n, episodes, steps + 1, dynamics.STATE_DIM),
        new(n, episodes, steps, dynamics.ACTION_DIM),
        new(n, episodes, steps),
        new(n, episodes, steps, dtype=torch.int64),
        new(n, episodes, dtype=torch.int64),
        new(n, episodes, steps),
        new(n, episodes, STATS, dtype=torch.float64),
    )


def _reinforce(
    params: torch.Tensor,
    rng: torch.Tensor,
    active: torch.Tensor,
    env: torch.Tensor,
    gamma: torch.Tensor,
    options: Sequence[int],
    hidden: Sequence[int],
    activation: int,
    min_std: float,
    steps: int,
    dist_eps: float = 0.0,
) -> tuple[torch.Tensor, ...]:
    n, episodes = rng.shape[:2]
    dtype = params.dtype
    reward = torch.empty(n, episodes, steps, dtype=dtype)
    returns = torch.empty_like(reward)
    cause = torch.empty(n, episodes, steps, dtype=torch.int64)
    length = torch.empty(n, episodes, dtype=torch.int64)
    counts = torch.empty(n, episodes, STATS, dtype=torch.float64)
    lib = _lib(dtype)
    sizes = _sizes(hidden)
    size = lib.dk_saved_size(
        _i64(dynamics.STATE_DIM), _i64(len(hidden)), sizes, _i64(n), _i64(episodes), _i64(steps)
    )
    saved = torch.empty(size, dtype=dtype)
    grad = torch.empty_like(params)
    loss = torch.empty(n, dtype=torch.float64)
    std_mean = torch.empty_like(loss)
    actions_finite = torch.empty(n, dtype=torch.bool)
    params, rng = params.contiguous(), rng.to(torch.int64).contiguous()
    active = active.to(torch.uint8).contiguous()
    env, gamma = env.to(torch.float64).contiguous(), gamma.to(torch.float64).contiguous()
    flags = torch.tensor(list(options), dtype=torch.int64)
    lib.dk_reinforce(
        _i64(torch.get_num_threads()),
        _i64(dynamics.STATE_DIM),
        _i64(len(hidden)),
        sizes,
        _i64(activation),
        ctypes.c_double(min_std),
        ctypes.c_double(dist_eps),
        _i64(n),
        _i64(episodes),
        _i64(steps),
        *(_p(t) for t in (params, rng, active, env, gamma, flags, reward, cause, length, returns, counts)),
        *(_p(t) for t in (saved, grad, loss, std_mean, actions_finite)),
    )
    return grad, loss, std_mean, actions_finite, length, counts


def _reinforce_fake(
    params, rng, active, env, gamma, options, hidden, activation, min_std, steps, dist_eps=0.0
):
    n, episodes = rng.shape[:2]
    scalar = params.new_empty(n, dtype=torch.float64)
    return (
        torch.empty_like(params),
        scalar,
        torch.empty_like(scalar),
        params.new_empty(n, dtype=torch.bool),
        params.new_empty(n, episodes, dtype=torch.int64),
        params.new_empty(n, episodes, STATS, dtype=torch.float64),
    )


_LIB.impl("rollout", _rollout, "CPU")
_LIB.impl("reinforce", _reinforce, "CPU")
torch.library.register_fake("drone_torchrl::rollout", _rollout_fake, lib=_LIB)
torch.library.register_fake("drone_torchrl::reinforce", _reinforce_fake, lib=_LIB)


def rollout(
    params: torch.Tensor,
    start: torch.Tensor | None,
    noise: torch.Tensor | None,
    rng: torch.Tensor | None,
    active: torch.Tensor,
    env: torch.Tensor,
    gamma: torch.Tensor,
    hidden: Sequence[int],
    activation: int,
    min_std: float,
    steps: int,
    dist_eps: float = 0.0,
) -> tuple[torch.Tensor, ...]:
    """``drone_torchrl::rollout``: fly every active agent's ``E`` episodes until each ends or ``steps`` pass.

    Args:
        params: ``[N, P]`` flat parameters.
        start: ``[N, E, 6]`` start states (None with ``rng``).
        noise: ``[N, E, steps, 2]`` standard normals (``action = f(loc + scale * noise)``), or None
            for the deterministic action (or with ``rng``).
        rng: ``[N, E, 2]`` int64, each agent's seed and update counter (the same for its ``E``
            rows): the start states and the action noise are then drawn inside the kernel, exactly
            where :mod:`drone_torchrl.training.rng` draws them (``uniform`` bit for bit, ``normal``
            to float rounding), and only for the steps flown.
        active: ``[N]`` bool; inactive agents fly nothing (length 0).
        env: :func:`env_constants`.
        gamma: ``[N]``, each agent's discount for the returns-to-go.
        hidden, activation, min_std: the network (:data:`ACTIVATION_CODES`).
        dist_eps: added to the mean and to the std, ``Normal(mu + eps, sigma + eps)``
            (:class:`~drone_torchrl.modules.ThreeNetPolicy`'s ``distribution_eps``).

    Returns ``states [N, E, steps + 1, 6]`` (before each step, then after the last),
    ``action [N, E, steps, 2]``, ``reward [N, E, steps]``, ``cause [N, E, steps]`` (int64
    :class:`TerminationCause` codes), ``length [N, E]`` (int64), ``returns [N, E, steps]`` (each
    step's discounted return-to-go, :func:`~drone_torchrl.objectives.reinforce.discounted_returns`)
    and ``stats [N, E, 4]`` float64 (:data:`STAT_NAMES`); entries after an episode's end hold zeros.
    """
    return torch.ops.drone_torchrl.rollout(
        params, start, noise, rng, active, env, gamma, list(hidden), activation, min_std, steps, dist_eps
    )


# The loss options drone_torchrl::reinforce takes, in its order (drone_kernels.cpp: LossOptions).
LOSS_OPTIONS = ("baseline_mean", "normalize_returns", "discount_weight", "mean_log_prob")


def reinforce(
    params: torch.Tensor,
    rng: torch.Tensor,
    active: torch.Tensor,
    env: torch.Tensor,
    gamma: torch.Tensor,
    options: Sequence[int],
    hidden: Sequence[int],
    activation: int,
    min_std: float,
    steps: int,
    dist_eps: float = 0.0,
) -> tuple[torch.Tensor, ...]:
    """``drone_torchrl::reinforce``: one REINFORCE update's episodes and gradient for every active agent.

    The episodes of :func:`rollout` with ``rng`` (``[N, E, 2]``: each agent's seed and update
    counter), then each agent's loss, the ``loss_per_agent`` of
    :func:`~drone_torchrl.objectives.reinforce.reinforce_terms` (``options``: the four flags of
    :data:`LOSS_OPTIONS`; ``gamma`` ``[N]``), and its gradient in the parameters, back-propagated
    through the hidden outputs the rollout kept (no second forward pass). Inactive agents get zeros.

    Returns ``grad [N, P]``, ``loss [N]`` and ``std_mean [N]`` (float64: the policy's mean std over
    the valid steps and motors), ``actions_finite [N]`` (bool), ``length [N, E]`` and
    ``counts [N, E, 4]`` (:data:`STAT_NAMES`).
    """
    return torch.ops.drone_torchrl.reinforce(
        params, rng, active, env, gamma, list(options), list(hidden), activation, min_std, steps, dist_eps
    )


def check_supported(in_dim: int, hidden: Sequence[int], activation: str, dtype: torch.dtype) -> str | None:
    """None where the kernels cover this network, else why not."""
    if in_dim != dynamics.STATE_DIM:
        return f"observations of {in_dim} values (the kernel flies the {dynamics.STATE_DIM}-value state)"
    if activation not in ACTIVATION_CODES:
        return f"activation {activation!r}"
    if len(hidden) > MAX_LAYERS or any(not 0 < h <= MAX_WIDTH for h in hidden):
        return f"hidden sizes {list(hidden)} (at most {MAX_LAYERS} layers of at most {MAX_WIDTH})"
    if dtype not in DTYPES:
        return f"dtype {dtype}"
    return None
