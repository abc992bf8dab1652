"""PPO / PPO-Lag: the pure pieces against hand-computed values, the rollout's truncation
bootstrap, the Lagrange multiplier's direction, the deterministic policy of a checkpoint, and a
slow learning test on Pendulum-v1."""

from __future__ import annotations

import math

import pytest
import torch
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from conftest import CounterEnv
from safenav.algos.ppo import PPO, collect_rollout
from safenav.algos.ppo_config import PPOConfig
from safenav.algos.ppo_losses import (
    action_to_unit,
    beta_concentrations,
    beta_entropy,
    beta_log_prob,
    beta_mean_action,
    clipped_policy_loss,
    clipped_value_loss,
    gae,
    lagrangian_advantage,
    normalize,
    sample_beta_action,
    unit_to_action,
)
from safenav.common.lagrange import Lagrange
from safenav.common.rollout import Rollout, ValueNorm
from safenav.envs.vector import TorchVecEnv
from safenav.nn.config import NetConfig

SMALL = NetConfig(hidden=(16, 16))


# ------------------------------------------------------------------------------------- GAE
def test_gae_hand_case_with_truncation_in_the_middle_and_a_termination():
    # env 0: truncated at t=1 (bootstrap from V(final obs) = 10, trace cut), terminated at t=3.
    # env 1: no episode end; bootstraps from V(s_4) = 2 after the rollout.
    gamma, lam = 0.5, 0.5
    rewards = torch.tensor([[1.0, 1.0], [2.0, 1.0], [3.0, 1.0], [4.0, 1.0]])
    values = torch.tensor([[0.5, 0.0], [1.0, 0.0], [1.5, 0.0], [2.0, 0.0]])
    next_values = torch.tensor([[1.0, 0.0], [10.0, 0.0], [2.0, 0.0], [7.0, 2.0]])
    terminated = torch.tensor([[False, False], [False, False], [False, False], [True, False]])
    truncated = torch.tensor([[False, False], [True, False], [False, False], [False, False]])
    adv, ret = gae(rewards, values, next_values, terminated, truncated, gamma, lam)
    # env 0: deltas 1 + .5 - .5 = 1, 2 + 5 - 1 = 6, 3 + 1 - 1.5 = 2.5, 4 + 0 - 2 = 2 (terminal)
    #        A_3 = 2, A_2 = 2.5 + .25 * 2 = 3, A_1 = 6 (trace cut), A_0 = 1 + .25 * 6 = 2.5
    # env 1: deltas 1, 1, 1, 1 + .5 * 2 = 2; A_3 = 2, A_2 = 1.5, A_1 = 1.375, A_0 = 1.34375
    expected = torch.tensor([[2.5, 1.34375], [6.0, 1.375], [3.0, 1.5], [2.0, 2.0]])
    torch.testing.assert_close(adv, expected)
    torch.testing.assert_close(ret, expected + values)


def test_gae_takes_several_signals_at_once():
    rewards = torch.rand(5, 3, 2)
    values, next_values = torch.rand(5, 3, 2), torch.rand(5, 3, 2)
    term, trunc = torch.rand(5, 3) < 0.3, torch.rand(5, 3) < 0.3
    adv, _ = gae(rewards, values, next_values, term.unsqueeze(-1), trunc.unsqueeze(-1), 0.9, 0.8)
    for k in range(2):
        one, _ = gae(rewards[..., k], values[..., k], next_values[..., k], term, trunc, 0.9, 0.8)
        torch.testing.assert_close(adv[..., k], one)


def test_lambda_one_no_ends_is_the_discounted_return_minus_value():
    r, v = torch.tensor([[1.0], [2.0], [3.0]]), torch.tensor([[0.3], [0.2], [0.1]])
    nv = torch.tensor([[0.2], [0.1], [5.0]])
    no = torch.zeros(3, 1, dtype=torch.bool)
    _, ret = gae(r, v, nv, no, no, 0.9, 1.0)
    assert ret[0, 0].item() == pytest.approx(1 + 0.9 * 2 + 0.81 * 3 + 0.729 * 5)


