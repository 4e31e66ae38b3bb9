"""The C++ kernels as PyTorch functions (CPU; rollout and reinforce also CUDA): the fast engine.

- ``ops.rollout``: whole episodes of many agents' stochastic (or deterministic) policies
  on the drone, each row until its episode ends: what :class:`~drone_torchrl.envs.drone_env.DroneEnv` and
  :class:`~drone_torchrl.modules.stacked.StackedThreeNet` compute, in one call.
- ``ops.reinforce``: one REINFORCE update's episodes (the rollout above) and each
  agent's loss and gradient, the arithmetic of :class:`~drone_torchrl.objectives.reinforce.ReinforceLoss`
  (tested against it), back-propagated through the hidden outputs the rollout kept.
- ``ops.segments``: PPO/A2C's batches, ``n`` drones of one agent flown a number of
  steps with auto-reset and their state carried across calls: what TorchRL's collector gives over
  :class:`~drone_torchrl.envs.drone_env.DroneEnv` (tested against it).

Each takes the drone (:func:`env_constants`) and its disturbances (:func:`disturbance_constants`,
the physics of :mod:`drone_torchrl.envs.disturbances`: wind, gusts, mass, motor gains, lag, delay,
observation noise, observed commands); the policy then sees
:func:`~drone_torchrl.envs.disturbances.observation_names`.
Parameters are each agent's flat vector
(:attr:`StackedThreeNet.flat <drone_torchrl.modules.stacked.StackedThreeNet.flat>`).
"""

from __future__ import annotations

import ctypes
import struct
from collections.abc import Mapping, Sequence
from dataclasses import fields
from functools import partial
from typing import Any, NamedTuple

import torch

from drone_torchrl.envs import disturbances, dynamics
from drone_torchrl.envs.params import PARAM, DroneParams
from drone_torchrl.kernels.build import ENV_CONSTANTS, cuda_library, library, unavailable_reason

#: The code of each activation as the kernels take it (``activation`` argument).
ACTIVATION_CODES = {"tanh": 0, "relu": 1, "elu": 2}
#: The rollout's per-row counts (``Stat`` in drone_kernels.cpp), from which the episode metrics follow.
STAT_NAMES = ("return", "zone_steps", "negative_commands", "termination_cause")
STATS = len(STAT_NAMES)
# The kernel's fixed limits (drone_kernels.cpp: kMaxLayers, kMaxWidth).
MAX_LAYERS = 16
# Agents per call of the REINFORCE kernel (its scratch memory is this many agents' at most).
AGENTS_PER_CALL = 4096
# Agents of a population evaluated per call (each keeps eval.episodes whole episodes until scored).
AGENTS_PER_EVALUATION = 1024
MAX_WIDTH = 1024
DTYPES = (torch.float32, torch.float64)


def _words(*values: torch.Tensor | float | int | None) -> ctypes.Array:
    """The values as the kernels read them, 8-byte words: a tensor its address, a float its bits, None 0."""

    def word(value: torch.Tensor | float | int | None) -> int:
        if isinstance(value, torch.Tensor):
            return value.data_ptr()
        return struct.unpack("q", struct.pack("d", value))[0] if isinstance(value, float) else value or 0

    return (ctypes.c_int64 * len(values))(*map(word, values))


def _net(in_dim: int, hidden: Sequence[int], activation: int, min_std: float, dist_eps: float) -> list:
    """The network's words of every entry point (``NetSpec`` in drone_kernels.cpp)."""
    pad = [0] * (MAX_LAYERS - len(hidden))
    return [in_dim, len(hidden), activation, float(min_std), float(dist_eps), *hidden, *pad]


def _lib(dtype: torch.dtype = torch.float32, device: torch.device | None = None) -> ctypes.CDLL:
    cuda = device is not None and device.type == "cuda"
    lib = (cuda_library if cuda else library)(double=dtype == torch.float64)
    if lib is None:
        engine = "CUDA engine" if cuda else "C++ kernels"
        raise RuntimeError(f"the drone_torchrl {engine} is not available: {unavailable_reason()}")
    return lib


