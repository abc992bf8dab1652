"""Fuzzing the deployment inputs: garbage in, a bounded setpoint (or hover) out, nothing crashes.

What must hold, whatever arrives: every setpoint the runtime returns, and every one the flight loop
sends, is finite, and either zero with ``hover`` or within ``v_max`` on each goal-frame axis
(world: horizontal speed <= sqrt(2) ``v_max``, vertical <= ``v_max``); the runtime never flies
without a goal, or on a vehicle state, map or tracker input that is stale, future-stamped or
rejected; ``update_*`` never raise; ``decode_frame`` raises only ``ValueError``; no link thread
dies; the simulated vehicle's state stays finite and its acceleration within its limit. Cases per
run (fixed seeds; hypothesis derandomized, with a fixed number of examples):

| target | garbage | cases |
|---|---|---|
| ``OnboardRuntime`` (hypothesis) | sequences of 10-30 updates: state, depth images, point clouds, obstacle tracks and goals that are NaN / Inf / huge, empty, wrong-shaped (1-D or 3-D depth, 2x2 ``R``, ``(P, 4)`` clouds, 2-vectors), wrong-dtyped (int of NaN, float16, complex, object, strings); stamps NaN / Inf / future / backwards / duplicated / stale; garbage policy outputs (NaN, 1e30, wrong shapes, None); no shield, the shield, the memory shield | 120 sequences (~2,300 updates) |
| ``OnboardRuntime`` (seeded) | the same generator, each on the Numba kernels and on the batched NumPy / torch paths | 40 x 60 = 2,400 updates per path |
| ``OnboardRuntime``, a pillar list (seeded) | the same generator for a policy with ``static_tracked``: the list built from the map the garbage fills, passed as the fourth array, finite whenever the policy runs | 12 x 60 = 720 updates |
| ``OnboardRuntime`` + shield | tracks next to the vehicle with huge finite heights, widths, velocities; per path | 500 steps per path |
| ``OnboardRuntime``, threads | 3 sensor threads x 200 garbage updates against >= 300 control steps | 600 updates |
| ``decode_frame`` | random bytes: raw, length-prefixed, random JSON headers, nesting to depth 3,000 | 10,000 bodies |
| ``decode_frame`` | bit flips, truncations, insertions, header-byte swaps, splices of valid frames | 3,000 bodies |
| ``decode_frame`` (hypothesis) | JSON headers with fields of random type and value, random payload | 150 headers |
| ``PerceptionClient`` over TCP | garbage frames, a raising handler, an oversized length, a frame cut by a disconnect | 300 frames, 3 connections |
| ``SimVehicle`` MAVLink parser | random datagrams: raw, MAVLink 1/2 start bytes, bit-flipped, truncated or junk-wrapped valid packets | 10,000 datagrams |
| ``SimVehicle`` MAVLink handler | valid-CRC setpoints, commands, mode changes, PARAM_SET / PARAM_REQUEST_READ with NaN / Inf / huge fields | 3,000 messages |
| MAVSDK (``fly``'s MAVLink parser) | random datagrams into its UDP port beside a live vehicle | 10,000 datagrams |
| ``FlightController`` loop | telemetry NaN / Inf / huge, stamps NaN / Inf / future / backwards / duplicated, dropouts; garbage perception frames from a thread; garbage policy outputs | 10 flights, >= 200 ticks |

Bugs they found, fixed: ``set_goal`` took a NaN ``start`` (NaN goal-frame yaw: the ray cast then
raised); tracks of absurd but finite size or speed made the batched shield return NaN, which the
runtime sent as the setpoint (111 of 1,500 such steps); ``update_*`` raised on wrong-shaped or
non-numeric arrays, from the sensor threads; ``decode_frame`` let ``OverflowError`` (``1e400``) and
``RecursionError`` out and passed wrong-length obstacle vectors and a non-object ``truth`` on, which
raised later; an exception in ``on_frame`` ended ``PerceptionClient``'s thread; ``fly`` took a NaN
telemetry stamp as fresh, a NaN position as the goal frame's start, and a NaN goal until after
takeoff; ``PARAM_SET MPC_XY_VEL_MAX <= 0`` made the simulated vehicle's state NaN.
"""

from __future__ import annotations

import contextlib
import json
import math
import socket
import struct
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from safenav.deploy import kernels, px4
from safenav.deploy.camera import PinholeCamera, rig_poses
from safenav.deploy.frames import ned_to_enu
from safenav.deploy.perception_link import (
    MAX_FRAME_BYTES,
    DepthImage,
    PerceptionClient,
    PerceptionFrame,
    TrackedObstacle,
    decode_frame,
    encode_frame,
)
from safenav.deploy.runtime import OnboardRuntime, RuntimeConfig
from safenav.deploy.shield import ShieldConfig
from safenav.deploy.sim_vehicle import SimVehicle, SimVehicleConfig
from safenav.envs.config import make_config
from safenav.errors import SafenavError

pytestmark = [
    pytest.mark.usefixtures("one_thread"),
    # Garbage overflows float32 casts and the like on purpose.
    pytest.mark.filterwarnings("ignore::RuntimeWarning"),
]

M = mavlink
CFG = make_config("easy")
V_MAX = CFG.v_max

RUNTIME_SEQUENCES = 120
SHIELD_CASES = 500
SEEDED_SEQUENCES, SEEDED_UPDATES = 40, 60
STATIC_SEQUENCES = 12
CFG_STATIC = make_config("easy", static_tracked=4, static_source="map")
THREADS, THREAD_UPDATES, THREAD_STEPS = 3, 200, 300
DECODE_RANDOM = 10_000
DECODE_MUTATED = 3_000
DECODE_HEADERS = 150
CLIENT_GARBAGE_FRAMES = 300
SIM_DATAGRAMS = 10_000
SIM_MESSAGES = 3_000
MAVSDK_DATAGRAMS = 10_000
FLIGHTS, MIN_FLIGHT_TICKS = 10, 200

SPECIAL = (math.nan, math.inf, -math.inf, 0.0, -0.0, 5e-324, 1e-300, 1e30, -1e30, 3.5e38, -3.5e38,
           1e300, -1e300)  # fmt: skip
# Stamp offsets from the clock (None: no stamp, the runtime stamps it): duplicated, backwards,
# stale, future, non-finite.
STAMP_OFFSETS = (None, None, None, 0.0, 0.0, -0.01, -0.05, -0.3, -2.0, -1e9, 0.05, 0.3, 5.0,
                 math.nan, math.inf, -math.inf, 1e300)  # fmt: skip
KINDS = ("state", "depth", "points", "obstacles", "frame", "goal", "tick", "step")
CAM = PinholeCamera.from_fov(10, 8, 90.0)
POSES = rig_poses([0.0, 0.0, 1.5], 0.3)


