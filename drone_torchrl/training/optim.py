"""Adam and AdamW for a population: one update for every agent's stacked parameters at once.

``torch.optim.Adam`` takes one learning rate per parameter group ("Tensor lr must be 1-element"),
so N agents with N learning rates would need N optimizers and N Python calls per update. Adam is
element-wise, so here each hyper-parameter is a ``[N]`` tensor broadcast over the agent dim of
the stacked parameters, and the whole population steps in a fixed number of kernels. The
arithmetic follows ``torch.optim.Adam`` / ``AdamW`` (``foreach=False``, ``amsgrad=False``), which
the tests check agent by agent.

Gradient clipping is per agent too: :func:`clip_grad_norms` scales each agent's gradient by
``max_norm / (norm + 1e-6)`` when its norm exceeds ``max_norm``, as ``clip_grad_norm_`` does.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from tensordict import TensorDictBase

# torch.nn.utils.clip_grad_norm_ adds this to the norm before dividing.
CLIP_EPS = 1e-6


def _per_agent(values: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``[N]`` -> ``[N, 1, ..., 1]`` to broadcast over one stacked parameter."""
    return values.reshape(values.shape[0], *([1] * (like.ndim - 1)))


def grad_norms(params: TensorDictBase) -> torch.Tensor:
    """Each agent's gradient 2-norm over all its parameters: ``[N]`` (0 where there is no gradient)."""
    squares = [p.grad.pow(2).flatten(1).sum(1) for p in params.values(True, True) if p.grad is not None]
    if not squares:
        return torch.zeros(params.batch_size[0], device=params.device)
    return torch.stack(squares).sum(0).sqrt()


def clip_grad_norms(params: TensorDictBase, max_norm: float) -> torch.Tensor:
    """Clip each agent's gradient to ``max_norm`` (``inf``: no clipping); returns the norms before."""
    norms = grad_norms(params)
    if math.isfinite(max_norm):
        coef = (max_norm / (norms + CLIP_EPS)).clamp(max=1.0)
        for p in params.values(True, True):
            if p.grad is not None:
                p.grad.mul_(_per_agent(coef, p.grad))
    return norms


class PopulationAdam:
    """Adam (``decoupled_weight_decay=False``) or AdamW (``True``) over ``[N, ...]`` parameters.

    Args:
        params: the stacked parameters (leaves with a leading agent dim ``N``).
        lr, weight_decay: ``[N]`` tensors (or floats), one value per agent.
        betas, eps: shared by all agents.
    """

    def __init__(
        self,
        params: TensorDictBase,
        lr: torch.Tensor | float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        weight_decay: torch.Tensor | float = 0.0,
        decoupled_weight_decay: bool = False,
    ) -> None:
        n = params.batch_size[0]
        device = next(iter(params.values(True, True))).device
        self.params = params
        self.lr = torch.as_tensor(lr, dtype=torch.float64, device=device).expand(n).clone()
        self.weight_decay = (
            torch.as_tensor(weight_decay, dtype=torch.float64, device=device).expand(n).clone()
        )
        self.betas = betas
        self.eps = eps
        self.decoupled = decoupled_weight_decay
        # Known once, so the step does not ask the device (a host sync) for every parameter.
        self._coupled_decay = not decoupled_weight_decay and bool(self.weight_decay.any())
        self.steps = torch.zeros(n, dtype=torch.float64, device=device)
        self.exp_avg = params.detach().clone().zero_()
        self.exp_avg_sq = params.detach().clone().zero_()

    def zero_grad(self) -> None:
        for p in self.params.values(True, True):
            p.grad = None

    @torch.no_grad()
    def step(self, agents: torch.Tensor | None = None) -> None:
        """One Adam step of the agents where ``agents`` (``[N]`` bool) is true (default: all)."""
        beta1, beta2 = self.betas
        if agents is None:
            self.steps += 1
            lr = self.lr
        else:
            self.steps += agents.to(self.steps.dtype)
            lr = torch.where(agents, self.lr, 0.0)  # agents that do not step keep their parameters
        # Per-agent scalars in float64, as torch.optim.Adam computes them in Python floats.
        steps = self.steps.clamp(min=1.0)
        step_size = (lr / (1 - beta1**steps)).float()
        bias2_sqrt = (1 - beta2**steps).sqrt().float()
        decay = (lr * self.weight_decay).float()
        for key, param in self.params.items(True, True):
            grad = param.grad
            if grad is None:
                continue
            if self.decoupled:
                param.mul_(1 - _per_agent(decay, param))
            elif self._coupled_decay:
                grad = grad + _per_agent(self.weight_decay.float(), param) * param
            exp_avg, exp_avg_sq = self.exp_avg.get(key), self.exp_avg_sq.get(key)
            new_avg = exp_avg.lerp(grad, 1 - beta1)
            new_sq = exp_avg_sq.mul(beta2).addcmul_(grad, grad, value=1 - beta2)
            if agents is not None:
                mask = _per_agent(agents, param)
                new_avg, new_sq = torch.where(mask, new_avg, exp_avg), torch.where(mask, new_sq, exp_avg_sq)
            exp_avg.copy_(new_avg)
            exp_avg_sq.copy_(new_sq)
            denom = (exp_avg_sq.sqrt() / _per_agent(bias2_sqrt, param)).add_(self.eps)
            param.sub_(_per_agent(step_size, param) * (exp_avg / denom))

    # ------------------------------------------------------------------ one agent's state
    def agent_state(self, agent: int, names: list[str]) -> dict[str, Any]:
        """Agent ``agent``'s state in ``torch.optim.Adam.state_dict()``'s layout (params in ``names`` order)."""
        keys = [tuple(name.split(".")) for name in names]
        state = {
            i: {
                "step": self.steps[agent].detach().to(torch.float32).cpu(),
                "exp_avg": self.exp_avg.get(key)[agent].clone(),
                "exp_avg_sq": self.exp_avg_sq.get(key)[agent].clone(),
            }
            for i, key in enumerate(keys)
        }
        group = {
            "lr": float(self.lr[agent]),
            "betas": self.betas,
            "eps": self.eps,
            "weight_decay": float(self.weight_decay[agent]),
            "amsgrad": False,
            "maximize": False,
            "foreach": None,
            "capturable": False,
            "differentiable": False,
            "fused": None,
            "decoupled_weight_decay": self.decoupled,
            "params": list(range(len(keys))),
        }
        return {"state": state, "param_groups": [group]}

    def load_agent_state(self, agent: int, names: list[str], state: dict[str, Any]) -> None:
        """Load a ``torch.optim.Adam`` (or this class's) state dict of one agent; a fresh optimizer
        state (no ``state`` entries yet) leaves the agent's moments at zero."""
        keys = [tuple(name.split(".")) for name in names]
        entries = state["state"]
        for i, key in enumerate(keys):
            if i not in entries:
                continue
            self.exp_avg.get(key)[agent] = entries[i]["exp_avg"]
            self.exp_avg_sq.get(key)[agent] = entries[i]["exp_avg_sq"]
            self.steps[agent] = float(entries[i]["step"])
