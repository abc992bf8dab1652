"""SafeNav-v1: API, determinism, vector == single, geometry, sensing, reward, episode ends."""

from __future__ import annotations

import doctest
import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import safenav  # noqa: F401  (registers SafeNav-v1)
from safenav.envs import nav, sensors
from safenav.envs.config import EnvConfig, make_config
from safenav.envs.nav import SafeNavVectorEnv, fixed_scenario
from safenav.envs.scripted import go_to_goal
from safenav.envs.world import world_from_obstacles

# A still, hand-built world: movers stand still, every step is the same geometry.
STILL = dict(dyn_speed_range=(0.0, 0.0), num_static=4, num_dynamic=4)


def hand_env(pillars=(), movers=(), preset="easy", **overrides) -> SafeNavVectorEnv:
    env = SafeNavVectorEnv(1, preset=preset, output="torch", autoreset_mode="Disabled",
                           **{**STILL, **overrides})  # fmt: skip
    env.set_worlds([world_from_obstacles(env.cfg, list(pillars), list(movers))])
    return env


def place(env: SafeNavVectorEnv, start, goal=(8.0, 8.0, 1.5)) -> dict:
    obs, _ = env.reset(options={"starts": [start], "goals": [goal]})
    return obs


def hover_step(env: SafeNavVectorEnv):
    return env.step(torch.zeros(1, 3))


# ---------------------------------------------------------------- API
def test_check_env_passes():
    env = gym.make("SafeNav-v1", preset="easy")
    check_env(env.unwrapped, skip_render_check=False)


def test_observation_spaces_match_spec():
    env = gym.make("SafeNav-v1")
    obs, _ = env.reset(seed=3)
    assert env.observation_space["state"].shape == (8,)
    assert env.observation_space["lidar"].shape == (4, 36)
    assert env.observation_space["dynamic"].shape == (5, 10)
    assert all(obs[k].dtype == np.float32 for k in obs)
    assert env.observation_space.contains(obs)
    assert env.action_space.shape == (3,) and env.action_space.high.max() == 1.0


def test_make_vec_uses_native_batched_env():
    envs = gym.make_vec("SafeNav-v1", num_envs=8, preset="easy")
    assert isinstance(envs.unwrapped, SafeNavVectorEnv)
    obs, _ = envs.reset(seed=0)
    assert obs["lidar"].shape == (8, 4, 36)
    obs, reward, term, trunc, info = envs.step(envs.action_space.sample())
    assert reward.shape == (8,) and info["cost"].shape == (8,)


def test_doctests_of_env_module():
    result = doctest.testmod(nav, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 4 and result.failed == 0


# ---------------------------------------------------------------- determinism
def rollout(env, seed: int, steps: int = 60):
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(0)
    out = [obs["lidar"].copy(), obs["dynamic"].copy(), obs["state"].copy()]
    for _ in range(steps):
        obs, r, te, tr, info = env.step(rng.uniform(-1, 1, (3,)).astype(np.float32))
        out += [obs["state"].copy(), obs["lidar"].copy(), obs["dynamic"].copy(), np.float32(r)]
        if te or tr:
            obs, _ = env.reset()
    return out


def test_same_seed_gives_identical_rollouts():
    a = rollout(gym.make("SafeNav-v1", preset="medium"), seed=7)
    b = rollout(gym.make("SafeNav-v1", preset="medium"), seed=7)
    c = rollout(gym.make("SafeNav-v1", preset="medium"), seed=8)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c, strict=True))


