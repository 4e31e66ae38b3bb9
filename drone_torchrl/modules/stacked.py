"""The three-net policy of many agents at once: one set of parameters stacked over a leading agent dim.

:class:`StackedThreeNet` holds N agents' :class:`~drone_torchrl.modules.ThreeNetPolicy` weights as
one ``TensorDictParams`` of ``[N, ...]`` leaves (``TensorDict.from_modules(..., as_module=True)``,
as TorchRL's ``MultiAgentMLP`` holds its agents), so an optimizer step, a clip or a forward is a
fixed number of kernels whatever N is. The forward applies every agent's net to its own
observations with batched matrix products (``torch.baddbmm``), one kernel per layer.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.modules import TanhNormal

from drone_torchrl.modules.policy import ACTIVATIONS, ThreeNetPolicy

Layers = list[tuple[torch.Tensor, torch.Tensor]]


def _linear_names(net: ThreeNetPolicy) -> list[str]:
    shared = [f"shared.{i}" for i, m in enumerate(net.shared) if isinstance(m, nn.Linear)]
    return [*shared, "mean", "std"]


class StackedThreeNet(nn.Module):
    """N :class:`ThreeNetPolicy` nets with stacked parameters, applied at once to ``[N, ..., 6]`` observations.

    ``nets`` give the architecture and each agent's initial weights (copied; the nets themselves
    are not used afterwards). ``params`` holds the ``[N, ...]`` leaves, keyed like the net's own
    parameters (``("shared", "0", "weight")`` for ``shared.0.weight``).
    """

    def __init__(self, nets: list[ThreeNetPolicy], activation: str) -> None:
        super().__init__()
        shapes = {tuple(p.shape for p in net.parameters()) for net in nets}
        kinds = {tuple(type(m) for m in net.shared if not isinstance(m, nn.Linear)) for net in nets}
        if len(shapes) > 1 or len({net.min_std for net in nets}) > 1:
            raise ValueError("stacked nets must share hidden_sizes and min_std")
        if kinds != {(ACTIVATIONS[activation],) * (len(nets[0].shared) // 2)}:
            raise ValueError(f"stacked nets must all use activation={activation!r}")
        self.params = TensorDict.from_modules(*nets, as_module=True)
        self.activation = ACTIVATIONS[activation]()
        self.min_std = nets[0].min_std
        self.linears = [tuple(name.split(".")) for name in _linear_names(nets[0])]
        self.names = [name for name, _ in nets[0].named_parameters()]
        self.n_hidden = len(self.linears) - 2
        hidden = [m.out_features for m in nets[0].shared if isinstance(m, nn.Linear)]
        self.spec = {"hidden_sizes": hidden, "activation": activation, "min_std": self.min_std}

    def __len__(self) -> int:
        return self.params.batch_size[0]

    def stacked(self, params: TensorDict | None = None) -> Layers:
        """``[(W^T [N, in, out], b [N, 1, out]), ...]``: hidden layers, then the mean and std heads."""
        params = self.params if params is None else params
        return [
            (params.get((*key, "weight")).transpose(1, 2), params.get((*key, "bias")).unsqueeze(1))
            for key in self.linears
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

    def layers(self) -> Layers:
        return self.stacked()

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.apply_stacked(self.stacked(), observation)

    # ------------------------------------------------------------------ one agent
    def agent_state_dict(self, agent: int) -> dict[str, torch.Tensor]:
        """Agent ``agent``'s weights as a :class:`ThreeNetPolicy` state dict (copies)."""
        return {name: self.params.get(tuple(name.split(".")))[agent].detach().clone() for name in self.names}

    @torch.no_grad()
    def load_agent_state_dict(self, agent: int, state: dict[str, torch.Tensor]) -> None:
        missing = set(self.names) - set(state)
        if missing:
            raise KeyError(f"missing policy weights: {sorted(missing)}")
        for name in self.names:
            self.params.get(tuple(name.split(".")))[agent] = state[name]

    def agent_net(self, agent: int) -> ThreeNetPolicy:
        """A standalone copy of agent ``agent``'s policy (for videos, checkpoints and export).

        Built on the meta device and then given the weights, so it draws nothing from torch's RNG
        (the TorchRL collector samples from it: a checkpoint must not change the run)."""
        with torch.device("meta"):
            net = ThreeNetPolicy(**self.spec)
        net.load_state_dict(self.agent_state_dict(agent), assign=True)
        return net


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
