"""How hard is SafeNav-v1 itself? A privileged planner flies the validation episodes
(docs/csac-v1.md, "A privileged planner: how hard is the scenario?").

:class:`OraclePlanner` is a sampling-based model-predictive planner that reads the simulator's
true state: every pillar (footprint and height), the border wall, every moving obstacle's position,
size and current velocity. Each control step, for all unfinished episodes at once (batched):

1. **Candidates**: ``headings`` bearings (evenly spaced, the first straight at the goal) x
   ``speeds`` x ``climbs`` (vertical speeds) constant velocity commands, plus hover and
   :func:`~safenav.envs.scripted.go_to_goal`'s command. Each becomes the env's action (goal frame,
   / ``v_max``, clipped to [-1, 1]) and is rolled out as the env will apply that action.
2. **Rollout**: each command held for ``horizon`` control steps through the env's own velocity
   tracker (:func:`~safenav.envs.dynamics.velocity_tracker`: same dt, substeps, 0.4 s lag,
   3 m/s^2 limit).
3. **Forecast** of the moving obstacles: constant velocity (``constant``), or the env's own
   obstacle model stepped ahead on a copy of its state (``exact``: perfect foresight of the
   speed changes and turns that are drawn from the map's seed).
4. **Score**: a candidate that collides under this model (clearance to a pillar, a moving
   obstacle or the wall at most ``uav_radius``, or outside the altitude band) before it reaches
   the goal is ruled out (when all are, the one that collides latest is flown). The rest score
   the cost-to-go at the horizon's end (``geodesic``: a Dijkstra field around the pillars on a
   0.25 m grid, combined with the altitude difference; ``euclid``: the straight distance), or
   minus the time left if they reach the goal, + 100 per metre of their deepest intrusion into
   the margins (``margin`` from pillars, wall and band limits, ``margin + mover_margin`` from
   moving obstacles), + ``w_clear`` x (``clear_cap`` - least clearance)+, + ``w_smooth`` x the
   change of the world-frame command (m/s). The lowest is flown; all is replanned every step.

``privileged_range`` limits its view to what a policy's observation holds: the pillars and wall
sides within that horizontal distance of the UAV (the range image's 4 m, though as exact
geometry, not 144 beams), and the ``num_tracked`` (5) nearest moving obstacles whose centres lie
within it (the ``dynamic`` observation's rule); by default with ``euclid`` progress (no map).
The oracle has no memory either way.

Validation maps only (the test and held-out seeds are refused). Run:
``.venv/bin/python experiments/oracle_planner.py --env-seeds 12345 12346 12347 12348
--episodes 104 [--horizon 20 --margin 0.1 --privileged-range 4 --forecast exact]
--json results/csac-v1/oracle/val.json``.
"""

from __future__ import annotations

import argparse
import ast
import copy
import dataclasses
import json
import math
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from safenav.envs.config import make_config
from safenav.envs.dynamics import goal_frame_to_world, velocity_tracker, world_to_goal_frame
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.scripted import go_to_goal
from safenav.envs.sensors import (
    RangeImageSpec,
    beam_hit_points,
    moving_obstacle_clearance,
    pillar_clearance,
)
from safenav.envs.world import CUBOID_HEIGHT, CYLINDER_HEIGHT, border_clearance
from safenav.experiments.evaluate import evaluate
from safenav.experiments.selection import RESERVED_SEEDS, VALIDATION_SEEDS

FAR = 1.0e4  # m: where obstacles outside the planner's view are put
W_MARGIN = 100.0  # cost per metre of intrusion into the margins (1 cm = 1 m of cost-to-go)


