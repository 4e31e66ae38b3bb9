"""The population's Adam/AdamW and gradient clipping against torch.optim and clip_grad_norm_, agent by agent."""

import pytest
import torch
from tensordict import TensorDict

from drone_torchrl.modules import StackedThreeNet, ThreeNetPolicy
from drone_torchrl.training.optim import Adam, adam_state, clip_grad_norms

LRS = [1e-3, 3e-4, 5e-2]
DECAYS = [0.0, 0.01, 0.1]


def _loss(net_params_out: tuple[torch.Tensor, torch.Tensor], target: torch.Tensor) -> torch.Tensor:
    loc, scale = net_params_out
    return ((loc - target) ** 2).sum() + (scale.log() ** 2).sum()


@pytest.mark.parametrize("path", ["fused", "masked"])
@pytest.mark.parametrize("decoupled", [False, True])
@pytest.mark.parametrize("max_norm", [float("inf"), 0.5])
def test_population_adam_equals_torch_per_agent(decoupled, max_norm, path):
    torch.manual_seed(0)
    nets = [ThreeNetPolicy([8, 8]) for _ in LRS]
    reference = [ThreeNetPolicy([8, 8]) for _ in LRS]
    for ref, net in zip(reference, nets, strict=True):
        ref.load_state_dict(net.state_dict())
    stacked = StackedThreeNet(nets, "tanh")
    flat = stacked.flat
    state = TensorDict(
        {"params": flat, **adam_state(flat, torch.tensor(LRS, dtype=torch.float64), torch.tensor(DECAYS))},
        batch_size=[len(LRS)],
    )
    adam = Adam(decoupled_weight_decay=decoupled, coupled_decay=not decoupled)
    step = adam.step if path == "fused" else adam._masked_step
    cls = torch.optim.AdamW if decoupled else torch.optim.Adam
    ref_optims = [
        cls(r.parameters(), lr=lr, weight_decay=wd, foreach=False)
        for r, lr, wd in zip(reference, LRS, DECAYS, strict=True)
    ]
    obs, target = torch.randn(len(LRS), 5, 6), torch.randn(len(LRS), 5, 2)
    for i in range(6):
        # Agent 1 sits out every other step: its parameters and moments must not move then.
        active = torch.tensor([True, i % 2 == 0, True])
        flat.grad = None
        out = stacked(obs)
        sum(_loss((out[0][k], out[1][k]), target[k]) for k in range(len(LRS))).backward()
        norms = clip_grad_norms(flat.grad, max_norm)
        step(state, flat.grad, active)
        for k, (ref, ref_optim) in enumerate(zip(reference, ref_optims, strict=True)):
            ref_optim.zero_grad()
            _loss(ref(obs[k]), target[k]).backward()
            ref_norm = torch.nn.utils.clip_grad_norm_(ref.parameters(), max_norm)
            torch.testing.assert_close(norms[k], ref_norm, rtol=1e-5, atol=1e-6)
            if bool(active[k]):
                ref_optim.step()
    params = stacked.params
    for k, ref in enumerate(reference):
        for name, value in ref.named_parameters():
            torch.testing.assert_close(params.get(tuple(name.split(".")))[k], value, rtol=1e-5, atol=1e-7)
    # The state of one agent round-trips through torch.optim.Adam's state-dict layout.
    names = [n for n, _ in reference[0].named_parameters()]
    saved = adam.agent_state(state, 1, names, stacked.views)
    assert float(saved["state"][0]["step"]) == 3.0  # agent 1 stepped on steps 0, 2 and 4
    ref_state = ref_optims[1].state_dict()
    for i in range(len(names)):
        torch.testing.assert_close(
            saved["state"][i]["exp_avg"], ref_state["state"][i]["exp_avg"], rtol=1e-5, atol=1e-8
        )
    # ... and loads back into a fresh state.
    fresh = state.clone()
    fresh["exp_avg"].zero_()
    Adam.load_agent_state(fresh, 1, names, stacked.views, ref_state)
    torch.testing.assert_close(fresh["exp_avg"][1], state["exp_avg"][1], rtol=1e-5, atol=1e-8)


def test_a_learning_rate_changed_between_steps_is_the_one_the_next_step_uses():
    """Population-based training rewrites an agent's lr (and weight decay) in the state between
    steps: the next fused step takes the new values, as a fresh optimizer on the same state does
    (the agents' grouping by lr was made once per run, so a changed lr went unused)."""
    torch.manual_seed(0)
    params = torch.randn(3, 5)
    grads = [torch.randn(3, 5) for _ in range(2)]
    state = TensorDict(
        {"params": params, **adam_state(params, torch.tensor(LRS, dtype=torch.float64), torch.zeros(3))},
        batch_size=[3],
    )
    adam = Adam()
    adam.step(state, grads[0].clone())
    state["lr"][0] = 0.5
    state["weight_decay"][2] = 0.1
    fresh_state = state.clone()
    adam.step(state, grads[1].clone())
    Adam(coupled_decay=True).step(fresh_state, grads[1].clone())
    assert torch.equal(state["params"], fresh_state["params"])
