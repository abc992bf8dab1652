"""PPO on a ``Discrete(n)`` action space: the categorical policy's functions, the env's view of an
action index, the update, the CLI (refusal by the SAC family, training, the saved policy, render)
and a bandit it must learn."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from conftest import run_cli
from safenav.algos.ppo import PPO, collect_rollout
from safenav.algos.ppo_config import PPOConfig
from safenav.common.rollout import Rollout
from safenav.envs.vector import TorchVecEnv, policy_action_to_env, to_discrete_action
from safenav.nn.categorical import (
    categorical_entropy,
    categorical_log_prob,
    greedy_action,
    sample_categorical,
)
from safenav.nn.config import NetConfig

SMALL = NetConfig(hidden=(16, 16), shared_extractor=False)


def run(capsys, argv: list[str]) -> tuple[int, str, str]:
    code, out, err = run_cli(capsys, argv)
    assert "Traceback" not in out + err
    return code, out, err


class ThreeArmedEnv(gym.Env):
    """Actions -1, 0, 1 (``Discrete(3, start=-1)``); reward 1 for action 1, else 0; the
    observation is the last action taken; episodes of 4 steps (truncated). ``taken`` records
    every action as the env received it."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = gym.spaces.Discrete(3, start=-1)

    def __init__(self) -> None:
        self.t, self.taken = 0, []

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(1, np.float32), {}

    def step(self, action):
        assert self.action_space.contains(action), action
        self.taken.append(int(action))
        self.t += 1
        return np.full(1, action, np.float32), float(action == 1), False, self.t >= 4, {}


def three_armed(n: int = 2) -> TorchVecEnv:
    envs = SyncVectorEnv([ThreeArmedEnv for _ in range(n)], autoreset_mode=AutoresetMode.SAME_STEP)
    return TorchVecEnv(envs)


# ------------------------------------------------------------------------ the distribution
def test_categorical_log_prob_and_entropy_match_torch_distributions():
    g = torch.Generator().manual_seed(0)
    logits = 3 * torch.randn(64, 5, generator=g)
    action = torch.randint(0, 5, (64, 1), generator=g).float()
    ref = torch.distributions.Categorical(logits=logits)
    torch.testing.assert_close(categorical_log_prob(logits, action), ref.log_prob(action[:, 0]))
    torch.testing.assert_close(categorical_entropy(logits), ref.entropy())


def test_categorical_hand_values_greedy_action_and_sample_frequencies():
    logits = torch.log(torch.tensor([[0.2, 0.5, 0.3]]))
    assert categorical_log_prob(logits, torch.tensor([[1.0]])).item() == pytest.approx(
        math.log(0.5)
    )
    h = -(0.2 * math.log(0.2) + 0.5 * math.log(0.5) + 0.3 * math.log(0.3))
    assert categorical_entropy(logits).item() == pytest.approx(h)
    assert greedy_action(logits).tolist() == [[1.0]]
    torch.manual_seed(0)
    draws = sample_categorical(logits.expand(20000, 3))
    assert draws.shape == (20000, 1) and draws.dtype == torch.float32
    freq = torch.bincount(draws[:, 0].long(), minlength=3).float() / 20000
    torch.testing.assert_close(freq, torch.tensor([0.2, 0.5, 0.3]), atol=0.015, rtol=0)


# ---------------------------------------------------------------------------- the env's view
def test_the_env_gets_the_index_plus_start_as_an_integer():
    env = three_armed()
    assert env.num_actions == 3 and env.action_dim == 1
    env.reset(seed=0)
    env.step(torch.tensor([[0.0], [2.0]]))
    env.step(torch.tensor([[1.0], [7.0]]))  # out of range: clamped to the last action
    taken = [e.taken for e in env.envs.envs]
    assert taken == [[-1, 0], [1, 1]]
    idx = to_discrete_action(torch.tensor([[0.4], [1.6]]), 5, 3)
    assert idx.dtype == np.int64 and idx.tolist() == [5, 7]
    meta = {"num_actions": 3, "action_low": [-1.0], "action_high": [1.0]}
    assert int(policy_action_to_env(torch.tensor([2.0]), meta)) == 1
    box = {"action_low": [0.0], "action_high": [4.0]}
    assert policy_action_to_env(torch.tensor([0.5]), box).tolist() == [3.0]


def test_the_sac_family_refuses_a_discrete_env():
    from safenav.algos.config import CSACConfig
    from safenav.algos.csac import CSACLearner
    from safenav.common.config import RunConfig
    from safenav.errors import SafenavError

    with pytest.raises(SafenavError, match=r"discrete: CSAC, SAC and SAC-Lag need continuous"):
        CSACLearner(three_armed(), RunConfig(total_steps=100), CSACConfig(net=SMALL))


