"""A privileged planner for SafeNav (docs/csac-v1.md, "A privileged planner: how hard is the
scenario?"): the scenario's difficulty measured by a controller that reads the simulator's state
(``experiments/oracle_planner.py``), a labeller for imitation (``experiments/teacher_student.py``)
and the pilot of the planner's flights a learner can replay (``CSACConfig.planner_share``).

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
With ``sense="lidar"`` it sees only the range image's hit points (``memory``: of the last
images); otherwise it has no memory. ``experiments/oracle_planner.py`` flies it on validation
maps.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from safenav.envs.dynamics import goal_frame_to_world, velocity_tracker, world_to_goal_frame
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.scripted import go_to_goal
from safenav.envs.sensors import (
    RangeImageSpec,
    beam_hit_points,
    moving_obstacle_clearance,
    pillar_clearance,
)
from safenav.envs.world import CUBOID_HEIGHT, CYLINDER_HEIGHT, DYN_WIDTHS, border_clearance

FAR = 1.0e4  # m: where obstacles outside the planner's view are put
W_MARGIN = 100.0  # cost per metre of intrusion into the margins (1 cm = 1 m of cost-to-go)
SHORT_MOVE_SPEEDS = (0.5, 1.0)
"""Horizontal speeds (m/s) of :meth:`OraclePlanner.short_move_candidates`."""
SHORT_MOVE_CLIMBS = (-0.25, 0.0, 0.25)
"""Vertical speeds (m/s) of :meth:`OraclePlanner.short_move_candidates`."""
SHORT_MOVE_STEPS = 5
"""Control steps a short move is held before its stop (0.5 s at 10 Hz: 0.1-0.4 m of flight)."""
MAP_PILLARS = 512
"""Pillars a :class:`PlannerFilter` with ``handover_map`` remembers per episode (the paper's
arena holds 350)."""
HANDOVER_EXITS = ("time", "nearer")
"""When a :class:`PlannerFilter`'s stall handover ends (its ``handover_exit``)."""
HANDOVER_CAP = 3
"""The longest ``handover_exit="nearer"`` handover, in handovers of ``stall``'s length."""
MAP_MATCH = 0.05
"""Distance (m, per axis) within which two sightings of a pillar's centre are the same pillar."""
ScanFn = Callable[[SafeNavVectorEnv, torch.Tensor], torch.Tensor]
"""``scan(env, ids) -> (len(ids), K, 2)``: world ``(x, y)`` of obstacle columns (``FAR`` = none)."""


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
    policies' flight shield knows beside the range image. The scan comes from the deployment
    layer, above this one: the planner takes it as ``OraclePlanner(config, scan=...)``
    (``experiments/oracle_planner.py``'s ``scan_columns``)."""
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
    keep_band: bool = False
    """Keep the altitude band of NavRL's height penalty (the env's ``band``: between the start's
    and the goal's altitudes) as a margin: each metre outside it is an intrusion (``W_MARGIN`` per
    metre, as the margins; not ruled out, since a pillar may be passed only above it). Without
    it the planner knows only the ground and the ceiling, and the height penalty charges its
    flights more than anything else (docs/csac-v1.md, "The planner's flights in the replay")."""
    near_pillars: int = 24
    """Pillars checked per episode: the nearest footprints (24 cover about 7 m at the paper
    density; a 2-3 s rollout reaches 4-6 m)."""
    near_movers: int = 12
    """Moving obstacles checked per episode with full view: the nearest (12 cover about 10 m at
    the paper density; UAV and obstacle close at most 3.5 m/s)."""
    mover_turn: float = 0.0
    """Seconds (0: off) in which a moving obstacle may turn any way at its speed: its clearance at
    forecast time t is reduced by its speed x min(t, mover_turn), a reachable set around the
    constant-velocity forecast (beyond NavRL; screened on validation: docs/csac-v1.md, "A forecast
    that lets movers turn")."""
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


def to_action(v_world: torch.Tensor, cos_yaw, sin_yaw, v_max: float) -> torch.Tensor:
    """A world-frame velocity command ``(..., 3)`` as the env's action: goal frame, / v_max,
    clipped to [-1, 1] (the inverse of the env's ``goal_frame_to_world(a * v_max, ...)``)."""
    return (world_to_goal_frame(v_world, cos_yaw, sin_yaw) / v_max).clamp(-1.0, 1.0)


def grid_graph(pxy: np.ndarray, half: np.ndarray, cfg, res: float, block_penalty: float,
               margin: float):  # fmt: skip
    """The 8-connected grid over the arena (cells of side ``res``, ``G = ceil(map_size / res)``
    a side) as a sparse graph for :func:`scipy.sparse.csgraph.dijkstra`: each edge as long as it
    is, times ``1 + block_penalty`` where a cell lies within ``uav_radius + margin`` of a pillar's
    footprint ``pxy (P, 2)``, ``half (P,)`` (any height) or of the wall (finite: no cell is
    unreachable). Returns ``(graph, G)``."""
    from scipy.sparse import coo_matrix

    g = int(math.ceil(cfg.map_size / res))
    centres = -cfg.half + (np.arange(g) + 0.5) * res
    cx, cy = np.meshgrid(centres, centres, indexing="ij")
    cells = np.stack([cx.ravel(), cy.ravel()], -1)  # (G*G, 2), ix major
    ids = np.arange(g * g).reshape(g, g)
    pairs = [(ids[:, :-1], ids[:, 1:], 1.0), (ids[:-1, :], ids[1:, :], 1.0),
             (ids[:-1, :-1], ids[1:, 1:], math.sqrt(2)), (ids[:-1, 1:], ids[1:, :-1], math.sqrt(2))]  # fmt: skip
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
    return graph, g


def goal_cells(goals: np.ndarray, cfg, res: float) -> np.ndarray:
    """The grid cell index (of :func:`grid_graph`) of each goal ``(N, 2)``."""
    g = int(math.ceil(cfg.map_size / res))
    cell = np.clip(((goals + cfg.half) / res).astype(np.int64), 0, g - 1)
    return cell[:, 0] * g + cell[:, 1]


def geodesic_fields(
    env: SafeNavVectorEnv, res: float, block_penalty: float, margin: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cost-to-go to each episode's goal around the pillars: ``(fields (F, G, G), index (N,))``,
    ``fields[index[i], ix, iy]`` the path length (m) from the cell centre ``(ix, iy)`` to env
    ``i``'s goal over :func:`grid_graph` (cells near a pillar, any height, or the wall cost
    ``1 + block_penalty`` times more)."""
    from scipy.sparse.csgraph import dijkstra

    cfg = env.cfg
    goal_id = goal_cells(env.goal[:, :2].cpu().numpy(), cfg, res)
    worlds = env.world_idx.cpu().numpy()
    fields, index = [], np.zeros(env.num_envs, dtype=np.int64)
    for w in range(env.num_worlds):
        pxy = env.pillar_xy[w, : env.n_static].cpu().numpy()
        half = env.pillar_half[w, : env.n_static].cpu().numpy()
        graph, g = grid_graph(pxy, half, cfg, res, block_penalty, margin)
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

    def __init__(self, config: OracleConfig | None = None, scan: ScanFn | None = None) -> None:
        self.cfg = config or OracleConfig()
        if self.cfg.map_scan and scan is None:
            raise ValueError("map_scan=True needs scan=: the map scan's columns (n, K, 2) of envs "
                             "ids, e.g. experiments/oracle_planner.py's scan_columns")  # fmt: skip
        self.scan = scan
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
        """Episodes that ended (success or collision, the env's own tests, its collision rule
        included): they get zero actions and no planning (the evaluator ignores them)."""
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
        hit_static = static <= ec.uav_radius
        if ec.collision_rule == "navrl" and bool(hit_static.any()):  # as the env counts it
            ids = hit_static.nonzero().squeeze(-1)
            hit_static[ids] = env._beam_reads_pillar(ids)
        collided = (hit_static | (dyn <= ec.uav_radius)
                    | (border_clearance(pos, ec.half) <= ec.uav_radius)
                    | (pos[:, 2] < ec.z_min) | (pos[:, 2] > ec.z_max))  # fmt: skip
        arrived = (env.goal - pos).norm(dim=-1) < ec.goal_tolerance
        self.finished |= (collided | arrived) & (env.steps > 0)

    # -------------------------------------------------------------- candidates and rollouts
    def candidates(self, obs, env, ids: torch.Tensor) -> torch.Tensor:
        """World-frame commands ``(n, K, 3)`` of episodes ``ids``, as the env will apply them."""
        c, ec = self.cfg, env.cfg
        grid = self._command_grid(env, ids, c.speeds, c.climbs)
        n = len(ids)
        cos_y, sin_y = env.cos_yaw[ids, None], env.sin_yaw[ids, None]
        straight = goal_frame_to_world(go_to_goal({"state": obs["state"][ids]}) * ec.v_max,
                                       cos_y[:, 0], sin_y[:, 0])  # fmt: skip
        cmds = torch.cat([grid, torch.zeros(n, 1, 3, device=env.device), straight[:, None]], 1)
        # Exactly what the env applies: goal frame, clipped per axis, back to the world frame.
        return goal_frame_to_world(to_action(cmds, cos_y, sin_y, ec.v_max) * ec.v_max, cos_y, sin_y)

    def short_move_candidates(self, env, ids: torch.Tensor) -> torch.Tensor:
        """World-frame commands ``(n, K, 3)`` of episodes ``ids`` that :meth:`choose` holds for
        :data:`SHORT_MOVE_STEPS` steps and then stops (``short``): the :attr:`OracleConfig.headings`
        from the goal's bearing at :data:`SHORT_MOVE_SPEEDS` and :data:`SHORT_MOVE_CLIMBS`, as the
        env will apply them. A held 2 s command leaves a pocket between pillars only where the
        whole 2 s is free; a step of a few decimetres and a stop finds a way out in steps."""
        cmds = self._command_grid(env, ids, SHORT_MOVE_SPEEDS, SHORT_MOVE_CLIMBS)
        cos_y, sin_y, v_max = env.cos_yaw[ids, None], env.sin_yaw[ids, None], env.cfg.v_max
        return goal_frame_to_world(to_action(cmds, cos_y, sin_y, v_max) * v_max, cos_y, sin_y)

    def _command_grid(self, env, ids: torch.Tensor, speeds: tuple[float, ...],
                      climbs: tuple[float, ...]) -> torch.Tensor:  # fmt: skip
        """World-frame commands ``(n, headings * speeds * climbs, 3)``: the
        :attr:`OracleConfig.headings` evenly spaced from the goal's bearing, at each horizontal
        speed and climb rate."""
        c = self.cfg
        to_goal = env.goal[ids] - env.pos[ids]
        bearing = torch.atan2(to_goal[:, 1], to_goal[:, 0])
        ang = bearing[:, None] + torch.arange(c.headings, device=env.device) * (
            2 * math.pi / c.headings
        )
        sp = torch.tensor(speeds, device=env.device)
        cl = torch.tensor(climbs, device=env.device)
        n, j, s, k = len(ids), c.headings, len(speeds), len(climbs)
        vx = (ang.cos()[:, :, None] * sp)[..., None].expand(n, j, s, k)
        vy = (ang.sin()[:, :, None] * sp)[..., None].expand(n, j, s, k)
        return torch.stack([vx, vy, cl.expand(n, j, s, k)], -1).reshape(n, -1, 3)

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
        ids = self._step_start(obs, env)
        actions = torch.zeros(env.num_envs, 3, device=env.device)
        if len(ids) == 0:
            return actions
        cmds = self.candidates(obs, env, ids)  # (n, K, 3)
        scene = self.scene(obs, env, ids)
        chosen = self.choose(scene, cmds)
        self.prev_cmd[ids] = chosen
        actions[ids] = to_action(chosen, env.cos_yaw[ids], env.sin_yaw[ids], env.cfg.v_max)
        return actions

    def _step_start(self, obs: dict[str, torch.Tensor], env: SafeNavVectorEnv) -> torch.Tensor:
        """Per-evaluation bookkeeping at each step; the episodes still to plan for."""
        if env is not self._env or not torch.equal(env.goal, self._goals):
            self._start(env)
        self._update_finished(env)
        return (~self.finished).nonzero().squeeze(-1)

    def scene(self, obs: dict[str, torch.Tensor], env: SafeNavVectorEnv, ids: torch.Tensor) -> dict:
        """What the planner knows of episodes ``ids`` now (pillars, moving obstacles and their
        forecast, wall, range-image hits), for :meth:`simulate`. With ``sense="lidar"`` it also
        remembers this step's range image: call it once per step."""
        c, ec = self.cfg, env.cfg
        n = len(ids)
        pos0 = env.pos[ids]
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
        width = cuboid = None
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
        hits = columns = hit_r = None
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
                columns = self.scan(env, ids)
            if c.fill_gaps:  # the gap to the next beam at each hit's range
                d = (hits - pos0[:, None]).norm(dim=-1).clamp(max=ec.lidar_range)
                hit_r = d * math.sin(math.pi / ec.lidar_h_beams)
        return _scene(env, ids, rng, pxy=pxy, phalf=phalf, ph=ph, nd=nd, future=future,
                      width=width, cuboid=cuboid, hits=hits, columns=columns,
                      hit_r=hit_r)  # fmt: skip

    def observed_scene(self, obs: dict[str, torch.Tensor], env: SafeNavVectorEnv,
                       ids: torch.Tensor) -> dict:  # fmt: skip
        """:meth:`scene` from what a vehicle has on board: the observation's ``static`` rows (the
        pillars' footprints and tops, ``EnvConfig.static_tracked``) and ``dynamic`` rows (the
        tracked moving obstacles, forecast at constant velocity), the vehicle's position,
        velocity and goal (odometry and mission; here the env's) and the arena's wall (its
        geofence). Nothing else of the simulator is read. Static rows layout:
        ``safenav.envs.config.STATIC_FEATURES``; dynamic rows:
        :func:`~safenav.envs.sensors.dynamic_obstacle_features`."""
        if "static" not in obs:
            raise ValueError("the observed view needs the observation's pillar list "
                             "(EnvConfig.static_tracked > 0)")  # fmt: skip
        c, ec = self.cfg, env.cfg
        rng = ec.lidar_range
        pos0 = env.pos[ids]
        cy, sy = env.cos_yaw[ids, None], env.sin_yaw[ids, None]
        world = lambda g: goal_frame_to_world(g, cy, sy)  # noqa: E731  (n, M, 3) goal frame
        st = obs["static"][ids].to(pos0.dtype)
        flat = torch.cat([st[..., 2:4] * rng, torch.zeros_like(st[..., :1])], -1)
        pxy = pos0[:, None, :2] + world(flat)[..., :2]
        phalf = st[..., 4] * 0.4
        ph = torch.where(st[..., 6] > 0.5, pos0[:, None, 2] + st[..., 5] * rng, -FAR)
        dyn = obs["dynamic"][ids].to(pos0.dtype)
        nd = dyn.shape[1]
        future = width = cuboid = None
        if nd:
            dist = torch.sqrt((dyn[..., 3] * rng) ** 2 + (dyn[..., 4] * rng) ** 2)
            centre = pos0[:, None] + world(dyn[..., 0:3] * dist[..., None])
            vel = world(dyn[..., 5:8] * ec.v_max)
            t = torch.arange(1, c.horizon + 1, device=pos0.device, dtype=pos0.dtype)
            future = centre[None] + t[:, None, None, None] * ec.dt * vel[None]  # (H, n, D, 3)
            seen = dyn.abs().sum(-1) > 0  # rows of zeros are empty slots
            future = torch.where(seen[None, ..., None], future, FAR)
            width = ((dyn[..., 8] * (len(DYN_WIDTHS) - 1) + 1.0) * DYN_WIDTHS[0])[:, None]
            cuboid = (dyn[..., 9] > 0.5)[:, None]
        return _scene(env, ids, rng, pxy=pxy, phalf=phalf, ph=ph, nd=nd, future=future,
                      width=width, cuboid=cuboid)  # fmt: skip

    def simulate(self, scene: dict, cmds: torch.Tensor, p: torch.Tensor, v: torch.Tensor,
                 t0: int = 0, steps: int | None = None) -> dict[str, torch.Tensor]:  # fmt: skip
        """Roll the commands ``cmds`` ``(n, K, 3)`` (world frame, each held) through the env's
        velocity tracker from positions ``p`` and velocities ``v`` ``(n, K, 3)``, steps ``t0 + 1``
        to ``t0 + steps`` of the horizon (default: to its end), against ``scene``. Returns
        ``first_hit`` (the first step in a collision, ``horizon + 1`` if none), ``reach`` (the
        first at the goal, likewise), ``intrude`` (deepest intrusion into the margins, m),
        ``least`` (least clearance, m), each ``(n, K)``, and the end state ``p``, ``v``."""
        c, ec = self.cfg, scene["env"].cfg
        n, k = cmds.shape[:2]
        dev = cmds.device
        steps = c.horizon - t0 if steps is None else steps
        pxy, phalf, ph, nd = scene["pxy"], scene["phalf"], scene["ph"], scene["nd"]
        hits, columns, hit_r, wall_seen = (scene["hits"], scene["columns"], scene["hit_r"],
                                           scene["wall_seen"])  # fmt: skip
        lo, hi = scene["band"]  # NavRL's altitude band
        goal = scene["goal"]
        never = c.horizon + 1
        first_hit = torch.full((n, k), never, device=dev)  # first step in a collision
        reach = torch.full((n, k), never, device=dev)  # first step at the goal
        intrude = torch.zeros(n, k, device=dev)  # deepest intrusion into the margins (m)
        least = torch.full((n, k), math.inf, device=dev)  # least clearance (m)
        turn_speed = None  # (n, 1, D): each mover's speed, for mover_turn's reachable set
        if nd and c.mover_turn > 0:
            future = scene["future"]
            turn_speed = ((future[1, ..., :2] - future[0, ..., :2]).norm(dim=-1) / ec.dt)[:, None]
        for t in range(t0, t0 + steps):
            p, v = velocity_tracker(p, v, cmds, ec.dt, ec.physics_substeps,
                                    ec.velocity_time_constant, ec.max_acceleration)  # fmt: skip
            if hits is None:
                dx = ((p[..., None, 0] - pxy[:, None, :, 0]).abs() - phalf[:, None]).clamp(min=0)
                dy = ((p[..., None, 1] - pxy[:, None, :, 1]).abs() - phalf[:, None]).clamp(min=0)
                dz = (p[..., None, 2] - ph[:, None]).clamp(min=0)
                static = (dx * dx + dy * dy + dz * dz).sqrt()
                static = (
                    static.amin(-1) if static.shape[-1] else torch.full_like(p[..., 0], math.inf)
                )
                static = torch.minimum(
                    static, torch.where(wall_seen, _sides(p, ec.half), math.inf).amin(-1)
                )
            else:  # the beams' hit points: what the range image shows, nothing between beams
                dist = torch.cdist(p, hits)
                static = (dist if hit_r is None else dist - hit_r[:, None]).amin(-1)
                if columns is not None:
                    static = torch.minimum(static, torch.cdist(p[..., :2], columns).amin(-1))
            static = static - ec.uav_radius
            mover = torch.full_like(static, math.inf)
            if nd:
                gap = mover_clearance(scene["future"][t], scene["width"], scene["cuboid"], p)
                if turn_speed is not None:
                    gap = gap - turn_speed * min((t + 1) * ec.dt, c.mover_turn)
                mover = gap.amin(-1) - ec.uav_radius
            band = torch.minimum(p[..., 2] - ec.z_min, ec.z_max - p[..., 2])
            clear = torch.minimum(static, mover)
            going = reach == never  # not at the goal before this step
            hit = going & (first_hit == never) & ((clear <= 0) | (band <= 0))
            first_hit = torch.where(hit, t + 1, first_hit)
            depth = torch.maximum(torch.maximum(c.margin - static, c.margin + c.mover_margin - mover),
                                  c.margin - band).clamp(min=0)  # fmt: skip
            if c.keep_band:
                depth = torch.maximum(depth, torch.maximum(lo - p[..., 2], p[..., 2] - hi))
            intrude = torch.where(going, torch.maximum(intrude, depth), intrude)
            least = torch.where(going, torch.minimum(least, clear), least)
            at_goal = ((p - goal[:, None]) ** 2).sum(-1) < (0.9 * ec.goal_tolerance) ** 2
            reach = torch.where(going & at_goal, t + 1, reach)
        return {"first_hit": first_hit, "reach": reach, "intrude": intrude, "least": least,
                "p": p, "v": v}  # fmt: skip

    def move_then_stop(self, scene: dict, cmds: torch.Tensor, p: torch.Tensor, v: torch.Tensor,
                       steps: int) -> dict[str, torch.Tensor]:  # fmt: skip
        """:meth:`simulate` of ``cmds`` held for ``steps`` steps and then a zero command for the
        rest of the horizon (a stop, through the velocity tracker), as one rollout each."""
        head = self.simulate(scene, cmds, p, v, 0, steps)
        tail = self.simulate(scene, torch.zeros_like(cmds), head["p"], head["v"], steps)
        never = self.cfg.horizon + 1
        done = head["reach"] < never  # at the goal before the stop: the rest does not count
        both = lambda key, f: torch.where(done, head[key], f(head[key], tail[key]))  # noqa: E731
        return {"first_hit": both("first_hit", torch.minimum),
                "reach": torch.where(done, head["reach"], tail["reach"]),
                "intrude": both("intrude", torch.maximum), "least": both("least", torch.minimum),
                "p": tail["p"], "v": tail["v"]}  # fmt: skip

    def choose(self, scene: dict, cmds: torch.Tensor, short: torch.Tensor | None = None,
               field: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:  # fmt: skip
        """The planner's command ``(n, 3)`` among ``cmds`` ``(n, K, 3)``, each held from now for
        the horizon, and ``short`` ``(n, S, 3)`` (:meth:`short_move_candidates`), each held for
        :data:`SHORT_MOVE_STEPS` steps and then a stop: the lowest score (module docstring).
        ``field``: ``(fields (n, G, G), use (n,))``, a geodesic cost-to-go of its own for the
        episodes where ``use`` (:class:`PlannerFilter`'s ``handover_map``)."""
        c, env = self.cfg, scene["env"]
        ec, ids = env.cfg, scene["ids"]
        start = lambda m: (scene["pos"][:, None].expand(n, m, 3).contiguous(),  # noqa: E731
                           scene["vel"][:, None].expand(n, m, 3).contiguous())  # fmt: skip
        n, k = cmds.shape[:2]
        roll = self.simulate(scene, cmds, *start(k))
        if short is not None:
            brief = self.move_then_stop(scene, short, *start(short.shape[1]), SHORT_MOVE_STEPS)
            roll = {key: torch.cat([roll[key], brief[key]], 1) for key in roll}
            cmds = torch.cat([cmds, short], 1)
        first_hit, reach, intrude, least = (
            roll[x] for x in ("first_hit", "reach", "intrude", "least")
        )
        p = roll["p"]
        goal = scene["goal"]
        never = c.horizon + 1

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
        if field is not None:
            grid, use = field
            geo = torch.maximum(sample_field(grid, p[..., :2], ec.half, c.grid_resolution), flat)
            horiz = torch.where(use[:, None], geo, horiz)
            ctg = torch.where(use[:, None], (geo * geo + delta[..., 2] ** 2).sqrt(), ctg)
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
        return cmds[torch.arange(n, device=env.device), best]


def _scene(env: SafeNavVectorEnv, ids: torch.Tensor, view_range: float, **parts) -> dict:
    """A scene of episodes ``ids``: their vehicles' state, goals and altitude bands, the wall's
    sides within ``view_range`` (m), and the obstacles' ``parts`` (no range-image hits unless
    given)."""
    pos = env.pos[ids]
    return {"env": env, "ids": ids, "pos": pos, "vel": env.vel[ids], "goal": env.goal[ids],
            "wall_seen": (_sides(pos, env.cfg.half) <= view_range)[:, None],  # (n, 1, 4)
            "band": (env.band[ids, 0, None], env.band[ids, 1, None]),
            "hits": None, "columns": None, "hit_r": None, **parts}  # fmt: skip


def _sides(p: torch.Tensor, half: float) -> torch.Tensor:
    """Distances ``(..., 4)`` from points ``p`` ``(..., 3)`` to the four sides of the wall."""
    return torch.stack([half - p[..., 0], half + p[..., 0], half - p[..., 1], half + p[..., 1]], -1)


class AutoresetPlanner(OraclePlanner):
    """The planner on auto-resetting envs (``SAME_STEP``, as in training): its per-episode state
    (the previous command, the remembered hit points) restarts for each env whose goal changed,
    not for all, and no env is ever left finished (a finished episode is reset at once)."""

    @torch.no_grad()
    def __call__(self, obs: dict[str, torch.Tensor], env: SafeNavVectorEnv) -> torch.Tensor:
        if self._env is not env:
            self._start(env)
        new = (env.goal != self._goals).any(-1)
        self.prev_cmd[new] = 0.0
        if self.seen is not None:  # --sense lidar: a new episode remembers nothing
            self.seen[new] = FAR
        self._goals = env.goal.clone()
        self.finished[:] = False
        return super().__call__(obs, env)

    def _update_finished(self, env: SafeNavVectorEnv) -> None:
        pass


FILTER_VIEWS = ("simulator", "observation")
"""What :class:`PlannerFilter` sees (its ``view``)."""
STALL_TESTS = ("tumbling", "sliding")
"""When :class:`PlannerFilter`'s stall handover tests for a stall (its ``stall_test``)."""
FILTER_STALL = (5.0, 1.0, 5.0)
"""The stall handover of ``safenav train --flight-filter`` and ``eval --planner-filter``: less than
1 m nearer the goal over the last 5 s (:data:`FILTER_STALL_TEST`) and the planner flies 5 s.
Adopted by its validation screen (2026-12-05; docs/csac-v1.md, "A sliding stall test"), after
the first handover, 2 m in tumbling 10 s windows (:data:`FILTER_STALL_TUMBLING`)."""
FILTER_STALL_TEST = "sliding"
"""The adopted ``stall_test`` of :data:`FILTER_STALL`."""
FILTER_SHORT_MOVES = True
"""Whether the adopted filter's planner weighs short moves (``PlannerFilter(short_moves=...)``;
adopted by its validation screen, 2026-12-05: docs/csac-v1.md, "Short moves for the filter's
planner")."""
FILTER_BRAKING_CAP = False
"""Whether the flight shield keeps its braking cap behind the adopted filter (``"braking_cap":
false`` in a :func:`filter_spec`: the shield flies without it where the filter flies after it;
adopted by its validation screen, 2026-12-06: docs/csac-v1.md, "The braking cap behind the
filter"). The periodic evaluations and the selection, which fly no filter, keep the cap."""
FILTER_STALL_TUMBLING = (10.0, 2.0, 5.0)
"""The first adopted handover (tested in tumbling windows): what a policy's recorded filter
without a ``"stall_test"`` (trained before 2026-12-05) flies."""


def observes_pillars(cfg) -> bool:
    """Whether an env config's observation has the pillar list (``static_tracked`` > 0) that the
    filter's observed view, in the simulator and on board, flies on. The one test of it: the
    trainer, ``safenav fly`` and the onboard runtime refuse a filter without it."""
    return bool(cfg is not None and getattr(cfg, "static_tracked", 0))


def filter_spec(view: str = "observation",
                stall: tuple[float, float, float] | None = FILTER_STALL,
                stall_test: str = FILTER_STALL_TEST,
                short_moves: bool = FILTER_SHORT_MOVES,
                handover_map: bool = False, handover_exit: str = "time",
                braking_cap: bool = FILTER_BRAKING_CAP) -> dict:  # fmt: skip
    """A :class:`PlannerFilter` as a policy's ``meta["flight_filter"]`` records it (``safenav
    train --flight-filter``): ``{"view": ..., "stall": [window, progress, handover] or None,
    "stall_test": ...}`` and ``"short_moves": true``, ``"handover_map": true``,
    ``"handover_exit": "nearer"`` and ``"braking_cap": false`` (the flight shield before the
    filter without its braking cap: :func:`shield_under_filter`) where set; by default the
    adopted one."""
    if view not in FILTER_VIEWS:
        raise ValueError(f"view={view!r}: choose one of {FILTER_VIEWS}")
    if stall_test not in STALL_TESTS:
        raise ValueError(f"stall_test={stall_test!r}: choose one of {STALL_TESTS}")
    if (handover_map or handover_exit != "time") and stall is None:
        raise ValueError("handover_map and handover_exit shape the stall handovers: they need a "
                         "stall setting")  # fmt: skip
    if handover_exit not in HANDOVER_EXITS:
        raise ValueError(f"handover_exit={handover_exit!r}: choose one of {HANDOVER_EXITS}")
    stall = None if stall is None else [float(x) for x in stall]
    spec = {"view": view, "stall": stall, "stall_test": stall_test}
    if short_moves:
        spec["short_moves"] = True
    if handover_map:
        spec["handover_map"] = True
    if handover_exit != "time":
        spec["handover_exit"] = handover_exit
    if not braking_cap:
        spec["braking_cap"] = False
    return spec


def lifts_braking_cap(planner_filter: dict | None) -> bool:
    """Whether the shield before the filter ``planner_filter`` (a :func:`filter_spec`; None: no
    filter) flies without its braking cap: where the filter records ``"braking_cap": false``."""
    return planner_filter is not None and planner_filter.get("braking_cap", True) is False


def shield_under_filter(shield: dict | None, planner_filter: dict | None) -> dict | None:
    """The flight shield spec ``shield`` (``meta["flight_shield"]``) as it flies before the
    filter ``planner_filter``: without its braking cap where :func:`lifts_braking_cap`, else
    unchanged."""
    if shield is None or not lifts_braking_cap(planner_filter):
        return shield
    return {**shield, "brake": False}


def filter_from_spec(spec: dict) -> PlannerFilter:
    """A fresh :class:`PlannerFilter` of a :func:`filter_spec`, as the policy that records it
    was reported behind (a record without ``"stall_test"``, from before 2026-12-05: tumbling
    windows). ValueError for a record that names no such filter."""
    if not isinstance(spec, dict) or spec.get("view") not in FILTER_VIEWS:
        raise ValueError(f"planner filter {spec!r}: no view among {FILTER_VIEWS}")
    stall = spec.get("stall")
    if stall is not None and not (isinstance(stall, (list, tuple)) and len(stall) == 3 and
                                  all(isinstance(x, (int, float)) for x in stall)):  # fmt: skip
        raise ValueError(f"planner filter {spec!r}: stall is [window s, progress m, handover s]")
    if not isinstance(spec.get("braking_cap", True), bool):
        raise ValueError(f"planner filter {spec!r}: braking_cap is true or false")
    return PlannerFilter(view=spec["view"], stall=None if stall is None else tuple(stall),
                         stall_test=spec.get("stall_test", "tumbling"),
                         short_moves=bool(spec.get("short_moves", False)),
                         handover_map=bool(spec.get("handover_map", False)),
                         handover_exit=spec.get("handover_exit", "time"))  # fmt: skip


class PlannerFilter(OraclePlanner):
    """A model-predictive safety filter over a policy (beyond the paper and NavRL): the
    Simplex architecture (Sha, 2001; with a learned controller, Phan et al., 2020, "Neural
    Simplex Architecture") with the planner as its safe controller, and a predictive safety
    filter's test (Wabersich & Zeilinger, 2021) of each action.

    Called as a shield, ``action = filter(env, obs, action)``. Each step, for each unfinished
    episode, the policy's command is held for ``hold`` control steps and then each of the
    planner's candidates (:meth:`~OraclePlanner.candidates`) for the rest of the horizon, all
    through the env's velocity tracker against what the planner's config lets it see. The
    policy's action flies unchanged (bit for bit) if its own steps and at least one continuation
    (the policy's command itself held on, or a candidate) neither collide nor enter the margins
    (``margin`` from pillars, wall and altitude limits, ``margin + mover_margin`` from moving
    obstacles forecast at constant velocity): a way out is left after it. Otherwise the
    planner's own choice flies (:meth:`~OraclePlanner.choose`).
    ``overrides`` counts the steps where it did, ``steps`` all filtered steps, and
    ``overridden`` ``(N,)`` says which envs' actions it replaced at the last call.

    ``view``: what it sees. ``"simulator"``: its config's view read from the simulator (with
    ``PLANNER_PILLARS``, the pillars, wall and moving obstacles within 4 m; a diagnostic of what
    the ``static`` entry's geometry allows); ``"observation"``: what the vehicle has on board,
    the observation's pillar list and tracked moving obstacles, its odometry and the arena's
    wall (:meth:`~OraclePlanner.observed_scene`; docs/csac-v1.md).

    ``stall``: ``(window s, progress m, handover s)`` or None (off): a recovery behaviour, as
    navigation stacks have. Where an episode has come less than ``progress`` metres nearer its
    goal over the last ``window`` seconds, the planner flies the next ``handover`` seconds
    (counted in ``handovers`` and in ``overrides``), then the policy again. ``stall_test``: when
    that is tested: ``"sliding"`` (adopted, :data:`FILTER_STALL_TEST`), every step over the last
    ``window`` seconds, a full window after the episode's start or the last handover;
    ``"tumbling"`` (the first), at the end of back-to-back windows, so a dither is handed over one
    to two windows after it starts.

    ``short_moves`` (adopted, :data:`FILTER_SHORT_MOVES`; docs/csac-v1.md "Short moves for the
    filter's planner"): where
    the planner flies, it also weighs :meth:`~OraclePlanner.short_move_candidates`, each held
    0.5 s and then a stop: in a pocket between pillars, where every command held 2 s collides,
    the planner otherwise hovers there (watched on validation).

    ``handover_map`` (docs/csac-v1.md, "A map for the stall handover"): the filter remembers
    every pillar its view has shown in the episode (up to :data:`MAP_PILLARS`), and at the start
    of each stall handover plans the handover on a geodesic cost-to-go to the goal around them
    (:func:`grid_graph`, Dijkstra) instead of the straight distance, whose local minima (a goal
    behind a row of pillars) are where the stalls were watched to dither. Screened on
    validation, not adopted; the onboard filter does not take it (nor ``handover_exit``).

    ``handover_exit``: when a handover ends. ``"time"``: after ``handover`` s. ``"nearer"``
    (docs/csac-v1.md, "A handover that ends nearer the goal"): not before the UAV is ``progress``
    m nearer its goal than where it stalled (a Bug algorithm's leave condition), at most
    :data:`HANDOVER_CAP` times ``handover`` s (with ``handover_map``: screened, not adopted)."""

    def __init__(self, config: OracleConfig | None = None, hold: int = 1,
                 scan: ScanFn | None = None, view: str = "simulator",
                 stall: tuple[float, float, float] | None = None,
                 stall_test: str = FILTER_STALL_TEST,
                 short_moves: bool = False, handover_map: bool = False,
                 handover_exit: str = "time") -> None:  # fmt: skip
        super().__init__(config or PLANNER_PILLARS, scan)
        if not 1 <= hold < self.cfg.horizon:
            raise ValueError(f"hold={hold}: between 1 and the horizon - 1 ({self.cfg.horizon - 1})")
        if view not in FILTER_VIEWS:
            raise ValueError(f"view={view!r}: choose one of {FILTER_VIEWS}")
        if stall is not None and (len(stall) != 3 or not all(0 < x < math.inf for x in stall)):
            raise ValueError(f"stall={stall!r}: (window s, progress m, handover s), each > 0")
        if stall_test not in STALL_TESTS:
            raise ValueError(f"stall_test={stall_test!r}: choose one of {STALL_TESTS}")
        self.hold, self.view, self.stall, self.stall_test = int(hold), view, stall, stall_test
        if (handover_map or handover_exit != "time") and stall is None:
            raise ValueError("handover_map and handover_exit shape the stall handovers: they "
                             "need stall=")  # fmt: skip
        if handover_exit not in HANDOVER_EXITS:
            raise ValueError(f"handover_exit={handover_exit!r}: choose one of {HANDOVER_EXITS}")
        self.handover_exit = handover_exit
        self.short_moves, self.handover_map = bool(short_moves), bool(handover_map)
        self.overrides = self.steps = self.handovers = 0
        self.overridden: torch.Tensor | None = None

    @property
    def override_share(self) -> float:
        """The share of the filtered steps where the planner flew (0 before any)."""
        return self.overrides / max(self.steps, 1)

    @property
    def handover_share(self) -> float:
        """The share of the filtered steps that were stall handovers (0 before any)."""
        return self.handovers / max(self.steps, 1)

    def _start(self, env: SafeNavVectorEnv) -> None:
        super()._start(env)
        n = env.num_envs
        self._mark = torch.full((n,), math.inf, device=env.device)  # goal distance, window start
        self._mark_step = torch.zeros(n, dtype=torch.long, device=env.device)
        self._handover_left = torch.zeros(n, dtype=torch.long, device=env.device)
        if self.stall is not None and self.stall_test == "sliding":  # the last window's distances
            w = max(1, round(self.stall[0] / env.cfg.dt))
            self._history = torch.full((n, w + 1), math.inf, device=env.device)
        self._stall_dist = torch.full((n,), math.inf, device=env.device)
        self._extend_left = torch.zeros(n, dtype=torch.long, device=env.device)
        if self.handover_map:  # the pillars seen in each episode, and each handover's field
            self._map_xy = torch.full((n, MAP_PILLARS, 2), FAR, device=env.device)
            self._map_half = torch.zeros(n, MAP_PILLARS, device=env.device)
            self._fields: dict[int, torch.Tensor] = {}

    def _remember(self, env: SafeNavVectorEnv, ids: torch.Tensor, scene: dict) -> None:
        """Add the pillars in view (``scene``'s rows above ground) to episodes ``ids``' maps; an
        episode at its first step starts an empty map. A pillar within :data:`MAP_MATCH` of one
        remembered (both centres) is the same pillar."""
        fresh = ids[env.steps[ids] == 0]
        self._map_xy[fresh], self._map_half[fresh] = FAR, 0.0
        xy, half = scene["pxy"].to(self._map_xy.dtype), scene["phalf"].to(self._map_xy.dtype)
        known = self._map_xy[ids]  # (n, M, 2)
        same = ((xy[:, :, None] - known[:, None]).abs().amax(-1) < MAP_MATCH).any(-1)
        new = (scene["ph"] > -FAR / 2) & ~same  # (n, m)
        count = (known[..., 0] < FAR / 2).sum(-1)
        slot = count[:, None] + new.long().cumsum(-1) - 1
        rows, cols = (new & (slot < MAP_PILLARS)).nonzero(as_tuple=True)
        self._map_xy[ids[rows], slot[rows, cols]] = xy[rows, cols]
        self._map_half[ids[rows], slot[rows, cols]] = half[rows, cols]

    def _plan_handover(self, env: SafeNavVectorEnv, i: int) -> None:
        """Episode ``i``'s geodesic cost-to-go to its goal around the pillars it has seen."""
        from scipy.sparse.csgraph import dijkstra

        c = self.cfg
        known = self._map_xy[i, :, 0] < FAR / 2
        pxy = self._map_xy[i, known].cpu().double().numpy()
        half = self._map_half[i, known].cpu().double().numpy()
        graph, g = grid_graph(pxy, half, env.cfg, c.grid_resolution, c.block_penalty, c.margin)
        goal = goal_cells(env.goal[i : i + 1, :2].cpu().numpy(), env.cfg, c.grid_resolution)
        dist = dijkstra(graph, directed=False, indices=int(goal[0]))
        self._fields[i] = torch.as_tensor(dist.reshape(g, g), dtype=torch.float32,
                                          device=env.device)  # fmt: skip

    def _handing_over(self, env: SafeNavVectorEnv, ids: torch.Tensor) -> torch.Tensor:
        """``stall``'s test for episodes ``ids``: ``(n,)`` True where the planner flies now."""
        window, progress, handover = self.stall
        to_steps = lambda s: max(1, round(s / env.cfg.dt))  # noqa: E731
        w, h = to_steps(window), to_steps(handover)
        d = (env.goal[ids] - env.pos[ids]).norm(dim=-1)
        t = env.steps[ids].to(torch.long)
        if self.handover_exit == "nearer":
            self._extend(env, ids, d, t, progress, h)
        test = self._sliding_stalled if self.stall_test == "sliding" else self._tumbling_stalled
        stalled = test(ids, d, t, w, progress)
        if self.handover_map:
            for i in ids[stalled].tolist():
                self._plan_handover(env, i)
        self._handover_left[ids[stalled]] = h
        if self.handover_exit == "nearer":
            self._stall_dist[ids[stalled]] = d[stalled]
            self._extend_left[ids[stalled]] = HANDOVER_CAP * h - h
        if self.stall_test == "sliding":
            self._mark_step[ids[stalled]] = t[stalled] + h  # a full window after it ends
        handing = self._handover_left[ids] > 0
        self._handover_left[ids[handing]] -= 1
        self.handovers += int(handing.sum())
        return handing

    def _extend(self, env: SafeNavVectorEnv, ids: torch.Tensor, d: torch.Tensor, t: torch.Tensor,
                progress: float, h: int) -> None:  # fmt: skip
        """``handover_exit="nearer"``: a handover whose time is up goes on, a step at a time, while
        the UAV is not ``progress`` m nearer its goal than where it stalled, up to
        :data:`HANDOVER_CAP` handovers long (the next stall test a full window after it ends);
        with ``handover_map`` its field is planned again where it goes on."""
        nearer = d <= self._stall_dist[ids] - progress
        self._extend_left[ids[nearer]] = 0
        go_on = (self._handover_left[ids] == 0) & (self._extend_left[ids] > 0)
        if self.handover_map:
            for i in ids[go_on & (self._extend_left[ids] == HANDOVER_CAP * h - h)].tolist():
                self._plan_handover(env, i)
        self._handover_left[ids[go_on]] = 1
        self._extend_left[ids[go_on]] -= 1
        self._mark_step[ids[go_on]] = t[go_on] + 1

    def _tumbling_stalled(self, ids: torch.Tensor, d: torch.Tensor, t: torch.Tensor, w: int,
                          progress: float) -> torch.Tensor:  # fmt: skip
        """The ``"tumbling"`` test: at the end of each ``w``-step window, progress over it."""
        begun = (t == 0) | torch.isinf(self._mark[ids])  # a new episode: its window starts now
        due = ~begun & (t - self._mark_step[ids] >= w)
        stalled = due & (self._mark[ids] - d < progress)
        restart = begun | due
        self._mark[ids[restart]] = d[restart]
        self._mark_step[ids[restart]] = t[restart]
        return stalled

    def _sliding_stalled(self, ids: torch.Tensor, d: torch.Tensor, t: torch.Tensor, w: int,
                         progress: float) -> torch.Tensor:  # fmt: skip
        """The ``"sliding"`` test: distance now against ``w`` steps ago, every step, once ``w``
        steps of this episode have passed since its start or its last handover's end."""
        slots = self._history.shape[1]  # w + 1: now and w steps ago
        self._history[ids, t % slots] = d
        before = self._history[ids, (t - w) % slots]
        self._mark_step[ids[t == 0]] = 0
        free = self._handover_left[ids] == 0
        return free & (t - self._mark_step[ids] >= w) & (before - d < progress)

    @torch.no_grad()
    def __call__(  # type: ignore[override]  (a shield's signature, not a policy's)
        self, env: SafeNavVectorEnv, obs: dict[str, torch.Tensor], action: torch.Tensor
    ) -> torch.Tensor:
        ids = self._step_start(obs, env)
        out = action.clone()
        self.overridden = torch.zeros(env.num_envs, dtype=torch.bool, device=env.device)
        if len(ids) == 0:
            return out
        ec, never = env.cfg, self.cfg.horizon + 1
        cos_y, sin_y = env.cos_yaw[ids], env.sin_yaw[ids]
        # The command the env will apply for the policy's action (goal frame, clipped per axis).
        proposal = goal_frame_to_world(action[ids].clamp(-1.0, 1.0) * ec.v_max, cos_y, sin_y)
        cmds = self.candidates(obs, env, ids)  # (n, K, 3)
        scene = (self.scene if self.view == "simulator" else self.observed_scene)(obs, env, ids)
        if self.handover_map:
            self._remember(env, ids, scene)
        n, k = cmds.shape[:2]
        clean = lambda r: (r["first_hit"] == never) & (r["intrude"] <= 0)  # noqa: E731
        start = lambda sc: (sc["pos"][:, None], sc["vel"][:, None])  # noqa: E731  one rollout each
        # Held for the whole horizon, the policy's command is its own way out (one rollout);
        # only where it is not are the candidates tried after it.
        safe = clean(self.simulate(scene, proposal[:, None], *start(scene)))[:, 0]
        rest = (~safe).nonzero().squeeze(-1)
        if len(rest):
            sub = _scene_rows(scene, rest)
            head = self.simulate(sub, proposal[rest, None], *start(sub), 0, self.hold)
            tail = self.simulate(sub, cmds[rest], head["p"].expand(-1, k, 3).contiguous(),
                                 head["v"].expand(-1, k, 3).contiguous(), self.hold)  # fmt: skip
            safe[rest] = clean(head)[:, 0] & clean(tail).any(-1)
        handing = torch.zeros_like(safe)
        if self.stall is not None:
            handing = self._handing_over(env, ids)
            safe = safe & ~handing
        flown = proposal
        self.steps += n
        bad = (~safe).nonzero().squeeze(-1)
        if len(bad):  # the planner's choice (its smoothness term against the last flown command)
            self.overrides += len(bad)
            self.overridden[ids[bad]] = True
            short = self.short_move_candidates(env, ids[bad]) if self.short_moves else None
            field = None
            if self.handover_map and bool(handing[bad].any()):  # handovers fly their own field
                grids = [self._fields.get(i) for i in ids[bad].tolist()]
                planned = torch.tensor([x is not None for x in grids], device=env.device)
                use = handing[bad] & planned
                blank = torch.zeros_like(next(x for x in grids if x is not None))
                field = (torch.stack([blank if x is None else x for x in grids]), use)
            chosen = self.choose(_scene_rows(scene, bad), cmds[bad], short, field)
            flown = proposal.clone()
            flown[bad] = chosen
            out[ids[bad]] = to_action(chosen, cos_y[bad], sin_y[bad], ec.v_max).to(out.dtype)
        self.prev_cmd[ids] = flown
        return out


def behind_filter(shield, planner_filter: PlannerFilter):
    """A shield ``(env, obs, action) -> action``: ``shield`` (None: none), then
    ``planner_filter`` on its output."""
    if shield is None:
        return planner_filter
    return lambda env, obs, action: planner_filter(env, obs, shield(env, obs, action))


def _scene_rows(scene: dict, rows: torch.Tensor) -> dict:
    """The :meth:`OraclePlanner.scene` of the episodes ``rows`` of it (indices into its ``ids``)."""
    out = dict(scene)
    for key, value in scene.items():
        if key in ("env", "nd"):
            continue
        if key == "future":
            out[key] = None if value is None else value[:, rows]
        elif key == "band":
            out[key] = tuple(b[rows] for b in value)
        elif value is not None:
            out[key] = value[rows]
    return out


PLANNER_B_BEAMS = (-30.0, -15.0, 0.0, 15.0)
"""The beam elevations (degrees) planner B was measured with (``csac-shielded-memory``'s)."""

PLANNER_B = OracleConfig(sense="lidar", memory=10, ignore_ground=True,
                         climbs=(-0.75, -0.25, 0.0, 0.25, 0.75))  # fmt: skip
"""Planner B of docs/csac-v1.md: the range image's hits of the last second (10 images, ground
hits ignored), five climb rates, the observation's moving obstacles; 0.861 success / 0.097
collision on 144 validation episodes with the tilted beams of ``csac-shielded-memory``."""

PLANNER_PILLARS = OracleConfig(sense="exact", privileged_range=4.0,
                               climbs=(-0.75, -0.25, 0.0, 0.25, 0.75))  # fmt: skip
"""The pillar-geometry planner of docs/csac-v1.md ("What the range image costs"): the exact
footprints and tops of the pillars and the wall within 4 m (what ``static_tracked`` gives a
policy), the moving obstacles within 4 m forecast at constant velocity, five climb rates; 0.951
success / 0.021 collision on 144 validation episodes (with ``keep_band``: 0.896 / 0.000)."""

PLANNERS = {"range": PLANNER_B, "pillars": PLANNER_PILLARS}
"""The planners a learner may replay (``CSACConfig.planner_view``), by what they see."""

__all__ = ["FAR", "FILTER_BRAKING_CAP", "FILTER_SHORT_MOVES", "FILTER_STALL", "FILTER_STALL_TEST",
           "FILTER_STALL_TUMBLING", "FILTER_VIEWS", "HANDOVER_CAP", "HANDOVER_EXITS", "MAP_MATCH",
           "MAP_PILLARS", "PLANNERS", "PLANNER_B", "PLANNER_B_BEAMS", "PLANNER_PILLARS",
           "SHORT_MOVE_CLIMBS", "SHORT_MOVE_SPEEDS", "SHORT_MOVE_STEPS", "AutoresetPlanner",
           "OracleConfig", "OraclePlanner", "PlannerFilter", "ScanFn", "beam_hits",
           "behind_filter", "filter_from_spec", "filter_spec", "geodesic_fields", "goal_cells",
           "grid_graph", "lifts_braking_cap", "mover_clearance", "sample_field",
           "shield_under_filter", "to_action"]  # fmt: skip
