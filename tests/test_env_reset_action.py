"""Resets must not write into the caller's action tensor (regression test).

With unbounded thrust ``DroneEnv._step`` keeps the caller's action tensor itself for the render
overlay; the resets used to zero it in place, so a rollout recorded action 0 on every step that
ended an episode.
"""

from __future__ import annotations

import pytest
import torch

from drone_torchrl.envs import DroneEnv

SINK, HOVER = 0.1, 0.5  # thrust fractions: below hover the drone hits the floor within a few steps
STEPS = 12
# batch [] resets fully; in batch [3] the hovering middle row stays alive, so the resets are partial.
ACTIONS = {
    (): torch.tensor([SINK, SINK]),
    (3,): torch.tensor([[SINK, SINK], [HOVER, HOVER], [SINK, SINK]]),
}


@pytest.mark.parametrize("batch_size", list(ACTIONS))
@pytest.mark.parametrize("max_thrust", [None, 1.0])
def test_resets_do_not_modify_actions(batch_size: tuple[int, ...], max_thrust: float | None) -> None:
    env = DroneEnv(batch_size=list(batch_size), max_thrust=max_thrust)
    env.set_seed(0)
    action = ACTIONS[batch_size].clone()

    def policy(td):
        td["action"] = action
        return td

    with torch.no_grad():
        td = env.rollout(STEPS, policy, break_when_any_done=False)
    assert td["next", "done"].any(), "the rollout should contain a reset"
    torch.testing.assert_close(action, ACTIONS[batch_size])
    torch.testing.assert_close(td["action"], ACTIONS[batch_size].unsqueeze(-2).expand_as(td["action"]))
