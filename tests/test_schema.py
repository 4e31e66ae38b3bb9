"""The config schema (drone_torchrl/schema.py) and the YAML files agree, and the facts the code
reads from it are those it had as lists before."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from drone_torchrl import schema
from drone_torchrl.config import (
    ConfigError,
    check_overrides,
    complete,
    config_dir,
    leaves,
    per_agent_keys,
    resume_rule,
    run_config,
    schema_keys,
)


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (Path(config_dir()) / group).glob("*.yaml"))


@pytest.mark.parametrize(
    "overrides",
    [[f"{group}={option}"] for group in ("algo", "logger") for option in _options(group)]
    + [["experiment=bounded"], ["experiment=paper_code"], ["+sweep=landscape"], ["+sweep=gamma32"]],
    ids=str,
)
def test_every_option_sets_exactly_its_schemas_keys(overrides):
    """What Hydra composes has a value for every key of the schema and no other key (an open
    section's, env.disturbance.*, once its absent keys are filled in: drone_torchrl.config.complete)."""
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    complete(cfg)
    composed = leaves(cfg)
    assert not [key for key in composed if OmegaConf.is_missing(cfg, key)]
    keys = schema_keys("config", algo=cfg.algo.name, logger=cfg.logger.backend)
    assert list(composed) == list(keys)  # the same keys, in the schema's order


@pytest.mark.parametrize("name", ["eval", "export"])
def test_the_other_commands_configs_are_their_schemas(name):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose(name)
    complete(cfg, name)
    assert list(leaves(cfg)) == list(schema_keys(name))


def test_a_yaml_key_the_schema_lacks_fails_the_composition(tmp_path):
    (tmp_path / "algo").mkdir()
    (tmp_path / "algo" / "typo.yaml").write_text(
        "defaults:\n  - /schema_algo_reinforce@_here_\n  - _self_\nname: reinforce\nlrr: 0.1\n"
    )
    (tmp_path / "config.yaml").write_text("defaults:\n  - /schema_config@_here_\n  - algo: typo\n")
    with initialize_config_dir(str(tmp_path), version_base="1.3"), pytest.raises(Exception, match="lrr"):
        compose("config")


def test_per_agent_keys():
    assert set(per_agent_keys()) == {"seed", "algo.lr", "algo.gamma", "algo.weight_decay"}


def test_the_key_lists_do_not_depend_on_what_was_imported_first():
    """In a fresh process the cached key lists were made from the schemas stored so far: asked before
    any plug-in module was imported they lacked every algo.* key (so a resume rule, a per-agent key
    or a migrated config read wrong, depending on test order)."""
    import subprocess
    import sys

    code = "from drone_torchrl.config import per_agent_keys; print(sorted(per_agent_keys()))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == str(sorted(["seed", "algo.lr", "algo.gamma", "algo.weight_decay"]))


# What a continued run did with each key before the rules were the schema's (RESUME_KEYS,
# PROCESS_KEYS and FIXED_ON_RESUME of drone_torchrl/training/jobs.py).
# agent (added with population runs) goes with resume: the agent of a population run it continues.
PROCESS_KEYS = ("progress", "threads", "device", "resume", "agent")
RESUME_KEYS = (
    "algo.episodes",
    "sweep_name",
    "logger.",
    "checkpoint.",
    "eval.every_episodes",
    "eval.video",
    "eval.stop_return",  # added later, with the budget's rule in spirit: a raised one trains on
    "eval.rollback_drop",  # added later: set again (or null) on a continued run
)
# logger=wandb's project and entity hold its run id: a continued run keeps them (added with it).
FIXED_ON_RESUME = ("logger.backend", "logger.exp_name", "logger.project", "logger.entity")


def test_resume_rules_are_those_of_the_lists_they_replace():
    every = {}
    for algo in schema.stored_plugins("algo"):
        for logger in schema.stored_plugins("logger"):
            every.update(schema_keys("config", algo=algo, logger=logger))
    shared = {"algo.clip_epsilon", "algo.weight_decay", "logger.float_format", "logger.tracking_uri"}
    assert shared <= set(every)
    for key in every:
        listed = key not in FIXED_ON_RESUME and any(
            key == k or (k.endswith(".") and key.startswith(k)) for k in RESUME_KEYS
        )
        expected = (
            schema.PROCESS
            if key in PROCESS_KEYS
            else schema.BUDGET
            if key == "algo.episodes"
            else schema.IF_SET
            if listed
            else schema.KEPT
        )
        assert resume_rule(key) == expected, key


# The keys added since the first runs, with the value those runs behaved as (ADDED_KEYS of
# drone_torchrl/config.py before the rules were the schema's).
ADDED_KEYS = {
    "backend": "reference",  # engine before it (drone_torchrl/migrations.py); the first runs: torchrl
    "logger.every_updates": 1,
    "logger.video_stride": 1,
    "algo.optimizer": "adam",
    "algo.weight_decay": 0.0,
    "logger.flush_every_s": 10,
    "algo.name": "reinforce",
    "model.init_std": None,
    "algo.log_prob_reduction": "sum",
    "logger.backend": "tensorboard",
    "env.x_limit": 2.0,
    "env.z_min": 0.0,
    "env.z_max": 4.0,
    "env.alpha_limit": 1.0471975511965976,  # pi/3
    "env.zone_x_limit": 0.8,
    "env.zone_z_min": 2.2,
    "env.zone_z_max": 3.2,
    "env.bounds": "inclusive",
    "env.dtype": "float32",
}


@pytest.mark.parametrize("algo", ["reinforce", "ppo"])
def test_an_old_runs_config_gets_the_added_keys(algo):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = OmegaConf.to_container(compose("config", overrides=[f"algo={algo}"]), resolve=True)
    complete(cfg)  # today's every key, env.disturbance.* too
    now = leaves(cfg)
    old = dict(cfg)
    for key in ADDED_KEYS:
        section, _, leaf = key.rpartition(".")
        (old[section] if section else old).pop(leaf, None)
    if algo != "reinforce":
        old["algo"]["name"] = algo
    filled = leaves(run_config(old))
    expected = {key: value for key, value in ADDED_KEYS.items() if key in now} | {"algo.name": algo}
    assert {key: filled[key] for key in expected} == expected
    assert set(filled) == set(now)


@pytest.mark.parametrize(
    ("overrides", "names"),
    [
        (["~logger.every_updates"], "logger.every_updates"),
        (["algo=ppo", "~algo.clip_epsilon"], "algo.clip_epsilon"),
        (["~seed"], "seed"),
        (["algo=reinforce_plus", "algo.gae_lambda=0.9"], "algo=ppo"),  # every option that has the key
        (["logger=mlflow", "logger.float_format=x"], "logger=csv"),
    ],
)
def test_overrides_hydra_would_refuse_in_several_lines_are_one(overrides, names):
    with pytest.raises(ConfigError) as info:
        check_overrides(overrides)
    assert "\n" not in str(info.value) and names in str(info.value)


def test_a_key_of_the_plug_in_an_experiment_picks_is_accepted():
    # experiment=hover_optimal picks algo=ppo: its keys are this run's keys (they were refused as
    # "not a key of this algo" when only algo= on the command line picked the plug-in).
    check_overrides(["experiment=hover_optimal", "algo.num_envs=256"])
    check_overrides(["algo=a2c,ppo", "algo.num_envs=256"])  # a sweep: both jobs have it
    with pytest.raises(ConfigError, match="algo.num_envs is not a key of this algo"):
        check_overrides(["experiment=bounded", "algo.num_envs=256"])  # bounded keeps REINFORCE


@pytest.mark.parametrize("sweep", ["algo=reinforce,ppo", "experiment=bounded,hover_optimal"])
def test_a_sweep_accepts_only_keys_every_one_of_its_jobs_has(sweep):
    with pytest.raises(ConfigError, match="algo.num_envs is not a key of this algo"):
        check_overrides([sweep, "algo.num_envs=256"])


def test_the_keys_are_every_plug_in_s_whoever_asks_first():
    """``_every_key`` and ``schema_keys`` are cached: asked before anything had discovered the plug-ins
    (a test module reading them at import), they cached the keys without any algorithm's, and every
    continued run of that process then kept its checkpoint's budget (``algo.episodes`` looked like
    a kept key). A fresh process asks them first."""
    import subprocess
    import sys

    probe = (
        "from drone_torchrl.config import _every_key, resume_rule, schema_keys\n"
        "print('algo.episodes' in _every_key('config'), resume_rule('algo.episodes'),"
        " 'algo.num_envs' in schema_keys('config', algo='ppo'))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["True", "budget", "True"]


def test_the_env_nodes_physics_and_arena_are_drone_params():
    """One home: the schema's env keys for the drone are DroneParams' fields, with its defaults, and
    no conf/ file restates them (a composed run gets the paper's drone all the same)."""
    from dataclasses import asdict, fields

    from drone_torchrl.envs.params import PARAM, PARAM_NAMES, DroneParams

    env_keys = [f.name for f in fields(schema.EnvConf)]
    assert env_keys[: len(PARAM_NAMES)] == list(PARAM_NAMES)
    rules = {f.name: f.metadata.get(schema.RULE) for f in fields(schema.EnvConf)}
    for f in fields(DroneParams):  # a field added after the first runs: an old config gets its default
        assert rules[f.name].is_added == f.metadata[PARAM].new
        assert not rules[f.name].is_added or rules[f.name].added == f.default
    assert rules["bounds"].choices == ("inclusive", "strict")
    yaml = OmegaConf.load(Path(config_dir()) / "env" / "drone.yaml")
    assert not set(yaml) & set(PARAM_NAMES) and set(yaml) == {
        "max_steps",
        "reset_mode",
        "dtype",
        "num_workers",
    }
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=["env.max_thrust=1.5"])
    assert {k: cfg.env[k] for k in PARAM_NAMES} == {**asdict(DroneParams()), "max_thrust": 1.5}