# --------------------------------------------------------------------------- clipped losses
def test_clipped_policy_loss_hand_case():
    ratio = torch.tensor([1.5, 0.5, 1.05, 0.8])
    adv = torch.tensor([1.0, 1.0, -2.0, -1.0])
    old = torch.zeros(4)
    loss = clipped_policy_loss(torch.log(ratio), old, adv, 0.1)
    # min(rho A, clip(rho) A): 1.1 (clipped), 0.5, -2.1, -0.9 (clipped) -> mean -0.35
    assert loss.item() == pytest.approx(0.35)


def test_clipped_policy_loss_gradient_vanishes_outside_the_trust_region():
    log_prob = torch.log(torch.tensor([1.5, 0.5])).requires_grad_()
    clipped_policy_loss(log_prob, torch.zeros(2), torch.tensor([1.0, -1.0]), 0.1).backward()
    # both ratios lie beyond the clip in the direction their advantage favours: no gradient
    assert log_prob.grad.tolist() == [0.0, 0.0]


def test_clipped_value_loss_hand_case():
    values, old = torch.tensor([1.0, 2.0]), torch.tensor([0.5, 2.0])
    returns = torch.tensor([2.0, 1.0])
    # env 0: (1 - 2)^2 = 1 vs (0.6 - 2)^2 = 1.96 -> 1.96; env 1: 1 vs 1 -> 1; 0.5 * mean = 0.74
    assert clipped_value_loss(values, old, returns, 0.1).item() == pytest.approx(0.74)
    assert clipped_value_loss(values, old, returns, 0.0).item() == pytest.approx(0.5)


def test_lagrangian_advantage_and_normalize():
    assert lagrangian_advantage(torch.tensor(1.0), torch.tensor(2.0), 1.0).item() == -0.5
    assert lagrangian_advantage(torch.tensor(1.0), torch.tensor(2.0), 0.0).item() == 1.0
    x = torch.tensor([1.0, 2.0, 3.0])
    torch.testing.assert_close(normalize(x, scale=False), torch.tensor([-1.0, 0.0, 1.0]))
    std = math.sqrt(2 / 3)
    torch.testing.assert_close(normalize(x), torch.tensor([-1 / std, 0.0, 1 / std]))


# ------------------------------------------------------------------------------ Beta policy
def test_beta_concentrations_are_one_plus_softplus():
    a, b = beta_concentrations(torch.tensor([0.0]), torch.tensor([-100.0]))
    assert a.item() == pytest.approx(1.0 + math.log(2.0))
    assert b.item() == pytest.approx(1.0)


def test_action_scaling_round_trip():
    x = torch.tensor([0.0, 0.25, 0.5, 1.0])
    torch.testing.assert_close(unit_to_action(x), torch.tensor([-1.0, -0.5, 0.0, 1.0]))
    torch.testing.assert_close(
        action_to_unit(torch.tensor([-0.5, 0.0, 0.5])), torch.tensor([0.25, 0.5, 0.75])
    )


def test_beta_log_prob_hand_values():
    # Beta(2, 2) at x = 0.5: 6 x (1 - x) = 1.5 on [0, 1], 0.75 on [-1, 1] (action 0)
    # Beta(3, 2) at x = 0.75: 12 x^2 (1 - x) = 1.6875 on [0, 1], 0.84375 on [-1, 1] (action 0.5)
    alpha, beta = torch.tensor([[2.0, 3.0]]), torch.tensor([[2.0, 2.0]])
    lp = beta_log_prob(alpha, beta, torch.tensor([[0.0, 0.5]]))
    assert lp.item() == pytest.approx(math.log(0.75) + math.log(0.84375), rel=1e-5)


def test_beta_log_prob_and_entropy_match_torch_distributions():
    g = torch.Generator().manual_seed(0)
    alpha, beta = 1 + 3 * torch.rand(64, 3, generator=g), 1 + 3 * torch.rand(64, 3, generator=g)
    x = 0.02 + 0.96 * torch.rand(64, 3, generator=g)
    ref = torch.distributions.Beta(alpha, beta)
    expected = ref.log_prob(x).sum(-1) - 3 * math.log(2.0)
    torch.testing.assert_close(
        beta_log_prob(alpha, beta, unit_to_action(x)), expected, rtol=1e-4, atol=1e-4
    )
    torch.testing.assert_close(beta_entropy(alpha, beta), ref.entropy().sum(-1) + 3 * math.log(2.0))


