"""``EnvConfig.lidar_memory``: the memory image appended to the range image (beyond the paper);
the beams' elevations as a string from the command line."""

from __future__ import annotations

import pytest
import torch

from safenav.deploy.export import check_deployable
from safenav.envs.config import make_config, observation_shapes
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.scripted import go_to_goal
from safenav.errors import SafenavError
from safenav.experiments.flight import scenario_config

E = 4  # elevation rows


def _env(n: int = 8, memory: int = 10, **kw) -> SafeNavVectorEnv:
    return SafeNavVectorEnv(n, preset="paper", output="torch", lidar_memory=memory, **kw)


def test_layout_and_validation() -> None:
    assert observation_shapes(make_config("paper"))["lidar"] == (4, 36)
    assert observation_shapes(make_config("paper", lidar_memory=10))["lidar"] == (8, 36)
    assert observation_shapes(make_config("paper", lidar_memory=5, lidar_history=2))["lidar"] == (
        12,
        36,
    )
    assert observation_shapes({"lidar_v_angles": [0, 10], "lidar_h_beams": 36,
                               "num_tracked": 5})["lidar"] == (2, 36)  # fmt: skip
    for bad in (-1, 101, 2.5, True):
        with pytest.raises(ValueError, match="lidar_memory"):
            make_config("paper", lidar_memory=bad)
    env = _env(2)
    assert env.single_observation_space["lidar"].shape == (8, 36)


def test_first_image_is_its_own_memory_then_memory_only_adds() -> None:
    env = _env()
    obs, _ = env.reset(seed=200_000)
    cur, mem = obs["lidar"][:, :E], obs["lidar"][:, E:]
    assert torch.allclose(mem, cur, atol=1e-4)  # the same points, re-projected
    gained = 0.0
    for _ in range(30):
        obs, *_ = env.step(go_to_goal(obs))
        cur, mem = obs["lidar"][:, :E], obs["lidar"][:, E:]
        # the current image's points are remembered: no cell of the memory is farther
        assert (mem >= cur - 1e-4).all()
        gained = max(gained, float((mem - cur).max()))
    assert gained > 0.2  # and it shows obstacles the current image no longer does


def test_one_step_memory_is_the_current_image() -> None:
    env = _env(memory=1)
    obs, _ = env.reset(seed=200_001)
    for _ in range(5):
        obs, *_ = env.step(go_to_goal(obs))
        assert torch.allclose(obs["lidar"][:, E:], obs["lidar"][:, :E], atol=1e-4)


def test_a_new_episode_forgets() -> None:
    env = _env(n=4)
    obs, _ = env.reset(seed=200_002)
    action = torch.tensor([[1.0, 0.0, -1.0]]).repeat(4, 1)  # dive: every episode crashes soon
    for _ in range(100):
        obs, _, term, trunc, info = env.step(action)
        done = term | trunc
        if done.any():
            i = done.nonzero()[0, 0]
            # the first observation of the next episode: its memory is that image alone
            assert torch.allclose(obs["lidar"][i, E:], obs["lidar"][i, :E], atol=1e-4)
            # while the last observation of the old one remembered more
            assert info["final_obs"]["lidar"].shape == (4, 2 * E, 36)
            return
    pytest.fail("no episode ended")


def test_partial_reset_keeps_the_other_envs_memory() -> None:
    env = _env(n=4)
    obs, _ = env.reset(seed=200_003)
    for _ in range(15):
        obs, *_ = env.step(go_to_goal(obs))
    before = obs["lidar"].clone()
    mask = torch.tensor([True, False, False, False])
    obs, _ = env.reset(options={"reset_mask": mask})
    assert torch.allclose(obs["lidar"][1:], before[1:])  # unchanged state, unchanged memory
    assert torch.allclose(obs["lidar"][0, E:], obs["lidar"][0, :E], atol=1e-4)


def test_memory_policies_fly_their_own_observation_and_are_not_exported() -> None:
    cfg = make_config("paper", lidar_memory=10)
    assert scenario_config(cfg, "easy").lidar_memory == 10
    with pytest.raises(SafenavError, match="lidar_memory"):
        check_deployable(cfg, "policy.pt")
    check_deployable(make_config("paper"), "policy.pt")


def test_tuple_fields_from_the_command_line() -> None:
    """``--env-kwargs lidar_v_angles "(-30,-15,0,15)"`` arrives as a string: make_config reads it."""
    assert make_config("paper", lidar_v_angles="(-30,-15,0,15)").lidar_v_angles == (-30, -15, 0, 15)
    assert make_config("paper", lidar_v_angles="0, 10").lidar_v_angles == (0.0, 10.0)
    with pytest.raises(ValueError, match="comma-separated"):
        make_config("paper", lidar_v_angles="low,high")
    env = SafeNavVectorEnv(2, preset="paper", output="torch", lidar_v_angles="-30,-15,0,15")
    assert env.cfg.lidar_v_angles == (-30.0, -15.0, 0.0, 15.0)
