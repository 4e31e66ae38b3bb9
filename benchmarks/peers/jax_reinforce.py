"""An independent JAX peer of the project's REINFORCE study ("PureJaxRL style"), for benchmarking.

    python benchmarks/peers/jax_reinforce.py --grid lr --episodes 6000      # one grid, this process
    python benchmarks/peers/jax_reinforce.py --grid gamma --episodes 600    # a short rehearsal
    python benchmarks/peers/jax_reinforce.py --study --episodes 6000        # both grids side by side

What it implements, written from the project's source but sharing no code with it (only jax, numpy
and the standard library are imported; ``tests/test_jax_peer.py`` checks it against the project):

- the physics of ``drone_torchrl/envs/dynamics.py`` with the default ``DroneParams`` (mass 1,
  motor distance 1, gravity 9.81, dt 0.02, floor tolerance 0.05, unbounded thrust): state
  ``[x, x_dot, z, z_dot, alpha, alpha_dot]``, action = the two motor commands as fractions of the
  weight, one semi-implicit Euler step, termination causes (out of x 1, floor 2, ceiling 3, tilt 4;
  the lowest non-zero code wins), reward 0 on the terminating step, 10 in the target zone, 1
  elsewhere, episodes truncated after 300 steps, "floor" start states (x and alpha uniform in
  +-0.01, the rest 0);
- the paper's policy (``ThreeNetPolicy`` + the "normal" head of ``make_actor``): trunk 6-32-32 with
  tanh, a linear mean head and a linear std head with softplus + 1e-6, an independent Normal per
  motor over unbounded thrust, log-probabilities summed over the motors; every layer initialised
  like PyTorch's ``nn.Linear`` default (weights and biases uniform in +-1/sqrt(fan_in));
- plain Monte-Carlo REINFORCE (``ReinforceLoss`` with the paper's settings): returns-to-go
  ``G_t = sum_{k>=t} gamma^(k-t) r_k`` over the episode, ``loss = -sum_t G_t log pi(a_t|s_t)``
  over its valid steps (up to and including the terminating or truncating one), one episode per
  update, no baseline, no normalisation, no gradient clipping;
- ``torch.optim.Adam`` (betas 0.9/0.999, eps 1e-8, no weight decay), one per agent, per-agent lr;
- the study: grid ``lr`` (lr in {1e-3, 5e-4, 1e-4, 5e-5} x seeds 0..3 at gamma 0.99) and grid
  ``gamma`` (gamma in {0.9, 0.95, 0.99, 0.999} x seeds 0..3 at lr 1e-4), 16 agents each, 6000
  episodes (= updates) per agent; the final metric of an agent is the mean return of its last 100
  episodes (the project's running mean at the end of training).

How it runs: one update of every agent of the grid (rollout, returns-to-go, gradients, Adam) is a
pure function; ``--scan`` updates (default 100) are one ``lax.scan`` compiled once with
``jax.jit``, so Python runs once per 100 updates. The rollout is batched over the agents (one
``[16, 6]`` state, the nets ``vmap``-ed); the loss is ``jax.grad``-ed and ``vmap``-ed over them;
Adam runs on each agent's weights as one flat vector. Rollouts: ``--rollout while`` (default)
flies a ``lax.while_loop`` that stops as soon as every agent's episode has ended (checked every
``--unroll`` steps); ``--rollout scan`` always flies 300 steps in a ``lax.scan`` and masks the
steps after each episode's end. Both give bit-identical episodes. The gradient runs over all 300
stored steps (masked) by default; ``--chunk 50`` (any divisor of 300) accumulates it over chunks
of 50 steps, only as far as the longest episode of the update. In this study both early stops pay
little: one of the 16 agents flies all 300 steps in about 96% of the updates (the loop runs to the
longest episode), so the defaults are the ones measured fastest on grid ``lr`` (``while`` about 3%
faster than ``scan``, chunk 300 about 12% faster than chunk 50). A different chunk sums the gradient
in another order: same to float rounding, but training then diverges from the default run's.

How it differs from the project:

- its own random numbers (JAX's threefry): with ``init_key, train_key = split(key(s))``, agent
  ``s`` draws its initial weights from ``init_key`` and update ``u``'s start state and action
  noise from ``fold_in(train_key, u)``, so results do not depend on ``--scan``. Runs are
  statistically, not bitwise, comparable with the project's (which draws from its own
  counter-based generator); like there, the agents of a grid that share a seed share their
  initial weights and noise stream;
- the two heads are stored as one ``[32, 4]`` layer (one matrix product; the same function), and
  the initial weights are drawn as one vector, so a seed's weights differ from PyTorch's;
- returns-to-go by blocks of 20 steps (two small matrix products over all 300 steps, rewards after
  the episode's end being zero): float rounding differs from the project's at the 1e-7 level;
- Adam's bias corrections are computed in float32 as ``-expm1(t * log(beta))`` (PyTorch: in
  Python doubles), which agrees to float32 rounding;
- nothing is logged, checkpointed or evaluated: it trains and reports the returns.

One CPU thread per process, as the project trains with one torch thread per process: before jax is
imported this module appends to ``XLA_FLAGS``::

    --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1
    --xla_cpu_parallel_codegen_split_count=1

and sets ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS`` to 1 (unless set). The
first flag keeps XLA's matrix products on the calling thread; the third makes XLA compile in one
thread (without it, compilation runs on several cores: about 5.5 s of CPU in 3.5 s of wall-clock
here); ``intra_op_parallelism_threads=1`` is the common recipe's setting but not an XLA flag (no
leading ``--``), which XLA ignores. Each run prints its process CPU time next to its wall-clock: with
these settings they agree (a second busy thread would make the CPU time larger). ``--study`` starts
the two grids as two such processes side by side (like ``benchmarks/full_study.py`` does for the
project: one per core).

Compile time is measured cold: JAX's persistent compilation cache is switched off unless
``--cache-dir DIR`` is given. Printed times: imports (jax included, from the first line of this
module), setup (initial weights), compile (trace, lower and XLA-compile the update loop, ahead of
time), train (every update, waiting for the result) and total (this module's first line to the
end; the interpreter's own start-up, a few tens of ms, comes on top).
"""