def test_beta_entropy_hand_values():
    # Beta(1, 1) is uniform: entropy 0 on [0, 1], log 2 on [-1, 1]
    assert beta_entropy(torch.ones(1, 1), torch.ones(1, 1)).item() == pytest.approx(math.log(2.0))
    # Beta(2, 2): log B(2,2) - 2 psi(2) + 2 psi(4) = -log 6 + 5/3 on [0, 1]
    h = beta_entropy(torch.full((1, 1), 2.0), torch.full((1, 1), 2.0)).item()
    assert h == pytest.approx(-math.log(6.0) + 5 / 3 + math.log(2.0), rel=1e-5)


def test_beta_mean_action_and_samples():
    assert beta_mean_action(torch.tensor([3.0]), torch.tensor([1.0])).item() == pytest.approx(0.5)
    torch.manual_seed(0)
    a = sample_beta_action(torch.full((20000, 1), 3.0), torch.full((20000, 1), 1.0))
    assert a.min() >= -1 and a.max() <= 1
    assert a.mean().item() == pytest.approx(0.5, abs=0.02)


# ------------------------------------------------------------------------- value normalisation
def test_value_norm_tracks_the_returns_and_round_trips():
    norm = ValueNorm(2, beta=0.9)
    x = torch.tensor([[1.0, 10.0], [3.0, 30.0]])
    torch.testing.assert_close(norm.normalize(x), x)  # no statistics yet: identity
    norm.update(x)  # one debiased update: exactly the batch statistics
    mean, std = norm.stats()
    torch.testing.assert_close(mean, torch.tensor([2.0, 20.0]))
    torch.testing.assert_close(std, torch.tensor([1.0, 10.0]))
    torch.testing.assert_close(norm.denormalize(norm.normalize(x)), x)


# -------------------------------------------------------------------- rollout and truncation
def counter_envs() -> TorchVecEnv:
    return TorchVecEnv(SyncVectorEnv([lambda: CounterEnv(True), lambda: CounterEnv(False)],
                                     autoreset_mode=AutoresetMode.SAME_STEP))  # fmt: skip


@pytest.mark.parametrize("constrained", [False, True])
def test_rollout_bootstraps_truncation_from_the_final_observation(constrained):
    torch.manual_seed(0)
    env = counter_envs()
    agent = PPO(env.obs_shapes, 1, PPOConfig(constrained=constrained, net=SMALL))
    k = 2 if constrained else 1
    rollout = Rollout(4, 2, env.obs_shapes, 1, k)
    obs = env.reset(seed=0)
    obs, episodes = collect_rollout(env, agent, rollout, obs)
    assert rollout.terminated[:, 0].tolist() == [False, False, True, False]
    assert rollout.truncated[:, 1].tolist() == [False, False, True, False]
    v = lambda t: agent.value({"obs": torch.tensor([[float(t)]])})[0]  # noqa: E731
    # env 1 (truncated at t=2 -> final obs [3]): V(final obs), not V(first obs of the next episode)
    torch.testing.assert_close(rollout.next_values[2, 1], v(3))
    assert not torch.allclose(v(3), v(0))
    # elsewhere V(s_{t+1}); after the rollout V(obs after), here obs [1] (t=1 of episode 2)
    torch.testing.assert_close(rollout.next_values[0, 1], rollout.values[1, 1])
    torch.testing.assert_close(rollout.next_values[3, 0], v(1))
    assert rollout.rewards[:, 0, 0].tolist() == [1.0] * 4
    if constrained:  # cost signal side by side: cost 1 at the end of each episode
        assert rollout.rewards[:, 0, 1].tolist() == [0.0, 0.0, 1.0, 0.0]
    assert len(episodes) == 1 and episodes[0]["cost"].tolist() == [1.0, 1.0]


