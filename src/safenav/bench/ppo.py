"""PPO's training throughput: env steps consumed per second, rollout collection plus update.

One iteration is what training does per rollout (:class:`safenav.algos.ppo.PPOLearner`):
``rollout_steps`` vector steps of the ``paper`` scenario with the Beta policy sampling actions and
the critic valuing each observation (and the final observation of every truncated episode), then
GAE and ``epochs`` x ``num_minibatches`` Adam steps on the default
:class:`~safenav.algos.ppo_config.PPOConfig` (the paper architecture: range-image CNN + dynamic
MLP + state -> 256x256 trunk). Logging, checkpoints and curricula are left out: they cost nothing
measurable per rollout.
"""

from __future__ import annotations

import time

import torch


def bench_ppo(num_envs: int = 256, rollouts: int = 3, preset: str = "paper", device: str = "cpu",
              threads: int | None = None, constrained: bool = False, seed: int = 0) -> float:  # fmt: skip
    """Env steps per second of PPO training (collection + update), the median over ``rollouts``
    timed iterations after one warm-up iteration; ``threads`` sets ``torch.set_num_threads``
    (None: leave it)."""
    import statistics

    from safenav.algos.ppo import PPO, collect_rollout
    from safenav.algos.ppo_config import PPOConfig
    from safenav.common.rollout import Rollout
    from safenav.envs.vector import TorchVecEnv, make_vec_env

    if threads is not None:
        torch.set_num_threads(threads)
    torch.manual_seed(seed)
    cfg = PPOConfig(constrained=constrained)
    env = TorchVecEnv(make_vec_env("SafeNav-v1", num_envs, device, preset), device)
    agent = PPO(env.obs_shapes, env.action_dim, cfg).to(device)
    rollout = Rollout(cfg.rollout_steps, num_envs, env.obs_shapes, env.action_dim,
                      agent.num_values, device)  # fmt: skip
    obs = env.reset(seed=seed + 100_000)
    rates = []
    for i in range(rollouts + 1):
        t0 = time.perf_counter()
        obs, _ = collect_rollout(env, agent, rollout, obs)
        agent.update(rollout)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        if i > 0:  # the first iteration warms up allocators and kernels
            rates.append(cfg.rollout_steps * num_envs / (time.perf_counter() - t0))
    env.close()
    return statistics.median(rates)


__all__ = ["bench_ppo"]
