"""One Stable-Baselines3 trial of ``safenav bench gym``: SB3's SAC or PPO with rl-baselines3-zoo's
hyperparameters (hyperparams/sac.yml, ppo.yml; SB3's defaults where the zoo lists the task under
its ``default`` entry), evaluated on the same schedule as safenav's runs (deterministic, the same
number of episodes), written as ``RESULT.json``. Run by :mod:`safenav.bench.gym` as
``python -m safenav.bench.sb3_trial ENV ALGO SEED STEPS EVAL_EVERY EVAL_EPISODES OUT_DIR``.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# Zoo entries by task (names as in the zoo's files: its v2-v4 entries for our v3/v5 envs).
SAC_ZOO: dict[str, dict[str, Any]] = {
    "Pendulum-v1": {"learning_rate": 1e-3},
    "MountainCarContinuous-v0": {
        "learning_rate": 3e-4, "buffer_size": 50_000, "batch_size": 512, "ent_coef": 0.1,
        "train_freq": 32, "gradient_steps": 32, "gamma": 0.9999, "tau": 0.01,
        "learning_starts": 0, "use_sde": True,
        "policy_kwargs": {"log_std_init": -3.67, "net_arch": [64, 64]},
    },
    "LunarLanderContinuous-v3": {
        "batch_size": 256, "learning_rate": ("lin", 7.3e-4), "buffer_size": 1_000_000,
        "ent_coef": "auto", "gamma": 0.99, "tau": 0.01, "train_freq": 1, "gradient_steps": 1,
        "learning_starts": 10_000, "policy_kwargs": {"net_arch": [400, 300]},
    },
    "InvertedPendulum-v5": {},
    "Hopper-v5": {"learning_starts": 10_000},
    "HalfCheetah-v5": {"learning_starts": 10_000},
}  # fmt: skip
PPO_ZOO: dict[str, dict[str, Any]] = {
    "Pendulum-v1": {
        "n_envs": 4, "n_steps": 1024, "gae_lambda": 0.95, "gamma": 0.9, "n_epochs": 10,
        "ent_coef": 0.0, "learning_rate": 1e-3, "clip_range": 0.2, "use_sde": True,
        "sde_sample_freq": 4,
    },
    "MountainCarContinuous-v0": {
        "normalize": True, "n_envs": 1, "batch_size": 256, "n_steps": 8, "gamma": 0.9999,
        "learning_rate": 7.77e-5, "ent_coef": 0.00429, "clip_range": 0.1, "n_epochs": 10,
        "gae_lambda": 0.9, "max_grad_norm": 5, "vf_coef": 0.19, "use_sde": True,
        "policy_kwargs": {"log_std_init": -3.29, "ortho_init": False},
    },
    "LunarLanderContinuous-v3": {
        "n_envs": 16, "n_steps": 1024, "batch_size": 64, "gae_lambda": 0.98, "gamma": 0.999,
        "n_epochs": 4, "ent_coef": 0.01,
    },
    "InvertedPendulum-v5": {
        "normalize": True, "n_envs": 1, "batch_size": 64, "n_steps": 32, "gamma": 0.999,
        "learning_rate": 0.000222425, "ent_coef": 1.37976e-07, "clip_range": 0.4, "n_epochs": 5,
        "gae_lambda": 0.9, "max_grad_norm": 0.3, "vf_coef": 0.19816,
    },
    "Hopper-v5": {
        "normalize": True, "n_envs": 1, "batch_size": 32, "n_steps": 512, "gamma": 0.999,
        "learning_rate": 9.80828e-05, "ent_coef": 0.00229519, "clip_range": 0.2, "n_epochs": 5,
        "gae_lambda": 0.99, "max_grad_norm": 0.7, "vf_coef": 0.835671,
        "policy_kwargs": {"log_std_init": -2, "ortho_init": False, "activation_fn": "relu",
                          "net_arch": {"pi": [256, 256], "vf": [256, 256]}},
    },
    "HalfCheetah-v5": {
        "normalize": True, "n_envs": 1, "batch_size": 64, "n_steps": 512, "gamma": 0.98,
        "learning_rate": 2.0633e-05, "ent_coef": 0.000401762, "clip_range": 0.1, "n_epochs": 20,
        "gae_lambda": 0.92, "max_grad_norm": 0.8, "vf_coef": 0.58096,
        "policy_kwargs": {"log_std_init": -2, "ortho_init": False, "activation_fn": "relu",
                          "net_arch": {"pi": [256, 256], "vf": [256, 256]}},
    },
    "CartPole-v1": {
        "n_envs": 8, "n_steps": 32, "batch_size": 256, "gae_lambda": 0.8, "gamma": 0.98,
        "n_epochs": 20, "ent_coef": 0.0, "learning_rate": ("lin", 1e-3), "clip_range": ("lin", 0.2),
    },
    "Acrobot-v1": {
        "normalize": True, "n_envs": 16, "n_steps": 256, "gae_lambda": 0.94, "gamma": 0.99,
        "n_epochs": 4, "ent_coef": 0.0,
    },
    "LunarLander-v3": {
        "n_envs": 16, "n_steps": 1024, "batch_size": 64, "gae_lambda": 0.98, "gamma": 0.999,
        "n_epochs": 4, "ent_coef": 0.01,
    },
}  # fmt: skip


@dataclass(frozen=True)
class Linear:
    """The zoo's ``lin_X`` schedule: X times SB3's remaining progress (1 at the start, 0 at the
    end); its repr is the zoo's spelling, so the trial file records the value."""

    start: float

    def __call__(self, progress: float) -> float:
        return progress * self.start

    def __repr__(self) -> str:
        return f"lin_{self.start:g}"