@pytest.fixture(params=["compiled", "batched"])
def kernel_path(request, monkeypatch) -> str:
    """Both implementations of depth insertion and the shield: the Numba kernels (when Numba is
    installed) and the batched NumPy / torch paths (without it)."""
    if request.param == "compiled" and not kernels.AVAILABLE:
        pytest.skip("Numba not installed")
    monkeypatch.setattr(kernels, "AVAILABLE", request.param == "compiled")
    return request.param


def assert_bounded(velocity, velocity_ned, yaw_enu: float, hover: bool) -> None:
    """The setpoint invariant: finite; zero when hovering; each goal-frame axis within v_max."""
    v, ned = np.asarray(velocity, dtype=float), np.asarray(velocity_ned, dtype=float)
    assert v.shape == (3,) and ned.shape == (3,), (v, ned)
    assert np.isfinite(v).all() and np.isfinite(ned).all(), (v, ned)
    np.testing.assert_array_equal(ned, [v[1], v[0], -v[2]])
    if hover:
        assert not v.any(), v
        return
    c, s = math.cos(yaw_enu), math.sin(yaw_enu)
    goal_frame = np.array([c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2]])
    assert np.abs(goal_frame).max() <= V_MAX * (1 + 1e-6), goal_frame


def check_setpoint(sp, rt: OnboardRuntime) -> None:
    assert_bounded(sp.velocity, sp.velocity_ned, rt.goal_yaw, sp.hover)
    assert math.isfinite(sp.yaw_ned_deg) or rt.goal is None


class Garbage:
    """Seeded inputs of every kind the deployment takes: sane ones (``good``) or garbage."""

    def __init__(self, seed: int, p_good: float = 0.5) -> None:
        self.rng = np.random.default_rng(seed)
        self.p_good = p_good

    def good(self) -> bool:
        return bool(self.rng.random() < self.p_good)

    def pick(self, options):
        return options[int(self.rng.integers(len(options)))]

    def number(self) -> float:
        r = self.rng.random()
        if r < 0.4:
            return float(self.pick(SPECIAL))
        if r < 0.7:
            return float(self.rng.normal() * 10.0 ** self.rng.integers(0, 8))
        return float(self.rng.uniform(-10, 10))

    def numbers(self, shape) -> np.ndarray:
        a = self.rng.uniform(-10, 10, shape)
        mask = self.rng.random(shape) < self.pick((0.0, 0.05, 0.5, 1.0))
        a[mask] = self.rng.choice(SPECIAL, size=int(mask.sum()))
        return a

    def cast(self, a: np.ndarray):
        """``a`` in a wrong dtype now and then (ints of NaN, float16 overflow, complex, object)."""
        dtype = self.pick((None, None, np.float32, np.float16, np.int32, np.uint16, np.int8, bool,
                           np.complex64, object))  # fmt: skip
        with np.errstate(all="ignore"):
            return a if dtype is None else a.astype(dtype)

    def vec3(self, good: bool, scale: float = 1.0):
        if good:
            return self.rng.normal(size=3) * scale
        k = self.rng.integers(9)
        if k <= 2:
            return self.cast(self.numbers((3,)))
        if k == 3:
            return self.numbers((int(self.pick((0, 1, 2, 4, 9))),))
        if k == 4:
            return self.numbers((3, 1))  # reshapes to 3: accepted if finite
        if k == 5:
            return self.numbers((2, 3))
        if k == 6:
            return [1.0, "x", 2.0]
        if k == 7:
            return self.pick(("abc", None, [[1.0, 2.0], [3.0]], {"x": 1}))
        return self.numbers((3,)).tolist()

    def stamp(self, now: float):
        off = self.pick(STAMP_OFFSETS)
        return None if off is None else now + off

    def state(self, good: bool):
        if good:
            p = np.array([0.0, 0.0, 1.5]) + 0.2 * self.rng.normal(size=3)
            return p, self.rng.normal(size=3)
        return self.vec3(False), self.vec3(self.good())

    def depth_image(self, good: bool) -> DepthImage:
        R, t = POSES[int(self.rng.integers(len(POSES)))]
        if good:
            d = self.rng.uniform(0.3, 9.0, (CAM.height, CAM.width)).astype(np.float32)
            d[self.rng.random(d.shape) < 0.2] = self.pick((0.0, np.nan))
            return DepthImage(d, CAM.fx, CAM.fy, CAM.cx, CAM.cy, R, t)
        shape = self.pick(((0, 0), (0, 5), (CAM.height, CAM.width), (CAM.height, CAM.width, 3),
                           (7,), (), (1, 1), (60, 80)))  # fmt: skip
        depth = self.cast(self.numbers(shape)) if self.rng.random() < 0.95 else "depth"
        intr = [
            self.number() if self.rng.random() < 0.3 else v
            for v in (CAM.fx, CAM.fy, CAM.cx, CAM.cy)
        ]
        k = self.rng.integers(6)
        R = (self.numbers((3, 3)), self.numbers((2, 2)), R * 1e30, R.T[::-1])[k] if k < 4 else R
        t = self.vec3(self.good(), 1.0) if self.rng.random() < 0.5 else t
        return DepthImage(depth, *intr, R, t)

    def points(self, good: bool):
        if good:
            return self.rng.uniform(-10, 10, (int(self.rng.integers(0, 200)), 3)).astype(np.float32)
        k = self.rng.integers(7)
        if k <= 1:
            return self.cast(self.numbers((int(self.rng.integers(0, 3000)), 3)))
        if k == 2:
            return self.numbers((int(self.rng.integers(1, 50)), int(self.pick((1, 2, 4, 6)))))
        if k == 3:
            return self.numbers(self.pick(((3,), (), (0,), (2, 3, 3))))
        if k == 4:
            return self.pick(([], "xyz", None, [[1.0, 2.0, 3.0], [4.0, 5.0]]))
        return self.numbers((int(self.rng.integers(0, 50)), 3)).tolist()

    def obstacle(self, good: bool) -> TrackedObstacle:
        if good:
            p = np.array([0.0, 0.0, 1.5]) + self.rng.uniform(-5, 5, 3)
            return TrackedObstacle(p, self.rng.normal(size=3), float(self.pick((0.5, 0.75, 1.0))),
                                   float(self.pick((1.0, 5.0))), self.pick((None, True, False)))  # fmt: skip
        return TrackedObstacle(self.vec3(self.good(), 3.0), self.vec3(self.good()),
                               self.number(), self.number(), self.pick((None, True, "yes", 0, [])))  # fmt: skip

    def obstacles(self, good: bool) -> list[TrackedObstacle]:
        return [self.obstacle(good or self.good()) for _ in range(int(self.rng.integers(0, 8)))]

    def images(self, good: bool) -> list[DepthImage]:
        return [self.depth_image(good or self.good()) for _ in range(int(self.rng.integers(0, 5)))]

    def frame(self, now: float, good: bool) -> PerceptionFrame:
        stamp = None if good else self.stamp(now)
        return PerceptionFrame(
            stamp=now if stamp is None else stamp,
            depth=self.images(good) if self.rng.random() < 0.6 else [],
            points=self.points(good) if self.rng.random() < 0.4 else None,
            obstacles=self.obstacles(good) if self.rng.random() < 0.6 else None,
        )

    def policy_output(self):
        if self.good():
            return np.tanh(self.rng.normal(size=(1, 3)) * 2).astype(np.float32)
        k = self.rng.integers(8)
        if k <= 2:
            return self.cast(self.numbers((1, 3)))
        if k == 3:
            return self.numbers(self.pick(((3,), (1, 2), (2, 3), (), (1, 3, 1))))
        if k == 4:
            return [[self.number() for _ in range(3)]]
        if k == 5:
            return None
        return np.full((1, 3), self.pick((1e30, -1e30, 3.5e38, 7.0)), dtype=np.float64)

    def policy(self):
        return lambda s, l, d: self.policy_output()  # noqa: E741


