"""``EnvConfig.lidar_history``: a short memory of range images in the observation (beyond the
paper, default 1). Shapes, the history's shift and refills, bit-identity at 1, training and
evaluating a history policy, and the deploy refusal."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import train_tiny_csac
from safenav.cli import main
from safenav.envs.config import EnvConfig, make_config, observation_shapes
from safenav.envs.nav import SafeNavVectorEnv
from safenav.errors import SafenavError

pytestmark = pytest.mark.usefixtures("one_thread")
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                 reason="no CUDA device"))]  # fmt: skip
E = 4  # elevations of the range image


def rows(lidar: torch.Tensor, i: int) -> torch.Tensor:
    """The image of ``i`` steps ago in a stacked ``(N, E * k, C)`` observation."""
    return lidar[:, i * E : (i + 1) * E]


def images_equal(lidar: torch.Tensor, k: int) -> bool:
    return all(torch.equal(rows(lidar, i), rows(lidar, 0)) for i in range(1, k))


def actions(n: int, steps: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(steps, n, 3, generator=torch.Generator().manual_seed(seed)) * 2 - 1


# ---------------------------------------------------------------- configuration and shapes
@pytest.mark.parametrize("bad", [0, 9, 2.5, True, "3"])
def test_invalid_history_is_refused(bad):
    with pytest.raises(ValueError, match="lidar_history"):
        EnvConfig(lidar_history=bad)


def test_whole_floats_from_the_command_line_become_integers():
    # --env-kwargs NAME VALUE parses numbers as floats
    cfg = make_config("easy", lidar_history=3.0, num_tracked=4.0)
    assert cfg.lidar_history == 3 and isinstance(cfg.lidar_history, int) and cfg.num_tracked == 4
    with pytest.raises(ValueError, match="lidar_history"):
        make_config("easy", lidar_history=2.5)


def test_observation_shapes():
    assert observation_shapes(EnvConfig())["lidar"] == (4, 36)
    assert observation_shapes(EnvConfig(lidar_history=3))["lidar"] == (12, 36)
    old = {"lidar_v_angles": [-10, 0, 10, 20], "lidar_h_beams": 36, "num_tracked": 5}
    assert observation_shapes(old)["lidar"] == (4, 36)  # a checkpoint from before the option
    env = SafeNavVectorEnv(2, preset="easy", lidar_history=3)
    assert env.single_observation_space["lidar"].shape == (12, 36)
    obs, _ = env.reset(seed=0)
    assert obs["lidar"].shape == (2, 12, 36) and env.observation_space.contains(obs)


# ---------------------------------------------------------------- the history
def test_history_of_one_is_bit_identical_and_longer_ones_add_rows_only():
    n = 8
    plain, one, three = (SafeNavVectorEnv(n, preset="easy", output="torch", **kw)
                         for kw in ({}, {"lidar_history": 1}, {"lidar_history": 3}))  # fmt: skip
    obs = [e.reset(seed=7)[0] for e in (plain, one, three)]
    for t, a in enumerate([None, *actions(n, 20)]):
        if a is not None:
            steps = [e.step(a) for e in (plain, one, three)]
            obs = [s[0] for s in steps]
            for i in (1, 2, 3):  # reward, terminated, truncated
                assert all(torch.equal(s[i], steps[0][i]) for s in steps[1:])
        ref, o1, o3 = obs
        for key in ref:
            assert torch.equal(o1[key], ref[key]), (t, key)
        assert torch.equal(rows(o3["lidar"], 0), ref["lidar"]), t
        assert torch.equal(o3["state"], ref["state"]) and torch.equal(o3["dynamic"], ref["dynamic"])


@pytest.mark.parametrize("device", DEVICES)
def test_reset_fills_with_the_first_image_and_steps_shift(device):
    k, n = 3, 4
    env = SafeNavVectorEnv(n, preset="easy", device=device, output="torch", lidar_history=k)
    obs, _ = env.reset(seed=0)
    assert images_equal(obs["lidar"], k)
    assert bool((obs["lidar"] > 0).any())  # copies of a real image, not zeros
    prev = obs["lidar"]
    for a in actions(n, 3):
        obs, _, term, trunc, _ = env.step(a.to(device))
        assert not bool((term | trunc).any())
        assert torch.equal(rows(obs["lidar"], 1), rows(prev, 0))  # the previous current image
        assert torch.equal(rows(obs["lidar"], 2), rows(prev, 1))
        prev = obs["lidar"]
    assert not images_equal(obs["lidar"], k)  # it moved: the history differs from a fresh one
    last = obs["lidar"].clone()
    obs["lidar"].zero_()  # a caller's in-place change does not reach the env's history
    obs, *_ = env.step(torch.zeros(n, 3, device=device))
    assert torch.equal(rows(obs["lidar"], 1), rows(last, 0))


@pytest.mark.parametrize("device", DEVICES)
def test_autoreset_refills_only_the_finished_env(device):
    k = 2
    env = SafeNavVectorEnv(2, preset="easy", device=device, output="torch", lidar_history=k)
    env.reset(seed=0)
    # env 0 just above the ground, pushed down: a ground collision in a few steps; env 1 hovers
    starts = np.array([[0.0, -8.0, 0.21], [0.0, -8.0, 1.5]], np.float32)
    goals = np.array([[0.0, 8.0, 1.5], [0.0, 8.0, 1.5]], np.float32)
    prev = env.reset(options={"starts": starts, "goals": goals})[0]["lidar"]
    down = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]], device=device)
    for _ in range(20):
        obs, _, term, trunc, info = env.step(down)
        if bool(term[0]):
            break
        prev = obs["lidar"]
    assert bool(term[0]) and bool(info["collision"][0]) and not bool((term | trunc)[1])
    assert info["_final_obs"].tolist() == [True, False]
    final = info["final_obs"]["lidar"]
    assert torch.equal(rows(final, 1)[0], rows(prev, 0)[0])  # the finished episode's history
    assert not torch.equal(rows(final, 0)[0], rows(obs["lidar"], 0)[0])  # not the new episode's
    assert images_equal(obs["lidar"][:1], k)  # env 0: copies of its new episode's first image
    assert torch.equal(rows(obs["lidar"], 1)[1], rows(prev, 0)[1])  # env 1 flies on, shifted


def test_reset_mask_refills_only_the_masked_envs():
    k = 3
    env = SafeNavVectorEnv(2, preset="easy", output="torch", lidar_history=k,
                           autoreset_mode="Disabled")  # fmt: skip
    env.reset(seed=0)
    for a in actions(2, 4):
        obs, *_ = env.step(a)
    before = obs["lidar"]
    assert not images_equal(before[1:], k)
    obs, _ = env.reset(options={"reset_mask": np.array([True, False])})
    assert images_equal(obs["lidar"][:1], k)
    assert torch.equal(obs["lidar"][1], before[1])  # env 1 keeps its history


def test_shield_reads_the_current_image():
    from safenav.deploy.shield import env_shield

    env = SafeNavVectorEnv(3, preset="easy", output="torch", lidar_history=2)
    obs, _ = env.reset(seed=0)
    plain = SafeNavVectorEnv(3, preset="easy", output="torch")
    plain_obs, _ = plain.reset(seed=0)
    a = actions(3, 1)[0]
    assert torch.equal(env_shield(env, obs, a), env_shield(plain, plain_obs, a))


# ---------------------------------------------------------------- train, evaluate, deploy
@pytest.fixture(scope="module")
def history_run(tmp_path_factory) -> Path:
    torch.set_num_threads(1)
    run_dir = tmp_path_factory.mktemp("runs") / "history"
    return train_tiny_csac(run_dir, "lidar_history", "2")


def test_train_and_eval_with_history(history_run, tmp_path):
    from safenav.algos.policy import load_policy

    config = json.loads((history_run / "config.json").read_text())
    assert config["env_config"]["lidar_history"] == 2
    policy = load_policy(history_run / "checkpoint.pt")
    assert policy.obs_shapes["lidar"] == (8, 36) and policy.env_config().lidar_history == 2
    for extra in ([], ["--preset", "easy"]):  # a preset keeps the policy's history
        out = tmp_path / f"eval{len(extra)}.json"
        main(["eval", str(history_run), "--episodes", "2", "--json", str(out), *extra])
        assert json.loads(out.read_text())["episodes"] == 2


def test_scenario_config_keeps_the_policys_history():
    from safenav.experiments.flight import scenario_config

    mine = make_config("easy", lidar_history=3)
    assert scenario_config(mine, None) is mine
    assert scenario_config(mine, "paper") == make_config("paper", lidar_history=3)
    assert scenario_config(None, "easy") == make_config("easy")
    # and its sensor: tilted beams would otherwise give an image of the same shape, read wrongly
    tilted = make_config("paper", lidar_v_angles=(-30.0, -15.0, 0.0, 15.0), lidar_memory=10)
    flown = scenario_config(tilted, "easy")
    assert flown.lidar_v_angles == (-30.0, -15.0, 0.0, 15.0) and flown.lidar_memory == 10
    assert flown.num_static == make_config("easy").num_static  # the easy scenario's map


def test_validation_flies_with_the_history(history_run):
    from safenav.common.checkpoint import load_checkpoint
    from safenav.experiments.selection import validation_score

    score = validation_score(episodes=4)(load_checkpoint(history_run / "checkpoint.pt"))
    assert 0.0 <= score <= 1.0


def test_deploy_refuses_a_history_policy(history_run, tmp_path, capsys):
    from safenav.deploy.export import check_deployable, export_onnx, load_sidecar
    from safenav.deploy.runtime import OnboardRuntime
    from safenav.deploy.scripted import GoToGoalActor

    cfg = make_config("easy", lidar_history=2)
    check_deployable(make_config("easy"), "memoryless")  # k = 1 deploys
    with pytest.raises(SystemExit) as exit_:
        main(["export", str(history_run / "checkpoint.pt"), "--onnx", str(tmp_path / "p.onnx")])
    assert exit_.value.code == 2
    assert "lidar_history > 1 cannot be deployed yet" in capsys.readouterr().err
    assert not (tmp_path / "p.onnx").exists()
    with pytest.raises(SafenavError, match="cannot be deployed yet"):
        export_onnx(GoToGoalActor(cfg), cfg, tmp_path / "q.onnx")
    with pytest.raises(SafenavError, match="cannot be deployed yet"):
        OnboardRuntime(lambda s, lidar, d: np.zeros((1, 3), np.float32), cfg)
    # an ONNX policy whose sidecar says k > 1 (written by hand or by a later safenav) is not flown
    main(["export", "--scripted", "--preset", "easy", "--onnx", str(tmp_path / "s.onnx")])
    sidecar = tmp_path / "s.onnx.json"
    meta = json.loads(sidecar.read_text())
    meta["env_config"]["lidar_history"] = 2
    sidecar.write_text(json.dumps(meta))
    with pytest.raises(SafenavError, match="cannot be deployed yet"):
        load_sidecar(tmp_path / "s.onnx")
