"""A privileged planner's flights for a learner to replay (``--csac.planner-share``, beyond the
paper; docs/csac-v1.md, "The planner's flights in the replay").

Before training, :func:`fly_planner` flies planner B (:data:`~safenav.envs.planner.PLANNER_B`:
the range image's hits of the last second, the observation's moving obstacles, read from the
simulator; or, ``--csac.planner-view pillars``, the pillars' exact geometry within 4 m) on
``planner_envs`` envs of the run's own env config at the curriculum's final density, on maps
of their own (:meth:`~safenav.common.config.RunConfig.planner_env_seed`: neither the training maps
nor the validation, held-out or test ones), until ``planner_steps`` transitions. The learner keeps
them apart from its replay buffer and draws a fixed share of each minibatch from them (RLPD's
symmetric sampling, Ball et al. 2023, "Efficient Online Reinforcement Learning with Offline Data",
there with a share of 0.5). The policy never sees the planner at flight time; the planner's
transitions are not counted in the run's env steps (they are reported beside them).

The global RNG is left as a run without the flights would find it, so that both start from
the same initial weights and the same random warm-up.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np
import torch

from safenav.common.buffer import Batch
from safenav.common.checkpoint import rng_state, set_rng_state
from safenav.common.config import RunConfig
from safenav.common.progress import ProgressDisplay
from safenav.envs.planner import PLANNERS, AutoresetPlanner
from safenav.envs.vector import TorchVecEnv, make_vec_env

Flight = tuple[Batch, torch.Tensor, torch.Tensor]
"""One vector step of the planner: ``(transition, truncated, valid)``, as a learner stores it."""


def fly_planner(run: RunConfig, env_kwargs: dict[str, Any], steps: int, num_envs: int,
                device: torch.device | str, progress: bool = True,
                keep_band: bool = False, view: str = "range",
                ) -> tuple[list[Flight], dict[str, Any]]:  # fmt: skip
    """``ceil(steps / num_envs)`` vector steps of the planner on the run's env (``env_kwargs``:
    its overrides, the density among them), keeping NavRL's altitude band when ``keep_band``
    (``OracleConfig.keep_band``), the planner of ``view`` (``PLANNERS``): the flights and their
    statistics (``transitions``, ``episodes``, ``success_rate``, ``collision_rate`` of the
    episodes that ended (None if none did), ``wall_s``)."""
    t0 = time.perf_counter()
    rng = rng_state()  # Python, NumPy and torch: restored below
    try:
        env = TorchVecEnv(make_vec_env(run.env, num_envs, device, run.preset, **env_kwargs), device)
        nav = env.envs.unwrapped
        planner = AutoresetPlanner(dataclasses.replace(PLANNERS[view], keep_band=keep_band))
        obs = env.reset(seed=run.planner_env_seed())
        flights: list[Flight] = []
        ended = {"success": [], "collision": []}
        n = math.ceil(steps / num_envs)
        display = ProgressDisplay(n * num_envs, enabled=progress, title="planner flights")
        try:
            for i in range(n):
                actions = planner(obs, nav)
                step = env.step(actions)
                own = lambda o: {k: v.clone() for k, v in o.items()}  # noqa: E731 (no aliasing)
                flights.append((Batch(own(obs), actions, step.reward, step.cost,
                                      own(step.real_next_obs), step.terminated),
                                step.truncated, step.valid))  # fmt: skip
                if step.episodes is not None:
                    for k in ended:
                        ended[k] += step.episodes[k].tolist()
                obs = step.next_obs
                display.advance((i + 1) * num_envs)
        finally:
            display.close()
            env.envs.close()
    finally:
        set_rng_state(rng)
    episodes = len(ended["success"])
    rate = lambda k: float(np.mean(ended[k])) if episodes else None  # noqa: E731
    stats = {"transitions": n * num_envs, "episodes": episodes, "success_rate": rate("success"),
             "collision_rate": rate("collision"), "wall_s": time.perf_counter() - t0}  # fmt: skip
    return flights, stats


__all__ = ["Flight", "fly_planner"]
