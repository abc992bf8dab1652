"""``redraw_maps`` and ``--map-refresh-mode per-env``: new training maps without cutting an
episode. Each env ends the episode it flies in its old map, then starts the next one in the new
map of its slot; the episodes in flight are exactly those of an env that never redrew."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from safenav.envs.nav import SafeNavVectorEnv

pytestmark = pytest.mark.usefixtures("one_thread")

N, W = 8, 4


def make_env() -> SafeNavVectorEnv:
    # Short episodes (8 s = 80 steps) so that every env ends one within the test.
    env = SafeNavVectorEnv(num_envs=N, preset="easy", output="torch", num_worlds=W,
                           max_episode_seconds=8.0)  # fmt: skip
    env.reset(seed=3)
    return env


def test_redraw_cuts_no_episode_and_moves_each_env_at_its_next_episode():
    env, twin = make_env(), make_env()
    gen = torch.Generator().manual_seed(0)
    act = lambda: torch.rand(N, 3, generator=gen) * 2 - 1  # noqa: E731
    for _ in range(5):
        a = act()
        env.step(a)
        twin.step(a)
    env.redraw_maps(50)
    assert len(env.worlds) == 2 * W and env.pillar_xy.shape[0] == 2 * W
    moved = torch.zeros(N, dtype=torch.bool)
    for _ in range(200):
        a = act()
        obs, reward, term, trunc, info = env.step(a)
        obs2, reward2, term2, trunc2, info2 = twin.step(a)
        # envs still in the episode they flew at the redraw: the same step as without it
        old = ~moved
        assert torch.equal(reward[old], reward2[old])
        assert torch.equal(term[old], term2[old]) and torch.equal(trunc[old], trunc2[old])
        ended = term | trunc
        for k in obs:
            assert torch.equal(obs[k][old & ~ended], obs2[k][old & ~ended]), k
            last = old & ended
            if bool(last.any()):
                assert torch.equal(info["final_obs"][k][last], info2["final_obs"][k][last]), k
        moved |= ended
        # an env that ended an episode flies the new map of its slot from then on
        slots = env.world_idx[moved]
        assert torch.equal(slots, W + torch.arange(N)[moved] % W)
        assert torch.equal(env.world_seed[slots], 50 + torch.arange(N)[moved] % W)
        assert torch.equal(env.world_idx[~moved], torch.arange(N)[~moved] % W)
        if bool(moved.all()):
            break
    assert bool(moved.all()), "every env should end an 80-step episode within 200 steps"
    assert env.can_redraw_maps()
    # one map set again: the broadcast observation equals the per-env one
    fast, _ = env._sense()
    each, _ = env._sense(torch.arange(N))
    for k in fast:
        assert torch.equal(fast[k], each[k]), k


def test_a_second_redraw_waits_for_every_env_and_reset_returns_to_one_map_set():
    env = make_env()
    env.redraw_maps(50)
    assert not env.can_redraw_maps()
    with pytest.raises(RuntimeError, match="two redraws ago"):
        env.redraw_maps(60)  # no env has moved yet
    for _ in range(200):
        env.step(torch.zeros(N, 3))
        if env.can_redraw_maps():
            break
    assert env.can_redraw_maps()
    env.redraw_maps(60)  # the first set's slots, drawn anew
    assert env.pillar_xy.shape[0] == 2 * W
    assert torch.equal(env.world_seed[:W], 60 + torch.arange(W))
    assert torch.equal(env.world_seed[W:], 50 + torch.arange(W))
    env.reset(seed=7)
    assert len(env.worlds) == W and env.pillar_xy.shape[0] == W and env.can_redraw_maps()
    assert torch.equal(env.world_idx, torch.arange(N) % W)
    o1, _ = env.reset(seed=7)
    o2, _ = make_env().reset(seed=7)
    for k in o1:
        assert torch.equal(o1[k], o2[k]), k


@pytest.mark.long
def test_train_with_per_env_map_refresh(tmp_path):
    from safenav.cli import main

    run = tmp_path / "run"
    # 16 envs x the easy preset's 300-step limit: maps every 4800 env steps, twice in 10k.
    main(["train", "--algo", "ppo", "--preset", "easy", "--num-envs", "16", "--total-steps",
          "10000", "--map-refresh-every", "4800", "--map-refresh-mode", "per-env",
          "--eval-every", "0", "--no-progress", "--no-tensorboard", "--run-dir", str(run)])  # fmt: skip
    events = [json.loads(line) for line in (run / "events.jsonl").read_text().splitlines()]
    maps = [e for e in events if e["event"] == "maps"]
    assert [e["global_step"] // 4800 for e in maps] == [1, 2]
    assert all(e["mode"] == "per-env" for e in maps)
    assert json.loads((run / "config.json").read_text())["run"]["map_refresh_mode"] == "per-env"
    rows = (run / "progress.csv").read_text().splitlines()
    assert len(rows) > 1 and np.isfinite(float(rows[-1].split(",")[1]))


def test_the_memory_estimate_counts_both_map_sets_of_per_env_redraws(monkeypatch):
    """A per-env run holds the old and the new maps (2 x the maps' memory, ``redraw_maps``); the
    estimate that refuses a run too large for the machine counts both."""
    import safenav.common.checks as checks
    from safenav.algos.config import CSACConfig
    from safenav.commands.train import check_training_memory
    from safenav.common.config import RunConfig
    from safenav.common.memory import env_bytes
    from safenav.envs.vector import env_spaces

    obs_shapes, action_dim, env_cfg, _ = env_spaces("SafeNav-v1", "easy")
    one, two = env_bytes(64, env_cfg), env_bytes(64, env_cfg, map_sets=2)
    maps = min(env_cfg.num_worlds or 16, 64) * (env_cfg.map_size / env_cfg.grid_resolution) ** 2
    assert two - one == pytest.approx(maps * 16) and maps > 0
    seen = []
    monkeypatch.setattr(checks, "check_memory", lambda need, *a, **k: seen.append(need))
    cfg = CSACConfig()
    for mode in ("all", "per-env"):
        run = RunConfig(num_envs=64, total_steps=100_000, preset="easy", map_refresh_mode=mode)
        check_training_memory("csac", run, cfg, obs_shapes, action_dim, env_cfg)
    assert seen[1] - seen[0] == pytest.approx(two - one)
