"""Adam and AdamW for a population: one update for every agent's stacked parameters at once.

``torch.optim.Adam`` takes one learning rate per parameter group ("Tensor lr must be 1-element"),
so N agents with N learning rates would need N optimizers and N Python calls per update. Adam is
element-wise, so here each hyper-parameter is a ``[N]`` tensor broadcast over the agent dim of
the stacked parameters, and the whole population steps in a fixed number of kernels. The
arithmetic follows ``torch.optim.Adam`` / ``AdamW`` (``foreach=False``, ``amsgrad=False``), which
the tests check agent by agent.

Parameters, gradients and moments are ``[N, P]`` tensors (every agent's parameters in one row,
see :class:`~drone_torchrl.modules.stacked.StackedThreeNet`), so a step is about twenty kernels whatever
N and the depth of the network. Gradient clipping is per agent too: :func:`clip_grad_norms`
scales each agent's gradient by ``max_norm / (norm + 1e-6)`` when its norm exceeds ``max_norm``,
as ``clip_grad_norm_`` does.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase

from drone_torchrl.compat import fused_adam

# torch.nn.utils.clip_grad_norm_ adds this to the norm before dividing.
CLIP_EPS = 1e-6


def clip_grad_norms(grad: torch.Tensor, max_norm: float) -> torch.Tensor:
    """Clip each agent's row of ``grad`` ``[N, P]`` in place to ``max_norm``; returns the norms before.

    ``max_norm=inf`` clips nothing.
    """
    norms = grad.pow(2).sum(1).sqrt()  # each agent's 2-norm over all its parameters
    if max_norm != float("inf"):
        grad.mul_((max_norm / (norms + CLIP_EPS)).clamp(max=1.0).unsqueeze(1))
    return norms


def adam_state(params: torch.Tensor, lr: torch.Tensor, weight_decay: torch.Tensor) -> dict[str, torch.Tensor]:
    """Fresh Adam entries of a population's state: zero moments and step counts, per-agent hyper-parameters."""
    n, device = params.shape[0], params.device
    return {
        "exp_avg": torch.zeros_like(params, requires_grad=False),
        "exp_avg_sq": torch.zeros_like(params, requires_grad=False),
        # float32, as torch.optim.Adam keeps its step counts (exact to 2**24 steps).
        "adam_steps": torch.zeros(n, dtype=torch.float32, device=device),
        "lr": torch.as_tensor(lr, dtype=torch.float64, device=device).expand(n).clone(),
        "weight_decay": torch.as_tensor(weight_decay, dtype=torch.float64, device=device).expand(n).clone(),
    }


