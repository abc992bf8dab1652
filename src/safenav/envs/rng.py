"""Counter-based random numbers: ``u = hash(seed, stream, counter)``, batched, no state.

The simulator draws its per-episode and per-obstacle randomness this way so that a batch of
environments needs no per-env generator and env ``i`` of a vector env draws exactly what a single
env with the same seed draws (vector == N single envs, step for step, on any device).
"""

from __future__ import annotations

import torch

_MASK = 0xFFFFFFFF
_MUL = 0x45D9F3B  # < 2**27, so products of 32-bit values stay inside int64
_GOLDEN = 0x9E3779B9


def _mix32(x: torch.Tensor) -> torch.Tensor:
    """A 32-bit integer finaliser (xor-shift-multiply), on int64 tensors holding 32-bit values."""
    x = (x ^ (x >> 16)) & _MASK
    x = (x * _MUL) & _MASK
    x = x ^ (x >> 16)
    x = (x * _MUL) & _MASK
    return x ^ (x >> 16)


def hash_ints(*keys: torch.Tensor | int) -> torch.Tensor:
    """Hash broadcastable integer keys into 32-bit values (int64 tensor)."""
    h: torch.Tensor | None = None
    for k in keys:
        k = torch.as_tensor(k, dtype=torch.int64) if not isinstance(k, torch.Tensor) else k.long()
        k = k & _MASK
        h = _mix32(k + _GOLDEN) if h is None else _mix32((h ^ _mix32(k + _GOLDEN)) + _GOLDEN)
    assert h is not None, "hash_ints needs at least one key"
    return h


def uniform(*keys: torch.Tensor | int) -> torch.Tensor:
    """Uniform float32 in [0, 1) from the keys (24 bits of the hash)."""
    return (hash_ints(*keys) >> 8).to(torch.float32) * (1.0 / (1 << 24))
