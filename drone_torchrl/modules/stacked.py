"""The three-net policy of many agents at once: one set of parameters stacked over a leading agent dim.

:class:`StackedThreeNet` holds N agents' :class:`~drone_torchrl.modules.policy.ThreeNetPolicy` weights as
one ``[N, P]`` parameter (:attr:`~StackedThreeNet.flat`: each agent's weights and biases one after
the other, in ``named_parameters()`` order), so an optimizer step, a clip, a finite check or a C++
kernel call is one operation whatever N and the depth are. :attr:`~StackedThreeNet.params` views
the same storage as a ``TensorDict`` of ``[N, ...]`` leaves keyed like the net's own parameters
(``("shared", "0", "weight")`` for ``shared.0.weight``), as ``TensorDict.from_modules`` and TorchRL's
``MultiAgentMLP`` hold theirs. The PyTorch forward applies every agent's net to its own
observations with batched matrix products (``torch.baddbmm``), one kernel per layer; the fast
engine's C++ kernels (:mod:`drone_torchrl.kernels`) read ``flat`` directly.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.modules import TanhNormal

from drone_torchrl.modules.policy import ACTIVATIONS, ThreeNetPolicy, shift_distribution


class StackedThreeNet(nn.Module):
    """N :class:`~.policy.ThreeNetPolicy` nets with stacked parameters, applied to ``[N, ..., D]`` at once.

    Args:
        nets: the architecture and each agent's initial weights (copied; the nets themselves are
            not used afterwards).
        activation: the hidden layers' activation (a key of ``ACTIVATIONS``).
        flat: every agent's initial weights ``[N, P]``, laid out as ``nets[0]``'s (then ``nets`` is
            one net: the architecture), for populations too large to build a module per agent.
    """

    def __init__(self, nets: list[ThreeNetPolicy], activation: str, flat: torch.Tensor | None = None) -> None:
        super().__init__()
        shapes = {tuple(p.shape for p in net.parameters()) for net in nets}
        kinds = {tuple(type(m) for m in net.shared if not isinstance(m, nn.Linear)) for net in nets}
        if len(shapes) > 1 or len({(net.min_std, net.distribution_eps) for net in nets}) > 1:
            raise ValueError("stacked nets must share hidden_sizes, min_std and distribution_eps")
        if kinds != {(ACTIVATIONS[activation],) * (len(nets[0].shared) // 2)}:
            raise ValueError(f"stacked nets must all use activation={activation!r}")
        first = nets[0]
        self.names = [name for name, _ in first.named_parameters()]
        self.shapes = [p.shape for p in first.parameters()]
        if flat is None:
            flat = torch.stack(
                [torch.cat([p.detach().reshape(-1) for p in net.parameters()]) for net in nets]
            )
        #: Every agent's weights and biases ``[N, P]``, one agent per row, in ``nets[0]``'s parameter order.
        self.flat = nn.Parameter(flat)
        self.activation_name = activation
        self.activation = ACTIVATIONS[activation]()
        self.min_std = first.min_std
        self.distribution_eps = first.distribution_eps
        self.hidden = [f"shared.{i}" for i, m in enumerate(first.shared) if isinstance(m, nn.Linear)]
        self.hidden_sizes = [m.out_features for m in first.shared if isinstance(m, nn.Linear)]

    def __len__(self) -> int:
        return self.flat.shape[0]

    def views(self, flat: torch.Tensor) -> TensorDict:
        """``flat`` (``[N, P]``, or anything laid out like it: a gradient, Adam's moments) as named ``[N, ...]`` views."""
        leaves, start = {}, 0
        for name, shape in zip(self.names, self.shapes, strict=True):
            size = math.prod(shape)
            leaves[tuple(name.split("."))] = flat[:, start : start + size].unflatten(1, shape)
            start += size
        return TensorDict(leaves, batch_size=flat.shape[:1])

    @property
    def params(self) -> TensorDict:
        """:attr:`flat` as named ``[N, ...]`` views, one per parameter of the single net."""
        return self.views(self.flat)

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Every agent's action mean and std ``[N, ..., A]`` for its observations ``[N, ..., D]``."""
        params, shape = self.params, observation.shape

        def linear(name: str, x: torch.Tensor) -> torch.Tensor:  # every agent's layer: x W^T + b
            key = tuple(name.split("."))
            weight, bias = params.get((*key, "weight")), params.get((*key, "bias"))
            return torch.baddbmm(bias.unsqueeze(1), x, weight.transpose(1, 2))

        h = observation.reshape(shape[0], -1, shape[-1])
        for name in self.hidden:
            h = self.activation(linear(name, h))
        loc = linear("mean", h)
        scale = nn.functional.softplus(linear("std", h)) + self.min_std
        loc, scale = shift_distribution(loc, scale, self.distribution_eps)
        out_shape = (*shape[:-1], loc.shape[-1])
        return loc.reshape(out_shape), scale.reshape(out_shape)

    # ------------------------------------------------------------------ one agent
    def agent_state_dict(self, agent: int) -> dict[str, torch.Tensor]:
        """Agent ``agent``'s weights as a :class:`~.policy.ThreeNetPolicy` state dict (copies)."""
        params = self.params
        return {name: params.get(tuple(name.split(".")))[agent].detach().clone() for name in self.names}

    @torch.no_grad()
    def load_agent_state_dict(self, agent: int, state: dict[str, torch.Tensor]) -> None:
        """Overwrite agent ``agent``'s parameters with a single policy's ``state_dict``."""
        missing = set(self.names) - set(state)
        if missing:
            raise KeyError(f"missing policy weights: {sorted(missing)}")
        self.flat[agent] = torch.cat([state[name].reshape(-1).to(self.flat) for name in self.names])

    def agent_net(self, agent: int) -> ThreeNetPolicy:
        """A standalone copy of agent ``agent``'s policy (for videos, checkpoints and export).

        Built on the meta device and then given the weights, so it draws nothing from torch's RNG
        (the TorchRL collector samples from it: a checkpoint must not change the run).
        """
        with torch.device("meta"):
            # The observation's width D: 6, or 6 + 2k with past commands observed.
            net = ThreeNetPolicy(
                self.hidden_sizes,
                self.activation_name,
                self.min_std,
                self.shapes[0][1],
                distribution_eps=self.distribution_eps,
            )
        net.load_state_dict(self.agent_state_dict(agent), assign=True)
        return net


class ActionSampler:
    """``action = f(loc + scale * noise)``: the actor's distribution, sampled with given noise.

    Drawing the noise outside lets each agent draw from its own generator; ``noise=None`` gives
    the deterministic action (the mean, or its squashed image, as ``ExplorationType.DETERMINISTIC``).

    Args:
        distribution: the head's distribution, ``"normal"`` or ``"tanh_normal"`` .
        max_thrust: the per-motor thrust limit (``"tanh_normal"`` only).
    """

    def __init__(self, distribution: str, max_thrust: float | None) -> None:
        self.squash = None
        if distribution == "tanh_normal":
            # TorchRL's own tanh + affine transform, so samples match what TanhNormal.log_prob inverts.
            probe = TanhNormal(torch.zeros(2), torch.ones(2), low=0.0, high=float(max_thrust), tanh_loc=False)
            self.squash = probe.transforms[0]

    def __call__(self, loc: torch.Tensor, scale: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        """The action from the head's ``loc`` and ``scale`` and normals ``noise`` (None: the mean)."""
        pre = loc if noise is None else loc + scale * noise
        return pre if self.squash is None else self.squash(pre)