# ------------------------------------------------------------------------------- PPO itself
@pytest.mark.parametrize("constrained", [False, True])
def test_ppo_acts_with_indices_and_its_update_moves_the_policy(constrained):
    torch.manual_seed(0)
    env = three_armed()
    agent = PPO(
        env.obs_shapes, 1, PPOConfig(net=SMALL, num_minibatches=2, constrained=constrained), 3
    )
    obs = {"obs": torch.randn(6, 1)}
    action, log_prob, values = agent.act(obs)
    assert action.shape == (6, 1) and set(action[:, 0].tolist()) <= {0.0, 1.0, 2.0}
    assert values.shape == (6, 2 if constrained else 1)
    logits, _ = agent.model(obs)
    torch.testing.assert_close(
        log_prob, torch.log_softmax(logits, -1).gather(-1, action.long())[:, 0]
    )
    torch.testing.assert_close(agent.act(obs, deterministic=True)[0], greedy_action(logits))
    torch.testing.assert_close(agent.policy_module()(obs["obs"]), greedy_action(logits))
    rollout = Rollout(8, 2, env.obs_shapes, 1, agent.num_values)
    collect_rollout(env, agent, rollout, env.reset(seed=0))
    before = [p.detach().clone() for p in agent.model.parameters()]
    metrics = agent.update(rollout)
    assert all(math.isfinite(float(v)) for v in metrics.values())
    assert any(not torch.equal(a, b) for a, b in zip(before, agent.model.parameters(), strict=True))


def test_ppo_learns_the_three_armed_bandit():
    """Reward 1 only for the third action: from a uniform start (1/3 of the steps rewarded),
    within 30 rollouts of 64 steps the deterministic policy takes it and the sampled one takes it
    most of the time."""
    torch.manual_seed(0)
    env = three_armed(4)
    cfg = PPOConfig(net=SMALL, num_minibatches=4, epochs=4, lr=3e-3, entropy_coef=0.0)
    agent = PPO(env.obs_shapes, 1, cfg, 3)
    rollout = Rollout(16, 4, env.obs_shapes, 1, 1)
    obs = env.reset(seed=0)
    for _ in range(30):
        obs, _ = collect_rollout(env, agent, rollout, obs)
        agent.update(rollout)
    assert rollout.rewards.mean().item() > 0.8
    assert (
        agent.act({"obs": torch.tensor([[-1.0], [0.0], [1.0]])}, deterministic=True)[0].tolist()
        == [[2.0]] * 3
    )


# ------------------------------------------------------------------------------------- CLI
def test_cli_trains_ppo_on_cartpole_and_its_policy_acts_and_renders(tmp_path, capsys):
    from safenav.algos.policy import load_policy

    code, _, err = run(capsys, ["train", "--algo", "sac", "--env", "CartPole-v1", "--run-dir",
                                str(tmp_path / "sac")])  # fmt: skip
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Discrete(2)" in err and "--algo ppo" in err, err
    assert not (tmp_path / "sac").exists()

    run_dir = tmp_path / "ppo"
    code, out, err = run(capsys, ["train", "--algo", "ppo", "--env", "CartPole-v1", "--total-steps",
                                  "512", "--run-dir", str(run_dir), "--no-progress",
                                  "--no-tensorboard", "--ppo.distribution", "gaussian"])  # fmt: skip
    assert code == 0, err
    assert "recipe classic-ppo" in out and "PPO's policy is categorical" in err
    policy = load_policy(run_dir)
    assert policy.meta["policy_head"] == "categorical" and policy.meta["num_actions"] == 2
    actions = policy(torch.randn(5, 4))
    assert actions.shape == (5, 1) and set(actions[:, 0].tolist()) <= {0.0, 1.0}
    assert int(policy_action_to_env(policy(np.zeros(4, np.float32)), policy.meta)) in (0, 1)

    gif = tmp_path / "cartpole.gif"
    code, out, err = run(capsys, ["render", str(run_dir / "checkpoint.pt"), "--out", str(gif),
                                  "--fps", "10"])  # fmt: skip
    assert code == 0, err
    assert gif.stat().st_size > 1000


@pytest.mark.slow
def test_ppo_learns_cartpole_with_the_zoo_recipe(tmp_path, capsys):
    """CartPole-v1 with no flag but --algo and --env (classic-ppo: the zoo's tuned entry,
    100k steps): the final evaluation balances the pole for (nearly) all 500 steps."""
    import csv

    code, _, err = run(capsys, ["train", "--algo", "ppo", "--env", "CartPole-v1", "--run-dir",
                                str(tmp_path / "run"), "--no-progress", "--no-tensorboard"])  # fmt: skip
    assert code == 0, err
    with (tmp_path / "run" / "progress.csv").open() as f:
        evals = [float(r["eval/return"]) for r in csv.DictReader(f) if r["eval/return"]]
    assert evals[-1] >= 475, evals


def test_the_sb3_side_of_the_bench_takes_the_zoo_cartpole_entry_with_its_linear_schedules():
    from safenav.bench.sb3_trial import hyperparameters

    kwargs, n_envs, normalize = hyperparameters("ppo", "CartPole-v1")
    assert (n_envs, normalize, kwargs["n_steps"], kwargs["batch_size"]) == (8, False, 32, 256)
    for key, start in (
        ("learning_rate", 1e-3),
        ("clip_range", 0.2),
    ):  # lin_X: X at the start, 0 at the end
        assert kwargs[key](1.0) == pytest.approx(start) and kwargs[key](0.0) == 0.0
        assert repr(kwargs[key]) == f"lin_{start:g}"  # the trial file records the zoo's value
    assert hyperparameters("ppo", "Acrobot-v1")[1:] == (16, True)


