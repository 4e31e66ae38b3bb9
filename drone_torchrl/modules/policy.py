"""The paper's policy (section 3.2.1): a shared trunk, a mean head and a std head, as a TorchRL actor."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import IndependentNormal, ProbabilisticActor, TanhNormal

from drone_torchrl.envs.dynamics import ACTION_DIM, STATE_DIM

DISTRIBUTIONS = ("normal", "tanh_normal")
ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU}


class ThreeNetPolicy(nn.Module):
    """Shared trunk -> (mean head, std head), the three nets of the paper.

    - shared net: ``len(hidden_sizes)`` hidden layers (paper: two of 32, tanh);
    - mean net: one linear layer to the two motor commands;
    - std net: one linear layer, ``softplus`` (the paper's ``log(1 + exp(.))``), plus ``min_std``
      so the distribution never collapses to zero width.

    ``distribution_eps`` (default 0) is then added to both outputs: the policy is
    ``Normal(mu + eps, sigma + eps)``, as the paper's public code builds it (with ``eps = 1e-6``).
    Its gradients are those of ``mu`` and ``sigma``; it only moves the mean by ``eps`` and widens the
    std by ``eps``.

    Args:
        hidden_sizes: the shared net's hidden layer widths.
        activation: the hidden layers' activation (a key of ``ACTIVATIONS``).
        min_std: the floor added to the std head's softplus.
        obs_dim: the observation's width ``D``.
        action_dim: the action's width ``A`` (the two motor commands).
        distribution_eps: added to the mean and the std.
    """

    def __init__(
        self,
        hidden_sizes: Sequence[int] = (32, 32),
        activation: str = "tanh",
        min_std: float = 1e-6,
        obs_dim: int = STATE_DIM,
        action_dim: int = ACTION_DIM,
        distribution_eps: float = 0.0,
    ) -> None:
        super().__init__()
        check_distribution_eps(distribution_eps)
        layers: list[nn.Module] = []
        width = obs_dim
        for size in hidden_sizes:
            layers += [nn.Linear(width, size), ACTIVATIONS[activation]()]
            width = size
        self.shared = nn.Sequential(*layers)
        self.mean = nn.Linear(width, action_dim)
        self.std = nn.Linear(width, action_dim)
        self.min_std = min_std
        self.distribution_eps = float(distribution_eps)

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The action distribution's mean and std ``[..., A]`` for observations ``[..., D]``."""
        features = self.shared(observation)
        loc, scale = self.mean(features), nn.functional.softplus(self.std(features)) + self.min_std
        return shift_distribution(loc, scale, self.distribution_eps)


# The largest model.distribution_eps accepted: a numerical guard (the paper's code uses 1e-6), not a knob
# that moves the mean by a meaningful fraction of a motor command.
MAX_DISTRIBUTION_EPS = 1e-2


def check_distribution_eps(eps: float) -> None:
    """Raise ``ValueError`` unless ``0 <= eps <= MAX_DISTRIBUTION_EPS`` (finite)."""
    if isinstance(eps, bool) or not isinstance(eps, int | float) or not 0 <= eps <= MAX_DISTRIBUTION_EPS:
        raise ValueError(
            f"model.distribution_eps={eps!r} is not allowed; expected a number in [0, {MAX_DISTRIBUTION_EPS}]"
        )


def shift_distribution(
    loc: torch.Tensor, scale: torch.Tensor, eps: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(loc + eps, scale + eps)``: the paper's code's ``Normal(mu + eps, sigma + eps)``; unchanged at 0."""
    if eps == 0:
        return loc, scale
    return loc + eps, scale + eps


def init_exploration(
    net: ThreeNetPolicy, std: float, mean: float = 0.0, weights: Mapping[str, torch.Tensor] | None = None
) -> None:
    """Start ``net`` at the mean head's output ``mean`` with exploration noise ``std`` in every state.

    The heads' weights are scaled down 100x (as in PPO implementations that initialise the policy
    head near zero), the mean head's bias is ``mean`` and the std head's bias is set so
    ``softplus(bias) + min_std = std``. PyTorch's default gives a std of about 0.7 that varies
    with the state, which on a TanhNormal over ``[0, max_thrust]`` flips the drone within a few
    steps.

    Args:
        net: the policy (its ``min_std``; its parameters unless ``weights`` is given).
        std: the starting std, > ``net.min_std``.
        mean: the mean head's starting output.
        weights: the tensors to set, by parameter name (``"mean.weight"``, ...); default ``net``'s
            own. Views ``[N, ...]`` of many agents' stacked weights set every agent at once.
    """
    if not std > net.min_std:
        raise ValueError(
            f"model.init_std={std!r} is not allowed; expected a number > model.min_std={net.min_std}"
        )
    p = dict(net.named_parameters()) if weights is None else weights
    with torch.no_grad():
        p["mean.weight"].mul_(0.01)
        p["mean.bias"].fill_(mean)
        p["std.weight"].mul_(0.01)
        p["std.bias"].fill_(math.log(math.expm1(std - net.min_std)))


def make_actor(
    distribution: str = "normal",
    hidden_sizes: Sequence[int] = (32, 32),
    activation: str = "tanh",
    min_std: float = 1e-6,
    max_thrust: float | None = None,
    device: torch.device | str = "cpu",
    distribution_eps: float = 0.0,
) -> ProbabilisticActor:
    """Build the policy as a ``ProbabilisticActor`` reading ``"observation"``, writing ``"action"``.

    ``distribution="normal"`` (the paper): an independent Normal per motor over unbounded thrust;
    the log-probability is the SUM over the two motors (a proper joint density; the paper's code,
    after Gymnasium's REINFORCE tutorial, averaged them, which halves the gradient: an effective
    learning rate twice the paper's at the same alpha under plain SGD, and the same under Adam
    up to its epsilon). ``distribution="tanh_normal"``: a ``TanhNormal`` squashed onto
    ``[0, max_thrust]``, so every sampled thrust is physical (needs ``max_thrust``).

    In ``ExplorationType.DETERMINISTIC`` (evaluation) the action is the mean, or its squashed image.
    """
    if activation not in ACTIVATIONS:
        raise ValueError(
            f"model.activation={activation!r} is not allowed; expected one of {tuple(ACTIVATIONS)}"
        )
    distribution_head(distribution, max_thrust)  # refused before the net is built
    net = ThreeNetPolicy(hidden_sizes, activation, min_std, distribution_eps=distribution_eps).to(device)
    return actor_from_net(net, distribution, max_thrust)


def distribution_head(distribution: str, max_thrust: float | None) -> tuple[type, dict]:
    """The TorchRL distribution class and its keyword arguments for the head ``distribution``.

    Called as ``cls(loc, scale, **kwargs)``. What the actor samples from and the losses score with.
    Raises ``ValueError`` for a head that cannot be built.
    """
    if distribution not in DISTRIBUTIONS:
        raise ValueError(
            f"model.distribution={distribution!r} is not allowed; expected one of {DISTRIBUTIONS}"
        )
    if distribution == "tanh_normal" and max_thrust is None:
        raise ValueError(
            "model.distribution='tanh_normal' needs a bounded action: set env.max_thrust (e.g. 1.0)"
        )
    if distribution == "normal":
        return IndependentNormal, {}
    # tanh_loc=False keeps the mean head's scale: with True and bounds [0, A] a zero mean maps near A.
    return TanhNormal, {"low": 0.0, "high": float(max_thrust), "tanh_loc": False}


def actor_from_net(
    net: nn.Module, distribution: str, max_thrust: float | None, return_log_prob: bool = False
) -> ProbabilisticActor:
    """The distribution head over any module mapping ``observation`` to ``(loc, scale)``.

    Used for one :class:`ThreeNetPolicy` and for the stacked nets of a population alike, so both
    sample and score actions with the same distribution. ``return_log_prob``: also write the
    sampled action's ``"action_log_prob"`` (PPO's importance ratio needs it).
    """
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    dist_class, dist_kwargs = distribution_head(distribution, max_thrust)
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=["action"],
        distribution_class=dist_class,
        distribution_kwargs=dist_kwargs,
        return_log_prob=return_log_prob,
    )
