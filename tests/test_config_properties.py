"""Property-based checks of config validation over the whole schema (drone_torchrl/schema.py, every
plug-in's keys: ``config._every_key``), with Hypothesis (``derandomize=True``: the same examples on
every run).

- Any value of any kind (the key's own type, and None, huge and tiny numbers, NaN, infinities,
  strings short and very long, interpolations, lists, mappings) in any key: validation accepts it
  or raises the one-line :class:`ConfigError`, never another exception, never several lines.
- A value inside the key's documented range (its rule's bounds and choices; for the env's own
  arguments the bounds ``drone_env``/``disturbances`` document) is accepted, with memory to spare
  (the memory check is the one bound that depends on the machine: tests/test_memory_estimate.py).
"""

from __future__ import annotations

import copy
import functools
import math
import re

import pytest
from hypothesis import HealthCheck, given, reject, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf
from omegaconf.errors import GrammarParseError

from drone_torchrl import loggers, memory_estimate
from drone_torchrl.checks import FLOAT32_MAX, INT64_MAX, ConfigError
from drone_torchrl.config import _every_key, _option_plugins, config_dir, group_options, schema_keys, validate
from drone_torchrl.envs import disturbances, dynamics, params
from drone_torchrl.kernels import ops
from drone_torchrl.schema import Rule

KEYS = _every_key("config")
# Hypothesis' examples per property (the test's runtime: about 4 ms an example).
EXAMPLES = 1500


def _base(key: str):
    """The default config with the plug-in options that have ``key`` (algo=ppo for algo.num_envs)."""
    group = key.split(".")[0]
    if key in KEY_NEEDS:
        return _composed(KEY_NEEDS[key])
    if group not in ("algo", "logger") or key in schema_keys("config"):
        return _composed(())
    for option in group_options(group):
        if key in schema_keys("config", **_option_plugins("config", ((group, option),))):
            return _composed((*OPTION_NEEDS.get(f"{group}={option}", ()), f"{group}={option}"))
    raise AssertionError(f"no {group} option has {key}")


# What an option needs besides the default config, as its refusal says (SAC's TanhNormal actor:
# bounded thrust).
OPTION_NEEDS = {"algo=sac": ("experiment=bounded",)}
# What a key of the default config needs to take a value other than null, as its refusal says
# (going back to the best evaluation is an on-policy learner's: algo=ppo or a2c; the agent to continue
# is a population run's, named by resume=).
KEY_NEEDS = {"eval.rollback_drop": ("algo=ppo",), "agent": ("resume=population_0",)}


@functools.cache
def _composed(overrides: tuple[str, ...]):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=["eval.video=false", *overrides])


def _with(key: str, value, **related):
    cfg = copy.deepcopy(_base(key))
    for k, v in {key: value, **related}.items():
        try:
            OmegaConf.update(cfg, k, v, merge=False)
        except GrammarParseError:  # "${": no config holds it (Hydra's parser refuses it: test_bad_inputs)
            reject()
    return cfg


def _validates_or_refuses_in_one_line(cfg) -> None:
    try:
        validate(cfg)
    except ConfigError as err:
        message = str(err)
        assert message.strip() and "\n" not in message.strip(), message
        assert len(message) < 1000, message  # a value shown in full would make a line of any length


HUGE_INTS = [10**30, -(10**30), 2**63, -(2**63) - 1, 10**400, -(10**400), 2**64]
ODD_FLOATS = [math.nan, math.inf, -math.inf, 1e300, -1e300, 5e-324, -0.0, FLOAT32_MAX * 1.0001]
ODD_TEXT = [
    "${oops}",
    "${oops",
    "???",
    "null",
    "",
    " ",
    "abc",
    "1e300",
    "../..",
    "a/b",
    "x" * 100_000,
    "é\n\t",
]
ANY_VALUE = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.sampled_from(HUGE_INTS),
    st.floats(),
    st.sampled_from(ODD_FLOATS),
    st.text(max_size=30),
    st.sampled_from(ODD_TEXT),
    st.lists(st.one_of(st.integers(), st.floats(), st.text(max_size=5), st.none()), max_size=4),
    st.dictionaries(st.text(max_size=6), st.one_of(st.integers(), st.text(max_size=4)), max_size=3),
)


def _own_type(rule: Rule) -> st.SearchStrategy:
    """Values of the key's own type, in range or not."""
    if rule.kind == "number":
        return st.floats(allow_nan=False, allow_infinity=False)
    if rule.kind == "integer":
        return st.integers(min_value=-(2**70), max_value=2**70)
    if rule.kind == "flag":
        return st.booleans()
    if rule.kind == "choice":
        return st.sampled_from(rule.choices)
    if rule.kind == "sizes":
        return st.lists(st.integers(min_value=-(2**70), max_value=2**70), max_size=4)
    return st.text(max_size=40)