from __future__ import annotations

import os
import sys
import time

_T0 = time.perf_counter()
_CPU0 = time.process_time()

ONE_THREAD_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1 --xla_cpu_parallel_codegen_split_count=1"


def _one_thread() -> None:
    """Ask XLA (and any BLAS) for one CPU thread; must run before jax is imported."""
    flags = os.environ.get("XLA_FLAGS", "")
    if ONE_THREAD_XLA_FLAGS not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {ONE_THREAD_XLA_FLAGS}".strip()
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")


_one_thread()

import argparse  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import threading  # noqa: E402
from functools import partial  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax import lax  # noqa: E402

_T_IMPORTED = time.perf_counter()

# ----------------------------------------------------------------------------- physics (dynamics.py)

STATE_DIM, ACTION_DIM = 6, 2
X, X_DOT, Z, Z_DOT, ALPHA, ALPHA_DOT = range(STATE_DIM)
X_LIMIT = 2.0
Z_MIN, Z_MAX = 0.0, 4.0
ALPHA_LIMIT = math.pi / 3
ZONE_X_LIMIT = 0.8
ZONE_Z_MIN, ZONE_Z_MAX = 2.2, 3.2
ZONE_Z_CENTRE = 0.5 * (ZONE_Z_MIN + ZONE_Z_MAX)
REWARD_TERMINATED, REWARD_IN_ZONE, REWARD_ALIVE = 0.0, 10.0, 1.0
RESET_NOISE = 0.01
OUT_X, FLOOR, CEILING, TILT = 1, 2, 3, 4

MASS = 1.0
MOTOR_DISTANCE = 1.0
GRAVITY = 9.81
DT = 0.02
FLOOR_TOLERANCE = 0.05
LEVER_ARM = 0.5 * MOTOR_DISTANCE
INERTIA = 0.4 * MASS * LEVER_ARM**2
WEIGHT = MASS * GRAVITY
MAX_STEPS = 300

# ----------------------------------------------------------------------------- agent and study

HIDDEN = (32, 32)
MIN_STD = 1e-6
BETA1, BETA2, ADAM_EPS = 0.9, 0.999, 1e-8
WINDOW = 100  # the running-mean window of the final metric

GRIDS = {
    "lr": [(lr, 0.99, seed) for lr in (1e-3, 5e-4, 1e-4, 5e-5) for seed in range(4)],
    "gamma": [(1e-4, gamma, seed) for gamma in (0.9, 0.95, 0.99, 0.999) for seed in range(4)],
}


