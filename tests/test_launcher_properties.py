"""Property-based checks of the search and population launchers' settings (``hydra.launcher.*``), with
Hypothesis (``derandomize=True``: the same examples on every run), as tests/test_config_properties.py
checks the config schema.

- Any value of any kind (None, booleans, huge and tiny numbers, NaN, infinities, strings short and
  too long for a file name, lists, mappings) in any of ``hydra/launcher=pbt``'s, ``halving``'s and
  ``pbt_replay``'s keys (:meth:`.pbt.PBTSettings.of`, :meth:`.pbt.HalvingSettings.of`,
  :meth:`.pbt.ReplaySettings.of`): accepted, or the one-line :class:`ConfigError` naming
  ``hydra.launcher.<the key>``; never another exception.
- Accepted settings are usable: PBT's explore step keeps every value on the searched list, or inside
  the searched range and finite; a halving search either fits its budget and population or is
  refused naming the key; its first rung is the first step due.
- Any ``hydra.launcher.<name>`` on drone-train's command line (the population launcher takes
  ``search``, ``fused`` ``folders``, the search launchers ``search`` and theirs): accepted exactly when the launcher has the key, else one line naming
  the override and the launcher (:func:`drone_torchrl.command_line.check_launcher_keys`).

No training: each example checks settings and one explore step (a few ms).
"""

from __future__ import annotations

import functools
import math
from dataclasses import fields, replace

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from drone_torchrl.checks import ConfigError
from drone_torchrl.training.pbt import STATE_KEYS, HalvingSettings, PBTSettings, Range, ReplaySettings

# Hypothesis' examples per property: about 5 ms each for the settings, 0.3 s per new launcher key
# set for the command line (each composes the launcher's config once).
EXAMPLES = 300
COMMAND_LINE_EXAMPLES = 60
SETTINGS = settings(
    max_examples=EXAMPLES, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)

# Any value a YAML override can give, and then some: what a key must refuse in one line if it is not its kind.
SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.just("x" * 300),  # a name no file system takes
)
ANY = st.one_of(
    SCALARS, st.lists(SCALARS, max_size=4), st.dictionaries(st.text(max_size=4), SCALARS, max_size=2)
)
SEARCHABLE = sorted(STATE_KEYS)
KEYS = st.one_of(
    st.lists(st.sampled_from(SEARCHABLE), max_size=3),  # repeats and [] among them
    st.lists(st.sampled_from([*SEARCHABLE, "seed", "model.hidden_sizes", "algo.lr "]), max_size=4),
)


def _mostly(own: st.SearchStrategy) -> st.SearchStrategy:
    """A key's own kind of value (near and past its bounds) three times in four, else any value: a
    fair share of examples set every key to something allowed, and are accepted."""
    return st.integers(min_value=0, max_value=3).flatmap(lambda pick: ANY if pick == 3 else own)


PBT_VALUES = {
    "every_updates": _mostly(st.integers(min_value=-2, max_value=10_000)),
    "quantile": _mostly(st.floats(min_value=-0.1, max_value=0.7)),
    "perturb": _mostly(st.lists(st.floats(min_value=0.005, max_value=150), max_size=3)),
    "resample_probability": _mostly(st.floats(min_value=-0.5, max_value=1.5)),
    "keys": _mostly(KEYS),
}
HALVING_VALUES = {
    "rungs": _mostly(
        st.one_of(
            st.lists(st.integers(min_value=-1, max_value=3000), max_size=4, unique=True).map(sorted),
            st.lists(st.integers(min_value=-1, max_value=3000), max_size=4),
        )
    ),
    "fraction": _mostly(st.floats(min_value=-0.1, max_value=1.1)),
    "keys": _mostly(KEYS),
}
# Four agents' values inside every searched key's bounds (algo=reinforce's rules).
AGENT_VALUES = {
    "seed": [0, 1, 2, 3],
    "algo.lr": [1e-4, 3e-4, 1e-3, 3e-3],
    "algo.gamma": [0.9, 0.95, 0.99, 0.999],
    "algo.weight_decay": [0.0, 1e-5, 1e-4, 1e-3],
}


def _params(values: dict) -> st.SearchStrategy[dict]:
    """Some of a launcher's keys, each with any value."""
    return st.fixed_dictionaries({}, optional=values)


def _refused_naming_a_given_key(err: ConfigError, params: dict) -> None:
    """One line that names ``hydra.launcher.<key>`` for a key the example set (the defaults are allowed)."""
    message = str(err)
    assert "\n" not in message, message
    assert any(message.startswith(f"hydra.launcher.{key}=") for key in params), message
    event(f"refused: {message.split('=')[0]}")


@functools.cache
def _config():
    from hydra import compose, initialize_config_dir

    from drone_torchrl.config import config_dir

    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=["backend=fast"])


def _with_budget(episodes: int):
    cfg = OmegaConf.create(OmegaConf.to_container(_config()))
    cfg.algo.episodes = episodes
    return cfg


