"""The config schema: every key of ``conf/``'s configs as Hydra structured configs.

With each key go what it allows and what the code needs to know of it, declared once, beside the
key.

Each ``conf/`` file lists its schema first in its defaults list (``/schema_config@_here_``,
``/schema_algo_ppo@algo``...), so Hydra composes every config onto its dataclass: a YAML key the
schema lacks fails the composition, and a schema key a YAML leaves unset stays ``???`` (refused in
one line by :func:`drone_torchrl.config.check_keys`). The values themselves stay in the YAML files
with their comments; the dataclasses hold no defaults, but the env's physics and arena, whose
defaults are :class:`~drone_torchrl.envs.params.DroneParams`' (:class:`EnvConf`).

Every field is typed ``Any`` on purpose: OmegaConf's typed nodes convert what they can (``off`` to
``False``, ``1`` to ``1.0``, ``123`` to ``"123"``) and refuse the rest with a multi-line error during
composition. ``Any`` keeps each value as the user typed it, and the field's :class:`Rule` (its kind
and bounds, in the field's metadata) refuses it in one line that names the key. Struct mode still
holds: a key the schema lacks cannot be set without ``+`` (which
:func:`~drone_torchrl.config.check_overrides` refuses first), and a key of a nested schema cannot be
deleted (OmegaConf refuses deleting fields of a dataclass; ``check_overrides`` says so first).

Plug-in groups (``algo``, ``logger``): the top-level field is a :class:`Rule` whose ``plugin_key``
is the key that names the plug-in (``algo.name``); each plug-in's own schema is stored as
``schema_<group>_<plug-in>`` (:func:`store_plugin`), and the options of the group (any number per
plug-in: ``algo=reinforce_plus`` is REINFORCE's schema with other values) list it in their defaults.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf

from drone_torchrl.checks import INT64_MAX, ConfigError, check_number, dotted
from drone_torchrl.envs.disturbances import MAX_GAIN_SPREAD, MAX_MASS_SPREAD, MAX_STEPS_BACK, Disturbance
from drone_torchrl.envs.dynamics import DTYPES
from drone_torchrl.envs.params import PARAM, DroneParams
from drone_torchrl.migrations import BACKENDS, REFERENCE
from drone_torchrl.modules.policy import ACTIVATIONS, DISTRIBUTIONS, MAX_DISTRIBUTION_EPS

# ------------------------------------------------------------------------------------ the bounds
# Bounds of values that have no natural limit. A learning rate above 1 only diverges with Adam's
# unit-scale steps; seeds are signed 64-bit integers in torch.
MAX_LR = 1.0
MAX_SEED = INT64_MAX
# Episodes flown side by side (an update's, an evaluation's, drone-eval's) live in memory together:
# about 25 kB each for 300 steps, so 10,000 take a quarter of a GB.
MAX_PARALLEL_EPISODES = 10_000
# torch's intra-op threads; far past the cores they only slow it down (and 10^5 crashes it).
MAX_THREADS = 256
# An initial exploration std (or a floor under the std) past this is no longer "near the mean":
# thrusts are fractions of the weight.
MAX_INIT_STD = 10.0
# REINFORCE's optimizers: adam (the paper's text), adamw (decoupled weight decay, the paper's code).
OPTIMIZERS = ("adam", "adamw")
# drone-export's file formats: a torch.export program (plain torch) or an ONNX model (onnxruntime and
# other ONNX runtimes; the onnx extra). Each is also the output's file suffix (drone_torchrl/export.py).
EXPORT_FORMATS = ("pt2", "onnx")

# ------------------------------------------------------------------ what a continued run does
# A run continued from a checkpoint keeps the checkpoint's value of a key, unless the key says:
KEPT = "kept"  #: the checkpoint's value; a command line that changes it is refused
IF_SET = "if set"  #: taken from the command line when it sets the key (logging, checkpointing...)
BUDGET = "budget"  #: also taken from the config without a command line (the episode budget)
PROCESS = "process"  #: always the current config's (where and how this process runs)

# The metadata key of a field's rule.
RULE = "drone_torchrl"
# "Not added in a later format": the key was in the first runs' configs.
_ORIGINAL = object()


@dataclass(frozen=True)
class Rule:
    """What one key allows and what the code needs to know of it.

    Attributes:
        kind: ``number``, ``integer``, ``flag`` (true or false), ``choice``, ``sizes`` (a non-empty
            list of layer sizes), ``text`` (a non-empty string) or ``free`` (checked by code: the
            env's arguments, paths, folder names, devices).
        low, high: bounds; a string is another key whose value is the bound (``env.max_steps``).
        low_open: ``low`` itself is not allowed.
        optional: null is allowed too.
        choices: the values a ``choice`` allows.
        expected: what the one-line error says is allowed, where the kind's own words do not fit.
        per_agent: may differ between the agents of one population (every other key must be equal).
        on_resume: :data:`KEPT`, :data:`IF_SET`, :data:`BUDGET` or :data:`PROCESS`.
        added: the value runs saved before the key existed behaved as (a checkpoint's config gets it
            filled in); absent for keys the first runs had.
        plugin_key: of a plug-in group's field: the key of the group that names the plug-in.
    """

    kind: str = "free"
    low: float | str | None = None
    high: float | str | None = None
    low_open: bool = False
    optional: bool = False
    choices: tuple = ()
    expected: str | None = None
    per_agent: bool = False
    on_resume: str = KEPT
    added: Any = _ORIGINAL
    plugin_key: str | None = None

    @property
    def is_added(self) -> bool:
        """Whether the key came after the first runs (a config without it gets ``added``)."""
        return self.added is not _ORIGINAL

    def check(self, key: str, value: Any, cfg: Mapping[str, Any]) -> None:
        """Raise :class:`~.checks.ConfigError` (one line) if ``value`` of ``key`` breaks the rule.

        ``cfg`` (the resolved config as nested dicts) gives the bounds that are other keys.
        """
        kind = self.kind
        if kind == "free" or (self.optional and value is None):
            return
        if kind == "number" or kind == "integer":
            low, high = (dotted(cfg, b) if isinstance(b, str) else b for b in (self.low, self.high))
            check_number(key, value, low=low, high=high, low_open=self.low_open, integer=kind == "integer")
            return
        if kind == "flag":
            ok, expected = isinstance(value, bool), "true or false"
        elif kind == "choice":
            ok, expected = value in self.choices, self.expected or f"one of {list(self.choices)}"
        elif kind == "sizes":
            ok = isinstance(value, list) and bool(value)
            ok = ok and all(
                isinstance(s, int) and not isinstance(s, bool) and 1 <= s <= INT64_MAX for s in value
            )
            expected = "a non-empty list of integers >= 1, e.g. [32,32]"
        elif kind == "text":
            ok = isinstance(value, str) and bool(value.strip())
            expected = "null or a non-empty string" if self.optional else "a non-empty string"
        else:
            raise AssertionError(f"unknown rule kind {kind!r} of {key}")
        if not ok:
            raise ConfigError.of(key, value, expected)

    def field(self) -> Any:
        """A dataclass field of this rule, its value to come from the YAML files."""
        return field(default=MISSING, metadata={RULE: self})


# Field makers: ``lr: Any = a_number(low=0, low_open=True, high=MAX_LR, per_agent=True)``, each a
# config field holding a value of its kind, checked by a :class:`Rule` of its arguments; ``free``: one
# the code checks itself (the env's arguments, paths, folder names, devices).
def _field_maker(name: str) -> Callable[..., Any]:
    kind = name.rpartition("_")[2]

    def maker(**rule: Any) -> Any:
        return Rule(kind, **rule).field()

    maker.__name__ = maker.__qualname__ = name  # the API docs list it under its own name
    maker.__doc__ = f"A config field holding a {kind} value, checked by a :class:`Rule` of these arguments."
    return maker


a_number, an_integer, a_flag, a_text, free = map(
    _field_maker, ("a_number", "an_integer", "a_flag", "a_text", "free")
)


def one_of(choices: tuple, **rule: Any) -> Any:
    """A config field holding one of ``choices``, checked by a :class:`Rule`."""
    return Rule("choice", choices=tuple(choices), **rule).field()


# The metadata key of an open section's schema (:func:`open_section`).
SECTION = "drone_torchrl_section"


def open_section(node: type) -> Any:
    """A config field holding a section whose keys (those of dataclass ``node``) may be left out.

    A key left out is its rule's ``added`` value. The section is an empty mapping by default, so a
    default run's config does not list values that only restate the nominal case, and open (not
    struct) in Hydra's ConfigStore (as ``_store`` keeps it), so ``env.disturbance.wind=0.3`` sets one of its
    keys without ``+``.
    """
    return field(default_factory=dict, metadata={SECTION: node})


# ------------------------------------------------------------------------- the shared groups
# env.* keys that are not DroneEnv arguments: the TorchRL collector's worker processes.
ENV_NON_ARGS = ("num_workers",)


_NOMINAL = Disturbance()


@dataclass
class DisturbanceConf:
    """``env.disturbance.*``: wind, gusts, mass and motor mismatch, lag, delay, observation noise.

    Each one's physics is in drone_torchrl/envs/disturbances.py; presets: ``disturbance=none|mild|strong``.
    They came after the first runs: a config without them flew the nominal drone. An
    :func:`open_section`: ``disturbance=none`` leaves it empty, and a key it lacks is its ``added`` value.
    """

    wind: Any = a_number(low=0, added=_NOMINAL.wind)
    gust: Any = a_number(low=0, added=_NOMINAL.gust)
    gust_time: Any = a_number(low=0, low_open=True, added=_NOMINAL.gust_time)
    mass: Any = a_number(low=0, high=MAX_MASS_SPREAD, added=_NOMINAL.mass)
    motor_gain: Any = a_number(low=0, high=MAX_GAIN_SPREAD, added=_NOMINAL.motor_gain)
    motor_lag: Any = a_number(low=0, added=_NOMINAL.motor_lag)
    noise_position: Any = a_number(low=0, added=_NOMINAL.noise_position)
    noise_angle: Any = a_number(low=0, added=_NOMINAL.noise_angle)
    action_delay: Any = an_integer(low=0, high=MAX_STEPS_BACK, added=_NOMINAL.action_delay)
    observed_actions: Any = an_integer(low=0, high=MAX_STEPS_BACK, added=_NOMINAL.observed_actions)


def _param_key(f: dataclasses.Field) -> tuple[str, Any, Any]:
    """The env node's key of :class:`~drone_torchrl.envs.params.DroneParams`' field ``f``, its default too.

    The env checks its value itself (``make_params``); a choice (``bounds``) is checked here as
    well. A field that came after the first runs (its ``Param.new``) is ``added`` as its default.
    """
    param = f.metadata[PARAM]
    added = {"added": f.default} if param.new else {}
    rule = Rule("choice", choices=param.choices, **added) if param.choices else Rule(**added)
    return f.name, Any, field(default=f.default, metadata={RULE: rule})


EnvConf = dataclasses.make_dataclass(
    "EnvConf",
    [
        *map(_param_key, dataclasses.fields(DroneParams)),
        ("max_steps", Any, free()),
        ("reset_mode", Any, free()),
        ("dtype", Any, one_of(tuple(DTYPES), added="float32")),
        ("disturbance", Any, open_section(DisturbanceConf)),
        ("num_workers", Any, an_integer(low=0)),
    ],
    namespace={
        "__module__": __name__,
        "__doc__": """``env.*``: the DroneEnv arguments (the env checks them itself).

    The drone's physics and arena are :class:`~drone_torchrl.envs.params.DroneParams`' fields, their
    defaults too (``conf/env/drone.yaml`` does not restate them). ``dtype`` came after the first
    runs: a checkpoint or run folder without it gets ``float32``.
    """,
    },
)


@dataclass
class ModelConf:
    """``model.*``: the three-net policy."""

    distribution: Any = one_of(DISTRIBUTIONS)
    hidden_sizes: Any = Rule("sizes").field()
    activation: Any = one_of(tuple(ACTIVATIONS))
    min_std: Any = a_number(low=0, high=MAX_INIT_STD)
    init_std: Any = a_number(low="model.min_std", low_open=True, high=MAX_INIT_STD, optional=True, added=None)
    distribution_eps: Any = a_number(low=0, high=MAX_DISTRIBUTION_EPS, added=0.0)


@dataclass
class CheckpointConf:
    """``checkpoint.*`` of a training run."""

    every_episodes: Any = an_integer(low=1, on_resume=IF_SET)
    keep_best: Any = a_flag(on_resume=IF_SET)


@dataclass
class PeriodicEvalConf:
    """``eval.*`` of a training run."""

    every_episodes: Any = an_integer(low=0, on_resume=IF_SET)
    episodes: Any = an_integer(low=1, high=MAX_PARALLEL_EPISODES)
    seed: Any = an_integer(low=0, high=MAX_SEED)
    video: Any = a_flag(on_resume=IF_SET)
    stop_return: Any = a_number(optional=True, on_resume=IF_SET, added=None)
    rollback_drop: Any = a_number(low=0, low_open=True, optional=True, on_resume=IF_SET, added=None)


# ---------------------------------------------------------------------- the primary configs
# Field order is the composed config's key order (what --cfg job prints and config.yaml saves):
# the order of conf/config.yaml's defaults list, then its own keys.
@dataclass
class TrainConfig:
    """``conf/config.yaml``: drone-train."""

    env: EnvConf = field(default_factory=EnvConf)
    model: ModelConf = field(default_factory=ModelConf)
    # The plug-in groups: their key that names the plug-in, whose schema is schema_<group>_<plug-in>;
    # a config without it is from before plug-ins, as added.
    algo: Any = Rule(plugin_key="name", added="reinforce").field()
    logger: Any = Rule(plugin_key="backend", added="tensorboard").field()
    seed: Any = an_integer(low=0, high=MAX_SEED, per_agent=True)
    # A run continues with the backend that wrote it (their random draws differ); configs saved
    # before the key existed name it through engine/algo.collector (drone_torchrl/migrations.py).
    backend: Any = one_of(BACKENDS, added=REFERENCE)
    device: Any = free(on_resume=PROCESS)
    threads: Any = an_integer(low=1, high=MAX_THREADS, on_resume=PROCESS)
    resume: Any = free(on_resume=PROCESS)
    # resume=<population run> agent=K: which agent of a population run's checkpoint to continue.
    agent: Any = an_integer(low=0, optional=True, on_resume=PROCESS, added=None)
    progress: Any = one_of((True, False, "auto"), expected="true, false or auto", on_resume=PROCESS)
    sweep_name: Any = free(on_resume=IF_SET)
    checkpoint: CheckpointConf = field(default_factory=CheckpointConf)
    eval: PeriodicEvalConf = field(default_factory=PeriodicEvalConf)


@dataclass
class EvalConfig:
    """``conf/eval.yaml``: drone-eval."""

    env: EnvConf = field(default_factory=EnvConf)
    checkpoint: Any = free()
    agent: Any = an_integer(low=0, optional=True)
    episodes: Any = an_integer(low=1, high=MAX_PARALLEL_EPISODES)
    seed: Any = an_integer(low=0, high=MAX_SEED)
    device: Any = free()
    video: Any = a_flag()
    plot: Any = a_flag()
    video_fps: Any = an_integer(low=1)


@dataclass
class ExportConfig:
    """``conf/export.yaml``: drone-export."""

    checkpoint: Any = free()
    agent: Any = an_integer(low=0, optional=True)
    format: Any = one_of(
        EXPORT_FORMATS,
        optional=True,
        expected=f"one of {list(EXPORT_FORMATS)}, or null (from the output's suffix)",
    )
    output: Any = free()


# --------------------------------------------------------------------------------- algorithms
# Keys several algorithms share: one rule each.
LR = Rule("number", low=0, low_open=True, high=MAX_LR, per_agent=True)
GAMMA = Rule("number", low=0, high=1, per_agent=True)
EPISODES = Rule("integer", low=1, on_resume=BUDGET)
ADAM_EPS = Rule("number", low=0, low_open=True, high=1)
MAX_GRAD_NORM = Rule("number", low=0, low_open=True, optional=True)
# The on-policy loop's (drone_torchrl/algorithms/ppo.py: OnPolicy), PPO's and A2C's.
ANNEAL_LR = Rule("flag")
GAE_LAMBDA = Rule("number", low=0, high=1)
NUM_ENVS = Rule("integer", low=1, high=MAX_PARALLEL_EPISODES)
STEPS_PER_BATCH = Rule("integer", low=1)
EPOCHS = Rule("integer", low=1)
MINIBATCH_SIZE = Rule("integer", low=1)
ENTROPY_COEFF = Rule("number", low=0)
CRITIC_COEFF = Rule("number", low=0, low_open=True)
REWARD_SCALE = Rule("number", low=0, low_open=True)
VALUE_HIDDEN_SIZES = Rule("sizes")


# ------------------------------------------------------------------------------------ loggers
# A continued run keeps its logs in one backend and folder; the other logger keys may change.
@dataclass
class TensorBoardConf:
    """``logger.*`` of ``logger.backend=tensorboard``; every backend has these keys."""

    backend: Any = free()
    exp_name: Any = free()
    video_stride: Any = an_integer(low=1, on_resume=IF_SET, added=1)
    every_updates: Any = an_integer(low=1, on_resume=IF_SET, added=1)
    flush_every_s: Any = a_number(low=0, on_resume=IF_SET, added=10)


# ------------------------------------------------------------------------ in Hydra's ConfigStore
# Stored at the root, not in a group: Hydra's --help lists every config group as options to choose,
# and a schema is not one. conf/ lists them as /schema_config@_here_, /schema_algo_ppo@algo...
PREFIX = "schema"
PRIMARY = {"config": TrainConfig, "eval": EvalConfig, "export": ExportConfig}


# Every schema stored, by its name: the checks read the dataclasses here, not back from the
# ConfigStore (which copies a node at every load, and a population validates every job).
_SCHEMAS: dict[str, type] = {}


def _store(name: str, node: type) -> None:
    stored = OmegaConf.structured(node)
    for key in open_sections(node):  # Hydra keeps a node's own struct flag through composition
        OmegaConf.set_struct(OmegaConf.select(stored, key), False)
    ConfigStore.instance().store(name=name, node=stored, provider="drone_torchrl")
    _SCHEMAS[name] = node


@functools.cache
def open_sections(node: type, prefix: str = "") -> dict[str, dict[str, Any]]:
    """Schema ``node``'s :func:`open_section` fields, nested ones too, with the ``added`` value of each key.

    ``{"env.disturbance": {"wind": 0.0, ...}}``: what a key the section leaves out is.
    """
    out = {}
    for f in dataclasses.fields(node):
        section = f.metadata.get(SECTION)
        if section is not None:
            out[f"{prefix}{f.name}"] = {g.name: g.metadata[RULE].added for g in dataclasses.fields(section)}
        elif dataclasses.is_dataclass(f.default_factory):
            out.update(open_sections(f.default_factory, f"{prefix}{f.name}."))
    return out


def store_plugin(group: str, plugin: str, node: type) -> None:
    """Store ``node`` as the schema of plug-in ``plugin`` of ``group`` (``schema_algo_ppo``).

    What ``conf/<group>/<option>.yaml`` lists first in its defaults, and where the checks find its keys.
    """
    _store(f"{PREFIX}_{group}_{plugin}", node)


for _name, _node in PRIMARY.items():
    _store(f"{PREFIX}_{_name}", _node)
# Each plug-in stores its own schema where it registers itself (drone_torchrl/algorithms/a2c.py:
# store_plugin("algo", "a2c", A2CConf)); drone_torchrl.config.config_dir() discovers every plug-in
# before Hydra composes.


# ------------------------------------------------------------------------------ reading it back
def plugin_schema(group: str, plugin: Any) -> type | None:
    """The schema of plug-in ``plugin`` of ``group``, or None if none is stored."""
    return _SCHEMAS.get(f"{PREFIX}_{group}_{plugin}") if isinstance(plugin, str) and plugin else None


@functools.cache
def plugin_groups(name: str = "config") -> dict[str, Rule]:
    """``{"algo": rule, "logger": rule}``: the plug-in groups of a primary config.

    ``rule.plugin_key`` names the plug-in.
    """
    return {
        f.name: rule
        for f in dataclasses.fields(PRIMARY[name])
        if (rule := f.metadata.get(RULE)) is not None and rule.plugin_key
    }


def fields(node: type, plugins: Mapping[str, type | None], prefix: str = "") -> Iterator[tuple[str, Rule]]:
    """``("algo.lr", rule)`` for every key of schema ``node``, in order.

    A plug-in group's keys are those of its schema in ``plugins`` (a group whose schema is None has
    no keys).
    """
    for f in dataclasses.fields(node):
        key = f"{prefix}{f.name}"
        section = f.metadata.get(SECTION, f.default_factory)
        if dataclasses.is_dataclass(section):  # a section (env, model...) or an open one (env.disturbance)
            yield from fields(section, plugins, f"{key}.")
            continue
        rule = f.metadata.get(RULE, Rule())
        if rule.plugin_key:
            plugin = plugins.get(f.name)
            if plugin is not None:
                yield from fields(plugin, plugins, f"{key}.")
            continue
        yield key, rule


def stored_plugins(group: str) -> list[str]:
    """The plug-ins of ``group`` whose schemas are in the ConfigStore, sorted."""
    prefix = f"{PREFIX}_{group}_"
    return sorted(n.removeprefix(prefix) for n in _SCHEMAS if n.startswith(prefix))
