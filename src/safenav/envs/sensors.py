"""Sensing as pure batched functions: the range image, obstacle clearances, tracked obstacles.

The range image (paper III-D) is ray-cast from a 2.5-D occupancy grid (a height map: the top of
the occupied column per cell, 0 = free) and the ground plane. The onboard runtime (:mod:`safenav.deploy`) builds
such a grid from depth images and calls the very same :func:`raycast_height_map`.

Why it is fast: all vertical beams of one azimuth share the same horizontal line, so the grid is
read once per (azimuth, sample); a beam of elevation ``e`` hits sample ``k`` when the column there
rises above it, ``(h_k - z) / r_k > tan e``. Occupied samples are few (a few per cent), so the
first hit of every elevation is a scatter-min over those alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from safenav.envs.config import EnvConfig

HEIGHT_QUANTUM = 0.025
"""Height-map unit in metres: maps are stored as uint8 (0 = free, top at most 6.375 m), a quarter of
the memory of float32, which keeps the ray caster's random reads in cache."""


def quantize_heights(heights: torch.Tensor) -> torch.Tensor:
    """Float heights (m) -> the uint8 map the ray caster reads (columns above 6.375 m are clipped,
    which no beam below 4.9 m of altitude can tell apart)."""
    return torch.round(heights / HEIGHT_QUANTUM).clamp(0, 255).to(torch.uint8)


