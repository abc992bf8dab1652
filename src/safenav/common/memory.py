"""Memory a training run or an evaluation will need, estimated from its config before anything is
allocated, so that ``--num-envs 10000000`` is refused with the figure instead of dying out of
memory minutes later (:func:`safenav.common.checks.check_memory` compares it with the machine).

The estimates are rough upper bounds (within a factor of about 2), not accounting:

- SafeNav env: ~64 KB per env (state, obstacles, sensing buffers; measured 29 KB/env on the easy
  and 55 KB/env on the paper preset at 2048 envs) plus 16 bytes per occupancy-grid cell of each
  of its ``num_worlds`` maps, twice with per-env map redraws (the env then holds the old and the
  new map set, ``SafeNavVectorEnv.redraw_maps``); another Gymnasium env: ~16 KB per copy;
- replay buffer: ``capacity x (2 observations + action + 4 scalars)`` float32 (its storage is one
  tensor), plus the n-step columns when used; PPO rollout: ``rollout_steps x num_envs``
  transitions, twice (minibatch copies);
- networks: the MLPs' weights with gradients and Adam moments (4 copies), targets (1 copy);
- per-step activations: ``num_envs`` observations through the networks, x8.
"""

from __future__ import annotations

import math
from typing import Any

from safenav.common.families import PPO_ALGOS

FLOAT = 4
SAFENAV_ENV_BYTES = 64 * 1024
GYM_ENV_BYTES = 16 * 1024


def env_bytes(num_envs: int, env_config: Any | None, map_sets: int = 1) -> float:
    """The vector env's memory (``env_config`` None: a non-SafeNav Gymnasium env) holding
    ``map_sets`` sets of maps at a time (2 with per-env redraws)."""
    if env_config is None:
        return num_envs * GYM_ENV_BYTES
    worlds = getattr(env_config, "num_worlds", 0) or min(num_envs, 16)
    cells = (env_config.map_size / env_config.grid_resolution) ** 2
    return num_envs * SAFENAV_ENV_BYTES + map_sets * min(worlds, num_envs) * cells * 16


def _mlp_params(sizes: list[int]) -> int:
    return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:], strict=False))


def network_bytes(net: Any, obs_floats: int, action_dim: int, critics: int,
                  obs_shapes: dict[str, tuple[int, ...]] | None = None) -> float:  # fmt: skip
    """The actor and ``critics`` critics (each with a target copy and its own extractor at
    worst) with Adam state."""
    lidar = (obs_shapes or {}).get("lidar", (4, 36))
    channels = [lidar[0], *net.lidar_channels]
    convs = sum(
        a * b * net.lidar_kernel + b for a, b in zip(channels[:-1], channels[1:], strict=False)
    )
    extractor = (convs + channels[-1] * lidar[-1] * net.lidar_embed
                 + _mlp_params([10, net.dynamic_hidden, net.dynamic_embed])
                 + _mlp_params([obs_floats, *net.flatten_hidden]))  # fmt: skip
    features = net.lidar_embed + net.dynamic_embed + obs_floats + max(net.flatten_hidden, default=0)
    actor = extractor + _mlp_params([features, *net.hidden, 2 * action_dim])
    critic = extractor + _mlp_params([features + action_dim, *net.hidden, 1])
    return (4 * (actor + critics * critic) + critics * critic) * FLOAT


def training_memory(algo: str, num_envs: int, total_steps: int, cfg: Any,
                    obs_shapes: dict[str, tuple[int, ...]], action_dim: int,
                    env_config: Any | None, eval_episodes: int = 0,
                    map_sets: int = 1) -> dict[str, float]:  # fmt: skip
    """Bytes per part of a training run of ``algo`` with algorithm config ``cfg``; the training
    envs hold ``map_sets`` map sets (2 with ``--map-refresh-mode per-env``)."""
    obs = sum(math.prod(s) for s in obs_shapes.values())
    parts = {"envs": env_bytes(num_envs, env_config, map_sets)}
    if algo in PPO_ALGOS:
        per = obs + action_dim + 1 + 3 * 2 + 1
        parts["rollout"] = 2 * cfg.rollout_steps * num_envs * per * FLOAT
        critics = 2
    else:
        capacity = min(cfg.buffer_size, max(total_steps, cfg.batch_size))
        width = 2 * obs + action_dim + 4 + (obs + 2 if getattr(cfg, "cost_n_step", 1) > 1 else 0)
        parts["replay buffer"] = capacity * width * FLOAT
        critics = cfg.num_critics + (cfg.num_cost_critics or cfg.num_critics)
        parts["minibatches"] = 4 * cfg.batch_size * width * FLOAT
    parts["networks"] = network_bytes(cfg.net, obs, action_dim, critics, obs_shapes)
    n_step = getattr(cfg, "cost_n_step", 1)
    if n_step > 1:  # the n-step window keeps n vector steps of transitions
        parts["n-step window"] = n_step * num_envs * (2 * obs + action_dim + 4) * FLOAT
    if eval_episodes:  # the periodic evaluation flies its episodes as one vector env
        parts["evaluation envs"] = env_bytes(eval_episodes, env_config)
    parts["activations"] = 8 * num_envs * (obs + max(cfg.net.hidden, default=0)) * FLOAT
    return parts


__all__ = ["env_bytes", "network_bytes", "training_memory"]