def test_the_categorical_note_appears_only_where_a_continuous_distribution_was_asked_for():
    from safenav.commands.train import discrete_note
    from safenav.common.config import RunConfig

    run = RunConfig(env="CartPole-v1")
    assert discrete_note(run, PPOConfig(), 2) == ""  # the default Beta: nothing was asked
    assert discrete_note(run, PPOConfig(distribution="gaussian"), None) == ""  # continuous
    note = discrete_note(run, PPOConfig(distribution="gaussian", use_sde=True), 2)
    assert "Discrete(2)" in note and "--ppo.distribution gaussian and --ppo.use-sde" in note


# ------------------------------------------------------------------ discrete observations
def test_a_discrete_observation_trains_as_its_one_hot_vector_and_renders(tmp_path, capsys):
    """FrozenLake-v1 observes its cell, Discrete(16): Gymnasium's FlattenObservation turns it
    into the one-hot vector the networks read, in training and in render alike."""
    from safenav.algos.policy import load_policy
    from safenav.envs.vector import flat_observations

    env = flat_observations(gym.make("FrozenLake-v1"))
    obs, _ = env.reset(seed=0)
    assert env.observation_space.shape == (16,) and obs.tolist() == [1.0] + [0.0] * 15
    box = gym.make("Pendulum-v1")
    assert flat_observations(box) is box  # a Box is read as it is

    run_dir = tmp_path / "lake"
    code, _, err = run(capsys, ["train", "--algo", "ppo", "--env", "FrozenLake-v1", "--total-steps",
                                "256", "--ppo.rollout-steps", "256", "--ppo.num-minibatches", "4",
                                "--run-dir", str(run_dir), "--no-progress", "--no-tensorboard"])  # fmt: skip
    assert code == 0, err
    policy = load_policy(run_dir)
    assert policy.obs_shapes == {"obs": (16,)} and policy.meta["num_actions"] == 4
    code, out, err = run(capsys, ["render", str(run_dir / "checkpoint.pt"), "--out",
                                  str(tmp_path / "lake.gif"), "--fps", "4"])  # fmt: skip
    assert code == 0 and "'ended': True" in out, err


def test_a_task_without_a_time_limit_is_said_so_and_its_film_is_bounded(tmp_path):
    """CliffWalking-v1 has no time limit: train says so (and how to give one), and render stops
    filming an episode that has not ended after max_frames frames instead of filling the memory."""
    from safenav.commands.train import time_limit_note
    from safenav.common.config import RunConfig
    from safenav.experiments.gym_render import render_gym_episode

    note = time_limit_note(RunConfig(env="CliffWalking-v1"))
    assert "no time limit" in note and "--env-kwargs max_episode_steps" in note
    assert (
        time_limit_note(RunConfig(env="CliffWalking-v1", env_kwargs={"max_episode_steps": 50}))
        == ""
    )
    assert time_limit_note(RunConfig(env="CartPole-v1")) == ""

    class Left:  # a deterministic policy that walks into the west wall for ever
        meta = {
            "env_id": "CliffWalking-v1",
            "num_actions": 4,
            "action_low": [0.0],
            "action_high": [3.0],
        }

        def __call__(self, obs):
            return torch.tensor([3.0])  # action 3: west

    stats = render_gym_episode(tmp_path / "cliff.gif", Left(), fps=4, max_frames=12)
    assert stats["ended"] is False and stats["frames"] == 12 and stats["length"] == 12
    assert (tmp_path / "cliff.gif").stat().st_size > 0


def test_a_cost_function_reads_the_envs_own_discrete_observation(tmp_path, capsys, monkeypatch):
    """--cost-fn sees what the env returns (FrozenLake's cell index), not the one-hot vector."""
    import sys
    import types

    seen: list = []
    module = types.ModuleType("lake_costs")

    def hole_cost(obs, action, next_obs, info):
        seen.append(next_obs)
        return float(next_obs in (5, 7, 11, 12))  # FrozenLake 4x4's holes

    module.hole_cost = hole_cost
    monkeypatch.setitem(sys.modules, "lake_costs", module)
    code, _, err = run(capsys, ["train", "--algo", "ppo_lag", "--env", "FrozenLake-v1",
                                "--cost-fn", "lake_costs:hole_cost", "--total-steps", "64",
                                "--ppo.rollout-steps", "64", "--ppo.num-minibatches", "2",
                                "--run-dir", str(tmp_path / "run"), "--no-progress",
                                "--no-tensorboard"])  # fmt: skip
    assert code == 0, err
    assert seen and all(np.ndim(o) == 0 and 0 <= int(o) < 16 for o in seen)