@dataclass(frozen=True)
class OracleConfig:
    """Settings of :class:`OraclePlanner`."""

    horizon: int = 20
    """Control steps each candidate command is held and checked for (20 = 2 s at 10 Hz)."""
    headings: int = 16
    """Horizontal directions, evenly spaced from the bearing of the goal."""
    speeds: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0)
    """Horizontal speeds of the candidates (m/s; the env clips each goal-frame axis to v_max)."""
    climbs: tuple[float, ...] = (-0.75, 0.0, 0.75)
    """Vertical speeds of the candidates (m/s)."""
    margin: float = 0.1
    """Clearance (m) beyond the UAV radius to keep from pillars, the wall and the altitude limits
    (an intrusion is penalised, a collision rules a candidate out)."""
    mover_margin: float = 0.6
    """Extra margin (m) from moving obstacles: they turn without slowing down when they reach a
    local goal, which a constant-velocity forecast does not see coming (0.6 chosen on training
    maps 100000-100001 among 0.2-0.8)."""
    clear_cap: float = 1.0
    """Clearance (m) above which a candidate earns no more for being clear."""
    w_clear: float = 0.5
    """Cost per metre of least clearance below ``clear_cap`` (in metres of cost-to-go)."""
    w_smooth: float = 0.1
    """Cost per m/s of change of the command."""
    privileged_range: float = math.inf
    """Horizontal range (m) within which pillars, wall and moving obstacles are seen; inf: all."""
    progress: str = "auto"
    """Cost-to-go: ``geodesic`` (around the pillars), ``euclid`` (straight); ``auto``: geodesic
    with full view, euclid with a limited ``privileged_range`` (no map)."""
    forecast: str = "constant"
    """Moving obstacles ahead: ``constant`` velocity or ``exact`` (the env's model, foresight)."""
    sense: str = "exact"
    """Pillars and wall: ``exact`` footprints and sides (within ``privileged_range``), or
    ``lidar``: only the points where the observation's beams hit (its range image, no memory), each
    as an obstacle point; with ``lidar`` the moving obstacles are the observation's too (the
    ``num_tracked`` nearest within its range)."""
    fill_gaps: bool = False
    """With ``lidar``: each hit point is a disc as wide as the gap to the next beam at its range
    (``d sin(pi / beams)``), as if what lies between two beams were solid (conservative); with
    ``memory`` > 1, ``d`` is a remembered point's range from where the UAV is now."""
    memory: int = 1
    """With ``lidar``: the hit points of the last ``memory`` range images (each placed in the world
    from where it was taken; an episode starts with none), 1 = the current image only."""
    map_scan: bool = False
    """With ``lidar``: also the hits of the flight shield's map scan (``map_scan_hits``: 72 level
    beams on the height map from the UAV's lower extent, the nearest 24), each a column that spans
    all altitudes (tested in the horizontal plane, as the shield tests them): what the learned
    policies' flight shield knows beside the range image."""
    cruise: float | None = None
    """Altitude (m) to hold while the goal is farther than ``cruise_until`` horizontally: the
    cost-to-go there is the horizontal one plus ``|z - cruise|`` (a Euclidean combination would
    weigh 1 m of altitude 20 m from the goal at 2.5 cm); None: the goal's altitude throughout.
    Low enough, the level beam sees every pillar's side (the shortest is 1 m) instead of losing a
    low pillar's top below the lowest beam as the UAV closes in. Use with ``ignore_ground``."""
    cruise_until: float = 5.0
    """Horizontal distance (m) from the goal within which ``cruise`` gives way to the goal's
    altitude (at 0.75 m/s of climb and 1.6 m/s ahead, 2 m of climb takes about 4 m)."""
    ignore_ground: bool = False
    """With ``lidar``: beams that hit the ground (z < 5 cm) give no obstacle point (the altitude
    band is checked on its own). Without it, flying low, the downward beam's ground hits a few
    metres ahead count as obstacles and push the planner up."""
    near_pillars: int = 24
    """Pillars checked per episode: the nearest footprints (24 cover about 7 m at the paper
    density; a 2-3 s rollout reaches 4-6 m)."""
    near_movers: int = 12
    """Moving obstacles checked per episode with full view: the nearest (12 cover about 10 m at
    the paper density; UAV and obstacle close at most 3.5 m/s)."""
    grid_resolution: float = 0.25
    """Cell side (m) of the geodesic cost-to-go grid."""
    block_penalty: float = 20.0
    """Extra cost factor of a grid cell within ``uav_radius + margin`` of a pillar or the wall."""

    @property
    def limited(self) -> bool:
        return math.isfinite(self.privileged_range) or self.sense == "lidar"

    @property
    def progress_kind(self) -> str:
        if self.progress == "auto":
            return "euclid" if self.limited else "geodesic"
        return self.progress

    def __post_init__(self) -> None:
        if self.progress not in ("auto", "geodesic", "euclid"):
            raise ValueError(f"progress={self.progress!r}: choose auto, geodesic or euclid")
        if self.forecast not in ("constant", "exact"):
            raise ValueError(f"forecast={self.forecast!r}: choose constant or exact")
        if self.sense not in ("exact", "lidar"):
            raise ValueError(f"sense={self.sense!r}: choose exact or lidar")
        if self.memory < 1:
            raise ValueError(f"memory={self.memory}: at least the current range image (1)")
        if self.horizon < 1 or self.headings < 1 or not self.speeds or not self.climbs:
            raise ValueError("horizon, headings, speeds and climbs must be non-empty")