def integrate(state: jax.Array, action: jax.Array) -> jax.Array:
    """One semi-implicit Euler step of eqs. 2.1-2.3 (``[..., 6]`` states, ``[..., 2]`` actions)."""
    x, x_dot, z, z_dot, alpha, alpha_dot = (state[..., i] for i in range(STATE_DIM))
    thrust_left = action[..., 0] * WEIGHT
    thrust_right = action[..., 1] * WEIGHT
    total = thrust_left + thrust_right
    x_ddot = jnp.sin(-alpha) * total / MASS
    z_ddot = jnp.cos(alpha) * total / MASS - GRAVITY
    alpha_ddot = (thrust_right - thrust_left) * (LEVER_ARM / INERTIA)
    x_dot = x_dot + x_ddot * DT
    z_dot = z_dot + z_ddot * DT
    alpha_dot = alpha_dot + alpha_ddot * DT
    return jnp.stack(
        (x + x_dot * DT, x_dot, z + z_dot * DT, z_dot, alpha + alpha_dot * DT, alpha_dot), axis=-1
    )


def termination_cause(state: jax.Array) -> jax.Array:
    """Cause code (int32) per state, 0 inside the domain; the lowest non-zero code wins."""
    x, z, alpha = state[..., X], state[..., Z], state[..., ALPHA]
    cause = jnp.zeros(state.shape[:-1], jnp.int32)
    cause = jnp.where(jnp.abs(alpha) > ALPHA_LIMIT, TILT, cause)
    cause = jnp.where(z > Z_MAX, CEILING, cause)
    cause = jnp.where(z < Z_MIN - FLOOR_TOLERANCE, FLOOR, cause)
    return jnp.where(jnp.abs(x) > X_LIMIT, OUT_X, cause)


def in_target_zone(state: jax.Array) -> jax.Array:
    x, z, alpha = state[..., X], state[..., Z], state[..., ALPHA]
    return (
        (jnp.abs(x) <= ZONE_X_LIMIT) & (z >= ZONE_Z_MIN) & (z <= ZONE_Z_MAX) & (jnp.abs(alpha) <= ALPHA_LIMIT)
    )


def reward(state: jax.Array, terminated: jax.Array) -> jax.Array:
    alive = jnp.where(in_target_zone(state), REWARD_IN_ZONE, REWARD_ALIVE)
    return jnp.where(terminated, REWARD_TERMINATED, alive).astype(state.dtype)


