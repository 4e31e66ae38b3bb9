"""Config validation checks the env's arguments without building an env (drone_env.check_env_args),
with the same one-line messages, and the evaluator's helpers read them the same way."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir

from drone_torchrl.checks import ConfigError
from drone_torchrl.config import config_dir, env_kwargs, validate
from drone_torchrl.envs import drone_env
from drone_torchrl.evaluation import max_return, reference_optimum


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=list(overrides))


@pytest.fixture
def no_env(monkeypatch):
    """Building a DroneEnv fails the test."""

    def refuse(self, *args, **kwargs):
        raise AssertionError("a DroneEnv was built")

    monkeypatch.setattr(drone_env.DroneEnv, "__init__", refuse)


def test_validation_builds_no_env(no_env):
    validate(_cfg("algo.episodes=2"), training=False)
    with pytest.raises(ConfigError) as err:
        validate(_cfg("env.mass=-1.0"), training=False)
    assert str(err.value) == "env.mass=-1.0 is not allowed; expected a finite number >= 0.001 and <= 10000.0"
    with pytest.raises(ConfigError) as err:
        validate(_cfg("env.zone_z_min=10.0"), training=False)
    assert str(err.value) == (
        "env.zone_z_min=10.0 is not allowed; expected a finite number >= z_min (0.0) and < z_max (4.0)"
    )


def test_the_evaluator_reads_the_arguments_without_an_env(no_env):
    kwargs = env_kwargs(_cfg("env.max_steps=200", "env.max_thrust=1.0"))
    assert max_return(kwargs) == 2000.0
    optimum = reference_optimum(kwargs)
    assert optimum is not None and 0 < optimum.best_return < 2000.0


def test_a_fresh_process_validates_a_composed_config(tmp_path):
    """A launcher's worker (joblib, submitit) gets the composed config and has imported no plug-in:
    validating it there found no logger schema ("has no config schema") and failed every job."""
    import subprocess
    import sys

    from omegaconf import OmegaConf

    path = tmp_path / "config.yaml"
    OmegaConf.save(_cfg("algo=ppo", "logger=csv"), path)
    code = (
        "import sys; from omegaconf import OmegaConf; from drone_torchrl.config import validate; "
        "validate(OmegaConf.load(sys.argv[1])); print('valid')"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0 and proc.stdout.strip() == "valid", proc.stderr[-2000:]
