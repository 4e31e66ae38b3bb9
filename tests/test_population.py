"""The fast engine's populations (backend=fast): agents trained in one population follow the runs they
follow alone, evaluate as they would alone, resume, and fail alone."""

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from torchrl.modules import TanhNormal

from drone_torchrl.config import config_dir, env_kwargs
from drone_torchrl.evaluation import evaluate
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.io.episodes_csv import read_episodes
from drone_torchrl.modules import ActionSampler, StackedThreeNet, ThreeNetPolicy
from drone_torchrl.modules.factory import build_policies, build_policy
from drone_torchrl.training.jobs import group_key, prepare
from drone_torchrl.training.trainer import Trainer, train_jobs

COMMON = [
    "backend=fast",
    "env.max_steps=60",
    "eval.every_episodes=0",
    "eval.episodes=3",
    "eval.video=false",
    "progress=false",
]


def _cfg(*overrides):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=[*COMMON, *overrides])


def _train(*jobs):
    return train_jobs([prepare(cfg, run_dir) for cfg, run_dir in jobs])


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
    action = ActionSampler("tanh_normal", 1.0)(loc, scale, noise)
    assert bool((action > 0).all() and (action < 1).all())
    dist = TanhNormal(loc, scale, low=0.0, high=1.0, tanh_loc=False)  # what make_actor uses
    assert bool(torch.isfinite(dist.log_prob(action)).all())
    torch.testing.assert_close(action, 0.5 * (torch.tanh(loc + scale * noise) + 1))


# Domain randomisation on the fast engine: every disturbance, and the last 2 commands observed.
DISTURBED = ("experiment=bounded", "disturbance=strong", "env.disturbance.observed_actions=2")


@pytest.mark.parametrize("preset", [("experiment=paper",), ("experiment=bounded",), DISTURBED])
def test_agent_in_a_batch_follows_its_solo_trajectory(tmp_path, preset):
    """50 episodes: seed 0 alone, first of a population of 3 and last of a population of 5, with
    other seeds, learning rates and discounts beside it."""
    mine = ("seed=0", "algo.lr=1e-3", "algo.gamma=0.99")
    others = [
        ("seed=1", "algo.lr=1e-4", "algo.gamma=0.9"),
        ("seed=2", "algo.lr=5e-4", "algo.gamma=0.999"),
        ("seed=3", "algo.lr=3e-3", "algo.gamma=0.95"),
        ("seed=4", "algo.lr=1e-3", "algo.gamma=0.5"),
    ]
    common = (*preset, "algo.episodes=50")
    small = [mine, *others[:2]]
    large = [*others, mine]
    jobs_small = [(_cfg(*common, *s), tmp_path / f"small{i}") for i, s in enumerate(small)]
    jobs_large = [(_cfg(*common, *s), tmp_path / f"large{i}") for i, s in enumerate(large)]
    assert len({group_key(cfg) for cfg, _ in jobs_small + jobs_large}) == 1
    _train(*jobs_small)
    _train(*jobs_large)
    _train((_cfg(*common, *mine), tmp_path / "alone"))
    solo, _ = read_episodes(tmp_path / "alone" / "episodes.csv")
    assert len(solo["episode"]) == 50
    for folder in ("small0", "large4"):
        fused, _ = read_episodes(tmp_path / folder / "episodes.csv")
        np.testing.assert_array_equal(solo["length"], fused["length"])
        np.testing.assert_allclose(solo["return"], fused["return"], rtol=1e-5)
        np.testing.assert_allclose(
            solo["negative_thrust_fraction"], fused["negative_thrust_fraction"], atol=1e-6
        )
        a = load_checkpoint(tmp_path / "alone" / "checkpoints" / "last.pt")["actor"]
        b = load_checkpoint(tmp_path / folder / "checkpoints" / "last.pt")["actor"]
        for key in a:
            torch.testing.assert_close(a[key], b[key], rtol=1e-5, atol=1e-6)
    # The other agents really are different runs.
    other, _ = read_episodes(tmp_path / "small1" / "episodes.csv")
    assert not np.array_equal(other["return"], solo["return"])


@pytest.mark.parametrize("preset", [(), ("experiment=bounded",), DISTURBED])
def test_population_evaluation_equals_each_actor_alone(tmp_path, preset):
    """The evaluator flying two agents on the fast engine equals it flying each agent's own actor
    through the reference (DroneEnv and TorchRL's rollout)."""
    cfgs = [_cfg(*preset, "algo.episodes=4", "eval.episodes=5", f"seed={s}") for s in (0, 1)]
    trainer = Trainer([prepare(cfg, tmp_path / f"run{i}") for i, cfg in enumerate(cfgs)])
    kwargs = env_kwargs(cfgs[0])
    stacked, _ = evaluate(trainer.learner.eval_policy(), kwargs, 5, 123, agents=2)
    for i in range(len(cfgs)):
        alone, _ = evaluate(trainer.population.actor(i), kwargs, 5, 123)
        torch.testing.assert_close(stacked["return"][i], alone["return"])
        torch.testing.assert_close(stacked["length"][i], alone["length"])
    trainer.close()