def _launch(lib: ctypes.CDLL, function: str, device: torch.device, net: list, args: tuple, sizes=()) -> None:
    """Call ``dk_<function>`` with its ``Call`` (drone_kernels.cpp): the launch, ``net`` and ``args``.

    The launch: the thread count (the CPU's), ``device``'s current stream and scratch memory (a
    GPU's: ``dk_cuda_scratch_size`` scalars for ``sizes``, allocated here, PyTorch's). The tensors
    in ``args`` live until the call returns.
    """
    memory, stream = None, None
    if device.type == "cuda":
        dtype = torch.float64 if lib.dk_real_bytes() == 8 else torch.float32
        memory = torch.empty(lib.dk_cuda_scratch_size(_words(*net, *sizes)), dtype=dtype, device=device)
        stream = torch.cuda.current_stream(device).cuda_stream
    code = getattr(lib, f"dk_{function}")(_words(torch.get_num_threads(), stream, memory, *net, *args))
    if code != 0:
        raise RuntimeError(f"ops.{function} on {device}: {lib.dk_cuda_error(ctypes.c_int64(code)).decode()}")


_CHOICES = {f.name: f.metadata[PARAM].choices for f in fields(DroneParams)}


def env_constants(
    params: DroneParams,
    squash_high: float | None,
    reset_mode: str = "floor",
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """The drone's constants (:data:`~.build.ENV_CONSTANTS`, float64): its physics and arena from ``params``.

    A choice is its index (``bounds``: 1 is strict), ``None`` is -1 (``max_thrust``: unbounded).
    ``squash_high``: the TanhNormal head's upper bound (actions in ``[0, squash_high]``), or None
    for the Normal head. ``reset_mode``: where the start states drawn in the kernel lie.
    """
    others = {
        "reward_zone": dynamics.REWARD_IN_ZONE,
        "reward_alive": dynamics.REWARD_ALIVE,
        "reward_terminated": dynamics.REWARD_TERMINATED,
        "reset_noise": dynamics.RESET_NOISE,
        "squash_high": squash_high,
        "reset_air": reset_mode == "air",
    }

    def number(name: str) -> float:
        value = others[name] if name in others else getattr(params, name)
        if _CHOICES.get(name):
            return float(_CHOICES[name].index(value))
        return -1.0 if value is None else float(value)

    return torch.tensor([number(name) for name in ENV_CONSTANTS], dtype=torch.float64, device=device)


#: The disturbance's magnitudes in the kernels' order (``DistConst`` in drone_kernels.cpp).
DISTURBANCE_CONSTANTS = disturbances.FIELDS
_GUST_TIME = DISTURBANCE_CONSTANTS.index("gust_time")


def disturbance_constants(
    disturbance: disturbances.Disturbance | Mapping[str, Any] | None, device: torch.device | str = "cpu"
) -> torch.Tensor:
    """The disturbance's magnitudes (:data:`DISTURBANCE_CONSTANTS`), float64.

    Magnitudes all zero (the gusts' time scale aside), or None, is the nominal drone, which the kernels fly as
    fast as ever.
    """
    d = disturbances.make(disturbance)
    return torch.tensor(
        [float(getattr(d, name)) for name in DISTURBANCE_CONSTANTS], dtype=torch.float64, device=device
    )


def _magnitudes(disturbance: torch.Tensor | None, device: torch.device | None = None) -> torch.Tensor | None:
    """``disturbance`` as the kernels read it (float64 on ``device``), or None for the nominal drone."""
    # The gusts' time scale alone changes nothing.
    nominal = disturbance is None or not bool(
        disturbance[:_GUST_TIME].any() or disturbance[_GUST_TIME + 1 :].any()
    )
    return None if nominal else _to(disturbance, torch.float64, device)


def steps_back(disturbance: torch.Tensor | None) -> tuple[int, int]:
    """``(action_delay, observed_actions)`` of ``disturbance`` (:func:`disturbance_constants`).

    The commands each drone keeps in flight and those it observes.
    """
    if disturbance is None:
        return 0, 0
    delay, observed = (DISTURBANCE_CONSTANTS.index(k) for k in ("action_delay", "observed_actions"))
    return int(disturbance[delay]), int(disturbance[observed])


def param_count(in_dim: int, hidden: Sequence[int]) -> int:
    """The flat parameter count of a network with ``in_dim`` inputs and ``hidden`` sizes."""
    widths = [in_dim, *hidden]
    layers = sum(a * b + b for a, b in zip(widths, widths[1:], strict=False))
    return layers + 2 * (dynamics.ACTION_DIM * widths[-1] + dynamics.ACTION_DIM)


def _check_net(params: torch.Tensor, hidden: Sequence[int], disturbance: torch.Tensor | None) -> int:
    """The policy's input width, which must be what it sees under ``disturbance``."""
    if disturbance is not None and tuple(disturbance.shape) != (len(DISTURBANCE_CONSTANTS),):
        raise ValueError(
            f"disturbance of shape {list(disturbance.shape)}; expected [{len(DISTURBANCE_CONSTANTS)}] "
            "(ops.disturbance_constants)"
        )
    if not all(0 <= k <= disturbances.MAX_STEPS_BACK for k in steps_back(disturbance)):
        raise ValueError(
            f"action_delay and observed_actions {steps_back(disturbance)} are not allowed; expected "
            f"integers in [0, {disturbances.MAX_STEPS_BACK}] (the kernels' command memory)"
        )
    in_dim = len(disturbances.observation_names({"observed_actions": steps_back(disturbance)[1]}))
    if params.shape[-1] != param_count(in_dim, hidden):
        raise ValueError(
            f"params of {params.shape[-1]} values do not fit the policy of {in_dim} inputs and hidden "
            f"sizes {list(hidden)} that the disturbance implies; expected {param_count(in_dim, hidden)}"
        )
    return in_dim


# ---------------------------------------------------------------------------------------- the ops
# Plain functions over the C interface: the package calls them eagerly (nothing traces them), so
# they carry no torch.library registration.


#: ``RolloutArgs``' segment fields (drone_kernels.cpp), which only :func:`segments` fills: their
#: count must follow that struct (the test of every op against the reference fails on a shift).
_NO_SEGMENTS = (None,) * 19


# The inputs follow the parameters to their device (None stays None).
def _to(
    x: torch.Tensor | None, dtype: torch.dtype, device: torch.device | None = None
) -> torch.Tensor | None:
    return None if x is None else x.to(device=device, dtype=dtype).contiguous()


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
    disturbance: torch.Tensor | None = None,
    keys: torch.Tensor | None = None,
    observations: bool = False,
) -> tuple[torch.Tensor, ...]:
    """Fly every active agent's ``E`` episodes until each ends or ``steps`` pass.

    Args:
        params: ``[N, P]`` flat parameters (a policy of the observation's inputs).
        start: ``[N, E, 6]`` start states (None with ``rng``).
        noise: ``[N, E, steps, 2]`` standard normals (``action = f(loc + scale * noise)``), or None
            for the deterministic action (or with ``rng``).
        rng: ``[N, E, 2]`` int64, each agent's seed and update counter (the same for its ``E``
            rows): the start states, the action noise and the episode keys are then drawn inside
            the kernel, exactly where :mod:`drone_torchrl.envs.rng` draws them (``uniform`` and
            ``keys`` bit for bit, ``normal`` to float rounding), and only for the steps flown.
        active: ``[N]`` bool; inactive agents fly nothing (length 0).
        env: :func:`env_constants`.
        gamma: ``[N]``, each agent's discount for the returns-to-go.
        hidden: the network's hidden layer widths.
        activation: its activation's code (:data:`ACTIVATION_CODES`).
        min_std: the floor added to the std head's softplus.
        steps: the most steps an episode flies (its truncation, ``env.max_steps``).
        dist_eps: added to the mean and to the std, ``Normal(mu + eps, sigma + eps)``
            (:class:`~drone_torchrl.modules.policy.ThreeNetPolicy`'s ``distribution_eps``).
        disturbance: :func:`disturbance_constants` (None: the nominal drone).
        keys: ``[N, E]`` int64 episode keys of the disturbances (as
            :func:`drone_torchrl.envs.disturbances.start` takes them); None: element ``e`` of
            ``rng.keys(seed, counter, rng.EPISODE_KEYS, (E,))``.
        observations: also return what the policy saw.

    Returns ``states [N, E, steps + 1, 6]`` (the true states, before each step, then after the
    last), ``action [N, E, steps, 2]``, ``reward [N, E, steps]``, ``cause [N, E, steps]`` (int64
    :class:`~.dynamics.TerminationCause` codes), ``length [N, E]`` (int64), ``returns [N, E, steps]`` (each
    step's discounted return-to-go, :func:`~drone_torchrl.objectives.reinforce.discounted_returns`),
    ``stats [N, E, 4]`` float64 (:data:`STAT_NAMES`) and, with ``observations``, what the policy
    saw before each step ``[N, E, steps, D]`` (D: the observation's width) (else an empty tensor); entries after
    an episode's end hold zeros.
    """
    if start is None and rng is None:
        raise ValueError("ops.rollout needs start states or rng keys")
    # rng [N, E, 2]: only its shape is read for E (the keys are per agent).
    n, episodes = (active.shape[0], rng.shape[1]) if start is None else start.shape[:2]
    in_dim = _check_net(params, hidden, disturbance)
    dtype, device = params.dtype, params.device
    # Bound to names: a pointer is only valid while its tensor lives.
    disturbance = _magnitudes(disturbance, device)
    if keys is None and rng is None and disturbance is not None:
        raise ValueError("ops.rollout under disturbances needs episode keys or rng keys")
    zeros, i64, shape = params.new_zeros, torch.int64, (n, episodes, steps)
    states, action = zeros(n, episodes, steps + 1, dynamics.STATE_DIM), zeros(*shape, dynamics.ACTION_DIM)
    reward, returns, cause = zeros(shape), zeros(shape), zeros(shape, dtype=i64)
    length, stats = zeros(n, episodes, dtype=i64), zeros(n, episodes, STATS, dtype=torch.float64)
    seen = zeros(*shape, in_dim) if observations else zeros(0)
    params, start, noise = params.contiguous(), _to(start, dtype, device), _to(noise, dtype, device)
    active, rng, keys = _to(active, torch.uint8, device), _to(rng, i64, device), _to(keys, i64, device)
    env, gamma = _to(env, torch.float64, device), _to(gamma, torch.float64, device)
    args = (n * episodes, episodes, steps, params, start, noise, rng, keys, active, env, disturbance, gamma)
    args += (states, action, reward, cause, length, returns, stats, seen if observations else None, None)
    net = _net(in_dim, hidden, activation, min_std, dist_eps)
    sizes = (n * episodes, 0, episodes, steps)
    _launch(_lib(dtype, device), "rollout", device, net, args + _NO_SEGMENTS, sizes)
    return states, action, reward, cause, length, returns, stats, seen