def mover_clearance(
    centre: torch.Tensor, width: torch.Tensor, cuboid: torch.Tensor, p: torch.Tensor
) -> torch.Tensor:
    """:func:`~safenav.envs.sensors.moving_obstacle_clearance` of points ``p (n, K, 3)`` to
    obstacles ``centre (n, M, 3)``, ``width``/``cuboid (n, 1, M)``: ``(n, K, M)``, per coordinate
    (a norm over a last axis of 3 is several times slower on a CPU)."""
    dx = centre[:, None, :, 0] - p[..., None, 0]
    dy = centre[:, None, :, 1] - p[..., None, 1]
    dz = centre[:, None, :, 2] - p[..., None, 2]
    hw = width / 2
    bx, by = (dx.abs() - hw).clamp(min=0), (dy.abs() - hw).clamp(min=0)
    bz = (dz.abs() - CUBOID_HEIGHT / 2).clamp(min=0)
    box = (bx * bx + by * by + bz * bz).sqrt()
    horiz = ((dx * dx + dy * dy).sqrt() - hw).clamp(min=0)
    above = (p[..., None, 2] - CYLINDER_HEIGHT).clamp(min=0)
    return torch.where(cuboid, box, (horiz * horiz + above * above).sqrt())


def beam_hits(lidar: torch.Tensor, pos: torch.Tensor, yaw: torch.Tensor, cfg) -> torch.Tensor:
    """World points ``(n, E * C, 3)`` where the newest range image ``lidar`` (``(n, >= E, C)``,
    ``(range - d) / range``) hit a pillar or the wall, seen from ``pos`` with beam column 0 at
    ``yaw``; beams without a hit are put ``FAR`` away."""
    spec = RangeImageSpec.for_config(cfg)
    ranges = cfg.lidar_range * (1.0 - lidar[:, : len(spec.v_angles)])
    return beam_hit_points(ranges, pos, yaw, spec, FAR)


def scan_columns(env: SafeNavVectorEnv, ids: torch.Tensor) -> torch.Tensor:
    """World ``(x, y)`` ``(n, K, 2)`` of the flight shield's map-scan hits for envs ``ids``
    (``safenav.deploy.shield.map_scan_hits`` with the env's shield config: columns in the heading
    frame, whose column 0 lies along ``yaw``); scan beams without a hit are put ``FAR`` away."""
    from safenav.deploy.shield import ShieldConfig, map_scan_hits

    pos, yaw = env.pos[ids], env.yaw[ids]
    rel, valid, _, _ = map_scan_hits(env.heights, env.grid.origin, env.grid.size,
                                     env.cfg.grid_resolution, pos, yaw,
                                     ShieldConfig.for_env(env.cfg), env.world_idx[ids])  # fmt: skip
    world = goal_frame_to_world(rel, torch.cos(yaw)[:, None], torch.sin(yaw)[:, None])
    return torch.where(valid[..., None], pos[:, None, :2] + world[..., :2], FAR)


def to_action(v_world: torch.Tensor, cos_yaw, sin_yaw, v_max: float) -> torch.Tensor:
    """A world-frame velocity command ``(..., 3)`` as the env's action: goal frame, / v_max,
    clipped to [-1, 1] (the inverse of the env's ``goal_frame_to_world(a * v_max, ...)``)."""
    return (world_to_goal_frame(v_world, cos_yaw, sin_yaw) / v_max).clamp(-1.0, 1.0)


def geodesic_fields(
    env: SafeNavVectorEnv, res: float, block_penalty: float, margin: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cost-to-go to each episode's goal around the pillars: ``(fields (F, G, G), index (N,))``,
    ``fields[index[i], ix, iy]`` the path length (m) from the cell centre ``(ix, iy)`` to env
    ``i``'s goal over an 8-connected grid whose cells near a pillar (any height) or the wall cost
    ``1 + block_penalty`` times more (finite: a field with no unreachable cell)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    cfg = env.cfg
    g = int(math.ceil(cfg.map_size / res))
    centres = -cfg.half + (np.arange(g) + 0.5) * res
    cx, cy = np.meshgrid(centres, centres, indexing="ij")
    cells = np.stack([cx.ravel(), cy.ravel()], -1)  # (G*G, 2), ix major
    ids = np.arange(g * g).reshape(g, g)
    pairs = [(ids[:, :-1], ids[:, 1:], 1.0), (ids[:-1, :], ids[1:, :], 1.0),
             (ids[:-1, :-1], ids[1:, 1:], math.sqrt(2)), (ids[:-1, 1:], ids[1:, :-1], math.sqrt(2))]  # fmt: skip
    goals = env.goal[:, :2].cpu().numpy()
    goal_cell = np.clip(((goals + cfg.half) / res).astype(np.int64), 0, g - 1)
    goal_id = goal_cell[:, 0] * g + goal_cell[:, 1]
    worlds = env.world_idx.cpu().numpy()
    fields, index = [], np.zeros(env.num_envs, dtype=np.int64)
    for w in range(env.num_worlds):
        pxy = env.pillar_xy[w, : env.n_static].cpu().numpy()
        half = env.pillar_half[w, : env.n_static].cpu().numpy()
        clear = np.full(len(cells), np.inf)
        for i in range(0, len(pxy), 64):  # footprint distance of every cell, 64 pillars at a time
            d = np.clip(
                np.abs(cells[:, None] - pxy[None, i : i + 64]) - half[None, i : i + 64, None],
                0,
                None,
            )
            clear = np.minimum(clear, np.linalg.norm(d, axis=-1).min(-1))
        clear = np.minimum(clear, cfg.half - np.abs(cells).max(-1))
        cost = 1.0 + block_penalty * (clear <= cfg.uav_radius + margin)
        rows, cols, vals = [], [], []
        for a, b, length in pairs:
            a, b = a.ravel(), b.ravel()
            rows.append(a), cols.append(b), vals.append(length * res * (cost[a] + cost[b]) / 2)
        graph = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(g * g, g * g)).tocsr()  # fmt: skip
        mine = np.nonzero(worlds == w)[0]
        sources, inverse = np.unique(goal_id[mine], return_inverse=True)
        dist = dijkstra(graph, directed=False, indices=sources)
        index[mine] = sum(f.shape[0] for f in fields) + inverse
        fields.append(dist.reshape(-1, g, g))
    out = torch.as_tensor(np.concatenate(fields), dtype=torch.float32, device=env.device)
    return out, torch.as_tensor(index, device=env.device)


