"""``experiments/oracle_planner.py``: the privileged planner's action conversion, its clearance and
forecast against the env's own, and that it flies where the straight-to-goal policy crashes."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

from safenav.envs.config import make_config
from safenav.envs.dynamics import goal_frame_to_world
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.scripted import go_to_goal
from safenav.envs.sensors import moving_obstacle_clearance, pillar_clearance
from safenav.envs.world import CUBOID_HEIGHT, CYLINDER_HEIGHT
from safenav.experiments.evaluate import evaluate

ROOT = Path(__file__).resolve().parents[1]


def _oracle_module():
    spec = importlib.util.spec_from_file_location(
        "oracle_planner", ROOT / "experiments" / "oracle_planner.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules["oracle_planner"] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


oracle = _oracle_module()


def _env(n: int = 8) -> tuple[SafeNavVectorEnv, dict]:
    env = SafeNavVectorEnv(n, preset="easy", output="torch", autoreset_mode="Disabled")
    obs, _ = env.reset(seed=12345)
    return env, obs


def test_command_straight_at_the_goal_is_go_to_goal_action():
    env, obs = _env()
    for _ in range(3):  # not at rest, off the start's heading
        obs, *_ = env.step(torch.tensor([[0.3, -0.8, 0.5]]).expand(env.num_envs, 3))
    to_goal = env.goal - env.pos
    dist = to_goal.norm(dim=-1, keepdim=True)
    v = to_goal / dist * env.cfg.v_max * dist.clamp(max=1.0)  # go_to_goal: full speed, slower < 1 m
    action = oracle.to_action(v, env.cos_yaw, env.sin_yaw, env.cfg.v_max)
    assert torch.allclose(action, go_to_goal(obs), atol=1e-5)
    # The env turns the action back into the same world-frame command (inside the box).
    assert torch.allclose(
        goal_frame_to_world(action * env.cfg.v_max, env.cos_yaw, env.sin_yaw), v, atol=1e-5
    )
    # The planner's candidates include it, and hover.
    ids = torch.arange(env.num_envs)
    cmds = oracle.OraclePlanner().candidates(obs, env, ids)
    assert torch.allclose(cmds[:, -1], v, atol=1e-5)
    assert bool((cmds[:, -2] == 0).all())
    # A command beyond the box is applied clipped, as the env clips the action.
    far = oracle.OraclePlanner(oracle.OracleConfig(speeds=(5.0,), headings=4, climbs=(0.0,)))
    clipped = far.candidates(obs, env, ids)
    a = oracle.to_action(clipped, env.cos_yaw[:, None], env.sin_yaw[:, None], env.cfg.v_max)
    assert a.abs().max() <= 1.0 and (a.abs() == 1.0).any()


def test_mover_clearance_matches_the_env():
    g = torch.Generator().manual_seed(0)
    centre = torch.rand(3, 7, 3, generator=g) * 4
    width = torch.rand(3, 1, 7, generator=g) + 0.25
    cuboid = torch.rand(3, 1, 7, generator=g) < 0.5
    p = torch.rand(3, 5, 3, generator=g) * 4
    p[0, 0, 2] = 5.5  # above a cylinder's top
    ours = oracle.mover_clearance(centre, width, cuboid, p)
    rel = centre[:, None] - p[:, :, None]
    ref = moving_obstacle_clearance(rel, width, cuboid, p[..., 2], CUBOID_HEIGHT, CYLINDER_HEIGHT)
    assert torch.allclose(ours, ref, atol=1e-5)


def test_exact_forecast_is_the_future_and_leaves_the_env_alone():
    env, _ = _env()
    planner = oracle.OraclePlanner(oracle.OracleConfig(forecast="exact", horizon=25))
    for _ in range(15):  # some obstacles near a turn or a speed change
        env.step(torch.zeros(env.num_envs, 3))
    state = (
        env.dyn_pos.clone(),
        env.dyn_goal.clone(),
        env.dyn_goal_counter.clone(),
        env.world_step,
    )
    future = planner.forecast(env)
    assert torch.equal(env.dyn_pos, state[0]) and torch.equal(env.dyn_goal, state[1])
    assert torch.equal(env.dyn_goal_counter, state[2]) and env.world_step == state[3]
    turned = env.dyn_goal_counter.clone()
    for t in range(25):
        env.step(torch.zeros(env.num_envs, 3))
        assert torch.equal(future[t], env.dyn_pos)
    assert bool((env.dyn_goal_counter != turned).any())  # some turned inside the horizon
    constant = oracle.OraclePlanner().forecast(env)
    assert torch.allclose(constant[0], env.dyn_pos + env.cfg.dt * env.dyn_vel)


def test_oracle_flies_where_straight_to_goal_crashes():
    torch.set_num_threads(1)
    cfg = make_config("easy")
    straight = evaluate(go_to_goal, cfg, env_seed=12345, episodes=16)
    planned = evaluate(oracle.OraclePlanner(), cfg, env_seed=12345, episodes=16)
    assert straight["collision_rate"] >= 0.5
    assert planned["collision_rate"] <= 0.1 and planned["success_rate"] >= 0.8


def test_cli_refuses_test_and_held_out_maps(tmp_path):
    with pytest.raises(SystemExit, match="test or held-out"):
        oracle.main(["--env-seeds", "1", "--episodes", "2", "--json", str(tmp_path / "x.json")])


def test_beam_hits_lie_on_the_surfaces_the_range_image_saw():
    env = SafeNavVectorEnv(8, preset="paper", output="torch", autoreset_mode="Disabled")
    obs, _ = env.reset(seed=200_123)
    pts = oracle.beam_hits(obs["lidar"], env.pos, env.yaw, env.cfg)  # (8, 144, 3)
    assert pts.shape == (8, 4 * 36, 3)
    hit = pts[..., 0].abs() < 1e3
    seen = obs["lidar"][:, :4].reshape(8, -1) > 1e-4
    assert torch.equal(hit, seen) and hit.any()
    w, ns = env.world_idx, env.n_static
    per = lambda t: t[w, :ns].repeat_interleave(pts.shape[1], 0)  # noqa: E731
    flat = pts.reshape(-1, 3)
    pillars = pillar_clearance(
        flat, per(env.pillar_xy), per(env.pillar_half), per(env.pillar_height)
    )
    h = env.cfg.half
    x, y = flat[:, 0], flat[:, 1]
    wall = torch.stack([h - x, h + x, h - y, h + y], -1).amin(-1)
    surface = torch.minimum(pillars, wall).clamp(min=0).reshape(pts.shape[:2])
    solid = hit & (pts[..., 2] > 0.05)  # the rest hit the ground
    # within the occupancy grid's quantisation (0.1 m) of a pillar or the wall
    assert surface[solid].max() <= 0.1


def test_scan_columns_lie_on_pillar_sides():
    """The map-scan hits, brought into the world, lie on the side of a pillar (or the wall) in
    the horizontal plane: the shield's heading frame turned back by the planner correctly."""
    env = SafeNavVectorEnv(8, preset="paper", output="torch", autoreset_mode="Disabled")
    env.reset(seed=200_123)
    cols = oracle.scan_columns(env, torch.arange(8))  # (8, K, 2)
    hit = cols[..., 0].abs() < 1e3
    assert hit.any()
    w, ns = env.world_idx, env.n_static
    flat = cols.reshape(-1, 2)
    per = lambda t: t[w, :ns].repeat_interleave(cols.shape[1], 0)  # noqa: E731
    foot = ((flat[:, None] - per(env.pillar_xy)).abs()
            - per(env.pillar_half)[..., None]).clamp(min=0).norm(dim=-1).amin(-1)  # fmt: skip
    h = env.cfg.half
    x, y = flat[:, 0], flat[:, 1]
    wall = torch.stack([h - x, h + x, h - y, h + y], -1).amin(-1)
    side = torch.minimum(foot, wall.clamp(min=0)).reshape(cols.shape[:2])
    assert side[hit].max() <= 0.15  # the height map's quantisation