def test_vector_env_equals_single_envs_step_for_step():
    n, seed = 3, 11
    vec = SafeNavVectorEnv(n, preset="easy", num_worlds=n)
    singles = [gym.make("SafeNav-v1", preset="easy").unwrapped for _ in range(n)]
    vobs, _ = vec.reset(seed=seed)
    sobs = [e.reset(seed=seed + i)[0] for i, e in enumerate(singles)]
    for i in range(n):
        for k in vobs:
            np.testing.assert_array_equal(sobs[i][k], vobs[k][i])
    rng = np.random.default_rng(1)
    for _ in range(120):
        a = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
        vobs, vr, vte, vtr, vinfo = vec.step(a)
        for i, e in enumerate(singles):
            o, r, te, tr, info = e.step(a[i])
            assert (te, tr) == (bool(vte[i]), bool(vtr[i]))
            assert r == pytest.approx(float(vr[i]), abs=1e-5)
            assert info["cost"] == float(vinfo["cost"][i])
            final = vinfo["final_obs"] if (te or tr) else vobs
            for k in o:
                np.testing.assert_allclose(o[k], final[k][i], atol=1e-5)
            if te or tr:
                o, _ = e.reset()
                for k in o:
                    np.testing.assert_allclose(o[k], vobs[k][i], atol=1e-5)


def test_fixed_test_scenario_is_bit_identical():
    cfg = make_config("paper")
    s1, g1 = fixed_scenario(cfg, env_seed=1, episodes=200)
    s2, g2 = fixed_scenario(cfg, env_seed=1, episodes=200)
    assert torch.equal(s1, s2) and torch.equal(g1, g2)
    assert s1.shape == (200, 3)
    # Golden values: the integer hash and IEEE float32 arithmetic give these on every machine.
    assert s1[0].tolist() == [-24.0, -9.215079307556152, 1.3129823207855225]
    assert (g1[:, :2] - s1[:, :2]).norm(dim=-1).min() >= cfg.min_goal_distance


# ---------------------------------------------------------------- collision geometry
@pytest.mark.parametrize(
    ("start", "collides"),
    [
        ((0.0, -0.69, 1.0), True),  # side of a 0.8 m pillar at (0, 0): face at y=-0.4, gap 0.29
        ((0.0, -0.71, 1.0), False),  # gap 0.31 > radius
        ((0.6, -0.6, 1.0), True),  # corner: distance sqrt(0.2^2 + 0.2^2) = 0.283
        ((0.63, -0.63, 1.0), False),  # corner: 0.325
        ((0.0, 0.0, 2.25), True),  # above a 2 m pillar by 0.25
        ((0.0, 0.0, 2.35), False),  # above it by 0.35
    ],
)
def test_pillar_collision_geometry(start, collides):
    env = hand_env(pillars=[(0.0, 0.0, 0.8, 2.0)])
    place(env, start)
    _, _, term, _, info = hover_step(env)
    assert bool(info["collision"][0]) is collides
    assert float(info["cost"][0]) == (1.0 if collides else 0.0)
    if collides:  # the episode record says what was hit
        ep = info["episode"]
        assert (
            bool(ep["hit_static"][0]),
            bool(ep["hit_dynamic"][0]),
            bool(ep["out_of_bounds"][0]),
        ) == (True, False, False)


@pytest.mark.parametrize(
    ("start", "body", "navrl"),
    [
        ((0.0, -0.69, 1.0), True, True),  # the side: a level beam reads ~0.29 < 0.3
        ((0.0, -0.71, 1.0), False, False),  # the side at 0.31
        # just above the top edge: the level beam passes over, the -10 deg beam meets the side
        # at 0.2945 (the grid range image would read 0.3046: the exact cast is needed)
        ((0.0, -0.69, 2.02), True, True),
        ((0.0, 0.0, 2.047), True, True),  # over the top by 0.047: -10 deg reads 0.27 on the top
        ((0.0, 0.0, 2.25), True, False),  # over the top by 0.25: the -10 deg beam hits the
        # top plane 1.4 m out, past the pillar's edge (0.4 m), so no beam reads < 0.3
        ((0.0, 0.0, 2.35), False, False),
    ],
)
def test_navrl_collision_rule_counts_only_what_a_beam_reads(start, body, navrl):
    """``collision_rule="navrl"`` is NavRL's ``max(lidar_scan) > lidar_range - 0.3``: a graze of
    a pillar top that no beam sees is no collision, a side within 0.3 m still is."""
    for rule, collides in (("body", body), ("navrl", navrl)):
        env = hand_env(pillars=[(0.0, 0.0, 0.8, 2.0)], collision_rule=rule)
        place(env, start)
        _, _, _, _, info = hover_step(env)
        assert bool(info["collision"][0]) is collides, rule