def step(state: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(next_state, reward, termination_cause)``, as ``dynamics.step`` with unbounded thrust."""
    next_state = integrate(state, action)
    cause = termination_cause(next_state)
    return next_state, reward(next_state, cause != 0), cause


def start_states(uniform: jax.Array, mode: str = "floor") -> jax.Array:
    """Start states from uniforms in [0, 1) of shape ``[..., 6]`` (``dynamics.states_from_uniform``)."""
    noise = (2.0 * uniform - 1.0) * RESET_NOISE
    if mode == "air":
        return noise + jnp.zeros(STATE_DIM, uniform.dtype).at[Z].set(ZONE_Z_CENTRE)
    return noise * jnp.zeros(STATE_DIM, uniform.dtype).at[jnp.array([X, ALPHA])].set(1.0)


# ----------------------------------------------------------------------------- policy

# One agent's weights are one flat float32 vector (Adam then updates every weight in one pass); the
# layers are static slices of it. Weights are [fan_in, fan_out] (``x @ w + b``): PyTorch's transposed.
# The mean and std heads are one [32, 4] layer ("wh", "bh"; columns 0-1 the mean head's, 2-3 the std
# head's): one matrix product instead of two, the same numbers as two separate heads.
LAYER_SHAPES = (
    ("w1", (STATE_DIM, HIDDEN[0])),
    ("b1", (HIDDEN[0],)),
    ("w2", (HIDDEN[0], HIDDEN[1])),
    ("b2", (HIDDEN[1],)),
    ("wh", (HIDDEN[1], 2 * ACTION_DIM)),
    ("bh", (2 * ACTION_DIM,)),
)
FAN_IN = {
    "w1": STATE_DIM,
    "b1": STATE_DIM,
    "w2": HIDDEN[0],
    "b2": HIDDEN[0],
    "wh": HIDDEN[1],
    "bh": HIDDEN[1],
}
_OFFSETS = np.cumsum([0] + [math.prod(shape) for _, shape in LAYER_SHAPES]).tolist()
N_PARAMS = _OFFSETS[-1]


def unflatten(flat: jax.Array) -> dict[str, jax.Array]:
    """One agent's flat weight vector ``[N_PARAMS]`` as named layers."""
    return {
        name: flat[lo:hi].reshape(shape)
        for (name, shape), lo, hi in zip(LAYER_SHAPES, _OFFSETS[:-1], _OFFSETS[1:], strict=True)
    }


def flatten(layers: dict) -> jax.Array:
    """Inverse of :func:`unflatten`; with a leading agent axis on every layer, ``[N, N_PARAMS]``."""
    lead = layers["b1"].shape[:-1]
    return jnp.concatenate([jnp.reshape(layers[name], (*lead, -1)) for name, _ in LAYER_SHAPES], axis=-1)


def init_params(key: jax.Array) -> jax.Array:
    """One agent's flat weights, like ``nn.Linear``'s default: every weight and bias uniform in
    +-1/sqrt(fan_in) of its layer (one draw of ``N_PARAMS`` uniforms)."""
    bound = np.concatenate(
        [np.full(math.prod(shape), 1.0 / math.sqrt(FAN_IN[name]), np.float32) for name, shape in LAYER_SHAPES]
    )
    return jax.random.uniform(key, (N_PARAMS,), jnp.float32, -1.0, 1.0) * bound


def torch_state_dict(flat) -> dict[str, np.ndarray]:
    """One agent's weights as ``ThreeNetPolicy().state_dict()`` arrays (numpy, ``[out, in]``)."""
    p = {name: np.asarray(value) for name, value in unflatten(jnp.asarray(flat)).items()}
    return {
        "shared.0.weight": p["w1"].T.copy(),
        "shared.0.bias": p["b1"].copy(),
        "shared.2.weight": p["w2"].T.copy(),
        "shared.2.bias": p["b2"].copy(),
        "mean.weight": p["wh"][:, :ACTION_DIM].T.copy(),
        "mean.bias": p["bh"][:ACTION_DIM].copy(),
        "std.weight": p["wh"][:, ACTION_DIM:].T.copy(),
        "std.bias": p["bh"][ACTION_DIM:].copy(),
    }


def from_torch_state_dict(state: dict) -> np.ndarray:
    """Inverse of :func:`torch_state_dict` (accepts numpy arrays or CPU tensors)."""
    s = {name: np.asarray(value, np.float32) for name, value in state.items()}
    layers = {
        "w1": s["shared.0.weight"].T,
        "b1": s["shared.0.bias"],
        "w2": s["shared.2.weight"].T,
        "b2": s["shared.2.bias"],
        "wh": np.concatenate([s["mean.weight"].T, s["std.weight"].T], axis=1),
        "bh": np.concatenate([s["mean.bias"], s["std.bias"]]),
    }
    return np.asarray(flatten(layers))


def softplus(x: jax.Array) -> jax.Array:
    """``torch.nn.functional.softplus`` (beta 1, threshold 20), safe to differentiate."""
    return jnp.where(x > 20.0, x, jnp.log1p(jnp.exp(jnp.minimum(x, 20.0))))


def policy(p: dict[str, jax.Array], obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(loc, scale)`` of one agent's Normal head (layers ``p``, see :func:`unflatten`) for
    observations ``[..., 6]``."""
    h = jnp.tanh(obs @ p["w1"] + p["b1"])
    h = jnp.tanh(h @ p["w2"] + p["b2"])
    heads = h @ p["wh"] + p["bh"]
    return heads[..., :ACTION_DIM], softplus(heads[..., ACTION_DIM:]) + MIN_STD


def log_prob(loc: jax.Array, scale: jax.Array, action: jax.Array) -> jax.Array:
    """The two motors' Normal log-densities, summed (``torch.distributions.Normal.log_prob``)."""
    per_motor = -((action - loc) ** 2) / (2 * scale**2) - jnp.log(scale) - math.log(math.sqrt(2 * math.pi))
    return per_motor.sum(-1)


# ----------------------------------------------------------------------------- REINFORCE

BLOCK = 20  # returns-to-go: 300 steps as 15 blocks of 20


def discount_tables(gamma: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """One agent's tables for :func:`returns_to_go`: ``within [L, L]`` (``gamma^(j-i)`` for ``j >= i``),
    ``across [B, B]`` (``gamma^(L (c-b))`` for ``c >= b``) and ``tail [L]`` (``gamma^(L-i)``)."""
    gamma = jnp.asarray(gamma, jnp.float32)
    blocks = MAX_STEPS // BLOCK
    i = np.arange(BLOCK)
    b = np.arange(blocks)
    lag, block_lag = i[None, :] - i[:, None], b[None, :] - b[:, None]
    within = jnp.where(lag >= 0, gamma ** np.maximum(lag, 0).astype(np.float32), 0.0)
    across = jnp.where(block_lag >= 0, gamma ** (BLOCK * np.maximum(block_lag, 0)).astype(np.float32), 0.0)
    return within, across, gamma ** (BLOCK - i).astype(np.float32)


def returns_to_go(reward: jax.Array, tables) -> jax.Array:
    """``G_t = sum_{k>=t} gamma^(k-t) r_k`` for one episode ``reward [300]`` (zeros past its end).

    Blocked: discounted suffix sums inside each block of ``L`` steps (a small matrix product), the
    blocks' own returns from the block sums (another), and each step's share of the next block's.
    """
    within, across, tail = tables
    r = reward.reshape(-1, BLOCK)
    inner = r @ within.T  # [B, L]: sums inside the block
    block_returns = across @ inner[:, 0]  # [B]: G at each block's first step
    later = jnp.concatenate([block_returns[1:], jnp.zeros(1, r.dtype)])
    return (inner + tail * later[:, None]).reshape(-1)


def steps_loss(layers, obs, action, returns, valid) -> jax.Array:
    """``-sum_t G_t log pi(a_t|s_t)`` over the ``valid`` ones of some steps of one agent's episode."""
    loc, scale = policy(layers, obs)
    return -jnp.where(valid, returns * log_prob(loc, scale, action), 0.0).sum()


def episode_loss(flat, obs, action, reward, valid, gamma) -> jax.Array:
    """One agent's REINFORCE loss on one episode (``obs [300, 6]``, ``action [300, 2]``,
    ``reward [300]``, ``valid [300]``: the steps up to and including the episode's last)."""
    returns = returns_to_go(jnp.where(valid, reward, 0.0), discount_tables(gamma))
    return steps_loss(unflatten(flat), obs, action, returns, valid)


def loss_grads(params, obs, action, reward, valid, tables, chunk: int = MAX_STEPS) -> jax.Array:
    """Every agent's gradient of its :func:`episode_loss` (``[N, N_PARAMS]``), from batched episodes
    ``[N, 300, ...]`` and per-agent :func:`discount_tables`.

    ``jax.grad`` of the loss, ``vmap``-ed over the agents: over all 300 steps at once (the default),
    or, with ``chunk`` (a divisor of 300) smaller, accumulated over chunks of ``chunk`` steps only as
    far as the longest episode goes (the loss is a sum over steps).
    """
    returns = jax.vmap(returns_to_go)(jnp.where(valid, reward, 0.0), tables)
    longest = valid.sum(-1).max()
    # The layers are sliced out of the flat vectors once, outside the loop: as separate arrays the
    # matrix products run as such (sliced inside, XLA fuses the slice into a slower product).
    layers = jax.vmap(unflatten)(params)
    if chunk >= MAX_STEPS:  # one pass over every step
        return flatten(jax.vmap(jax.grad(steps_loss))(layers, obs, action, returns, valid))

    def body(c, total):
        part = [lax.dynamic_slice_in_dim(x, c * chunk, chunk, axis=1) for x in (obs, action, returns, valid)]
        grads = jax.vmap(jax.grad(steps_loss))(layers, *part)
        return jax.tree_util.tree_map(jnp.add, total, grads)

    zeros = jax.tree_util.tree_map(jnp.zeros_like, layers)
    return flatten(lax.fori_loop(0, (longest + chunk - 1) // chunk, body, zeros))


def adam_init(params: jax.Array) -> dict[str, jax.Array]:
    return {"m": jnp.zeros_like(params), "v": jnp.zeros_like(params), "count": jnp.zeros((), jnp.int32)}


def adam_update(params, grads, opt, lr):
    """One ``torch.optim.Adam`` step of one agent (betas 0.9/0.999, eps 1e-8, no weight decay)."""
    count = opt["count"] + 1
    t = count.astype(jnp.float32)
    bias_correction1 = -jnp.expm1(t * math.log(BETA1))
    bias_correction2_sqrt = jnp.sqrt(-jnp.expm1(t * math.log(BETA2)))
    m = opt["m"] + (1 - BETA1) * (grads - opt["m"])  # torch's lerp_
    v = opt["v"] * BETA2 + (1 - BETA2) * grads * grads
    params = params - (lr / bias_correction1) * (m / (jnp.sqrt(v) / bias_correction2_sqrt + ADAM_EPS))
    return params, {"m": m, "v": v, "count": count}


# ----------------------------------------------------------------------------- rollouts


def _agents_step(layers, state, noise, done, t):
    """One step of every agent's episode (``state [N, 6]``, ``noise [N, 2]``, ``done [N]``: ended
    before this step). Finished episodes keep their last state; their steps are invalid."""
    loc, scale = jax.vmap(policy)(layers, state)
    action = loc + scale * noise
    next_state, r, cause = step(state, action)
    valid = ~done
    ended = done | (cause != 0) | (t + 1 >= MAX_STEPS)
    next_state = jnp.where(done[:, None], state, next_state)
    return next_state, ended, (state, action, jnp.where(valid, r, 0.0), valid)


def rollout_scan(params, start, noise, unroll: int = 1):
    """Every agent's episode over a fixed 300-step ``lax.scan``: ``(obs [N, T, 6], action [N, T, 2],
    reward [N, T], valid [N, T])``. ``noise``: ``[N, T, 2]`` standard normals."""

    layers = jax.vmap(unflatten)(params)  # once, outside the loop (see loss_grads)

    def body(carry, xs):
        state, done = carry
        eps, t = xs
        state, done, out = _agents_step(layers, state, eps, done, t)
        return (state, done), out

    done = jnp.zeros(start.shape[:1], bool)
    xs = (jnp.swapaxes(noise, 0, 1), jnp.arange(MAX_STEPS))
    _, outs = lax.scan(body, (start, done), xs, unroll=unroll)
    return tuple(jnp.swapaxes(a, 0, 1) for a in outs)


def rollout_while(params, start, noise, unroll: int = 1):
    """As :func:`rollout_scan`, in a ``lax.while_loop`` that stops once every episode has ended
    (checked every ``unroll`` steps, which must divide 300); unflown steps are invalid."""
    n = start.shape[0]
    layers = jax.vmap(unflatten)(params)  # once, outside the loop (see loss_grads)
    noise_t = jnp.swapaxes(noise, 0, 1)
    buffers = (
        jnp.zeros((MAX_STEPS, n, STATE_DIM), start.dtype),
        jnp.zeros((MAX_STEPS, n, ACTION_DIM), start.dtype),
        jnp.zeros((MAX_STEPS, n), start.dtype),
        jnp.zeros((MAX_STEPS, n), bool),
    )

    def cond(carry):
        t, _, done, _ = carry
        return (t < MAX_STEPS) & ~jnp.all(done)

    def body(carry):
        t, state, done, bufs = carry
        for _ in range(unroll):
            eps = lax.dynamic_index_in_dim(noise_t, t, keepdims=False)
            state, done, out = _agents_step(layers, state, eps, done, t)
            bufs = tuple(lax.dynamic_update_index_in_dim(b, o, t, 0) for b, o in zip(bufs, out, strict=True))
            t = t + 1
        return t, state, done, bufs

    carry = (jnp.zeros((), jnp.int32), start, jnp.zeros((n,), bool), buffers)
    _, _, _, bufs = lax.while_loop(cond, body, carry)
    return tuple(jnp.swapaxes(a, 0, 1) for a in bufs)


ROLLOUTS = {"while": rollout_while, "scan": rollout_scan}


# ----------------------------------------------------------------------------- training


def agent_keys(seeds) -> tuple[jax.Array, jax.Array]:
    """Per-agent ``(init_keys, train_keys)`` from integer seeds."""
    pairs = jax.vmap(lambda s: jax.random.split(jax.random.key(s)))(jnp.asarray(seeds, jnp.uint32))
    return pairs[:, 0], pairs[:, 1]


def draws(train_key: jax.Array, update: jax.Array, mode: str = "floor") -> tuple[jax.Array, jax.Array]:
    """One agent's start state ``[6]`` and action noise ``[300, 2]`` for update number ``update``:
    one draw of uniforms in (-1, 1), the noise by ``jax.random.normal``'s own map ``sqrt(2) erfinv(u)``."""
    low = np.nextafter(np.float32(-1.0), np.float32(0.0))
    u = jax.random.uniform(
        jax.random.fold_in(train_key, update), (STATE_DIM + MAX_STEPS * ACTION_DIM,), jnp.float32, low, 1.0
    )
    start = start_states(0.5 * (u[:STATE_DIM] + 1.0), mode)
    return start, (math.sqrt(2.0) * lax.erf_inv(u[STATE_DIM:])).reshape(MAX_STEPS, ACTION_DIM)


def update(
    carry, update_index, *, train_keys, lrs, tables, rollout="while", unroll=1, chunk=MAX_STEPS, mode="floor"
):
    """One REINFORCE update of every agent: fly one episode each, then one Adam step each.

    ``carry = (params [N, N_PARAMS], opt)``; returns it and each agent's episode ``(return, length)``.
    """
    params, opt = carry
    start, noise = jax.vmap(partial(draws, update=update_index, mode=mode))(train_keys)
    obs, action, r, valid = ROLLOUTS[rollout](params, start, noise, unroll)
    grads = loss_grads(params, obs, action, r, valid, tables, chunk)
    params, opt = jax.vmap(adam_update)(params, grads, opt, lrs)
    return (params, opt), (r.sum(-1), valid.sum(-1))


def make_train_chunk(length: int, **kwargs):
    """``(carry, first_update, train_keys, lrs, gammas) -> (carry, (returns [length, N], lengths
    [length, N]))``: ``length`` updates in one ``lax.scan`` (to be jitted)."""

    def chunk(carry, first, train_keys, lrs, gammas):
        tables = jax.vmap(discount_tables)(gammas)
        fn = partial(update, train_keys=train_keys, lrs=lrs, tables=tables, **kwargs)
        return lax.scan(fn, carry, first + jnp.arange(length))

    return chunk


@jax.jit
def init_agents(seeds) -> tuple[jax.Array, dict, jax.Array]:
    """Stacked ``(params, opt, train_keys)`` of agents with these seeds."""
    init_keys, train_keys = agent_keys(seeds)
    params = jax.vmap(init_params)(init_keys)
    return params, jax.vmap(adam_init)(params), train_keys


def train(
    lrs,
    gammas,
    seeds,
    episodes: int,
    scan: int = 100,
    rollout: str = "while",
    unroll: int = 1,
    chunk: int = MAX_STEPS,
    mode: str = "floor",
) -> dict:
    """Train ``len(seeds)`` agents for ``episodes`` updates; returns their per-episode returns and
    lengths (``[episodes, N]`` numpy arrays), final weights and the wall-clock split."""
    if MAX_STEPS % unroll or MAX_STEPS % chunk:
        raise ValueError(f"unroll={unroll} and chunk={chunk} must divide {MAX_STEPS}")
    t_setup = time.perf_counter()
    params, opt, train_keys = init_agents(jnp.asarray(seeds, jnp.uint32))
    lrs = jnp.asarray(lrs, jnp.float32)
    gammas = jnp.asarray(gammas, jnp.float32)
    carry = jax.block_until_ready((params, opt))
    t_compile = time.perf_counter()
    lengths = [scan] * (episodes // scan) + ([episodes % scan] if episodes % scan else [])
    compiled = {}
    for length in sorted(set(lengths)):
        fn = make_train_chunk(length, rollout=rollout, unroll=unroll, chunk=chunk, mode=mode)
        compiled[length] = jax.jit(fn).lower(carry, jnp.int32(0), train_keys, lrs, gammas).compile()
    t_train = time.perf_counter()
    returns, steps, done = [], [], 0
    for length in lengths:
        carry, (ret, n) = compiled[length](carry, jnp.int32(done), train_keys, lrs, gammas)
        returns.append(ret)
        steps.append(n)
        done += length
    returns = np.concatenate([np.asarray(r) for r in returns])
    steps = np.concatenate([np.asarray(n) for n in steps])
    t_end = time.perf_counter()
    return {
        "returns": returns,
        "lengths": steps,
        "params": np.asarray(carry[0]),
        "setup_s": t_compile - t_setup,
        "compile_s": t_train - t_compile,
        "train_s": t_end - t_train,
    }


def final_metric(returns: np.ndarray, window: int = WINDOW) -> np.ndarray:
    """Each agent's mean return over its last ``window`` episodes (``returns [episodes, N]``)."""
    return returns[-window:].mean(0)


# ----------------------------------------------------------------------------- command line


def run_grid(args: argparse.Namespace) -> None:
    grid = GRIDS[args.grid]
    lrs, gammas, seeds = zip(*grid, strict=True)
    seeds = [s + args.seed_offset for s in seeds]
    print(
        f"grid {args.grid}: {len(grid)} agents x {args.episodes} episodes, rollout={args.rollout}, "
        f"unroll={args.unroll}, chunk={args.chunk}, scan={args.scan}, jax {jax.__version__} on {jax.devices()[0].platform}",
        flush=True,
    )
    result = train(lrs, gammas, seeds, args.episodes, args.scan, args.rollout, args.unroll, args.chunk)
    finals = final_metric(result["returns"])
    for (lr, gamma, seed), final, length in zip(
        grid, finals, result["lengths"][-WINDOW:].mean(0), strict=True
    ):
        print(
            f"  lr={lr:g} gamma={gamma:g} seed={seed + args.seed_offset}: final return {final:8.1f}"
            f"  (mean length {length:5.1f})"
        )
    total = time.perf_counter() - _T0
    cpu = time.process_time() - _CPU0
    print(f"median final return over {len(grid)} agents: {statistics.median(finals.tolist()):.1f}")
    print(
        f"wall-clock: imports {_T_IMPORTED - _T0:.2f} s, setup {result['setup_s']:.2f} s, "
        f"compile {result['compile_s']:.2f} s, train {result['train_s']:.2f} s, total {total:.2f} s "
        f"(process CPU time {cpu:.2f} s; {int(result['lengths'].sum())} agent-steps flown)",
        flush=True,
    )
    if args.save:
        np.savez(
            args.save, returns=result["returns"], lengths=result["lengths"], lr=lrs, gamma=gammas, seed=seeds
        )


def run_study(args: argparse.Namespace) -> None:
    """Both grids as two processes side by side; prints each one's output and wall-clock."""
    base = [
        sys.executable,
        os.path.abspath(__file__),
        "--episodes",
        str(args.episodes),
        "--scan",
        str(args.scan),
        "--seed-offset",
        str(args.seed_offset),
        "--rollout",
        args.rollout,
        "--unroll",
        str(args.unroll),
        "--chunk",
        str(args.chunk),
    ]
    if args.cache_dir:
        base += ["--cache-dir", args.cache_dir]
    start = time.perf_counter()
    results: dict[str, tuple[int, str, float]] = {}

    def launch(grid: str) -> threading.Thread:
        cmd = [*base, "--grid", grid]
        print("$", " ".join(cmd[1:]), "&", flush=True)
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

        def wait() -> None:
            out, _ = proc.communicate()
            results[grid] = (proc.returncode, out, time.perf_counter() - start)

        thread = threading.Thread(target=wait)
        thread.start()
        return thread

    threads = [launch(grid) for grid in GRIDS]
    for thread in threads:
        thread.join()
    end = time.perf_counter()
    for grid in GRIDS:
        code, out, elapsed = results[grid]
        print(f"\n--- grid {grid}: exit {code}, {elapsed:.2f} s from the study's start\n{out.rstrip()}")
    print(f"\nstudy (both grids side by side): {end - start:.2f} s = {(end - start) / 60:.2f} min")
    if any(code for code, _, _ in results.values()):
        sys.exit("a grid failed")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--grid", choices=tuple(GRIDS), help="train one grid in this process")
    what.add_argument("--study", action="store_true", help="both grids as two processes side by side")
    parser.add_argument("--episodes", type=int, default=6000, help="episodes (= updates) per agent")
    parser.add_argument("--scan", type=int, default=100, help="updates per compiled lax.scan call")
    parser.add_argument("--seed-offset", type=int, default=0, help="added to every agent's seed")
    parser.add_argument("--rollout", choices=tuple(ROLLOUTS), default="while", help="see the docstring")
    parser.add_argument("--unroll", type=int, default=1, help="env steps per loop iteration (divides 300)")
    parser.add_argument(
        "--chunk", type=int, default=MAX_STEPS, help="loss steps per gradient chunk (divides 300)"
    )
    parser.add_argument("--cache-dir", help="turn JAX's persistent compilation cache on, in this folder")
    parser.add_argument("--save", help="grid only: write every episode's return and length to this .npz")
    args = parser.parse_args()
    if args.episodes < WINDOW or args.scan < 1:
        parser.error(f"--episodes must be >= {WINDOW} and --scan >= 1")
    if args.cache_dir:
        jax.config.update("jax_compilation_cache_dir", args.cache_dir)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    else:
        jax.config.update("jax_enable_compilation_cache", False)
    if args.study:
        run_study(args)
    else:
        run_grid(args)


if __name__ == "__main__":
    main()
