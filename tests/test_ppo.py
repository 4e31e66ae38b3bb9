"""algo=ppo and the on-policy loop every on-policy algorithm shares (TorchRL's collector, GAE, the
run record), the algorithm registry, and drone-export. The loop's tests run for every registered
on-policy algorithm (algo=ppo, algo=a2c, and any plug-in added later); each algorithm's own checks
live in its test module (tests/test_a2c.py)."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from drone_torchrl import algorithms
from drone_torchrl.algorithms import ppo
from drone_torchrl.algorithms.ppo import OnPolicy
from drone_torchrl.config import config_dir, run_config
from drone_torchrl.envs import DroneEnv
from drone_torchrl.episodes import EpisodeTracker, episode_stats
from drone_torchrl.export import export_policy, load_policy
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.io.episodes_csv import read_episodes
from drone_torchrl.modules.factory import build_actor
from drone_torchrl.training.trainer import train

QUIET = ["eval.video=false", "progress=false", "eval.episodes=2"]
# Every registered algorithm on the on-policy loop (its YAML option has the algorithm's name).
ON_POLICY = [name for name in algorithms.names() if issubclass(algorithms.get(name).learner, OnPolicy)]


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=list(overrides))


@pytest.mark.parametrize("backend", ["reference", "fast"])
def test_ppo_learns_on_a_small_budget(tmp_path, backend):
    """The does-it-learn check of SB3's test suite: the last tenth's mean return at least doubles
    the first tenth's (seed 0, 400 episodes: about 7 s here with TorchRL's collector)."""
    run = tmp_path / "run"
    train(
        _cfg("algo=ppo", "experiment=bounded", f"backend={backend}", "algo.episodes=400", *QUIET),
        run,
    )
    returns = read_episodes(run / "episodes.csv")[0]["return"]
    tenth = len(returns) // 10
    first, last = returns[:tenth].mean(), returns[-tenth:].mean()
    assert last >= 2 * first, (first, last)
    state = load_checkpoint(run / "checkpoints" / "last.pt")
    assert {"actor", "critic", "optimizer"} <= set(state) and state["final"] is not None


def test_episode_tracker_equals_episode_stats_across_batches():
    """Episodes cut across collector batches are booked whole, with the metrics of episode_stats."""
    env = DroneEnv(batch_size=[3], max_steps=9, reset_mode="air", dt=0.1)
    env.set_seed(0)
    # Drone 0 hovers (truncated every 9 steps), drone 1 spins into a TILT after a few steps, drone 2
    # climbs at full thrust; episodes end at different steps, across the 5-step batches below.
    thrust = torch.tensor([[0.5, 0.5], [0.0, 1.5], [1.0, 1.0]])

    def policy(td):
        return td.set("action", thrust.clone())

    rollout = env.rollout(21, policy, break_when_any_done=False)
    tracker = EpisodeTracker(3)
    booked = {k: [] for k in ("return", "length", "termination_cause")}
    for chunk in rollout.split(5, dim=1):  # batches of 5 steps: episodes straddle them
        ended = tracker.update(chunk)
        for k in booked:
            booked[k] += ended[k]
    # The reference: cut the rollout into episodes by hand and use episode_stats on each.
    done = rollout.get(("next", "done")).squeeze(-1)
    expected = []
    for t in range(21):
        for env_i in done[:, t].nonzero().squeeze(-1).tolist():
            start = max([s + 1 for s in range(t) if done[env_i, s]], default=0)
            stats = episode_stats(rollout[env_i, start : t + 1].unsqueeze(0))
            expected.append(
                (stats["return"].item(), stats["length"].item(), stats["termination_cause"].item())
            )
    assert list(zip(*booked.values(), strict=True)) == expected
    assert len({length for _, length, _ in expected}) >= 2 and len(expected) >= 5


@pytest.mark.parametrize("backend", ["reference", "fast"])
@pytest.mark.parametrize("algo", ON_POLICY)
def test_on_policy_runs_resume_and_keep_their_critic(tmp_path, algo, backend):
    run = tmp_path / "run"
    train(
        _cfg(
            f"algo={algo}",
            f"backend={backend}",
            "algo.episodes=64",
            "algo.num_envs=8",
            "algo.steps_per_batch=32",
            "algo.minibatch_size=64",
            "algo.epochs=2",  # what is checked is the resume, not the learning: fewer passes
            *QUIET,
        ),
        run,
    )
    first = load_checkpoint(run / "checkpoints" / "last.pt")
    train(_cfg(f"resume={run}", "algo.episodes=128", *QUIET))
    second = load_checkpoint(run / "checkpoints" / "last.pt")
    # The batch that reaches the budget is cut at the step its last episode ends: only episodes
    # ending on that same step (at most num_envs - 1 = 7) pass it.
    assert 128 <= second["episodes_done"] < 128 + 8 and 64 <= first["episodes_done"] < 64 + 8
    assert second["updates_done"] > first["updates_done"]
    episodes = read_episodes(run / "episodes.csv")[0]["episode"]
    assert episodes.tolist() == list(range(second["episodes_done"]))  # none lost, none twice
    assert not torch.equal(first["critic"]["module.0.weight"], second["critic"]["module.0.weight"])


@pytest.mark.parametrize("preset", ["paper", "bounded"])
def test_exported_policy_runs_with_plain_torch_and_matches_the_actor(tmp_path, preset):
    """Train briefly, export, load in a fresh interpreter that never imports drone_torchrl, and
    compare with the actor's deterministic action clamped as the env clamps it."""
    run = tmp_path / "run"
    algo = (
        ["algo.episodes=4", "env.max_steps=30"]
        if preset == "paper"
        else [
            "algo=ppo",
            "algo.episodes=16",
            "algo.num_envs=8",
            "algo.steps_per_batch=16",
            "algo.minibatch_size=64",
        ]
    )
    train(_cfg(f"experiment={preset}", *algo, *QUIET), run)
    out = export_policy(run, tmp_path / "policy.pt2").path
    observations = torch.randn(257, 6) * torch.tensor([1.0, 2.0, 1.0, 2.0, 0.3, 1.0]) + torch.tensor(
        [0, 0, 2.0, 0, 0, 0]
    )
    torch.save(observations, tmp_path / "obs.pt")
    script = (
        "import sys, torch\n"
        f"policy = torch.export.load({str(out)!r}).module()\n"
        f"torch.save(policy(torch.load({str(tmp_path / 'obs.pt')!r})), {str(tmp_path / 'act.pt')!r})\n"
        "assert 'drone_torchrl' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120)
    exported = torch.load(tmp_path / "act.pt")

    state = load_checkpoint(run / "checkpoints" / "last.pt")
    cfg = run_config(state["config"])
    actor = build_actor(cfg)
    actor.load_state_dict(state["actor"])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        action = actor(TensorDict({"observation": observations}, batch_size=[257]))["action"]
    if cfg.env.max_thrust is not None:
        action = action.clamp(0.0, cfg.env.max_thrust)
        assert exported.min() >= 0 and exported.max() <= cfg.env.max_thrust
    assert exported.shape == (257, 2) and exported.dtype == torch.float32
    np.testing.assert_allclose(exported.numpy(), action.numpy(), rtol=1e-5, atol=1e-6)
    policy, _, _ = load_policy(run)
    np.testing.assert_allclose(policy(observations).detach().numpy(), action.numpy(), rtol=1e-6, atol=1e-7)


def test_algorithm_presets_compose_and_validate():
    from drone_torchrl.config import validate

    plus = _cfg("algo=reinforce_plus")
    assert plus.algo.name == "reinforce" and plus.algo.baseline == "mean" and plus.algo.normalize_returns
    assert plus.algo.episodes % plus.algo.episodes_per_update == 0
    ppo = _cfg("algo=ppo", "experiment=bounded")
    assert ppo.algo.name == "ppo" and ppo.model.distribution == "tanh_normal" and ppo.env.max_thrust == 1.0
    assert (ppo.algo.num_envs * ppo.algo.steps_per_batch) % ppo.algo.minibatch_size == 0
    for cfg in (plus, ppo, _cfg("algo=ppo"), _cfg("algo=reinforce_plus", "experiment=bounded")):
        validate(cfg)


def test_the_registry_names_every_algorithm_and_refuses_others_in_one_line():
    import re

    from drone_torchrl.algorithms.ppo import PPO
    from drone_torchrl.algorithms.reinforce import Reinforce
    from drone_torchrl.checks import ConfigError

    names = algorithms.names()
    assert {"ppo", "reinforce"} <= set(names) and list(names) == sorted(names)
    assert algorithms.get("ppo").learner is PPO and algorithms.get("reinforce").learner is Reinforce
    expected = re.escape(f"expected one of {list(names)} (registered in")
    with pytest.raises(ConfigError, match=rf"^algo.name='dqn' is not allowed; {expected}"):
        algorithms.get("dqn")


@pytest.mark.parametrize("backend", ["reference", "fast"])
@pytest.mark.parametrize("algo", ON_POLICY)
def test_a_budget_smaller_than_a_batch_trains_that_many_episodes(tmp_path, algo, backend):
    """64 drones x 64 steps from the floor end dozens of short episodes in the first batch; a budget
    of 20 used to train all of them (43), and resuming with 40 then said "finished"."""
    run = tmp_path / "run"
    train(_cfg(f"algo={algo}", f"backend={backend}", "algo.episodes=20", *QUIET), run)
    done = load_checkpoint(run / "checkpoints" / "last.pt")["episodes_done"]
    assert 20 <= done < 20 + 64
    rows = read_episodes(run / "episodes.csv")[0]
    assert rows["episode"].tolist() == list(range(done))
    # Every episode booked past the budget ended on the cut's last step, the same one as the 20th.
    train(_cfg(f"resume={run}", "algo.episodes=40", *QUIET))
    again = load_checkpoint(run / "checkpoints" / "last.pt")["episodes_done"]
    assert 40 <= again < 40 + 64 and again > done
    assert read_episodes(run / "episodes.csv")[0]["episode"].tolist() == list(range(again))


def test_a_checkpoint_without_its_algorithms_entries_is_refused_in_one_line(tmp_path):
    from drone_torchrl.config import ConfigError
    from drone_torchrl.io.checkpoint import save_checkpoint

    run = tmp_path / "run"
    train(
        _cfg(
            "algo=ppo",
            "algo.episodes=8",
            "algo.num_envs=8",
            "algo.steps_per_batch=8",
            "algo.minibatch_size=64",
            *QUIET,
        ),
        run,
    )
    last = run / "checkpoints" / "last.pt"
    state = load_checkpoint(last)
    del state["critic"]
    save_checkpoint(state, last)
    with pytest.raises(ConfigError, match=r"lacks critic \(algo.name=ppo writes it\)") as error:
        train(_cfg(f"resume={run}", "algo.episodes=16", *QUIET))
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("preset", [["experiment=hover_optimal"], ["algo=ppo"]])  # TanhNormal, Normal
def test_ppo_losses_equal_torchrls_default_clip_ppo_loss_on_one_batch(preset):
    """algo=ppo's losses are pure speed changes: on one batch, TorchRL's ClipPPOLoss as documented
    (functional, entropy bonus) gives the same losses and gradients, to float rounding, as the
    ClipPPOLoss algo=ppo builds (no entropy term when entropy_coeff is 0, the nets' own parameters)
    and as backend=fast's plain-torch clip_ppo_losses. The batch's log-probabilities are shifted by
    up to +-0.5 so that about half of the ratios leave [1 - 0.2, 1 + 0.2]: a loss clipped at
    another epsilon differs."""
    from types import SimpleNamespace

    from torchrl.objectives import ClipPPOLoss

    from drone_torchrl.algorithms.ppo import PPO, clip_ppo_losses, pre_image
    from drone_torchrl.modules.factory import build_critic, build_policy, observation_dim
    from drone_torchrl.modules.policy import distribution_head

    cfg = _cfg(*preset)
    algo = cfg.algo
    assert algo.entropy_coeff == 0
    net = build_policy(cfg, 0)
    actor = build_actor(cfg, net, return_log_prob=True)
    critic = build_critic(cfg)
    built = PPO.make_loss(SimpleNamespace(cfg=cfg), actor, critic)
    reference = ClipPPOLoss(
        actor,
        critic,
        clip_epsilon=algo.clip_epsilon,
        entropy_coeff=algo.entropy_coeff,
        critic_coeff=algo.critic_coeff,
        normalize_advantage=True,
    )
    frames = 512
    generator = torch.Generator().manual_seed(0)
    observations = torch.randn(frames, observation_dim(cfg), generator=generator)
    batch = TensorDict({"observation": observations}, [frames])
    with torch.no_grad():
        actor(batch)
    keys = reference.tensor_keys
    log_prob = keys.sample_log_prob
    batch[log_prob] = batch[log_prob] + torch.rand(batch[log_prob].shape, generator=generator) - 0.5
    batch["advantage"] = torch.randn(frames, 1, generator=generator)
    batch["value_target"] = torch.randn(frames, 1, generator=generator)
    params = [*actor.parameters(), *critic.parameters()]
    head = distribution_head(cfg.model.distribution, cfg.env.max_thrust)
    eps, coeff = torch.tensor(algo.clip_epsilon), torch.tensor(algo.critic_coeff)
    plain = [
        batch["observation"],
        *pre_image(head, batch[keys.action]),
        *(batch[key] for key in (log_prob, keys.advantage, keys.value_target)),
    ]

    def losses_and_gradients(loss):
        out = loss(batch.clone())
        total = sum(value for key, value in out.items() if key.startswith("loss_"))
        return out, torch.autograd.grad(total, params)

    def fused(_):
        return TensorDict(clip_ppo_losses(net, critic.module, plain, eps, coeff))

    want, want_grads = losses_and_gradients(reference)
    assert 0.3 < want["clip_fraction"] < 0.7, want["clip_fraction"]
    assert want["loss_entropy"] == 0 and "loss_entropy" not in built.out_keys
    for got, got_grads in map(losses_and_gradients, (built, fused)):
        for key in ("loss_objective", "loss_critic", "clip_fraction", "kl_approx"):
            torch.testing.assert_close(got[key], want[key], rtol=1e-5, atol=1e-7)
        assert sorted(k for k, _ in got.items() if k.startswith("loss_")) == ["loss_critic", "loss_objective"]
        assert len(got_grads) == len(params) and any(g.abs().max() > 0 for g in got_grads)
        for g, w in zip(got_grads, want_grads, strict=True):
            torch.testing.assert_close(g, w, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("algo", ON_POLICY)
def test_a_stop_signal_ends_an_on_policy_run_after_its_batch_with_a_checkpoint(tmp_path, monkeypatch, algo):
    """SIGTERM during the second batch: that batch is booked, last.pt counts both batches' episodes,
    the run stops with exit code 143; resumed, it goes on from there, no episode lost or twice."""
    import signal

    from drone_torchrl.training.run import RunRecord
    from drone_torchrl.training.signals import TrainingStopped

    record, booked = RunRecord.record, []

    def record_then_signal(self, episodes, metrics):
        record(self, episodes, metrics)
        booked.append(len(episodes["return"]))
        if len(booked) == 2:
            signal.raise_signal(signal.SIGTERM)

    monkeypatch.setattr(RunRecord, "record", record_then_signal)
    run = tmp_path / "run"
    small = ["algo.num_envs=8", "algo.steps_per_batch=32", "algo.minibatch_size=64", "algo.epochs=1", *QUIET]
    with pytest.raises(TrainingStopped) as stopped:
        train(_cfg(f"algo={algo}", "algo.episodes=100000", *small), run)
    assert stopped.value.exit_code == 143 and stopped.value.run_dirs == [run]
    state = load_checkpoint(run / "checkpoints" / "last.pt")
    assert (state["updates_done"], state["episodes_done"], state["final"]) == (2, sum(booked), None)
    monkeypatch.undo()
    train(_cfg(f"resume={run}", f"algo.episodes={sum(booked) + 8}", *QUIET))
    again = load_checkpoint(run / "checkpoints" / "last.pt")
    assert again["episodes_done"] >= sum(booked) + 8 and again["final"] is not None
    assert read_episodes(run / "episodes.csv")[0]["episode"].tolist() == list(range(again["episodes_done"]))


@pytest.mark.parametrize("backend", ["reference", "fast"])
def test_target_kl_ends_a_batch_s_epochs_at_the_first_minibatch_past_its_margin(backend):
    """``algo.target_kl``: before each step after the batch's first, a minibatch whose approximate KL
    from the flying policy exceeds 1.5 x target_kl ends the batch's epochs (Stable-Baselines3's
    rule). 2 epochs x 4 minibatches, the loss's kl_approx replaced by a given sequence, target 0.1
    (margin 0.15): no target or a sequence under the margin, 8 steps; 0.16 at the third minibatch,
    2 steps; over the margin from the first, 1 step (the batch's first step is always taken)."""
    from drone_torchrl.training.jobs import Job

    small = ["algo=ppo", f"backend={backend}", "algo.num_envs=8", "algo.steps_per_batch=32"]
    small += ["algo.minibatch_size=64", "algo.epochs=2"]
    cases = {
        ("null", (0.9,) * 8): 8,
        ("0.1", (0.0, 0.14, 0.149, 0.149, 0.1, 0.0, 0.149, 0.149)): 8,
        ("0.1", (0.0, 0.1, 0.16, 0.0, 0.0, 0.0, 0.0, 0.0)): 2,
        ("0.1", (9.0,) * 8): 1,
    }
    for (target, kls), expected in cases.items():
        learner = algorithms.get("ppo").learner([Job(_cfg(*small, f"algo.target_kl={target}"), run_dir=None)])
        taken, sequence, losses = [], iter(kls), learner.minibatches.losses

        def given_kl(minibatch, losses=losses, sequence=sequence):
            return {**losses(minibatch), "kl_approx": torch.tensor(next(sequence))}

        step = learner.optimizer.step
        learner.minibatches.losses = given_kl
        learner.optimizer.step = lambda *a, step=step, taken=taken, **k: (taken.append(1), step(*a, **k))[1]
        metrics = learner.learn(next(learner._batches))
        assert len(taken) == expected, (target, kls)
        assert all(np.isfinite(v) for v in metrics.values()) and "train/kl_approx" in metrics


def test_dual_clip_bounds_a_negative_advantage_s_term_by_c_times_it():
    """``clip_ppo_losses(dual_clip=3)`` by hand on 3 frames, log-ratios 100 (e^100 overflows float32),
    0 and -0.1, advantages -1, 2, -1 (standardised: -1, 2, -1 over sqrt(3)), clip 0.2: the first
    term is 3 x its advantage instead of -inf, the others ClipPPOLoss's; the gradient is finite. Without
    the bound the loss is inf."""
    from drone_torchrl.algorithms.ppo_fast import LOG_SQRT_2PI

    class Fixed(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.loc = torch.nn.Parameter(torch.zeros(3, 2))

        def forward(self, observation):
            return self.loc, torch.ones(3, 2)

    log_ratio = torch.tensor([100.0, 0.0, -0.1])
    minibatch = [
        torch.zeros(3, 6),  # observation
        torch.zeros(3, 2),  # the actions' pre-images: at the mean
        torch.zeros(3),  # log-determinant
        -2 * LOG_SQRT_2PI - log_ratio,  # log-probability when flown
        torch.tensor([[-1.0], [2.0], [-1.0]]),  # advantage
        torch.zeros(3, 1),  # value target
    ]
    policy, value = Fixed(), lambda observation: torch.zeros(3, 1)
    eps, coeff = torch.tensor(0.2), torch.tensor(0.5)
    bounded = ppo.clip_ppo_losses(policy, value, minibatch, eps, coeff, dual_clip=3.0)
    a = torch.tensor([-1.0, 2.0, -1.0]) / math.sqrt(3)
    expected = -(3 * a[0] + a[1] + math.exp(-0.1) * a[2]) / 3
    assert float(bounded["loss_objective"].detach()) == pytest.approx(float(expected), rel=1e-6)
    bounded["loss_objective"].backward()
    assert bool(torch.isfinite(policy.loc.grad).all())
    assert (
        float(ppo.clip_ppo_losses(policy, value, minibatch, eps, coeff)["loss_objective"].detach())
        == math.inf
    )


@pytest.mark.parametrize("backend", ["reference", "fast"])
def test_rollback_drop_puts_the_best_evaluations_state_back_once(tmp_path, monkeypatch, backend, capsys):
    """eval.rollback_drop: after an evaluation more than it below the best, the actor, critic and
    optimizer are the best evaluation's again (best.pt's), once per best; last.pt keeps that state
    so a continued run carries it on, and best.pt's own state is the best one when forked from."""
    seen = []  # each evaluation: its return, the best so far, and the actor's weights after it
    after_evaluation = OnPolicy.after_evaluation

    def spy(self, run, best_before):
        after_evaluation(self, run, best_before)
        weights = {k: v.clone() for k, v in self.actor_module.state_dict().items()}
        seen.append((run.last_eval_return, run.best_eval, self.returned_to_best, weights))

    monkeypatch.setattr(OnPolicy, "after_evaluation", spy)
    common = (
        "algo=ppo",
        "experiment=bounded",
        f"backend={backend}",
        "algo.num_envs=8",
        "algo.steps_per_batch=32",
        "algo.minibatch_size=64",
        "algo.epochs=2",
        "eval.every_episodes=8",
        "checkpoint.every_episodes=8",
        *QUIET,
    )
    run = tmp_path / "run"
    # Any evaluation below the best by more than 0.001 (return units) sends the run back.
    train(_cfg(*common, "algo.episodes=96", "eval.rollback_drop=0.001"), run)
    returns = [r for r, *_ in seen]
    assert len(seen) >= 8 and len(set(returns)) > 1  # the evaluations differ: else nothing to test
    said = capsys.readouterr().out.count("eval.rollback_drop=0.001 below the best")
    rollbacks = [i for i in range(1, len(seen)) if seen[i][2] and not seen[i - 1][2]]
    assert rollbacks and said == len(rollbacks)
    for i in rollbacks:
        best_at = max(j for j in range(i) if seen[j][0] == seen[i][1])  # the evaluation that set the best
        for key, value in seen[best_at][3].items():
            torch.testing.assert_close(seen[i][3][key], value, rtol=0, atol=0)
        # Once per best: a second drop below the same best does not send the run back again.
        assert all(seen[j][2] for j in range(i, len(seen)) if seen[j][1] == seen[i][1])
    last = load_checkpoint(run / "checkpoints" / "last.pt")
    best = load_checkpoint(run / "checkpoints" / "best.pt")
    kept = last["rollback"]["state"]
    assert kept["return"] == last["best_eval_return"] == best["best_eval_return"]
    for part in ("actor", "critic"):
        for key, value in best[part].items():
            torch.testing.assert_close(kept[part][key], value, rtol=0, atol=0)

    # A continued run goes on with last.pt's; best.pt (its evaluation's state not yet kept) holds it.
    learner = OnPolicy.__new__(OnPolicy)
    learner.rollback_drop = 0.001
    learner._load_best_state(last)
    assert learner.best_state is kept and learner.returned_to_best == last["rollback"]["returned"]
    learner._load_best_state(best)
    assert learner.best_state["return"] == best["best_eval_return"] and not learner.returned_to_best
    for key, value in best["optimizer"]["state"][0].items():  # a copy: Adam steps its state in place
        assert torch.equal(learner.best_state["optimizer"]["state"][0][key], value)
        assert learner.best_state["optimizer"]["state"][0][key] is not value
    learner._load_best_state({**best, "best_eval_return": -math.inf})  # a fork: no best yet
    assert learner.best_state["return"] == best["best_eval_return"]  # (unchanged by it)

    # Without it the same seed evaluates the same up to the first rollback, and otherwise after it.
    with_it = returns
    seen.clear()
    train(_cfg(*common, "algo.episodes=96"), tmp_path / "plain")
    first = rollbacks[0]
    assert [r for r, *_ in seen[: first + 1]] == with_it[: first + 1]
    assert [r for r, *_ in seen[first + 1 :]] != with_it[first + 1 :]
