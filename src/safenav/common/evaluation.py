"""Periodic evaluation during training: deterministic actions on a fixed set of episodes."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from safenav.common.envs import TorchVecEnv

EVAL_SEED = 12345
"""Seed of the evaluation env: fixed, so that successive evaluations (and runs) see the same maps
and episodes; distinct from the training seeds and from the test scenario's env seed 1."""


@torch.no_grad()
def evaluate_episodes(env: TorchVecEnv, act: Callable[[dict[str, torch.Tensor]], torch.Tensor],
                      episodes: int, seed: int = EVAL_SEED, max_steps: int = 1_000_000) -> dict[str, float]:  # fmt: skip
    """Run every env of ``env`` for the same number of episodes (``ceil(episodes / num_envs)``, so
    short episodes are not over-represented) with actions ``act(obs)``; mean episode statistics."""
    quota = math.ceil(episodes / env.num_envs)
    done_count = torch.zeros(env.num_envs, dtype=torch.long, device=env.device)
    rows: dict[str, list[torch.Tensor]] = {}
    obs = env.reset(seed=seed)
    for _ in range(max_steps):
        if bool((done_count >= quota).all()):
            break
        step = env.step(act(obs))
        obs = step.next_obs
        if step.episodes is not None:
            ended = (step.terminated | step.truncated).nonzero().squeeze(-1)
            keep = done_count[ended] < quota
            done_count[ended] += 1
            for k, v in step.episodes.items():
                rows.setdefault(k, []).append(v[keep])
    out = {}
    for k, vs in rows.items():
        v = torch.cat(vs).float()
        v = v[~torch.isnan(v)]
        out[k] = float(v.mean()) if v.numel() else math.nan
    out["episodes"] = float(sum(len(v) for v in rows.get("return", [])))
    return out


__all__ = ["EVAL_SEED", "evaluate_episodes"]