def test_collision_rule_is_checked():
    with pytest.raises(ValueError, match="collision_rule"):
        make_config("easy", collision_rule="lidar")


@pytest.mark.parametrize(
    ("start", "collides"),
    [
        ((0.0, -0.75, 1.0), True),  # standing cylinder of width 1.0: surface at 0.5, gap 0.25
        ((0.0, -0.85, 3.5), False),  # gap 0.35, at any altitude
        ((0.0, -0.79, 3.9), True),  # cylinder is 5 m tall: collides high up too
    ],
)
def test_standing_cylinder_geometry(start, collides):
    env = hand_env(movers=[(0.0, 0.0, 2.5, 1.0, False)])
    place(env, start)
    _, _, _, _, info = hover_step(env)
    assert bool(info["collision"][0]) is collides
    if collides:
        ep = info["episode"]
        assert (
            bool(ep["hit_static"][0]),
            bool(ep["hit_dynamic"][0]),
            bool(ep["out_of_bounds"][0]),
        ) == (False, True, False)


@pytest.mark.parametrize(
    ("start", "collides"),
    [
        ((0.0, 0.0, 3.25), False),  # cuboid spans z in [1.5, 2.5]: above by 0.75
        ((0.0, 0.0, 2.75), True),  # above by 0.25
        ((0.0, 0.0, 1.25), True),  # below by 0.25
        ((0.0, 0.0, 0.85), False),  # below by 0.65
        ((0.0, -0.7, 2.0), True),  # level, side at y=-0.5: gap 0.2
        ((0.0, -0.9, 2.0), False),  # level, gap 0.4
    ],
)
def test_floating_cuboid_geometry(start, collides):
    env = hand_env(movers=[(0.0, 0.0, 2.0, 1.0, True)])
    place(env, start)
    _, _, _, _, info = hover_step(env)
    assert bool(info["collision"][0]) is collides


def test_ground_and_ceiling_are_collisions():
    env = hand_env()
    for z in (0.15, 4.1):
        place(env, (0.0, 0.0, z))
        info = hover_step(env)[4]
        assert bool(info["collision"][0])
        ep = info["episode"]
        assert (
            bool(ep["hit_static"][0]),
            bool(ep["hit_dynamic"][0]),
            bool(ep["out_of_bounds"][0]),
        ) == (False, False, True)
    place(env, (0.0, 0.0, 2.0))
    assert not bool(hover_step(env)[4]["collision"][0])


# ---------------------------------------------------------------- sensing
def analytic_beam_distance(pos, az, box_lo, box_hi):
    """Horizontal beam from ``pos`` at azimuth ``az`` against one box (slab method)."""
    d = np.array([math.cos(az), math.sin(az), 0.0])
    t_near, t_far = -np.inf, np.inf
    for i in range(3):
        if abs(d[i]) < 1e-12:
            if not box_lo[i] <= pos[i] <= box_hi[i]:
                return np.inf
            continue
        t1, t2 = (box_lo[i] - pos[i]) / d[i], (box_hi[i] - pos[i]) / d[i]
        t_near, t_far = max(t_near, min(t1, t2)), min(t_far, max(t1, t2))
    return t_near if t_far >= t_near >= 0 else np.inf