@SETTINGS
@given(params=_params(PBT_VALUES), episodes=st.integers(min_value=1, max_value=20_000), log=st.booleans())
def test_pbt_settings_are_accepted_and_usable_or_refused_in_one_line(params, episodes, log):
    try:
        search = PBTSettings.of(params)
    except ConfigError as err:
        _refused_naming_a_given_key(err, params)
        return
    event("accepted")
    assert [f.name for f in fields(search) if f.name != "ranges"] == list(PBT_VALUES)
    assert search.every_updates >= 1 and 0 < search.quantile <= 0.5 and 0 <= search.resample_probability <= 1
    assert all(0.01 <= f <= 100 for f in search.perturb)
    assert len(set(search.keys)) == len(search.keys) and set(search.keys) <= set(STATE_KEYS)
    cfg = _with_budget(episodes)
    agents = len(AGENT_VALUES["seed"])
    try:
        search.check(cfg, agents)
    except ConfigError as err:  # a step past the budget, or a quantile of no agent: named, in one line
        message = str(err)
        assert "\n" not in message, message
        if message.startswith("hydra.launcher.every_updates="):
            assert search.every_updates >= episodes // cfg.algo.episodes_per_update
        else:
            assert message.startswith("hydra.launcher.quantile=") and int(agents * search.quantile) < 1
    rng = np.random.default_rng(0)
    pbt = search.make(cfg, AGENT_VALUES, None)
    for key in search.keys:  # a list key moves among its list's values
        explored = pbt.explore(key, np.array(AGENT_VALUES[key]), rng)
        assert set(explored.tolist()) <= set(AGENT_VALUES[key]), (key, explored)
    bounds = search.bounds(cfg)
    for key in search.keys:  # a range key stays inside its range and its rule's bounds
        low, high = sorted(AGENT_VALUES[key])[1:3]
        ranged = replace(search, ranges=(Range(key, low, high, log and low > 0),)).make(
            cfg, AGENT_VALUES, None
        )
        explored = ranged.explore(key, np.array(AGENT_VALUES[key]), rng)
        assert all(math.isfinite(v) and low <= v <= high for v in explored), (key, explored)
        assert all(bounds[key][0] <= v <= bounds[key][1] for v in explored)


@SETTINGS
@given(
    params=_params(HALVING_VALUES),
    episodes=st.integers(min_value=1, max_value=20_000),
    agents=st.integers(min_value=1, max_value=64),
)
def test_halving_settings_are_accepted_and_usable_or_refused_in_one_line(params, episodes, agents):
    try:
        search = HalvingSettings.of(params)
    except ConfigError as err:
        _refused_naming_a_given_key(err, params)
        return
    event("accepted")
    assert list(search.rungs) == sorted(set(search.rungs)) and search.rungs[0] >= 1
    assert 0 < search.fraction < 1
    try:
        search.check(_with_budget(episodes), agents)
    except ConfigError as err:  # a rung past the budget, or too few agents to stop one: named, in one line
        message = str(err)
        assert "\n" not in message, message
        if message.startswith("hydra.launcher.rungs="):
            assert search.rungs[-1] >= episodes // _config().algo.episodes_per_update
        else:
            assert message.startswith("hydra.launcher.fraction=") and int(agents * search.fraction) < 1
        event(f"refused by the run: {message.split('=')[0]}")
        return
    event("usable")
    assert search.rungs[-1] < episodes // _config().algo.episodes_per_update
    assert int(agents * search.fraction) >= 1
    values = {key: np.resize(AGENT_VALUES[key], agents).tolist() for key in SEARCHABLE}
    values["seed"] = list(range(agents))
    halving = search.make(_with_budget(episodes), values, None)
    assert halving.updates_until_due(0) == search.rungs[0]


@SETTINGS
@given(
    run=st.one_of(ANY, st.sampled_from(["", ".", "/", "/nowhere", "a/" + "x" * 300, "/" + "y/" * 3000])),
    agent=ANY,
)
def test_a_replay_of_anything_but_a_finished_search_is_refused_in_one_line(run, agent):
    """No such run exists here: whatever ``run`` and ``agent`` are, one line naming hydra.launcher.run."""
    with pytest.raises(ConfigError) as info:
        ReplaySettings.of({"run": run, "agent": agent})
    assert "\n" not in str(info.value)
    assert str(info.value).startswith("hydra.launcher.run="), str(info.value)


# One launcher, preset: its search (the fused option: its folders) and the search's keys.
LAUNCHER_KEYS = {
    "population": ["search"],
    "fused": ["folders"],
    "pbt": ["search", *PBT_VALUES],
    "halving": ["search", *HALVING_VALUES],
    "pbt_replay": ["search", "run", "agent"],
}


@settings(max_examples=COMMAND_LINE_EXAMPLES, derandomize=True, deadline=None)
@given(
    launcher=st.sampled_from(sorted(LAUNCHER_KEYS)),
    name=st.one_of(
        st.sampled_from(sorted({k for keys in LAUNCHER_KEYS.values() for k in keys} | {"bogus", "n_jobs"})),
        st.from_regex(r"[a-z_]{1,12}", fullmatch=True),
    ),
    plus=st.booleans(),
    value=st.sampled_from(["1", "0", "-1", "[1]", "[inf]", "null", "abc", "1e300"]),
)
def test_a_launcher_key_on_the_command_line_is_the_launcher_s_or_one_line(launcher, name, plus, value):
    from drone_torchrl.apps.train import register_plugins
    from drone_torchrl.command_line import check_launcher_keys

    pytest.importorskip("pyarrow")  # the population launchers' extra (the command checks it first)
    register_plugins()
    override = f"{'+' if plus else ''}hydra.launcher.{name}={value}"
    try:
        check_launcher_keys([f"hydra/launcher={launcher}", override])
    except ConfigError as err:
        message = str(err)
        assert "\n" not in message and message.startswith(f"{override} is not allowed"), message
        assert f"hydra/launcher={launcher}" in message
        assert name not in LAUNCHER_KEYS[launcher]
        return
    assert name in LAUNCHER_KEYS[launcher]
