"""Sensing as pure batched functions: the range image, obstacle clearances, tracked obstacles.

The range image (paper III-D) is ray-cast from a 2.5-D occupancy grid (a height map: the top of
the occupied column per cell, 0 = free ground). The onboard runtime (:mod:`safenav.deploy`) builds
such a grid from depth images and calls the very same :func:`raycast_height_map`.

Why it is fast: all vertical beams of one azimuth share the same horizontal line, so the grid is
read once per (azimuth, sample); a beam of elevation ``e`` hits sample ``k`` when the column there
rises above it, ``(h_k - z) / r_k > tan e``. The running maximum of that slope along the beam is
monotone, so the first hit of every elevation is one ``searchsorted``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from safenav.envs.config import EnvConfig


@dataclass(frozen=True)
class RangeImageSpec:
    """Beam layout of the range image: ``len(v_angles) x h_beams`` beams of ``max_range`` m."""

    h_beams: int = 36
    v_angles: tuple[float, ...] = (-10.0, 0.0, 10.0, 20.0)
    max_range: float = 4.0
    resolution: float = 0.1  # sample spacing along the beam = grid resolution

    @staticmethod
    def for_config(cfg: EnvConfig) -> RangeImageSpec:
        return RangeImageSpec(
            h_beams=cfg.lidar_h_beams,
            v_angles=tuple(cfg.lidar_v_angles),
            max_range=cfg.lidar_range,
            resolution=cfg.grid_resolution,
        )

    @property
    def num_samples(self) -> int:
        return int(math.ceil(self.max_range / self.resolution))

    def azimuths(self, device=None) -> torch.Tensor:
        """Beam azimuths relative to the sensor heading (column 0 looks forward), radians."""
        return torch.arange(self.h_beams, device=device, dtype=torch.float32) * (
            2 * math.pi / self.h_beams
        )

    def elevations(self, device=None) -> torch.Tensor:
        return torch.tensor(self.v_angles, device=device, dtype=torch.float32) * (math.pi / 180)


def raycast_height_map(
    heights: torch.Tensor,
    grid_origin: float,
    grid_size: int,
    pos: torch.Tensor,
    heading: torch.Tensor,
    spec: RangeImageSpec,
    cell_offset: torch.Tensor | None = None,
) -> torch.Tensor:
    """Hit distances of every beam, ``(N, V, H)`` in metres (``max_range`` = no hit).

    Args:
        heights: flat ``(W * G * G,)`` (or ``(G, G)``) height map(s), row index = x cell.
        grid_origin: x = y coordinate of the grid's lower corner.
        grid_size: ``G``, cells per side.
        pos: ``(N, 3)`` sensor positions; heading: ``(N,)`` yaw of beam column 0.
        cell_offset: ``(N,)`` flat offset of each sensor's map (``w * G * G``), or None.

    Accuracy: within one grid cell of the true distance to the occupied cells (the sample spacing
    equals the resolution; the hit is reported at the sample boundary before the first occupied
    sample).
    """
    heights = heights.reshape(-1)
    n = pos.shape[0]
    res = spec.resolution
    k = spec.num_samples
    dev = pos.device
    steps = torch.arange(k, device=dev, dtype=torch.float32) + 0.5  # sample k at (k + 0.5) res
    az = heading[:, None] + spec.azimuths(dev)[None, :]  # (N, H)
    # Cell coordinates of every sample, in units of cells; clamped so that beams stay on the grid.
    lo, hi = float(k + 1), float(grid_size - k - 2)
    fx = ((pos[:, 0] - grid_origin) / res).clamp(lo, hi)
    fy = ((pos[:, 1] - grid_origin) / res).clamp(lo, hi)
    ix = torch.floor(torch.addcmul(fx[:, None, None], torch.cos(az)[:, :, None], steps))
    iy = torch.floor(torch.addcmul(fy[:, None, None], torch.sin(az)[:, :, None], steps))
    flat = torch.addcmul(iy, ix, torch.tensor(float(grid_size), device=dev)).long()
    if cell_offset is not None:
        flat += cell_offset[:, None, None]
    h = heights[flat]  # (N, H, K)
    # Slope from the sensor to the column top; its running max is monotone along the beam.
    slope = (h - pos[:, 2, None, None]) * (1.0 / (steps * res))
    running = torch.cummax(slope, dim=-1).values.reshape(n * spec.h_beams, k)
    elev = spec.elevations(dev)
    tans = torch.tan(elev).expand(n * spec.h_beams, -1).contiguous()
    first = torch.searchsorted(running, tans, right=True)  # index of first hit, k = none
    cos_e = torch.cos(elev)
    reach = torch.floor(spec.max_range * cos_e / res + 1e-4)  # samples within range per elevation
    dist = first.to(torch.float32) * res / cos_e
    dist = torch.where(first.to(torch.float32) < reach, dist, torch.full_like(dist, spec.max_range))
    return dist.clamp(max=spec.max_range).reshape(n, spec.h_beams, -1).transpose(1, 2)


def raycast_boxes_bruteforce(
    box_lo: torch.Tensor,
    box_hi: torch.Tensor,
    pos: torch.Tensor,
    heading: torch.Tensor,
    spec: RangeImageSpec,
) -> torch.Tensor:
    """Reference ray caster: every beam against every box (slab method) and the ground plane.

    ``box_lo``/``box_hi``: ``(N, P, 3)`` corners of each sensor's boxes. Returns ``(N, V, H)``.
    """
    dev = pos.device
    az = heading[:, None] + spec.azimuths(dev)[None, :]  # (N, H)
    el = spec.elevations(dev)  # (V,)
    d = torch.stack(
        [
            torch.cos(el)[None, :, None] * torch.cos(az)[:, None, :],
            torch.cos(el)[None, :, None] * torch.sin(az)[:, None, :],
            torch.sin(el)[None, :, None].expand(pos.shape[0], -1, az.shape[1]),
        ],
        dim=-1,
    ).reshape(pos.shape[0], -1, 3)  # (N, B, 3)
    inv = 1.0 / torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)
    o = pos[:, None, None, :]
    t1 = (box_lo[:, None, :, :] - o) * inv[:, :, None, :]  # (N, B, P, 3)
    t2 = (box_hi[:, None, :, :] - o) * inv[:, :, None, :]
    t_near = torch.minimum(t1, t2).amax(-1)
    t_far = torch.maximum(t1, t2).amin(-1)
    hit = (t_far >= t_near) & (t_far >= 0)
    t = torch.where(hit, t_near.clamp(min=0), torch.full_like(t_near, math.inf)).amin(-1)
    ground = torch.where(d[..., 2] < 0, -pos[:, None, 2] / d[..., 2].clamp(max=-1e-9), math.inf)
    t = torch.minimum(t, ground).clamp(max=spec.max_range)
    return t.reshape(pos.shape[0], len(spec.v_angles), spec.h_beams)


def box_surface_distance(
    rel: torch.Tensor, half: torch.Tensor
) -> torch.Tensor:
    """Distance from points to axis-aligned boxes (0 inside): ``rel`` = point - centre, ``(..., 3)``."""
    return (rel.abs() - half).clamp(min=0).norm(dim=-1)


def pillar_clearance(
    pos: torch.Tensor, pillar_xy: torch.Tensor, pillar_half: torch.Tensor, pillar_height: torch.Tensor
) -> torch.Tensor:
    """Distance from each point to its nearest pillar (ground-standing box), ``(N,)``.

    ``pillar_*``: ``(N, P, ...)`` or broadcastable ``(P, ...)``. Empty P gives +inf.
    """
    if pillar_xy.shape[-2] == 0:
        return torch.full(pos.shape[:1], math.inf, device=pos.device)
    dx = ((pos[:, None, 0] - pillar_xy[..., 0]).abs() - pillar_half).clamp(min=0)
    dy = ((pos[:, None, 1] - pillar_xy[..., 1]).abs() - pillar_half).clamp(min=0)
    dz = (pos[:, None, 2] - pillar_height).clamp(min=0)
    return (dx * dx + dy * dy + dz * dz).sqrt().amin(-1)


def moving_obstacle_clearance(
    rel: torch.Tensor, width: torch.Tensor, is_cuboid: torch.Tensor, uav_z: torch.Tensor,
    cuboid_height: float, cylinder_height: float,
) -> torch.Tensor:
    """Distance from the UAV to each moving obstacle's surface, ``(N, D)``.

    ``rel`` = obstacle centre - UAV, ``(N, D, 3)``. Cuboids are ``width x width x cuboid_height``
    boxes; cylinders of diameter ``width`` stand on the ground, ``cylinder_height`` tall.
    """
    half_w = width / 2
    box = (rel.abs() - torch.stack([half_w, half_w, torch.full_like(half_w, cuboid_height / 2)], -1))
    box = box.clamp(min=0).norm(dim=-1)
    horiz = (rel[..., :2].norm(dim=-1) - half_w).clamp(min=0)
    above = (uav_z[:, None] - cylinder_height).clamp(min=0)
    cyl = (horiz * horiz + above * above).sqrt()
    return torch.where(is_cuboid, box, cyl)


__all__ = [
    "RangeImageSpec",
    "box_surface_distance",
    "moving_obstacle_clearance",
    "pillar_clearance",
    "raycast_boxes_bruteforce",
    "raycast_height_map",
]
