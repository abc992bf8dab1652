"""The onboard runtime: sensor data -> observation -> policy -> velocity setpoint, with guards.

:class:`OnboardRuntime` builds the observation exactly as ``SafeNav-v1`` does, from what a drone
has instead of the simulator's ground truth:

- **range image**: an occupancy grid (:class:`~safenav.deploy.mapping.HeightMap`, the env's grid
  layout) updated from depth images (intrinsics + camera pose) or point clouds, ray-cast by the
  very same :func:`safenav.envs.sensors.raycast_height_map`;
- **dynamic**: tracked moving obstacles (centre, velocity, width, height) turned into the env's
  features by the very same :func:`safenav.envs.sensors.dynamic_obstacle_features`;
- **static** (only for a policy with a pillar list, ``EnvConfig.static_tracked`` K > 0): the
  pillars as the map shows them, as the env builds them with ``static_source="map"``: in a window
  of the map around the vehicle, each group of occupied cells one footprint
  (:func:`safenav.envs.sensors.map_footprints`), the K nearest by the very same
  :func:`safenav.envs.sensors.static_obstacle_features`;
- **state**: the vehicle's position and velocity (world ENU) and the goal.

:meth:`OnboardRuntime.step` returns a :class:`Setpoint`: a world-frame (ENU) velocity, clamped to
``v_max`` per goal-frame axis as in the env, and its NED form for PX4 (``(v_y, v_x, -v_z)``, see
:mod:`safenav.deploy.frames`). Guards, each giving a hover setpoint (zero velocity) and a reason,
logged when it changes: no goal; missing, stale (older than ``max_*_age_s``), future-stamped or
non-finite vehicle state; missing or stale map / tracker input; a perception input that was
rejected (non-finite camera pose, non-finite tracked obstacle, or data that cannot be read as
the documented arrays: wrong shape, not numeric) until the next good one; a non-finite
observation, policy output or shielded action. Depth pixels that are NaN, 0 or beyond range are
"no return" (the camera convention) and are skipped, not an error. ``update_*`` never raise on bad
sensor data (``tests/test_deploy_fuzz.py``); :meth:`OnboardRuntime.set_goal` raises ``ValueError``
for a goal or start that is not a finite 3-vector (an operator's or programmer's error).

Thread safety: ``update_*`` may be called from sensor threads while ``step`` runs in the control
loop; one lock serialises them.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from safenav.deploy.export import check_deployable, input_names
from safenav.deploy.frames import enu_to_ned, goal_frame_yaw, yaw_enu_to_ned
from safenav.deploy.mapping import HeightMap
from safenav.deploy.onboard_filter import OnboardFilter, VehicleView
from safenav.deploy.perception_link import DepthImage, PerceptionFrame, TrackedObstacle
from safenav.deploy.shield import MemoryShield, ShieldConfig, map_scan_hits, shield_action
from safenav.envs.config import EnvConfig
from safenav.envs.nav import DIST_SCALE, Z_SCALE
from safenav.envs.planner import observes_pillars
from safenav.envs.sensors import (
    FAR_POINT,
    RangeImageSpec,
    beam_hit_points,
    dequantize_heights,
    dynamic_obstacle_features,
    map_footprints,
    memory_image,
    raycast_height_map,
    static_obstacle_features,
)
from safenav.envs.world import GridSpec

log = logging.getLogger("safenav.deploy.runtime")

PolicyFn = Callable[..., np.ndarray]
"""``(state, lidar, dynamic) -> action``, NumPy float32 batches of 1; ``(state, lidar, dynamic,
static)`` for a policy with a pillar list (``EnvConfig.static_tracked`` > 0)."""


@dataclass
class RuntimeConfig:
    """Guards and perception settings of the onboard runtime."""

    max_state_age_s: float = 0.25
    """Vehicle state older than this (s) -> hover."""
    max_map_age_s: float = 0.5
    """No depth image / point cloud for this long (s) -> hover."""
    max_obstacle_age_s: float = 0.5
    """No tracker output for this long (s) -> hover (``require_tracker``)."""
    require_tracker: bool = True
    """Hover without fresh tracker output; False flies on the map alone."""
    future_tolerance_s: float = 0.1
    """Inputs stamped further in the future than this are rejected (clock mismatch)."""
    depth_stride: int = 2
    """Use every n-th depth pixel in both directions (2: a quarter of the pixels; the map still
    fills in, since successive frames see every cell from slightly different places)."""
    depth_max_range: float = 8.0
    """Depth returns beyond this range (m) are skipped."""
    max_obstacle_speed: float = 20.0
    """Tracked obstacles faster than this (m/s, per axis) are tracker faults: hover. (Absurd speeds
    or sizes overflow the shield's float32 geometry and would switch it off.)"""
    max_obstacle_size: float = 50.0
    """Tracked obstacles wider or taller than this (m) are tracker faults: hover."""
    cuboid_below_height: float = 2.5
    """Tracked obstacles shorter than this (m) are the env's floating cuboids, taller ones its
    standing cylinders (the env has 1 m cuboids and 5 m cylinders), unless the tracker says."""
    shield: ShieldConfig | None = None
    """Velocity-obstacle shield applied to the policy's action (None: off)."""
    shield_memory: int = 1
    """Range images the shield takes its static obstacles from, one per control step: 1 the
    current one (NavRL's shield), N > 1 the beam hits of the last N, kept in the world frame by
    odometry (:class:`~safenav.deploy.shield.MemoryShield`; a new goal forgets them). ``safenav
    fly --shield-memory`` counts the env's 10 Hz images and converts to the setpoint rate."""
    shield_map: bool = False
    """The shield also takes the map scan's hits (:func:`~safenav.deploy.shield.map_scan_hits`
    on the map built from depth images): the pillars at the vehicle's lower extent, whether the
    range image's beams see them now or not."""
    policy_memory: int = 0
    """Range images in the policy's memory image (``EnvConfig.lidar_memory`` > 0), one per
    control step; 0: the env's ``lidar_memory`` (the runtime steps at the env's rate). ``safenav
    fly`` converts the env's 10 Hz images to its setpoint rate (:meth:`for_flight`)."""
    planner_filter: bool = False
    """After the shield, the planner filter (:class:`~safenav.deploy.onboard_filter.OnboardFilter`,
    beyond the paper; ``safenav eval --planner-filter``'s observed view with the stall handover):
    the pillar planner flies where the command leaves no way out, and for 5 s where the flight
    came less than 1 m nearer its goal over the last 5 s (``FILTER_STALL``). Needs the policy's
    pillar list (``EnvConfig.static_tracked`` > 0)."""
    geofence: bool = True
    """Mark the env's arena border as a wall in the onboard map, as the simulator does (SafeNav-v1
    trains policies in a closed arena): the flight area is a geofence the policy sees coming. As
    in the env, the wall is no pillar of the ``static`` list (a policy with ``static_tracked``)."""

    @classmethod
    def for_flight(cls, env_config: EnvConfig, shield_memory: int, rate_hz: float,
                   shield_map: bool = False, mover_margin: float = 0.0,
                   brake: bool = False, planner_filter: bool = False) -> RuntimeConfig:  # fmt: skip
        """The runtime of ``safenav fly``: no shield (``shield_memory`` 0), the shield (1), or the
        memory shield of the last ``shield_memory`` range images at the env's control rate (10 Hz:
        20 is 2 s, as ``safenav eval --shield-memory 20``), i.e. that many seconds of setpoints at
        ``rate_hz``; ``shield_map``: the shield also takes the map scan; ``mover_margin``: metres
        more clearance from tracked moving obstacles; ``brake``: the braking cap (it needs the
        odometry's altitude: the memory shield's path); ``planner_filter``: the planner filter
        after it. :class:`~safenav.errors.SafenavError` if the memory is more than 100
        setpoints."""
        from safenav.errors import SafenavError

        # The policy's memory image (lidar_memory) spans the same seconds at the setpoint rate.
        policy_memory = (max(1, round(env_config.lidar_memory * rate_hz * env_config.dt))
                         if env_config.lidar_memory else 0)  # fmt: skip
        if policy_memory > 1000:
            raise SafenavError(f"lidar_memory {env_config.lidar_memory} at --rate {rate_hz:g} Hz is "
                               f"{policy_memory} range images, more than 1000")  # fmt: skip
        if shield_memory <= 0:
            return cls(policy_memory=policy_memory, planner_filter=planner_filter)
        steps = 1 if shield_memory == 1 else max(2, round(shield_memory * rate_hz * env_config.dt))
        if steps > 100:
            raise SafenavError(f"--shield-memory {shield_memory} ({shield_memory * env_config.dt:g} s of range "
                               f"images) at --rate {rate_hz:g} Hz is {steps} setpoints, more than 100")  # fmt: skip
        braking = ShieldConfig.braking_of(env_config) if brake else {}
        return cls(shield=ShieldConfig.for_env(env_config, mover_margin=mover_margin, **braking),
                   shield_memory=steps, shield_map=shield_map,
                   policy_memory=policy_memory, planner_filter=planner_filter)  # fmt: skip


@dataclass
class Setpoint:
    """What :meth:`OnboardRuntime.step` returns."""

    velocity: np.ndarray
    """World ENU velocity, m/s (zero when hovering)."""
    velocity_ned: np.ndarray
    """The same in PX4's NED frame: (north, east, down)."""
    yaw_ned_deg: float
    """Heading to hold: the goal frame's x axis, NED degrees (nan before a goal is set)."""
    hover: bool
    reason: str = ""
    action: np.ndarray | None = None
    """Normalised goal-frame action after the shield."""
    policy_action: np.ndarray | None = None
    """The policy's own action."""
    shielded: bool = False
    filtered: bool = False
    """The planner filter replaced the command (``RuntimeConfig.planner_filter``)."""
    observation: dict[str, np.ndarray] | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)