@dataclass
class Oracle:
    """What the runtime was fed, for the necessary conditions of a non-hover setpoint: a goal;
    the last vehicle state finite and fresh; the last map (and tracker) input on time."""

    config: RuntimeConfig
    goal: bool = False
    last: dict[str, tuple[float, bool]] = field(default_factory=dict)

    def fed(self, source: str, stamp, now: float, content_ok: bool = True) -> None:
        eff = now if stamp is None else float(stamp)
        on_time = math.isfinite(eff) and eff <= now + self.config.future_tolerance_s
        self.last[source] = (eff, on_time and content_ok)

    def may_fly(self, now: float) -> bool:
        c = self.config
        need = [("state", c.max_state_age_s), ("map", c.max_map_age_s)]
        if c.require_tracker:
            need.append(("tracker", c.max_obstacle_age_s))
        for source, limit in need:
            stamp, ok = self.last.get(source, (-math.inf, False))
            if not ok or now - stamp > limit:
                return False
        return self.goal


def finite_state(p, v) -> bool:
    try:
        a = np.asarray(p, dtype=np.float64).reshape(3)
        b = np.asarray(v, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        return False
    return bool(np.isfinite(a).all() and np.isfinite(b).all())


@dataclass
class Stats:
    updates: int = 0
    steps: int = 0
    flew: int = 0
    hovered: int = 0
    guards: set[str] = field(default_factory=set)
    """Hover reasons seen, by their first two words ("map stamp", "stale map", ...)."""


def run_sequence(shield: int, require_tracker: bool, policy_seed: int, ops, stats: Stats,
                 cfg=CFG, wrap=None) -> None:  # fmt: skip
    """A ready runtime (good state, goal, map, tracker; ``shield``: 0 none, 1 the shield, N the
    memory shield of N images), then ``ops`` ``(kind, seed, good, stamp_offset)``, one control
    step after each; every setpoint is checked. ``cfg``: the policy's env configuration;
    ``wrap``: a wrapper around the garbage policy (to check what it is given)."""
    config = RuntimeConfig(
        require_tracker=require_tracker,
        shield=ShieldConfig.for_env(cfg) if shield else None,
        shield_memory=max(1, shield),
    )
    clock = [100.0]
    policy = Garbage(policy_seed, 0.7).policy()
    rt = OnboardRuntime(wrap(policy) if wrap else policy, cfg, config, clock=lambda: clock[0])
    oracle = Oracle(config)
    rt.update_state([0.0, 0.0, 1.5], [0.0, 0.0, 0.0])
    oracle.fed("state", None, clock[0])
    rt.set_goal([6.0, 2.0, 1.5])
    oracle.goal = True
    rt.update_points(np.zeros((0, 3)))
    oracle.fed("map", None, clock[0])
    rt.update_obstacles([])
    oracle.fed("tracker", None, clock[0])
    for kind, seed, good, offset in ops:
        g = Garbage(seed)
        now = clock[0]
        stamp = None if offset is None else now + offset
        stats.updates += 1
        if kind == "state":
            p, v = g.state(good)
            rt.update_state(p, v, stamp)
            oracle.fed("state", stamp, now, finite_state(p, v))
        elif kind == "depth":
            rt.update_depth(g.images(good), stamp)
            oracle.fed("map", stamp, now)
        elif kind == "points":
            rt.update_points(g.points(good), stamp)
            oracle.fed("map", stamp, now)
        elif kind == "obstacles":
            rt.update_obstacles(g.obstacles(good), stamp)
            oracle.fed("tracker", stamp, now)
        elif kind == "frame":
            frame = g.frame(now, good)
            rt.update_frame(frame)
            if frame.obstacles is not None:
                oracle.fed("tracker", frame.stamp, now)
            if frame.depth or frame.points is not None:
                oracle.fed("map", frame.stamp, now)
        elif kind == "goal":
            start = None if g.good() else g.vec3(good, 5.0)
            try:
                rt.set_goal(g.vec3(good, 5.0), start=start)
            except ValueError:  # documented: not a finite 3-vector
                pass
            else:
                oracle.goal = True
        elif kind == "tick":
            clock[0] += float(g.pick((0.0, 0.01, 0.05, 0.2, 0.6)))
        sp = rt.step()
        stats.steps += 1
        check_setpoint(sp, rt)
        if sp.hover:
            stats.hovered += 1
            stats.guards.update(" ".join(part.split()[:2]) for part in sp.reason.split("; "))
        else:
            stats.flew += 1
            assert oracle.may_fly(clock[0]), (kind, oracle.last, clock[0])
        clock[0] += 0.01


ops_strategy = st.tuples(
    st.sampled_from(KINDS), st.integers(0, 2**32 - 1), st.booleans(), st.sampled_from(STAMP_OFFSETS)
)


@settings(max_examples=RUNTIME_SEQUENCES, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])  # fmt: skip
@given(shield=st.sampled_from([0, 1, 5]), require_tracker=st.booleans(), policy_seed=st.integers(0, 2**32 - 1),
       ops=st.lists(ops_strategy, min_size=10, max_size=30))  # fmt: skip
def test_runtime_sequences_give_bounded_setpoints(
    shield, require_tracker, policy_seed, ops
) -> None:
    run_sequence(shield, require_tracker, policy_seed, ops, Stats())