def test_range_image_matches_analytic_distance_to_pillars():
    pillars = [(2.0, 0.3, 0.8, 5.0), (-1.1, 2.6, 0.4, 5.0), (0.2, -3.05, 0.8, 1.0)]
    env = hand_env(pillars=pillars)
    start = (0.0, 0.0, 1.5)
    place(env, start, goal=(8.0, 0.0, 1.5))  # goal frame = world frame (yaw 0)
    obs, _ = env._sense()
    ranges = (1 - obs["lidar"][0]) * env.cfg.lidar_range
    res = env.cfg.grid_resolution
    row = env.cfg.lidar_v_angles.index(0.0)
    checked = 0
    for j in range(36):
        az = 2 * math.pi * j / 36
        best = min(
            analytic_beam_distance(
                np.array(start),
                az,
                np.array([x - s / 2, y - s / 2, 0]),
                np.array([x + s / 2, y + s / 2, h]),
            )  # fmt: skip
            for x, y, s, h in pillars
        )
        expect = min(best, env.cfg.lidar_range)
        # grazing beams (within half a cell of a corner) may round either way
        if expect < env.cfg.lidar_range:
            checked += 1
        assert abs(float(ranges[row, j]) - expect) <= res + 1e-4 or _grazing(
            start, az, pillars, res
        )
    assert checked >= 4
    # the 1 m pillar is under the 0 deg beam at 1.5 m altitude: not seen by it
    assert float(ranges[row, 27]) == pytest.approx(env.cfg.lidar_range)


def _grazing(start, az, pillars, res) -> bool:
    for x, y, s, _ in pillars:
        for cx in (x - s / 2, x + s / 2):
            for cy in (y - s / 2, y + s / 2):
                # perpendicular distance from the corner to the beam line
                dx, dy = cx - start[0], cy - start[1]
                if abs(-math.sin(az) * dx + math.cos(az) * dy) < res:
                    return True
    return False


def test_grid_raycaster_agrees_with_bruteforce():
    a = SafeNavVectorEnv(16, preset="medium", output="torch")
    b = SafeNavVectorEnv(16, preset="medium", output="torch", raycaster="bruteforce")
    a.reset(seed=5)
    b.reset(seed=5)
    errs = []
    for _ in range(30):
        act = torch.rand(16, 3) * 2 - 1
        oa, ob = a.step(act)[0], b.step(act)[0]
        errs.append(((oa["lidar"] - ob["lidar"]).abs() * a.cfg.lidar_range).flatten())
    err = torch.cat(errs)
    assert (err <= a.cfg.grid_resolution + 1e-4).float().mean() > 0.97
    assert float(err.median()) == 0.0


def test_downward_beam_sees_the_ground():
    env = hand_env()
    place(env, (0.0, 0.0, 0.5))
    _, aux = env._sense()
    row = env.cfg.lidar_v_angles.index(-10.0)
    expect = 0.5 / math.sin(math.radians(10))
    assert torch.allclose(aux["ranges"][0, row], torch.full((36,), expect), atol=1e-3)


def test_dynamic_features_track_nearest_in_range():
    movers = [
        (1.5, 0.0, 2.5, 0.5, False),
        (0.0, 3.0, 1.5, 1.0, True),
        (0.0, -6.0, 2.5, 0.25, False),
    ]
    env = hand_env(movers=movers)
    place(env, (0.0, 0.0, 1.5), goal=(8.0, 0.0, 1.5))
    obs, _ = env._sense()
    dyn = obs["dynamic"][0]
    assert torch.allclose(dyn[0, :3], torch.tensor([1.0, 0.0, 0.0]), atol=1e-5)  # cylinder: z rel 0
    assert float(dyn[0, 3]) == pytest.approx(1.5 / 4)
    assert float(dyn[0, 8]) == pytest.approx(1 / 3) and float(dyn[0, 9]) == 0.0
    assert float(dyn[1, 3]) == pytest.approx(3.0 / 4) and float(dyn[1, 9]) == 1.0
    assert torch.all(dyn[2:] == 0)  # the third is 6 m away: beyond range