def test_lidar_sensing_flies_the_easy_map():
    torch.set_num_threads(1)
    cfg = make_config("easy")
    planned = evaluate(oracle.OraclePlanner(oracle.OracleConfig(sense="lidar")), cfg,
                       env_seed=12345, episodes=16)  # fmt: skip
    assert planned["success_rate"] >= 0.6


def test_cruise_holds_its_altitude_until_near_the_goal():
    """``cruise`` brings the UAV down to the cruise altitude on the way and up to the goal's at
    the end; ``ignore_ground`` is what lets it fly low (ground hits are no obstacle points)."""
    torch.set_num_threads(1)
    env, obs = _env(8)
    config = oracle.OracleConfig(sense="lidar", cruise=0.6, ignore_ground=True,
                                 climbs=(-0.75, -0.25, 0.0, 0.25, 0.75))  # fmt: skip
    planner = oracle.OraclePlanner(config)
    heights, far = [], []
    for _ in range(80):
        obs, *_ = env.step(planner(obs, env))
        heights.append(env.pos[:, 2].clone())
        far.append((env.goal - env.pos)[:, :2].norm(dim=-1) > config.cruise_until + 2)
    z, far = torch.stack(heights[40:]), torch.stack(far[40:])
    assert far.any() and (z[far] - 0.6).abs().max() < 0.35
    # without the option, the downward beams' ground hits are obstacle points like any other
    pts = oracle.beam_hits(obs["lidar"], env.pos, env.yaw, env.cfg)
    assert (pts[..., 2].abs() < 0.05).any()


