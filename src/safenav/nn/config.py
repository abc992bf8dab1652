"""Network configuration (torch-free, so that the CLI can build its parser without torch)."""

from __future__ import annotations

from dataclasses import dataclass

TRUNKS = ("navrl", "relu", "tanh")
"""The hidden-layer kinds of PPO's networks (:attr:`NetConfig.trunk`)."""


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
    trunk: str = "navrl"
    """PPO's hidden layers (``hidden``), actor and critic: ``navrl`` = Linear -> LeakyReLU ->
    LayerNorm (NavRL's ``make_mlp``, the default), ``relu`` = Linear -> ReLU (rl-baselines3-zoo's
    tuned MuJoCo entries, ``activation_fn=nn.ReLU``), ``tanh`` = Linear -> tanh (SB3's and
    CleanRL's default). The SAC family's MLPs are Linear -> ReLU whatever this says."""

    def __post_init__(self) -> None:
        sizes = (*self.hidden, *self.lidar_channels, *self.lidar_strides, *self.flatten_hidden,
                 self.lidar_kernel, self.lidar_embed, self.dynamic_hidden, self.dynamic_embed)  # fmt: skip
        if self.trunk not in TRUNKS:
            raise ValueError(f"trunk={self.trunk!r} must be one of {', '.join(TRUNKS)}")
        if any(n < 1 for n in sizes):
            raise ValueError(f"network sizes, strides and kernel must be >= 1 (got {self})")
        if len(self.lidar_channels) != len(self.lidar_strides):
            raise ValueError(f"lidar-channels {self.lidar_channels} and lidar-strides "
                             f"{self.lidar_strides} need one entry per convolution each")  # fmt: skip


__all__ = ["TRUNKS", "NetConfig"]