def sample_field(field: torch.Tensor, xy: torch.Tensor, half: float, res: float) -> torch.Tensor:
    """Bilinear interpolation of ``field (B, G, G)`` (cell centres) at ``xy (B, ..., 2)``."""
    g = field.shape[-1]
    u = ((xy + half) / res - 0.5).clamp(0.0, g - 1.0)
    i0 = u.floor().clamp(max=g - 2).long()
    f = u - i0
    flat = field.reshape(field.shape[0], -1)
    lead = xy.shape[1:-1]
    ix, iy = i0[..., 0].reshape(len(xy), -1), i0[..., 1].reshape(len(xy), -1)
    at = lambda dx, dy: torch.gather(flat, 1, (ix + dx) * g + iy + dy).reshape(len(xy), *lead)  # noqa: E731
    fx, fy = f[..., 0], f[..., 1]
    return ((1 - fx) * (1 - fy) * at(0, 0) + fx * (1 - fy) * at(1, 0)
            + (1 - fx) * fy * at(0, 1) + fx * fy * at(1, 1))  # fmt: skip


class OraclePlanner:
    """The privileged sampling MPC (see the module docstring); a policy for
    :func:`~safenav.experiments.evaluate.evaluate` (``needs_env``: called as ``policy(obs, env)``).
    It keeps per-episode state (previous command, finished episodes, goal fields) for one
    evaluation at a time; a new env or new goals start it afresh."""

    needs_env = True

    def __init__(self, config: OracleConfig | None = None) -> None:
        self.cfg = config or OracleConfig()
        self._env: SafeNavVectorEnv | None = None
        self._goals: torch.Tensor | None = None

    # -------------------------------------------------------------- per evaluation
    def _start(self, env: SafeNavVectorEnv) -> None:
        self._env, self._goals = env, env.goal.clone()
        n = env.num_envs
        self.finished = torch.zeros(n, dtype=torch.bool, device=env.device)
        self.prev_cmd = torch.zeros(n, 3, device=env.device)
        self.seen: torch.Tensor | None = None  # (n, memory * E * C, 3) remembered hit points
        if self.cfg.progress_kind == "geodesic":
            self.fields, self.field_index = geodesic_fields(
                env, self.cfg.grid_resolution, self.cfg.block_penalty, self.cfg.margin
            )

    def _update_finished(self, env: SafeNavVectorEnv) -> None:
        """Episodes that ended (success or collision, the env's own tests): they get zero
        actions and no planning (the evaluator ignores them)."""
        ec, w = env.cfg, env.world_idx
        pos = env.pos
        static = pillar_clearance(pos, env.pillar_xy[w, : env.n_static],
                                  env.pillar_half[w, : env.n_static],
                                  env.pillar_height[w, : env.n_static])  # fmt: skip
        dyn = torch.full_like(static, math.inf)
        if env.n_dynamic:
            nd = env.n_dynamic
            rel = env.dyn_pos[w, :nd] - pos[:, None]
            dyn = moving_obstacle_clearance(rel, env.dyn_width[w, :nd], env.dyn_is_cuboid[w, :nd],
                                            pos[:, 2], CUBOID_HEIGHT, CYLINDER_HEIGHT).amin(-1)  # fmt: skip
        collided = ((static <= ec.uav_radius) | (dyn <= ec.uav_radius)
                    | (border_clearance(pos, ec.half) <= ec.uav_radius)
                    | (pos[:, 2] < ec.z_min) | (pos[:, 2] > ec.z_max))  # fmt: skip
        arrived = (env.goal - pos).norm(dim=-1) < ec.goal_tolerance
        self.finished |= (collided | arrived) & (env.steps > 0)

    # -------------------------------------------------------------- candidates and rollouts
    def candidates(self, obs, env, ids: torch.Tensor) -> torch.Tensor:
        """World-frame commands ``(n, K, 3)`` of episodes ``ids``, as the env will apply them."""
        c, ec = self.cfg, env.cfg
        to_goal = env.goal[ids] - env.pos[ids]
        bearing = torch.atan2(to_goal[:, 1], to_goal[:, 0])
        ang = bearing[:, None] + torch.arange(c.headings, device=env.device) * (
            2 * math.pi / c.headings
        )
        sp = torch.tensor(c.speeds, device=env.device)
        cl = torch.tensor(c.climbs, device=env.device)
        n, j, s, k = len(ids), c.headings, len(c.speeds), len(c.climbs)
        vx = (ang.cos()[:, :, None] * sp)[..., None].expand(n, j, s, k)
        vy = (ang.sin()[:, :, None] * sp)[..., None].expand(n, j, s, k)
        vz = cl.expand(n, j, s, k)
        grid = torch.stack([vx, vy, vz], -1).reshape(n, -1, 3)
        cos_y, sin_y = env.cos_yaw[ids, None], env.sin_yaw[ids, None]
        straight = goal_frame_to_world(go_to_goal({"state": obs["state"][ids]}) * ec.v_max,
                                       cos_y[:, 0], sin_y[:, 0])  # fmt: skip
        cmds = torch.cat([grid, torch.zeros(n, 1, 3, device=env.device), straight[:, None]], 1)
        # Exactly what the env applies: goal frame, clipped per axis, back to the world frame.
        return goal_frame_to_world(to_action(cmds, cos_y, sin_y, ec.v_max) * ec.v_max, cos_y, sin_y)

    def forecast(self, env: SafeNavVectorEnv) -> torch.Tensor:
        """Moving obstacles' centres after each of the next ``horizon`` steps, ``(H, W, D, 3)``."""
        h, dt = self.cfg.horizon, env.cfg.dt
        if self.cfg.forecast == "constant":
            t = torch.arange(1, h + 1, device=env.device, dtype=torch.float32)[:, None, None, None]
            return env.dyn_pos[None] + t * dt * env.dyn_vel[None]
        ghost = copy.copy(env)  # the env's own obstacle model on a copy of its state
        ghost.dyn_goal_counter = (
            env.dyn_goal_counter.clone()
        )  # (the one tensor it updates in place)
        out = []
        for _ in range(h):
            ghost._step_obstacles()
            out.append(ghost.dyn_pos)
        return torch.stack(out)

    @torch.no_grad()
    def __call__(self, obs: dict[str, torch.Tensor], env: SafeNavVectorEnv) -> torch.Tensor:
        if env is not self._env or not torch.equal(env.goal, self._goals):
            self._start(env)
        self._update_finished(env)
        actions = torch.zeros(env.num_envs, 3, device=env.device)
        ids = (~self.finished).nonzero().squeeze(-1)
        if len(ids) == 0:
            return actions
        c, ec = self.cfg, env.cfg
        cmds = self.candidates(obs, env, ids)  # (n, K, 3)
        n, k = cmds.shape[:2]
        pos0, goal = env.pos[ids], env.goal[ids]
        w = env.world_idx[ids]
        rng = ec.lidar_range if c.sense == "lidar" else c.privileged_range

        # Pillars: the nearest footprints (those out of view sink below the ground).
        ns = env.n_static
        pxy, phalf, ph = env.pillar_xy[w, :ns], env.pillar_half[w, :ns], env.pillar_height[w, :ns]
        foot = ((pos0[:, None, :2] - pxy).abs() - phalf[..., None]).clamp(min=0).norm(dim=-1)
        m = min(c.near_pillars, ns)
        d_sel, p_idx = torch.topk(foot, m, dim=-1, largest=False)
        pxy, phalf = (
            torch.gather(pxy, 1, p_idx[..., None].expand(n, m, 2)),
            torch.gather(phalf, 1, p_idx),
        )
        ph = torch.where(d_sel <= rng, torch.gather(ph, 1, p_idx), -FAR)
        # Moving obstacles: the nearest (with a limited view: the observation's nearest in range).
        nd = env.n_dynamic
        future = self.forecast(env)[:, w, :nd] if nd else None  # (H, n, D, 3)
        if nd:
            centre = (env.dyn_pos[w, :nd, :2] - pos0[:, None, :2]).norm(dim=-1)
            width, cuboid = env.dyn_width[w, :nd], env.dyn_is_cuboid[w, :nd]
            md = min(ec.num_tracked if c.limited else c.near_movers, nd)
            near = centre if c.limited else centre - width / 2
            _, m_idx = torch.topk(near, md, dim=-1, largest=False)
            seen = torch.gather(centre, 1, m_idx) <= rng
            future = torch.gather(future, 2, m_idx[None, ..., None].expand(c.horizon, n, md, 3))
            future = torch.where(seen[None, ..., None], future, FAR)
            width, cuboid = (
                torch.gather(width, 1, m_idx)[:, None],
                torch.gather(cuboid, 1, m_idx)[:, None],
            )
        # The wall: each side seen within range.
        sides = lambda p: torch.stack([ec.half - p[..., 0], ec.half + p[..., 0],  # noqa: E731
                                       ec.half - p[..., 1], ec.half + p[..., 1]], -1)  # fmt: skip
        wall_seen = (sides(pos0) <= rng)[:, None]  # (n, 1, 4)
        hits = columns = None
        if c.sense == "lidar":
            now = beam_hits(obs["lidar"], env.pos, env.yaw, ec)  # every env: the memory is per env
            if c.ignore_ground:
                now = torch.where(now[..., 2:] < 0.05, FAR, now)
            if c.memory == 1:
                self.seen = now
            elif self.seen is None:  # a new evaluation: nothing seen before its first image
                self.seen = torch.cat(
                    [now, torch.full_like(now, FAR).repeat(1, c.memory - 1, 1)], 1
                )
            else:
                self.seen = torch.cat([now, self.seen[:, : -now.shape[1]]], 1)
            hits = self.seen[ids]
            if c.map_scan:
                columns = scan_columns(env, ids)
            hit_r = None
            if c.fill_gaps:  # the gap to the next beam at each hit's range
                d = (hits - pos0[:, None]).norm(dim=-1).clamp(max=ec.lidar_range)
                hit_r = d * math.sin(math.pi / ec.lidar_h_beams)

        p = pos0[:, None].expand(n, k, 3).contiguous()
        v = env.vel[ids, None].expand(n, k, 3).contiguous()
        never = c.horizon + 1
        first_hit = torch.full((n, k), never, device=env.device)  # first step in a collision
        reach = torch.full((n, k), never, device=env.device)  # first step at the goal
        intrude = torch.zeros(n, k, device=env.device)  # deepest intrusion into the margins (m)
        least = torch.full((n, k), math.inf, device=env.device)  # least clearance (m)
        for t in range(c.horizon):
            p, v = velocity_tracker(p, v, cmds, ec.dt, ec.physics_substeps,
                                    ec.velocity_time_constant, ec.max_acceleration)  # fmt: skip
            if hits is None:
                dx = ((p[..., None, 0] - pxy[:, None, :, 0]).abs() - phalf[:, None]).clamp(min=0)
                dy = ((p[..., None, 1] - pxy[:, None, :, 1]).abs() - phalf[:, None]).clamp(min=0)
                dz = (p[..., None, 2] - ph[:, None]).clamp(min=0)
                static = (dx * dx + dy * dy + dz * dz).sqrt().amin(-1)
                static = torch.minimum(static, torch.where(wall_seen, sides(p), math.inf).amin(-1))
            else:  # the beams' hit points: what the range image shows, nothing between beams
                dist = torch.cdist(p, hits)
                static = (dist if hit_r is None else dist - hit_r[:, None]).amin(-1)
                if columns is not None:
                    static = torch.minimum(static, torch.cdist(p[..., :2], columns).amin(-1))
            static = static - ec.uav_radius
            mover = torch.full_like(static, math.inf)
            if nd:
                mover = mover_clearance(future[t], width, cuboid, p).amin(-1) - ec.uav_radius
            band = torch.minimum(p[..., 2] - ec.z_min, ec.z_max - p[..., 2])
            clear = torch.minimum(static, mover)
            going = reach == never  # not at the goal before this step
            hit = going & (first_hit == never) & ((clear <= 0) | (band <= 0))
            first_hit = torch.where(hit, t + 1, first_hit)
            depth = torch.maximum(torch.maximum(c.margin - static, c.margin + c.mover_margin - mover),
                                  c.margin - band).clamp(min=0)  # fmt: skip
            intrude = torch.where(going, torch.maximum(intrude, depth), intrude)
            least = torch.where(going, torch.minimum(least, clear), least)
            at_goal = ((p - goal[:, None]) ** 2).sum(-1) < (0.9 * ec.goal_tolerance) ** 2
            reach = torch.where(going & at_goal, t + 1, reach)

        # Cost-to-go at the horizon's end; minus the time left for those that reach the goal.
        delta = goal[:, None] - p
        flat = delta[..., :2].norm(dim=-1)  # straight horizontal distance to the goal
        if c.progress_kind == "geodesic":
            geo = sample_field(
                self.fields[self.field_index[ids]], p[..., :2], ec.half, c.grid_resolution
            )
            horiz = torch.maximum(geo, flat)
            ctg = (horiz * horiz + delta[..., 2] ** 2).sqrt()
        else:
            horiz = flat
            ctg = delta.norm(dim=-1)
        if c.cruise is not None:  # far from the goal: horizontal cost-to-go + |z - cruise|
            far = flat > c.cruise_until
            ctg = torch.where(far, horiz + (c.cruise - p[..., 2]).abs(), ctg)
        score = torch.where(reach < never, -(never - reach) * ec.dt, ctg)
        score = score + W_MARGIN * intrude + c.w_clear * (c.clear_cap - least).clamp(min=0)
        score = score + c.w_smooth * (cmds - self.prev_cmd[ids, None]).norm(dim=-1)
        # A collision rules a candidate out; when all collide, the latest collision wins.
        score = torch.where(
            first_hit < never, 1e6 - 1e3 * first_hit + score.clamp(-1e2, 9e2), score
        )
        best = score.argmin(-1)
        chosen = cmds[torch.arange(n, device=env.device), best]
        self.prev_cmd[ids] = chosen
        actions[ids] = to_action(chosen, env.cos_yaw[ids], env.sin_yaw[ids], ec.v_max)
        return actions


