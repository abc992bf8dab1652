"""The evaluation protocol of paper IV-B: one fixed test scenario, deterministic actions.

The map is the world drawn from env seed 1 at full density; the episodes are the fixed list of
:func:`safenav.envs.fixed_scenario` (200 by default). All episodes fly at once, one env each, in
one vector env: every episode sees the moving obstacles from their reset state, and the result is
the same for every run on every machine (up to float rounding of the policy network).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from rich.progress import Progress

from safenav.envs.config import EnvConfig, make_config
from safenav.envs.nav import SafeNavVectorEnv, fixed_scenario

Policy = Callable[[dict[str, torch.Tensor]], torch.Tensor]
"""Observations -> actions; a policy with ``needs_env = True`` (a privileged scripted probe) is
called as ``policy(obs, env)``."""
Shield = Callable[[SafeNavVectorEnv, dict[str, torch.Tensor], torch.Tensor], torch.Tensor]


def fixed_test_scenario(
    config: EnvConfig | None, env_seed: int, episodes: int
) -> tuple[EnvConfig, Any, Any]:
    """The test scenario's env config (``config``, else the ``paper`` preset, at full density on
    one world) and the start/goal pairs of its first ``episodes`` episodes."""
    cfg = (config or make_config("paper")).replace(density=1.0, num_worlds=1)
    starts, goals = fixed_scenario(cfg, env_seed, episodes)
    return cfg, starts, goals


@torch.no_grad()
def evaluate(
    policy: Policy,
    config: EnvConfig | None = None,
    env_seed: int = 1,
    episodes: int = 200,
    device: str = "cpu",
    shield: Shield | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Fly ``episodes`` episodes of the fixed test scenario; returns the metrics as a dict.

    ``policy`` maps a batch of observations (dict of tensors) to normalised actions. ``shield``,
    if given, corrects each action from the env's state before it is applied.

    Metrics: ``success_rate``, ``collision_rate``, ``timeout_rate`` (they sum to 1);
    ``mean_time_to_goal`` (s, successful episodes); ``mean_path_length`` (m); ``min_clearance``
    (m, the closest any episode came to an obstacle surface, negative inside one);
    ``mean_min_clearance`` (m, per-episode minimum averaged); ``mean_speed`` (m/s);
    ``mean_return``, ``mean_cost``; ``collision_static_rate``, ``collision_dynamic_rate``,
    ``collision_bounds_rate`` (what the collisions were with; bounds = the altitude band or the
    border wall), ``collision_border_rate`` (the wall alone); how the policy flies:
    ``detour_ratio`` (path length / straight start-goal distance, mean over successful episodes),
    ``border_time_fraction`` (share of all flight time within 2 m of the border),
    ``outside_time_fraction`` (share outside the map: 0 in the closed arena, kept as a guard);
    ``episodes``; and ``per_episode`` lists.
    """
    cfg, starts, goals = fixed_test_scenario(config, env_seed, episodes)
    env = SafeNavVectorEnv(episodes, config=cfg, device=device, output="torch",
                           autoreset_mode="Disabled")  # fmt: skip
    obs, _ = env.reset(seed=env_seed, options={"starts": starts, "goals": goals})
    done = torch.zeros(episodes, dtype=torch.bool, device=env.device)
    keys = ("success", "collision", "timeout", "time", "path_length", "min_clearance",
            "mean_speed", "return", "cost", "hit_static", "hit_dynamic", "out_of_bounds",
            "hit_border", "detour_ratio", "border_time", "outside_time")  # fmt: skip
    act = (lambda o: policy(o, env)) if getattr(policy, "needs_env", False) else policy
    record = {k: torch.zeros(episodes, device=env.device) for k in keys}
    arithmetic = contextlib.nullcontext()
    if shield is not None:  # one episode or 200: each flies as it does in the other's batch
        from safenav.deploy.shield import batched_arithmetic

        arithmetic = batched_arithmetic()
    with Progress(disable=not progress, transient=True) as bar, arithmetic:
        task = bar.add_task(f"eval {episodes} episodes", total=cfg.max_episode_steps)
        for _ in range(cfg.max_episode_steps):
            action = act(obs).to(env.device).clamp(-1, 1)
            if shield is not None:
                action = shield(env, obs, action)
            action = torch.where(done[:, None], torch.zeros_like(action), action)
            obs, _, term, trunc, info = env.step(action)
            ended = (term | trunc) & ~done
            if bool(ended.any()):
                for k in keys:
                    record[k][ended] = info["episode"][k][ended].float()
                done |= ended
            bar.advance(task)
            if bool(done.all()):
                break
    rec = {k: v.cpu().numpy() for k, v in record.items()}
    success = rec["success"] > 0.5
    steps = rec["time"]  # flight time per episode: weights of the time fractions
    return {
        "success_rate": float(success.mean()),
        "collision_rate": float((rec["collision"] > 0.5).mean()),
        "timeout_rate": float((rec["timeout"] > 0.5).mean()),
        "mean_time_to_goal": float(rec["time"][success].mean()) if success.any() else math.nan,
        "mean_path_length": float(rec["path_length"].mean()),
        "min_clearance": float(rec["min_clearance"].min()),
        "mean_min_clearance": float(rec["min_clearance"].mean()),
        "mean_speed": float(rec["mean_speed"].mean()),
        "mean_return": float(rec["return"].mean()),
        "mean_cost": float(rec["cost"].mean()),
        # Fractions of all episodes that ended touching a pillar / a moving obstacle / leaving
        # the altitude band (a collision can touch both obstacle kinds at once).
        "collision_static_rate": float((rec["hit_static"] > 0.5).mean()),
        "collision_dynamic_rate": float((rec["hit_dynamic"] > 0.5).mean()),
        "collision_bounds_rate": float((rec["out_of_bounds"] > 0.5).mean()),
        "collision_border_rate": float((rec["hit_border"] > 0.5).mean()),
        "detour_ratio": float(rec["detour_ratio"][success].mean()) if success.any() else math.nan,
        "border_time_fraction": float((rec["border_time"] * steps).sum() / steps.sum()),
        "outside_time_fraction": float((rec["outside_time"] * steps).sum() / steps.sum()),
        "episodes": int(episodes),
        "env_seed": int(env_seed),
        "per_episode": {k: np.round(v, 4).tolist() for k, v in rec.items()},
    }


__all__ = ["Policy", "Shield", "evaluate"]