# ---------------------------------------------------------------- reward, cost, episode ends
def test_cost_is_one_exactly_at_collision_steps():
    env = hand_env(pillars=[(0.0, 0.0, 0.8, 5.0)], terminate_on_collision=False)
    place(env, (-3.0, 0.0, 1.5), goal=(8.0, 0.0, 1.5))
    costs, collided = [], []
    for _ in range(60):
        _, _, _, _, info = env.step(torch.tensor([[0.5, 0.0, 0.0]]))
        costs.append(float(info["cost"][0]))
        collided.append(float(info["clearance"][0]) <= 0.0)
    assert costs == [1.0 if c else 0.0 for c in collided]
    assert 0 < sum(costs) < 60


def test_reward_collision_is_paid_at_collision_steps_only():
    """``reward_collision`` changes the reward of the collision step by exactly its value and
    leaves every other step (and the cost) as it was."""
    runs = []
    for penalty in (0.0, -100.0):
        env = hand_env(pillars=[(0.0, 0.0, 0.8, 5.0)], terminate_on_collision=False,
                       reward_collision=penalty)  # fmt: skip
        place(env, (-3.0, 0.0, 1.5), goal=(8.0, 0.0, 1.5))
        steps = [env.step(torch.tensor([[0.5, 0.0, 0.0]])) for _ in range(60)]
        runs.append([(float(r[0]), float(i["cost"][0])) for _, r, _, _, i in steps])
    plain, penalised = runs
    assert [c for _, c in plain] == [c for _, c in penalised] and sum(c for _, c in plain) > 0
    for (r0, c), (r1, _) in zip(plain, penalised, strict=True):
        assert r1 == pytest.approx(r0 - 100.0 * c, abs=1e-4)
    with pytest.raises(ValueError, match="reward_collision"):
        make_config("easy", reward_collision=1.0)


def test_stall_penalty_starts_after_stall_seconds_without_progress_and_stops_at_progress():
    """``w_stall`` (a named departure) subtracts its weight at each step from ``stall_seconds``
    of hovering on, nothing while the UAV closes on the goal, and stops at the next progress."""
    runs = []
    for w in (0.0, 0.5):
        env = hand_env(w_stall=w, stall_seconds=1.0, stall_progress=0.5)  # 10 steps at 10 Hz
        place(env, (-3.0, 0.0, 1.5), goal=(8.0, 0.0, 1.5))
        actions = [[0.0, 0.0, 0.0]] * 25 + [[1.0, 0.0, 0.0]] * 15  # hover 2.5 s, then fly at it
        steps = [env.step(torch.tensor([a])) for a in actions]
        runs.append([float(r[0]) for _, r, _, _, _ in steps])
    plain, stalled = runs
    extra = [r0 - r1 for r0, r1 in zip(plain, stalled, strict=True)]
    assert extra[:9] == pytest.approx([0.0] * 9, abs=1e-5)  # 9 steps: no penalty yet
    assert extra[9:25] == pytest.approx([0.5] * 16, abs=1e-5)  # from the 10th stalled step on
    assert extra[-5:] == pytest.approx([0.0] * 5, abs=1e-5)  # flying at the goal: progress
    for name, bad in (("w_stall", -0.5), ("stall_seconds", 0.0), ("stall_progress", -1.0),
                      ("w_stall", float("nan"))):  # fmt: skip
        with pytest.raises(ValueError, match=name):
            make_config("easy", **{name: bad})