def hyperparameters(algo: str, env_id: str) -> tuple[dict[str, Any], int, bool]:
    """``(SB3 keyword arguments, n_envs, normalize)`` of the zoo's entry (SB3 defaults if none)."""
    import torch.nn as nn

    table = SAC_ZOO if algo == "sac" else PPO_ZOO
    kwargs = dict(table.get(env_id, {}))
    n_envs, normalize = int(kwargs.pop("n_envs", 1)), bool(kwargs.pop("normalize", False))
    for key in ("learning_rate", "clip_range"):
        value = kwargs.get(key)
        if isinstance(value, tuple):  # the zoo's "lin_X": linear decay from X to 0
            kwargs[key] = Linear(value[1])
    policy_kwargs = dict(kwargs.get("policy_kwargs", {}))
    if policy_kwargs.get("activation_fn") == "relu":
        policy_kwargs["activation_fn"] = nn.ReLU
    if policy_kwargs:
        kwargs["policy_kwargs"] = policy_kwargs
    return kwargs, n_envs, normalize


def run_trial(env_id: str, algo: str, seed: int, steps: int, eval_every: int, episodes: int,
              out: Path) -> dict[str, Any]:  # fmt: skip
    """Train, evaluate every ``eval_every`` steps and at the end; write ``out/result.json``."""
    import numpy as np
    import torch
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.logger import Logger
    from stable_baselines3.common.vec_env import VecNormalize, sync_envs_normalization

    import safenav  # noqa: F401  (registers the velocity tasks)
    from safenav.envs.vector import quiet_mujoco

    quiet_mujoco()
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    kwargs, n_envs, normalize = hyperparameters(algo, env_id)
    env = make_vec_env(env_id, n_envs=n_envs, seed=seed)
    eval_env = make_vec_env(env_id, n_envs=1, seed=seed + 10_000)
    if normalize:
        env = VecNormalize(env, gamma=kwargs.get("gamma", 0.99))
        eval_env = VecNormalize(eval_env, training=False, norm_reward=False)
    model = (SAC if algo == "sac" else PPO)("MlpPolicy", env, seed=seed, device="cpu", verbose=0,
                                           **kwargs)  # fmt: skip
    # SB3's default logger makes a directory under /tmp for every run, written to or not.
    model.set_logger(Logger(folder=None, output_formats=[]))
    curve: list[list[float]] = []
    train_curve: list[list[float]] = []

    def evaluate(step: int) -> None:
        if normalize:
            sync_envs_normalization(env, eval_env)
        rets, _ = evaluate_policy(model, eval_env, n_eval_episodes=episodes, deterministic=True,
                                  return_episode_rewards=True)  # fmt: skip
        curve.append([step, float(np.mean(rets)), 0.0])
        recent = [ep["r"] for ep in model.ep_info_buffer]
        if recent:
            train_curve.append([step, float(np.mean(recent[-10:])), 0.0])
        (out / "progress.txt").write_text(str(step))

    class Every(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.next = eval_every

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next:
                while self.next <= self.num_timesteps:
                    self.next += eval_every
                evaluate(self.num_timesteps)
            elif self.num_timesteps % 1000 < n_envs:
                (out / "progress.txt").write_text(str(self.num_timesteps))
            return True

    t0 = time.perf_counter()
    model.learn(total_timesteps=steps, callback=Every())
    if not curve or curve[-1][0] < model.num_timesteps:
        evaluate(model.num_timesteps)
    wall = time.perf_counter() - t0
    result = {"steps": int(model.num_timesteps), "wall_clock_s": wall, "curve": curve,
              "train_curve": train_curve, "hyperparameters": {k: repr(v) for k, v in kwargs.items()},
              "n_envs": n_envs, "normalize": normalize}  # fmt: skip
    from safenav.common.jsonout import write_json

    write_json(out / "result.json", result)  # atomic: a killed trial leaves no half-written result
    return result


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    env_id, algo, seed, steps, every, episodes, out = args
    run_trial(env_id, algo, int(seed), int(steps), int(every), int(episodes), Path(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