# ------------------------------------------------------------------ command line
SUMMARY = ("success_rate", "collision_rate", "timeout_rate", "collision_static_rate",
           "collision_dynamic_rate", "collision_bounds_rate", "mean_speed", "mean_time_to_goal",
           "mean_min_clearance", "detour_ratio")  # fmt: skip


def run(config: OracleConfig, env_seeds: list[int], episodes: int, preset: str = "paper",
        env_overrides: dict | None = None) -> dict:  # fmt: skip
    """Fly the oracle on ``episodes`` episodes of each validation map; per map and pooled."""
    per_map, pooled = {}, {k: [] for k in ("success", "collision", "timeout", "hit_static",
                                           "hit_dynamic", "out_of_bounds", "time", "mean_speed")}  # fmt: skip
    for seed in env_seeds:
        if seed in RESERVED_SEEDS:
            raise SystemExit(f"env seed {seed} is a test or held-out map: use validation maps "
                             f"({', '.join(map(str, VALIDATION_SEEDS))})")  # fmt: skip
        t0 = time.perf_counter()
        res = evaluate(
            OraclePlanner(config),
            make_config(preset, **(env_overrides or {})),
            env_seed=seed,
            episodes=episodes,
        )
        per_ep = res.pop("per_episode")
        per_map[str(seed)] = {**{k: res[k] for k in SUMMARY}, "wall_s": round(time.perf_counter() - t0, 1),
                              "per_episode": {k: per_ep[k] for k in pooled}}  # fmt: skip
        for k in pooled:
            pooled[k] += per_ep[k]
        m = per_map[str(seed)]
        print(f"  map {seed}: success {m['success_rate']:.3f} collision {m['collision_rate']:.3f} "
              f"timeout {m['timeout_rate']:.3f} ({m['wall_s']:.0f} s)", flush=True)  # fmt: skip
    a = {k: np.asarray(v) for k, v in pooled.items()}
    ok = a["success"] > 0.5
    total = {
        "episodes": len(ok),
        "success_rate": float(ok.mean()),
        "collision_rate": float((a["collision"] > 0.5).mean()),
        "timeout_rate": float((a["timeout"] > 0.5).mean()),
        "collision_static_rate": float((a["hit_static"] > 0.5).mean()),
        "collision_dynamic_rate": float((a["hit_dynamic"] > 0.5).mean()),
        "collision_bounds_rate": float((a["out_of_bounds"] > 0.5).mean()),
        "mean_speed": float(a["mean_speed"].mean()),
        "mean_time_to_goal": float(a["time"][ok].mean()) if ok.any() else math.nan,
    }
    return {"pooled": total, "per_map": per_map}


