"""Actor and critic networks shared by the algorithms (paper III-D), and their configuration.

Gradient flow through the feature extractor(s), chosen by ``NetConfig.shared_extractor``:

- ``True`` (default): **one** extractor, owned by the critics and trained by the sum of the
  critic losses (Eqs. 7-8). The actor reads its features *detached* (the actor loss, Eq. 9, never
  changes the extractor), and the target critics have a Polyak copy of it. This is the paper's
  "common input" (III-D) with the stop-gradient of SAC-AE/DrQ, which keeps the actor's
  max-Q gradient from shaping features to fool the critic; it runs the CNN 3 times per update
  instead of 10 (docs/csac.md).
- ``False``: every network owns its extractor: the actor one (trained by Eq. 9), each critic
  member one (an ensemble, trained by its own MSBE), each target critic a Polyak copy.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from safenav.nn.config import NetConfig
from safenav.nn.extractors import FlattenExtractor, NavExtractor
from safenav.nn.layers import EnsembleMLP

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
NAV_KEYS = ("state", "lidar", "dynamic")
STATIC_KEY = "static"
"""The optional fourth SafeNav entry (``EnvConfig.static_tracked``; beyond the paper)."""


def is_nav_layout(shapes: dict[str, tuple[int, ...]]) -> bool:
    """True for the SafeNav observation (``state`` (S,), ``lidar`` (R, C), ``dynamic`` (K, F),
    optionally ``static`` (P, G))."""
    keys = set(shapes) - {STATIC_KEY}
    return (keys == set(NAV_KEYS) and len(shapes["state"]) == 1 and len(shapes["lidar"]) == 2
            and len(shapes["dynamic"]) == 2
            and len(shapes.get(STATIC_KEY, (0, 0))) == 2)  # fmt: skip


def input_order(shapes: dict[str, tuple[int, ...]]) -> tuple[str, ...]:
    """Positional input order of :class:`DeterministicActor`: ``(state, lidar, dynamic)`` for the
    SafeNav layout (then ``static`` if present), else the sorted keys (``("obs",)`` for a Box)."""
    if not is_nav_layout(shapes):
        return tuple(sorted(shapes))
    return NAV_KEYS + ((STATIC_KEY,) if STATIC_KEY in shapes else ())


def make_extractor(
    shapes: dict[str, tuple[int, ...]], net: NetConfig, ensemble_size: int = 1
) -> nn.Module:
    """:class:`NavExtractor` for the SafeNav layout, else :class:`FlattenExtractor`."""
    if is_nav_layout(shapes):
        return NavExtractor(shapes["lidar"], shapes["dynamic"], shapes["state"][0], net.lidar_channels,
                            net.lidar_strides, net.lidar_kernel, net.lidar_embed, net.dynamic_hidden,
                            net.dynamic_embed, ensemble_size,
                            static_shape=shapes.get(STATIC_KEY))  # fmt: skip
    return FlattenExtractor(shapes, net.flatten_hidden, ensemble_size)


def squashed_gaussian(mean: torch.Tensor, log_std: torch.Tensor, noise: torch.Tensor):
    """Reparameterised sample ``a = tanh(mean + std * noise)`` and its log-density under the
    tanh-squashed Gaussian (SAC, Haarnoja et al. 2018, App. C): ``log N(u) - sum log(1 - tanh(u)^2)``,
    with ``log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u))`` for stability. Returns ``(a, logp)``."""
    u = mean + log_std.exp() * noise
    log_normal = (-0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
    log_det = (2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))).sum(-1)
    return torch.tanh(u), log_normal - log_det


class Actor(nn.Module):
    """Features (or an observation dict, when it owns an ``extractor``) -> tanh-squashed Gaussian
    over ``[-1, 1]^A``: MLP ``hidden`` with ReLU, then mean and log-std (squashed into
    ``[LOG_STD_MIN, LOG_STD_MAX]`` by tanh, as CleanRL)."""

    def __init__(self, extractor: nn.Module | None, in_features: int, action_dim: int,
                 hidden: tuple[int, ...]) -> None:  # fmt: skip
        super().__init__()
        self.extractor = extractor
        layers: list[nn.Module] = []
        for a, b in zip((in_features, *hidden[:-1]), hidden, strict=True):
            layers += [nn.Linear(a, b), nn.ReLU(inplace=True)]
        self.trunk = nn.Sequential(*layers)
        self.head = nn.Linear(hidden[-1] if hidden else in_features, 2 * action_dim)

    def forward(self, x) -> tuple[torch.Tensor, torch.Tensor]:
        """``(mean, log_std)``, each ``(N, A)``."""
        if self.extractor is not None:
            x = self.extractor(x)
        if x.dim() == 3:  # a one-member extractor's (1, N, F)
            x = x[0]
        mean, log_std = self.head(self.trunk(x)).chunk(2, -1)
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(log_std) + 1.0)
        return mean, log_std

    def sample(
        self, x, noise: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(action, log_prob, deterministic action)``; the action is reparameterised with
        ``noise`` (``(N, A)``; None = a standard-normal draw)."""
        mean, log_std = self(x)
        noise = torch.randn_like(mean) if noise is None else noise
        action, logp = squashed_gaussian(mean, log_std, noise)
        return action, logp, torch.tanh(mean)


