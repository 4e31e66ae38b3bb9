"""The fused engine: agents trained in one batch follow the trajectories they follow alone."""

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from torchrl.modules import TanhNormal

from drone_torchrl.checkpoint import load_checkpoint
from drone_torchrl.config import config_dir
from drone_torchrl.evaluation import evaluate
from drone_torchrl.fused import FusedTrainer, StackedThreeNet, _Sampler, group_key, train_fused
from drone_torchrl.metrics import read_episode_csv
from drone_torchrl.modules import ThreeNetPolicy

COMMON = [
    "engine=fused",
    "compile=false",  # the equivalence is promised in eager mode; compile changes float rounding
    "env.max_steps=60",
    "eval.every_episodes=0",
    "eval.episodes=3",
    "eval.video=false",
    "progress=false",
]


def _cfg(*overrides):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=[*COMMON, *overrides])


def test_stacked_nets_equal_each_net_alone():
    torch.manual_seed(0)
    nets = [ThreeNetPolicy() for _ in range(3)]
    obs = torch.randn(3, 5, 7, 6)
    loc, scale = StackedThreeNet(nets, "tanh")(obs)
    for k, net in enumerate(nets):
        ref_loc, ref_scale = net(obs[k])
        torch.testing.assert_close(loc[k], ref_loc)
        torch.testing.assert_close(scale[k], ref_scale)


def test_tanh_sampler_matches_torchrl_tanh_normal():
    loc, scale, noise = torch.randn(64, 2), torch.rand(64, 2) + 0.1, torch.randn(64, 2) * 3
    action = _Sampler("tanh_normal", 1.0)(loc, scale, noise)
    assert bool((action > 0).all() and (action < 1).all())
    dist = TanhNormal(loc, scale, low=0.0, high=1.0, tanh_loc=False)  # what make_actor uses
    assert bool(torch.isfinite(dist.log_prob(action)).all())
    torch.testing.assert_close(action, 0.5 * (torch.tanh(loc + scale * noise) + 1))


@pytest.mark.parametrize("preset", ["paper", "bounded"])
def test_agent_in_a_batch_follows_its_solo_trajectory(tmp_path, preset):
    """50 episodes: the first agent alone and inside a batch of three with other seeds, lrs and gammas."""
    settings = [
        ("seed=0", "algo.lr=1e-3", "algo.gamma=0.99"),
        ("seed=1", "algo.lr=1e-4", "algo.gamma=0.9"),
        ("seed=2", "algo.lr=5e-4", "algo.gamma=0.999"),
    ]
    jobs = [
        (_cfg(f"experiment={preset}", "algo.episodes=50", *s), tmp_path / f"batch{i}")
        for i, s in enumerate(settings)
    ]
    assert len({group_key(cfg) for cfg, _ in jobs}) == 1
    train_fused(jobs)
    train_fused([(jobs[0][0], tmp_path / "alone")])
    solo, fused = (
        read_episode_csv(tmp_path / "alone" / "episodes.csv"),
        read_episode_csv(tmp_path / "batch0" / "episodes.csv"),
    )
    assert len(solo["episode"]) == 50
    assert solo["length"] == fused["length"]
    np.testing.assert_allclose(solo["return"], fused["return"], rtol=1e-6)
    np.testing.assert_allclose(solo["negative_thrust_fraction"], fused["negative_thrust_fraction"], atol=1e-6)
    a = load_checkpoint(tmp_path / "alone" / "checkpoints" / "last.pt")["actor"]
    b = load_checkpoint(tmp_path / "batch0" / "checkpoints" / "last.pt")["actor"]
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-5, atol=1e-6)
    # The other agents really are different runs.
    other = read_episode_csv(tmp_path / "batch1" / "episodes.csv")
    assert other["return"] != fused["return"]


def test_fused_evaluation_equals_the_standard_evaluation(tmp_path):
    cfg = _cfg("algo.episodes=4", "eval.episodes=5")
    trainer = FusedTrainer([(cfg, tmp_path / "run")], [None])
    (fused,) = trainer.evaluate(trainer.agents)
    from drone_torchrl.config import env_kwargs

    stats, _ = evaluate(
        trainer.agents[0].standalone_actor(), env_kwargs(cfg), cfg.eval.episodes, cfg.eval.seed
    )
    assert fused["return"] == pytest.approx(float(stats["return"].float().mean()))
    assert fused["length"] == pytest.approx(float(stats["length"].float().mean()))
    trainer.close()


def test_fused_resume_equals_an_uninterrupted_run(tmp_path):
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    train_fused([(_cfg("algo.episodes=12", "checkpoint.every_episodes=6"), whole)])
    train_fused([(_cfg("algo.episodes=6", "checkpoint.every_episodes=6"), cut)])
    assert (
        train_fused([(_cfg("algo.episodes=6", "checkpoint.every_episodes=6"), cut)])[0] is not None
    )  # finished: skipped
    train_fused([(_cfg("algo.episodes=12", "checkpoint.every_episodes=6"), cut)])
    a, b = read_episode_csv(whole / "episodes.csv"), read_episode_csv(cut / "episodes.csv")
    assert a["episode"] == b["episode"] == list(range(12))
    assert a["return"] == b["return"]


def test_bad_job_is_recorded_and_the_others_train(tmp_path):
    good, bad = _cfg("algo.episodes=3"), _cfg("algo.episodes=3", "algo.gamma=3")
    results = train_fused([(good, tmp_path / "good"), (bad, tmp_path / "bad")])
    assert results[0] is not None and results[1] is None
    assert "algo.gamma=3" in (tmp_path / "bad" / "FAILED.txt").read_text()
