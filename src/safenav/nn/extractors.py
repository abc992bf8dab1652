"""Feature extractors: observation (a dict of tensors) -> one feature vector per sample.

Observations are always dicts of ``(N, ...)`` tensors inside the algorithms; a ``Box`` observation
is the dict ``{"obs": x}`` (see :func:`safenav.envs.vector.obs_layout`). Two extractors:

- :class:`NavExtractor` for the SafeNav ``Dict`` (paper III-D): a 3-layer CNN on the ``lidar``
  range image -> 128, an MLP on the flattened ``dynamic`` matrix -> 64, concatenated with the
  8-d ``state`` -> 200 features.
- :class:`FlattenExtractor` for anything else (``Box``, or a ``Dict`` of ``Box`` es): flatten and
  concatenate, then an optional MLP (none by default: the actor and critic MLPs follow anyway).

Both are ensembles of ``E`` members (see :mod:`safenav.nn.layers`) and return ``(E, N, F)``; the
parameter-free :class:`FlattenExtractor` returns ``(N, F)``, shared by every member.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from safenav.nn.layers import CircularConv1d, EnsembleMLP


class NavExtractor(nn.Module):
    """SafeNav observation -> ``lidar_embed + dynamic_embed + state`` features (200 by default).

    Range image ``(R, C)`` (R = 4 elevation rows, C = 36 azimuth columns): the rows are the input
    channels of three circular 1-D convolutions along azimuth (kernel 5, channels 8/16/16,
    strides 2/2/1: 36 -> 18 -> 9 columns, a receptive field of 29 columns = 290 degrees), then
    ``Linear(9 * 16 -> 128)``. Dynamic obstacles ``(5, 10)``: ``50 -> 128 -> 64``. ReLU throughout.
    A range-image history (``EnvConfig.lidar_history`` k) is ``k * R`` rows: ``k * R`` input
    channels of the first convolution (frame stacking), nothing else changes. With a ``static``
    entry ``(P, G)`` (``static_shape``; ``EnvConfig.static_tracked``, beyond the paper) a second
    MLP of the dynamic one's sizes embeds it, ``P * G -> 128 -> 64``, concatenated after it.
    """

    def __init__(
        self,
        lidar_shape: tuple[int, int],
        dynamic_shape: tuple[int, int],
        state_dim: int,
        channels: tuple[int, ...] = (8, 16, 16),
        strides: tuple[int, ...] = (2, 2, 1),
        kernel: int = 5,
        lidar_embed: int = 128,
        dynamic_hidden: int = 128,
        dynamic_embed: int = 64,
        ensemble_size: int = 1,
        static_shape: tuple[int, int] | None = None,
    ) -> None:
        super().__init__()
        rows, length = lidar_shape
        if len(channels) != len(strides):
            raise ValueError(f"channels {channels} and strides {strides} must have the same length")
        if length % math.prod(strides) != 0:
            raise ValueError(f"{length} azimuth columns are not divisible by the strides {strides}")
        convs, c_in = [], rows
        for c_out, s in zip(channels, strides, strict=True):
            convs.append(CircularConv1d(length, c_in, c_out, kernel, s, ensemble_size))
            c_in, length = c_out, length // s
        self.convs = nn.ModuleList(convs)
        self.lidar_head = EnsembleMLP(
            c_in * length, (), lidar_embed, ensemble_size, final_activation=True
        )
        self.dynamic_mlp = EnsembleMLP(math.prod(dynamic_shape), (dynamic_hidden,), dynamic_embed,
                                       ensemble_size, final_activation=True)  # fmt: skip
        self.static_mlp = (EnsembleMLP(math.prod(static_shape), (dynamic_hidden,), dynamic_embed,
                                       ensemble_size, final_activation=True)
                           if static_shape else None)  # fmt: skip
        self.ensemble_size = ensemble_size
        self.out_features = (lidar_embed + dynamic_embed * (2 if static_shape else 1)
                             + state_dim)  # fmt: skip

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        lidar = obs["lidar"]
        x = lidar.transpose(1, 2).reshape(lidar.shape[0], -1)  # (N, C * R): channels last
        for conv in self.convs:
            x = torch.relu_(conv(x))
        x = self.lidar_head(x)
        y = self.dynamic_mlp(obs["dynamic"].flatten(1))
        state = obs["state"].expand(self.ensemble_size, *obs["state"].shape)
        if self.static_mlp is None:
            return torch.cat([x, y, state], -1)
        return torch.cat([x, y, self.static_mlp(obs["static"].flatten(1)), state], -1)


class FlattenExtractor(nn.Module):
    """Any observation dict -> its entries flattened and concatenated (sorted keys), then an
    optional ReLU MLP of sizes ``hidden``."""

    def __init__(self, shapes: dict[str, tuple[int, ...]], hidden: tuple[int, ...] = (),
                 ensemble_size: int = 1) -> None:  # fmt: skip
        super().__init__()
        self.keys = sorted(shapes)
        flat = sum(math.prod(shapes[k]) for k in self.keys)
        self.mlp = (EnsembleMLP(flat, hidden[:-1], hidden[-1], ensemble_size, final_activation=True)
                    if hidden else None)  # fmt: skip
        self.out_features = hidden[-1] if hidden else flat

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        x = (
            torch.cat([obs[k].flatten(1) for k in self.keys], -1)
            if len(self.keys) > 1
            else obs[self.keys[0]].flatten(1)
        )
        return x if self.mlp is None else self.mlp(x)


__all__ = ["FlattenExtractor", "NavExtractor"]