def seeded_ops(rng) -> list:
    """``SEEDED_UPDATES`` ops for :func:`run_sequence`, mostly good updates, so that the runtime
    flies between the bad ones."""
    pick = lambda options: options[int(rng.integers(len(options)))]  # noqa: E731
    return [(pick(KINDS), int(rng.integers(2**32)), bool(rng.random() < 0.7),
             None if rng.random() < 0.6 else pick(STAMP_OFFSETS))
            for _ in range(SEEDED_UPDATES)]  # fmt: skip


def test_runtime_seeded_garbage(kernel_path) -> None:
    rng = np.random.default_rng(2024)
    stats = Stats()
    for i in range(SEEDED_SEQUENCES):
        ops = seeded_ops(rng)
        run_sequence((0, 1, 5)[i % 3], i % 4 < 2, int(rng.integers(2**32)), ops, stats)
    assert stats.updates == SEEDED_SEQUENCES * SEEDED_UPDATES
    # The fuzz reached both paths, and many guards.
    assert stats.flew > 0.1 * stats.steps and stats.hovered > 0.3 * stats.steps, stats
    assert stats.guards >= {"vehicle state", "non-finite vehicle", "state stamp", "stale vehicle",
                            "depth image", "point cloud", "map stamp", "stale map", "tracked obstacles",
                            "non-finite or", "tracker stamp", "stale obstacle", "policy output",
                            "non-finite observation"}, stats.guards  # fmt: skip


def test_runtime_seeded_garbage_with_a_pillar_list() -> None:
    """A policy with a pillar list (``static_tracked``): whenever it runs, it gets the ``static``
    rows as its fourth array, finite and of its shape, built from whatever the garbage put in the
    map (pillars of the good clouds among them); the setpoints stay bounded."""
    rng = np.random.default_rng(77)
    stats, lists = Stats(), []
    k = CFG_STATIC.static_tracked

    def wrap(policy):
        def checked(state, lidar, dynamic, static):
            assert static.shape == (1, k, 7) and static.dtype == np.float32
            assert np.isfinite(static).all() and set(np.unique(static[0, :, 6])) <= {0.0, 1.0}
            lists.append(int(static[0, :, 6].sum()))
            return policy(state, lidar, dynamic)

        return checked

    for i in range(STATIC_SEQUENCES):
        ops = seeded_ops(rng)
        run_sequence((0, 1, 5)[i % 3], i % 4 < 2, int(rng.integers(2**32)), ops, stats,
                     cfg=CFG_STATIC, wrap=wrap)  # fmt: skip
    assert stats.updates == STATIC_SEQUENCES * SEEDED_UPDATES
    assert stats.flew > 0.1 * stats.steps and len(lists) >= stats.flew
    assert sum(n > 0 for n in lists) > 0.3 * len(lists)  # the map held pillars near the vehicle


def test_runtime_absurd_but_finite_tracks_with_the_shield(kernel_path) -> None:
    """Tracked obstacles near the vehicle with huge (finite) heights, widths or velocities: the
    shield's arithmetic overflows; the setpoint must not."""
    rng = np.random.default_rng(5)
    huge = (1e38, -1e38, 3e38, 1e30, 1e20, -1e20, 1e10)
    for case in range(SHIELD_CASES):
        action = np.clip(rng.normal(size=(1, 3)), -1, 1).astype(np.float32)
        config = RuntimeConfig(shield=ShieldConfig.for_env(CFG), shield_memory=1 + 4 * (case % 2))
        rt = OnboardRuntime(lambda s, l, d, a=action: a, CFG, config, clock=lambda: 100.0)  # noqa: E741
        rt.update_state([0.0, 0.0, 1.5], [0.0, 0.0, 0.0])
        rt.set_goal([5.0, 0.0, 1.5])
        rt.update_points(np.zeros((0, 3)))
        tracks = []
        for _ in range(int(rng.integers(1, 4))):
            p, v = rng.uniform(-2, 2, 3) + [0.0, 0.0, 1.5], rng.normal(size=3)
            if rng.random() < 0.5:
                p[2] = rng.choice(huge)
            if rng.random() < 0.5:
                v[rng.integers(3)] = rng.choice(huge)
            width = abs(float(rng.choice(huge))) if rng.random() < 0.3 else 0.5
            tracks.append(TrackedObstacle(p, v, width, float(rng.choice([1.0, 5.0, 1e30]))))
        rt.update_obstacles(tracks)
        check_setpoint(rt.step(), rt)


def test_runtime_garbage_from_sensor_threads() -> None:
    """Sensor threads feed garbage while the control loop steps: no update raises, no setpoint
    is unbounded."""
    rt = OnboardRuntime(Garbage(7, 0.7).policy(), CFG, RuntimeConfig(require_tracker=False,
                        shield=ShieldConfig.for_env(CFG)))  # fmt: skip
    rt.update_state([0.0, 0.0, 1.5], [0.0, 0.0, 0.0])
    rt.set_goal([6.0, 2.0, 1.5])
    errors: list[BaseException] = []

    def feed(seed: int) -> None:
        g = Garbage(seed)
        try:
            for _ in range(THREAD_UPDATES):
                now = time.monotonic()
                kind = g.pick(("state", "depth", "points", "obstacles", "frame"))
                good = g.good()
                if kind == "state":
                    rt.update_state(*g.state(good), g.stamp(now))
                elif kind == "depth":
                    rt.update_depth(g.images(good), g.stamp(now))
                elif kind == "points":
                    rt.update_points(g.points(good), g.stamp(now))
                elif kind == "obstacles":
                    rt.update_obstacles(g.obstacles(good), g.stamp(now))
                else:
                    rt.update_frame(g.frame(now, good))
        except BaseException as err:  # noqa: BLE001 -- reported below
            errors.append(err)

    threads = [threading.Thread(target=feed, args=(seed,)) for seed in range(THREADS)]
    for t in threads:
        t.start()
    steps = 0
    while steps < THREAD_STEPS or any(t.is_alive() for t in threads):
        check_setpoint(rt.step(), rt)
        steps += 1
    for t in threads:
        t.join()
    assert not errors, errors