#: The loss options ``ops.reinforce`` takes in its order (``LossOptions`` in drone_kernels.cpp).
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
    disturbance: torch.Tensor | None = None,
) -> tuple[torch.Tensor, ...]:
    """One REINFORCE update's episodes and gradient for every active agent, by the C++ engine.

    The episodes of :func:`rollout` with ``rng`` (``[N, E, 2]``: each agent's seed and update
    counter) and ``disturbance``, then each agent's loss, the ``loss_per_agent`` of
    :func:`~drone_torchrl.objectives.reinforce.reinforce_terms` (``options``: the four flags of
    :data:`LOSS_OPTIONS`; ``gamma`` ``[N]``), and its gradient in the parameters, back-propagated
    through the hidden outputs the rollout kept at the observations the policy saw (no second
    forward pass). Inactive agents get zeros.

    Returns ``grad [N, P]``, ``loss [N]`` and ``std_mean [N]`` (float64: the policy's mean std over
    the valid steps and motors), ``actions_finite [N]`` (bool), ``length [N, E]`` and
    ``counts [N, E, 4]`` (:data:`STAT_NAMES`).
    """
    n, episodes = rng.shape[:2]
    in_dim = _check_net(params, hidden, disturbance)
    dtype, device = params.dtype, params.device
    # Each agent's episodes and gradient are its own: the kernel runs on AGENTS_PER_CALL agents at a
    # time, so that its scratch (every step's rewards and what the backward pass reads) is that
    # many agents' whatever the population's size.
    chunk = max(1, min(n, AGENTS_PER_CALL))
    empty, zeros, f64, i64 = params.new_empty, params.new_zeros, torch.float64, torch.int64
    scratch = (chunk, episodes, steps)  # each call's, reused
    reward, returns, cause = empty(scratch), empty(scratch), empty(scratch, dtype=i64)
    length, counts = zeros(n, episodes, dtype=i64), zeros(n, episodes, STATS, dtype=f64)
    grad, loss, std_mean = torch.zeros_like(params), zeros(n, dtype=f64), zeros(n, dtype=f64)
    actions_finite = params.new_ones(n, dtype=torch.bool)
    lib, net = _lib(dtype, device), _net(in_dim, hidden, activation, min_std, dist_eps)
    sizes = (chunk * episodes, chunk, episodes, steps)
    saved = empty(lib.dk_saved_size(_words(*net, *sizes)))
    params, active, rng = params.contiguous(), _to(active, torch.uint8, device), _to(rng, i64, device)
    env, gamma = _to(env, torch.float64, device), _to(gamma, torch.float64, device)
    disturbance = _magnitudes(disturbance, device)
    for first in range(0, n, chunk):
        r = slice(first, min(n, first + chunk))
        k = r.stop - r.start
        roll = (k * episodes, episodes, steps, params[r], None, None, rng[r], None, active[r], env)
        roll += (disturbance, gamma[r], None, None, reward, cause, length[r], returns, counts[r], None, saved)
        args = (*roll, *_NO_SEGMENTS, k, *map(int, options), grad[r], loss[r], std_mean[r], actions_finite[r])
        _launch(lib, "reinforce", device, net, args, sizes)
    return grad, loss, std_mean, actions_finite, length, counts


