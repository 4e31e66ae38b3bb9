"""Config YAML through libyaml: the text OmegaConf.to_yaml writes, and Hydra's record files as a launcher writes them."""

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from drone_torchrl.config import config_dir
from drone_torchrl.io.yaml_text import save_yaml, to_yaml
from hydra_plugins.drone_torchrl_launcher.population_launcher import _JobReturn

AWKWARD = {
    "number_like": ["1e-3", "0x1F", "3.0", "1_000", ".5", "-7"],
    "bool_like": ["yes", "off", "True", "null", "~", ""],
    "text": ["é ü ß 日本語", "a: b", "- x", "# not a comment", "multi\nline\n", "word " * 40, "tab\there"],
    "values": [1, 2.5, -0.0, 1e-5, None, True, float("inf")],
    "nested": {"interpolation": "${values}", "list": [[1, 2], {"k": "v"}]},
}


@pytest.mark.parametrize("which", ["task", "hydra", "awkward"])
def test_the_text_is_omegaconfs(which):
    if which == "awkward":
        cfg = OmegaConf.create(AWKWARD)
    else:
        with initialize_config_dir(config_dir(), version_base="1.3"):
            cfg = compose("config", overrides=["algo.lr=3e-4", "sweep_name=lr"], return_hydra_config=True)
        if which == "task":
            cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    assert to_yaml(cfg) == OmegaConf.to_yaml(cfg)
    assert to_yaml(OmegaConf.to_container(cfg)) == OmegaConf.to_yaml(cfg)


def test_saved_files_read_back_equal(tmp_path):
    cfg = OmegaConf.create(AWKWARD)
    save_yaml(cfg, tmp_path / "c.yaml")
    assert (tmp_path / "c.yaml").read_bytes().decode("utf-8") == OmegaConf.to_yaml(cfg)
    assert OmegaConf.load(tmp_path / "c.yaml") == cfg


def test_a_fused_job_return_builds_its_hydra_config_when_read():
    container = {"hydra": {"job": {"name": "train", "num": 3}, "runtime": {"output_dir": "/x"}}}
    ret = _JobReturn(overrides=["seed=3"], working_dir="/w")
    ret._hydra_container = container
    assert ret.hydra_cfg == OmegaConf.create(container)
    assert ret.hydra_cfg.hydra.job.num == 3
    assert ret.hydra_cfg is ret.hydra_cfg  # built once
    ret.hydra_cfg = None
    assert ret.hydra_cfg is not None  # rebuilt from the container
