"""Training behind the safety shield (``safenav train --shield``, beyond the paper).

:class:`ShieldedVecEnv` puts a shield between a learner and its
:class:`~safenav.envs.vector.TorchVecEnv`: ``step(action)`` executes ``shield(env, obs,
action)``, the correction of the action by the velocity-obstacle shield on the observation the
action was chosen on, while the learner stores the action it chose. The shield is then part of
the env the policy learns in (Alshiekh et al., 2018, "Safe Reinforcement Learning via
Shielding": the shield as a post-posed layer), and the policy is meant to fly behind it: its
periodic evaluation, selection and final report do.

With a ``penalty`` (``safenav train --shield-penalty K``, beyond the paper and NavRL), the
learner's reward falls by ``K`` per m/s of correction at each step, so that it learns to ask for
velocities the shield lets through rather than to lean on it (a shield's penalty on the unsafe
action, as in Alshiekh et al.'s shielding with punishment). The episode statistics (returns in
the logs) are the env's own, without it.

The shield itself lives with the deployment code (:mod:`safenav.deploy.shield`), above this
layer: the caller passes a factory, ``shield_factory(spec)`` with ``spec`` from
:meth:`~safenav.common.config.RunConfig.shield_spec`, that returns a fresh shield (a memory shield
keeps one memory per env, so the training and evaluation envs each get their own).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from safenav.envs.vector import Step, TorchVecEnv

ShieldFn = Callable[[Any, dict[str, torch.Tensor], torch.Tensor], torch.Tensor]
"""``shield(nav_env, obs, action) -> action``: a :class:`~safenav.envs.nav.SafeNavVectorEnv`
with torch output, the observation the actions were chosen on, actions in ``[-1, 1]``."""


class ShieldedVecEnv:
    """A :class:`TorchVecEnv` whose env executes the shield's corrections (module docstring);
    every other attribute is the wrapped env's."""

    def __init__(self, env: TorchVecEnv, shield: ShieldFn, penalty: float = 0.0) -> None:
        if env.normalization is not None:  # the shield reads the env's own range image
            raise ValueError("the shield reads raw SafeNav observations: no --normalize-obs")
        if not 0.0 <= penalty < float("inf"):
            raise ValueError(f"shield penalty must be >= 0, got {penalty}")
        self.inner, self.shield, self.penalty = env, shield, float(penalty)
        self.nav = env.envs.unwrapped
        self._obs: dict[str, torch.Tensor] | None = None
        self.actions = 0
        self.corrected = torch.zeros((), dtype=torch.long, device=env.device)  # no sync per step

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def reset(self, seed: int | None = None) -> dict[str, torch.Tensor]:
        self._obs = self.inner.reset(seed=seed)
        return self._obs

    def step(self, action: torch.Tensor) -> Step:
        if self._obs is None:
            raise RuntimeError("ShieldedVecEnv.step before reset")
        action = action.clamp(-1.0, 1.0)
        safe = self.shield(self.nav, self._obs, action)
        self.actions += action.shape[0]
        self.corrected += (safe != action).any(-1).sum()
        step = self.inner.step(safe)
        self._obs = step.next_obs
        if self.penalty > 0:  # the learner pays for the correction it needed (m/s of it)
            change = (safe - action).norm(dim=-1) * self.nav.cfg.v_max
            step = step._replace(reward=step.reward - self.penalty * change * step.valid)
        return step

    def correction_rate(self) -> float:
        """The share of actions the shield changed since the last call (then counts anew)."""
        rate = int(self.corrected) / self.actions if self.actions else float("nan")
        self.actions = 0
        self.corrected.zero_()
        return rate


__all__ = ["ShieldFn", "ShieldedVecEnv"]
