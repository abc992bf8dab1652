"""``SafeNav-v1``: quadrotor navigation among static pillars and moving obstacles in a closed
arena, as a CMDP.

:class:`SafeNavVectorEnv` is the simulator: ``N`` UAVs stepped as one batch of tensors (no per-env
Python loop), on CPU or CUDA. :class:`SafeNavEnv` is the single-env view of it (``N = 1``).
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch
from gymnasium import Env, spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from safenav.envs import rng
from safenav.envs.config import CRUISE_HALF_BAND, EnvConfig, make_config, observation_shapes
from safenav.envs.dynamics import (
    goal_frame_to_world,
    move_obstacles,
    sample_obstacle_goals,
    sample_obstacle_speeds,
    velocity_tracker,
    world_to_goal_frame,
)
from safenav.envs.sensors import (
    FAR_POINT,
    RangeImageSpec,
    beam_hit_points,
    dequantize_heights,
    dynamic_obstacle_features,
    map_footprints,
    memory_image,
    moving_obstacle_clearance,
    pillar_boxes,
    pillar_clearance,
    quantize_heights,
    raycast_boxes_bruteforce,
    raycast_height_map,
    static_obstacle_features,
)
from safenav.envs.world import (
    CUBOID_HEIGHT,
    CUBOID_Z_RANGE,
    CYLINDER_HEIGHT,
    WALL_HEIGHT,
    GridSpec,
    World,
    border_clearance,
    border_walls,
    generate_world,
    height_map,
    side_points,
    world_from_obstacles,  # noqa: F401  (re-exported for custom maps)
)

# Observation scales: every feature lands roughly in [-1, 1] (documented in the class docstring).
DIST_SCALE = 20.0  # m, horizontal distance to goal
Z_SCALE = 4.0  # m, altitude difference to goal
# Random streams of episode sampling (keys of the counter-based generator).
_STREAMS = dict(s_side=1, s_along=2, s_z=3, g_side=4, g_along=5, g_z=6)
BORDER_BAND = 2.0  # m: flight this close to the border counts in the border-time metric
# Pillars (xy (N, P, 2), half side (N, P)) and moving obstacles (xy (N, D, 2), half width (N, D))
# as each episode sees them at its start: what a start or goal must keep clear of.
Obstacles = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]
START_CANDIDATES = 16  # draws of a site per start and per goal; some mover is inside ~1 site in 10
_CHUNK = 1 << 22  # candidate-obstacle pairs per clearance batch (bounds memory at big resets)


def _clearance_xy(points: torch.Tensor, obstacles: Obstacles) -> torch.Tensor:
    """Horizontal distance from candidate points ``(N, K, 2)`` to the nearest obstacle surface
    (pillar footprints; moving obstacles as discs of their half width), ``(N, K)``."""
    p_xy, p_half, m_xy, m_half = obstacles
    d = ((points[:, :, None, :] - p_xy[:, None]).abs() - p_half[:, None, :, None]).clamp(min=0)
    clear = (
        d.norm(dim=-1).amin(-1) if p_xy.shape[1] else points.new_full(points.shape[:2], math.inf)
    )
    if m_xy.shape[1]:
        m = (points[:, :, None, :] - m_xy[:, None]).norm(dim=-1) - m_half[:, None]
        clear = torch.minimum(clear, m.amin(-1))
    return clear


def _pick(candidates: torch.Tensor, clear: torch.Tensor, radius: float) -> torch.Tensor:
    """Per row, the first candidate whose clearance reaches ``radius`` (else the clearest)."""
    ok = clear >= radius
    k = torch.where(ok.any(-1), ok.to(torch.uint8).argmax(-1), clear.argmax(-1))
    return candidates[torch.arange(len(k), device=k.device), k]


def sample_episodes(
    cfg: EnvConfig,
    env_seed: torch.Tensor,
    counter: torch.Tensor,
    sites: torch.Tensor,
    obstacles: Obstacles | None = None,
):
    """Start and goal of episode ``counter`` of the env seeded ``env_seed`` (batched).

    Starts and goals are sites of the map (``sites``: ``(N, 4, S)`` positions along each side,
    ``edge_margin / 2`` from the border) at altitudes in ``start_height_range``; the goal is on
    another side than the start (NavRL draws sides), moved to the opposite side if closer than
    ``min_goal_distance``. Each is the first of ``START_CANDIDATES`` counter-based draws whose
    ``start_clearance`` disc holds none of ``obstacles`` (the clearest draw if none is clear), so
    that no episode starts or ends inside a moving obstacle.
    """
    n, k, ns = env_seed.shape[0], START_CANDIDATES, sites.shape[-1]
    cand = torch.arange(k, device=env_seed.device)[None, :]
    u = {key: rng.uniform(env_seed[:, None], counter[:, None], stream, cand)
         for key, stream in _STREAMS.items()}  # fmt: skip
    zlo, zhi = cfg.start_height_range
    rows = torch.arange(n, device=sites.device)[:, None]

    def at(side: torch.Tensor, slot_u: torch.Tensor, z_u: torch.Tensor) -> torch.Tensor:
        slot = torch.floor(slot_u * ns).long().clamp(max=ns - 1)
        return side_points(cfg, side, sites[rows, side, slot], zlo + z_u * (zhi - zlo))

    def first_clear(points: torch.Tensor) -> torch.Tensor:
        """Index of the chosen candidate per row."""
        if obstacles is None:
            return torch.zeros(n, dtype=torch.int64, device=points.device)
        size = max(1, _CHUNK // (k * max(1, obstacles[0].shape[1] + obstacles[2].shape[1])))
        clear = torch.cat([_clearance_xy(points[i : i + size, :, :2],
                                         tuple(t[i : i + size] for t in obstacles))  # type: ignore[arg-type]
                           for i in range(0, n, size)]) if n else points.new_zeros(0, k)  # fmt: skip
        ok = clear >= cfg.start_clearance - 1e-4
        return torch.where(ok.any(-1), ok.to(torch.uint8).argmax(-1), clear.argmax(-1))

    s_side = torch.floor(u["s_side"] * 4).long().clamp(max=3)
    starts = at(s_side, u["s_along"], u["s_z"])
    pick = first_clear(starts)
    start, side = starts[rows[:, 0], pick], s_side[rows, pick[:, None]]  # side: (N, 1)
    g_side = (side + 1 + torch.floor(u["g_side"] * 3).long().clamp(max=2)) % 4
    goals = at(g_side, u["g_along"], u["g_z"])
    near = (goals[..., :2] - start[:, None, :2]).norm(dim=-1) < cfg.min_goal_distance
    goals = torch.where(near[..., None], at((side + 2) % 4, u["g_along"], u["g_z"]), goals)
    return start, goals[rows[:, 0], first_clear(goals)]


def world_obstacles(world: World) -> Obstacles:
    """A world's obstacles as the test scenario's episodes see them when they start: every
    pillar, the moving obstacles at their origins."""
    return (torch.as_tensor(world.pillar_xy)[None], torch.as_tensor(world.pillar_half)[None],
            torch.as_tensor(world.dyn_origin[:, :2])[None],
            torch.as_tensor(world.dyn_width / 2)[None])  # fmt: skip


def fixed_scenario(cfg: EnvConfig, env_seed: int = 1, episodes: int = 200):
    """The fixed test scenario (paper IV-B): starts and goals of ``episodes`` episodes, from seed.

    The map is the world of ``env_seed`` at full density; episode ``k`` draws as episode ``k`` of
    the env seeded ``env_seed``, among the map's sites, clear of the moving obstacles at their
    origins (all episodes fly at once from the world's reset). Bit-identical on every machine
    (counter-based integer hashing; the clearance test compares float32 distances with 2 m).
    """
    cfg = cfg.replace(density=1.0)
    world = generate_world(cfg, env_seed)
    seeds = torch.full((episodes,), int(env_seed), dtype=torch.int64)
    sites = torch.as_tensor(world.site_along)[None].expand(episodes, -1, -1)
    obstacles = tuple(t.expand(episodes, *t.shape[1:]) for t in world_obstacles(world))
    return sample_episodes(cfg, seeds, torch.arange(episodes, dtype=torch.int64), sites, obstacles)


class SafeNavVectorEnv(VectorEnv):
    """A batch of UAVs navigating to goals among pillars and moving obstacles (a CMDP).

    ## Description
    The paper's scenario (Fig. 2): a 50 m x 50 m arena with up to 350 static pillars and 100
    moving obstacles of 8 classes, spread up to its border, which is a wall; a quadrotor with a
    0.3 m collision sphere flies from a start near one side to a goal near another, across the
    clutter, using velocity commands. Each env flies in map ``i % num_worlds``; a map is drawn at
    ``reset(seed=...)`` and kept, each episode draws a new start and goal in it.

    ## Action Space
    ``Box(-1, 1, (3,))``: the velocity command in the goal frame (x from start to goal, z up,
    fixed at reset), scaled by ``v_max`` (2 m/s). A PX4-like first-order velocity tracker
    (time constant 0.4 s, 3 m/s^2 limit) follows it.

    ## Observation Space
    ``Dict``: ``state`` (8,): unit vector to goal in the goal frame (3), horizontal distance to
    goal / 20 m (1), z distance to goal / 4 m (1), velocity in the goal frame / v_max (3).
    ``lidar`` (4, 36): ``(4 - d) / 4`` for beam distances ``d`` ray-cast from the occupancy grid
    (pillars and the border wall), rows at elevations -10, 0, 10, 20 degrees, columns every 10
    degrees from the goal direction. With ``lidar_history`` k > 1 (beyond the paper; default 1):
    ``(4 k, 36)``, the images of the last k control steps stacked as rows, newest first (rows
    ``4 i`` to ``4 i + 3`` are the image of ``i`` steps ago); an episode starts with k copies of
    its first image.
    ``dynamic`` (5, 10): the 5 nearest moving obstacles within 4 m (zeros beyond), each: unit
    relative position in the goal frame (3), horizontal distance / 4 (1), z distance / 4 (1),
    velocity in the goal frame / v_max (3), width class / 3 (1), 1 for floating cuboids (1).
    ``static`` (K, 7), only with ``static_tracked`` K > 0 (beyond the paper): the K pillars
    nearest by clearance within 4 m (zeros beyond), each: nearest footprint point and centre
    relative to the UAV in the goal frame / 4 (2 + 2), half side / 0.4 m (1), (top - altitude)
    / 4 (1), 1 (1).

    ## Rewards
    NavRL's shaping: velocity toward the goal (m/s) + mean log(beam distance / range) + mean
    log(clearance / range) of the tracked obstacles - 0.1 |v_t - v_{t-1}| - 8 x squared excursion
    outside the start-goal altitude band (+-0.2 m; far from the goal ``cruise_height`` +- 0.3 m
    instead if set, a named departure) + 20 on reaching the goal. NavRL's +1 per
    step is dropped: with success ending the episode it would pay loitering. ``reward_collision``
    (default 0) adds a reward at a collision step: -100 is the survival stream a crash loses in
    NavRL (about 1 / (1 - 0.99)), in terminal form. ``w_stall`` (default 0, a named departure)
    subtracts a penalty per step once the distance to the goal has not fallen by
    ``stall_progress`` below its least value for ``stall_seconds``.

    ## Cost
    ``info["cost"]`` (paper Eq. 3): 1 at a step with a collision (pillar, moving obstacle, the
    border wall, ground below ``z_min``, ceiling above ``z_max``), else 0 (with
    ``near_miss_margin`` > 0, a named departure: 1 at the episode's first near miss instead).
    Never folded into the reward.

    ## Starting State
    Hovering (zero velocity) at one of the map's start/goal sites (``start_sites`` per side, 1 m
    from the border, each the centre of a 2 m disc free of pillars and of moving obstacles when
    the episode starts), altitude in [0.5, 2.5] m; the goal is a site on another side, at least
    ``min_goal_distance`` away. Between them the map is as cluttered as anywhere, up to the
    border: no obstacle-free corridor joins them except by chance of the draw.

    ## Episode End
    Terminated on success (within 0.5 m of the goal) or collision; truncated at the time limit
    (60 s = 600 steps). Autoreset ``SAME_STEP``: the returned observation of a finished env is the
    first of its next episode; ``info["final_obs"]`` holds the last one (``info["_final_obs"]``
    marks which envs finished) and ``info["episode"]`` its statistics (return, cost, length,
    success / collision / timeout, time, path length, minimum clearance, mean speed,
    ``detour_ratio`` (path length / start-goal distance), ``border_time`` and ``outside_time``
    (shares of its steps within 2 m of the border and outside the map), and what a collision was
    with: ``hit_static``, ``hit_dynamic``, ``out_of_bounds`` (altitude band or border wall),
    ``hit_border``).

    ## Gymnasium 1.x conventions
    ``metadata["autoreset_mode"]`` declares the mode: ``SAME_STEP`` (default) or ``DISABLED``
    (``NEXT_STEP`` is refused). ``SAME_STEP`` as Gymnasium's ``SyncVectorEnv`` does it, with one
    difference: ``info["final_obs"]`` is batched (a dict of ``(num_envs, ...)`` arrays, valid
    rows marked by ``info["_final_obs"]``), not an object array of per-env observations;
    Gymnasium's ``DictInfoToList`` turns it into per-env ones. ``info["final_info"]`` holds the
    finished envs' info of their last step (``cost``, ``success``, ``collision``, ``clearance``,
    ``episode``, each with its ``_key`` mask; ``info["_final_info"]``): the same arrays as the
    top-level keys, which keep them. ``DISABLED``: nothing resets by itself; ``reset(options=
    {"reset_mask": mask})`` starts the next episode of the envs in ``mask`` only.
    ``info["episode"]`` also has ``RecordEpisodeStatistics``' keys: ``r`` (return), ``l``
    (length), ``t`` (wall-clock seconds), 0 where the episode goes on: right on every Gymnasium,
    while that wrapper counts ``SAME_STEP`` episodes right only from Gymnasium 1.4 (before, it
    drops each episode's first step), and refuses to overwrite ``info["episode"]``: give it
    another ``stats_key``. ``DictInfoToList`` needs Gymnasium >= 1.2.2. Tested:
    ``gymnasium.utils.env_checker.check_env`` on :class:`SafeNavEnv`, the vector-env counterpart
    of its checks and of both autoreset modes in ``tests/test_gym_conventions.py``.

    ## Arguments
    ``num_envs``; ``preset`` (``"easy"``, ``"medium"``, ``"paper"``) or ``config``
    (:class:`EnvConfig`); any ``EnvConfig`` field as keyword; ``device`` (``"cpu"``,
    ``"cuda"``); ``output`` (``"numpy"`` or ``"torch"``: tensors stay on the device);
    ``autoreset_mode``; ``raycaster`` (``"grid"``, or ``"bruteforce"`` for the reference).

    >>> import gymnasium as gym, safenav
    >>> envs = gym.make_vec("SafeNav-v1", num_envs=4, preset="easy")
    >>> obs, info = envs.reset(seed=0)
    >>> obs["state"].shape, obs["lidar"].shape, obs["dynamic"].shape
    ((4, 8), (4, 4, 36), (4, 5, 10))
    >>> obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
    >>> sorted(k for k in info if not k.startswith("_"))[:3]
    ['clearance', 'collision', 'cost']

    ## Version History
    * v1: closed arena: the border is a wall (a collision, seen by the range sensor), obstacles
      fill the map up to it, starts and goals are drawn clear of obstacles; episode statistics
      ``detour_ratio``, ``border_time``, ``outside_time``, ``hit_border``.
    * v0: initial release (removed: nothing bounded x and y, and an obstacle-free 2 m ring along
      the border joined every start to every goal).
    """

    metadata = {
        "render_modes": ["rgb_array"],
        "render_fps": 10,
        "autoreset_mode": AutoresetMode.SAME_STEP,
    }

    def __init__(
        self,
        num_envs: int = 1,
        preset: str = "paper",
        config: EnvConfig | None = None,
        device: str | torch.device = "cpu",
        output: str = "numpy",
        autoreset_mode: AutoresetMode | str = AutoresetMode.SAME_STEP,
        render_mode: str | None = None,
        raycaster: str = "grid",
        max_episode_steps: int | None = None,  # accepted from gymnasium.make_vec; see EnvConfig
        **overrides: Any,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs={num_envs!r} is invalid: must be an integer >= 1")
        if config is None:
            config = make_config(preset, **overrides)
        elif overrides:
            config = config.replace(**overrides)
        if max_episode_steps is not None:
            config = config.replace(max_episode_seconds=max_episode_steps / config.control_hz)
        if output not in ("numpy", "torch"):
            raise ValueError(f"output={output!r} is invalid: choose 'numpy' or 'torch'")
        if raycaster not in ("grid", "bruteforce"):
            raise ValueError(f"raycaster={raycaster!r} is invalid: choose 'grid' or 'bruteforce'")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode={render_mode!r} is invalid: only 'rgb_array'")
        self.autoreset_mode = AutoresetMode(autoreset_mode)
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            raise ValueError("autoreset_mode NEXT_STEP is not supported: use SAME_STEP or DISABLED")
        self.metadata = {**self.metadata, "autoreset_mode": self.autoreset_mode}
        self.cfg = config
        self.num_envs = num_envs
        self.device = torch.device(device)
        self.output = output
        self.render_mode = render_mode
        self.raycaster = raycaster
        # Maps: the largest divisor of num_envs not above the request (env i flies in map i % W).
        wanted = min(config.num_worlds or 16, num_envs)
        self.num_worlds = max(d for d in range(1, wanted + 1) if num_envs % d == 0)
        self.grid = GridSpec.for_config(config)
        self._walls = border_walls(self.grid, config.half)
        self.spec_lidar = RangeImageSpec.for_config(config)

        shapes = observation_shapes(config)
        self.single_observation_space = spaces.Dict(
            {
                "state": spaces.Box(-np.inf, np.inf, shapes["state"], np.float32),
                "lidar": spaces.Box(0.0, 1.0, shapes["lidar"], np.float32),
                "dynamic": spaces.Box(-np.inf, np.inf, shapes["dynamic"], np.float32),
                **(
                    {"static": spaces.Box(-np.inf, np.inf, shapes["static"], np.float32)}
                    if "static" in shapes
                    else {}
                ),
            }
        )
        self.single_action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)

        dev, n = self.device, num_envs
        z3 = lambda: torch.zeros(n, 3, device=dev)  # noqa: E731
        self.pos, self.vel, self.prev_vel, self.start, self.goal = z3(), z3(), z3(), z3(), z3()
        self.yaw = torch.zeros(n, device=dev)
        self.cos_yaw, self.sin_yaw = torch.ones(n, device=dev), torch.zeros(n, device=dev)
        self.band = torch.zeros(n, 2, device=dev)
        self.steps = torch.zeros(n, dtype=torch.int64, device=dev)
        self.episode_counter = torch.zeros(n, dtype=torch.int64, device=dev)
        self.env_seed = torch.zeros(n, dtype=torch.int64, device=dev)
        self.world_idx = torch.arange(n, device=dev) % self.num_worlds
        # redraw_maps: envs that move to the newest map set when their next episode starts, that
        # set (0 or 1: world slots [set * W, set * W + W)), its seed; _mixed while envs fly in both.
        self._pending = torch.zeros(n, dtype=torch.bool, device=dev)
        self._map_set, self._map_set_seed, self._mixed = 0, 0, False
        self.straight = torch.zeros(n, device=dev)  # start-goal distance of the episode
        self._stats = {k: torch.zeros(n, device=dev) for k in
                       ("return", "cost", "path_length", "speed_sum", "border_steps",
                        "outside_steps")}  # fmt: skip
        self._min_clear = torch.full((n,), math.inf, device=dev)
        # w_stall: the least distance to the goal so far and the steps since it last fell.
        self._best_dist = torch.zeros(n, device=dev)
        self._stalled = torch.zeros(n, dtype=torch.int64, device=dev)
        # Wall-clock start of each episode (time.perf_counter), for the episode statistic "t".
        self._t0 = torch.zeros(n, dtype=torch.float64, device=dev)
        self.worlds: list[World] = []
        self._fresh_worlds = False
        self._trail: list[np.ndarray] = []
        self.render_env_index = 0
        self._last_ranges: torch.Tensor | None = None
        # Range-image history (lidar_history > 1): the stacked lidar rows of the last step,
        # newest image first; observations get copies (a caller may change them in place).
        self._lidar_hist: torch.Tensor | None = None
        # Memory image (lidar_memory > 0): the world hit points of the last lidar_memory range
        # images, (N, lidar_memory, E * C, 3), a ring filled at slot _mem_slot; FAR = no point.
        self._mem: torch.Tensor | None = None
        self._mem_slot = 0

    # ------------------------------------------------------------------ worlds and density
    def _build_worlds(self, base_seed: int) -> None:
        self.set_worlds([generate_world(self.cfg, base_seed + i) for i in range(self.num_worlds)])

    def set_worlds(self, worlds: list[World]) -> None:
        """Install maps (one per world slot, e.g. from :func:`~safenav.envs.world.world_from_obstacles`);
        moving obstacles restart at their origins. ``reset()`` without a seed keeps them."""
        cfg, dev, w = self.cfg, self.device, self.num_worlds
        if len(worlds) != w:
            raise ValueError(f"set_worlds needs {w} worlds (num_worlds), got {len(worlds)}")
        self.worlds = list(worlds)
        self._fresh_worlds = True
        self.world_idx = torch.arange(self.num_envs, device=dev) % w  # one map set again
        self._pending.zero_()
        self._map_set, self._map_set_seed, self._mixed = 0, int(worlds[0].seed), False
        self.env_seed = torch.arange(self.num_envs, dtype=torch.int64, device=dev) + worlds[0].seed
        for name, t in self._map_tensors(self.worlds).items():
            setattr(self, name, t)
        self._obstacle_id = torch.arange(cfg.num_dynamic, device=dev)
        self._apply_density()
        self._reset_obstacles()

    def _map_tensors(self, worlds: list[World]) -> dict[str, torch.Tensor]:
        """The per-map tensors of ``worlds``, one row per map (``world_seed`` from ``World.seed``)."""
        out = {
            name: torch.as_tensor(np.stack([getattr(wd, name) for wd in worlds]),
                                  dtype=torch.bool if name == "dyn_is_cuboid" else torch.float32,
                                  device=self.device)
            for name in ("pillar_xy", "pillar_half", "pillar_height", "dyn_origin", "dyn_width",
                         "dyn_is_cuboid", "site_along")
        }  # fmt: skip
        out["world_seed"] = torch.tensor([wd.seed for wd in worlds], dtype=torch.int64,
                                         device=self.device)  # fmt: skip
        return out

    def _apply_density(self) -> None:
        self.n_static, self.n_dynamic = self.cfg.active_static, self.cfg.active_dynamic
        maps = quantize_heights(
            torch.stack([height_map(w, self.n_static, self._walls) for w in self.worlds])
        )
        self.heights = maps.to(self.device).reshape(-1)
        if self.cfg.static_tracked and self.cfg.static_source == "map":
            # the static rows from the map, as the onboard runtime builds them from its own
            tops = dequantize_heights(maps)
            footprints = map_footprints(tops, (tops > 0) & ~self._walls, self.grid.origin,
                                        self.grid.resolution)  # fmt: skip
            self.map_pillars = tuple(t.to(self.device) for t in footprints)

    def set_density(self, density: float) -> None:
        """Set the fraction of active obstacles (density curriculum, paper Fig. 2); maps are kept."""
        self.cfg = self.cfg.replace(density=float(density))
        if self.worlds:
            self._apply_density()

    @property
    def density(self) -> float:
        return self.cfg.density

    def redraw_maps(self, seed: int) -> None:
        """Draw a new map set (map ``w`` from ``seed + w``, as ``reset(seed=seed)``) without
        cutting any episode: each env flies its current episode to its end in its old map and
        starts the next one in the new map of its slot (its episodes then drawn from ``seed + i``,
        counted from 0, as after a reset). The env holds two map sets at a time (2 x the maps'
        memory from the first call on); a second redraw before every env has moved to the
        previous one is refused (:meth:`can_redraw_maps`; at most the time limit,
        ``max_episode_steps`` steps, after a redraw). ``reset(seed=...)`` and :meth:`set_worlds`
        return to one map set."""
        if not self.worlds:
            raise RuntimeError("call reset() before redraw_maps()")
        w = self.num_worlds
        new = 1 - self._map_set
        if not self.can_redraw_maps():
            raise RuntimeError(
                "redraw_maps: some envs still fly maps from two redraws ago; wait until "
                "can_redraw_maps() (each env has ended the episode it flew at the last redraw)"
            )
        fresh = [generate_world(self.cfg, int(seed) + i) for i in range(w)]
        maps, slots = self._map_tensors(fresh), slice(new * w, new * w + w)
        if len(self.worlds) == w:  # the first redraw: room for a second map set
            self.worlds += fresh
            for name, t in maps.items():
                setattr(self, name, torch.cat([getattr(self, name), t]))
            for name in ("dyn_pos", "dyn_goal", "dyn_vel", "dyn_speed", "dyn_goal_counter"):
                setattr(self, name, torch.cat([getattr(self, name)] * 2))  # new rows reset below
        else:
            self.worlds[slots] = fresh
            for name, t in maps.items():
                getattr(self, name)[slots] = t
        self._apply_density()
        self._reset_obstacles(slots)
        self._map_set, self._map_set_seed, self._mixed = new, int(seed), True
        self._pending.fill_(True)

    def can_redraw_maps(self) -> bool:
        """Whether :meth:`redraw_maps` may run: every env has moved to the last map set drawn."""
        return not self._mixed

    def _move_to_new_maps(self, ids: torch.Tensor) -> None:
        """Envs ``ids``, about to start an episode: those a redraw left pending fly the new map
        of their slot from now on, their episodes counted from 0 with seed ``seed + i``."""
        if not self._mixed:
            return
        move = ids[self._pending[ids]]
        if move.numel():
            self.world_idx[move] = self._map_set * self.num_worlds + move % self.num_worlds
            self.env_seed[move] = self._map_set_seed + move
            self.episode_counter[move] = 0
            self._pending[move] = False
        self._mixed = bool(self._pending.any())

    def _obstacle_goal(self, counter: torch.Tensor) -> torch.Tensor:
        cfg = self.cfg
        return sample_obstacle_goals(
            self.world_seed[:, None], self._obstacle_id[None, :], counter, self.dyn_origin,
            self.dyn_is_cuboid, cfg.dyn_local_range, cfg.mover_limit,
            CUBOID_Z_RANGE, CYLINDER_HEIGHT / 2,
        )  # fmt: skip

    @property
    def _speed_period(self) -> int:
        """Steps between resampled obstacle speeds (``dyn_speed_period`` seconds)."""
        return max(1, int(round(self.cfg.dyn_speed_period * self.cfg.control_hz)))

    def _reset_obstacles(self, slots: slice | None = None) -> None:
        """The moving obstacles of the maps in ``slots`` back at their origins, on the shared
        clock of speed epochs; ``None``: every map, and the clock back to 0 (a new map set)."""
        if slots is None:
            self.world_step = 0
            shape = (len(self.worlds), self.cfg.num_dynamic)
            self.dyn_goal_counter = torch.zeros(shape, dtype=torch.int64, device=self.device)
            self.dyn_pos, self.dyn_goal, self.dyn_vel = (torch.empty_like(self.dyn_origin)
                                                         for _ in range(3))  # fmt: skip
            self.dyn_speed = torch.empty(shape, device=self.device)
            slots = slice(None)
        self.dyn_goal_counter[slots] = 0
        self.dyn_pos[slots] = self.dyn_origin[slots]
        self.dyn_goal[slots] = self._obstacle_goal(self.dyn_goal_counter)[slots]
        self.dyn_vel[slots] = 0.0
        self.dyn_speed[slots] = sample_obstacle_speeds(
            self.world_seed[slots, None], self._obstacle_id[None, :],
            torch.tensor(self.world_step // self._speed_period), *self.cfg.dyn_speed_range,
        )  # fmt: skip

    def _step_obstacles(self) -> None:
        cfg = self.cfg
        self.world_step += 1
        period = self._speed_period
        if self.world_step % period == 0:
            self.dyn_speed = sample_obstacle_speeds(
                self.world_seed[:, None], self._obstacle_id[None, :],
                torch.tensor(self.world_step // period), *cfg.dyn_speed_range,
            )  # fmt: skip
        arrived = (self.dyn_goal - self.dyn_pos).norm(dim=-1) < 0.5
        if bool(arrived.any()):
            self.dyn_goal_counter += arrived.long()
            self.dyn_goal = torch.where(arrived[..., None], self._obstacle_goal(self.dyn_goal_counter),
                                        self.dyn_goal)  # fmt: skip
        self.dyn_pos, self.dyn_vel = move_obstacles(
            self.dyn_pos, self.dyn_goal, self.dyn_speed, cfg.dt
        )

    # ------------------------------------------------------------------ episodes
    def _start_obstacles(self, ids: torch.Tensor) -> Obstacles:
        """What the starts and goals of envs ``ids`` keep clear of: every pillar of their map (at
        full density, so episodes do not depend on the curriculum) and the active moving
        obstacles where they are now."""
        w, nd = self.world_idx[ids], self.n_dynamic
        return (self.pillar_xy[w], self.pillar_half[w], self.dyn_pos[w, :nd, :2],
                self.dyn_width[w, :nd] / 2)  # fmt: skip

    def _start_episodes(self, ids: torch.Tensor, starts=None, goals=None) -> None:
        if starts is None:
            starts, goals = sample_episodes(self.cfg, self.env_seed[ids], self.episode_counter[ids],
                                            self.site_along[self.world_idx[ids]],
                                            self._start_obstacles(ids))  # fmt: skip
        starts, goals = starts.to(self.device), goals.to(self.device)
        self.start[ids], self.goal[ids], self.pos[ids] = starts, goals, starts
        self.vel[ids] = 0.0
        self.prev_vel[ids] = 0.0
        heading = goals[:, :2] - starts[:, :2]
        yaw = torch.atan2(heading[:, 1], heading[:, 0])
        self.yaw[ids], self.cos_yaw[ids], self.sin_yaw[ids] = yaw, torch.cos(yaw), torch.sin(yaw)
        self.band[ids] = torch.stack([torch.minimum(starts[:, 2], goals[:, 2]) - 0.2,
                                      torch.maximum(starts[:, 2], goals[:, 2]) + 0.2], -1)  # fmt: skip
        self.steps[ids] = 0
        self.straight[ids] = (goals - starts).norm(dim=-1)
        self._best_dist[ids] = self.straight[ids]
        self._stalled[ids] = 0
        for v in self._stats.values():
            v[ids] = 0.0
        self._min_clear[ids] = math.inf
        self._t0[ids] = time.perf_counter()
        if self.render_mode is not None and bool((ids == self.render_env_index).any()):
            self._trail = []

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Reset every env. ``seed`` draws new maps (map ``w`` from ``seed + w``, env ``i``'s episodes
        from ``seed + i``); without it the maps are kept and each env starts its next episode.

        ``options``: ``"density"`` (float), ``"starts"`` and ``"goals"`` (``(num_envs, 3)`` arrays)
        to pin the episodes, e.g. to the fixed test scenario; ``"reset_mask"`` (a boolean
        ``(num_envs,)`` array, Gymnasium 1.x's way to reset some envs of a vector env, for
        ``DISABLED`` autoreset): only those envs start their next episode (rows of ``starts`` /
        ``goals`` outside the mask are ignored), the others fly on; the maps are kept.
        """
        options = dict(options or {})  # a copy: wrappers read "reset_mask" after this call
        unknown = set(options) - {"density", "starts", "goals", "reset_mask"}
        if unknown:
            raise ValueError(
                f"unknown reset option(s) {sorted(unknown)}: use density, starts, goals, reset_mask"
            )
        mask = self._reset_mask(options.get("reset_mask"), seed)
        if "density" in options:
            self.set_density(options["density"])
        if seed is not None or not self.worlds:
            if seed is None:
                seed = int(np.random.SeedSequence().entropy % (2**31))
            self._build_worlds(int(seed))
        if mask is not None:
            ids = mask.nonzero().squeeze(-1)
            self.episode_counter[ids] += 1
        else:
            ids = torch.arange(self.num_envs, device=self.device)
            if self._fresh_worlds:
                self.episode_counter.zero_()
            else:
                self.episode_counter += 1
        starts, goals = options.get("starts"), options.get("goals")
        if (starts is None) != (goals is None):
            raise ValueError("reset options 'starts' and 'goals' must be given together")
        if starts is not None:
            starts = torch.as_tensor(np.asarray(starts), dtype=torch.float32)
            goals = torch.as_tensor(np.asarray(goals), dtype=torch.float32)
            if starts.shape != (self.num_envs, 3) or goals.shape != (self.num_envs, 3):
                raise ValueError(f"starts/goals must have shape ({self.num_envs}, 3), "
                                 f"got {tuple(starts.shape)} and {tuple(goals.shape)}")  # fmt: skip
            if mask is not None:
                starts, goals = starts[ids.cpu()], goals[ids.cpu()]
        self._fresh_worlds = False
        self._move_to_new_maps(ids)
        self._start_episodes(ids, starts, goals)
        # All envs: an env outside the mask gets the observation of its unchanged state again.
        obs, aux = self._sense()
        self._last_ranges = aux["ranges"]
        if self.cfg.lidar_history > 1:  # a fresh episode remembers copies of its first image
            fresh = self._first_history(obs["lidar"])
            if mask is not None:  # the others keep their history
                fresh = torch.where(mask[:, None, None], fresh, self._lidar_hist)
            self._lidar_hist, obs["lidar"] = fresh, fresh.clone()
        if self.cfg.lidar_memory:
            start = mask if mask is not None else torch.ones(self.num_envs, dtype=torch.bool,
                                                              device=self.device)  # fmt: skip
            obs["lidar"] = self._remember(obs["lidar"], aux["ranges"], start=start)
        if self.render_mode is not None and bool((ids == self.render_env_index).any()):
            self._trail = [self.pos[self.render_env_index].cpu().numpy().copy()]
        info: dict[str, Any] = {"episode_id": self.episode_counter.clone()}
        if mask is not None:
            info["_episode_id"] = mask.clone()
        return self._out(obs), self._out(info)

    def _first_history(self, lidar: torch.Tensor) -> torch.Tensor:
        """The range-image history of episodes that start with image ``lidar`` ``(N, E, C)``:
        ``lidar_history`` copies of it, ``(N, E * lidar_history, C)`` (no zeros: a zero beam
        means free space, which a new episode has not seen)."""
        return lidar.repeat(1, self.cfg.lidar_history, 1)

    def _remember(self, lidar: torch.Tensor, ranges: torch.Tensor, ids: torch.Tensor | None = None,
                  start: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
        """``lidar`` with the memory image's rows appended (``EnvConfig.lidar_memory``).

        Three callers: a step (all envs: the current image joins the memory, the oldest leaves),
        reset (``start``: a bool mask of the envs that begin an episode; they forget and
        remember their first image, the others see their unchanged state again), and the
        SAME_STEP autoreset (``ids``: the envs whose next episode begins, observed alone)."""
        cfg, far = self.cfg, FAR_POINT
        sel = slice(None) if ids is None else ids
        pos, yaw = self.pos[sel], self.yaw[sel]
        hits = beam_hit_points(ranges, pos, yaw, self.spec_lidar, far)
        if self._mem is None:
            self._mem = torch.full((self.num_envs, cfg.lidar_memory, hits.shape[1], 3), far,
                                   device=self.device)  # fmt: skip
        if ids is not None:
            self._mem[ids] = far
            self._mem[ids, self._mem_slot] = hits
        elif start is not None:
            self._mem[start] = far
            self._mem[start, self._mem_slot] = hits[start]
        else:
            self._mem_slot = (self._mem_slot + 1) % cfg.lidar_memory
            self._mem[:, self._mem_slot] = hits
        return torch.cat([lidar, memory_image(self._mem[sel], pos, yaw, cfg)], 1)

    def _reset_mask(self, mask, seed: int | None) -> torch.Tensor | None:
        """The ``reset_mask`` option as a bool tensor on the device (``None``: reset all)."""
        if mask is None:
            return None
        if isinstance(mask, torch.Tensor):
            mask = mask.detach().cpu().numpy()
        mask = np.asarray(mask)
        if mask.dtype != np.bool_ or mask.shape != (self.num_envs,):
            raise ValueError(f"reset_mask must be a bool array of shape ({self.num_envs},), got "
                             f"{mask.dtype} {mask.shape}")  # fmt: skip
        if not mask.any():
            raise ValueError("reset_mask must select at least one env")
        if seed is not None:
            # A seed draws new maps, which every env flies in: not a per-env reset.
            raise ValueError("reset with a seed resets every env: pass no reset_mask with it")
        if not self.worlds:
            raise ValueError("reset_mask needs a first reset() of all envs")
        return torch.as_tensor(mask, device=self.device)

    # ------------------------------------------------------------------ sensing
    def _sense(
        self, ids: torch.Tensor | None = None
    ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Observation and reward inputs of all envs (``ids=None``) or of the envs ``ids``.

        For all envs, env ``i = r * W + w`` flies in map ``w``: viewing the batch as ``(R, W)``
        lets obstacle tensors ``(W, P)`` broadcast without gathering a copy per env.
        """
        cfg = self.cfg
        if ids is None and self._mixed:  # envs in two map sets (redraw_maps): gather per env
            ids = torch.arange(self.num_envs, device=self.device)
        if ids is None:
            r, w = self.num_envs // self.num_worlds, self.num_worlds
            first = self._map_set * w  # every env flies a map of the current set
            sel = lambda t: t.view(r, w, *t.shape[1:])  # noqa: E731
            per_map = lambda t, n: t[first : first + w, :n].unsqueeze(0)  # noqa: E731
        else:
            sel = lambda t: t[ids]  # noqa: E731
            world_ids = self.world_idx[ids]
            per_map = lambda t, n: t[world_ids, :n]  # noqa: E731
        pos, vel, goal = sel(self.pos), sel(self.vel), sel(self.goal)
        cos_y, sin_y = sel(self.cos_yaw), sel(self.sin_yaw)
        flat = lambda t: t.reshape(-1, *t.shape[pos.dim() - 1 :])  # noqa: E731  (R, W, ...) -> (N, ...)
        rng_ = cfg.lidar_range

        # Static obstacles: the range image, and the exact clearance to the nearest pillar.
        ps = self.n_static
        p_xy, p_half, p_h = (
            per_map(self.pillar_xy, ps),
            per_map(self.pillar_half, ps),
            per_map(self.pillar_height, ps),
        )
        pos_f = flat(pos)
        yaw_f = self.yaw if ids is None else self.yaw[ids]
        world_f = self.world_idx if ids is None else self.world_idx[ids]
        if self.raycaster == "grid":
            ranges = raycast_height_map(self.heights, self.grid.origin, self.grid.size, pos_f, yaw_f,
                                        self.spec_lidar, world_f)  # fmt: skip
        else:
            lo, hi = pillar_boxes(p_xy, p_half, p_h)
            walls_lo, walls_hi = self._wall_boxes()
            lo = torch.cat([lo, walls_lo.expand(*lo.shape[:-2], -1, -1)], -2)
            hi = torch.cat([hi, walls_hi.expand(*hi.shape[:-2], -1, -1)], -2)
            ranges = raycast_boxes_bruteforce(flat(lo.expand(*pos.shape[:-1], -1, -1)),
                                              flat(hi.expand(*pos.shape[:-1], -1, -1)),
                                              pos_f, yaw_f, self.spec_lidar)  # fmt: skip
        static_clear = flat(pillar_clearance(pos, p_xy, p_half, p_h))

        # Moving obstacles: exact clearance to all, features of the nearest few within range.
        nd, k = self.n_dynamic, cfg.num_tracked
        n = pos_f.shape[0]
        dynamic = torch.zeros(n, k, 10, device=self.device)
        tracked_clear = torch.full((n, k), rng_, device=self.device)
        dyn_clear = torch.full((n,), math.inf, device=self.device)
        if nd > 0:
            rel = per_map(self.dyn_pos, nd) - pos[..., None, :]  # (..., D, 3)
            width, cuboid = per_map(self.dyn_width, nd), per_map(self.dyn_is_cuboid, nd)
            clear_all = moving_obstacle_clearance(
                rel, width, cuboid, pos[..., 2], CUBOID_HEIGHT, CYLINDER_HEIGHT
            )
            dyn_clear = flat(clear_all.amin(-1))
            feats, idx, in_range = dynamic_obstacle_features(
                rel, per_map(self.dyn_vel, nd), width, cuboid, cos_y, sin_y, k, rng_, cfg.v_max)  # fmt: skip
            dynamic = flat(feats)
            kk = idx.shape[-1]
            tracked_clear[:, :kk] = flat(
                torch.where(in_range, torch.gather(clear_all, -1, idx), rng_)
            )

        # Beyond the paper (static_tracked): the nearest pillars' geometry.
        static = None
        if cfg.static_tracked:
            if cfg.static_source == "map":
                p_xy, p_half, p_h = (per_map(t, t.shape[1]) for t in self.map_pillars)
            static = flat(static_obstacle_features(pos, p_xy, p_half, p_h, cos_y, sin_y,
                                                   cfg.static_tracked, rng_))  # fmt: skip

        to_goal = flat(goal - pos)
        vel, cos_y, sin_y = flat(vel), flat(cos_y), flat(sin_y)
        dist = to_goal.norm(dim=-1)
        unit_goal = to_goal / dist[:, None].clamp(min=1e-6)
        state = torch.cat([
            world_to_goal_frame(unit_goal, cos_y, sin_y),
            (to_goal[:, :2].norm(dim=-1) / DIST_SCALE)[:, None],
            (to_goal[:, 2] / Z_SCALE)[:, None],
            world_to_goal_frame(vel, cos_y, sin_y) / cfg.v_max,
        ], -1)  # fmt: skip
        obs = {"state": state, "lidar": (rng_ - ranges) / rng_, "dynamic": dynamic}
        if static is not None:
            obs["static"] = static
        aux = {"ranges": ranges, "static_clear": static_clear, "dyn_clear": dyn_clear,
               "tracked_clear": tracked_clear, "dist": dist, "unit_goal": unit_goal}  # fmt: skip
        return obs, aux

    def _beam_reads_pillar(self, ids: torch.Tensor) -> torch.Tensor:
        """NavRL's static collision for envs ``ids``: a beam of the range image, cast exactly
        against the pillars of their maps (not the grid, whose tilted beams read only multiples
        of 0.1 m / cos e), reads less than the collision radius. Such a beam implies contact of
        the sphere, so only envs in contact need it (few per step)."""
        w, ps = self.world_idx[ids], self.n_static
        lo, hi = pillar_boxes(self.pillar_xy[w, :ps], self.pillar_half[w, :ps],
                              self.pillar_height[w, :ps])  # fmt: skip
        ranges = raycast_boxes_bruteforce(lo, hi, self.pos[ids], self.yaw[ids], self.spec_lidar)
        return ranges.flatten(1).amin(-1) < self.cfg.uav_radius

    def _wall_boxes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The border wall as four boxes (lower and upper corners, ``(4, 3)`` each) for the
        brute-force reference ray caster: slabs a beam's length thick outside each side."""
        h, t = self.cfg.half, self.cfg.lidar_range + 1.0
        lo = [(-h - t, h, 0.0), (h, -h - t, 0.0), (-h - t, -h - t, 0.0), (-h - t, -h - t, 0.0)]
        hi = [(h + t, h + t, WALL_HEIGHT), (h + t, h + t, WALL_HEIGHT), (h + t, -h, WALL_HEIGHT),
              (-h, h + t, WALL_HEIGHT)]  # fmt: skip
        as_t = lambda v: torch.tensor(v, dtype=torch.float32, device=self.device)  # noqa: E731
        return as_t(lo), as_t(hi)

    # ------------------------------------------------------------------ stepping
    def _check_actions(self, actions) -> torch.Tensor:
        a = torch.as_tensor(actions, dtype=torch.float32, device=self.device)
        if a.shape != (self.num_envs, 3):
            raise ValueError(f"actions must have shape ({self.num_envs}, 3), got {tuple(a.shape)}")
        if not bool(torch.isfinite(a).all()):
            raise ValueError("actions contain NaN or Inf")
        return a.clamp(-1.0, 1.0)

    def step(self, actions):
        cfg = self.cfg
        if not self.worlds:
            raise RuntimeError("call reset() before step()")
        a = self._check_actions(actions)
        cmd = goal_frame_to_world(a * cfg.v_max, self.cos_yaw, self.sin_yaw)
        self.prev_vel = self.vel
        old = self.pos
        self.pos, self.vel = velocity_tracker(old, self.vel, cmd, cfg.dt, cfg.physics_substeps,
                                              cfg.velocity_time_constant, cfg.max_acceleration)  # fmt: skip
        self._step_obstacles()
        obs, aux = self._sense()
        if cfg.lidar_history > 1:  # shift the history by one image, newest first
            older = self._lidar_hist[:, : -len(cfg.lidar_v_angles)]
            self._lidar_hist = torch.cat([obs["lidar"], older], 1)
            obs["lidar"] = self._lidar_hist.clone()
        if cfg.lidar_memory:
            obs["lidar"] = self._remember(obs["lidar"], aux["ranges"])

        z = self.pos[:, 2]
        border_clear = border_clearance(self.pos, cfg.half)
        clearance = torch.minimum(
            torch.minimum(aux["static_clear"], aux["dyn_clear"]), border_clear
        )
        hit_static = aux["static_clear"] <= cfg.uav_radius
        if cfg.collision_rule == "navrl" and bool(hit_static.any()):  # NavRL's rule (EnvConfig)
            ids = hit_static.nonzero().squeeze(-1)
            hit_static[ids] = self._beam_reads_pillar(ids)
        hit_dynamic = aux["dyn_clear"] <= cfg.uav_radius
        # The arena is closed: touching the border wall is a collision like leaving the altitude band.
        hit_border = border_clear <= cfg.uav_radius
        out_of_bounds = (z < cfg.z_min) | (z > cfg.z_max) | hit_border
        collision = hit_static | hit_dynamic | out_of_bounds
        success = (aux["dist"] < cfg.goal_tolerance) & ~collision
        # Reward (NavRL's terms; see class docstring).
        r_vel = (self.vel * aux["unit_goal"]).sum(-1)
        r_static = torch.log((aux["ranges"] / cfg.lidar_range).clamp(1e-3, 1.0)).mean((1, 2))
        r_dyn = torch.log((aux["tracked_clear"] / cfg.lidar_range).clamp(1e-3, 1.0)).mean(-1)
        p_smooth = (self.vel - self.prev_vel).norm(dim=-1)
        band_lo, band_hi = self.band[:, 0], self.band[:, 1]
        if cfg.cruise_height > 0:  # a named departure from NavRL (EnvConfig.cruise_height)
            beyond = (self.goal[:, :2] - self.pos[:, :2]).norm(dim=-1) - cfg.cruise_until
            # share of the cruise band: 1 far out, 0 near the goal; a ramp, or a step without one
            # (a step is a penalty cliff at cruise_until for a UAV that cruises low: cruise06)
            far = (
                (beyond / cfg.cruise_ramp).clamp(0, 1)
                if cfg.cruise_ramp > 0
                else (beyond > 0).float()
            )
            band_lo = band_lo + far * (cfg.cruise_height - CRUISE_HALF_BAND - band_lo)
            band_hi = band_hi + far * (cfg.cruise_height + CRUISE_HALF_BAND - band_hi)
        above = (z - band_hi).clamp(min=0)
        below = (band_lo - z).clamp(min=0)
        p_height = above * above + below * below
        reward = (cfg.w_velocity * r_vel + cfg.w_static * r_static + cfg.w_dynamic * r_dyn
                  - cfg.w_smooth * p_smooth - cfg.w_height * p_height + cfg.reward_goal * success.float()
                  + cfg.reward_collision * collision.float())  # fmt: skip
        if cfg.w_stall > 0:  # a named departure from NavRL (EnvConfig.w_stall)
            progress = aux["dist"] < self._best_dist - cfg.stall_progress
            self._best_dist = torch.where(progress, aux["dist"], self._best_dist)
            self._stalled = torch.where(progress, 0, self._stalled + 1)
            limit = round(cfg.stall_seconds * cfg.control_hz)
            reward = reward - cfg.w_stall * (self._stalled >= limit).float()
        if cfg.near_miss_margin > 0:  # a named departure from Eq. 3 (EnvConfig.near_miss_margin)
            near = collision | (clearance - cfg.uav_radius < cfg.near_miss_margin)
            # the episode's cost so far is 1 once its near miss is paid, else 0
            cost = (near & (self._stats["cost"] == 0)).float()
        else:
            cost = collision.float()

        self.steps += 1
        terminated = success | (collision & cfg.terminate_on_collision)
        truncated = (self.steps >= cfg.max_episode_steps) & ~terminated
        done = terminated | truncated
        st = self._stats
        st["return"] += reward
        st["cost"] += cost
        st["path_length"] += (self.pos - old).norm(dim=-1)
        st["speed_sum"] += self.vel.norm(dim=-1)
        st["border_steps"] += (border_clear <= BORDER_BAND).float()
        st["outside_steps"] += (border_clear < 0).float()
        self._min_clear = torch.minimum(self._min_clear, clearance - cfg.uav_radius)
        self._last_ranges = aux["ranges"]
        if self.render_mode is not None:
            self._trail.append(self.pos[self.render_env_index].cpu().numpy().copy())

        info: dict[str, Any] = {"cost": cost, "success": success, "collision": collision,
                                "clearance": clearance - cfg.uav_radius}  # fmt: skip
        if bool(done.any()):
            steps_f = self.steps.float()
            info["episode"] = {
                "return": st["return"].clone(), "cost": st["cost"].clone(), "length": self.steps.clone(),
                "success": success.clone(), "collision": collision.clone(), "timeout": truncated.clone(),
                "time": steps_f * cfg.dt, "path_length": st["path_length"].clone(),
                "min_clearance": self._min_clear.clone(), "mean_speed": st["speed_sum"] / steps_f,
                # How it flew: path length over the straight start-goal line, and the shares of
                # its time within BORDER_BAND of the border and outside the map (0: closed arena).
                "detour_ratio": st["path_length"] / self.straight.clamp(min=1e-6),
                "border_time": st["border_steps"] / steps_f, "outside_time": st["outside_steps"] / steps_f,
                # What the collision was with (an episode ends at its first one; both obstacle
                # kinds can be touched in the same step).
                "hit_static": hit_static.clone(), "hit_dynamic": hit_dynamic.clone(),
                "out_of_bounds": out_of_bounds.clone(), "hit_border": hit_border.clone(),
                # Gymnasium's RecordEpisodeStatistics keys: return, length, wall-clock seconds
                # (rounded to 1 us as it does), 0 where the episode goes on.
                "r": torch.where(done, st["return"], 0.0),
                "l": torch.where(done, self.steps, 0),
                "t": torch.where(done, (time.perf_counter() - self._t0).round(decimals=6), 0.0),
            }  # fmt: skip
            info["_episode"] = done.clone()
            if self.autoreset_mode == AutoresetMode.SAME_STEP:
                info["final_obs"] = {k: v.clone() for k, v in obs.items()}
                info["_final_obs"] = done.clone()
                ids = done.nonzero().squeeze(-1)
                self.episode_counter[ids] += 1
                self._move_to_new_maps(ids)
                self._start_episodes(ids)
                new_obs, new_aux = self._sense(ids)
                if cfg.lidar_history > 1:
                    new_obs["lidar"] = self._first_history(new_obs["lidar"])
                    self._lidar_hist[ids] = new_obs["lidar"]
                if cfg.lidar_memory:
                    new_obs["lidar"] = self._remember(new_obs["lidar"], new_aux["ranges"], ids=ids)
                for key in obs:
                    obs[key][ids] = new_obs[key]
                self._last_ranges[ids] = new_aux["ranges"]
        info = self._out(info)
        if "_final_obs" in info:
            # Gymnasium 1.x SAME_STEP: the finished envs' info of their last step, each key with
            # its "_key" mask: the same arrays as the top-level keys (which keep them), added
            # after the conversion so that NumPy output converts them once.
            mask = info["_final_obs"]
            final = {}
            for key in ("cost", "success", "collision", "clearance", "episode"):
                final[key], final[f"_{key}"] = info[key], mask
            info["final_info"], info["_final_info"] = final, mask
        return self._out(obs), self._out(reward), self._out(terminated), self._out(truncated), info

    def _out(self, x):
        """Tensors as the env's ``output`` type (NumPy views of CPU tensors cost no copy)."""
        if self.output == "torch":
            return x
        if isinstance(x, dict):
            return {k: self._out(v) for k, v in x.items()}
        if isinstance(x, torch.Tensor):
            return x.detach().cpu().numpy()
        return x

    # ------------------------------------------------------------------ rendering
    def render(self):
        """Top-down RGB image of env ``render_env_index``: pillars, moving obstacles, trail, goal."""
        if self.render_mode is None:
            return None
        from safenav.envs.render import render_topdown

        return render_topdown(self, self.render_env_index, trail=self._trail)

    def close_extras(self, **kwargs) -> None:
        self.worlds = []


class SafeNavEnv(Env):
    """Single-env view of :class:`SafeNavVectorEnv` (see it for the full description).

    >>> import gymnasium as gym, safenav
    >>> env = gym.make("SafeNav-v1", preset="easy")
    >>> obs, info = env.reset(seed=1)
    >>> {k: v.shape for k, v in obs.items()}
    {'state': (8,), 'lidar': (4, 36), 'dynamic': (5, 10)}
    >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    >>> float(info["cost"]) in (0.0, 1.0)
    True
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, preset: str = "paper", config: EnvConfig | None = None, device: str = "cpu",
                 render_mode: str | None = None, raycaster: str = "grid", **overrides: Any) -> None:  # fmt: skip
        self.vec = SafeNavVectorEnv(1, preset=preset, config=config, device=device, output="torch",
                                    autoreset_mode=AutoresetMode.DISABLED, render_mode=render_mode,
                                    raycaster=raycaster, **overrides)  # fmt: skip
        self.cfg = self.vec.cfg
        self.render_mode = render_mode
        self.observation_space = self.vec.single_observation_space
        self.action_space = self.vec.single_action_space

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if options and ("starts" in options or "goals" in options):
            options = dict(options)
            for key in ("starts", "goals"):
                if key in options:
                    options[key] = np.asarray(options[key], dtype=np.float32).reshape(1, 3)
        obs, info = self.vec.reset(seed=seed, options=options)
        return self._obs(obs), {"episode_id": int(info["episode_id"][0])}

    def step(self, action):
        a = np.asarray(action, dtype=np.float32)
        if a.shape != (3,):
            raise ValueError(f"action must have shape (3,), got {a.shape}")
        obs, reward, terminated, truncated, info = self.vec.step(a[None])
        out: dict[str, Any] = {k: (v[0].item() if v.dtype == torch.bool else float(v[0]))
                               for k, v in info.items() if isinstance(v, torch.Tensor)}  # fmt: skip
        if "episode" in info:
            out["episode"] = {k: v[0].item() for k, v in info["episode"].items()}
        return self._obs(obs), float(reward[0]), bool(terminated[0]), bool(truncated[0]), out

    @staticmethod
    def _obs(obs: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
        return {k: v[0].cpu().numpy() for k, v in obs.items()}

    def set_density(self, density: float) -> None:
        self.vec.set_density(density)

    def render(self):
        return self.vec.render()


__all__ = ["SafeNavEnv", "SafeNavVectorEnv", "sample_episodes", "fixed_scenario"]
