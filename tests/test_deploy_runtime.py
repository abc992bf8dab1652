"""The onboard runtime: the observation it builds from sensor data is the env's observation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from safenav.deploy.camera import PinholeCamera, render_depth, rig_poses
from safenav.deploy.frames import (
    enu_to_ned,
    local_ned_to_world,
    ned_to_enu,
    world_to_local_ned,
    yaw_enu_to_ned,
)
from safenav.deploy.perception_link import (
    DepthImage,
    PerceptionFrame,
    TrackedObstacle,
    decode_frame,
    encode_frame,
)
from safenav.deploy.runtime import OnboardRuntime, RuntimeConfig
from safenav.envs import SafeNavVectorEnv, make_config
from safenav.envs.sensors import (
    RangeImageSpec,
    pillar_clearance,
    quantize_heights,
    raycast_height_map,
)
from safenav.envs.world import height_map

pytestmark = pytest.mark.usefixtures("one_thread")


def const_policy(value=(0.5, 0.0, 0.0)):
    return lambda s, l, d: np.asarray([value], dtype=np.float32)  # noqa: E741


@pytest.fixture(scope="module")
def easy_env():
    cfg = make_config("easy")
    env = SafeNavVectorEnv(4, config=cfg, output="torch")
    env.reset(seed=3)
    return env


def pillar_boxes(env, w=0):
    ps = env.n_static
    xy, h, top = env.pillar_xy[w, :ps], env.pillar_half[w, :ps], env.pillar_height[w, :ps]
    lo = torch.cat([xy - h[:, None], torch.zeros(ps, 1)], -1)
    hi = torch.cat([xy + h[:, None], top[:, None]], -1)
    return lo, hi


def tracked(env, w):
    nd = env.n_dynamic
    return [
        TrackedObstacle(env.dyn_pos[w, i].numpy(), env.dyn_vel[w, i].numpy(), float(env.dyn_width[w, i]),
                        1.0 if bool(env.dyn_is_cuboid[w, i]) else 5.0, bool(env.dyn_is_cuboid[w, i]))
        for i in range(nd)
    ]  # fmt: skip


def test_observation_equals_the_envs_given_its_map_and_obstacles() -> None:
    """Same map, same obstacles, same state -> the runtime's observation is the env's, exactly
    for the range image (same ray caster) and to float precision for the features."""
    cfg = make_config("easy", num_dynamic=40)  # many moving obstacles: tracked rows are non-zero
    env = SafeNavVectorEnv(4, config=cfg, output="torch", num_worlds=2)
    env.reset(seed=5)
    gen = torch.Generator().manual_seed(0)
    g2 = env.grid.size**2
    nonzero_dynamic = 0
    for _ in range(15):
        obs, _, term, trunc, _ = env.step(torch.rand(4, 3, generator=gen) * 2 - 1)
        for i in range(4):
            if bool(term[i] | trunc[i]):
                continue
            w = int(env.world_idx[i])
            rt = OnboardRuntime(const_policy(), cfg, RuntimeConfig(require_tracker=True))
            rt.map.cast_map = env.heights[w * g2 : (w + 1) * g2].clone()
            rt.update_state(env.pos[i].numpy(), env.vel[i].numpy())
            rt.set_goal(env.goal[i].numpy(), start=env.start[i].numpy())
            rt.update_obstacles(tracked(env, w))
            mine, _ = rt.observation()
            assert torch.equal(mine["lidar"][0], obs["lidar"][i])
            torch.testing.assert_close(mine["state"][0], obs["state"][i], atol=2e-6, rtol=1e-5)
            torch.testing.assert_close(mine["dynamic"][0], obs["dynamic"][i], atol=2e-6, rtol=1e-5)
            nonzero_dynamic += int(obs["dynamic"][i].abs().sum() > 0)
    assert nonzero_dynamic > 0


def _static_rows_checked(env, obs, ids, where: str) -> int:
    """For each env ``i`` in ``ids``: a runtime given the env's map, position and goal frame
    builds the env's ``static`` rows (the same to float precision: its footprints' centres are
    offset from its window's corner, the env's from its map's); returns the rows of pillars."""
    g2 = env.grid.size**2
    rows = 0
    for i in ids:
        w = int(env.world_idx[i])
        rt = OnboardRuntime(const_policy(), env.cfg, RuntimeConfig(require_tracker=False))
        rt.map.cast_map = env.heights[w * g2 : (w + 1) * g2].clone()
        rt.update_state(env.pos[i].numpy(), env.vel[i].numpy())
        rt.set_goal(env.goal[i].numpy(), start=env.start[i].numpy())
        mine, _ = rt.observation()
        assert mine["static"].shape == (1, env.cfg.static_tracked, 7)
        torch.testing.assert_close(mine["static"][0], obs["static"][i], atol=2e-6, rtol=0,
                                   msg=lambda m, i=i: f"{where}, env {i}: {m}")  # fmt: skip
        rows += int(obs["static"][i, :, 6].sum())
    return rows


