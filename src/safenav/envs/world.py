"""World generation: pillars, moving obstacles and the occupancy grid (height map) of one map.

A world is drawn from one integer seed with NumPy, once per ``reset(seed=...)``; stepping never
touches it. Obstacles are generated at full count in random order, so the density curriculum
activates a prefix (``k`` first pillars) and a lower density is always a subset of a higher one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from safenav.envs.config import EnvConfig

# Pillar heights, piecewise uniform (NavRL): (low, high, probability).
PILLAR_HEIGHT_BINS = ((1.0, 1.5, 0.10), (1.5, 2.0, 0.15), (2.0, 4.0, 0.20), (4.0, 6.0, 0.55))
# Moving-obstacle classes (NavRL): 4 widths x {1 m floating cuboid, 5 m standing cylinder}.
DYN_WIDTHS = (0.25, 0.5, 0.75, 1.0)
CUBOID_HEIGHT = 1.0
CYLINDER_HEIGHT = 5.0
CUBOID_Z_RANGE = (0.5, 4.5)  # centre altitude of a floating cuboid (spans [0, 5] m)


@dataclass
class GridSpec:
    """Geometry of the occupancy grid: ``size x size`` cells of ``resolution`` m from ``origin``."""

    origin: float  # x (and y) of the grid's lower corner
    resolution: float
    size: int

    @staticmethod
    def for_config(cfg: EnvConfig) -> GridSpec:
        # Padding of one beam range plus a metre lets rays from slightly outside the map stay inside.
        pad = cfg.lidar_range + 1.0
        size = int(math.ceil((cfg.map_size + 2 * pad) / cfg.grid_resolution))
        return GridSpec(origin=-cfg.half - pad, resolution=cfg.grid_resolution, size=size)


@dataclass
class World:
    """One map, as NumPy arrays (obstacles in random order: prefixes are the density subsets)."""

    seed: int
    pillar_xy: np.ndarray  # (P, 2) centres
    pillar_half: np.ndarray  # (P,) half side of the square footprint
    pillar_height: np.ndarray  # (P,)
    dyn_origin: np.ndarray  # (D, 3)
    dyn_width: np.ndarray  # (D,)
    dyn_is_cuboid: np.ndarray  # (D,) bool
    pillar_rank_grid: np.ndarray  # (G, G) int32: index of the pillar covering a cell, -1 free


def _sample_pillar_heights(rng: np.random.Generator, n: int) -> np.ndarray:
    probs = np.array([b[2] for b in PILLAR_HEIGHT_BINS])
    which = rng.choice(len(PILLAR_HEIGHT_BINS), size=n, p=probs / probs.sum())
    lows = np.array([b[0] for b in PILLAR_HEIGHT_BINS])[which]
    highs = np.array([b[1] for b in PILLAR_HEIGHT_BINS])[which]
    return rng.uniform(lows, highs)


def _place_pillars(rng: np.random.Generator, cfg: EnvConfig) -> tuple[np.ndarray, np.ndarray]:
    """Non-overlapping square pillars inside the interior, by batched rejection sampling."""
    n = cfg.num_static
    half_sides = rng.choice(np.asarray(cfg.pillar_sides, dtype=np.float64), size=n) / 2.0
    limit = cfg.half - cfg.edge_margin
    xy = np.zeros((n, 2))
    placed = 0
    tries = 0
    while placed < n:
        tries += 1
        if tries > 200 * n + 1000:
            raise ValueError(
                f"EnvConfig.num_static={n} is invalid: could place only {placed} non-overlapping "
                f"pillars in the {2 * limit:.1f} m interior"
            )
        hs = half_sides[placed]
        cand = rng.uniform(-limit + hs, limit - hs, size=2)
        if placed:
            gap = np.abs(xy[:placed] - cand) - (half_sides[:placed, None] + hs)
            if np.any(np.all(gap < 0.0, axis=1)):  # boxes overlap iff they overlap on both axes
                continue
        xy[placed] = cand
        placed += 1
    return xy, half_sides


def _rasterize(grid: GridSpec, xy: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Cells whose centres lie inside a pillar's footprint hold that pillar's index."""
    rank = np.full((grid.size, grid.size), -1, dtype=np.int32)
    res = grid.resolution
    for i, ((cx, cy), h) in enumerate(zip(xy, half, strict=True)):
        # cell k has centre origin + (k + 0.5) res; inside iff |centre - c| <= h
        x0 = int(math.ceil((cx - h - grid.origin) / res - 0.5))
        x1 = int(math.floor((cx + h - grid.origin) / res - 0.5))
        y0 = int(math.ceil((cy - h - grid.origin) / res - 0.5))
        y1 = int(math.floor((cy + h - grid.origin) / res - 0.5))
        rank[max(x0, 0) : x1 + 1, max(y0, 0) : y1 + 1] = i
    return rank


