"""Policies without training: a scripted go-to-goal actor with obstacle repulsion.

It has the trained actor's interface (``(state, lidar, dynamic) -> action in [-1, 1]^3``, the env's
observation layout) and exports to ONNX like it, so the whole deployment chain (export, runtime,
MAVLink, PX4 offboard) can be tested and demonstrated without a checkpoint.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from safenav.envs.config import EnvConfig


class GoToGoalActor(nn.Module):
    """Fly toward the goal, slowing within ``slow_radius`` m, pushed away from range-image hits
    of the level beams and from tracked moving obstacles (an artificial potential field), and
    sideways when an obstacle stands straight in the way (the field's classic trap).

    Observation scales are the env's: ``state[3] * 20`` and ``state[4] * 4`` are the horizontal and
    vertical distances to the goal; ``lidar = (4 - d) / 4``; ``dynamic[:, :, 3] = d / 4``.
    """

    def __init__(
        self, cfg: EnvConfig | None = None, slow_radius: float = 1.5, repulsion: float = 1.5
    ) -> None:
        super().__init__()
        cfg = cfg or EnvConfig()
        self.slow_radius = float(slow_radius)
        self.repulsion = float(repulsion)
        az = torch.arange(cfg.lidar_h_beams, dtype=torch.float32) * (
            2 * math.pi / cfg.lidar_h_beams
        )
        self.register_buffer("beam_dirs", torch.stack([torch.cos(az), torch.sin(az)], -1))  # (H, 2)
        # Rows of the range image at elevations in [0, 10] degrees: the level beams.
        rows = [i for i, e in enumerate(cfg.lidar_v_angles) if 0.0 <= e <= 10.0] or [0]
        self.register_buffer("rows", torch.tensor(rows, dtype=torch.int64))

    def forward(
        self, state: torch.Tensor, lidar: torch.Tensor, dynamic: torch.Tensor
    ) -> torch.Tensor:
        unit = state[:, 0:3]
        dist = torch.sqrt((state[:, 3] * 20.0) ** 2 + (state[:, 4] * 4.0) ** 2)
        attract = unit * torch.clamp(dist / self.slow_radius, 0.0, 1.0)[:, None]
        near = lidar.index_select(1, self.rows).amax(1)  # (N, H): 1 at the sensor, 0 free
        push = -(near**3) @ self.beam_dirs  # (N, 2)
        d_near = (1.0 - dynamic[:, :, 3]).clamp(0.0, 1.0) * (dynamic[:, :, 3] > 0).to(state.dtype)
        push = push - ((d_near**2)[..., None] * dynamic[:, :, 0:2]).sum(1)
        # Escape the potential field's trap (an obstacle straight between UAV and goal): when the
        # push opposes the way to the goal, add a sideways push, on the goal's side (left on a tie).
        way = attract[:, :2]
        perp = torch.stack([-push[:, 1], push[:, 0]], -1)
        side = torch.where((perp * way).sum(-1, keepdim=True) < 0, -1.0, 1.0)
        norms = push.norm(dim=-1, keepdim=True) * way.norm(dim=-1, keepdim=True) + 1e-6
        opposed = (-(push * way).sum(-1, keepdim=True) / norms).clamp(0.0, 1.0)
        push = push + perp * side * opposed
        push3 = torch.cat([push, torch.zeros_like(push[:, :1])], -1)
        return torch.clamp(attract + self.repulsion * push3 / 3.0, -1.0, 1.0)


__all__ = ["GoToGoalActor"]