@dataclass(eq=False)
class Adam:
    """Adam or AdamW over the ``[N, P]`` ``"params"`` of a population's state.

    The state also holds ``"exp_avg"``, ``"exp_avg_sq"``, ``"adam_steps"``, per-agent ``"lr"`` and
    ``"weight_decay"`` (:func:`adam_state`).

    Args:
        betas: Adam's moment decays, shared by all agents.
        eps: Adam's denominator term, shared by all agents.
        decoupled_weight_decay: AdamW's decoupled weight decay (False: Adam's coupled one).
        coupled_decay: whether any agent has a (coupled) weight decay, known at construction so
            that the step does not ask the device (a host sync).
    """

    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = 1e-8
    decoupled_weight_decay: bool = False
    coupled_decay: bool = False
    _rows: tuple | None = field(default=None, init=False, repr=False)

    @torch.no_grad()
    def step(self, state: TensorDictBase, grad: torch.Tensor, agents: torch.Tensor | None = None) -> None:
        """One step of the agents where ``agents`` (``[N]`` bool) is true (default: all), in place.

        On the CPU this is PyTorch's own fused Adam kernel (what ``torch.optim.Adam(fused=True)``
        runs), once per group of agents that share a learning rate and weight decay, each agent's
        row its own parameter with its own step count; elsewhere the arithmetic below, masked, so
        that it never asks the device which agents step (a host sync).
        """
        if grad.device.type == "cpu":
            self._fused_step(state, grad, agents)
        else:
            self._masked_step(state, grad, agents)

    @torch.no_grad()
    def _masked_step(self, state: TensorDictBase, grad: torch.Tensor, agents: torch.Tensor | None) -> None:
        beta1, beta2 = self.betas
        param, exp_avg, exp_avg_sq = state["params"], state["exp_avg"], state["exp_avg_sq"]
        steps, lr, weight_decay = state["adam_steps"], state["lr"], state["weight_decay"]
        if agents is None:
            steps += 1
        else:
            steps += agents.to(steps.dtype)
            lr = torch.where(agents, lr, 0.0)  # agents that do not step keep their parameters
        # Per-agent scalars in float64, as torch.optim.Adam computes them in Python floats.
        t = steps.to(torch.float64).clamp(min=1.0)
        step_size = (lr / (1 - beta1**t)).to(param.dtype).unsqueeze(1)
        bias2_sqrt = (1 - beta2**t).sqrt().to(param.dtype).unsqueeze(1)
        if self.decoupled_weight_decay:
            param.mul_(1 - (lr * weight_decay).to(param.dtype).unsqueeze(1))
        elif self.coupled_decay:
            grad = grad + weight_decay.to(param.dtype).unsqueeze(1) * param
        new_avg = exp_avg.lerp(grad, 1 - beta1)
        new_sq = exp_avg_sq.mul(beta2).addcmul_(grad, grad, value=1 - beta2)
        if agents is not None:
            mask = agents.unsqueeze(1)
            new_avg = torch.where(mask, new_avg, exp_avg)
            new_sq = torch.where(mask, new_sq, exp_avg_sq)
        exp_avg.copy_(new_avg)
        exp_avg_sq.copy_(new_sq)
        denom = (exp_avg_sq.sqrt() / bias2_sqrt).add_(self.eps)
        param.sub_(step_size * (exp_avg / denom))

    def _fused_step(self, state: TensorDictBase, grad: torch.Tensor, agents: torch.Tensor | None) -> None:
        params, lr, decay = state["params"], state["lr"], state["weight_decay"]
        if (
            self._rows is None
            or self._rows[0] is not params
            or not (torch.equal(self._rows[4], lr) and torch.equal(self._rows[5], decay))
        ):
            # Row views of the state's tensors, and the agents grouped by learning rate and weight
            # decay: made again only when those change (population-based training changes them).
            steps = state["adam_steps"]
            columns = [t.unbind(0) for t in (params, state["exp_avg"], state["exp_avg_sq"], steps)]
            groups: dict[tuple[float, float], list[int]] = {}
            for i, key in enumerate(zip(lr.tolist(), decay.tolist(), strict=True)):
                groups.setdefault(key, []).append(i)
            self._rows = (params, steps, columns, groups, lr.clone(), decay.clone())
        _, steps, columns, groups, _, _ = self._rows
        if agents is None:
            steps += 1
            chosen = None
        else:
            steps += agents
            chosen = agents.tolist()
        grads = grad.unbind(0)
        kernel = fused_adam(self.decoupled_weight_decay)
        for (lr, decay), members in groups.items():
            members = members if chosen is None else [i for i in members if chosen[i]]
            if not members:
                continue
            param, exp_avg, exp_avg_sq, step = ([column[i] for i in members] for column in columns)
            kernel(
                param, [grads[i] for i in members], exp_avg, exp_avg_sq, [], step,
                lr=lr, beta1=self.betas[0], beta2=self.betas[1], weight_decay=decay, eps=self.eps,
                amsgrad=False, maximize=False,
            )  # fmt: skip

    # ------------------------------------------------------------------ one agent's state
    def agent_state(
        self,
        state: TensorDictBase,
        agent: int,
        names: list[str],
        views: Callable[[torch.Tensor], TensorDictBase],
    ) -> dict[str, Any]:
        """Agent ``agent``'s optimizer state in ``torch.optim.Adam.state_dict()``'s layout.

        Params are in ``names`` order; ``views`` splits an ``[N, P]`` tensor into named parameters.
        """
        keys = [tuple(name.split(".")) for name in names]
        exp_avg, exp_avg_sq = views(state["exp_avg"]), views(state["exp_avg_sq"])
        step = state["adam_steps"][agent].detach().to(torch.float32).cpu()
        entries = {
            i: {
                "step": step.clone(),
                "exp_avg": exp_avg.get(key)[agent].clone(),
                "exp_avg_sq": exp_avg_sq.get(key)[agent].clone(),
            }
            for i, key in enumerate(keys)
        }
        # torch.optim.Adam's own param group of these values: its layout and its defaults.
        group = torch.optim.Adam(
            [torch.zeros(0, requires_grad=True) for _ in keys],
            lr=float(state["lr"][agent]),
            betas=self.betas,
            eps=self.eps,
            weight_decay=float(state["weight_decay"][agent]),
            decoupled_weight_decay=self.decoupled_weight_decay,
        ).state_dict()["param_groups"][0]
        return {"state": entries, "param_groups": [group]}

    @staticmethod
    @torch.no_grad()
    def load_agent_state(
        state: TensorDictBase,
        agent: int,
        names: list[str],
        views: Callable[[torch.Tensor], TensorDictBase],
        saved: dict[str, Any],
    ) -> None:
        """Load a ``torch.optim.Adam`` (or :meth:`agent_state`) state dict into agent ``agent``.

        A fresh optimizer state (no ``state`` entries yet) leaves the agent's moments at zero.
        """
        keys = [tuple(name.split(".")) for name in names]
        exp_avg, exp_avg_sq = views(state["exp_avg"]), views(state["exp_avg_sq"])
        entries = saved["state"]
        for i, key in enumerate(keys):
            if i not in entries:
                continue
            exp_avg.get(key)[agent] = entries[i]["exp_avg"]
            exp_avg_sq.get(key)[agent] = entries[i]["exp_avg_sq"]
            state["adam_steps"][agent] = float(entries[i]["step"])
