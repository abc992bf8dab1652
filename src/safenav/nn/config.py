"""Network configuration (torch-free, so that the CLI can build its parser without torch)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class NetConfig:
    """Network sizes (paper III-D, IV) and how the feature extractor is shared."""

    hidden: tuple[int, ...] = (256, 256)
    """Hidden layers of the actor MLP and of every critic MLP (paper IV: two layers)."""
    shared_extractor: bool = True
    """One extractor trained by the critics and read detached by the actor (True), or one per
    network (False); see the module docstring. An ablation switch."""
    lidar_channels: tuple[int, ...] = (8, 16, 16)
    """Channels of the 3 circular convolutions over the range image's azimuth columns."""
    lidar_strides: tuple[int, ...] = (2, 2, 1)
    """Their strides (36 -> 18 -> 9 -> 9 columns)."""
    lidar_kernel: int = 5
    """Their kernel width in columns (odd)."""
    lidar_embed: int = 128
    """Range-image embedding size (paper IV: 128)."""
    dynamic_hidden: int = 128
    """Hidden layer of the dynamic-obstacle MLP."""
    dynamic_embed: int = 64
    """Dynamic-obstacle embedding size (paper IV: 64)."""
    flatten_hidden: tuple[int, ...] = ()
    """MLP of the extractor for non-SafeNav observations (Box): () = flatten only."""


__all__ = ["NetConfig"]