def test_a_population_is_evaluated_a_slice_of_agents_at_a_time_as_all_at_once(tmp_path, monkeypatch):
    """Trainer.evaluate flies ops.AGENTS_PER_EVALUATION agents per call (the episodes of one slice
    are held at once): 5 agents as slices of 2, 2 and 1 book each agent the evaluation it gets in
    one call of all 5 (a slice given another agent's rows, or stats joined out of order, differ)."""
    from drone_torchrl.training import trainer as trainer_module

    cfgs = [_cfg("algo.episodes=4", "eval.episodes=3", f"seed={s}") for s in range(5)]
    trainer = Trainer([prepare(cfg, tmp_path / f"run{i}") for i, cfg in enumerate(cfgs)])
    with torch.no_grad():  # agents that fly differently: untrained ones all fall at once
        flat = trainer.population.policy.flat
        flat.add_(torch.randn(flat.shape, generator=torch.Generator().manual_seed(0)))
    booked = []
    for run in trainer.runs:
        run.record_eval = lambda result, *_, booked=booked: booked.append(result["return"])
    trainer.evaluate(list(range(5)))
    monkeypatch.setattr(trainer_module, "AGENTS_PER_EVALUATION", 2)
    trainer.evaluate(list(range(5)))
    trainer.close()
    assert booked[:5] == booked[5:] and len(set(booked[:5])) >= 3


def test_fused_resume_equals_an_uninterrupted_run(tmp_path):
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    _train((_cfg("algo.episodes=12", "checkpoint.every_episodes=6"), whole))
    _train((_cfg("algo.episodes=6", "checkpoint.every_episodes=6"), cut))
    (again,) = _train((_cfg("algo.episodes=6", "checkpoint.every_episodes=6"), cut))
    assert again.final is not None and again.error is None  # finished: skipped
    _train((_cfg("algo.episodes=12", "checkpoint.every_episodes=6"), cut))
    (a, _), (b, _) = read_episodes(whole / "episodes.csv"), read_episodes(cut / "episodes.csv")
    assert a["episode"].tolist() == b["episode"].tolist() == list(range(12))
    np.testing.assert_array_equal(a["return"], b["return"])


def test_a_diverged_agent_stops_alone_and_keeps_its_last_finite_checkpoint(tmp_path):
    """Agent 1's weights turn NaN right after its episode-4 checkpoint: it stops with FAILED.txt at
    the next update (NaN actions, loss and gradients), the other agents finish, and its last.pt
    still holds the finite episode-4 weights."""
    common = ("algo.episodes=10", "checkpoint.every_episodes=2")
    jobs = [prepare(_cfg(*common, f"seed={s}"), tmp_path / f"agent{s}") for s in range(3)]
    trainer = Trainer(jobs)
    for _ in range(4):  # one episode per update: episodes 0..3, checkpoints after episodes 2 and 4
        trainer.step([0, 1, 2], 1)
    with torch.no_grad():
        trainer.population.policy.params.get(("mean", "bias"))[1] = float("nan")
    finals = trainer.train()
    assert finals[0] is not None and finals[2] is not None and finals[1] is None
    failed = (tmp_path / "agent1" / "FAILED.txt").read_text()
    assert "training diverged at episode 4: non-finite actions and loss and gradients" in failed
    last = load_checkpoint(tmp_path / "agent1" / "checkpoints" / "last.pt")
    assert last["episodes_done"] == 4 and last["final"] is None
    assert all(bool(torch.isfinite(v).all()) for v in last["actor"].values())
    rows, _ = read_episodes(tmp_path / "agent1" / "episodes.csv")
    assert rows["episode"].tolist() == [0, 1, 2, 3]  # the diverged update is not recorded
    for s in (0, 2):
        assert load_checkpoint(tmp_path / f"agent{s}" / "checkpoints" / "last.pt")["episodes_done"] == 10


@pytest.mark.parametrize("preset", ["paper", "bounded"])
def test_checkpoint_actor_entries_equal_a_built_actor(preset):
    """Population.state writes each agent's actor in make_actor's layout (keys, order, values)."""
    from drone_torchrl.modules.factory import build_actor
    from drone_torchrl.training.population import Population

    cfgs = [_cfg(f"experiment={preset}", f"seed={s}") for s in range(3)]
    population = Population(cfgs)
    for agent in range(3):
        expected = build_actor(cfgs[agent], population.policy.agent_net(agent)).state_dict()
        got = population.checkpoint_entries(agent)["actor"]
        assert list(got) == list(expected)
        for key in expected:
            torch.testing.assert_close(got[key], expected[key], rtol=0, atol=0)
        assert not any(got[k].data_ptr() == p.data_ptr() for k in got for p in population.policy.parameters())


@pytest.mark.parametrize(
    "overrides",
    [
        [],
        ["experiment=bounded", "model.init_std=0.3"],
        ["model.hidden_sizes=[16,8,4]", "model.activation=relu"],
        ["env.dtype=float64"],
    ],
)
def test_stacked_policies_start_from_each_seeds_own_weights(overrides, monkeypatch):
    """build_policies draws every agent's weights without a module each: agent i's equal
    build_policy(cfg, seed_i)'s (torch.manual_seed then nn.Linear's init), bit for bit. Also when the
    one-draw-per-row shortcut does not round as uniform_ does (forced here): it then draws layer by
    layer."""
    cfg = _cfg(*overrides)
    seeds = [0, 1, 7, 12345, 2**31 - 1]
    alone = StackedThreeNet([build_policy(cfg, seed) for seed in seeds], cfg.model.activation)
    torch.manual_seed(12345)  # whatever torch's generator held before
    stacked = build_policies(cfg, seeds)
    assert stacked.names == alone.names and stacked.flat.dtype == alone.flat.dtype
    assert torch.equal(stacked.flat, alone.flat)
    after_stacked = torch.get_rng_state()
    build_policy(cfg, seeds[-1])
    assert torch.equal(after_stacked, torch.get_rng_state())  # the reference collector draws from it next
    addcmul = torch.addcmul
    monkeypatch.setattr(torch, "addcmul", lambda *a: addcmul(*a) + 1e-3)
    assert torch.equal(build_policies(cfg, seeds).flat, alone.flat)
