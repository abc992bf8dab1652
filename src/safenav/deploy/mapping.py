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

from safenav.deploy import kernels
from safenav.deploy.camera import backproject
from safenav.deploy.perception_link import DepthImage
from safenav.envs import sensors as _sensors
from safenav.envs.world import WALL_HEIGHT, GridSpec, border_walls


def height_map_walls(grid: GridSpec, half: float) -> torch.Tensor:
    """Flat ``(G * G,)`` heights: ``WALL_HEIGHT`` outside the ``[-half, half]^2`` arena, else 0."""
    return border_walls(grid, half).reshape(-1).to(torch.float32) * WALL_HEIGHT


_QUANTIZE = getattr(_sensors, "quantize_heights", None)


class HeightMap:
    """A world-fixed height map over ``grid``, updated from sensor data.

    Args:
        grid: cells and origin (use ``GridSpec.for_config(cfg)`` to cover the env's map).
        ground_band: points below this altitude (m) are ground and leave the map unchanged.
        exclusion_margin: tracked obstacles' boxes are inflated by this much (m) when points
            inside them are left out of the map.
        geofence: half side (m) of the arena whose border is a wall in the map (None: no wall).
    """

    def __init__(
        self,
        grid: GridSpec,
        ground_band: float = 0.05,
        exclusion_margin: float = 0.25,
        surface_offset: float | None = None,
        compiled: bool | None = None,
        geofence: float | None = None,
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
        # The arena's border as the simulator's wall (cells outside [-geofence, geofence]^2): the
        # map's floor, which sensor data raises and clear() restores.
        self.floor = torch.zeros(g * g, dtype=torch.float32)
        if geofence is not None:
            self.floor = height_map_walls(grid, float(geofence))
        self.heights = self.floor.clone()
        # The map in the ray caster's storage format (uint8 quanta if the env uses them).
        self.cast_map = _QUANTIZE(self.heights) if _QUANTIZE is not None else self.heights
        self.points_inserted = 0
        self._mask = np.zeros((g, g), dtype=bool)  # scratch grid for the obstacle exclusion
        # Depth insertion through the compiled kernel (kernels) when Numba is installed.
        self.compiled = kernels.AVAILABLE if compiled is None else bool(compiled)
        if self.compiled and not kernels.AVAILABLE:
            raise ValueError("compiled=True needs Numba (pip install 'safenav[deploy]')")

    def clear(self) -> None:
        """Forget all sensor data (the geofence wall stays)."""
        self.heights.copy_(self.floor)
        self.cast_map.copy_(_QUANTIZE(self.heights) if _QUANTIZE is not None else self.heights)
        self.points_inserted = 0

    def insert_points(self, points, exclude_boxes=None, normals=None) -> int:
        """Raise the columns under ``points`` ``(P, 3)`` (world); returns how many were used.

        ``exclude_boxes``: ``(M, 2, 3)`` ``[lo, hi]`` corners of tracked obstacles; points inside
        (inflated by ``exclusion_margin``) are not inserted. Non-finite points are skipped.
        ``normals``: ``(P, 3)`` unit surface normals facing the sensor (or the reversed viewing
        rays); points on steep surfaces are moved ``surface_offset`` horizontally into them.
        Array-likes (NumPy, CPU tensors) are accepted.
        """
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        g, res, origin = self.grid.size, self.grid.resolution, self.grid.origin
        with np.errstate(invalid="ignore"):
            keep = np.isfinite(pts).all(-1) & (pts[:, 2] > self.ground_band)
        pts = pts[keep]
        x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
        if normals is not None and self.surface_offset > 0:
            nxy = np.asarray(normals, dtype=np.float32).reshape(-1, 3)[keep, :2]
            nn = np.sqrt(nxy[:, 0] ** 2 + nxy[:, 1] ** 2)
            k = np.where(nn > 0.5, -self.surface_offset / np.maximum(nn, 1e-6), 0.0)
            x, y = x + nxy[:, 0] * k, y + nxy[:, 1] * k
        ix = np.floor((x - origin) / res).astype(np.int64)
        iy = np.floor((y - origin) / res).astype(np.int64)
        on = (ix >= 0) & (ix < g) & (iy >= 0) & (iy < g)
        if exclude_boxes is not None and len(exclude_boxes):
            on &= ~self._inside_boxes(
                ix, iy, x, y, z, on, np.asarray(exclude_boxes, dtype=np.float32)
            )
        flat = ix[on] * g + iy[on]
        if flat.size == 0:
            return 0
        cells = torch.from_numpy(flat)
        self.heights.scatter_reduce_(
            0, cells, torch.from_numpy(np.ascontiguousarray(z[on])), reduce="amax"
        )
        return self._written(cells)

    def _written(self, cells: torch.Tensor) -> int:
        """Bring the cast map's ``cells`` (flat indices, repeats allowed) up to date with the
        heights and count them as inserted points; returns how many."""
        if _QUANTIZE is not None:
            self.cast_map[cells] = _QUANTIZE(self.heights[cells])
        self.points_inserted += int(cells.numel())
        return int(cells.numel())

    def _inside_boxes(self, ix, iy, x, y, z, on, boxes: np.ndarray) -> np.ndarray:
        """Which points lie inside the inflated boxes: cells under the boxes' footprints first
        (a mask on the grid), then the exact test on those few points."""
        g, res, origin = self.grid.size, self.grid.resolution, self.grid.origin
        lo = boxes[:, 0] - self.exclusion_margin
        hi = boxes[:, 1] + self.exclusion_margin
        c0 = np.clip(np.floor((lo[:, :2] - origin) / res).astype(np.int64), 0, g)
        c1 = np.clip(np.floor((hi[:, :2] - origin) / res).astype(np.int64) + 1, 0, g)
        for (a0, b0), (a1, b1) in zip(c0, c1, strict=True):
            self._mask[a0:a1, b0:b1] = True
        cand = np.flatnonzero(on)
        cand = cand[self._mask[ix[cand], iy[cand]]]
        for (a0, b0), (a1, b1) in zip(c0, c1, strict=True):
            self._mask[a0:a1, b0:b1] = False
        inside = np.zeros(ix.shape, dtype=bool)
        if cand.size:  # one box at a time: reductions over short trailing axes are slow in NumPy
            xc, yc, zc = x[cand], y[cand], z[cand]
            hit = np.zeros(cand.size, dtype=bool)
            for (x0, y0, z0), (x1, y1, z1) in zip(lo, hi, strict=True):
                hit |= (xc >= x0) & (xc <= x1) & (yc >= y0) & (yc <= y1) & (zc >= z0) & (zc <= z1)
            inside[cand] = hit
        return inside

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
            if self.compiled and np.ndim(imgs[0].depth) == 2:
                n += self._insert_depth_compiled(imgs, stride, max_range, exclude_boxes)
                continue
            pts, normals = backproject(
                np.stack([np.asarray(im.depth, dtype=np.float32) for im in imgs]),
                [im.fx for im in imgs], [im.fy for im in imgs], [im.cx for im in imgs], [im.cy for im in imgs],
                np.stack([np.asarray(im.R, dtype=np.float32).reshape(3, 3) for im in imgs]),
                np.stack([np.asarray(im.t, dtype=np.float32).reshape(3) for im in imgs]),
                stride=stride, max_range=max_range, with_normals=True,
            )  # fmt: skip
            n += self.insert_points(pts, exclude_boxes, normals)
        return n

    def _insert_depth_compiled(self, imgs, stride, max_range, exclude_boxes) -> int:
        """``insert_depth`` for images of one shape, in one pass of the Numba kernel."""
        f32 = np.float32
        depth = np.ascontiguousarray(np.stack([np.asarray(im.depth, dtype=f32) for im in imgs]))
        intr = [
            np.array([getattr(im, k) for im in imgs], dtype=f32) for k in ("fx", "fy", "cx", "cy")
        ]
        R = np.ascontiguousarray(
            np.stack([np.asarray(im.R, dtype=f32).reshape(3, 3) for im in imgs])
        )
        t = np.ascontiguousarray(np.stack([np.asarray(im.t, dtype=f32).reshape(3) for im in imgs]))
        boxes = (
            np.zeros((0, 2, 3), f32) if exclude_boxes is None else np.asarray(exclude_boxes, f32)
        )
        lo = np.ascontiguousarray(boxes[:, 0] - f32(self.exclusion_margin))
        hi = np.ascontiguousarray(boxes[:, 1] + f32(self.exclusion_margin))
        touched = np.empty(depth[:, ::stride, ::stride].size, dtype=np.int64)
        n = kernels.insert_depth_kernel(
            depth, *intr, R, t, int(stride), f32(max_range),
            f32(self.ground_band), f32(self.surface_offset), f32(self.grid.origin), f32(self.grid.resolution),
            lo, hi, self._mask, self.heights.numpy(), touched,
        )  # fmt: skip
        return self._written(torch.from_numpy(touched[:n]))


__all__ = ["HeightMap"]
