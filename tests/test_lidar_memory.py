"""``EnvConfig.lidar_memory``: the memory image appended to the range image (beyond the paper);
the beams' elevations as a string from the command line; the onboard runtime's memory image."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import train_tiny_csac
from safenav.cli import main
from safenav.deploy.export import OnnxPolicy, check_deployable, load_sidecar
from safenav.deploy.runtime import OnboardRuntime, RuntimeConfig
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


def test_memory_policies_fly_their_own_observation_and_deploy() -> None:
    cfg = make_config("paper", lidar_memory=10)
    assert scenario_config(cfg, "easy").lidar_memory == 10
    check_deployable(cfg, "policy.pt")  # the onboard runtime builds the memory image
    with pytest.raises(SafenavError, match="lidar_history"):
        check_deployable(make_config("paper", lidar_memory=10, lidar_history=2), "policy.pt")


def _runtime_of(env: SafeNavVectorEnv, i: int, config: RuntimeConfig | None = None):
    """An onboard runtime that sees env ``i``'s map and flies to its goal."""
    g2 = env.grid.size**2
    w = int(env.world_idx[i])
    rt = OnboardRuntime(lambda s, lidar, d: np.zeros((1, 3), np.float32), env.cfg,
                        config or RuntimeConfig(require_tracker=False))  # fmt: skip
    rt.map.cast_map = env.heights[w * g2 : (w + 1) * g2].clone()
    rt.update_state(env.pos[i].numpy(), env.vel[i].numpy())
    rt.set_goal(env.goal[i].numpy(), start=env.start[i].numpy())
    return rt


def test_the_onboard_runtime_builds_the_envs_memory_image() -> None:
    """Same map, same flight -> the runtime's memory image is the env's at every step (its
    odometry places the remembered hits as the env's state does), and a new goal forgets."""
    env = _env(n=4, memory=5)
    obs, _ = env.reset(seed=200_004)
    runtimes = {i: _runtime_of(env, i) for i in range(4)}  # until its episode ends
    compared = gained = 0.0
    for _ in range(40):
        for i, rt in runtimes.items():
            rt.update_state(env.pos[i].numpy(), env.vel[i].numpy())
            peek, _ = rt.observation()  # looking does not remember
            mine, _ = rt.observation(remember=True)
            assert torch.equal(peek["lidar"], mine["lidar"])
            assert mine["lidar"].shape == (1, 2 * E, 36)
            torch.testing.assert_close(mine["lidar"][0], obs["lidar"][i], atol=1e-5, rtol=0)
            gained = max(gained, float((mine["lidar"][0, E:] - mine["lidar"][0, :E]).max()))
            compared += 1
        obs, _, term, trunc, _ = env.step(go_to_goal(obs))
        for i in (term | trunc).nonzero().flatten().tolist():
            runtimes.pop(i, None)
    assert compared >= 80 and gained > 0.2  # many steps, and the memory showed more
    rt = _runtime_of(env, 0)
    for _ in range(3):
        rt.observation(remember=True)
    rt.update_state(env.pos[0].numpy() + 1.0, env.vel[0].numpy())
    rt.set_goal(env.goal[0].numpy(), start=env.pos[0].numpy())  # a new flight
    fresh, _ = rt.observation(remember=True)
    torch.testing.assert_close(fresh["lidar"][0, E:], fresh["lidar"][0, :E], atol=1e-5, rtol=0)


def test_fly_spans_the_memorys_seconds_at_its_setpoint_rate() -> None:
    cfg = make_config("paper", lidar_memory=10)  # 10 images at 10 Hz: 1 s
    assert RuntimeConfig.for_flight(cfg, 0, 20.0).policy_memory == 20
    assert RuntimeConfig.for_flight(cfg, 1, 10.0).policy_memory == 10
    assert RuntimeConfig.for_flight(make_config("paper"), 0, 20.0).policy_memory == 0


def test_a_memory_policy_exports_and_its_sidecar_says_so(tmp_path) -> None:
    pytest.importorskip("onnxruntime")
    run = train_tiny_csac(tmp_path / "memory", "lidar_memory", "3")
    onnx = tmp_path / "policy.onnx"
    main(["export", str(run / "checkpoint.pt"), "--onnx", str(onnx)])
    meta, cfg = load_sidecar(onnx)
    assert cfg.lidar_memory == 3
    lidar = meta["observation"]["lidar"]
    assert lidar["shape"] == [8, 36] and lidar["memory_rows"]["control_steps"] == 3
    runtime = OnboardRuntime(OnnxPolicy(onnx), cfg, RuntimeConfig(require_tracker=False))
    runtime.update_state([0.0, -8.0, 1.5], [0.0, 0.0, 0.0])
    runtime.update_points(np.zeros((0, 3)))
    runtime.set_goal([0.0, 8.0, 1.5])
    setpoint = runtime.step()
    assert not setpoint.hover and setpoint.observation["lidar"].shape == (8, 36)


def test_tuple_fields_from_the_command_line() -> None:
    """``--env-kwargs lidar_v_angles "(-30,-15,0,15)"`` arrives as a string: make_config reads it."""
    assert make_config("paper", lidar_v_angles="(-30,-15,0,15)").lidar_v_angles == (-30, -15, 0, 15)
    assert make_config("paper", lidar_v_angles="0, 10").lidar_v_angles == (0.0, 10.0)
    assert make_config("paper", lidar_v_angles=[-30, 0]).lidar_v_angles == (-30, 0)  # TOML array
    with pytest.raises(ValueError, match="comma-separated"):
        make_config("paper", lidar_v_angles="low,high")
    env = SafeNavVectorEnv(2, preset="paper", output="torch", lidar_v_angles="-30,-15,0,15")
    assert env.cfg.lidar_v_angles == (-30.0, -15.0, 0.0, 15.0)