def generate_world(cfg: EnvConfig, seed: int) -> World:
    """Draw a full-density world from ``seed`` (deterministic on every machine)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x5AFE]))
    xy, half = _place_pillars(rng, cfg)
    heights = _sample_pillar_heights(rng, cfg.num_static)

    d = cfg.num_dynamic
    classes = rng.permutation(np.arange(d) % (2 * len(DYN_WIDTHS)))
    widths = np.asarray(DYN_WIDTHS)[classes % len(DYN_WIDTHS)]
    is_cuboid = classes < len(DYN_WIDTHS)
    limit = cfg.half - cfg.edge_margin - 0.5  # obstacle surfaces stay out of the edge band
    origin = np.zeros((d, 3))
    origin[:, :2] = rng.uniform(-limit, limit, size=(d, 2))
    origin[:, 2] = np.where(is_cuboid, rng.uniform(*CUBOID_Z_RANGE, size=d), CYLINDER_HEIGHT / 2.0)
    grid = GridSpec.for_config(cfg)
    return World(
        seed=int(seed),
        pillar_xy=xy.astype(np.float32),
        pillar_half=half.astype(np.float32),
        pillar_height=heights.astype(np.float32),
        dyn_origin=origin.astype(np.float32),
        dyn_width=widths.astype(np.float32),
        dyn_is_cuboid=is_cuboid,
        pillar_rank_grid=_rasterize(grid, xy, half),
    )


def world_from_obstacles(
    cfg: EnvConfig,
    pillars: list[tuple[float, float, float, float]] = (),
    movers: list[tuple[float, float, float, float, bool]] = (),
    seed: int = 0,
) -> World:
    """A hand-made world: ``pillars`` as ``(x, y, side, height)``, moving obstacles as
    ``(x, y, z, width, is_cuboid)`` (their origins). For tests and custom maps; obstacles beyond
    ``cfg.num_static`` / ``cfg.num_dynamic`` are an error."""
    if len(pillars) > cfg.num_static or len(movers) > cfg.num_dynamic:
        raise ValueError(f"world_from_obstacles: {len(pillars)} pillars / {len(movers)} movers exceed "
                         f"num_static={cfg.num_static} / num_dynamic={cfg.num_dynamic}")  # fmt: skip
    p = np.asarray(pillars, dtype=np.float64).reshape(-1, 4)
    m = np.asarray(movers, dtype=np.float64).reshape(-1, 5)
    # Unused slots: far outside the map, never active at the configured counts.
    far = cfg.half + 1000.0
    xy = np.concatenate([p[:, :2], np.full((cfg.num_static - len(p), 2), far)])
    half = np.concatenate([p[:, 2] / 2, np.full(cfg.num_static - len(p), 0.2)])
    heights = np.concatenate([p[:, 3], np.zeros(cfg.num_static - len(p))])
    origin = np.concatenate([m[:, :3], np.full((cfg.num_dynamic - len(m), 3), far)])
    width = np.concatenate([m[:, 3], np.full(cfg.num_dynamic - len(m), 0.25)])
    cuboid = np.concatenate([m[:, 4] > 0.5, np.ones(cfg.num_dynamic - len(m), dtype=bool)])
    grid = GridSpec.for_config(cfg)
    return World(
        seed=seed, pillar_xy=xy.astype(np.float32), pillar_half=half.astype(np.float32),
        pillar_height=heights.astype(np.float32), dyn_origin=origin.astype(np.float32),
        dyn_width=width.astype(np.float32), dyn_is_cuboid=cuboid,
        pillar_rank_grid=_rasterize(grid, p[:, :2], p[:, 2] / 2),
    )  # fmt: skip


def height_map(world: World, active_pillars: int) -> torch.Tensor:
    """The 2.5-D occupancy grid: top of the occupied column per cell (0 = free), float32."""
    rank = torch.from_numpy(world.pillar_rank_grid).long()
    heights = torch.cat([torch.from_numpy(world.pillar_height), torch.zeros(1)])
    active = (rank >= 0) & (rank < active_pillars)
    return torch.where(active, heights[rank.clamp(min=0)], torch.zeros(()))


__all__ = ["GridSpec", "World", "generate_world", "height_map", "world_from_obstacles"]