def test_set_goal_rejects_garbage_with_a_clear_error() -> None:
    rt = OnboardRuntime(lambda s, l, d: np.zeros((1, 3), np.float32), CFG)  # noqa: E741
    for goal in ([np.nan, 0, 1], [1e400, 0, 1], [1, 2], "abc", None, [[1, 2], [3]]):
        with pytest.raises(ValueError, match="goal"):
            rt.set_goal(goal, start=[0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="start"):
        rt.set_goal([1.0, 2.0, 1.0], start=[np.nan, 0.0, 0.0])
    with pytest.raises(ValueError, match="before the first vehicle state"):
        rt.set_goal([1.0, 2.0, 1.0])
    assert rt.goal is None and rt.step().reason == "no goal set"


# ---------------------------------------------------------------------- perception link
JSON_KEYS = ("stamp", "depth", "points", "obstacles", "truth", "shape", "dtype", "scale", "fx", "fy",
             "cx", "cy", "R", "t", "offset", "nbytes", "n", "p", "v", "width", "height", "cuboid")  # fmt: skip
JSON_LITERALS = ("NaN", "Infinity", "-Infinity", "1e400", "-1e400", "0", "-1", "1e9",
                 "123456789012345678901234567890", '"uint16"', '"float32"', '"x"', "null", "true",
                 "[]", "{}")  # fmt: skip


def random_json(rng: np.random.Generator, depth: int = 0) -> str:
    """Random JSON text (Python's json reads NaN, Infinity and 1e400 as floats), keys mostly the
    frame header's own."""
    r = rng.random()
    if depth > 3 or r < 0.45:
        return (
            JSON_LITERALS[int(rng.integers(len(JSON_LITERALS)))]
            if rng.random() < 0.7
            else repr(float(rng.normal() * 100))
        )
    if r < 0.7:
        return (
            "["
            + ",".join(random_json(rng, depth + 1) for _ in range(int(rng.integers(0, 5))))
            + "]"
        )
    keys = [JSON_KEYS[int(rng.integers(len(JSON_KEYS)))] for _ in range(int(rng.integers(0, 6)))]
    return "{" + ",".join(f'"{k}":{random_json(rng, depth + 1)}' for k in keys) + "}"


def body_from_header(header: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(header)) + header + payload


def decode_or_reject(body: bytes) -> PerceptionFrame | None:
    """``decode_frame``: a frame, or ``ValueError`` (None) -- nothing else may come out."""
    try:
        return decode_frame(body)
    except ValueError:
        return None


class FrameSink:
    """A ready runtime that takes every decoded frame, stepping after each (its clock stands at
    100.05 s: frames stamped 100 s, as the valid ones, are fresh)."""

    def __init__(self) -> None:
        self.rt = OnboardRuntime(Garbage(3, 0.8).policy(), CFG, RuntimeConfig(require_tracker=False,
                                 shield=ShieldConfig.for_env(CFG)), clock=lambda: 100.05)  # fmt: skip
        self.rt.update_state([0.0, 0.0, 1.5], [0.0, 0.0, 0.0])
        self.rt.set_goal([6.0, 2.0, 1.5])
        self.frames = self.flew = 0

    def take(self, frame: PerceptionFrame) -> None:
        self.frames += 1
        self.rt.update_state([0.0, 0.0, 1.5], [0.0, 0.0, 0.0])
        self.rt.update_frame(frame)
        sp = self.rt.step()
        check_setpoint(sp, self.rt)
        self.flew += not sp.hover


def valid_frame(g: Garbage, now: float = 100.0, mark: int = 0) -> PerceptionFrame:
    return PerceptionFrame(stamp=now, depth=g.images(True)[:2], points=g.points(True)[:20],
                           obstacles=g.obstacles(True), truth={"good": mark, "mode": "HOLD"})  # fmt: skip


def test_decode_random_bytes() -> None:
    rng = np.random.default_rng(11)
    sink = FrameSink()
    kinds = {"raw": 0, "prefixed": 0, "json": 0, "nested": 0}
    for i in range(DECODE_RANDOM):
        payload = rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8).tobytes()
        k = i % 10
        if k < 3:
            body, kind = payload, "raw"
        elif k < 5:  # a plausible header length, then random bytes
            hlen = int(rng.integers(0, len(payload) + 1))
            body, kind = struct.pack(">I", hlen) + payload, "prefixed"
        elif k < 9:
            body, kind = body_from_header(random_json(rng).encode(), payload), "json"
        else:  # absurd nesting: json's recursion limit
            n = int(rng.integers(1, 3000))
            body, kind = (
                body_from_header(b'{"stamp":1,"truth":' + b"[" * n + b"]" * n + b"}", b""),
                "nested",
            )
        kinds[kind] += 1
        frame = decode_or_reject(body)
        if frame is not None:
            sink.take(frame)
    assert sum(kinds.values()) == DECODE_RANDOM and min(kinds.values()) > 0


def test_decode_mutated_valid_frames() -> None:
    rng = np.random.default_rng(12)
    g = Garbage(12)
    sink = FrameSink()
    originals = [encode_frame(valid_frame(g), depth_as_uint16=bool(i % 2))[4:] for i in range(20)]
    rejected = 0
    for i in range(DECODE_MUTATED):
        body = bytearray(originals[i % len(originals)])
        k = rng.integers(5)
        if k == 0:  # bit flips
            for pos in rng.integers(0, len(body), int(rng.integers(1, 9))):
                body[pos] ^= 1 << int(rng.integers(8))
        elif k == 1:  # truncated
            body = body[: int(rng.integers(0, len(body)))]
        elif k == 2:  # random bytes inserted
            pos = int(rng.integers(0, len(body)))
            body[pos:pos] = rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8).tobytes()
        elif k == 3:  # a header byte replaced by a JSON token's first byte
            hlen = struct.unpack(">I", bytes(body[:4]))[0]
            pos = 4 + int(rng.integers(0, hlen))
            body[pos] = b'-0e9[{",:N'[int(rng.integers(10))]
        else:  # splice two frames
            other = originals[int(rng.integers(len(originals)))]
            cut = int(rng.integers(0, min(len(body), len(other))))
            body = body[:cut] + other[cut:]
        frame = decode_or_reject(bytes(body))
        if frame is None:
            rejected += 1
        else:
            sink.take(frame)
    assert 0 < rejected < DECODE_MUTATED and sink.flew > 0


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=4)
    | st.sampled_from(["uint16", "float32"]),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.sampled_from(JSON_KEYS), inner, max_size=4),
    max_leaves=12,
)  # fmt: skip
small_numbers = st.one_of(st.integers(-3, 64), st.floats(), json_values)
depth_specs = st.fixed_dictionaries(
    {"shape": st.one_of(st.lists(small_numbers, min_size=2, max_size=2), json_values),
     "dtype": st.sampled_from(["uint16", "float32", "int8"]) | json_values,
     "scale": small_numbers, "fx": small_numbers, "fy": small_numbers, "cx": small_numbers, "cy": small_numbers,
     "R": st.lists(small_numbers, min_size=9, max_size=9) | json_values,
     "t": st.lists(small_numbers, min_size=3, max_size=3) | json_values,
     "offset": small_numbers, "nbytes": small_numbers},
)  # fmt: skip
obstacle_specs = st.fixed_dictionaries(
    {"p": st.lists(small_numbers, min_size=3, max_size=3) | json_values,
     "v": st.lists(small_numbers, min_size=3, max_size=3) | json_values,
     "width": small_numbers, "height": small_numbers},
    optional={"cuboid": json_values},
)  # fmt: skip
headers = st.fixed_dictionaries(
    {"stamp": small_numbers},
    optional={"depth": st.lists(depth_specs, max_size=3) | json_values,
              "points": st.fixed_dictionaries({"n": small_numbers, "offset": small_numbers,
                                               "nbytes": small_numbers}) | json_values,
              "obstacles": st.lists(obstacle_specs, max_size=4) | json_values, "truth": json_values},
)  # fmt: skip