def dequantize_heights(heights: torch.Tensor) -> torch.Tensor:
    """The uint8 map of :func:`quantize_heights` -> float32 heights (m); a float map is returned as
    float32, already in metres (the onboard map may hold either)."""
    if heights.dtype == torch.uint8:
        return heights.to(torch.float32) * HEIGHT_QUANTUM
    return heights.to(torch.float32)


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
    map_index: torch.Tensor | None = None,
) -> torch.Tensor:
    """Hit distances of every beam, ``(N, V, H)`` in metres (``max_range`` = no hit).

    Args:
        heights: ``(W, G, G)`` (or ``(G, G)``) uint8 height maps (:func:`quantize_heights`), first
            cell index = x.
        grid_origin: x = y coordinate of the grid's lower corner.
        grid_size: ``G``, cells per side.
        pos: ``(N, 3)`` sensor positions; heading: ``(N,)`` yaw of beam column 0.
        map_index: ``(N,)`` which of the ``W`` maps each sensor sees (None: map 0).

    Accuracy: within one grid cell of the true distance to the occupied cells (the sample spacing
    equals the resolution; a hit is reported at the start of the first occupied sample's step).
    The ground (z = 0) is hit analytically by beams that point down.
    """
    heights = heights.reshape(-1)
    n, nh, nv = pos.shape[0], spec.h_beams, len(spec.v_angles)
    res, k, dev = spec.resolution, spec.num_samples, pos.device
    steps = torch.arange(k, device=dev, dtype=torch.float32) + 0.5  # sample k at (k + 0.5) res
    az = heading[:, None] + spec.azimuths(dev)[None, :]  # (N, H)
    # Sample cells, in cell units; clamped so that beams stay on the grid. All values are > 0,
    # so truncation is floor. Map w's rows start at row w * G of the stacked maps.
    lo, hi = float(k + 1), float(grid_size - k - 2)
    fx = ((pos[:, 0] - grid_origin) / res).clamp(lo, hi)
    if map_index is not None:
        fx = fx + (map_index * grid_size).to(fx.dtype)
    fy = ((pos[:, 1] - grid_origin) / res).clamp(lo, hi)
    # int32 indices into a uint8 map: the cheapest gather on a CPU (measured: ~2.5x float32/int64).
    ix = torch.addcmul(fx[:, None, None], torch.cos(az)[:, :, None], steps).int()
    iy = torch.addcmul(fy[:, None, None], torch.sin(az)[:, :, None], steps).int()
    h = heights.index_select(0, ix.mul_(grid_size).add_(iy).view(-1))  # (N * H * K,) uint8
    elev = spec.elevations(dev)
    tans = torch.tan(elev)
    cos_e = torch.cos(elev)
    # Occupied samples are few: find them, then the first one each elevation's beam meets.
    # Sample k blocks beam e iff the column rises above it: (h_k - z) / r_k > tan e.
    occ = torch.nonzero(h).squeeze(-1)
    row, kk = occ // k, occ % k
    top = dequantize_heights(h[occ])
    slope = (top - pos[row // nh, 2]) / ((kk.to(torch.float32) + 0.5) * res)
    blocked = torch.bucketize(slope, tans)  # beams e < blocked are hit at kk
    first = torch.full((n * nh * (nv + 1),), k, dtype=torch.int64, device=dev)
    first.scatter_reduce_(0, row * (nv + 1) + blocked, kk, reduce="amin")
    first = first.view(n * nh, nv + 1)[:, 1:]
    first = torch.flip(torch.cummin(torch.flip(first, [-1]), -1).values, [-1])  # (N*H, V)
    reach = torch.floor(spec.max_range * cos_e / res + 1e-4)  # samples within range per elevation
    firstf = first.to(torch.float32)
    dist = torch.where(firstf < reach, firstf * res / cos_e, spec.max_range)
    # Ground hits of downward beams, analytic: z / sin(-e).
    z = pos[:, 2].clamp(min=0.0).repeat_interleave(nh)[:, None]
    down = torch.where(tans < 0, z / (-torch.sin(elev)).clamp(min=1e-9), math.inf)
    dist = torch.minimum(dist, down).clamp(max=spec.max_range)
    return dist.reshape(n, nh, nv).transpose(1, 2)


FAR_POINT = 1.0e4
"""Where a beam without a hit puts its point (metres): far beyond any range, so that rings of
remembered hits (the memory image, the memory shield) can hold "no point" in the same tensor."""


def beam_hit_points(ranges: torch.Tensor, pos: torch.Tensor, heading: torch.Tensor,
                    spec: RangeImageSpec, far: float = FAR_POINT) -> torch.Tensor:  # fmt: skip
    """World points where the beams of a range image hit: ``ranges`` ``(N, E, C)`` metres cast
    from ``pos`` ``(N, 3)`` with column 0 at ``heading`` ``(N,)``; ``(N, E * C, 3)``, a beam
    without a hit (its full range) put ``far`` away."""
    az = heading[:, None] + spec.azimuths(ranges.device)[None]  # (N, C)
    el = spec.elevations(ranges.device)[None, :, None]  # (1, E, 1)
    dirs = torch.stack([torch.cos(el) * torch.cos(az)[:, None], torch.cos(el) * torch.sin(az)[:, None],
                        torch.sin(el).expand(len(az), -1, az.shape[1])], -1)  # fmt: skip
    hits = pos[:, None, None] + ranges[..., None] * dirs
    return torch.where((ranges < spec.max_range - 1e-4)[..., None], hits, far).flatten(1, 2)


def memory_image(points: torch.Tensor, pos: torch.Tensor, heading: torch.Tensor,
                 cfg: EnvConfig) -> torch.Tensor:  # fmt: skip
    """The memory image (``EnvConfig.lidar_memory``) of remembered world points ``(N, ..., 3)``
    (e.g. :func:`beam_hit_points` of past range images) seen from ``pos`` ``(N, 3)`` with column
    0 at ``heading`` ``(N,)``: per (elevation row, azimuth column) cell of the range image's
    layout the nearest point within range, ``(range - d) / range``; ``(N, E, C)``. A point goes
    to the row of the nearest beam elevation (the lowest row also takes every point below it).
    The simulator and the onboard runtime both call it."""
    e, c, r = len(cfg.lidar_v_angles), cfg.lidar_h_beams, cfg.lidar_range
    rel = points.flatten(1, -2) - pos[:, None]
    dist = rel.norm(dim=-1)
    az = torch.atan2(rel[..., 1], rel[..., 0]) - heading[:, None]
    col = torch.round(az * (c / (2 * math.pi))).long() % c
    elev = torch.rad2deg(torch.atan2(rel[..., 2], rel[..., :2].norm(dim=-1)))
    angles = torch.tensor(cfg.lidar_v_angles, device=points.device, dtype=points.dtype)
    row = torch.bucketize(elev, (angles[1:] + angles[:-1]) / 2)  # nearest beam's elevation
    cell = torch.full((len(pos), e * c), r, device=points.device, dtype=points.dtype)
    cell.scatter_reduce_(1, row * c + col, dist.clamp(max=r), "amin")
    return ((r - cell) / r).view(-1, e, c)


def pillar_boxes(
    xy: torch.Tensor, half: torch.Tensor, height: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper corners ``(..., P, 3)`` of ground-standing square pillars (centres ``xy``
    ``(..., P, 2)``, half sides and heights ``(..., P)``), for :func:`raycast_boxes_bruteforce`."""
    lo = torch.cat([xy - half[..., None], torch.zeros_like(half)[..., None]], -1)
    hi = torch.cat([xy + half[..., None], height[..., None]], -1)
    return lo, hi


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


def box_surface_distance(rel: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
    """Distance from points to axis-aligned boxes (0 inside): ``rel`` = point - centre, ``(..., 3)``."""
    return (rel.abs() - half).clamp(min=0).norm(dim=-1)


def pillar_clearances(
    pos: torch.Tensor,
    pillar_xy: torch.Tensor,
    pillar_half: torch.Tensor,
    pillar_height: torch.Tensor,
) -> torch.Tensor:
    """Distance from each point to every pillar (ground-standing box), ``(..., P)``.

    ``pos``: ``(..., 3)``; ``pillar_*``: ``(..., P, ...)`` broadcastable against it.
    """
    dx = ((pos[..., None, 0] - pillar_xy[..., 0]).abs() - pillar_half).clamp(min=0)
    dy = ((pos[..., None, 1] - pillar_xy[..., 1]).abs() - pillar_half).clamp(min=0)
    dz = (pos[..., None, 2] - pillar_height).clamp(min=0)
    return (dx * dx + dy * dy + dz * dz).sqrt()


def pillar_clearance(
    pos: torch.Tensor,
    pillar_xy: torch.Tensor,
    pillar_half: torch.Tensor,
    pillar_height: torch.Tensor,
) -> torch.Tensor:
    """Distance from each point to its nearest pillar (ground-standing box), ``pos.shape[:-1]``.

    ``pos``: ``(..., 3)``; ``pillar_*``: ``(..., P, ...)`` broadcastable against it. No pillars: +inf.
    """
    if pillar_xy.shape[-2] == 0:
        return torch.full(pos.shape[:-1], math.inf, device=pos.device)
    return pillar_clearances(pos, pillar_xy, pillar_half, pillar_height).amin(-1)


def static_obstacle_features(
    pos: torch.Tensor,
    pillar_xy: torch.Tensor,
    pillar_half: torch.Tensor,
    pillar_height: torch.Tensor,
    cos_yaw: torch.Tensor,
    sin_yaw: torch.Tensor,
    num_tracked: int,
    max_range: float,
) -> torch.Tensor:
    """The ``static`` observation ``(..., num_tracked, STATIC_FEATURES)`` (``EnvConfig.static_tracked``;
    beyond the paper): the ``num_tracked`` pillars nearest ``pos`` by clearance (3-D distance to the
    ground-standing box, :func:`pillar_clearances`) within ``max_range``, nearest first, zero rows
    beyond. Row layout (``safenav.envs.config.STATIC_FEATURES``): the footprint's nearest point
    relative to the UAV in the goal frame / range (x, y), the centre likewise (x, y), half side /
    0.4 m, (top - UAV altitude) / range, 1.

    ``pos`` ``(..., 3)``; ``pillar_xy`` ``(..., P, 2)``, ``pillar_half`` and ``pillar_height``
    ``(..., P)`` broadcastable against it (e.g. one map's pillars for many UAVs); ``cos_yaw``,
    ``sin_yaw`` ``(...)`` the goal-frame yaw.
    """
    from safenav.envs.config import STATIC_FEATURES

    lead = torch.broadcast_shapes(pos.shape[:-1], pillar_xy.shape[:-2])
    out = torch.zeros(*lead, num_tracked, STATIC_FEATURES, dtype=pos.dtype, device=pos.device)
    if pillar_xy.shape[-2] == 0 or num_tracked == 0:
        return out
    centre = pillar_xy - pos[..., None, :2]  # (..., P, 2)
    half = pillar_half[..., None]
    near = torch.clamp(torch.zeros_like(centre), min=centre - half, max=centre + half)
    clear = pillar_clearances(pos, pillar_xy, pillar_half, pillar_height)  # (..., P)
    kk = min(num_tracked, clear.shape[-1])
    d_sel, idx = torch.topk(clear, kk, dim=-1, largest=False)
    pick = lambda t: torch.gather(t.expand(*clear.shape), -1, idx)  # noqa: E731  rows of (..., P)
    c, s_ = cos_yaw[..., None], sin_yaw[..., None]

    def goal_frame(v: torch.Tensor) -> list[torch.Tensor]:  # (..., P, 2) -> picked rows, goal frame
        x, y = pick(v[..., 0]), pick(v[..., 1])
        return [(c * x + s_ * y) / max_range, (-s_ * x + c * y) / max_range]

    feats = torch.stack([
        *goal_frame(near), *goal_frame(centre), pick(pillar_half) / 0.4,
        (pick(pillar_height) - pos[..., None, 2]) / max_range,
        torch.ones_like(d_sel),
    ], -1)  # fmt: skip
    out[..., :kk, :] = torch.where((d_sel <= max_range)[..., None], feats, 0.0)
    return out


FAR_FOOTPRINT = 1.0e4
"""Centre coordinate (m) of a padding footprint of :func:`map_footprints`: never within range."""


def map_footprints(
    heights: torch.Tensor,
    occupied: torch.Tensor,
    origin: float,
    resolution: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pillar list as a height map shows it: each 4-connected group of ``occupied`` cells one
    footprint (its bounding box in the grid, as a square of the larger half side, and the tallest
    column in it), so that the onboard runtime builds from its map what the env's ``static``
    entry holds (``EnvConfig.static_source = "map"``; beyond the paper).

    ``heights`` ``(..., G, G)`` column tops (m; first index x, as
    :class:`~safenav.envs.world.GridSpec`), ``occupied`` ``(..., G, G)`` bool (the columns that
    are obstacles: above the ground, not the border wall). Returns ``(xy (..., P, 2), half (...,
    P), top (..., P))`` for the inputs of :func:`static_obstacle_features`, ``P`` the most
    footprints of any map, the others padded with footprints of no size at ``FAR_FOOTPRINT``. A
    pillar's footprint is its rasterised cells' box, within half a cell of the true one per side;
    touching pillars make one footprint that covers both (conservative).
    """
    lead, g = heights.shape[:-2], heights.shape[-1]
    hs = heights.reshape(-1, g, g).float()
    occ = occupied.reshape(-1, g, g)
    none = g * g  # larger than any cell index: "no label"
    flat_index = torch.arange(g * g, dtype=torch.int32, device=hs.device).reshape(g, g)
    labels = torch.where(occ, flat_index, none)
    while True:  # each cell takes the least label of its group (at most the group's diameter)
        padded = torch.nn.functional.pad(labels, (1, 1, 1, 1), value=none)
        least = torch.minimum(torch.minimum(labels, padded[:, :-2, 1:-1]), padded[:, 2:, 1:-1])
        least = torch.minimum(torch.minimum(least, padded[:, 1:-1, :-2]), padded[:, 1:-1, 2:])
        least = torch.where(occ, least, none)
        if torch.equal(least, labels):
            break
        labels = least
    boxes = []
    for m in range(hs.shape[0]):
        ix, iy = torch.nonzero(occ[m], as_tuple=True)
        groups, member = torch.unique(labels[m, ix, iy], return_inverse=True)
        n = groups.numel()

        def reduce(values: torch.Tensor, how: str, n: int = n, member: torch.Tensor = member):
            out = torch.zeros(n, dtype=values.dtype, device=values.device)
            return out.scatter_reduce(0, member, values, how, include_self=False)

        x0, x1, y0, y1 = (
            reduce(ix, "amin"),
            reduce(ix, "amax"),
            reduce(iy, "amin"),
            reduce(iy, "amax"),
        )
        top = reduce(hs[m, ix, iy], "amax")
        centre = torch.stack([x0 + x1 + 1, y0 + y1 + 1], -1).float() * (resolution / 2) + origin
        half = torch.maximum(x1 - x0 + 1, y1 - y0 + 1).float() * (resolution / 2)
        boxes.append((centre, half, top))
    p = max([b[1].numel() for b in boxes], default=0)
    xy = hs.new_full((hs.shape[0], p, 2), FAR_FOOTPRINT)
    half, top = hs.new_zeros((hs.shape[0], p)), hs.new_zeros((hs.shape[0], p))
    for m, (c, h, t) in enumerate(boxes):
        xy[m, : h.numel()], half[m, : h.numel()], top[m, : h.numel()] = c, h, t
    return xy.reshape(*lead, p, 2), half.reshape(*lead, p), top.reshape(*lead, p)


def moving_obstacle_clearance(
    rel: torch.Tensor,
    width: torch.Tensor,
    is_cuboid: torch.Tensor,
    uav_z: torch.Tensor,
    cuboid_height: float,
    cylinder_height: float,
) -> torch.Tensor:
    """Distance from the UAV to each moving obstacle's surface, ``(..., D)``.

    ``rel`` = obstacle centre - UAV, ``(..., D, 3)``; ``uav_z``: ``(...)``. Cuboids are ``width x width x cuboid_height``
    boxes; cylinders of diameter ``width`` stand on the ground, ``cylinder_height`` tall.
    """
    half_w = width / 2
    box = rel.abs() - torch.stack([half_w, half_w, torch.full_like(half_w, cuboid_height / 2)], -1)
    box = box.clamp(min=0).norm(dim=-1)
    horiz = (rel[..., :2].norm(dim=-1) - half_w).clamp(min=0)
    above = (uav_z[..., None] - cylinder_height).clamp(min=0)
    cyl = (horiz * horiz + above * above).sqrt()
    return torch.where(is_cuboid, box, cyl)


__all__ = [
    "FAR_POINT",
    "HEIGHT_QUANTUM",
    "RangeImageSpec",
    "beam_hit_points",
    "dynamic_obstacle_features",
    "memory_image",
    "map_footprints",
    "FAR_FOOTPRINT",
    "quantize_heights",
    "dequantize_heights",
    "box_surface_distance",
    "moving_obstacle_clearance",
    "pillar_boxes",
    "pillar_clearance",
    "pillar_clearances",
    "raycast_boxes_bruteforce",
    "raycast_height_map",
    "static_obstacle_features",
]


def dynamic_obstacle_features(
    rel: torch.Tensor,
    vel: torch.Tensor,
    width: torch.Tensor,
    is_cuboid: torch.Tensor,
    cos_yaw: torch.Tensor,
    sin_yaw: torch.Tensor,
    num_tracked: int,
    max_range: float,
    v_max: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``dynamic`` observation ``(..., num_tracked, 10)``, from obstacle geometry.

    The env (:class:`~safenav.envs.nav.SafeNavVectorEnv`) and the onboard runtime
    (:mod:`safenav.deploy.runtime`) both call it, so deployment computes exactly what training saw.

    Args:
        rel: ``(..., D, 3)`` obstacle centre - UAV (world); vel: ``(..., D, 3)`` obstacle
            velocities; width: ``(..., D)`` widths (m); is_cuboid: ``(..., D)`` floating 1 m cuboid
            (else a standing cylinder, whose relative z is taken as zero). ``vel``, ``width`` and
            ``is_cuboid`` may broadcast against ``rel`` (e.g. one map's obstacles for many UAVs).
        cos_yaw, sin_yaw: ``(...)`` goal-frame yaw.

    Returns ``(features, idx, in_range)``: the features of the ``num_tracked`` horizontally nearest
    obstacles within ``max_range`` (zero rows beyond), their indices ``(..., kk)`` into ``D`` and
    the in-range mask ``(..., kk)``, ``kk = min(num_tracked, D)``. Feature layout: unit relative
    position in the goal frame (3), horizontal distance / range (1), z distance / range (1),
    velocity in the goal frame / v_max (3), width class in [0, 1] (1), 1 for cuboids (1).
    """
    from safenav.envs.dynamics import world_to_goal_frame
    from safenav.envs.world import DYN_WIDTHS

    lead, nd = rel.shape[:-2], rel.shape[-2]
    k = num_tracked
    dynamic = torch.zeros(*lead, k, 10, device=rel.device, dtype=rel.dtype)
    kk = min(k, nd)
    if nd == 0:
        empty = torch.zeros(*lead, 0, dtype=torch.int64, device=rel.device)
        return dynamic, empty, empty.bool()
    # Standing cylinders span all altitudes: their relative z is zero (NavRL).
    rel = torch.cat([rel[..., :2], torch.where(is_cuboid, rel[..., 2], 0.0)[..., None]], -1)
    d2_sel, idx = torch.topk(rel[..., :2].norm(dim=-1), kk, dim=-1, largest=False)
    in_range = (d2_sel <= max_range)[..., None]

    def g(t: torch.Tensor) -> torch.Tensor:  # the tracked obstacles' rows of ``t``
        if t.dim() == rel.dim() - 1:
            return torch.gather(t.expand(*lead, nd), -1, idx)
        return torch.gather(t.expand(*lead, nd, t.shape[-1]), -2,
                            idx[..., None].expand(*idx.shape, t.shape[-1]))  # fmt: skip

    rel_gf = world_to_goal_frame(g(rel), cos_yaw[..., None], sin_yaw[..., None])
    unit = rel_gf / rel_gf.norm(dim=-1, keepdim=True).clamp(min=1e-6)
    width_class = (g(width) / DYN_WIDTHS[0] - 1.0) / (len(DYN_WIDTHS) - 1)
    feats = torch.cat([
        unit, d2_sel[..., None] / max_range, rel_gf[..., 2:3] / max_range,
        world_to_goal_frame(g(vel), cos_yaw[..., None], sin_yaw[..., None]) / v_max,
        width_class[..., None], g(is_cuboid).to(rel.dtype)[..., None],
    ], -1)  # fmt: skip
    dynamic[..., :kk, :] = torch.where(in_range, feats, 0.0)
    return dynamic, idx, in_range[..., 0]
