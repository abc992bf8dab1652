"""Ensemble layers: ``E`` independent copies of a layer evaluated in one batched matmul.

Every layer here keeps a leading *member* dimension ``E`` on its parameters. A member is one
network of an ensemble (one critic head of a double critic, say); ``E = 1`` is an ordinary layer.
Inputs are either ``(N, in)``, shared by all members, or ``(E, N, in)``, one slice per member;
outputs are always ``(E, N, out)``. One ``baddbmm`` replaces ``E`` separate ``Linear`` calls, which
on a CPU at batch 256 is what makes four critics affordable (docs/csac.md, "Measurements").

:class:`CircularConv1d` is a 1-D convolution over a *circular* axis (the 36 azimuth columns of the
range image wrap around), written as one dense matmul per layer: its ``(L * C_in, L_out * C_out)``
weight is built from the ``K``-tap kernel at each call by a matmul with fixed 0/1 shift matrices.
At these sizes (L <= 36, C <= 16) that "circulant" form beat ``nn.Conv1d``, ``nn.Conv2d`` and an
unfold + matmul im2col on this CPU, forward and backward (``experiments/cnn_forms.py``).
"""

from __future__ import annotations

import math

import torch
from torch import nn


def ensemble_linear(
    x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, members: int
) -> torch.Tensor:
    """``x @ weight + bias`` per member: ``x`` ``(N, in)`` shared by all members, ``(1, N, in)``
    (also shared) or ``(E, N, in)``; ``weight`` ``(E, in, out)``, ``bias`` ``(E, 1, out)`` ->
    ``(E, N, out)``. ``members`` is ``E`` as a Python int: branching on it (not on tensor shapes)
    keeps ``torch.jit.trace`` exact and quiet."""
    if x.dim() == 2:
        if members == 1:
            return torch.addmm(bias[0], x, weight[0]).unsqueeze(0)
        x = x.expand(members, *x.shape)
    elif members > 1 and x.shape[0] == 1:  # a one-member input is shared by every member
        x = x.expand(members, *x.shape[1:])
    return torch.baddbmm(bias, x, weight)


class EnsembleLinear(nn.Module):
    """``E`` independent ``Linear(in_features, out_features)`` layers (PyTorch's default init)."""

    def __init__(self, in_features: int, out_features: int, ensemble_size: int = 1) -> None:
        super().__init__()
        self.in_features, self.out_features, self.ensemble_size = (
            in_features,
            out_features,
            ensemble_size,
        )
        bound = 1.0 / math.sqrt(in_features)
        self.weight = nn.Parameter(
            torch.empty(ensemble_size, in_features, out_features).uniform_(-bound, bound)
        )
        self.bias = nn.Parameter(
            torch.empty(ensemble_size, 1, out_features).uniform_(-bound, bound)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return ensemble_linear(x, self.weight, self.bias, self.ensemble_size)

    def extra_repr(self) -> str:
        return f"in={self.in_features}, out={self.out_features}, ensemble_size={self.ensemble_size}"


class EnsembleMLP(nn.Module):
    """``E`` independent MLPs ``in -> hidden... -> out`` with ReLU between layers (none at the end
    unless ``final_activation``)."""

    def __init__(
        self,
        in_features: int,
        hidden: tuple[int, ...],
        out_features: int,
        ensemble_size: int = 1,
        final_activation: bool = False,
    ) -> None:
        super().__init__()
        sizes = (in_features, *hidden, out_features)
        self.layers = nn.ModuleList(
            EnsembleLinear(a, b, ensemble_size) for a, b in zip(sizes[:-1], sizes[1:], strict=True)
        )
        self.final_activation = final_activation

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < last or self.final_activation:
                x = torch.relu_(x)  # in place: the fresh matmul output is not needed for backward
        return x


def circular_shift_matrix(length: int, stride: int, kernel: int) -> torch.Tensor:
    """``(L * L_out, K)`` 0/1 matrix: entry ``[(l, o), j]`` is 1 when input column ``l`` feeds tap
    ``j`` of output column ``o`` of a circularly padded, strided convolution."""
    out_len = length // stride
    p = torch.zeros(length, out_len, kernel)
    for o in range(out_len):
        for j in range(kernel):
            p[(o * stride + j - kernel // 2) % length, o, j] = 1.0
    return p.reshape(length * out_len, kernel)


class CircularConv1d(nn.Module):
    """``E`` independent 1-D convolutions over a circular axis of length ``L`` (odd ``K`` taps,
    padding ``K // 2`` taken from the other end, stride ``s``), channels-last and flattened:
    input ``(N, L * C_in)`` or ``(E, N, L * C_in)``, output ``(E, N, (L // s) * C_out)``.

    Same function as ``nn.Conv1d(C_in, C_out, K, stride=s)`` on the circularly padded
    channels-first input (tested), computed as one dense matmul per call (see module docstring).
    """

    def __init__(self, length: int, in_channels: int, out_channels: int, kernel: int = 5,
                 stride: int = 1, ensemble_size: int = 1) -> None:  # fmt: skip
        super().__init__()
        if kernel % 2 != 1:
            raise ValueError(f"kernel={kernel} must be odd")
        if length % stride != 0:
            raise ValueError(f"length {length} must be a multiple of stride {stride}")
        self.length, self.in_channels, self.out_channels = length, in_channels, out_channels
        self.kernel, self.stride, self.ensemble_size = kernel, stride, ensemble_size
        self.out_length = length // stride
        bound = 1.0 / math.sqrt(in_channels * kernel)  # nn.Conv1d's default init
        self.weight = nn.Parameter(
            torch.empty(ensemble_size, kernel, in_channels * out_channels).uniform_(-bound, bound)
        )
        self.bias = nn.Parameter(
            torch.empty(ensemble_size, 1, out_channels).uniform_(-bound, bound)
        )
        self.register_buffer(
            "shift", circular_shift_matrix(length, stride, kernel), persistent=False
        )

    def dense_weight(self) -> torch.Tensor:
        """The ``(E, L * C_in, L_out * C_out)`` matrix of the convolution."""
        e, ln, lo, ci, co = (
            self.ensemble_size,
            self.length,
            self.out_length,
            self.in_channels,
            self.out_channels,
        )
        w = torch.matmul(self.shift, self.weight)  # (E, L * L_out, C_in * C_out)
        return w.view(e, ln, lo, ci, co).transpose(2, 3).reshape(e, ln * ci, lo * co)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        bias = self.bias.repeat(1, 1, self.out_length)
        return ensemble_linear(x, self.dense_weight(), bias, self.ensemble_size)

    def extra_repr(self) -> str:
        return (f"length={self.length}, {self.in_channels}->{self.out_channels}, kernel={self.kernel}, "
                f"stride={self.stride}, ensemble_size={self.ensemble_size}")  # fmt: skip


__all__ = [
    "CircularConv1d",
    "EnsembleLinear",
    "EnsembleMLP",
    "circular_shift_matrix",
    "ensemble_linear",
]
