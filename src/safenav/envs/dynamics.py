"""Motion as pure batched functions: the UAV's velocity tracker and the moving obstacles."""

from __future__ import annotations

import torch

from safenav.envs import rng


def velocity_tracker(
    pos: torch.Tensor,
    vel: torch.Tensor,
    cmd: torch.Tensor,
    dt: float,
    substeps: int,
    time_constant: float,
    max_acceleration: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """PX4-offboard-like velocity tracking: first order toward ``cmd`` with an acceleration limit.

    ``a = clip_norm((cmd - v) / time_constant, max_acceleration)``, integrated semi-implicitly
    (velocity first) over ``substeps`` steps of ``dt / substeps``. Returns the new ``(pos, vel)``.
    """
    h = dt / substeps
    for _ in range(substeps):
        acc = (cmd - vel) / time_constant
        norm = acc.norm(dim=-1, keepdim=True)
        acc = acc * (max_acceleration / norm.clamp(min=max_acceleration))
        vel = vel + acc * h
        pos = pos + vel * h
    return pos, vel


def goal_frame_to_world(
    v: torch.Tensor, cos_yaw: torch.Tensor, sin_yaw: torch.Tensor
) -> torch.Tensor:
    """Rotate ``(..., 3)`` vectors from the goal frame (x toward the goal, z up) to the world."""
    x, y = v[..., 0], v[..., 1]
    return torch.stack([cos_yaw * x - sin_yaw * y, sin_yaw * x + cos_yaw * y, v[..., 2]], dim=-1)


def world_to_goal_frame(
    v: torch.Tensor, cos_yaw: torch.Tensor, sin_yaw: torch.Tensor
) -> torch.Tensor:
    """Inverse of :func:`goal_frame_to_world`; ``cos_yaw``/``sin_yaw`` broadcast against ``v[..., 0]``."""
    x, y = v[..., 0], v[..., 1]
    return torch.stack([cos_yaw * x + sin_yaw * y, -sin_yaw * x + cos_yaw * y, v[..., 2]], dim=-1)


# Random streams of the moving obstacles (keys of the counter-based generator).
_STREAM_GOAL_X, _STREAM_GOAL_Y, _STREAM_GOAL_Z, _STREAM_SPEED = 11, 12, 13, 14


def sample_obstacle_goals(
    world_seed: torch.Tensor,
    obstacle_id: torch.Tensor,
    counter: torch.Tensor,
    origin: torch.Tensor,
    is_cuboid: torch.Tensor,
    local_range: float,
    xy_limit: float,
    z_range: tuple[float, float],
    cylinder_z: float,
) -> torch.Tensor:
    """Local goals within ``+-local_range`` of each obstacle's origin, kept inside the map."""
    ux = rng.uniform(world_seed, obstacle_id, counter, _STREAM_GOAL_X)
    uy = rng.uniform(world_seed, obstacle_id, counter, _STREAM_GOAL_Y)
    uz = rng.uniform(world_seed, obstacle_id, counter, _STREAM_GOAL_Z)
    gx = (origin[..., 0] + (2 * ux - 1) * local_range).clamp(-xy_limit, xy_limit)
    gy = (origin[..., 1] + (2 * uy - 1) * local_range).clamp(-xy_limit, xy_limit)
    gz = torch.where(is_cuboid, z_range[0] + uz * (z_range[1] - z_range[0]), cylinder_z)
    return torch.stack([gx, gy, gz], dim=-1)


def sample_obstacle_speeds(
    world_seed: torch.Tensor, obstacle_id: torch.Tensor, epoch: torch.Tensor, lo: float, hi: float
) -> torch.Tensor:
    return lo + rng.uniform(world_seed, obstacle_id, epoch, _STREAM_SPEED) * (hi - lo)


def move_obstacles(
    pos: torch.Tensor, goal: torch.Tensor, speed: torch.Tensor, dt: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Move toward the goal at ``speed`` without overshooting; returns ``(pos, velocity)``."""
    delta = goal - pos
    dist = delta.norm(dim=-1, keepdim=True)
    step = torch.minimum(speed[..., None] * dt, dist)
    vel = delta / dist.clamp(min=1e-6) * (step / dt)
    return pos + vel * dt, vel


__all__ = [
    "goal_frame_to_world",
    "move_obstacles",
    "sample_obstacle_goals",
    "sample_obstacle_speeds",
    "velocity_tracker",
    "world_to_goal_frame",
]
