"""Colored-noise exploration of the SAC family (``--csac.action-noise-beta``,
``safenav.common.colored_noise``): the noise's statistics, its resets, the rollout path, white
noise (beta 0) bit-identical to the plain sample, and a short run with resume."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSAC, CSACLearner
from safenav.common.colored_noise import ColoredNoise
from safenav.common.config import RunConfig
from safenav.envs.vector import TorchVecEnv, make_vec_env
from safenav.nn.config import NetConfig
from safenav.nn.networks import squashed_gaussian


def sequences(beta: float, num_envs: int = 64, horizon: int = 1000) -> np.ndarray:
    """``(num_envs, horizon)``: every sample of one full sequence per env (one action dim)."""
    torch.manual_seed(0)
    noise = ColoredNoise(beta, num_envs, 1, horizon)
    return torch.stack([noise.sample()[:, 0] for _ in range(horizon)], 1).numpy()


def lag1(x: np.ndarray) -> float:
    x = x - x.mean(1, keepdims=True)
    return float(((x[:, 1:] * x[:, :-1]).sum(1) / (x * x).sum(1)).mean())


@pytest.mark.parametrize("beta", [0.0, 1.0, 2.0])
def test_noise_has_unit_variance(beta):
    """Unit variance as ``colorednoise`` normalises it: over the nonzero frequencies, so the
    zero-frequency term adds a little (about 7 % at beta 1, 30 % at beta 2)."""
    x = sequences(beta)
    assert x.dtype == np.float32 and np.isfinite(x).all()
    assert float((x * x).mean()) == pytest.approx({0.0: 1.0, 1.0: 1.07, 2.0: 1.3}[beta], abs=0.1)


def test_pink_noise_is_temporally_correlated_and_white_is_not():
    assert lag1(sequences(1.0)) > 0.5
    assert abs(lag1(sequences(0.0))) < 0.1
    assert lag1(sequences(2.0)) > lag1(sequences(1.0))


def test_reset_regenerates_only_the_masked_envs_and_is_reproducible():
    torch.manual_seed(3)
    noise = ColoredNoise(1.0, 4, 2, 50)
    first = noise.sample()
    assert first.shape == (4, 2) and first.dtype == torch.float32
    for _ in range(9):
        noise.sample()
    before = noise.noise.clone()
    noise.reset(torch.tensor([True, False, True, False]))
    eps = noise.sample()
    assert noise.index.tolist() == [1, 11, 1, 11]
    assert torch.equal(noise.noise[[1, 3]], before[[1, 3]])
    assert not torch.equal(noise.noise[0], before[0]) and not torch.equal(noise.noise[2], before[2])
    assert torch.equal(eps[[1, 3]], before[[1, 3], :, 10])
    # a sequence that runs out starts anew
    for _ in range(39):
        noise.sample()
    assert noise.index.tolist() == [40, 50, 40, 50]
    noise.sample()
    assert noise.index.tolist() == [41, 1, 41, 1]
    torch.manual_seed(3)
    assert torch.equal(ColoredNoise(1.0, 4, 2, 50).sample(), first)


@pytest.mark.parametrize("beta", [-0.1, 2.5, math.nan, math.inf])
def test_config_rejects_a_bad_beta(beta):
    with pytest.raises(ValueError, match="action-noise-beta"):
        CSACConfig(action_noise_beta=beta)
    with pytest.raises(ValueError, match="beta"):
        ColoredNoise(beta, 1, 1, 10)


def test_white_noise_act_is_the_plain_reparameterised_sample():
    """beta 0 leaves ``act`` as it was: the same draw of ``torch.randn_like`` as before."""
    cfg = CSACConfig(constrained=False, net=NetConfig(hidden=(16, 16)))
    agent = CSAC({"obs": (3,)}, 2, cfg)
    obs = {"obs": torch.randn(5, 3)}
    torch.manual_seed(7)
    actions = agent.act(obs)
    torch.manual_seed(7)
    with torch.no_grad():
        mean, log_std = agent.actor(obs["obs"])
        expected, _ = squashed_gaussian(mean, log_std, torch.randn_like(mean))
        given = agent.act(obs, noise=torch.zeros(5, 2))
    assert torch.equal(actions, expected)
    assert torch.equal(given, torch.tanh(mean))  # zero noise: the mean action
    assert torch.equal(agent.act(obs, deterministic=True, noise=torch.ones(5, 2)), torch.tanh(mean))


@pytest.mark.parametrize("beta", [0.0, 1.0])
def test_learner_rollouts_use_the_noise_and_restart_it_with_each_episode(beta):
    torch.manual_seed(0)
    env = TorchVecEnv(make_vec_env("Pendulum-v1", 2, "cpu"), "cpu")
    cfg = CSACConfig(constrained=False, learning_starts=0, batch_size=8, buffer_size=500,
                     action_noise_beta=beta, net=NetConfig(hidden=(16, 16)))  # fmt: skip
    learner = CSACLearner(env, RunConfig(env="Pendulum-v1", total_steps=500), cfg)
    if beta == 0:
        assert learner.noise is None
        return
    noise = learner.noise
    assert noise.horizon == 200 and noise.noise.shape == (2, 1, 200)  # Pendulum's time limit
    obs = env.reset(seed=0)
    for step in range(1, 201):
        obs, episodes, _ = learner.collect(env, obs, step, 0.0)
        if step == 10:
            assert noise.index.tolist() == [10, 10]
    assert episodes and noise.index.tolist() == [200, 200]  # truncated at 200: new sequences next
    seq = noise.noise.clone()
    learner.collect(env, obs, 201, 0.0)
    assert noise.index.tolist() == [1, 1] and not torch.equal(noise.noise, seq)
    env.close()


def test_train_and_resume_with_pink_noise(tmp_path):
    from safenav.cli import main
    from safenav.common.checkpoint import load_checkpoint

    run_dir = tmp_path / "pink"
    main(["train", "--algo", "sac", "--env", "Pendulum-v1", "--total-steps", "600",
          "--num-envs", "2", "--csac.learning-starts", "100", "--csac.batch-size", "32",
          "--csac.net.hidden", "32", "32", "--csac.action-noise-beta", "1", "--no-progress",
          "--no-tensorboard", "--eval-every", "0", "--torch-threads", "1",
          "--run-dir", str(run_dir)])  # fmt: skip
    ckpt = load_checkpoint(run_dir / "checkpoint.pt")
    assert ckpt["global_step"] == 600 and ckpt["config"]["csac"]["action_noise_beta"] == 1.0
    main(["train", "--algo", "sac", "--resume", str(run_dir), "--total-steps", "800",
          "--no-progress"])  # fmt: skip
    assert load_checkpoint(run_dir / "checkpoint.pt")["global_step"] == 800


def test_classic_sac_recipe_explores_mountain_car_with_pink_noise():
    from safenav.recipes import apply, load_recipe

    recipe = load_recipe("classic-sac")
    car = apply(CSACConfig(), recipe.section("csac", "MountainCarContinuous-v0"))
    assert car.action_noise_beta == 1.0
    assert apply(CSACConfig(), recipe.section("csac", "Pendulum-v1")).action_noise_beta == 0.0