def test_static_rows_equal_the_envs_from_the_map() -> None:
    """A policy with a pillar list (``static_tracked``): the runtime's rows, built from a window
    of its map, are those the env builds from its whole map with ``static_source="map"``, when
    its map is the env's: anywhere in the dense paper arena (starts drawn over all of it, up to
    the wall, some in or against pillars), over steps (the goal frame fixed at the start)."""
    cfg = make_config("paper", static_tracked=8, static_source="map")
    n = 16
    env = SafeNavVectorEnv(n, config=cfg, output="torch", num_worlds=2)
    env.reset(seed=7)
    rng = np.random.default_rng(1)
    lim = cfg.half - 0.2
    starts = np.c_[rng.uniform(-lim, lim, (n, 2)), rng.uniform(0.3, 3.5, n)]
    goals = np.c_[rng.uniform(-lim, lim, (n, 2)), rng.uniform(0.5, 2.5, n)]
    obs, _ = env.reset(options={"starts": starts, "goals": goals})
    rows = _static_rows_checked(env, obs, range(n), "at the start")
    gen = torch.Generator().manual_seed(0)
    for step in range(3):
        obs, _, term, trunc, _ = env.step(torch.rand(n, 3, generator=gen) * 2 - 1)
        live = [i for i in range(n) if not bool(term[i] | trunc[i])]
        rows += _static_rows_checked(env, obs, live, f"step {step}")
    assert rows >= 100  # dense: most rows hold a pillar


def test_static_rows_of_touching_pillars_and_by_the_wall() -> None:
    """Touching pillars are one footprint for both (env and runtime); the geofence wall is none,
    and a pillar against it is one; an empty neighbourhood gives zero rows."""
    from safenav.envs.world import world_from_obstacles

    cfg = make_config("easy", static_tracked=4, static_source="map")
    env = SafeNavVectorEnv(3, config=cfg, output="torch", num_worlds=1)
    pillars = [(1.0, 0.0, 0.8, 2.0), (1.8, 0.0, 0.8, 3.0), (1.4, 0.6, 0.4, 1.0),  # one group
               (-1.5, 1.0, 0.4, 1.5), (9.7, 9.0, 0.6, 2.5), (9.0, 9.7, 0.6, 2.5)]  # fmt: skip
    env.set_worlds([world_from_obstacles(cfg, pillars)])
    starts = [[0.0, 0.0, 1.5], [8.8, 8.7, 1.0], [-7.0, -7.0, 1.0]]
    goals = [[5.0, 3.0, 1.5], [0.0, 8.0, 1.5], [7.0, -7.0, 1.5]]
    obs, _ = env.reset(options={"starts": starts, "goals": goals})
    assert _static_rows_checked(env, obs, range(3), "hand-made") == 2 + 2
    # the group of three: one footprint of half side 0.8 (its 1.6 m box), its tallest top
    merged = obs["static"][0, :, 4].argmax()
    assert obs["static"][0, merged, 4] * 0.4 == pytest.approx(0.8, abs=1e-6)
    assert obs["static"][0, merged, 5] * 4.0 == pytest.approx(3.0 - 1.5, abs=0.03)
    assert obs["static"][2].eq(0).all()