class OnboardRuntime:
    """Sensor data -> velocity setpoint (see the module docstring).

    Args:
        policy: ``(state (1, 8), lidar (1, 4, 36), dynamic (1, 5, 10)) -> action (1, 3)`` NumPy
            float32, e.g. :class:`~safenav.deploy.export.OnnxPolicy` (``lidar (1, 8, 36)`` with
            a memory image; a fourth argument ``static (1, K, 7)`` with a pillar list,
            ``static_tracked`` K > 0).
        env_config: the policy's env configuration (beam layout, scales, v_max, grid).
        config: guards and perception settings.
        grid: the map's extent (default: the env's map plus padding, world-fixed).
        clock: monotonic time source, seconds; stamps of inputs are on this clock.
    """

    def __init__(
        self,
        policy: PolicyFn,
        env_config: EnvConfig,
        config: RuntimeConfig | None = None,
        grid: GridSpec | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        check_deployable(env_config, "the onboard runtime's policy")
        self.policy = policy
        self.cfg = env_config
        self.config = config or RuntimeConfig()
        memory = self.config.shield_memory
        if not 1 <= memory <= 100 or (memory > 1 and self.config.shield is None):
            raise ValueError(
                f"shield_memory {memory}: 1-100 range images, above 1 only with a shield"
            )
        if self.config.shield_map and self.config.shield is None:
            raise ValueError("shield_map needs a shield")
        scan = self.config.shield_map
        self._memory_shield = (MemoryShield(memory, self.config.shield, map_scan=scan)
                               if self.config.shield is not None
                               and (memory > 1 or scan or self.config.shield.brake_time > 0)
                               else None)  # fmt: skip
        self._episode_start = True  # the memory shield's next image begins a new memory
        self._filter = None
        if self.config.planner_filter:
            if not observes_pillars(env_config):
                raise ValueError("planner_filter flies on the policy's pillar list: its env config "
                                 "has none (static_tracked 0)")  # fmt: skip

            self._filter = OnboardFilter()
        # The flight's start altitude (NavRL's altitude band) and its first step's time (the stall
        # clock): the filter's view of the vehicle.
        self._start_z = 0.0
        self._flight_t0: float | None = None
        if self.config.policy_memory < 0:
            raise ValueError(f"policy_memory {self.config.policy_memory}: 0 or more range images")
        # The policy's memory image: beam hits of the last images, world frame (see observation)
        self._mem_slots = (self.config.policy_memory or env_config.lidar_memory
                           if env_config.lidar_memory else 0)  # fmt: skip
        self._mem_points: torch.Tensor | None = None  # (slots, E * C, 3); FAR = no point
        self._mem_slot = 0
        self.clock = clock
        self.spec = RangeImageSpec.for_config(env_config)
        self.map = HeightMap(
            grid or GridSpec.for_config(env_config),
            geofence=env_config.half if self.config.geofence else None,
        )
        self._inputs = input_names(env_config)  # the policy's arguments: static last, if any
        # The pillar list's window: cells either side of the vehicle's, so that every pillar
        # (of the env's sides) whose clearance is within range lies wholly in it, with two cells
        # to spare (a pillar cut by the window's edge is then out of range, cut or not).
        reach = env_config.lidar_range + max(env_config.pillar_sides)
        self._static_reach = math.ceil(reach / self.map.grid.resolution - 1e-6) + 2
        self._lock = threading.Lock()
        self._goal: np.ndarray | None = None
        self._yaw = 0.0
        self._pos: np.ndarray | None = None
        self._vel: np.ndarray | None = None
        self._state_stamp = -math.inf
        self._map_stamp = -math.inf
        self._obstacles = np.zeros((0, 9), dtype=np.float32)  # p(3) v(3) width height cuboid
        self._obstacle_stamp = -math.inf
        self._faults: dict[str, str] = {}
        self._last_reason = ""
        self.steps = 0
        self.hover_steps = 0

    # ------------------------------------------------------------------ inputs
    def set_goal(self, goal, start=None) -> None:
        """Set the goal (world ENU); the goal frame's yaw is fixed from ``start`` (default: the
        current position) toward it, as the env fixes it at reset.

        Raises ``ValueError`` if ``goal`` or ``start`` is not a finite 3-vector, or if ``start``
        is None before the first vehicle state."""
        goal = _finite_vector(goal, "goal")
        start = None if start is None else _finite_vector(start, "start")
        with self._lock:
            if start is None:
                if self._pos is None:
                    raise ValueError(
                        "set_goal needs a start position before the first vehicle state"
                    )
                start = self._pos
            self._goal = goal
            self._yaw = goal_frame_yaw(start, goal)
            self._start_z, self._flight_t0 = float(start[2]), None
            if self._filter is not None:  # a new flight, even to the same goal
                self._filter.new_flight()
            self._episode_start = True  # a new flight: what the memory shield saw is not on it
            self._mem_points = None  # nor what the policy's memory image remembered

    @property
    def goal(self) -> np.ndarray | None:
        return None if self._goal is None else self._goal.copy()

    @property
    def goal_yaw(self) -> float:
        """Yaw (ENU, rad) of the goal frame."""
        return self._yaw

    def _stamp_ok(self, source: str, stamp: float) -> bool:
        if not math.isfinite(stamp) or stamp > self.clock() + self.config.future_tolerance_s:
            self._faults[source] = f"{source} stamp {stamp!r} is not finite or in the future"
            return False
        return True

    def _accepted(self, source: str, stamp: float, problem: str) -> bool:
        """Under the lock: False, with the fault recorded, if the input's stamp or its data (a
        ``problem`` found while reading it, outside the lock) is bad."""
        if not self._stamp_ok(source, stamp):
            return False
        if problem:
            self._faults[source] = problem
            return False
        return True

    def update_state(self, position, velocity, stamp: float | None = None) -> None:
        """Vehicle position and velocity, world ENU (from PX4's local NED: see frames)."""
        stamp = self.clock() if stamp is None else float(stamp)
        problem = ""
        try:
            p = np.asarray(position, dtype=np.float64).reshape(3)
            v = np.asarray(velocity, dtype=np.float64).reshape(3)
            if not (np.isfinite(p).all() and np.isfinite(v).all()):
                problem = "non-finite vehicle state"
        except (TypeError, ValueError) as err:
            problem = f"vehicle state rejected: {err}"
        with self._lock:
            if not self._accepted("state", stamp, problem):
                return
            self._faults.pop("state", None)
            self._pos, self._vel, self._state_stamp = p, v, stamp

    def _obstacle_boxes(self) -> np.ndarray:
        ob = self._obstacles
        half = np.stack([ob[:, 6] / 2, ob[:, 6] / 2, ob[:, 7] / 2], -1)
        return np.stack([ob[:, 0:3] - half, ob[:, 0:3] + half], 1)

    def update_depth(self, images: Sequence[DepthImage], stamp: float | None = None) -> int:
        """Insert depth images (one capture, e.g. all cameras of the rig) into the map; points
        inside tracked obstacles are left out. Returns the points inserted."""
        stamp = self.clock() if stamp is None else float(stamp)
        try:
            images, problem = [_checked_image(img) for img in images], ""
        except (TypeError, ValueError) as err:
            problem = f"depth image rejected: {err}"
        with self._lock:
            if not self._accepted("map", stamp, problem):
                return 0
            n = self.map.insert_depth(images, self.config.depth_stride, self.config.depth_max_range,
                                      self._obstacle_boxes())  # fmt: skip
            self._faults.pop("map", None)
            self._map_stamp = stamp
            return n

    def update_points(self, points, stamp: float | None = None) -> int:
        """Insert a world-frame point cloud ``(P, 3)``; non-finite points are skipped, a cloud of
        another shape is rejected."""
        stamp = self.clock() if stamp is None else float(stamp)
        try:
            pts, problem = np.asarray(points, dtype=np.float32), ""
            if pts.size == 0:
                pts = pts.reshape(0, 3)
            elif pts.ndim != 2 or pts.shape[1] != 3:
                problem = f"point cloud of shape {pts.shape} rejected: expected (P, 3)"
        except (TypeError, ValueError) as err:
            problem = f"point cloud rejected: {err}"
        with self._lock:
            if not self._accepted("map", stamp, problem):
                return 0
            n = self.map.insert_points(pts, self._obstacle_boxes())
            self._faults.pop("map", None)
            self._map_stamp = stamp
            return n

    def update_obstacles(
        self, obstacles: Sequence[TrackedObstacle], stamp: float | None = None
    ) -> None:
        """Replace the tracked moving obstacles (world ENU centres and velocities)."""
        stamp = self.clock() if stamp is None else float(stamp)
        rows, problem = [], ""
        try:
            for o in obstacles:
                cuboid = (
                    o.cuboid if o.cuboid is not None else o.height < self.config.cuboid_below_height
                )
                rows.append([*np.asarray(o.p, dtype=float).reshape(3), *np.asarray(o.v, dtype=float).reshape(3),
                             float(o.width), float(o.height), float(bool(cuboid))])  # fmt: skip
            with np.errstate(over="ignore"):  # beyond float32: inf, rejected below
                arr = np.asarray(rows, dtype=np.float32).reshape(-1, 9)
            c = self.config
            if not np.isfinite(arr).all() or (arr[:, 6:8] < 0).any():
                problem = "non-finite or negative-size tracked obstacle"
            elif (np.abs(arr[:, 3:6]) > c.max_obstacle_speed).any() or (
                arr[:, 6:8] > c.max_obstacle_size
            ).any():
                problem = (f"tracked obstacle faster than {c.max_obstacle_speed} m/s or larger "
                           f"than {c.max_obstacle_size} m")  # fmt: skip
        except (TypeError, ValueError) as err:
            problem = f"tracked obstacles rejected: {err}"
        with self._lock:
            if not self._accepted("tracker", stamp, problem):
                return
            self._faults.pop("tracker", None)
            self._obstacles, self._obstacle_stamp = arr, stamp

    def update_frame(self, frame: PerceptionFrame) -> None:
        """Everything in one perception frame: tracked obstacles first, then depth and points."""
        if frame.obstacles is not None:
            self.update_obstacles(frame.obstacles, frame.stamp)
        if frame.depth:
            self.update_depth(frame.depth, frame.stamp)
        if frame.points is not None:
            self.update_points(frame.points, frame.stamp)

    # ------------------------------------------------------------------ output
    def _hover(self, reason: str) -> Setpoint:
        self.hover_steps += 1
        if reason != self._last_reason:
            log.warning("hover: %s", reason)
            self._last_reason = reason
        yaw = yaw_enu_to_ned(self._yaw) if self._goal is not None else math.nan
        return Setpoint(np.zeros(3), np.zeros(3), math.degrees(yaw), hover=True, reason=reason)

    def _check_inputs(self, now: float) -> str:
        c = self.config
        if self._goal is None:
            return "no goal set"
        if self._faults:
            return "; ".join(sorted(self._faults.values()))
        for name, stamp, limit, needed in (
            ("vehicle state", self._state_stamp, c.max_state_age_s, True),
            ("map (depth / point cloud)", self._map_stamp, c.max_map_age_s, True),
            ("obstacle tracker", self._obstacle_stamp, c.max_obstacle_age_s, c.require_tracker),
        ):
            if not needed:
                continue
            if stamp == -math.inf:
                return f"no {name} input yet"
            if now - stamp > limit:
                return f"stale {name}: {now - stamp:.2f} s old > {limit:.2f} s"
        return ""

    def observation(self, remember: bool = False) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """The env-layout observation (batch of 1) and the raw range image (metres), now.

        A policy with a memory image (``EnvConfig.lidar_memory``) sees the current range image's
        beam hits with those of the images remembered before it, placed in the world by the
        odometry, as the env does; ``remember=True`` (:meth:`step`, once per control step) keeps
        the current hits for the next steps, in place of the oldest."""
        cfg = self.cfg
        pos = torch.tensor(self._pos, dtype=torch.float32)[None]
        yaw = torch.tensor([self._yaw], dtype=torch.float32)
        ranges = raycast_height_map(
            self.map.cast_map, self.map.grid.origin, self.map.grid.size, pos, yaw, self.spec
        )
        ob = torch.from_numpy(self._obstacles)
        if ob.shape[0]:
            cos_y, sin_y = torch.cos(yaw), torch.sin(yaw)
            dynamic, _, _ = dynamic_obstacle_features(
                (ob[:, 0:3] - pos[0])[None], ob[None, :, 3:6], ob[None, :, 6], ob[None, :, 8] > 0.5,
                cos_y, sin_y, cfg.num_tracked, cfg.lidar_range, cfg.v_max,
            )  # fmt: skip
        else:
            dynamic = torch.zeros(1, cfg.num_tracked, 10)
        state = state_features(self._pos, self._vel, self._goal, self._yaw, cfg.v_max)
        lidar = (cfg.lidar_range - ranges) / cfg.lidar_range
        if self._mem_slots:
            lidar = torch.cat([lidar, self._memory_image(ranges, pos, yaw, remember)], 1)
        obs = {"state": torch.from_numpy(state)[None], "lidar": lidar, "dynamic": dynamic}
        if cfg.static_tracked:
            obs["static"] = self._static_rows(pos, yaw)
        return obs, ranges

    def _static_rows(self, pos: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
        """The ``static`` entry ``(1, K, 7)``, as the env builds it with ``static_source="map"``
        from its whole map: the footprints (:func:`~safenav.envs.sensors.map_footprints`) of the
        occupied columns in a window of ``2 * _static_reach + 1`` cells a side around the
        vehicle's cell (the whole map takes ~0.2 s), then the K nearest within range.

        Occupied: a column above the ground (sensor data raises only columns of points above the
        map's ground band) that is not the geofence wall (the map's ``floor``); its top as the
        ray caster reads it (the quantized ``cast_map``, as the env's). The part of the window
        beyond the map is free. A group of touching pillars that reaches beyond the window is cut
        at its edge where the env takes it whole: the one difference from the env's list."""
        cfg, grid, m = self.cfg, self.map.grid, self.map
        g, res, r = grid.size, grid.resolution, self._static_reach
        side = 2 * r + 1
        # The vehicle's cell, clamped first (a finite position far away would overflow a cell
        # index): beyond the map by more than the window, the window holds no map cell.
        corner = []
        for x in self._pos[:2]:
            cell = min(max((float(x) - grid.origin) / res, -side), g + side)
            corner.append(math.floor(cell) - r)
        (x0, y0), tops = corner, torch.zeros(side, side)
        occupied = torch.zeros(side, side, dtype=torch.bool)
        ax, bx = max(x0, 0), min(x0 + side, g)
        ay, by = max(y0, 0), min(y0 + side, g)
        if ax < bx and ay < by:
            cast = m.cast_map.view(g, g)[ax:bx, ay:by]
            col = dequantize_heights(cast)
            wall = m.floor.view(g, g)[ax:bx, ay:by] > 0
            tops[ax - x0 : bx - x0, ay - y0 : by - y0] = col
            occupied[ax - x0 : bx - x0, ay - y0 : by - y0] = (col > 0) & ~wall
        xy, half, top = map_footprints(tops, occupied, 0.0, res)
        xy = xy + torch.tensor([grid.origin + x0 * res, grid.origin + y0 * res])
        cos_y, sin_y = torch.cos(yaw), torch.sin(yaw)
        return static_obstacle_features(pos, xy[None], half[None], top[None], cos_y, sin_y,
                                        cfg.static_tracked, cfg.lidar_range)  # fmt: skip

    def _memory_image(self, ranges: torch.Tensor, pos: torch.Tensor, yaw: torch.Tensor,
                      remember: bool) -> torch.Tensor:  # fmt: skip
        """The memory image ``(1, E, C)`` of the current hits and the remembered ones (a ring
        of ``_mem_slots`` images, the oldest at ``_mem_slot``: the current hits replace it)."""
        hits = beam_hit_points(ranges, pos, yaw, self.spec)[0]
        if self._mem_points is None:  # a new flight: the first image is all it remembers
            self._mem_points = torch.full((self._mem_slots, *hits.shape), FAR_POINT)
            self._mem_slot = 0
        others = torch.cat(
            [self._mem_points[: self._mem_slot], self._mem_points[self._mem_slot + 1 :]]
        )
        image = memory_image(torch.cat([others, hits[None]])[None], pos, yaw, self.cfg)
        if remember:
            self._mem_points[self._mem_slot] = hits
            self._mem_slot = (self._mem_slot + 1) % self._mem_slots
        return image

    def distance_to_goal(self) -> float:
        with self._lock:
            if self._goal is None or self._pos is None:
                return math.inf
            return float(np.linalg.norm(self._goal - self._pos))

    def step(self, now: float | None = None) -> Setpoint:
        """One control step: the velocity setpoint for ``now`` (default: the clock)."""
        now = self.clock() if now is None else float(now)
        self.steps += 1
        with self._lock, torch.inference_mode():
            reason = self._check_inputs(now)
            if reason:
                return self._hover(reason)
            t0 = time.perf_counter()
            obs, _ = self.observation(remember=True)
            t1 = time.perf_counter()
            np_obs = {k: v.numpy() for k, v in obs.items()}
            if not all(np.isfinite(v).all() for v in np_obs.values()):
                return self._hover("non-finite observation")
            raw = np.asarray(self.policy(*(np_obs[k] for k in self._inputs)), dtype=np.float32)
            t2 = time.perf_counter()
            if raw.shape != (1, 3) or not np.isfinite(raw).all():
                return self._hover(
                    f"policy output not finite or of shape {raw.shape} (expected (1, 3))"
                )
            action = torch.from_numpy(np.clip(raw, -1.0, 1.0))
            shielded = False
            if self.config.shield is not None:
                if self._memory_shield is not None:  # the odometry places the remembered hits
                    pos = torch.tensor(self._pos, dtype=torch.float32)[None]
                    yaw = torch.tensor([self._yaw], dtype=torch.float32)
                    fresh = torch.tensor([self._episode_start])
                    extra = None
                    if self.config.shield_map:
                        m, scfg = self.map, self.config.shield
                        extra = map_scan_hits(m.cast_map, m.grid.origin, m.grid.size,
                                              self.cfg.grid_resolution, pos, yaw, scfg)  # fmt: skip
                    action, corrected = self._memory_shield.apply(obs, action, pos, yaw, fresh,
                                                                  extra=extra)  # fmt: skip
                    self._episode_start = False
                else:
                    action, corrected = shield_action(obs, action, self.config.shield)
                shielded = bool(corrected[0])
                if not torch.isfinite(action).all():  # absurd (finite) tracker data can do this
                    return self._hover("shielded action not finite")
            t3 = time.perf_counter()
            filtered = False
            if self._filter is not None:
                if self._flight_t0 is None:
                    self._flight_t0 = now
                view = VehicleView.of(self.cfg, self._pos, self._vel, self._goal, self._yaw,
                                      self._start_z, now - self._flight_t0)  # fmt: skip
                action = self._filter(view, obs, action)
                filtered = bool(self._filter.overridden[0])
                if not torch.isfinite(action).all():
                    return self._hover("filtered action not finite")
            t4 = time.perf_counter()
            # Goal frame -> world (as goal_frame_to_world): rotate by the goal yaw about z.
            a = action[0].numpy().astype(np.float64) * self.cfg.v_max
            c, s = math.cos(self._yaw), math.sin(self._yaw)
            v = np.array([c * a[0] - s * a[1], s * a[0] + c * a[1], a[2]])
            if self._last_reason:
                log.info("resuming: inputs are good again")
                self._last_reason = ""
            return Setpoint(
                velocity=v, velocity_ned=enu_to_ned(v), yaw_ned_deg=math.degrees(yaw_enu_to_ned(self._yaw)),
                hover=False, action=action[0].numpy().copy(), policy_action=raw[0].copy(), shielded=shielded,
                filtered=filtered, observation={k: v[0].copy() for k, v in np_obs.items()},
                timings_ms={"observation": (t1 - t0) * 1e3, "policy": (t2 - t1) * 1e3, "shield": (t3 - t2) * 1e3,
                            **({"filter": (t4 - t3) * 1e3} if self._filter is not None else {})},
            )  # fmt: skip


def _finite_vector(x, what: str) -> np.ndarray:
    """``x`` as a finite float64 3-vector, else ``ValueError`` naming ``what``."""
    try:
        v = np.asarray(x, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise ValueError(f"{what} {x!r} is not a 3-vector") from None
    if not np.isfinite(v).all():
        raise ValueError(f"{what} {v.tolist()} is not finite")
    return v


def _checked_image(img: DepthImage) -> DepthImage:
    """``img`` with arrays of the documented shapes (depth ``(H, W)`` float32, ``R`` 3x3, ``t``
    3); ``ValueError`` (or ``TypeError``) if it cannot be read so or its camera pose or
    intrinsics are not finite (``fx``, ``fy`` also not zero)."""
    depth = np.asarray(img.depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth of shape {depth.shape}, expected (H, W)")
    R = np.asarray(img.R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(img.t, dtype=np.float64).reshape(3)
    k = [float(x) for x in (img.fx, img.fy, img.cx, img.cy)]
    # Checked as the map's float32 kernels read them: 1e-50 is a zero focal length there, 1e300 inf.
    with np.errstate(over="ignore", under="ignore"):
        r32, t32, k32 = (np.asarray(x, dtype=np.float32) for x in (R, t, k))
    if not (np.isfinite(r32).all() and np.isfinite(t32).all() and np.isfinite(k32).all()
            and k32[0] != 0 and k32[1] != 0):  # fmt: skip
        raise ValueError("non-finite camera pose or intrinsics (as float32)")
    return DepthImage(depth, *k, R, t)


def state_features(pos, vel, goal, yaw: float, v_max: float) -> np.ndarray:
    """The env's ``state`` observation ``(8,)`` float32 for one vehicle (see ``SafeNavVectorEnv``;
    tested equal to it): unit vector to the goal in the goal frame, horizontal distance / 20 m,
    z distance / 4 m, velocity in the goal frame / v_max."""
    c, s = math.cos(yaw), math.sin(yaw)
    to_goal = np.asarray(goal, dtype=np.float32) - np.asarray(pos, dtype=np.float32)
    v = np.asarray(vel, dtype=np.float32)
    unit = to_goal / max(float(np.sqrt(np.dot(to_goal, to_goal))), 1e-6)
    return np.array([
        c * unit[0] + s * unit[1], -s * unit[0] + c * unit[1], unit[2],
        math.hypot(to_goal[0], to_goal[1]) / DIST_SCALE, to_goal[2] / Z_SCALE,
        (c * v[0] + s * v[1]) / v_max, (-s * v[0] + c * v[1]) / v_max, v[2] / v_max,
    ], dtype=np.float32)  # fmt: skip


__all__ = ["OnboardRuntime", "PolicyFn", "RuntimeConfig", "Setpoint", "state_features"]
