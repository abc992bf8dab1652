"""SafeNav-v1's closed arena: the border is a wall, obstacles fill the map up to it, starts and
goals are clear sites, and no policy scores by flying around the obstacle field."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import safenav
from safenav.envs import SafeNavVectorEnv, fixed_scenario, make_config
from safenav.envs.nav import _clearance_xy, world_obstacles
from safenav.envs.render import WALL, render_topdown
from safenav.envs.scripted import BorderFollower, go_to_goal
from safenav.envs.world import (
    border_clearance,
    generate_world,
    side_points,
    world_from_obstacles,
)
from safenav.experiments.evaluate import evaluate


def empty_env(cfg, n: int = 1) -> SafeNavVectorEnv:
    env = SafeNavVectorEnv(n, config=cfg.replace(num_worlds=1), output="torch",
                           autoreset_mode="Disabled")  # fmt: skip
    env.set_worlds([world_from_obstacles(env.cfg)])
    return env


def fly(env, start, velocity, steps):
    """From hover at ``start``, command ``velocity`` (world frame, m/s) for up to ``steps``
    steps; returns the last info. The goal lies 5 m west, so the goal frame's x points west."""
    start = torch.tensor([start], dtype=torch.float32)
    goal = start - torch.tensor([[5.0, 0.0, 0.0]])
    env.reset(options={"starts": start, "goals": goal})
    a = torch.tensor([[-velocity[0], -velocity[1], velocity[2]]]) / env.cfg.v_max
    info = {}
    for _ in range(steps):
        _, _, term, trunc, info = env.step(a)
        if bool(term[0] or trunc[0]):
            break
    return info


def test_v1_is_the_registered_id_and_v0_names_it():
    assert safenav.ENV_ID == "SafeNav-v1"
    assert gym.make("SafeNav-v1", preset="easy").unwrapped.cfg.map_size == 20.0
    with pytest.raises(gym.error.Error, match="SafeNav-v1"):
        gym.make("SafeNav-v0")


def test_leaving_the_map_horizontally_is_a_collision_with_cost():
    env = empty_env(make_config("easy"))
    info = fly(env, (env.cfg.half - 2.0, 0.0, 1.5), (2.0, 0.0, 0.0), 100)
    ep = info["episode"]
    assert bool(ep["collision"][0]) and bool(ep["hit_border"][0]) and bool(ep["out_of_bounds"][0])
    assert not bool(ep["hit_static"][0]) and not bool(ep["hit_dynamic"][0])
    assert float(info["cost"][0]) == 1.0
    assert float(ep["outside_time"][0]) == 0.0  # ended at the wall, never outside
    # it ended when the collision sphere touched the wall, not before
    assert env.cfg.half - env.pos[0, 0] <= env.cfg.uav_radius
    assert env.cfg.half - env.pos[0, 0] > env.cfg.uav_radius - 0.4


def test_the_border_wall_is_seen_by_both_ray_casters():
    cfg = make_config("easy", num_worlds=1)
    for caster in ("grid", "bruteforce"):
        env = SafeNavVectorEnv(1, config=cfg, output="torch", autoreset_mode="Disabled",
                               raycaster=caster)  # fmt: skip
        env.set_worlds([world_from_obstacles(env.cfg)])
        start = torch.tensor([[cfg.half - 2.5, 0.0, 1.5]])
        goal = torch.tensor([[cfg.half - 2.5, 5.0, 1.5]])  # goal frame: x north, beam 27 looks east
        env.reset(options={"starts": start, "goals": goal})
        _, aux = env._sense()
        ranges = aux["ranges"][0, cfg.lidar_v_angles.index(0.0)]
        east = int(round(270 / (360 / cfg.lidar_h_beams)))
        assert float(ranges[east]) == pytest.approx(2.5, abs=cfg.grid_resolution + 1e-3), caster
        west = int(round(90 / (360 / cfg.lidar_h_beams)))
        assert float(ranges[west]) == pytest.approx(cfg.lidar_range), caster