class QEnsemble(nn.Module):
    """``E`` critics ``Q(s, a)`` in one module: features (or an observation dict, when it owns an
    ensemble ``extractor``) and action -> ``(E, N)``. Each member: MLP ``hidden`` with ReLU -> 1,
    then the ``output`` map for a value that cannot be below 0, such as a cost's: ``linear``
    (none), ``softplus`` (``softplus(q)``, trained through it) or ``clipped`` (``max(q, 0)`` for
    every reader, while the loss trains the linear ``q``: ``forward(..., raw=True)``)."""

    def __init__(self, extractor: nn.Module | None, in_features: int, action_dim: int,
                 hidden: tuple[int, ...], ensemble_size: int = 2,
                 output: str = "linear") -> None:  # fmt: skip
        super().__init__()
        if output not in ("linear", "softplus", "clipped"):
            raise ValueError(f"output={output!r}: linear, softplus or clipped")
        self.extractor = extractor
        self.ensemble_size = ensemble_size
        self.output = output
        self.mlp = EnsembleMLP(in_features + action_dim, hidden, 1, ensemble_size)

    @property
    def nonnegative(self) -> bool:
        """Whether every value it returns (but ``raw`` ones) is >= 0."""
        return self.output != "linear"

    def forward(self, x, action: torch.Tensor, raw: bool = False) -> torch.Tensor:
        """``(E, N)`` values; ``raw``: the ``clipped`` critic's linear output, which its loss
        trains (a gradient at every value: a critic driven below 0 comes back when its targets
        do, where a softplus one, pushed far below 0 by Adam, stays at ~0 for good)."""
        q = self.preactivation(x, action)
        return q if raw and self.output == "clipped" else self.read(q)

    def preactivation(self, x, action: torch.Tensor) -> torch.Tensor:
        """``(E, N)`` linear outputs ``q``, before the ``output`` map."""
        if self.extractor is not None:
            x = self.extractor(x)
        if x.dim() == 3:
            action = action.expand(x.shape[0], *action.shape)
        return self.mlp(torch.cat([x, action], -1)).squeeze(-1)

    def read(self, q: torch.Tensor) -> torch.Tensor:
        """The values every reader sees from linear outputs ``q``: the ``output`` map."""
        if self.output == "softplus":
            return nn.functional.softplus(q)
        if self.output == "clipped":
            return q.clamp(min=0.0)
        return q


class DeterministicActor(nn.Module):
    """The deployable policy: observation tensors (positional, in ``input_names`` order) ->
    ``tanh(mean)`` in ``[-1, 1]^A``. Traceable (``torch.jit.trace``, ONNX export)."""

    def __init__(
        self, encoder: nn.Module | None, actor: Actor, input_names: tuple[str, ...]
    ) -> None:
        super().__init__()
        self.encoder = encoder
        self.actor = actor
        self.input_names = tuple(input_names)

    def gaussian(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The Gaussian before the tanh, ``(mean, log_std)``, each ``(N, A)``: ``forward`` takes its
        mean, ``Policy.sample`` draws from it."""
        obs = dict(zip(self.input_names, inputs, strict=True))
        return self.actor(self.encoder(obs) if self.encoder is not None else obs)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        mean, _ = self.gaussian(*inputs)
        return torch.tanh(mean)


__all__ = ["NAV_KEYS", "Actor", "DeterministicActor", "NetConfig", "QEnsemble", "is_nav_layout",
           "make_extractor", "squashed_gaussian"]  # fmt: skip
