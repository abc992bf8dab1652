"""World generation: pillars, moving obstacles and the occupancy grid (height map) of one map.

A world is drawn from one integer seed with NumPy, once per ``reset(seed=...)``; stepping never
touches it. Obstacles are generated at full count in random order, so the density curriculum
activates a prefix (``k`` first pillars) and a lower density is always a subset of a higher one.
Obstacles fill the whole map up to its border, which is a wall (:func:`border_walls`): the arena
is closed, and no obstacle-free ring joins starts to goals (SafeNav-v1).
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
WALL_HEIGHT = 6.0  # the border wall in the height map: above every beam the UAV can cast


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
    site_along: np.ndarray  # (4, S) start/goal sites: position along sides N, E, S, W (m)


def _sample_pillar_heights(rng: np.random.Generator, n: int) -> np.ndarray:
    probs = np.array([b[2] for b in PILLAR_HEIGHT_BINS])
    which = rng.choice(len(PILLAR_HEIGHT_BINS), size=n, p=probs / probs.sum())
    lows = np.array([b[0] for b in PILLAR_HEIGHT_BINS])[which]
    highs = np.array([b[1] for b in PILLAR_HEIGHT_BINS])[which]
    return rng.uniform(lows, highs)


def side_points(cfg: EnvConfig, side, along, z=None) -> np.ndarray:
    """Points ``edge_margin / 2`` from side ``side`` (0: north, 1: east, 2: south, 3: west) at
    ``along`` (x on north/south, y on east/west); NumPy or torch, broadcast; ``z`` appended."""
    lib = np if isinstance(along, np.ndarray) else torch
    edge = cfg.half - cfg.edge_margin / 2
    sign = lib.where((side == 0) | (side == 1), edge, -edge)
    horizontal = (side == 0) | (side == 2)  # north / south: along is x
    x, y = lib.where(horizontal, along, sign), lib.where(horizontal, sign, along)
    return lib.stack([x, y] if z is None else [x, y, z], -1)


def _draw_sites(rng: np.random.Generator, cfg: EnvConfig) -> np.ndarray:
    """``start_sites`` positions per side, one in each equal stretch (away from its ends), so
    that sites spread along the side and keep their clear discs apart."""
    s, span = cfg.start_sites, 2 * (cfg.half - cfg.edge_margin)
    offsets = rng.uniform(0.15, 0.85, size=(4, s))
    return -span / 2 + (np.arange(s) + offsets) * (span / s)


def _site_xy(cfg: EnvConfig, site_along: np.ndarray) -> np.ndarray:
    sides = np.repeat(np.arange(4), site_along.shape[1])
    return side_points(cfg, sides, site_along.reshape(-1))


def _place_pillars(
    rng: np.random.Generator, cfg: EnvConfig, sites: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Non-overlapping square pillars anywhere inside the map but the sites' clear discs, by
    rejection sampling."""
    n = cfg.num_static
    half_sides = rng.choice(np.asarray(cfg.pillar_sides, dtype=np.float64), size=n) / 2.0
    limit = cfg.half
    xy = np.zeros((n, 2))
    placed = 0
    tries = 0
    while placed < n:
        tries += 1
        if tries > 200 * n + 1000:
            raise ValueError(
                f"EnvConfig.num_static={n} is invalid: could place only {placed} non-overlapping "
                f"pillars in the {2 * limit:.1f} m map"
            )
        hs = half_sides[placed]
        cand = rng.uniform(-limit + hs, limit - hs, size=2)
        if placed:
            gap = np.abs(xy[:placed] - cand) - (half_sides[:placed, None] + hs)
            if np.any(np.all(gap < 0.0, axis=1)):  # boxes overlap iff they overlap on both axes
                continue
        near = (np.abs(sites - cand) - hs).clip(min=0)
        if np.any((near * near).sum(-1) < cfg.start_clearance**2):
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
    site_along = _draw_sites(rng, cfg)
    sites = _site_xy(cfg, site_along)
    xy, half = _place_pillars(rng, cfg, sites)
    heights = _sample_pillar_heights(rng, cfg.num_static)

    d = cfg.num_dynamic
    classes = rng.permutation(np.arange(d) % (2 * len(DYN_WIDTHS)))
    widths = np.asarray(DYN_WIDTHS)[classes % len(DYN_WIDTHS)]
    is_cuboid = classes < len(DYN_WIDTHS)
    limit = cfg.mover_limit
    origin = np.zeros((d, 3))
    origin[:, :2] = rng.uniform(-limit, limit, size=(d, 2))
    for _ in range(1000):  # redraw origins inside a site's clear disc
        gap = np.linalg.norm(origin[:, None, :2] - sites[None], axis=-1) - widths[:, None] / 2
        inside = (gap < cfg.start_clearance).any(-1)
        if not inside.any():
            break
        origin[inside, :2] = rng.uniform(-limit, limit, size=(int(inside.sum()), 2))
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
        site_along=site_along.astype(np.float32),
    )