def test_obstacles_fill_the_border_band_and_sites_keep_clear_discs():
    cfg = make_config("paper")
    world = generate_world(cfg, 1)
    sides = np.repeat(np.arange(4), cfg.start_sites)
    site_xy = torch.as_tensor(side_points(cfg, sides, world.site_along.reshape(-1)))
    # each site is the centre of a start_clearance disc free of pillars and mover origins
    obstacles = world_obstacles(world)
    assert float(_clearance_xy(site_xy[None].float(), obstacles).min()) >= cfg.start_clearance
    # Outside those discs the 2 m band along the border is as cluttered as the rest of the map
    # (v0: no pillar in it). Areas by counting a fine grid of points.
    g = torch.linspace(-cfg.half, cfg.half, 501)
    pts = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    free_disc = (pts[:, None] - site_xy[None]).norm(dim=-1).amin(-1) < cfg.start_clearance
    in_band = border_clearance(pts, cfg.half) < cfg.edge_margin
    cell = (cfg.map_size / 500) ** 2
    band_area = float((in_band & ~free_disc).sum()) * cell
    rest_area = float((~in_band & ~free_disc).sum()) * cell
    xy = torch.as_tensor(world.pillar_xy)
    band = border_clearance(xy, cfg.half) < cfg.edge_margin
    assert float(band.sum()) / band_area > 0.75 * float((~band).sum()) / rest_area
    movers = border_clearance(torch.as_tensor(world.dyn_origin), cfg.half) < 2 * cfg.edge_margin
    assert int(movers.sum()) >= 5


def test_test_scenario_starts_and_goals_are_clear_on_different_sides():
    cfg = make_config("paper")
    starts, goals = fixed_scenario(cfg, 1, 200)
    obstacles = tuple(t.expand(200, *t.shape[1:]) for t in world_obstacles(generate_world(cfg, 1)))
    for points in (starts, goals):
        assert (
            float(_clearance_xy(points[:, None, :2], obstacles).min()) >= cfg.start_clearance - 1e-3
        )
        edge = border_clearance(points, cfg.half)
        assert torch.allclose(edge, torch.full_like(edge, cfg.edge_margin / 2))

    def side(p):  # 0 north, 1 east, 2 south, 3 west
        horizontal = p[:, 0].abs() > p[:, 1].abs()
        return torch.where(horizontal, 1 + 2 * (p[:, 0] < 0), 2 * (p[:, 1] < 0))

    assert bool((side(starts) != side(goals)).all())
    assert float((goals - starts)[:, :2].norm(dim=-1).min()) >= cfg.min_goal_distance


def test_training_resets_never_start_inside_a_moving_obstacle():
    env = SafeNavVectorEnv(64, preset="paper", output="torch")
    env.reset(seed=3)
    zero = torch.zeros(64, 3)
    starts_checked = 0
    for _ in range(300):  # obstacles move; episodes restart at their current positions
        _, _, _, _, info = env.step(zero)  # hovering at the start: episodes time out or are hit
        if "episode" in info:
            ids = info["_episode"].nonzero().squeeze(-1)
            nd = env.n_dynamic
            rel = env.dyn_pos[env.world_idx[ids], :nd, :2] - env.pos[ids, None, :2]
            gap = rel.norm(dim=-1) - env.dyn_width[env.world_idx[ids], :nd] / 2
            starts_checked += len(ids)
            # the clearest of 16 candidate sites is chosen; all 16 occupied is improbable
            assert float(gap.amin()) > env.cfg.uav_radius
    env.reset(seed=4)
    nd = env.n_dynamic
    rel = env.dyn_pos[env.world_idx, :nd, :2] - env.pos[:, None, :2]
    gap = rel.norm(dim=-1) - env.dyn_width[env.world_idx, :nd] / 2
    assert float(gap.amin()) >= env.cfg.start_clearance - 1e-3


