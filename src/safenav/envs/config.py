"""Typed configuration of ``SafeNav-v1`` and its named presets.

Values marked (paper) come from the seed paper, (NavRL) from NavRL's open-source environment.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

CRUISE_HALF_BAND = 0.3
"""Half width (m) of the height penalty's band around ``EnvConfig.cruise_height``."""
COLLISION_RULES = ("body", "navrl")
"""Values of ``EnvConfig.collision_rule``."""
STATIC_FEATURES = 7
"""Columns of a ``static`` observation row (``EnvConfig.static_tracked``; beyond the paper): the
nearest point of the pillar's footprint relative to the UAV (goal frame x, y) / range (2), its
centre likewise (2), half side / 0.4 m (1), top minus the UAV's altitude / range (1), 1 (1)."""


@dataclass(frozen=True)
class EnvConfig:
    """SafeNav-v1 configuration. The defaults are the paper scenario (``preset="paper"``)."""

    map_size: float = 50.0
    """Side of the square flight area in metres; x, y in [-map_size/2, map_size/2] (paper)."""
    num_static: int = 350
    """Number of static pillars at full density (paper)."""
    num_dynamic: int = 100
    """Number of moving obstacles at full density, 8 equal classes (paper, NavRL)."""
    density: float = 1.0
    """Fraction of the obstacles that are active; the trainer's density curriculum raises it."""
    pillar_sides: tuple[float, ...] = (0.4, 0.8)
    """Footprint sides of the square pillars in metres (NavRL)."""
    edge_margin: float = 2.0
    """Starts and goals lie ``edge_margin / 2`` from the border. (SafeNav-v0 kept this band free of
    obstacles, a ring that joined every start to every goal; v1 fills it like the interior.)"""
    start_sites: int = 6
    """Start/goal sites per side of the arena, drawn with the map; episodes start and end at them
    (at random altitudes), each the centre of an obstacle-free disc (v1)."""
    start_clearance: float = 2.0
    """Radius of the obstacle-free disc around each site in metres: no pillar footprint or moving
    obstacle origin lies closer; an episode starts at a site no moving obstacle is inside (v1)."""

    z_min: float = 0.2
    """Lowest allowed altitude; below it is a ground collision (NavRL)."""
    z_max: float = 4.0
    """Highest allowed altitude; above it is a ceiling collision (NavRL)."""
    uav_radius: float = 0.3
    """Radius of the UAV's collision sphere in metres (NavRL)."""
    collision_rule: str = "body"
    """How a static collision is detected. ``"body"`` (the default, the spec's): the collision
    sphere touches a pillar's geometry, its side or its top. ``"navrl"``: NavRL's rule
    (``training/scripts/env.py``: ``max(lidar_scan) > lidar_range - 0.3``), a collision only when
    a beam of the range image reads less than the radius; a UAV that grazes a pillar's top that no
    beam hits flies on. The beams are cast exactly against the pillars for the test (as NavRL's
    ray caster does against its obstacle mesh), not read off the grid-based range image, whose
    tilted beams read only multiples of 0.1 m / cos(elevation). For figures comparable with
    NavRL-based papers (docs/csac-v1.md, "The paper's collision rule"); not for training a policy
    to fly. Moving obstacles, the wall and the altitude band collide as under ``"body"``."""
    v_max: float = 2.0
    """Largest commanded speed per goal-frame axis in m/s (paper)."""
    control_hz: float = 10.0
    """Policy rate in Hz."""
    physics_substeps: int = 4
    """Physics integration steps per control step."""
    velocity_time_constant: float = 0.4
    """Time constant of the first-order velocity tracker in seconds (PX4 offboard-like)."""
    max_acceleration: float = 3.0
    """Acceleration limit of the velocity tracker in m/s^2 (PX4 MPC_ACC_HOR default)."""

    lidar_range: float = 4.0
    """Range of the range-image beams in metres (NavRL)."""
    lidar_h_beams: int = 36
    """Horizontal beams, evenly spaced over 360 degrees (NavRL)."""
    lidar_v_angles: tuple[float, ...] = (-10.0, 0.0, 10.0, 20.0)
    """Elevations of the vertical beams in degrees (NavRL)."""
    grid_resolution: float = 0.1
    """Cell side of the occupancy grid map in metres."""
    lidar_history: int = 1
    """Range images in the observation: the current one and those of the previous
    ``lidar_history - 1`` control steps, stacked as extra rows, newest first (rows
    ``[i * E, (i + 1) * E)`` are the image of ``i`` steps ago, ``E`` = elevations); an episode
    starts with copies of its first image. 1 = the paper's memoryless observation (the default).
    Beyond the paper: a short memory of obstacles that left the field of view or fell between
    beams. Extra rows, not a new axis, keep the observation's rank: the range-image encoder reads
    the rows as the input channels of its circular convolution over azimuth, so the images of
    successive steps become channels (frame stacking) and every code path that handles the
    ``(rows, beams)`` image (replay buffer, networks, checkpoints) works unchanged; readers of the
    current image (the shield) take its first ``E`` rows. Not deployable yet (``safenav export`` /
    ``fly`` refuse it: the onboard runtime builds memoryless observations)."""

    lidar_memory: int = 0
    """Control steps of range images remembered in a **memory image** appended to the
    observation's ``lidar`` rows (0 = none, the paper's observation; the default). Beyond the
    paper: the beams' hit points of the last ``lidar_memory`` steps (the current one included),
    kept in the world where they were seen, are re-projected each step into ``E`` more rows of
    the same layout (columns every ``360 / beams`` degrees from the goal direction; rows by
    elevation, the lowest also holding every point below it): per cell the nearest remembered
    point, ``(range - d) / range``. It shows a pillar that fell under the lowest beam or between
    two beams as the UAV closed in, which a memoryless range image loses (docs/csac-v1.md, "The
    sensor, not only the learning"). Deployable: the onboard runtime keeps the hits by odometry
    and builds the same rows (``safenav export`` / ``fly``; ``RuntimeConfig.policy_memory``)."""
    num_tracked: int = 5
    """Number of nearest moving obstacles in the observation (NavRL)."""
    static_tracked: int = 0
    """Pillars in a ``static`` observation entry (0 = none, the paper's observation; the default).
    Beyond the paper: the ``static_tracked`` pillars nearest the UAV (by clearance) within
    ``lidar_range``, one row of ``STATIC_FEATURES`` each in the goal frame, as the ``dynamic``
    rows (:func:`safenav.envs.sensors.static_obstacle_features`): the pillars' geometry where the
    range image shows a few hit points. A planner with this view passes every pillar on the
    validation episodes (docs/csac-v1.md, "What the range image costs"). ``static_source``
    says where the list comes from."""
    static_source: str = "exact"
    """Where the ``static`` rows come from (with ``static_tracked`` > 0): ``exact``, the pillars'
    footprints as drawn; ``map``, the footprints the height map shows
    (:func:`safenav.envs.sensors.map_footprints`: each group of occupied cells, its box within half
    a cell of the pillar's, touching pillars one footprint), the list the onboard runtime builds
    from its own map, so that what trains is what flies (``safenav export`` / ``fly``)."""
    dyn_speed_range: tuple[float, float] = (0.5, 1.5)
    """Speed range of moving obstacles in m/s, resampled every ``dyn_speed_period`` (NavRL)."""
    dyn_speed_period: float = 2.0
    """Seconds between speed resamples of the moving obstacles (NavRL)."""
    dyn_local_range: float = 5.0
    """Moving obstacles pick local goals within +-this many metres of their origin (NavRL)."""

    goal_tolerance: float = 0.5
    """Success when the UAV is within this distance of the goal (NavRL)."""
    start_height_range: tuple[float, float] = (0.5, 2.5)
    """Altitude range of starts and goals in metres (NavRL)."""
    min_goal_distance: float = 20.0
    """Least horizontal start-goal distance; shorter draws move the goal to the opposite side."""
    max_episode_seconds: float = 60.0
    """Time limit in simulated seconds; reaching it truncates the episode."""
    terminate_on_collision: bool = True
    """End the episode at a collision (paper); if False, it continues and cost keeps counting."""

    reward_goal: float = 20.0
    """Reward for reaching the goal (replaces NavRL's +1 per step, which pays loitering)."""
    w_velocity: float = 1.0
    """Weight of the velocity-toward-goal reward (NavRL)."""
    w_static: float = 1.0
    """Weight of the static safety reward, mean log beam distance (NavRL)."""
    w_dynamic: float = 1.0
    """Weight of the dynamic safety reward, mean log clearance to tracked obstacles (NavRL)."""
    w_smooth: float = 0.1
    """Weight of the penalty on the change of velocity between steps (NavRL)."""
    w_height: float = 8.0
    """Weight of the penalty on leaving the start-goal altitude band (NavRL)."""
    cruise_height: float = 0.0
    """0 = NavRL's height penalty band, the start-goal band, throughout (the default). > 0, a
    departure from NavRL's reward: while the goal is farther than ``cruise_until`` metres
    horizontally, the band is ``cruise_height`` +- ``CRUISE_HALF_BAND`` (0.3 m) instead, so that the
    UAV cruises low, where the level beams see the side of every pillar (each is >= 1 m tall) and
    none is lost below the lowest beam (docs/csac-v1.md, "Altitude, not memory")."""
    cruise_until: float = 5.0
    """Horizontal distance to the goal (m) below which the start-goal band applies again when
    ``cruise_height`` > 0."""
    cruise_ramp: float = 0.0
    """With ``cruise_height`` > 0: over this many metres beyond ``cruise_until`` the band's bounds
    move linearly from the cruise band to the start-goal band (climbing 1.9 m over a 5 m ramp at
    2 m/s takes 0.8 m/s). 0 = a step at ``cruise_until``: a penalty cliff there for a UAV cruising
    low under a high goal (up to 8 x 1.7^2 per step), measured as ``cruise06``."""
    reward_collision: float = 0.0
    """Reward at a collision step (<= 0). 0 = none (the paper: collisions are the cost's, never the
    reward's). NavRL's +1 per step survival bonus, dropped here, made a crash cost the rest of
    that stream, about 1 / (1 - gamma) = 100 at gamma 0.99; -100 restores that loss in terminal
    form without paying loitering."""

    w_stall: float = 0.0
    """Reward penalty per step while the UAV has made no progress for ``stall_seconds`` (a
    departure from NavRL's reward; 0 = off, the default). Progress is the distance to the goal
    falling ``stall_progress`` metres below its least value so far in the episode; the penalty
    stops at the next such step. Against pockets among pillars where a policy behind the shield
    hovers until the time limit (docs/csac-v1.md, "A penalty on time without progress"). At most
    about ``w_stall / (1 - gamma)`` discounted (50 at 0.5 and gamma 0.99), kept below the crash
    loss so that a crash never pays for ending it."""
    stall_seconds: float = 3.0
    """With ``w_stall`` > 0: seconds without progress before the penalty starts."""
    stall_progress: float = 0.5
    """With ``w_stall`` > 0: metres by which the distance to the goal must fall below its least
    value so far to count as progress."""
    near_miss_margin: float = 0.0
    """Metres of clearance under which the cost counts a near miss (a departure from the paper's
    Eq. 3 cost, whose event is contact; 0 = off, the default). With a margin > 0 the cost of a
    step is 1 at the episode's first step whose clearance from the pillars, the moving obstacles
    and the wall falls under the margin, or that collides, and 0 at every other step: an episode
    costs 1 if the UAV ever came that near (a body inflated by the margin), so a budget d is a
    probability of a near miss per episode and the constraint curriculum's d_init / d_min keep
    their units. ``info["collision"]`` and the episode statistics still count contact. Measured
    behind the shield (0.1 m, d_min 0.25, four seeds at 1 M): less success and more contact
    than Eq. 3's cost, so no recipe uses it (docs/csac-v1.md, "A cost that counts near misses")."""

    num_worlds: int = 0
    """Independent maps in a vector env (env i flies in map i % num_worlds); 0 = min(num_envs, 16)."""

    # -- derived values -------------------------------------------------------------------
    @property
    def half(self) -> float:
        return self.map_size / 2.0

    @property
    def mover_limit(self) -> float:
        """Largest |x| or |y| of a moving obstacle's centre (its surface stays inside the map)."""
        return self.half - 0.5

    @property
    def dt(self) -> float:
        """Control period in seconds."""
        return 1.0 / self.control_hz

    @property
    def max_episode_steps(self) -> int:
        return int(round(self.max_episode_seconds * self.control_hz))

    @property
    def active_static(self) -> int:
        return int(round(self.num_static * self.density))

    @property
    def active_dynamic(self) -> int:
        return int(round(self.num_dynamic * self.density))

    def replace(self, **changes) -> EnvConfig:
        """A copy with ``changes`` applied and validated."""
        return dataclasses.replace(self, **changes)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""

        def bad(name: str, why: str) -> None:
            raise ValueError(f"EnvConfig.{name}={getattr(self, name)!r} is invalid: {why}")

        def finite(name: str) -> None:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                bad(name, "must be a number")
            if not math.isfinite(value):
                bad(name, "must be finite")

        for name in (
            "map_size", "density", "edge_margin", "start_clearance", "z_min", "z_max", "uav_radius", "v_max",
            "control_hz", "velocity_time_constant", "max_acceleration", "lidar_range",
            "grid_resolution", "dyn_speed_period", "dyn_local_range", "goal_tolerance",
            "min_goal_distance", "max_episode_seconds", "reward_goal", "w_velocity", "w_static",
            "w_dynamic", "w_smooth", "w_height", "reward_collision", "cruise_height", "cruise_until",
            "cruise_ramp", "w_stall", "stall_seconds", "stall_progress", "near_miss_margin",
        ):  # fmt: skip
            finite(name)
        for name in ("num_static", "num_dynamic", "physics_substeps", "lidar_h_beams",
                     "num_tracked", "num_worlds", "start_sites", "lidar_history",
                     "lidar_memory", "static_tracked"):  # fmt: skip
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                bad(name, "must be an integer")
            if value < 0:
                bad(name, "must be >= 0")
        for name in ("map_size", "v_max", "control_hz", "velocity_time_constant",
                     "max_acceleration", "lidar_range", "grid_resolution", "uav_radius",
                     "dyn_speed_period", "goal_tolerance", "max_episode_seconds"):  # fmt: skip
            if getattr(self, name) <= 0:
                bad(name, "must be > 0")
        for name in ("physics_substeps", "lidar_h_beams", "num_tracked", "start_sites",
                     "lidar_history"):  # fmt: skip
            if getattr(self, name) < 1:
                bad(name, "must be >= 1")
        if self.lidar_history > 8:
            bad("lidar_history", "must be at most 8 (range images in the observation)")
        if not 0 <= self.lidar_memory <= 100:
            bad("lidar_memory", "must lie in [0, 100] control steps (0 = no memory image)")
        if self.static_tracked > 32:
            bad("static_tracked", "must lie in [0, 32] pillars (0 = no static entry)")
        if self.static_source not in ("exact", "map"):
            bad(
                "static_source",
                "must be 'exact' (the drawn footprints) or 'map' (the height map's)",
            )
        for name in ("w_smooth", "w_height", "w_stall"):
            if getattr(self, name) < 0:
                bad(name, "must be >= 0 (a penalty's weight; a negative one pays for it)")
        if self.stall_seconds <= 0:
            bad("stall_seconds", "must be > 0")
        if self.stall_progress < 0:
            bad("stall_progress", "must be >= 0 m")
        if not 0.0 <= self.near_miss_margin <= 2.0:
            bad("near_miss_margin", "must lie in [0, 2] m (0 = the paper's cost: contact)")
        if self.reward_collision > 0:
            bad("reward_collision", "must be <= 0 (a penalty; a positive value pays crashes)")
        if not 0.0 <= self.density <= 1.0:
            bad("density", "must lie in [0, 1]")
        if not 0.0 <= self.z_min < self.z_max:
            bad("z_max", "must exceed z_min >= 0")
        if self.edge_margin < 1.0 or 2 * self.edge_margin >= self.map_size - 2.0:
            bad("edge_margin", "must be >= 1 m and leave at least 2 m of interior")
        if not 0.0 <= self.start_clearance <= self.map_size / 4:
            bad("start_clearance", "must lie in [0, map_size / 4]")
        if self.edge_margin / 2 <= self.uav_radius:
            bad(
                "edge_margin", "must put starts (edge_margin / 2 from the border) clear of the wall"
            )
        if not self.pillar_sides or any(
            (not math.isfinite(s)) or s <= 0 for s in self.pillar_sides
        ):
            bad("pillar_sides", "must be a non-empty tuple of positive sizes")
        if self.collision_rule not in COLLISION_RULES:
            bad("collision_rule", f"must be one of {', '.join(COLLISION_RULES)}")
        if not self.lidar_v_angles or any(abs(a) >= 80 for a in self.lidar_v_angles):
            bad("lidar_v_angles", "must be a non-empty tuple of elevations within +-80 degrees")
        lo, hi = self.dyn_speed_range
        if not (0 <= lo <= hi) or not math.isfinite(hi):
            bad("dyn_speed_range", "must be (low, high) with 0 <= low <= high")
        lo, hi = self.start_height_range
        if not (self.z_min < lo <= hi < self.z_max):
            bad("start_height_range", "must lie strictly inside (z_min, z_max)")
        if self.cruise_height and not (
            self.z_min < self.cruise_height - CRUISE_HALF_BAND
            and self.cruise_height + CRUISE_HALF_BAND < self.z_max
        ):
            bad(
                "cruise_height",
                f"must be 0 (off) or keep +-{CRUISE_HALF_BAND} m inside (z_min, z_max)",
            )
        if self.cruise_until < 0:
            bad("cruise_until", "must be >= 0")
        if self.cruise_ramp < 0:
            bad("cruise_ramp", "must be >= 0")
        if self.grid_resolution > self.lidar_range / 4:
            bad("grid_resolution", "must be at most lidar_range / 4")
        # Pillars may cover at most 30 % of the map (less the sites' clear discs) so that placement
        # (and flight) is possible.
        mean_area = sum(s * s for s in self.pillar_sides) / len(self.pillar_sides)
        free = self.map_size**2 - 4 * self.start_sites * math.pi * self.start_clearance**2
        if self.num_static * mean_area > 0.3 * free:
            bad(
                "num_static",
                f"{self.num_static} pillars do not fit in the {self.map_size:.1f} m map "
                "(at most 30 % cover)",
            )
        if self.min_goal_distance > self.map_size:
            bad("min_goal_distance", "must not exceed map_size")


