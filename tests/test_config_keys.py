"""The keys a default run's config lists (issue 40): at most 60, env.disturbance empty unless set, and
the keys removed with their one value (drone_torchrl.migrations.FIXED) read from old configs."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from drone_torchrl import migrations
from drone_torchrl.config import ConfigError, config_dir, env_kwargs, run_config
from drone_torchrl.envs.disturbances import Disturbance

# The bound on what `drone-train --cfg job` prints for a default run.
MAX_KEYS = 60


def _composed(*overrides: str) -> dict:
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return OmegaConf.to_container(compose("config", overrides=list(overrides)), resolve=True)


def _leaves(node: object) -> int:
    """Non-mapping values (a list is one), as the issue counts `--cfg job`'s keys."""
    return sum(_leaves(v) for v in node.values()) if isinstance(node, dict) else 1


def test_a_default_run_lists_at_most_60_keys():
    cfg = _composed()
    assert _leaves(cfg) <= MAX_KEYS  # 68 before: 10 nominal disturbances and the two FIXED keys
    assert cfg["env"]["disturbance"] == {} and "metrics" not in cfg and "video_fps" not in cfg["logger"]


def test_a_disturbance_key_is_set_without_a_preset_and_the_rest_are_nominal():
    nominal = Disturbance()
    flown = env_kwargs(_composed("env.disturbance.wind=0.3"))["disturbance"]
    assert flown == {**vars(nominal), "wind": 0.3}
    assert env_kwargs(_composed())["disturbance"] == vars(nominal)
    assert env_kwargs(_composed("disturbance=mild"))["disturbance"]["gust_time"] == nominal.gust_time


@pytest.mark.parametrize(("key", "old"), [("metrics.running_mean_window", 100), ("logger.video_fps", 50)])
def test_a_saved_config_with_a_removed_key_reads_only_with_its_one_value(key, old):
    saved = _composed()
    section, leaf = key.split(".")
    saved.setdefault(section, {})[leaf] = old
    assert OmegaConf.select(run_config(saved), key, default="gone") == "gone"
    saved[section][leaf] = old + 1
    with pytest.raises(ConfigError, match=f"{key}={old + 1} is not allowed: the key was removed"):
        run_config(saved)


def test_a_removed_key_on_the_command_line_is_a_note_with_its_value_and_refused_with_another():
    args, notes = migrations.legacy_arguments(["metrics.running_mean_window=100", "seed=1"])
    assert args == ["+legacy.metrics.running_mean_window=100", "seed=1"] and len(notes) == 1
    with pytest.raises(ValueError, match="logger.video_fps=25 is not allowed"):
        migrations.legacy_arguments(["logger.video_fps=25"])