@pytest.mark.long
def test_the_border_follower_cannot_score_by_going_around():
    """The loophole probe succeeds in an empty arena (so it is a competent border follower) and
    fails in the cluttered one: no obstacle-free way round the field exists."""
    open_arena = make_config("paper", num_static=0, num_dynamic=0, max_episode_seconds=120.0)
    result = evaluate(BorderFollower(), open_arena, episodes=40)
    assert result["success_rate"] >= 0.9
    assert result["border_time_fraction"] > 0.95 and result["detour_ratio"] > 1.2
    result = evaluate(BorderFollower(), make_config("paper"), episodes=60)
    assert result["success_rate"] <= 0.10
    assert result["outside_time_fraction"] == 0.0


def test_flight_metrics_of_a_straight_flight():
    cfg = make_config("paper", num_static=0, num_dynamic=0)
    result = evaluate(go_to_goal, cfg, episodes=30)
    assert result["success_rate"] == 1.0
    # path length over start-goal distance: straight, ending 0.5 m short of the goal centre
    assert 0.95 <= result["detour_ratio"] <= 1.02
    assert 0.0 < result["border_time_fraction"] < 0.5
    assert result["outside_time_fraction"] == 0.0
    for key in ("detour_ratio", "border_time", "outside_time", "hit_border"):
        assert len(result["per_episode"][key]) == 30


def test_render_draws_the_wall_and_the_outcome():
    env = SafeNavVectorEnv(1, preset="easy", output="torch", autoreset_mode="Disabled",
                           render_mode="rgb_array")  # fmt: skip
    env.reset(seed=0)
    img = render_topdown(env, 0, outcome="collision")
    from safenav.envs.render import HEADER, LEGEND

    assert img.shape == (600 + HEADER + LEGEND, 600, 3)
    assert tuple(img[HEADER + 1, 300]) == WALL and tuple(img[HEADER + 300, 1]) == WALL
    assert tuple(img[HEADER + 300, 300]) != WALL
    plain = render_topdown(env, 0)
    assert not np.array_equal(img[:HEADER], plain[:HEADER])  # the outcome label


def test_write_gif_is_a_looping_animation_pillow_reads_back(tmp_path):
    from PIL import Image, ImageSequence

    from safenav.envs.render import write_gif

    red, blue = np.zeros((8, 10, 3), np.uint8), np.zeros((8, 10, 3), np.uint8)
    red[..., 0], blue[..., 2] = 255, 255
    write_gif(tmp_path / "a.gif", [red, blue, blue], fps=5)
    with Image.open(tmp_path / "a.gif") as gif:
        assert gif.info["loop"] == 0
        frames = [(np.asarray(f.convert("RGB")), f.info["duration"])
                  for f in ImageSequence.Iterator(gif)]  # fmt: skip
    # Pillow merges the two identical blue frames into one of twice the duration.
    assert [d for _, d in frames] == [200, 400]
    assert tuple(frames[0][0][4, 5]) == (255, 0, 0) and tuple(frames[1][0][4, 5]) == (0, 0, 255)
    with pytest.raises(ValueError, match="at least one frame"):
        write_gif(tmp_path / "b.gif", [], fps=5)


def test_the_flight_demos_gif_draws_the_wall(tmp_path):
    from PIL import Image, ImageSequence

    from safenav.deploy.demo import render_flight_gif
    from safenav.envs.render import HEADER

    cfg = make_config("paper")
    snaps = [{"t": 0.2 * i, "pos": [-24.0 + 0.3 * i, -9.2, 1.3], "dyn_pos": [], "collisions": 0}
             for i in range(3)]  # fmt: skip
    render_flight_gif(tmp_path / "f.gif", cfg, 1, snaps, [-24.0, -9.2, 1.3], [19.0, 24.0, 1.2])
    with Image.open(tmp_path / "f.gif") as gif:
        frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(gif)]
    assert len(frames) == 3
    assert tuple(frames[-1][HEADER + 1, 280]) == WALL