PRESETS: dict[str, dict] = {
    # Small and sparse: learning tests, the closed-loop flight test, quick demos.
    "easy": dict(map_size=20.0, num_static=12, num_dynamic=6, min_goal_distance=10.0,
                 max_episode_seconds=30.0),
    # Between: a third of the paper area at two thirds of its density.
    "medium": dict(map_size=30.0, num_static=80, num_dynamic=24, min_goal_distance=14.0,
                   max_episode_seconds=45.0),
    # The paper scenario (Fig. 2): 50 m x 50 m, 350 pillars, 100 moving obstacles.
    "paper": dict(),
}  # fmt: skip


def observation_shapes(cfg: EnvConfig | Mapping[str, Any]) -> dict[str, tuple[int, ...]]:
    """SafeNav's observation layout under ``cfg`` (an EnvConfig, or one as a dict, e.g. from
    a checkpoint): ``state`` (8,), ``lidar`` (elevations x (lidar_history + 1 if lidar_memory
    else lidar_history), beams), ``dynamic`` (tracked, 10). A dict without ``lidar_history`` or
    ``lidar_memory`` (older checkpoints) has 1 and 0. With ``static_tracked`` K > 0 (beyond the
    paper) a fourth entry, ``static`` (K, ``STATIC_FEATURES``)."""
    c = cfg if isinstance(cfg, Mapping) else dataclasses.asdict(cfg)
    images = int(c.get("lidar_history", 1)) + (1 if int(c.get("lidar_memory", 0)) else 0)
    rows = len(c["lidar_v_angles"]) * images
    shapes = {"state": (8,), "lidar": (rows, int(c["lidar_h_beams"])),
              "dynamic": (int(c["num_tracked"]), 10)}  # fmt: skip
    if int(c.get("static_tracked", 0)):
        shapes["static"] = (int(c["static_tracked"]), STATIC_FEATURES)
    return shapes


