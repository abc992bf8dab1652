"""Learning tests (slow): SAC solves Pendulum; CSAC keeps a cost budget that SAC blows.

Run with ``make test-slow`` (``pytest -m slow``). Hyperparameters here are the usual SAC ones for
small control tasks (faster than the paper's, which are tuned for the UAV task), so that each
test finishes in a few minutes on two CPU cores.
"""

from __future__ import annotations

import csv
import dataclasses
import math

import gymnasium as gym
import numpy as np
import pytest

from safenav.algos.config import CSACConfig
from safenav.common.config import RunConfig
from safenav.common.curriculum import ConstraintCurriculumConfig
from safenav.nn.config import NetConfig
from safenav.training import train

pytestmark = pytest.mark.slow

FAST_SAC = CSACConfig(actor_lr=3e-4, reward_critic_lr=1e-3, cost_critic_lr=1e-3, alpha_lr=3e-4,
                      init_alpha=1.0, learning_starts=1000, updates_per_step=1.0, batch_size=256,
                      buffer_size=100_000, net=NetConfig(hidden=(256, 256)))  # fmt: skip


def rows(run_dir) -> list[dict[str, str]]:
    with (run_dir / "progress.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def last(run_dir, key: str, n: int = 1) -> float:
    vals = [float(r[key]) for r in rows(run_dir) if r.get(key)]
    return float(np.mean(vals[-n:]))


def test_sac_solves_pendulum(tmp_path):
    run = RunConfig(env="Pendulum-v1", num_envs=1, seed=0, total_steps=12_000, log_every=1000,
                    eval_every=12_000, eval_episodes=10, torch_threads=1, tensorboard=False)  # fmt: skip
    train("sac", run, FAST_SAC, tmp_path, progress=False)
    ret = last(tmp_path, "eval/return")
    assert ret > -300, f"SAC on Pendulum-v1: deterministic return {ret:.0f} after 12k steps"


class ShortcutEnv(gym.Env):
    """A tiny CMDP: 20 steps; reward = a, cost = 1 whenever a > 0. Unconstrained, the best policy
    pushes a -> 1 and pays cost 20 per episode; with a budget of 4 it must keep a <= 0 on most
    steps. The observation is the time left."""

    observation_space = gym.spaces.Box(0.0, 1.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    T = 20

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.ones(1, np.float32), {}

    def step(self, action):
        self.t += 1
        a = float(np.clip(action[0], -1.0, 1.0))
        obs = np.full(1, 1.0 - self.t / self.T, np.float32)
        return obs, a, self.t >= self.T, False, {"cost": float(a > 0.0)}


if "SafenavTestShortcut-v0" not in gym.registry:
    gym.register("SafenavTestShortcut-v0", entry_point=ShortcutEnv)


def test_csac_keeps_the_cost_budget_sac_does_not(tmp_path):
    budget = 4.0
    run = RunConfig(env="SafenavTestShortcut-v0", num_envs=1, seed=0, total_steps=8_000,
                    log_every=500, eval_every=0, torch_threads=1, tensorboard=False)  # fmt: skip
    cfg = dataclasses.replace(
        FAST_SAC, learning_starts=500, net=NetConfig(hidden=(64, 64)), lambda_lr=3e-2, cost_horizon=ShortcutEnv.T,
        curriculum=ConstraintCurriculumConfig(enabled=False, d_init=budget, d_min=budget),
    )  # fmt: skip
    train("csac", run, cfg, tmp_path / "csac", progress=False)
    train("sac", run, cfg, tmp_path / "sac", progress=False)
    csac_cost = last(tmp_path / "csac", "charts/episodic_cost", n=4)  # the last 2000 steps
    sac_cost = last(tmp_path / "sac", "charts/episodic_cost", n=4)
    lam = last(tmp_path / "csac", "constraint/lambda")
    assert sac_cost > 2 * budget, f"SAC should ignore the cost: {sac_cost:.1f} per episode"
    # E[Q_C] over replayed states weighs a cost by how many states precede it: the budget holds
    # on average, not exactly per episode (docs/csac.md), hence the tolerance
    assert csac_cost <= budget * 1.5, (
        f"CSAC cost {csac_cost:.1f} per episode exceeds the budget {budget}"
    )
    assert lam > 0 and math.isfinite(lam)
    assert (
        last(tmp_path / "csac", "charts/episodic_return", n=4) > -5
    )  # not simply a = -1 everywhere