def test_near_miss_cost_is_one_at_the_first_step_within_the_margin_and_contact_is_unchanged():
    """``near_miss_margin`` (a named departure from Eq. 3): the cost is 1 at the episode's first
    step whose clearance falls under the margin and 0 at every other step, even at a later
    contact; collisions are still counted as contact; a reset re-arms it."""
    runs = {}
    for margin in (0.0, 0.5):
        env = hand_env(pillars=[(0.0, 0.0, 0.8, 5.0)], terminate_on_collision=False,
                       near_miss_margin=margin)  # fmt: skip
        for episode in range(2):
            place(env, (-3.0, 0.0, 1.5), goal=(8.0, 0.0, 1.5))
            steps = [env.step(torch.tensor([[0.5, 0.0, 0.0]])) for _ in range(60)]
            runs[margin, episode] = [(float(i["cost"][0]), bool(i["collision"][0]),
                                      float(i["clearance"][0])) for *_, i in steps]  # fmt: skip
    contact = runs[0.0, 0]
    assert [c for c, _, _ in contact] == [float(hit) for _, hit, _ in contact]  # Eq. 3
    for episode in range(2):
        near = runs[0.5, episode]
        assert [hit for _, hit, _ in near] == [hit for _, hit, _ in contact]  # contact unchanged
        first = next(t for t, (_, _, clear) in enumerate(near) if clear < 0.5)
        assert first < next(t for t, (_, hit, _) in enumerate(near) if hit)  # before contact
        assert [c for c, _, _ in near] == [float(t == first) for t in range(len(near))]
    for bad in (-0.1, 3.0, float("nan")):
        with pytest.raises(ValueError, match="near_miss_margin"):
            make_config("easy", near_miss_margin=bad)


@pytest.mark.parametrize(
    "x, z, until, extra",
    [
        (-3.0, 2.0, 5.0, -8.0 * (2.0 - 0.9) ** 2),  # far, in the start-goal band: cruise penalty
        (-3.0, 0.6, 5.0, 8.0 * (1.8 - 0.6) ** 2),  # far, low: the start-goal band's penalty lifted
        (5.0, 0.6, 5.0, 0.0),  # within cruise_until (5 m): NavRL's band as before
        (5.0, 0.6, 3.2, 0.0),  # 3.0 m away horizontally (3.3 m in 3-D): the distance is horizontal
    ],
)
def test_cruise_height_moves_the_height_band_only_far_from_the_goal(x, z, until, extra):
    """``cruise_height`` (a named departure) swaps the height penalty's band for cruise_height +-
    0.3 m while the goal is farther than ``cruise_until`` horizontally, and changes nothing else."""
    rewards = []
    for cruise in (0.0, 0.6):
        env = hand_env(cruise_height=cruise, cruise_until=until)
        place(env, (-3.0, 0.0, 2.0), goal=(8.0, 0.0, 2.0))  # start-goal band [1.8, 2.2]
        env.pos[0] = torch.tensor([x, 0.0, z])
        _, r, _, _, info = hover_step(env)
        rewards.append((float(r[0]), float(info["cost"][0])))
    (r0, c0), (r1, c1) = rewards
    assert c0 == c1 == 0.0
    assert r1 - r0 == pytest.approx(extra, abs=1e-3)
    for bad in (0.4, 3.8, -1.0):
        with pytest.raises(ValueError, match="cruise_height"):
            make_config("easy", cruise_height=bad)
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="cruise_until"):
            make_config("easy", cruise_until=bad)


def test_cruise_ramp_moves_the_band_linearly_between_cruise_and_goal():
    """With ``cruise_ramp`` the band's bounds go linearly from the cruise band (beyond
    cruise_until + ramp) to the start-goal band (within cruise_until): no penalty cliff."""
    penalties = []
    for x in (-3.0, 1.0, 3.5):  # 11, 7 and 4.5 m from the goal: all, half and none of the cruise
        rewards = []
        for cruise in (0.0, 0.6):
            env = hand_env(cruise_height=cruise, cruise_until=5.0, cruise_ramp=4.0)
            place(env, (-3.0, 0.0, 2.0), goal=(8.0, 0.0, 2.0))  # start-goal band [1.8, 2.2]
            env.pos[0] = torch.tensor([x, 0.0, 0.6])
            rewards.append(float(hover_step(env)[1][0]))
        penalties.append(rewards[0] - rewards[1])  # the cruise penalty minus NavRL's
    lo_half = 1.8 + 0.5 * (0.3 - 1.8)  # the lower bound halfway: 1.05 m
    assert penalties == pytest.approx(
        [-8.0 * 1.2**2, -8.0 * 1.2**2 + 8.0 * (lo_half - 0.6) ** 2, 0.0], abs=1e-3
    )
    with pytest.raises(ValueError, match="cruise_ramp"):
        make_config("easy", cruise_ramp=-1.0)