def make_config(preset: str = "paper", **overrides) -> EnvConfig:
    """The named preset with ``overrides`` applied; ``ValueError`` for unknown names or fields.
    A whole float for an integer field is taken as that integer (a value written ``3.0`` in a
    recipe or JSON file), a list for a tuple field as that tuple (a TOML array), and a string of
    comma-separated numbers as that tuple (``--env-kwargs lidar_v_angles -30,-15,0,15``;
    brackets allowed)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}: choose one of {sorted(PRESETS)}")
    types = {f.name: f.type for f in dataclasses.fields(EnvConfig)}
    unknown = sorted(set(overrides) - set(types))
    if unknown:
        raise ValueError(f"unknown EnvConfig field(s) {unknown}; known fields: {sorted(types)}")
    for name, value in overrides.items():
        if types[name] in (int, "int") and isinstance(value, float) and value.is_integer():
            overrides[name] = int(value)
        elif str(types[name]).startswith("tuple") and isinstance(value, str):
            try:
                overrides[name] = tuple(
                    float(v) for v in value.strip("()[] ").split(",") if v.strip()
                )
            except ValueError:
                raise ValueError(f"EnvConfig.{name}={value!r} is invalid: give comma-separated "
                                 "numbers, e.g. -10,0,10,20") from None  # fmt: skip
        elif str(types[name]).startswith("tuple") and isinstance(value, list):
            overrides[name] = tuple(value)  # a recipe's TOML array or a JSON list
    return EnvConfig(**{**PRESETS[preset], **overrides})


__all__ = [
    "COLLISION_RULES",
    "PRESETS",
    "STATIC_FEATURES",
    "EnvConfig",
    "make_config",
    "observation_shapes",
]
