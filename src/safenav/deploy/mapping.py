"""The onboard occupancy grid: a 2.5-D height map built from depth images or point clouds.

Same layout as the simulator's map (:class:`safenav.envs.world.GridSpec`, first index = x cell,
value = top of the occupied column, 0 = free), so that :func:`safenav.envs.sensors.raycast_height_map`
ray-casts it exactly as it ray-casts the simulator's ground-truth map.

A point ``(x, y, z)`` above the ground band raises its cell's column to ``z`` (``amax``); points
inside a tracked moving obstacle (inflated) are left out, since those obstacles reach the policy
through the tracker, as in the env. Columns only grow: the map is for static obstacles (the paper's
setting); clearing stale cells by free-space carving is not implemented.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from safenav.deploy.camera import backproject
from safenav.deploy.perception_link import DepthImage
from safenav.envs import sensors as _sensors
from safenav.envs.world import GridSpec

_QUANTIZE = getattr(_sensors, "quantize_heights", None)


class HeightMap:
    """A world-fixed height map over ``grid``, updated from sensor data.

    Args:
        grid: cells and origin (use ``GridSpec.for_config(cfg)`` to cover the env's map).
        ground_band: points below this altitude (m) are ground and leave the map unchanged.
        exclusion_margin: tracked obstacles' boxes are inflated by this much (m) when points
            inside them are left out of the map.
    """

    def __init__(
        self,
        grid: GridSpec,
        ground_band: float = 0.05,
        exclusion_margin: float = 0.25,
        surface_offset: float | None = None,
    ) -> None:
        self.grid = grid
        # Returns lie on surfaces. Moving them half a cell into the obstacle (against the surface
        # normal) puts them in the first cell whose centre is inside it: the simulator's
        # rasterisation rule (occupied iff the cell centre is inside).
        self.surface_offset = (
            grid.resolution / 2 if surface_offset is None else float(surface_offset)
        )
        self.ground_band = float(ground_band)
        self.exclusion_margin = float(exclusion_margin)
        g = grid.size
        self.heights = torch.zeros(g * g, dtype=torch.float32)
        # The map in the ray caster's storage format (uint8 quanta if the env uses them).
        self.cast_map = _QUANTIZE(self.heights) if _QUANTIZE is not None else self.heights
        self.points_inserted = 0

    def clear(self) -> None:
        self.heights.zero_()
        self.cast_map.zero_()
        self.points_inserted = 0

    def insert_points(
        self,
        points: torch.Tensor,
        exclude_boxes: torch.Tensor | None = None,
        normals: torch.Tensor | None = None,
    ) -> int:
        """Raise the columns under ``points`` ``(P, 3)`` (world); returns how many were used.

        ``exclude_boxes``: ``(M, 2, 3)`` ``[lo, hi]`` corners of tracked obstacles; points inside
        (inflated by ``exclusion_margin``) are not inserted. Non-finite points are skipped.
        ``normals``: ``(P, 3)`` unit surface normals facing the sensor (or the reversed viewing
        rays); points on steep surfaces are moved ``surface_offset`` horizontally into them.
        """
        pts = points.to(torch.float32).reshape(-1, 3)
        if normals is not None and self.surface_offset > 0:
            nxy = normals.to(torch.float32).reshape(-1, 3)[:, :2]
            nn = nxy.norm(dim=-1, keepdim=True)
            shift = torch.where(nn > 0.5, nxy * (-self.surface_offset / nn.clamp(min=1e-6)), 0.0)
            pts = torch.cat([pts[:, :2] + shift, pts[:, 2:]], -1)
        keep = torch.isfinite(pts).all(-1) & (pts[:, 2] > self.ground_band)
        if exclude_boxes is not None and exclude_boxes.numel() > 0:
            lo = exclude_boxes[:, 0].to(torch.float32) - self.exclusion_margin
            hi = exclude_boxes[:, 1].to(torch.float32) + self.exclusion_margin
            inside = ((pts[:, None, :] >= lo[None]) & (pts[:, None, :] <= hi[None])).all(-1).any(-1)
            keep &= ~inside
        pts = pts[keep]
        g, res = self.grid.size, self.grid.resolution
        ix = torch.floor((pts[:, 0] - self.grid.origin) / res).long()
        iy = torch.floor((pts[:, 1] - self.grid.origin) / res).long()
        on = (ix >= 0) & (ix < g) & (iy >= 0) & (iy < g)
        flat, z = ix[on] * g + iy[on], pts[on, 2]
        if flat.numel() == 0:
            return 0
        self.heights.scatter_reduce_(0, flat, z, reduce="amax")
        if _QUANTIZE is not None:
            self.cast_map[flat] = _QUANTIZE(self.heights[flat])
        self.points_inserted += int(flat.numel())
        return int(flat.numel())

    def insert_depth(
        self,
        images: Sequence[DepthImage],
        stride: int = 1,
        max_range: float = math.inf,
        exclude_boxes: torch.Tensor | None = None,
    ) -> int:
        """Back-project depth images (pixels with NaN / 0 / beyond ``max_range`` skipped) and
        insert their points; returns how many were used. Images of one shape go as one batch."""
        n = 0
        groups: dict[tuple[int, ...], list[DepthImage]] = {}
        for img in images:
            groups.setdefault(tuple(np.shape(img.depth)), []).append(img)
        for imgs in groups.values():
            f32 = lambda xs: torch.as_tensor(np.asarray(xs, dtype=np.float32))  # noqa: E731
            depth = f32([im.depth for im in imgs])
            t = f32([np.asarray(im.t).reshape(3) for im in imgs])
            pts, normals = backproject(
                depth, f32([im.fx for im in imgs]), f32([im.fy for im in imgs]),
                f32([im.cx for im in imgs]), f32([im.cy for im in imgs]),
                f32([np.asarray(im.R).reshape(3, 3) for im in imgs]), t,
                stride=stride, max_range=max_range, with_normals=True,
            )  # fmt: skip
            n += self.insert_points(pts, exclude_boxes, normals)
        return n


__all__ = ["HeightMap"]