def test_truncation_is_not_termination():
    env = SafeNavVectorEnv(1, preset="easy", output="torch", max_episode_seconds=1.0, num_static=0,
                           num_dynamic=0)  # fmt: skip
    env.reset(seed=0)
    for _ in range(10):
        _, _, term, trunc, info = env.step(torch.zeros(1, 3))
    assert bool(trunc[0]) and not bool(term[0])
    assert bool(info["_final_obs"][0]) and bool(info["episode"]["timeout"][0])


def run_policy(env, policy, steps=400):
    obs, _ = env.reset(seed=0)
    total = 0.0
    for _ in range(steps):
        obs, r, term, trunc, info = env.step(policy(obs))
        total += float(r[0])
        if bool(term[0] or trunc[0]):
            return total, bool(info["success"][0]), bool(info["collision"][0])
    return total, False, False


def test_go_to_goal_beats_hovering_and_crashing():
    make = lambda: SafeNavVectorEnv(1, preset="easy", output="torch", num_static=0, num_dynamic=0,  # noqa: E731
                                    autoreset_mode="Disabled")  # fmt: skip
    ret_goal, success, _ = run_policy(make(), go_to_goal)
    ret_hover, s_h, _ = run_policy(make(), lambda o: torch.zeros(1, 3))
    ret_crash, _, crashed = run_policy(make(), lambda o: torch.tensor([[0.0, 0.0, -1.0]]))
    assert success and not s_h and crashed
    assert ret_goal > ret_hover and ret_goal > ret_crash


def test_density_activates_a_prefix_of_obstacles():
    env = SafeNavVectorEnv(2, preset="medium", output="torch")
    env.reset(seed=0)
    full = int((env.heights > 0).sum())
    env.set_density(0.2)
    assert env.n_static == 16 and env.n_dynamic == round(24 * 0.2)
    assert 0 < int((env.heights > 0).sum()) < full


# ---------------------------------------------------------------- configuration errors
@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        (dict(num_static=-1), "num_static"),
        (dict(num_dynamic=-3), "num_dynamic"),
        (dict(v_max=0.0), "v_max"),
        (dict(v_max=-2.0), "v_max"),
        (dict(num_static=100000), "num_static"),
        (dict(density=1.5), "density"),
        (dict(map_size=float("nan")), "map_size"),
    ],
)
def test_bad_config_names_the_field(overrides, field):
    with pytest.raises(ValueError, match=field):
        make_config("paper", **overrides)


def test_unknown_preset_and_field():
    with pytest.raises(ValueError, match="preset"):
        make_config("hard")
    with pytest.raises(ValueError, match="warp_speed"):
        make_config("easy", warp_speed=3)
    with pytest.raises(ValueError, match="preset"):
        gym.make("SafeNav-v1", preset="nope")


def test_bad_actions_raise_clear_errors():
    env = SafeNavVectorEnv(2, preset="easy")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.full((2, 3), np.nan, dtype=np.float32))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((3, 3), dtype=np.float32))


def test_config_is_a_typed_dataclass_with_paper_defaults():
    cfg = EnvConfig()
    assert (cfg.map_size, cfg.num_static, cfg.num_dynamic, cfg.v_max) == (50.0, 350, 100, 2.0)
    assert cfg.max_episode_steps == 600
    assert sensors.RangeImageSpec.for_config(cfg).num_samples == 40