def test_runtime_passes_the_pillar_list_to_the_policy() -> None:
    """The policy gets ``static`` as its fourth array (a policy without it, three: every other
    test); a pillar the depth / points put in the map is a row; the observation guard covers it."""
    cfg = make_config("easy", static_tracked=3, static_source="map")
    seen = []

    def policy(*arrays):
        seen.append([a.copy() for a in arrays])
        return np.zeros((1, 3), dtype=np.float32)

    rt = OnboardRuntime(policy, cfg, RuntimeConfig(require_tracker=False))
    rt.update_state([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    rt.set_goal([0.0, 5.0, 1.0])  # goal frame: x north (world +y), y west (world -x)
    # points on the faces of a 0.4 m pillar 2 m east, 1.5 m tall (just inside: its 4 x 4 cells)
    s = np.linspace(-0.19, 0.19, 9)
    face = [[2.0 + a, b, z] for a in s for b in (-0.19, 0.19) for z in (0.5, 1.0, 1.5)]
    face += [[2.0 + a, b, z] for a in (-0.19, 0.19) for b in s for z in (0.5, 1.0, 1.5)]
    rt.update_points(np.array(face))
    sp = rt.step()
    assert not sp.hover and len(seen) == 1 and len(seen[0]) == 4
    static = seen[0][3]
    assert static.shape == (1, 3, 7) and static.dtype == np.float32
    np.testing.assert_array_equal(sp.observation["static"], static[0])
    row = static[0, 0]
    assert row[6] == 1 and static[0, 1:].sum() == 0  # one pillar, the other rows empty
    # 2 m east = 2 m to the goal frame's right (-y): its near face 1.8 m away, half side 0.2 m
    np.testing.assert_allclose(row[:6] * [4, 4, 4, 4, 0.4, 4], [0.0, -1.8, 0.0, -2.0, 0.2, 0.5],
                               atol=1e-5)  # fmt: skip
    rt._static_rows = lambda pos, yaw: torch.full((1, 3, 7), math.nan)  # a bad list: hover
    sp = rt.step()
    assert sp.hover and "non-finite observation" in sp.reason and len(seen) == 1


def _bracket_maps(env):
    """The true height map grown and shrunk by one cell (and raised/lowered by one cell height):
    a range image within the map resolution of the truth lies between their range images."""
    truth = height_map(env.worlds[0], env.n_static, env._walls)  # the geofence wall included
    dil = F.max_pool2d(truth[None, None], 3, 1, 1)[0, 0]
    ero = -F.max_pool2d(-truth[None, None], 3, 1, 1)[0, 0]
    res = env.cfg.grid_resolution
    dil = torch.where(dil > 0, dil + res, 0.0)
    ero = torch.where(ero > 0, (ero - res).clamp(min=0.01), 0.0)
    return quantize_heights(truth), quantize_heights(dil), quantize_heights(ero)


@pytest.mark.parametrize("stride, min_bracketed, min_one_cell", [(1, 0.995, 0.98), (2, 0.98, 0.96)])
def test_depth_images_give_the_simulators_range_image_within_the_map_resolution(
    easy_env, stride, min_bracketed, min_one_cell
) -> None:
    """Depth images rendered from the simulator's own world (4 pinhole cameras, 90 degrees each)
    -> height map -> ray cast, against the simulator's range image from its true map."""
    env, cfg = easy_env, easy_env.cfg
    truth, dil, ero = _bracket_maps(env)
    lo, hi = pillar_boxes(env)
    xy, h, top = (
        env.pillar_xy[0, : env.n_static],
        env.pillar_half[0, : env.n_static],
        env.pillar_height[0, : env.n_static],
    )
    spec = RangeImageSpec.for_config(cfg)
    cam = PinholeCamera.from_fov(80, 60, 90.0)
    rng = np.random.default_rng(0)
    bracketed = one_cell = total = poses = 0
    while poses < 30:
        p = np.array(
            [rng.uniform(-8, 8), rng.uniform(-8, 8), rng.uniform(0.5, 3.0)], dtype=np.float32
        )
        if pillar_clearance(torch.tensor(p)[None], xy, h, top)[0] < cfg.uav_radius:
            continue  # inside or touching a pillar: no range image to compare
        poses += 1
        rt = OnboardRuntime(
            const_policy(), cfg, RuntimeConfig(require_tracker=False, depth_stride=stride)
        )
        rt.update_state(p, np.zeros(3))
        rt.set_goal(np.array([rng.uniform(-9, 9), rng.uniform(-9, 9), 1.5]), start=p)
        images = [DepthImage(render_depth(cam, R, t, lo, hi), cam.fx, cam.fy, cam.cx, cam.cy, R, t)
                  for R, t in rig_poses(p, yaw=rng.uniform(-3, 3))]  # fmt: skip
        assert rt.update_depth(images) > 0
        _, mine = rt.observation()
        pos, yaw = torch.tensor(p)[None], torch.tensor([rt.goal_yaw], dtype=torch.float32)
        r_true, r_dil, r_ero = (raycast_height_map(m, env.grid.origin, env.grid.size, pos, yaw, spec)
                                for m in (truth, dil, ero))  # fmt: skip
        bracketed += int(((mine >= r_dil - 1e-4) & (mine <= r_ero + 1e-4)).sum())
        cell = cfg.grid_resolution / torch.cos(spec.elevations())[None, :, None] + 1e-4
        one_cell += int(((mine - r_true).abs() <= cell).sum())
        total += mine.numel()
    assert bracketed / total >= min_bracketed, bracketed / total
    assert one_cell / total >= min_one_cell, one_cell / total


def test_tracked_obstacles_stay_out_of_the_map() -> None:
    cfg = make_config("easy")
    cam = PinholeCamera.from_fov(80, 60, 90.0)
    p = np.array([0.0, 0.0, 1.5])
    box_c = np.array([1.5, 0.0, 1.5])  # a 1 m floating cuboid 1.5 m ahead, nothing else
    lo = torch.tensor(np.array([box_c - 0.5]), dtype=torch.float32)
    hi = torch.tensor(np.array([box_c + 0.5]), dtype=torch.float32)
    images = [DepthImage(render_depth(cam, R, t, lo, hi), cam.fx, cam.fy, cam.cx, cam.cy, R, t)
              for R, t in rig_poses(p, 0.0)]  # fmt: skip
    seen = OnboardRuntime(const_policy(), cfg, RuntimeConfig(require_tracker=False))
    seen.update_depth(images)
    assert float((seen.map.heights - seen.map.floor).max()) > 1.5
    excluded = OnboardRuntime(const_policy(), cfg)
    excluded.update_obstacles([TrackedObstacle(box_c, np.zeros(3), 1.0, 1.0, True)])
    excluded.update_depth(images)
    assert torch.equal(excluded.map.heights, excluded.map.floor)  # only the geofence wall


def _ready_runtime(policy=None, **cfg_kwargs):
    cfg = make_config("easy")
    clock = [100.0]
    rt = OnboardRuntime(
        policy or const_policy(), cfg, RuntimeConfig(**cfg_kwargs), clock=lambda: clock[0]
    )
    rt.update_state([0.0, 0.0, 1.5], [0.0, 0.0, 0.0])
    rt.set_goal([5.0, 0.0, 1.5])
    rt.update_points(np.zeros((0, 3)))
    rt.update_obstacles([])
    return rt, clock


def test_runtime_flies_when_inputs_are_good_and_converts_to_ned() -> None:
    rt, _ = _ready_runtime(const_policy((0.5, 0.25, -0.1)))
    sp = rt.step()
    assert not sp.hover and sp.reason == ""
    # Goal due east: goal-frame x = east. v = action * v_max.
    np.testing.assert_allclose(sp.velocity, [1.0, 0.5, -0.2], atol=1e-6)
    np.testing.assert_allclose(sp.velocity_ned, [0.5, 1.0, 0.2], atol=1e-6)
    assert sp.yaw_ned_deg == pytest.approx(90.0)  # facing east


def test_runtime_clamps_to_v_max_per_goal_frame_axis() -> None:
    rt, _ = _ready_runtime(const_policy((7.0, -3.0, 2.0)))
    sp = rt.step()
    np.testing.assert_allclose(sp.velocity, [2.0, -2.0, 2.0], atol=1e-6)


@pytest.mark.parametrize(
    "spoil, reason",
    [
        (lambda rt, c: c.__setitem__(0, c[0] + 0.3), "stale vehicle state"),
        (lambda rt, c: rt.update_state([np.nan, 0, 1.5], [0, 0, 0]), "non-finite vehicle state"),
        (lambda rt, c: rt.update_state([0, 0, 1.5], [np.inf, 0, 0]), "non-finite vehicle state"),
        (lambda rt, c: rt.update_state([0, 0, 1.5], [0, 0, 0], stamp=c[0] + 5.0), "in the future"),
        (lambda rt, c: (c.__setitem__(0, c[0] + 0.6), rt.update_state([0, 0, 1.5], [0, 0, 0])), "stale map"),
        (lambda rt, c: (c.__setitem__(0, c[0] + 0.6), rt.update_state([0, 0, 1.5], [0, 0, 0]),
                        rt.update_points(np.zeros((0, 3)))), "stale obstacle tracker"),
        (lambda rt, c: rt.update_obstacles([TrackedObstacle(np.array([np.nan, 0, 0]), np.zeros(3), 0.5, 1.0)]),
         "non-finite or negative-size tracked obstacle"),
        (lambda rt, c: rt.update_depth([DepthImage(np.ones((4, 4), np.float32), 2, 2, 2, 2,
                                                   np.full((3, 3), np.nan), np.zeros(3))]), "non-finite camera pose"),
        # a focal length that is zero as the float32 map kernels read it (found by the fuzz)
        (lambda rt, c: rt.update_depth([DepthImage(np.ones((4, 4), np.float32), 1e-50, 2, 2, 2,
                                                   np.eye(3), np.zeros(3))]), "intrinsics (as float32)"),
        (lambda rt, c: rt.update_depth([DepthImage(np.ones((4, 4), np.float32), 2, 2, 2, 2,
                                                   np.eye(3), np.array([1e300, 0, 0]))]), "non-finite camera pose"),
    ],
)  # fmt: skip
def test_runtime_hovers_on_stale_or_invalid_inputs(spoil, reason) -> None:
    rt, clock = _ready_runtime()
    assert not rt.step().hover
    spoil(rt, clock)
    sp = rt.step()
    assert sp.hover and reason in sp.reason
    assert np.all(sp.velocity == 0) and np.all(sp.velocity_ned == 0)


def test_runtime_hovers_before_a_goal_and_on_bad_policy_output() -> None:
    cfg = make_config("easy")
    rt = OnboardRuntime(const_policy(), cfg)
    assert rt.step().reason == "no goal set"
    rt, _ = _ready_runtime(const_policy((np.nan, 0.0, 0.0)))
    sp = rt.step()
    assert sp.hover and "policy output" in sp.reason


def test_runtime_recovers_when_inputs_are_good_again() -> None:
    rt, clock = _ready_runtime()
    rt.update_obstacles([TrackedObstacle(np.array([np.nan, 0, 0]), np.zeros(3), 0.5, 1.0)])
    assert rt.step().hover
    rt.update_obstacles([TrackedObstacle(np.array([3.0, 0, 1.5]), np.zeros(3), 0.5, 1.0)])
    assert not rt.step().hover


def test_nan_depth_pixels_are_no_return_not_a_fault() -> None:
    rt, _ = _ready_runtime()
    cam = PinholeCamera.from_fov(16, 12, 90.0)
    d = np.full((12, 16), np.nan, np.float32)
    d[6, 8] = 1.0
    (R, t), *_ = rig_poses([0, 0, 1.5], 0.0)
    assert rt.update_depth([DepthImage(d, cam.fx, cam.fy, cam.cx, cam.cy, R, t)]) == 1
    assert not rt.step().hover


def test_frames() -> None:
    v = np.array([1.0, 2.0, 3.0])  # east, north, up
    np.testing.assert_allclose(enu_to_ned(v), [2.0, 1.0, -3.0])
    np.testing.assert_allclose(ned_to_enu(enu_to_ned(v)), v)
    origin = np.array([10.0, -5.0, 0.0])
    np.testing.assert_allclose(local_ned_to_world(world_to_local_ned(v, origin), origin), v)
    assert yaw_enu_to_ned(0.0) == pytest.approx(math.pi / 2)  # east
    assert yaw_enu_to_ned(math.pi / 2) == pytest.approx(0.0)  # north


def test_perception_frames_round_trip_and_reject_garbage() -> None:
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.3, 9.0, (6, 8)).astype(np.float32)
    depth[0, 0] = np.nan
    R, t = rig_poses([1.0, 2.0, 1.5], 0.3)[1]
    frame = PerceptionFrame(
        stamp=12.5, depth=[DepthImage(depth, 4.0, 4.0, 3.5, 2.5, R, t)],
        points=rng.normal(size=(5, 3)).astype(np.float32),
        obstacles=[TrackedObstacle(np.array([1.0, 2, 3]), np.array([0.5, 0, 0]), 0.5, 5.0)],
        truth={"collisions": 0},
    )  # fmt: skip
    for as_uint16, tol in ((True, 5e-4), (False, 0.0)):
        data = encode_frame(frame, depth_as_uint16=as_uint16)
        back = decode_frame(data[4:])
        got = back.depth[0].depth
        assert got[0, 0] == 0 or np.isnan(got[0, 0])  # no return stays no return
        np.testing.assert_allclose(got[1:], depth[1:], atol=tol)
        np.testing.assert_allclose(back.depth[0].R, R)
        np.testing.assert_allclose(back.points, frame.points)
        assert back.obstacles[0].height == 5.0 and back.truth == {"collisions": 0}
    for bad in (b"", b"\x00\x00\x00\x09{}", b"\x00\x00\x00\x02{}", b"\x00\x00\x00\x02{]xx"):
        with pytest.raises(ValueError):
            decode_frame(bad)


@pytest.mark.parametrize(("scan", "brake"), [(False, False), (True, False), (True, True)])
def test_runtime_memory_shield_is_the_simulators(scan, brake) -> None:
    """Given the env's map and the env's state each step, the runtime's memory shield (its own
    range images, placed by odometry; a new goal forgets them; with ``scan`` the map scan of its
    own map; with ``brake`` the braking cap, from its odometry's altitude) corrects the actions as ``MemoryShield`` does on the env, over episodes that end and
    restart. Positions go to the
    world frame and back, so a near-tie may fall the other way now and then (as in
    ``test_memory_shield_of_one_image_is_env_shield``)."""
    from safenav.deploy.shield import MemoryShield, ShieldConfig
    from safenav.envs.scripted import go_to_goal

    cfg = make_config("easy", num_dynamic=0)  # static obstacles: the range image is exact
    env = SafeNavVectorEnv(4, config=cfg, output="torch")
    obs, _ = env.reset(seed=7)
    shield_cfg = ShieldConfig.for_env(cfg, **(ShieldConfig.braking_of(cfg) if brake else {}))
    sim = MemoryShield(10, shield_cfg, map_scan=scan)
    wanted = [np.zeros((1, 3), np.float32)]
    runtimes = [
        OnboardRuntime(lambda s, l, d: wanted[0], cfg, clock=lambda: 100.0,  # noqa: E741
                       config=RuntimeConfig(shield=shield_cfg, shield_memory=10, shield_map=scan,
                                            require_tracker=False))
        for _ in range(4)
    ]  # fmt: skip
    g2 = env.grid.size**2
    rows = corrected = flips = apart = 0
    for _ in range(100):
        a = go_to_goal(obs).clamp(-1.0, 1.0)
        shielded = sim(env, obs, a)
        for i, rt in enumerate(runtimes):
            w = int(env.world_idx[i])
            rt.map.cast_map = env.heights[w * g2 : (w + 1) * g2].clone()
            rt.update_points(np.zeros((0, 3)))
            rt.update_state(env.pos[i].numpy(), env.vel[i].numpy())
            if int(env.steps[i]) == 0:
                rt.set_goal(env.goal[i].numpy(), start=env.start[i].numpy())
            wanted[0] = a[i : i + 1].numpy()
            sp = rt.step()
            assert not sp.hover, sp.reason
            sim_corrected = bool((shielded[i] != a[i]).any())
            corrected += int(sim_corrected)
            flips += int(sp.shielded != sim_corrected)
            apart += int(np.abs(sp.action - shielded[i].numpy()).max() > 1e-3)
            rows += 1
        obs, *_ = env.step(shielded)
    assert corrected > 40  # the comparison covered corrections, not only untouched actions
    assert flips <= 0.01 * rows and apart <= 0.02 * rows, (flips, apart, corrected, rows)


def test_runtime_memory_shield_remembers_a_pillar_until_a_new_goal() -> None:
    """A pillar 2 m ahead, then gone from the range image (as a low pillar's top leaves the lowest
    beam): the memory shield still turns away from where it was seen, the memoryless one flies
    on; a new goal forgets it."""
    from safenav.deploy.shield import ShieldConfig

    cfg = make_config("easy")
    shield = ShieldConfig.for_env(cfg)
    side = (-0.2, 0.0, 0.2)
    pillar = np.array(
        [[2.0 + dx, dy, z] for dx in side for dy in side for z in np.arange(0.1, 4.0, 0.1)]
    )
    for memory, remembers in ((1, False), (20, True)):
        rt, _ = _ready_runtime(const_policy((1.0, 0.0, 0.0)), shield=shield, shield_memory=memory)
        rt.update_points(pillar)
        assert rt.step().shielded
        rt.map.clear()
        rt.update_points(np.zeros((0, 3)))
        assert rt.step().shielded is remembers, memory
        rt.set_goal([5.0, 0.0, 1.5])
        assert not rt.step().shielded


def test_runtime_map_scan_sees_a_pillar_top_below_the_beams() -> None:
    """A pillar 1 m ahead whose top is 0.25 m below the vehicle: under the −10° beam (1.32 m
    there), so the range image is empty and the memoryless shield flies on; the map scan (the
    map the depth images built, cast level from the vehicle's lower extent) turns away."""
    from safenav.deploy.shield import ShieldConfig

    cfg = make_config("easy")
    side = (-0.2, 0.0, 0.2)
    pillar = np.array([[1.0 + dx, dy, z] for dx in side for dy in side for z in (0.5, 1.0, 1.25)])
    for scan in (False, True):
        rt, _ = _ready_runtime(const_policy((1.0, 0.0, 0.0)), shield=ShieldConfig.for_env(cfg),
                               shield_map=scan)  # fmt: skip
        rt.update_points(pillar)
        obs, _ = rt.observation()
        assert float(obs["lidar"][0].max()) == 0.0  # nothing in the range image
        assert rt.step().shielded is scan


def test_runtime_refuses_shield_memory_or_map_without_a_shield() -> None:
    from safenav.deploy.shield import ShieldConfig

    cfg = make_config("easy")
    with pytest.raises(ValueError, match="shield_memory"):
        OnboardRuntime(const_policy(), cfg, RuntimeConfig(shield_memory=20))
    with pytest.raises(ValueError, match="shield_memory"):
        OnboardRuntime(
            const_policy(), cfg, RuntimeConfig(shield=ShieldConfig.for_env(cfg), shield_memory=0)
        )
    with pytest.raises(ValueError, match="shield_map"):
        OnboardRuntime(const_policy(), cfg, RuntimeConfig(shield_map=True))