@settings(max_examples=EXAMPLES, derandomize=True, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_any_value_in_any_key_is_accepted_or_refused_in_one_line(data):
    key = data.draw(st.sampled_from(sorted(KEYS)), label="key")
    value = data.draw(st.one_of(_own_type(KEYS[key]), ANY_VALUE), label="value")
    _validates_or_refuses_in_one_line(_with(key, value))


# ----------------------------------------------------------------------------- documented ranges
def _between(
    low: float, high: float, *, low_open: bool = False, high_open: bool = False
) -> st.SearchStrategy:
    return st.floats(min_value=low, max_value=high, exclude_min=low_open, exclude_max=high_open)


# The env's own arguments (free in the schema: the env checks them), with the bounds it documents;
# the arena's relative to the defaults of the others (x_limit 2, zone_x_limit 0.8, z 0..4, zone
# 2.2..3.2).
_PAPER = params.DroneParams()  # the arena's defaults
ENV_RANGES = {
    "env.mass": _between(params.MIN_MASS, params.MAX_MASS),
    "env.motor_distance": _between(params.MIN_MOTOR_DISTANCE, params.MAX_MOTOR_DISTANCE),
    "env.gravity": _between(0.0, params.MAX_GRAVITY, low_open=True),
    "env.dt": _between(0.0, params.MAX_DT, low_open=True),
    "env.max_thrust": st.one_of(st.none(), _between(0.0, params.MAX_THRUST, low_open=True)),
    "env.floor_tolerance": _between(0.0, params.MAX_FLOOR_TOLERANCE),
    "env.max_steps": st.integers(min_value=1, max_value=INT64_MAX),
    "env.reset_mode": st.sampled_from(dynamics.RESET_MODES),
    "env.x_limit": _between(_PAPER.zone_x_limit, params.MAX_ARENA),
    "env.z_min": _between(-params.MAX_ARENA, _PAPER.zone_z_min),
    "env.z_max": _between(_PAPER.zone_z_max, params.MAX_ARENA),
    "env.alpha_limit": _between(0.0, math.pi, low_open=True),
    "env.zone_x_limit": _between(0.0, _PAPER.x_limit, low_open=True),
    "env.zone_z_min": _between(_PAPER.z_min, _PAPER.zone_z_max, high_open=True),
    "env.zone_z_max": _between(_PAPER.zone_z_min, _PAPER.z_max, low_open=True),
    **{f"env.disturbance.{name}": _between(0.0, high) for name, high in disturbances.MAX_MAGNITUDES.items()},
    "env.disturbance.gust_time": _between(0.0, disturbances.MAX_TIME, low_open=True),
}
# Keys whose documented range is a relation to other keys, drawn with the related keys set as their
# messages say: (strategy, the related keys for a value).
RELATED = {
    # a divisor of algo.num_envs x algo.steps_per_batch (64 x 64 in algo=ppo and 32 x 100 in algo=a2c)
    "algo.minibatch_size": lambda cfg: (
        st.sampled_from(_divisors(cfg.algo.num_envs * cfg.algo.steps_per_batch)),
        {},
    ),
    # (the frames of a batch, an int64 count like every other)
    "algo.num_envs": lambda cfg: (None, lambda v: {"algo.minibatch_size": v * cfg.algo.steps_per_batch}),
    "algo.steps_per_batch": lambda cfg: (
        st.integers(min_value=1, max_value=INT64_MAX // cfg.algo.num_envs),
        lambda v: {"algo.minibatch_size": v * cfg.algo.num_envs},
    ),
    # SAC's minibatch is drawn from its buffer: at most algo.buffer_size frames
    "algo.batch_size": lambda cfg: (st.integers(min_value=1, max_value=cfg.algo.buffer_size), {}),
    "algo.buffer_size": lambda cfg: (None, lambda v: {"algo.batch_size": min(v, cfg.algo.batch_size)}),
    # REINFORCE's budget is a multiple of the episodes of an update
    "algo.episodes_per_update": lambda cfg: (None, lambda v: {"algo.episodes": v}),
    # backend=fast's kernels take layers up to ops.MAX_WIDTH wide (its refusal names backend=reference)
    "model.hidden_sizes": lambda cfg: (
        None,
        lambda v: {} if all(h <= ops.MAX_WIDTH for h in v) else {"backend": "reference"},
    ),
}
# Keys left out of the range property, and why.
LEFT_OUT = {
    "env.num_workers": "0 except with backend=reference and REINFORCE, where it divides algo.episodes_per_update",
    "algo.name": "a plug-in's name, not a value (test_bad_inputs: algo.name=dqn)",
    "logger.backend": "a plug-in's name, not a value",
    "resume": "a checkpoint to read (test_bad_inputs' resume rows)",
    "device": "this machine's devices (cpu here; test_bad_inputs' device rows)",
    "logger.mode": "online needs this machine's W&B credentials (test_wandb: each mode)",
}
# Text keys with a documented form (free or text rules that other checks narrow).
W_AND_B_NAME = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9 _.-]{0,40}", fullmatch=True)  # none of / \ # ? % :
TEXT_RANGES = {
    "logger.project": W_AND_B_NAME,
    "logger.entity": st.one_of(st.none(), W_AND_B_NAME),
    "logger.group": st.one_of(st.none(), W_AND_B_NAME),
    "logger.exp_name": st.from_regex(r"[a-z][a-z0-9_]{0,20}", fullmatch=True),
    "sweep_name": st.from_regex(r"[a-z][a-z0-9_]{0,20}", fullmatch=True),
    "logger.float_format": st.one_of(st.none(), st.sampled_from(["%.6g", "%.3f", "%g", "%e"])),
    "logger.tracking_uri": st.one_of(st.none(), st.just("sqlite:///mlflow.db")),
}


def _divisors(n: int) -> list[int]:
    return [d for d in range(1, n + 1) if n % d == 0]


@functools.cache
def _in_range(key: str) -> st.SearchStrategy:
    rule, cfg = KEYS[key], _base(key)
    if key in ENV_RANGES:
        return ENV_RANGES[key]
    if key in TEXT_RANGES:
        return TEXT_RANGES[key]
    resolved = OmegaConf.to_container(cfg, resolve=True)
    bound = lambda b: OmegaConf.select(OmegaConf.create(resolved), b) if isinstance(b, str) else b  # noqa: E731
    low, high = bound(rule.low), bound(rule.high)
    if rule.kind == "number":
        values = _between(
            -FLOAT32_MAX if low is None else low,
            FLOAT32_MAX if high is None else high,
            low_open=rule.low_open,
        )
    elif rule.kind == "integer":
        values = st.integers(
            min_value=-INT64_MAX if low is None else low + rule.low_open,
            max_value=INT64_MAX if high is None else high,
        )
    elif rule.kind == "flag":
        values = st.booleans()
    elif rule.kind == "choice":
        values = st.sampled_from(rule.choices)
    elif rule.kind == "sizes":
        values = st.lists(st.integers(min_value=1, max_value=INT64_MAX), min_size=1, max_size=4)
    else:
        values = st.text(min_size=1, max_size=40).filter(str.strip)
    return st.one_of(st.none(), values) if rule.optional else values


RANGED = sorted(k for k in KEYS if k not in LEFT_OUT)


@settings(max_examples=EXAMPLES, derandomize=True, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_every_value_inside_its_documented_range_is_accepted(data, monkeypatch_module):
    key = data.draw(st.sampled_from(RANGED), label="key")
    cfg = _base(key)
    strategy, related = RELATED[key](cfg) if key in RELATED else (None, None)
    value = data.draw(_in_range(key) if strategy is None else strategy, label="value")
    extra = {} if related is None else related(value) if callable(related) else related
    if key == "model.distribution" and value == "tanh_normal":
        extra["env.max_thrust"] = 1.0  # as its message says: tanh_normal needs a thrust bound
    cfg = _with(key, value, **extra)
    backend = loggers.get(cfg.logger.backend)
    if backend.installed:
        validate(cfg)
    else:  # the plain ".[test]" install: the value passes its checks, then the missing extra is named
        with pytest.raises(ConfigError, match=re.escape(f"drone_torchrl[{backend.extra}]")):
            validate(cfg)


@pytest.fixture(scope="module")
def monkeypatch_module():
    """Memory to spare: the estimate is checked against an unbounded machine."""
    mp = pytest.MonkeyPatch()
    mp.setattr(memory_estimate, "available_ram", lambda: (math.inf, "MemAvailable"))
    yield mp
    mp.undo()


def test_every_key_has_a_range_or_a_reason():
    """A new key gets a documented range here (its rule's, or ENV_RANGES/TEXT_RANGES) or a reason in
    LEFT_OUT; the keys are every plug-in's."""
    assert {"algo.num_envs", "algo.baseline", "logger.float_format", "logger.tracking_uri"} <= set(KEYS)
    free = [
        k for k, r in KEYS.items() if r.kind == "free" and k not in {**ENV_RANGES, **TEXT_RANGES, **LEFT_OUT}
    ]
    assert free == []
