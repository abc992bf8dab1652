"""Costs for Gymnasium envs that report none: ``--cost-fn module:function`` and the velocity tasks.

Constrained algorithms (CSAC, SAC-Lag, PPO-Lag) read the cost of a step from ``info["cost"]``
(:mod:`safenav.envs.vector`); an env without one makes them their unconstrained forms. Two ways
to give an env a cost:

- ``safenav train --env ID --cost-fn module:function``: :class:`CostFn` wraps every env of the run
  and sets ``info["cost"] = function(obs, action, next_obs, info)`` (``obs`` before the step,
  ``next_obs`` after it, ``info`` the env's own step info);
- a registered id whose env sets the cost itself, such as the velocity tasks below (or one of
  your own, registered with a wrapper and passed as ``--env module:ID``).

Velocity tasks
--------------
``SafetyHopperVelocity-v5`` and ``SafetyHalfCheetahVelocity-v5``: Gymnasium's ``Hopper-v5`` and
``HalfCheetah-v5`` (rewards, terminations and the 1000-step limit unchanged) with Safety-Gymnasium's
velocity cost: 1 in each step whose velocity exceeds the task's threshold, else 0. The velocity is
``|x_velocity|`` (``sqrt(x_velocity^2 + y_velocity^2)`` where the env reports ``y_velocity``), as
Safety-Gymnasium's documentation gives it (docs/environments/safe_velocity.rst; its code compares
the signed ``x_velocity``: the two differ only when the agent runs backwards faster than the
threshold). The thresholds are Safety-Gymnasium's ``v1`` ones (half the top speed PPO reaches after
1e7 steps, per the same page): Hopper 0.7402, HalfCheetah 3.2096. Safety-Gymnasium builds its
``v1`` tasks on Gymnasium's MuJoCo ``v4`` models; these use ``v5`` (Safety-Gymnasium does not
import on Python 3.11), so published figures compare approximately. The cost functions
:func:`hopper_velocity_cost` and :func:`half_cheetah_velocity_cost` give the same cost through
``--cost-fn`` (``--env Hopper-v5 --cost-fn safenav.common.costs:hopper_velocity_cost``).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from safenav.errors import SafenavError

CostFunction = Callable[[Any, Any, Any, dict], float]

VELOCITY_THRESHOLDS = {"Hopper-v5": 0.7402, "HalfCheetah-v5": 3.2096}
"""Safety-Gymnasium's v1 velocity thresholds (m/s) of the base tasks (module docstring)."""
VELOCITY_TASKS = {"SafetyHopperVelocity-v5": "Hopper-v5",
                  "SafetyHalfCheetahVelocity-v5": "HalfCheetah-v5"}  # fmt: skip
"""The registered velocity tasks and their base envs."""


def load_cost_fn(spec: str) -> CostFunction:
    """The callable named by ``module:function``; :class:`SafenavError` naming what is wrong."""
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise SafenavError(f"--cost-fn {spec!r}: give module:function, e.g. "
                           "safenav.common.costs:hopper_velocity_cost")  # fmt: skip
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise SafenavError(f"--cost-fn {spec}: cannot import {module_name} ({err})") from None
    fn = getattr(module, attr, None)
    if not callable(fn):
        raise SafenavError(f"--cost-fn {spec}: {module_name} has no function {attr}")
    return fn


class CostFn(gym.Wrapper):
    """Sets ``info["cost"] = fn(obs, action, next_obs, info)`` in every step (module docstring);
    ``fn`` is a callable or a ``module:function`` name."""

    def __init__(self, env: gym.Env, fn: CostFunction | str) -> None:
        super().__init__(env)
        self.fn = load_cost_fn(fn) if isinstance(fn, str) else fn
        self._obs: Any = None

    def reset(self, **kwargs: Any):
        obs, info = self.env.reset(**kwargs)
        self._obs = obs
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        cost = float(self.fn(self._obs, action, obs, info))
        if not math.isfinite(cost):
            raise ValueError(f"cost function {self.fn!r} returned {cost}")
        self._obs = obs
        return obs, reward, terminated, truncated, {**info, "cost": cost}


def velocity(info: dict) -> float:
    """The speed Safety-Gymnasium's velocity cost compares (module docstring)."""
    if "y_velocity" in info:
        return float(np.hypot(info["x_velocity"], info["y_velocity"]))
    return abs(float(info["x_velocity"]))


def velocity_cost(info: dict, threshold: float) -> float:
    """1.0 when the step's velocity exceeds ``threshold``, else 0.0."""
    if "x_velocity" not in info:
        raise KeyError("the velocity cost needs info['x_velocity'] (Gymnasium's MuJoCo "
                       "locomotion envs report it)")  # fmt: skip
    return float(velocity(info) > threshold)


def hopper_velocity_cost(obs, action, next_obs, info: dict) -> float:
    """``--cost-fn`` form of SafetyHopperVelocity's cost (threshold 0.7402) on Hopper-v5."""
    return velocity_cost(info, VELOCITY_THRESHOLDS["Hopper-v5"])


def half_cheetah_velocity_cost(obs, action, next_obs, info: dict) -> float:
    """``--cost-fn`` form of SafetyHalfCheetahVelocity's cost (threshold 3.2096) on
    HalfCheetah-v5."""
    return velocity_cost(info, VELOCITY_THRESHOLDS["HalfCheetah-v5"])


class VelocityCost(gym.Wrapper):
    """``info["cost"]`` = 1 in each step whose velocity exceeds ``threshold`` (module docstring);
    ``info["velocity"]`` the speed compared."""

    def __init__(self, env: gym.Env, threshold: float) -> None:
        super().__init__(env)
        self.threshold = float(threshold)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        cost = velocity_cost(info, self.threshold)
        return (
            obs,
            reward,
            terminated,
            truncated,
            {**info, "cost": cost, "velocity": velocity(info)},
        )


def make_velocity_task(base: str, threshold: float | None = None, **kwargs: Any) -> gym.Env:
    """The entry point of the velocity tasks: ``base`` (its unwrapped env: the registered id
    adds the time limit and Gymnasium's checks) under :class:`VelocityCost`."""
    env = gym.make(base, disable_env_checker=True, **kwargs).unwrapped
    return VelocityCost(env, VELOCITY_THRESHOLDS[base] if threshold is None else threshold)


def register_velocity_tasks() -> None:
    """Register :data:`VELOCITY_TASKS` with Gymnasium (once; ``import safenav`` does it)."""
    for task, base in VELOCITY_TASKS.items():
        if task not in gym.registry:
            gym.register(id=task, entry_point="safenav.common.costs:make_velocity_task",
                         kwargs={"base": base}, max_episode_steps=1000)  # fmt: skip


__all__ = ["VELOCITY_TASKS", "VELOCITY_THRESHOLDS", "CostFn", "VelocityCost", "half_cheetah_velocity_cost",
           "hopper_velocity_cost", "load_cost_fn", "make_velocity_task", "register_velocity_tasks",
           "velocity_cost"]  # fmt: skip
