"""The optimiser every algorithm uses."""

from __future__ import annotations

import torch


def adam(params, **kwargs) -> torch.optim.Adam:
    """Adam with the fused kernel (one kernel per group, 2.4x faster steps on CPU than the default
    per-parameter loop; docs/csac.md), when supported by the parameters' device."""
    try:
        return torch.optim.Adam(params, fused=True, **kwargs)
    except RuntimeError:
        return torch.optim.Adam(params, **kwargs)


__all__ = ["adam"]
