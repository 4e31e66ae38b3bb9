"""Sweep job configs derived from the first job equal Hydra's full composition of each job."""

from __future__ import annotations

import pytest
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.types import RunMode
from omegaconf import OmegaConf, open_dict

from drone_torchrl.config import ConfigError, config_dir
from hydra_plugins.drone_torchrl_launcher.compose import checked_batch, sweep_configs

# Job overrides as the basic sweeper produces them: plain values of several types, nested keys,
# a list, null, and kinds that need the full composition (a config group, +key, ~key).
JOBS = [
    ["algo.lr=0.001", "seed=0"],
    ["algo.lr=5e-05", "seed=1"],
    ["algo.lr=0.0001", "seed=3"],
    ["algo.lr=1", "seed=2"],
]
OTHER_KINDS = [
    ["algo.lr=0.001", "seed=0", "model.hidden_sizes=[16,8]", "env.max_thrust=null", "eval.video=false"],
    ["algo.lr=0.002", "seed=5", "model.hidden_sizes=[7]", "env.max_thrust=1.5", "eval.video=true"],
    ["algo.lr=0.002", "seed=5", "model.hidden_sizes=[7]", "env.max_thrust=1.5", "eval.video=off"],
]
FALLBACK = [
    ["algo.lr=0.001", "seed=0"],
    ["algo.lr=0.001", "experiment=bounded"],
    ["algo.lr=0.001", "+extra=3"],
    # A top-level key: OmegaConf refuses to delete a key of a nested schema (logger.*, algo.*...),
    # which check_overrides says in one line before Hydra composes.
    ["algo.lr=0.001", "seed=0", "~progress"],
]


def _loader_and_master():
    GlobalHydra.instance().clear()
    initialize_config_dir(config_dir(), version_base="1.3")
    loader = GlobalHydra.instance().config_loader()
    master = loader.load_configuration("config", overrides=[], run_mode=RunMode.MULTIRUN)
    return loader, master


@pytest.mark.parametrize("jobs", [JOBS, OTHER_KINDS, FALLBACK], ids=["values", "types", "fallback"])
def test_derived_configs_equal_full_composition(jobs):
    loader, master = _loader_and_master()
    try:
        # Each derived config is compared as it comes: the jobs share one hydra node, rewritten per job.
        for overrides, cfg in zip(jobs, sweep_configs(loader, master, jobs), strict=True):
            full = loader.load_sweep_config(master, list(overrides))
            assert OmegaConf.to_container(cfg, resolve=False) == OmegaConf.to_container(
                full, resolve=False
            ), overrides
            for key in ("hydra.sweep.dir", "hydra.sweep.subdir"):  # resolved in the job's own config
                assert OmegaConf.select(cfg, key) == OmegaConf.select(full, key), (key, overrides)
            assert list(cfg.hydra.overrides.task) == list(overrides)
    finally:
        GlobalHydra.instance().clear()


def test_a_checked_batch_is_each_job_s_config_without_hydra_s_node():
    """What the sweeper checks and the population launcher trains (``checked_batch``): each job's config
    without Hydra's node, or one config and a column per per-agent key when only those differ."""
    loader, master = _loader_and_master()
    try:
        jobs = OTHER_KINDS[:2]  # (eval.video=off is refused: what the check is for)
        batch = checked_batch(loader, master, jobs)
        assert batch.values is None and len(batch.configs) == len(jobs)
        for overrides, cfg in zip(jobs, batch.configs, strict=True):
            full = loader.load_sweep_config(master, list(overrides))
            with open_dict(full):
                del full["hydra"]
            assert "hydra" not in cfg
            assert OmegaConf.to_container(cfg, resolve=False) == OmegaConf.to_container(full, resolve=False)
        batch = checked_batch(loader, master, JOBS)
        assert batch.configs == [batch.configs[0]] * len(JOBS)
        assert (batch.values["seed"], batch.values["algo.lr"]) == ([0, 1, 3, 2], [0.001, 5e-05, 0.0001, 1])
        assert batch.hydra_record["hydra"]["overrides"]["task"] == JOBS[0]
        with pytest.raises(
            ConfigError, match=r"^eval.video='off' is not allowed.*\(in the sweep's job .* eval.video=off;"
        ):
            checked_batch(loader, master, OTHER_KINDS)
    finally:
        GlobalHydra.instance().clear()


def test_a_bad_override_still_fails():
    loader, master = _loader_and_master()
    try:
        with pytest.raises(Exception, match="nope"):
            list(sweep_configs(loader, master, [["seed=0"], ["algo.nope=1"]]))
    finally:
        GlobalHydra.instance().clear()


def test_compose_shortcut_is_used_for_plain_values(monkeypatch):
    loader, master = _loader_and_master()
    calls = []
    full = loader.load_sweep_config
    monkeypatch.setattr(loader, "load_sweep_config", lambda m, o: calls.append(o) or full(m, o))
    try:
        list(
            sweep_configs(
                loader, master, [[f"seed={s}", f"algo.lr={lr}"] for s in range(8) for lr in (1e-3, 1e-4)]
            )
        )
        assert len(calls) == 1
    finally:
        GlobalHydra.instance().clear()