def test_update_runs_and_moves_the_policy():
    torch.manual_seed(0)
    env = counter_envs()
    agent = PPO(env.obs_shapes, 1, PPOConfig(constrained=True, net=SMALL, num_minibatches=2))
    rollout = Rollout(8, 2, env.obs_shapes, 1, 2)
    collect_rollout(env, agent, rollout, env.reset(seed=0))
    before = [p.detach().clone() for p in agent.model.parameters()]
    metrics = agent.update(rollout)
    assert metrics["perf/gradient_steps"].item() == 4 * 2
    assert all(math.isfinite(float(v)) for v in metrics.values())
    assert any(not torch.equal(a, b) for a, b in zip(before, agent.model.parameters(), strict=True))


# --------------------------------------------------------------------------- Lagrange, PPO-Lag
def test_ppo_lag_lambda_rises_above_the_limit_falls_below_and_stays_non_negative():
    lag = Lagrange(init=0.5, lr=0.035)
    for _ in range(5):
        lag.update(torch.tensor([0.8]), 0.2)  # J_c = 0.8 > d = 0.2: violated
    high = float(lag.value)
    assert high > 0.5
    for _ in range(200):
        lag.update(torch.tensor([0.0]), 0.2)  # satisfied
    assert float(lag.value) < high and float(lag.value) == 0.0


def test_ppo_lag_actor_advantage_penalises_cost_more_as_lambda_grows():
    adv_r, adv_c = torch.tensor([1.0, 1.0]), torch.tensor([0.0, 2.0])  # the second action costs
    gaps = [(lambda a: (a[0] - a[1]).item())(lagrangian_advantage(adv_r, adv_c, lam))
            for lam in (0.0, 0.5, 5.0)]  # fmt: skip
    assert gaps[0] == 0.0 and gaps[0] < gaps[1] < gaps[2]


# ------------------------------------------------------------------------ deterministic policy
def test_policy_module_is_the_mapped_beta_mean():
    torch.manual_seed(0)
    env = counter_envs()
    agent = PPO(env.obs_shapes, 1, PPOConfig(net=SMALL))
    obs = {"obs": torch.randn(5, 1)}
    alpha, beta, _ = agent.model(obs)
    torch.testing.assert_close(agent.policy_module()(obs["obs"]), 2 * alpha / (alpha + beta) - 1)
    torch.testing.assert_close(
        agent.act(obs, deterministic=True)[0], 2 * alpha / (alpha + beta) - 1
    )


# ------------------------------------------------------------------------------ learning (slow)
@pytest.mark.slow
def test_ppo_learns_pendulum(tmp_path):
    """PPO (Pendulum-tuned: gamma 0.95, 64 envs x 64 steps, 10 epochs, lr 1e-3) lifts
    Pendulum-v1's return from about -1200 (random) above -400 within 150k env steps (~15 s on
    one thread; measured -255 at 65k)."""
    import csv

    from safenav.common.config import RunConfig
    from safenav.common.logger import prepare_run_dir
    from safenav.training import train

    prepare_run_dir(tmp_path, False, False)
    run = RunConfig(env="Pendulum-v1", num_envs=64, total_steps=150_000, seed=1, log_every=8192,
                    eval_every=0, tensorboard=False, checkpoint_every=10**9, torch_threads=1)  # fmt: skip
    cfg = PPOConfig(gamma=0.95, rollout_steps=64, num_minibatches=8, epochs=10, lr=1e-3,
                    entropy_coef=0.0, clip=0.2, value_clip=0.0, net=NetConfig(hidden=(64, 64)))  # fmt: skip
    train("ppo", run, cfg, tmp_path, progress=False)
    with (tmp_path / "progress.csv").open() as f:
        rows = [
            float(r["charts/episodic_return"])
            for r in csv.DictReader(f)
            if r["charts/episodic_return"]
        ]
    assert max(rows[-5:]) > -400, rows


def test_bench_ppo_reports_env_steps_per_second():
    from safenav.bench.ppo import bench_ppo

    assert bench_ppo(num_envs=8, rollouts=1, preset="easy") > 0