def world_from_obstacles(
    cfg: EnvConfig,
    pillars: list[tuple[float, float, float, float]] = (),
    movers: list[tuple[float, float, float, float, bool]] = (),
    seed: int = 0,
) -> World:
    """A hand-made world: ``pillars`` as ``(x, y, side, height)``, moving obstacles as
    ``(x, y, z, width, is_cuboid)`` (their origins). For tests and custom maps; obstacles beyond
    ``cfg.num_static`` / ``cfg.num_dynamic`` are an error. Start/goal sites are evenly spaced
    along each side (obstacles placed on them are the caller's choice)."""
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
    span = 2 * (cfg.half - cfg.edge_margin)
    even = -span / 2 + (np.arange(cfg.start_sites) + 0.5) * (span / cfg.start_sites)
    grid = GridSpec.for_config(cfg)
    return World(
        seed=seed, pillar_xy=xy.astype(np.float32), pillar_half=half.astype(np.float32),
        pillar_height=heights.astype(np.float32), dyn_origin=origin.astype(np.float32),
        dyn_width=width.astype(np.float32), dyn_is_cuboid=cuboid,
        pillar_rank_grid=_rasterize(grid, p[:, :2], p[:, 2] / 2),
        site_along=np.tile(even, (4, 1)).astype(np.float32),
    )  # fmt: skip


def border_walls(grid: GridSpec, half: float) -> torch.Tensor:
    """``(G, G)`` bool: the cells outside the ``[-half, half]^2`` map (by their centres, the
    rasterisation rule of pillars), i.e. the border wall that the range sensor sees."""
    centres = grid.origin + (torch.arange(grid.size, dtype=torch.float64) + 0.5) * grid.resolution
    outside = centres.abs() > half
    return outside[:, None] | outside[None, :]


def height_map(
    world: World, active_pillars: int, walls: torch.Tensor | None = None
) -> torch.Tensor:
    """The 2.5-D occupancy grid: top of the occupied column per cell (0 = free), float32;
    ``walls`` (from :func:`border_walls`) are ``WALL_HEIGHT`` tall."""
    rank = torch.from_numpy(world.pillar_rank_grid).long()
    heights = torch.cat([torch.from_numpy(world.pillar_height), torch.zeros(1)])
    active = (rank >= 0) & (rank < active_pillars)
    out = torch.where(active, heights[rank.clamp(min=0)], torch.zeros(()))
    if walls is not None:
        out = torch.where(walls, torch.tensor(WALL_HEIGHT), out)
    return out


def border_clearance(pos: torch.Tensor, half: float) -> torch.Tensor:
    """Horizontal distance from each point ``(..., >=2)`` to the border wall (negative outside)."""
    return half - pos[..., :2].abs().amax(-1)


__all__ = ["WALL_HEIGHT", "GridSpec", "World", "border_clearance", "border_walls",
           "generate_world", "height_map", "side_points", "world_from_obstacles"]  # fmt: skip
