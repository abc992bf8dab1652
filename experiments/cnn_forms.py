"""Which formulation of the range-image CNN is fastest on this CPU? (docs/csac.md, "Measurements")

Four implementations of a 3-layer CNN on the (4, 36) range image, each followed by the same
Linear -> 128, timed forward+backward (parameter gradients; the observation needs none) and
forward-only (no_grad) at batch 256, median of interleaved trials. A single dense layer on the
flattened image is the floor. Run: ``.venv/bin/python experiments/cnn_forms.py [--threads 1 2]``.

- ``conv2d``: image as (1, 4, 36), kernels 3x5, zero padding over elevation, circular over azimuth.
- ``conv1d``: elevation rows as 4 input channels, kernel 5 over azimuth, circular padding.
- ``unfold``: the conv1d maths as im2col (``Tensor.unfold`` of the padded input) + one matmul.
- ``circulant``: the conv1d maths as one dense matmul per layer, its (L*Cin, Lout*Cout) weight
  built each call from the 5-tap kernel by a matmul with fixed 0/1 shift matrices.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
import torch.nn.functional as F
from torch import nn

CHANNELS = (8, 16, 16)
STRIDES = (2, 2, 1)
K = 5


def cpad(x: torch.Tensor, p: int = K // 2) -> torch.Tensor:
    return torch.cat([x[..., -p:], x, x[..., :p]], -1)


def layer_specs(cin: int = 4, length: int = 36):
    specs = []
    for cout, s in zip(CHANNELS, STRIDES, strict=True):
        specs.append((cin, cout, s, length))
        cin, length = cout, length // s
    return specs, cin * length


class Conv2dNet(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        cin, layers, h, w = 1, [], 4, 36
        for cout, s in zip(CHANNELS, STRIDES, strict=True):
            sh = 2 if (s == 1 and h > 2) else 1  # halve elevation once
            layers.append(nn.Conv2d(cin, cout, (3, K), stride=(sh, s)))
            cin, h, w = cout, h // sh, w // s
        self.convs = nn.ModuleList(layers)
        self.fc = nn.Linear(cin * h * w, 128)

    def forward(self, x):
        x = x[:, None]
        for conv in self.convs:
            x = F.relu(conv(F.pad(cpad(x), (0, 0, 1, 1))))
        return self.fc(x.flatten(1))


class Conv1dNet(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        specs, flat = layer_specs()
        self.convs = nn.ModuleList(nn.Conv1d(ci, co, K, stride=s) for ci, co, s, _ in specs)
        self.fc = nn.Linear(flat, 128)

    def forward(self, x):
        for conv in self.convs:
            x = F.relu(conv(cpad(x)))
        return self.fc(x.flatten(1))


class UnfoldNet(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.specs, flat = layer_specs()
        self.w = nn.ParameterList(
            nn.Parameter(torch.randn(ci * K, co) / (ci * K) ** 0.5) for ci, co, _, _ in self.specs
        )
        self.b = nn.ParameterList(nn.Parameter(torch.zeros(co)) for _, co, _, _ in self.specs)
        self.fc = nn.Linear(flat, 128)

    def forward(self, x):
        x = x.transpose(1, 2)  # (N, L, C): channels last
        for (ci, co, s, _), w, b in zip(self.specs, self.w, self.b, strict=True):
            cols = cpad(x.transpose(1, 2)).transpose(1, 2).unfold(1, K, s)  # (N, Lout, C, K)
            lout = cols.shape[1]
            x = F.relu(torch.addmm(b, cols.reshape(-1, ci * K), w)).view(-1, lout, co)
        return self.fc(x.flatten(1))


def shift_matrices(length: int, stride: int) -> torch.Tensor:
    """(L * Lout, K): entry [(l, o), j] = 1 when input column l feeds tap j of output column o."""
    lout = length // stride
    p = torch.zeros(length, lout, K)
    for o in range(lout):
        for j in range(K):
            p[(o * stride + j - K // 2) % length, o, j] = 1.0
    return p.reshape(length * lout, K)


class CirculantNet(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.specs, flat = layer_specs()
        self.w = nn.ParameterList(
            nn.Parameter(torch.randn(K, ci * co) / (ci * K) ** 0.5) for ci, co, _, _ in self.specs
        )
        self.b = nn.ParameterList(nn.Parameter(torch.zeros(co)) for _, co, _, _ in self.specs)
        for i, (_, _, s, length) in enumerate(self.specs):
            self.register_buffer(f"p{i}", shift_matrices(length, s))
        self.fc = nn.Linear(flat, 128)

    def forward(self, x):
        x = x.transpose(1, 2).flatten(1)  # (N, L*C) channels last
        for i, ((ci, co, s, length), w, b) in enumerate(
            zip(self.specs, self.w, self.b, strict=True)
        ):
            lout = length // s
            dense = (getattr(self, f"p{i}") @ w).view(length, lout, ci, co).transpose(1, 2)
            x = F.relu(torch.addmm(b.repeat(lout), x, dense.reshape(length * ci, lout * co)))
        return self.fc(x)


class DenseNet(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.fc = nn.Linear(144, 128)

    def forward(self, x):
        return self.fc(x.flatten(1))


def check_equivalent() -> None:
    """unfold and circulant compute exactly the conv1d function (same weights)."""
    ref, unf, circ = Conv1dNet(), UnfoldNet(), CirculantNet()
    for net in (unf, circ):
        co, length = CHANNELS[-1], 144 // CHANNELS[-1]  # flatten order (L, C) instead of (C, L)
        net.fc.bias.data.copy_(ref.fc.bias.detach())
        net.fc.weight.data.copy_(
            ref.fc.weight.detach().view(-1, co, length).transpose(1, 2).reshape(-1, co * length)
        )
        for i, conv in enumerate(ref.convs):
            w = conv.weight.detach()  # (co, ci, K)
            net.b[i].data.copy_(conv.bias.detach())
            if net is unf:
                net.w[i].data.copy_(w.permute(1, 2, 0).reshape(-1, w.shape[0]))
            else:
                net.w[i].data.copy_(w.permute(2, 1, 0).reshape(K, -1))
    x = torch.rand(7, 4, 36)
    for net in (unf, circ):
        torch.testing.assert_close(net(x), ref(x), atol=1e-5, rtol=1e-4)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--trials", type=int, default=15)
    parser.add_argument("--iters", type=int, default=30)
    args = parser.parse_args()
    check_equivalent()
    nets = {"conv2d": Conv2dNet(), "conv1d": Conv1dNet(), "unfold": UnfoldNet(),
            "circulant": CirculantNet(), "dense (floor)": DenseNet()}  # fmt: skip
    x = torch.rand(args.batch, 4, 36)
    print("| threads | form | fwd+bwd ms | fwd ms | params |\n|---|---|---|---|---|")
    for threads in args.threads:
        torch.set_num_threads(threads)
        times = {name: ([], []) for name in nets}
        for _ in range(args.trials):  # interleave the forms so load changes hit all alike
            for name, net in nets.items():
                t = time.perf_counter()
                for _ in range(args.iters):
                    net.zero_grad(set_to_none=True)
                    net(x).sum().backward()
                times[name][0].append((time.perf_counter() - t) / args.iters * 1e3)
                t = time.perf_counter()
                with torch.no_grad():
                    for _ in range(args.iters):
                        net(x)
                times[name][1].append((time.perf_counter() - t) / args.iters * 1e3)
        for name, (fb, fw) in times.items():
            n = sum(p.numel() for p in nets[name].parameters())
            print(
                f"| {threads} | {name} | {statistics.median(fb):.2f} | {statistics.median(fw):.2f} | {n} |"
            )


if __name__ == "__main__":
    main()
