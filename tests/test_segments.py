"""backend=fast: the on-policy batches the fast engine flies
(drone_torchrl/training/segments.py) are the TorchRL collector's: the env's physics on every frame,
auto-reset, truncation at env.max_steps, episodes carried across batches."""

from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir

from drone_torchrl.config import config_dir, env_kwargs, physics_params, validate
from drone_torchrl.envs import dynamics
from drone_torchrl.episodes import EpisodeTracker
from drone_torchrl.evaluation import evaluate
from drone_torchrl.modules.factory import build_actor, build_policy
from drone_torchrl.modules.stacked import ActionSampler
from drone_torchrl.training.segments import FusedSegments

MAX_STEPS = 40


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose(
            "config",
            overrides=[
                "algo=ppo",
                "experiment=bounded",
                "backend=fast",
                "algo.num_envs=16",
                "algo.steps_per_batch=32",
                f"env.max_steps={MAX_STEPS}",
                *overrides,
            ],
        )


def _batches(cfg, n: int):
    torch.manual_seed(cfg.seed)
    net = build_policy(cfg, cfg.seed)
    segments = FusedSegments(cfg, build_actor(cfg, net, return_log_prob=True), net)
    return [next(segments) for _ in range(n)], segments


def test_every_frame_is_one_step_of_the_dynamics_with_auto_reset():
    """Each frame is dynamics.step of its observation and action; a drone goes on from where its
    last frame left it (across batches too) unless that frame ended its episode: then it starts on
    the floor at step 0. Episodes end by a crash (terminated) or at env.max_steps (truncated)."""
    cfg = _cfg()
    params = physics_params(env_kwargs(cfg))
    batches, _ = _batches(cfg, 4)
    whole = torch.cat(batches, dim=1)  # [16 drones, 4 x 32 steps]
    obs, action = whole["observation"], whole["action"]
    state, reward, cause = dynamics.step(obs, dynamics.clamp_action(action, cfg.env.max_thrust), params)
    following = whole["next"]
    torch.testing.assert_close(following["observation"], state, atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(following["reward"].squeeze(-1), reward)
    assert torch.equal(following["termination_cause"].squeeze(-1), cause)
    terminated = following["terminated"].squeeze(-1)
    truncated = following["truncated"].squeeze(-1)
    steps = whole["step_count"].squeeze(-1)
    assert torch.equal(terminated, cause != int(dynamics.TerminationCause.NONE))
    assert torch.equal(truncated, (steps + 1 == MAX_STEPS) & ~terminated)
    assert torch.equal(following["done"].squeeze(-1), terminated | truncated)
    assert bool((action >= 0).all()) and bool((action <= cfg.env.max_thrust).all())
    # Both ways to end an episode happen here, and some episodes straddle a batch boundary.
    assert int(terminated.sum()) >= 3 and int(truncated.sum()) >= 3
    done = following["done"].squeeze(-1)[:, :-1]
    goes_on = ~done
    assert torch.equal(obs[:, 1:][goes_on], following["observation"][:, :-1][goes_on])
    assert torch.equal(steps[:, 1:][goes_on], steps[:, :-1][goes_on] + 1)
    fresh = obs[:, 1:][done]  # a new episode on the floor: x and alpha within 0.01, at rest
    assert len(fresh) >= 6 and bool((steps[:, 1:][done] == 0).all())
    assert bool((fresh[:, 1] == params.z_min).all()) and bool((fresh[:, [0, 4]].abs() <= 0.01).all())
    assert bool((fresh[:, [2, 3, 5]] == 0).all())
    assert bool((steps[:, 0] == 0).all())  # the first batch starts every drone's first episode


def _noise(segments: FusedSegments, batch) -> torch.Tensor:
    """The standard normals behind each action under the net's current weights: the TanhNormal
    head's squash inverted, centred by its loc and scaled by its std."""
    loc, scale = segments.net(batch["observation"])
    squash = ActionSampler("tanh_normal", segments.cfg.env.max_thrust).squash
    z = (squash.inv(batch["action"]) - loc) / scale
    return z[z.isfinite()]


def test_actions_are_draws_of_the_current_policy_and_log_probs_are_its_density():
    """What PPO's ratio needs: each action is loc + std x N(0, 1) squashed, for the net's weights
    at the time of the batch (the learner changes them between batches), and the stored
    log-probability is the actor's density of that action."""
    cfg = _cfg()
    torch.manual_seed(cfg.seed)
    net = build_policy(cfg, cfg.seed)
    segments = FusedSegments(cfg, build_actor(cfg, net, return_log_prob=True), net)
    for change in (0.0, 0.3):  # the second batch flies a policy with a higher mean command
        with torch.no_grad():
            net.mean.bias += change
        batch = next(segments)
        z = _noise(segments, batch)
        assert z.numel() >= 0.95 * batch["action"].numel()  # a few saturated commands cannot be inverted
        assert abs(float(z.mean())) < 0.1 and abs(float(z.std()) - 1) < 0.1, (z.mean(), z.std())
        dist = segments.actor.get_dist(batch.select("observation"))
        stored = batch[segments.log_prob_key]
        torch.testing.assert_close(stored, dist.log_prob(batch["action"]))
        assert stored.shape == (16, 32) and bool(stored.isfinite().all())


def test_the_tracker_books_each_episode_once_with_its_return():
    """EpisodeTracker over the batches books every finished episode; their returns add up to the
    rewards of the frames before the last episode end of each drone."""
    cfg = _cfg()
    batches, _ = _batches(cfg, 3)
    tracker = EpisodeTracker(16)
    booked = []
    for batch in batches:
        booked += tracker.update(batch)["return"]
    whole = torch.cat(batches, dim=1)
    done = whole["next", "done"].squeeze(-1)
    reward = whole["next", "reward"].squeeze(-1)
    last_end = torch.where(done.any(-1), done.shape[-1] - 1 - done.flip(-1).int().argmax(-1), -1)
    before = torch.arange(done.shape[-1]) <= last_end.unsqueeze(-1)
    assert len(booked) == int(done.sum())
    assert sum(booked) == pytest.approx(float(reward[before].sum()), rel=1e-6)


def test_fast_batches_fly_the_disturbed_drone_with_what_the_policy_saw():
    """Under env.disturbance.* the batches hold the observation the policy saw: with
    observed_actions=2, a drone that goes on from step j sees at j + 1 the command it issued at j
    first among its past commands, and a new episode starts with none (zeros)."""
    cfg = _cfg("disturbance=mild", "env.disturbance.observed_actions=2", "algo.minibatch_size=256")
    validate(cfg)
    (batch,), _ = _batches(cfg, 1)
    obs, action = batch["observation"], batch["action"]
    assert obs.shape == (16, 32, 10)
    done = batch["next", "done"].squeeze(-1)
    going_on = ~done[:, :-1]
    torch.testing.assert_close(obs[:, 1:, 6:8][going_on], action[:, :-1][going_on])
    fresh = batch["step_count"].squeeze(-1) == 0
    assert bool(fresh.any()) and bool((obs[fresh][:, 6:] == 0).all())
    assert bool(done.any())  # some episodes end inside the batch


def test_evaluations_fly_the_net_as_it_stands_on_the_kernel_as_the_reference_does():
    """backend=fast's evaluations: the kernel flies the evaluator's start states with the net's weights
    of the moment, and its episodes are the reference's (TorchRL's env and the actor) to float rounding."""
    cfg = _cfg("env.max_steps=300", "env.reset_mode=air")  # starts all over the domain: varied episodes
    net = build_policy(cfg, cfg.seed)
    actor = build_actor(cfg, net)
    segments = FusedSegments(cfg, build_actor(cfg, net, return_log_prob=True), net)
    torch.manual_seed(1)
    with torch.no_grad():  # weights the segments have not seen: a stale copy would fly other episodes
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    kwargs = env_kwargs(cfg)
    kernel, _ = evaluate(segments.eval_policy(), kwargs, 20, 12345, agents=1)
    reference, _ = evaluate(actor, kwargs, 20, 12345)
    assert len(set(reference["length"].tolist())) > 3  # episodes of many lengths: the test sees steps
    torch.testing.assert_close(kernel["length"][0], reference["length"])
    torch.testing.assert_close(kernel["return"][0], reference["return"], rtol=0, atol=1e-3)