class Carried(NamedTuple):
    """What each drone carries from one :func:`segments` call to the next (``n`` drones).

    ``state`` ``[n, 6]``, its physical state; ``t`` ``[n]`` int64, its episode's step count (``-1``:
    its episode ended, a new one starts at the next call's step 0; a first call passes ``t = -1``
    everywhere, and the other values are then not read); ``key`` ``[n]`` int64, its episode key; the
    disturbances' internal state (:class:`drone_torchrl.envs.disturbances.Internal`): ``gust``
    ``[n]``, the gust force / nominal weight, ``thrust`` ``[n, 2]``, the motors' thrust fractions in
    effect (lag), ``pending`` ``[n, action_delay, 2]``, the commands issued but not yet acting,
    oldest first, ``issued`` ``[n, observed_actions, 2]``, the last commands issued, newest first.
    """

    state: torch.Tensor
    t: torch.Tensor
    key: torch.Tensor
    gust: torch.Tensor
    thrust: torch.Tensor
    pending: torch.Tensor
    issued: torch.Tensor


class Segment(NamedTuple):
    """One call's steps of each drone, ``[n, steps, ...]``, keyed as TorchRL's collector keys them.

    The keys are the env's: ``observation``, ``action``, ``step_count`` and ``next``'s
    ``observation``, ``reward``, ``termination_cause``, ``terminated``, ``truncated``.
    """

    observation: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    next_observation: torch.Tensor
    cause: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    step_count: torch.Tensor


