"""The three-net policy of many agents at once: parameters stacked over a leading agent dim.

Each agent keeps its own :class:`~drone_torchrl.modules.ThreeNetPolicy` (its own leaves, so its
own optimizer); :class:`StackedThreeNet` stacks their weights and applies every agent's net to its
own observations with batched matrix products (``torch.baddbmm``), one kernel per layer whatever
the number of agents.
"""

from __future__ import annotations

import torch
from torch import nn
from torchrl.modules import TanhNormal

from drone_torchrl.modules.policy import ACTIVATIONS, ThreeNetPolicy

Layers = list[tuple[torch.Tensor, torch.Tensor]]


def _linears(net: ThreeNetPolicy) -> list[nn.Linear]:
    return [m for m in net.shared if isinstance(m, nn.Linear)] + [net.mean, net.std]


class StackedThreeNet(nn.Module):
    """Applies A :class:`ThreeNetPolicy` nets at once to ``[A, ..., 6]`` observations.

    The parameters stay the agents' own leaves; they are stacked on every call (with gradients
    for the loss) or once per rollout without (:meth:`stacked` under ``no_grad``).
    """

    def __init__(self, nets: list[ThreeNetPolicy], activation: str) -> None:
        super().__init__()
        shapes = {tuple(p.shape for p in net.parameters()) for net in nets}
        kinds = {tuple(type(m) for m in net.shared if not isinstance(m, nn.Linear)) for net in nets}
        if len(shapes) > 1 or len({net.min_std for net in nets}) > 1:
            raise ValueError("stacked nets must share hidden_sizes and min_std")
        if kinds != {(ACTIVATIONS[activation],) * (len(nets[0].shared) // 2)}:
            raise ValueError(f"stacked nets must all use activation={activation!r}")
        self.nets = nn.ModuleList(nets)
        self.activation = ACTIVATIONS[activation]()
        self.min_std = nets[0].min_std
        self.n_hidden = len(_linears(nets[0])) - 2

    def stacked(self) -> Layers:
        """``[(W^T [A, in, out], b [A, 1, out]), ...]`` for the hidden layers, then mean and std heads."""
        layers = zip(*(_linears(net) for net in self.nets), strict=True)
        return [
            (
                torch.stack([m.weight for m in group]).transpose(1, 2),
                torch.stack([m.bias for m in group]).unsqueeze(1),
            )
            for group in layers
        ]

    def apply_stacked(self, layers: Layers, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        shape = observation.shape
        h = observation.reshape(shape[0], -1, shape[-1])
        for weight, bias in layers[: self.n_hidden]:
            h = self.activation(torch.baddbmm(bias, h, weight))
        (w_mean, b_mean), (w_std, b_std) = layers[self.n_hidden :]
        loc = torch.baddbmm(b_mean, h, w_mean)
        scale = nn.functional.softplus(torch.baddbmm(b_std, h, w_std)) + self.min_std
        out_shape = (*shape[:-1], loc.shape[-1])
        return loc.reshape(out_shape), scale.reshape(out_shape)

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.apply_stacked(self.stacked(), observation)


class ActionSampler:
    """``action = f(loc + scale * noise)``: the actor's distribution, sampled with given noise.

    Drawing the noise outside lets each agent draw from its own generator; ``noise=None`` gives
    the deterministic action (the mean, or its squashed image, as ``ExplorationType.DETERMINISTIC``).
    """

    def __init__(self, distribution: str, max_thrust: float | None) -> None:
        self.squash = None
        if distribution == "tanh_normal":
            # TorchRL's own tanh + affine transform, so samples match what TanhNormal.log_prob inverts.
            probe = TanhNormal(torch.zeros(2), torch.ones(2), low=0.0, high=float(max_thrust), tanh_loc=False)
            self.squash = probe.transforms[0]

    def __call__(self, loc: torch.Tensor, scale: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        pre = loc if noise is None else loc + scale * noise
        return pre if self.squash is None else self.squash(pre)