def main(argv: list[str] | None = None) -> dict:
    d = OracleConfig()
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--env-seeds", type=int, nargs="+", default=list(VALIDATION_SEEDS))
    ap.add_argument(
        "--episodes", type=int, default=104, help="per map (104 x 4 = 416, as validation)"
    )
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--horizon", type=int, default=d.horizon, help="control steps (10 Hz)")
    ap.add_argument("--headings", type=int, default=d.headings)
    ap.add_argument("--speeds", type=float, nargs="+", default=list(d.speeds))
    ap.add_argument("--climbs", type=float, nargs="+", default=list(d.climbs))
    ap.add_argument("--margin", type=float, default=d.margin, help="m beyond the UAV radius")
    ap.add_argument(
        "--mover-margin",
        type=float,
        default=d.mover_margin,
        help="m of extra margin from moving obstacles",
    )
    ap.add_argument("--w-clear", type=float, default=d.w_clear)
    ap.add_argument("--w-smooth", type=float, default=d.w_smooth)
    ap.add_argument(
        "--privileged-range",
        type=float,
        default=d.privileged_range,
        help="m: see pillars, wall and moving obstacles only this close (default: all)",
    )
    ap.add_argument("--progress", choices=("auto", "geodesic", "euclid"), default=d.progress)
    ap.add_argument("--forecast", choices=("constant", "exact"), default=d.forecast)
    ap.add_argument(
        "--sense",
        choices=("exact", "lidar"),
        default=d.sense,
        help="pillars and wall as exact geometry or as the range image's hit points",
    )
    ap.add_argument(
        "--fill-gaps",
        action="store_true",
        help="with --sense lidar: treat the space between neighbouring beams as solid",
    )
    ap.add_argument(
        "--memory",
        type=int,
        default=d.memory,
        help="with --sense lidar: range images remembered (1 = the current one)",
    )
    ap.add_argument(
        "--map-scan",
        action="store_true",
        help="with --sense lidar: also the flight shield's map-scan hits, as columns",
    )
    ap.add_argument(
        "--env",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="EnvConfig overrides of the preset (e.g. lidar_h_beams=72)",
    )
    ap.add_argument(
        "--causes",
        type=int,
        default=None,
        metavar="ENV_SEED",
        help="instead: sort the collisions of --episodes episodes of this validation "
        "map (experiments/collision_causes.py) and write them to --json",
    )
    ap.add_argument("--cruise", type=float, default=d.cruise,
                    help="m: altitude to hold until --cruise-until m from the goal")  # fmt: skip
    ap.add_argument("--cruise-until", type=float, default=d.cruise_until)
    ap.add_argument("--ignore-ground", action="store_true",
                    help="with --sense lidar: ground hits are not obstacles")  # fmt: skip
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    config = OracleConfig(horizon=args.horizon, headings=args.headings, speeds=tuple(args.speeds),
                          climbs=tuple(args.climbs), margin=args.margin,
                          mover_margin=args.mover_margin, w_clear=args.w_clear,
                          w_smooth=args.w_smooth, privileged_range=args.privileged_range,
                          progress=args.progress, forecast=args.forecast, sense=args.sense,
                          memory=args.memory, fill_gaps=args.fill_gaps, cruise=args.cruise,
                          map_scan=args.map_scan,
                          cruise_until=args.cruise_until,
                          ignore_ground=args.ignore_ground)  # fmt: skip
    if args.causes is not None:
        if args.causes in RESERVED_SEEDS:
            raise SystemExit(f"env seed {args.causes} is a test or held-out map")
        from collision_causes import classify

        out = classify(f"oracle planner {dataclasses.asdict(config)}", args.episodes, args.causes,
                       planner=OraclePlanner(config))  # fmt: skip
        print(json.dumps(out["causes"]))
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(out, indent=1) + "\n")
        return out
    k = config.headings * len(config.speeds) * len(config.climbs) + 2
    print(f"oracle: {k} candidates x {config.horizon} steps, margin {config.margin} m, "
          f"range {config.privileged_range} m, {config.sense} sensing, {config.progress_kind} progress, "
          f"{config.forecast} forecast", flush=True)  # fmt: skip
    t0 = time.perf_counter()
    overrides = {}
    for item in args.env:
        key, _, value = item.partition("=")
        try:
            overrides[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            overrides[key] = value
    out = run(config, args.env_seeds, args.episodes, args.preset, overrides)
    p = out["pooled"]
    print(f"pooled ({p['episodes']} episodes): success {p['success_rate']:.3f} collision "
          f"{p['collision_rate']:.3f} (static {p['collision_static_rate']:.3f}, dynamic "
          f"{p['collision_dynamic_rate']:.3f}, bounds {p['collision_bounds_rate']:.3f}) timeout "
          f"{p['timeout_rate']:.3f}; mean speed {p['mean_speed']:.2f} m/s, time to goal "
          f"{p['mean_time_to_goal']:.1f} s; {time.perf_counter() - t0:.0f} s")  # fmt: skip
    settings = dataclasses.asdict(config)
    if config.privileged_range == math.inf:
        settings["privileged_range"] = None  # JSON has no infinity: null = everything in view
    record = {"settings": {**settings, "progress_kind": config.progress_kind,
                           "candidates": k, "env_seeds": args.env_seeds, "episodes": args.episodes,
                           "preset": args.preset, "env_overrides": overrides, "threads": args.threads,
                           "machine": platform.node(), "date": time.strftime("%Y-%m-%d")},
              **out, "wall_s": round(time.perf_counter() - t0, 1)}  # fmt: skip
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(record, indent=1, allow_nan=True) + "\n")
        print(f"wrote {args.json}")
    return record


if __name__ == "__main__":
    main()