def segments(
    params: torch.Tensor,
    carried: Carried,
    noise: torch.Tensor,
    fresh: torch.Tensor,
    fresh_keys: torch.Tensor | None,
    max_steps: int,
    env: torch.Tensor,
    disturbance: torch.Tensor | None,
    hidden: Sequence[int],
    activation: int,
    min_std: float,
    dist_eps: float = 0.0,
) -> tuple[Segment, Carried]:
    """Fly ``n`` drones of one agent ``steps`` steps with auto-reset.

    What TorchRL's collector gives over a batched :class:`~drone_torchrl.envs.drone_env.DroneEnv` (``done =
    terminated | truncated``, a new episode as soon as one ends), given the same draws.

    Args:
        params: ``[P]`` the agent's flat parameters.
        carried: what each drone carries from the last call (what it returned).
        noise: ``[n, steps, 2]`` standard normals of the actions.
        fresh: ``[n, steps, 6]`` start states: a drone that starts a new episode at step ``j``
            starts from ``fresh[d, j]``.
        fresh_keys: ``[n, steps]`` int64, that episode's key ``fresh_keys[d, j]`` (None: the
            nominal drone, which draws nothing).
        max_steps: the episodes' truncation (``env.max_steps``).
        env: :func:`env_constants`.
        disturbance: :func:`disturbance_constants` (None: nominal).
        hidden: the network's hidden layer widths, as for :func:`rollout`.
        activation: its activation's code, as for :func:`rollout`.
        min_std: the std's floor, as for :func:`rollout`.
        dist_eps: the distribution's epsilon, as for :func:`rollout`.

    Returns the steps: per step ``[n, steps, ...]``, the observation the policy saw, the action, the
    reward, the next observation (what the env returns after the step: at the step count after it,
    with its noise; after an episode's last step, the terminal state's), the termination cause
    (int64), terminated and truncated (bool: the step count reached ``max_steps`` without
    terminating) and the step count before the step (int64). Then what is carried after the last
    step (``t = -1`` where the last step ended the episode).
    """
    if params.device.type != "cpu":
        raise ValueError(f"ops.segments runs on the CPU only; params are on {params.device}")
    in_dim = _check_net(params, hidden, disturbance)
    (n, steps), (delay, observed), a = noise.shape[:2], steps_back(disturbance), dynamics.ACTION_DIM
    shapes = {
        "state": (n, dynamics.STATE_DIM), "t": (n,), "key": (n,), "gust": (n,), "thrust": (n, a),
        "pending": (n, delay, a), "issued": (n, observed, a), "fresh": (n, steps, dynamics.STATE_DIM),
        "fresh_keys": (n, steps),
    }  # fmt: skip
    for name, tensor in {**carried._asdict(), "fresh": fresh, "fresh_keys": fresh_keys}.items():
        if tensor is not None and tuple(tensor.shape) != shapes[name]:
            raise ValueError(
                f"ops.segments: {name} of shape {list(tensor.shape)}; expected {list(shapes[name])}"
            )
    disturbance = _magnitudes(disturbance)
    if fresh_keys is None and disturbance is not None:
        raise ValueError("ops.segments under disturbances needs fresh_keys")
    dtype, i64 = params.dtype, torch.int64
    kinds = {"t": i64, "key": i64}  # the carried integers; the rest is real
    per_step = partial(torch.empty, n, steps)
    seg = Segment(
        *(per_step(*shape, dtype=dtype) for shape in ((in_dim,), (a,), (), (in_dim,))),
        *(per_step(dtype=kind) for kind in (i64, torch.bool, torch.bool, i64)),
    )
    out = Carried(*(torch.empty(shapes[k], dtype=kinds.get(k, dtype)) for k in Carried._fields))
    # Bound to names: a pointer is only valid while its tensor lives.
    state, t, key, *internal = (_to(x, kinds.get(k, dtype)) for k, x in carried._asdict().items())
    params, noise, fresh = params.contiguous(), _to(noise, dtype), _to(fresh, dtype)
    fresh_keys, env, active = _to(fresh_keys, i64), _to(env, torch.float64), torch.ones(1, dtype=torch.uint8)
    # RolloutArgs with t: one agent's drones (episodes = rows: every row flies agent 0).
    args = (n, max(n, 1), steps, params, state, noise, None, key, active, env, disturbance, None, None)
    args += (seg.action, seg.reward, seg.cause, None, None, None, seg.observation, None, max_steps, t)
    args += (*internal, fresh, fresh_keys, seg.next_observation, seg.terminated, seg.truncated)
    args += (seg.step_count, *out)
    _launch(_lib(dtype), "rollout", params.device, _net(in_dim, hidden, activation, min_std, dist_eps), args)
    return seg, out