@settings(max_examples=DECODE_HEADERS, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])  # fmt: skip
@given(header=headers, payload=st.binary(max_size=512))
def test_decode_garbage_headers(header, payload) -> None:
    frame = decode_or_reject(body_from_header(json.dumps(header).encode(), payload))
    if frame is not None:
        FrameSink().take(frame)


@contextlib.contextmanager
def perception_server():
    """A TCP server on loopback; yields ``(port, queue of connection scripts)``: each script is a
    function that gets the accepted connection."""
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    srv.settimeout(10.0)
    scripts: list = []
    stop = threading.Event()

    def serve() -> None:
        while scripts and not stop.is_set():
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            with conn:
                scripts.pop(0)(conn)

    thread = threading.Thread(target=serve, daemon=True)
    try:
        yield srv.getsockname()[1], scripts, thread
    finally:
        stop.set()
        srv.close()
        thread.join(timeout=5.0)


def test_perception_client_survives_a_garbage_stream() -> None:
    g, rng = Garbage(21), np.random.default_rng(21)
    good = [encode_frame(valid_frame(g, mark=i + 1)) for i in range(3)]
    boom = encode_frame(PerceptionFrame(stamp=1.0, truth={"boom": True}))
    got: list[PerceptionFrame] = []
    errors: list[str] = []
    done = threading.Event()

    def on_frame(frame: PerceptionFrame) -> None:
        if frame.truth.get("boom"):
            raise RuntimeError("handler failed")
        if frame.truth.get("good"):  # (a random header may decode too)
            got.append(frame)

    def first(conn) -> None:  # good, garbage, a raising handler, good, then an absurd length
        conn.sendall(good[0])
        for _ in range(CLIENT_GARBAGE_FRAMES):
            body = rng.integers(0, 256, int(rng.integers(0, 400)), dtype=np.uint8).tobytes()
            if rng.random() < 0.5:
                body = body_from_header(random_json(rng).encode(), body)
            conn.sendall(struct.pack(">I", len(body)) + body)
        conn.sendall(boom + good[1] + struct.pack(">I", MAX_FRAME_BYTES + 1) + b"\0" * 64)
        time.sleep(0.3)

    def second(conn) -> None:  # a frame cut in the middle, then the connection drops
        conn.sendall(good[2][: len(good[2]) // 2])

    def third(conn) -> None:
        conn.sendall(good[0])
        done.wait(5.0)

    with perception_server() as (port, scripts, thread):
        scripts.extend([first, second, third])
        thread.start()
        client = PerceptionClient("127.0.0.1", port, on_frame, errors.append).start()
        try:
            end = time.monotonic() + 20.0
            while len(got) < 3 and time.monotonic() < end:
                time.sleep(0.02)
            assert client._thread.is_alive()
        finally:
            done.set()
            client.close()
    assert len(got) == 3, errors[-5:]
    assert any("handler failed" in e for e in errors)
    assert any("too large" in e for e in errors)
    assert sum("bad perception frame dropped" in e for e in errors) > CLIENT_GARBAGE_FRAMES // 2


# ---------------------------------------------------------------------- MAVLink: the simulated vehicle
@pytest.fixture
def vehicle():
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    gcs.settimeout(0.5)
    sim = SimVehicle(
        SimVehicleConfig(connect=f"127.0.0.1:{gcs.getsockname()[1]}", perception_port=-1)
    )
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    yield sim, sender, gcs
    sim.close()
    sender.close()
    gcs.close()


class SimChecker:
    """Runs the vehicle's physics by hand between message batches and checks its state."""

    def __init__(self, sim: SimVehicle) -> None:
        self.sim = sim
        self.limit = sim.env_cfg.max_acceleration * 0.01 * (1 + 1e-9) + 1e-12

    def physics(self, steps: int = 5) -> None:
        sim = self.sim
        for _ in range(steps):
            before = sim.vel.copy()
            sim._physics(0.01)
            assert np.isfinite(sim.pos).all() and np.isfinite(sim.vel).all(), sim.params
            dv = np.linalg.norm(sim.vel - before)
            assert not sim.vel.any() or dv <= self.limit, (before, sim.vel)
            assert math.isfinite(sim.yaw)
            for sp in (sim.setpoint_vel, sim.setpoint_pos):
                assert sp is None or np.isfinite(sp).all()
            assert sim.mode_name in px4.MODE_NAMES.values()


def mutated_packets(rng: np.random.Generator, mav) -> list[bytes]:
    msgs = [
        M.MAVLink_set_position_target_local_ned_message(0, 1, 1, M.MAV_FRAME_LOCAL_NED, 0b0000_1101_1100_0111,
                                                         0, 0, 0, 1.0, 0.5, 0.0, 0, 0, 0, 0.3, 0),
        M.MAVLink_command_long_message(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0),
        M.MAVLink_command_long_message(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, 6, 0, 0, 0, 0, 0),
        M.MAVLink_param_set_message(1, 1, b"MPC_XY_VEL_MAX", 5.0, M.MAV_PARAM_TYPE_REAL32),
        M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3),
    ]  # fmt: skip
    return [m.pack(mav) for m in msgs]


def random_datagram(rng: np.random.Generator, packets: list[bytes]) -> bytes:
    k = rng.integers(6)
    noise = rng.integers(0, 256, int(rng.integers(0, 280)), dtype=np.uint8).tobytes()
    if k <= 1:
        return noise
    if k == 2:  # MAVLink 1 / 2 start byte and a length that may or may not fit
        return bytes([int(rng.choice([0xFE, 0xFD])), int(rng.integers(256))]) + noise
    pkt = bytearray(packets[int(rng.integers(len(packets)))])
    if k == 3:
        for pos in rng.integers(0, len(pkt), int(rng.integers(1, 4))):
            pkt[pos] ^= 1 << int(rng.integers(8))
        return bytes(pkt)
    if k == 4:
        return bytes(pkt[: int(rng.integers(0, len(pkt)))]) + noise[:8]
    return noise[:20] + bytes(pkt) + noise[20:40]  # a valid packet among junk


def test_sim_vehicle_random_datagrams(vehicle) -> None:
    sim, sender, gcs = vehicle
    rng = np.random.default_rng(31)
    packets = mutated_packets(rng, M.MAVLink(None, srcSystem=255, srcComponent=190))
    check = SimChecker(sim)
    for i in range(SIM_DATAGRAMS):
        sender.sendto(random_datagram(rng, packets), sim.mavlink_address)
        if i % 50 == 49:
            sim._receive()
            check.physics()
    sim._receive()
    assert sim.bad_messages > 0
    # Still the vehicle it was: it answers a command.
    gcs.setblocking(False)
    with contextlib.suppress(BlockingIOError):
        while True:  # the replies to the garbage
            gcs.recvfrom(65535)
    gcs.settimeout(0.5)
    mav = M.MAVLink(None, srcSystem=255, srcComponent=190)
    sender.sendto(M.MAVLink_command_long_message(1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0,
                                                 M.MAVLINK_MSG_ID_HOME_POSITION, 0, 0, 0, 0, 0, 0).pack(mav),
                  sim.mavlink_address)  # fmt: skip
    time.sleep(0.05)
    sim._receive()
    parser = M.MAVLink(None)
    acks = []
    with contextlib.suppress(TimeoutError):
        while not acks:
            data, _ = gcs.recvfrom(65535)
            acks += [m for m in parser.parse_buffer(data) or [] if m.get_type() == "COMMAND_ACK"
                     and m.command == M.MAV_CMD_REQUEST_MESSAGE]  # fmt: skip
    assert acks and acks[0].result == M.MAV_RESULT_ACCEPTED


def garbage_message(g: Garbage):
    def f() -> float:  # within float32, as the fields are (1e300 -> inf)
        with np.errstate(over="ignore"):
            return float(np.float32(g.number()))

    k = g.rng.integers(7)
    if k <= 1:
        return M.MAVLink_set_position_target_local_ned_message(
            0, int(g.pick((0, 1, 2))), 1, int(g.pick((1, 7, 8, 9, 0))), int(g.rng.integers(0, 65536)),
            *[f() for _ in range(11)])  # fmt: skip
    if k <= 4:
        cmds = (M.MAV_CMD_COMPONENT_ARM_DISARM, M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_NAV_LAND, M.MAV_CMD_DO_SET_MODE,
                M.MAV_CMD_REQUEST_MESSAGE, M.MAV_CMD_SET_MESSAGE_INTERVAL, int(g.rng.integers(0, 65536)))  # fmt: skip
        command = int(g.pick(cmds))
        p = [f() for _ in range(7)]
        if g.good():  # plausible enough to change the vehicle's state
            p[:3] = [1.0, float(g.pick((4, 6, 3, 2, 7))), float(g.pick((2, 3, 6, 0)))]
        if k <= 3:
            return M.MAVLink_command_long_message(1, int(g.pick((0, 1, 2))), command, 0, *p)
        return M.MAVLink_command_int_message(1, 1, int(g.pick((1, 0, 6))), command, 0, 0, *p[:4],
                                             int(g.rng.integers(-2**31, 2**31)), int(g.rng.integers(-2**31, 2**31)), p[6])  # fmt: skip
    if k == 5:
        name = g.pick([*px4.DEFAULT_PARAMS, "NOPE", ""]).encode()
        return M.MAVLink_param_set_message(1, 1, name, f(), M.MAV_PARAM_TYPE_REAL32)
    name = g.pick([*px4.DEFAULT_PARAMS, "X"]).encode()
    return M.MAVLink_param_request_read_message(1, 1, name, int(g.rng.integers(-32768, 32768)))


def test_sim_vehicle_garbage_fields_in_valid_messages(vehicle) -> None:
    sim, sender, _ = vehicle
    g = Garbage(32, p_good=0.6)
    mav = M.MAVLink(None, srcSystem=255, srcComponent=190)
    check = SimChecker(sim)
    for i in range(SIM_MESSAGES):
        sender.sendto(garbage_message(g).pack(mav), sim.mavlink_address)
        if i % 10 == 9:
            sim._receive()
            check.physics()
    assert sim.messages_received > 0.9 * SIM_MESSAGES
    assert sim.armed_time > -math.inf and any("param MPC_XY_VEL_MAX" in e for e in sim.events)


# ---------------------------------------------------------------------- MAVLink: fly's side (MAVSDK)
def test_mavsdk_survives_random_datagrams() -> None:
    """``fly``'s MAVLink parser is MAVSDK's C++ core: random datagrams into its UDP port, beside a
    live vehicle; telemetry keeps coming, finite."""
    pytest.importorskip("mavsdk")
    from safenav.deploy.demo import free_port
    from safenav.deploy.fly import MavsdkLink

    port = free_port()
    sim = SimVehicle(SimVehicleConfig(connect=f"127.0.0.1:{port}", perception_port=-1)).start()
    link = MavsdkLink(f"udpin://127.0.0.1:{port}")
    junk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        link.connect(20.0)
        end = time.monotonic() + 10.0
        while link.latest() is None and time.monotonic() < end:
            time.sleep(0.05)
        rng = np.random.default_rng(41)
        packets = mutated_packets(rng, M.MAVLink(None, srcSystem=42, srcComponent=1))
        for i in range(MAVSDK_DATAGRAMS):
            junk.sendto(random_datagram(rng, packets), ("127.0.0.1", port))
            if i % 25 == 24:
                time.sleep(0.001)  # paced, so that the socket's buffer does not drop them
        time.sleep(0.3)
        tel = link.latest()
        assert tel is not None and time.monotonic() - tel.stamp < 0.5
        assert np.isfinite(tel.position_ned).all() and np.isfinite(tel.velocity_ned).all()
        assert link.flight_mode() == "HOLD" and not link.in_air()
    finally:
        junk.close()
        link.close()
        sim.stop()


# ---------------------------------------------------------------------- the flight loop
class GarbageLink:
    """A vehicle link whose telemetry is garbage now and then; records every setpoint sent."""

    url = "garbage://"

    def __init__(self, seed: int, dropouts: bool) -> None:
        self.g = Garbage(seed, p_good=0.85)
        self.dropouts = dropouts
        self.sent: list[tuple[np.ndarray, float]] = []
        self.mode = "HOLD"
        self.last_stamp = time.monotonic()

    def connect(self, timeout_s):
        pass

    def wait_ready(self, timeout_s):
        pass

    def latest(self):
        from safenav.deploy.fly import Telemetry

        g, now = self.g, time.monotonic()
        if self.dropouts and g.rng.random() < 0.01:  # nothing yet, or a stale sample: link lost
            return None if g.good() else Telemetry(np.zeros(3), np.zeros(3), now - 5.0)
        stamp = now
        if not g.good():  # duplicated, backwards, future, non-finite
            stamp = g.pick((self.last_stamp, now - 0.1, now + 0.05, now + 5.0, math.nan, math.inf))
        self.last_stamp = stamp if math.isfinite(stamp) else self.last_stamp
        pos = np.array([0.0, 0.0, -1.5]) + g.rng.normal(size=3) * 0.1
        vel = g.rng.normal(size=3) * 0.3
        if not g.good():
            pos = g.numbers((3,))
        if not g.good():
            vel = g.numbers((3,))
        return Telemetry(pos, vel, stamp)

    def flight_mode(self):
        return self.mode

    def in_air(self):
        return False

    def arm(self):
        pass

    def takeoff(self, altitude_m):
        pass

    def start_offboard(self, yaw_deg):
        self.mode = "OFFBOARD"

    def send_velocity_ned(self, v_ned, yaw_deg):
        self.sent.append((np.array(v_ned, dtype=float), float(yaw_deg)))

    def hold(self):
        self.mode = "HOLD"

    def land(self):
        pass

    def close(self):
        pass


def test_flight_loop_with_garbage_telemetry_and_perception() -> None:
    from safenav.deploy.fly import FlightAborted, FlightController, FlyConfig

    ticks, moving, outcomes = 0, 0, []
    for i in range(FLIGHTS):
        g = Garbage(100 + i, p_good=0.8)
        rt = OnboardRuntime(g.policy(), CFG, RuntimeConfig(require_tracker=i % 2 == 0,
                            shield=ShieldConfig.for_env(CFG) if i % 3 else None))  # fmt: skip
        link = GarbageLink(200 + i, dropouts=i >= FLIGHTS - 3)
        ctl = FlightController(rt, link, FlyConfig(goal=(20.0, 5.0, 1.5), rate_hz=100.0, takeoff_altitude=0.0,
                                                   max_flight_s=0.6, link_timeout_s=0.3, ready_timeout_s=2.0,
                                                   takeoff_timeout_s=2.0))  # fmt: skip
        stop, errors = threading.Event(), []

        def perceive(seed: int, ctl: FlightController, stop: threading.Event, errors: list) -> None:
            """The perception client's thread."""
            p = Garbage(seed)
            try:
                while not stop.is_set():
                    ctl._on_frame(p.frame(time.monotonic(), p.rng.random() < 0.8))
                    time.sleep(0.005)
            except BaseException as err:  # noqa: BLE001 -- reported below
                errors.append(err)

        feeder = threading.Thread(target=perceive, args=(300 + i, ctl, stop, errors), daemon=True)
        feeder.start()
        try:
            ctl.fly()
            outcomes.append("reached")
        except FlightAborted as err:
            outcomes.append(str(err).split(":")[0])
        finally:
            stop.set()
            feeder.join()
        assert not errors, errors
        for v_ned, yaw_deg in link.sent:
            assert_bounded(ned_to_enu(v_ned), v_ned, rt.goal_yaw, hover=not v_ned.any())
            assert math.isfinite(yaw_deg)
        assert link.sent and not link.sent[-1][0].any()  # the last word is a stop
        ticks += ctl.log.ticks
        moving += sum(bool(v.any()) for v, _ in link.sent)
    assert ticks >= MIN_FLIGHT_TICKS, (ticks, outcomes)
    flown = outcomes.count("goal not reached within 1 s")  # flew to the end
    assert flown >= FLIGHTS // 2, outcomes
    print(f"{FLIGHTS} flights: {ticks} ticks, {moving} moving setpoints, outcomes {outcomes}")
    assert moving > 0.1 * ticks, (moving, ticks)  # it flew between the garbage, not only hovered


@pytest.mark.parametrize("name, value", [("goal", (math.nan, 0.0, 1.5)), ("goal", (1e400, 0.0, 1.5)),
                                         ("goal", (1.0, 2.0)), ("origin", (0.0, math.inf, 0.0))])  # fmt: skip
def test_flight_controller_rejects_garbage_goal_or_origin(name, value) -> None:
    from safenav.deploy.fly import FlightController, FlyConfig

    rt = OnboardRuntime(lambda s, l, d: np.zeros((1, 3), np.float32), CFG)  # noqa: E741
    kwargs = {"goal": (1.0, 2.0, 1.5), name: value}
    with pytest.raises(SafenavError, match=name):
        FlightController(rt, GarbageLink(0, False), FlyConfig(**kwargs))


def test_docstring_counts_match_the_tests() -> None:
    doc = __doc__ or ""
    for n in (RUNTIME_SEQUENCES, SHIELD_CASES, SEEDED_SEQUENCES * SEEDED_UPDATES,
              STATIC_SEQUENCES * SEEDED_UPDATES, THREADS * THREAD_UPDATES,
              DECODE_RANDOM, DECODE_MUTATED, DECODE_HEADERS, CLIENT_GARBAGE_FRAMES, SIM_DATAGRAMS,
              SIM_MESSAGES, MAVSDK_DATAGRAMS, FLIGHTS, MIN_FLIGHT_TICKS):  # fmt: skip
        assert f"{n:,}" in doc, n


@pytest.mark.parametrize(("v", "width", "height"), [((1e30, 0.0, 0.0), 0.5, 1.0), ((0.0, 0.0, 0.0), 1e30, 1.0),
                                                    ((0.0, 25.0, 0.0), 0.5, 1.0), ((0.0, 0.0, 0.0), 0.5, 60.0)])  # fmt: skip
def test_runtime_rejects_implausible_tracks(v, width, height) -> None:
    """Absurd speeds or sizes are tracker faults (hover), not obstacles that overflow the shield."""
    rt = OnboardRuntime(lambda s, l, d: np.full((1, 3), 0.5, np.float32), CFG,  # noqa: E741
                        RuntimeConfig(shield=ShieldConfig.for_env(CFG)), clock=lambda: 100.0)  # fmt: skip
    rt.update_state([0.0, 0.0, 1.5], [0.0, 0.0, 0.0])
    rt.set_goal([5.0, 0.0, 1.5])
    rt.update_points(np.zeros((0, 3)))
    rt.update_obstacles([TrackedObstacle(np.array([2.0, 0.0, 1.5]), np.array(v), width, height)])
    sp = rt.step()
    assert sp.hover and "faster than" in sp.reason
    rt.update_obstacles([TrackedObstacle(np.array([2.0, 0.0, 1.5]), np.zeros(3), 0.5, 1.0)])
    assert not rt.step().hover