def test_oracle_compare_pairs_episodes_by_map(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location(
        "oracle_compare", ROOT / "experiments" / "oracle_compare.py"
    )
    compare = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(compare)
    import json

    def planner_file(name, maps):  # the per_map layout oracle_planner.py --json writes
        per_map = {
            seed: {
                "per_episode": {
                    "success": s,
                    "collision": [1 - x for x in s],
                    "timeout": [0.0] * len(s),
                }
            }  # fmt: skip
            for seed, s in maps.items()
        }
        path = tmp_path / name
        path.write_text(json.dumps({"per_map": per_map}))
        return str(path)

    a = planner_file("a.json", {"1": [1.0, 0.0, 0.0, 1.0], "2": [0.0, 0.0]})
    b1 = planner_file("b1.json", {"1": [1.0, 1.0, 1.0, 1.0]})
    b2 = tmp_path / "b2.json"  # a safenav eval --json file: one map
    b2.write_text(json.dumps({"env_seed": 2, "per_episode": {
        "success": [1.0, 0.0], "collision": [0.0, 1.0], "timeout": [0.0, 0.0]}}))  # fmt: skip
    b2 = str(b2)
    out = tmp_path / "cmp.json"
    compare.main([a, "--against", b1, b2, "--json", str(out)])
    result = json.loads(out.read_text())
    assert result["episodes"] == 6 and result["maps"] == ["1", "2"]
    assert result["success"]["a"] == pytest.approx(2 / 6)
    assert result["success"]["b"] == pytest.approx(5 / 6)
    assert result["success"]["difference"] == pytest.approx(3 / 6)
    assert result["success"]["mcnemar"]["only_b"] == 3  # episodes where only B succeeded
    assert result["success"]["mcnemar"]["only_a"] == 0
    assert result["success"]["both"] == 2
    assert result["collision"]["difference"] == pytest.approx(-3 / 6)
    assert "6 paired episodes" in capsys.readouterr().out
    short = planner_file("short.json", {"1": [1.0], "2": [0.0, 0.0]})
    with pytest.raises(SystemExit, match="episodes"):
        compare.paired(compare.episodes([a]), compare.episodes([short]))
    with pytest.raises(SystemExit, match="different maps"):
        compare.paired(compare.episodes([a]), compare.episodes([b1]))


@pytest.mark.long
def test_eval_and_render_fly_the_planner(tmp_path):
    """``--policy planner``: planner B as a reference on any map, with the beams it was measured
    with, in ``safenav eval`` and ``safenav render``."""
    import json

    from safenav.cli import main
    from safenav.envs.planner import PLANNER_B_BEAMS
    from safenav.experiments.flight import resolve_policy

    torch.set_num_threads(1)
    planner, cfg = resolve_policy(None, "planner")
    assert planner.needs_env and cfg.lidar_v_angles == PLANNER_B_BEAMS
    out = tmp_path / "planner.json"
    main(["eval", "--policy", "planner", "--preset", "easy", "--env-seed", "12345",
          "--episodes", "4", "--json", str(out)])  # fmt: skip
    got = json.loads(out.read_text())
    assert got["checkpoint"] == "planner" and got["episodes"] == 4
    assert got["success_rate"] >= 0.5  # it flies the easy map
    gif = tmp_path / "planner.gif"
    main(["render", "--policy", "planner", "--preset", "easy", "--env-seed", "12345", "--out", str(gif)])  # fmt: skip
    assert gif.stat().st_size > 0


@pytest.mark.long
def test_keep_band_holds_navrls_altitude_band():
    """``keep_band``: the planner stays in the altitude band of NavRL's height penalty, which
    planner B, knowing only the ground and the ceiling, leaves."""
    from dataclasses import replace

    from safenav.envs.planner import PLANNER_B

    torch.set_num_threads(1)
    outside = {}
    for keep in (False, True):
        env, obs = _env(8)
        planner = oracle.OraclePlanner(replace(PLANNER_B, keep_band=keep))
        n_out = n_all = 0
        for _ in range(80):
            obs, _, term, trunc, _ = env.step(planner(obs, env))
            live = ~planner.finished
            z, lo, hi = env.pos[:, 2], env.band[:, 0], env.band[:, 1]
            n_out += int((((z < lo - 0.05) | (z > hi + 0.05)) & live).sum())
            n_all += int(live.sum())
        outside[keep] = n_out / max(n_all, 1)
    assert outside[True] <= 0.02 and outside[True] < outside[False], outside
