"""algo=sac: TorchRL's SACLoss, replay buffer and SoftUpdate on the fast engine's batches; its
checkpoints (the buffer as far as it is filled, the drones mid-episode) and resume."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torchrl.data import MultiStep
from torchrl.objectives.value import TD0Estimator

from drone_torchrl.algorithms.sac import FRAME_KEYS, n_step
from drone_torchrl.config import config_dir
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.io.episodes_csv import read_episodes
from drone_torchrl.training.jobs import prepare
from drone_torchrl.training.trainer import Trainer, train

# The slow test's margin: seed 0 went from a mean return of 33.0 (first 100 episodes) to 300.0 (last
# 100: every episode full length) on 2026-12-04, 9.1 times.
LEARNED_FACTOR = 3.0
QUIET = ["eval.video=false", "progress=false", "eval.episodes=2", "eval.every_episodes=0"]
# 8 drones x 8 steps a batch, 8 gradient steps on 32 frames: small enough for seconds.
SMALL = [
    "experiment=bounded",
    "algo=sac",
    "algo.num_envs=8",
    "algo.steps_per_batch=8",
    "algo.batch_size=32",
    "algo.updates_per_batch=8",
    *QUIET,
]


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def _stopped_after(cfg, run, updates: int) -> dict:
    """What a run stopped by a signal after ``updates`` updates leaves (the trainer saves every
    active run's checkpoint after the update in flight, then stops); its checkpoint."""
    trainer = Trainer([prepare(cfg, run)])
    for _ in range(updates):
        trainer.step([0])
    assert not trainer.runs[0].finished
    trainer.runs[0].save(trainer.learner.checkpoint_entries(0))
    trainer.close(quietly=True)
    return load_checkpoint(run / "checkpoints" / "last.pt")


def test_a_checkpoint_holds_the_buffer_only_as_far_as_it_is_filled(tmp_path):
    """5 batches of 8 x 8 = 64 frames: 320 frames of a 100,000-frame buffer are saved, each frame
    with the keys SAC samples (and the buffer's index); a buffer of 100 frames saves 100 and its
    write cursor, 320 mod 100."""
    big = _stopped_after(_cfg(*SMALL, "algo.episodes=100000", "algo.buffer_size=100000"), tmp_path / "big", 5)
    frames = big["replay_buffer"]["frames"]
    assert frames["observation"].shape == (320, 6) and frames["next"]["observation"].shape == (320, 6)
    assert frames["action"].shape == (320, 2) and frames["next"]["terminated"].shape == (320, 1)
    # The file holds 320 frames, not 100,000 (283 kB; 7.3 MB when the storage was saved whole).
    assert (tmp_path / "big" / "checkpoints" / "last.pt").stat().st_size < 400_000
    small = _stopped_after(
        _cfg(*SMALL, "algo.episodes=100000", "algo.buffer_size=100"), tmp_path / "small", 5
    )
    assert small["replay_buffer"]["frames"]["observation"].shape == (100, 6)
    assert small["replay_buffer"]["writer"]["_cursor"] == 320 % 100
    assert {k if isinstance(k, str) else "/".join(k) for k in FRAME_KEYS} <= {
        *frames,
        *(f"next/{k}" for k in frames["next"]),
    }


def test_a_resumed_run_equals_an_uninterrupted_one(tmp_path):
    """Stopped after 7 updates (its drones mid-episode, the buffer partly filled) and resumed, a run
    books the same episodes with the same returns and ends with the same weights, Q-networks,
    targets and temperature, to the bit, as the run that was never stopped."""
    common = [*SMALL, "algo.episodes=60", "algo.buffer_size=500"]  # the buffer wraps around too
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    train(_cfg(*common), whole)
    stopped = _stopped_after(_cfg(*common), cut, 7)
    assert stopped["drones"]["carried"] is not None
    assert 0 < stopped["episodes_done"] < 60
    assert (stopped["drones"]["episodes"][1] > 0).any()  # some drones were mid-episode
    train(_cfg(f"resume={cut}", "algo.episodes=60", "progress=false"))
    a, b = read_episodes(whole / "episodes.csv")[0], read_episodes(cut / "episodes.csv")[0]
    assert len(a["return"]) >= 60
    assert a["episode"].tolist() == b["episode"].tolist()
    np.testing.assert_array_equal(a["return"], b["return"])
    np.testing.assert_array_equal(a["length"], b["length"])
    wa, wb = (load_checkpoint(run / "checkpoints" / "last.pt") for run in (whole, cut))
    for entry in ("actor", "qvalue"):
        assert wa[entry].keys() == wb[entry].keys()
        assert all(torch.equal(wa[entry][k], wb[entry][k]) for k in wa[entry]), entry


def test_a_run_restarted_without_its_drones_differs(tmp_path):
    """The check above can fail: a resume that starts every drone afresh (as PPO's does) books other
    episodes than the uninterrupted run."""
    common = [*SMALL, "algo.episodes=40"]
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    train(_cfg(*common), whole)
    stopped = _stopped_after(_cfg(*common), cut, 5)
    from drone_torchrl.io.checkpoint import save_checkpoint

    stopped["drones"]["carried"] = None
    save_checkpoint(stopped, cut / "checkpoints" / "last.pt")
    train(_cfg(f"resume={cut}", "algo.episodes=40", "progress=false"))
    a, b = read_episodes(whole / "episodes.csv")[0], read_episodes(cut / "episodes.csv")[0]
    n = min(len(a["return"]), len(b["return"]))
    assert a["return"][:n].tolist() != b["return"][:n].tolist()


@pytest.mark.slow
def test_sac_learns_on_a_short_budget(tmp_path):
    """Seed 0, the YAML's settings, 600 episodes: the last 100 episodes' mean return is at least
    LEARNED_FACTOR times the first 100's (it crashes within about 30 steps at first)."""
    run = tmp_path / "run"
    train(_cfg("experiment=bounded", "algo=sac", "algo.episodes=600", *QUIET), run)
    returns = read_episodes(run / "episodes.csv")[0]["return"]
    first, last = returns[:100].mean(), returns[-100:].mean()
    print(f"first 100: {first:.1f}, last 100: {last:.1f}")
    assert last >= LEARNED_FACTOR * first, (first, last)


def _one_drone(rewards, terminated, truncated=None):
    """A ``[1, T]`` batch of one drone whose observation is its step index (to see which next
    observation a window ends on)."""
    steps = len(rewards)
    column = lambda values: torch.tensor(values).reshape(1, steps, 1)  # noqa: E731
    terminated = column(terminated)
    done = terminated | (column(truncated) if truncated is not None else False)
    obs = torch.arange(steps, dtype=torch.float32).reshape(1, steps, 1).expand(1, steps, 6)
    return TensorDict(
        {
            "observation": obs,
            "action": torch.zeros(1, steps, 2),
            "next": {
                "observation": obs + 1,
                "reward": column([float(r) for r in rewards]),
                "done": done,
                "terminated": terminated,
            },
        },
        batch_size=[1, steps],
    )


def test_an_n_step_window_with_a_crash_is_cut_there_and_not_bootstrapped():
    """gamma 0.5, 3-step windows; the drone crashes at step 2 (terminated), a new episode runs steps
    3-4 to the batch's end. By hand: step 0 sums 1 + 0.5 * 10 + 0.25 * 1 = 6.25 and ends on the crash
    (not bootstrapped); step 1: 10 + 0.5 * 1 = 10.5, the crash too; step 2: 1, the crash; step 3:
    10 + 0.5 * 1 = 10.5 over 2 steps, cut by the batch's end, bootstrapped from the observation after
    step 4 with 0.5^2. TorchRL's MultiStep alone leaves step 0's terminated False: its TD0 target
    would add the value after the crash."""
    batch = _one_drone([1, 10, 1, 10, 1], [False, False, True, False, False])
    raw = MultiStep(0.5, 3)(batch.clone())
    assert not raw.get(("next", "terminated"))[0, 0].item()  # the pitfall: the window's start's flag
    out = n_step(batch, 0.5, 3)
    torch.testing.assert_close(
        out.get(("next", "reward")).flatten(), torch.tensor([6.25, 10.5, 1.0, 10.5, 1.0])
    )
    assert out.get(("next", "terminated")).flatten().tolist() == [True, True, True, False, False]
    assert out.get("steps_to_next_obs").flatten().tolist() == [3, 2, 1, 2, 1]
    assert out.get(("next", "observation"))[0, :, 0].tolist() == [3.0, 3.0, 3.0, 5.0, 5.0]
    # TD0 (SACLoss's estimator) on these frames with a next value of 100 everywhere: the crash's
    # windows get their rewards alone, the others 0.5^steps x 100 on top.
    td0 = TD0Estimator(gamma=0.5, value_network=None)
    target = td0.value_estimate(out, next_value=torch.full((1, 5, 1), 100.0)).flatten()
    torch.testing.assert_close(target, torch.tensor([6.25, 10.5, 1.0, 10.5 + 25.0, 1.0 + 50.0]))


def test_a_step_limit_cut_inside_a_window_is_bootstrapped():
    """A window that ends on a truncation (the step limit, not a crash) bootstraps from the
    observation after it: step 0 sums 1 + 0.5 x 1 and is not terminated."""
    batch = _one_drone([1, 1, 1], [False, False, False], truncated=[False, True, False])
    out = n_step(batch, 0.5, 3)
    torch.testing.assert_close(out.get(("next", "reward")).flatten(), torch.tensor([1.5, 1.0, 1.0]))
    assert out.get(("next", "terminated")).flatten().tolist() == [False, False, False]
    assert out.get(("next", "done")).flatten().tolist() == [True, True, False]
    assert out.get("steps_to_next_obs").flatten().tolist() == [2, 1, 1]
