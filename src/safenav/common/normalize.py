"""Observation and reward normalisation of a Gymnasium run (``--normalize-obs``,
``--normalize-reward``): Stable-Baselines3's ``VecNormalize``, whose ``normalize: true`` the RL
Zoo's tuned entries use (e.g. PPO on MountainCarContinuous-v0).

- observations, per entry of every observation key (:class:`ObsNormalizer`):
  ``clip((x - mu) / sqrt(var + 1e-8), -10, 10)``, ``mu`` and ``var`` running over every
  observation the training env returns (reset and step);
- rewards (:class:`RewardScaler`): ``clip(r / sqrt(Var[R] + 1e-8), -10, 10)`` with ``R`` the
  discounted return so far, ``R <- gamma R + r`` (the algorithm's ``gamma``), set to 0 where an
  episode ends; ``Var[R]`` running over every step's ``R``. Not centred: the sign of a reward is
  kept. The cost (``info["cost"]``) is never scaled.

Running statistics (:class:`RunningMeanStd`) are Chan et al.'s parallel update of mean, variance
and count, as ``gymnasium.wrappers.utils.RunningMeanStd`` and SB3's, from the same start (count
``1e-4``, mean 0, variance 1), in float64 torch buffers, so that they live in ``state_dict``\\ s.
On the CPU the env side (updates, the observations and rewards it hands the learner) computes
through NumPy views of those buffers: the same float64 and float32 operations in the same order,
without torch's per-operation dispatch, which cost more than a MuJoCo step per env step (about
1 ms against 0.4 ms on Hopper-v5 with one env). The actor's normaliser (what ONNX export traces)
stays in torch.

The statistics are part of the policy: :class:`NormalizedActor` puts the observation normaliser
in front of a deterministic actor (what ``best.pt`` and ``load_policy`` hold, and what ONNX export
traces), with the statistics as they were when it was saved. :class:`EnvNormalization` is what
the training env (:class:`~safenav.envs.vector.TorchVecEnv`) applies: it updates the statistics
with each observation, then normalises it, its true final observation and its reward; the
episode statistics stay in the env's own units.

Why not Gymnasium's ``gymnasium.wrappers.vector.NormalizeObservation`` / ``NormalizeReward``:
the first refuses the ``SAME_STEP`` autoreset that safenav's vector envs use and leaves
``info["final_obs"]`` (the bootstrap observation of a truncated episode) unnormalised; wrapped
around the gymnasium env, the second would make every reported episode return a scaled one; and
neither clips.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

CLIP = 10.0
"""Bound of normalised observations and scaled rewards (SB3's ``clip_obs``, ``clip_reward``)."""
EPSILON = 1e-8
"""Added to the variance under the square root (SB3's ``epsilon``)."""


def _clip(x: np.ndarray, bound: float) -> np.ndarray:
    """``x`` clipped to ``[-bound, bound]`` in place (``np.clip``'s dispatch costs more here)."""
    np.minimum(x, bound, out=x)
    return np.maximum(x, -bound, out=x)


class RunningMeanStd(nn.Module):
    """Running mean and (population) variance of batches of ``shape``-sized values, float64
    buffers: ``update(x)`` folds in ``x`` ``(B, *shape)`` (Chan et al.'s parallel algorithm;
    ``gymnasium.wrappers.utils.update_mean_var_count_from_moments``)."""

    def __init__(self, shape: tuple[int, ...] = (), count: float = 1e-4) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(shape, dtype=torch.float64))
        self.register_buffer("var", torch.ones(shape, dtype=torch.float64))
        self.register_buffer("count", torch.tensor(count, dtype=torch.float64))

    def update(self, x: torch.Tensor) -> None:
        if self.mean.device.type == "cpu" and x.device.type == "cpu":
            self._update_numpy(x.detach().numpy().astype(np.float64))
        else:
            with torch.no_grad():
                self._update_torch(x.to(torch.float64))

    def _update_torch(self, x: torch.Tensor) -> None:
        n = x.shape[0]
        batch_mean, batch_var = x.mean(0), x.var(0, correction=0)
        delta = batch_mean - self.mean
        total = self.count + n
        m2 = self.var * self.count + batch_var * n + delta.square() * self.count * n / total
        self.mean.add_(delta * n / total)
        self.var.copy_(m2 / total)
        self.count.copy_(total)

    def numpy_views(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """NumPy views of the CPU buffers ``(mean, var, count)``, made again only when a buffer
        was replaced (``.to()``; ``load_state_dict`` copies in place)."""
        b = self._buffers
        key = (b["mean"], b["var"], b["count"])
        cached = self.__dict__.get("_views")
        if cached is None or any(t is not c for t, c in zip(key, cached[0], strict=True)):
            cached = (key, tuple(t.numpy() for t in key))
            self.__dict__["_views"] = cached
        return cached[1]

    def _update_numpy(self, x: np.ndarray) -> None:
        """:meth:`update` on NumPy views of the CPU buffers, operation for operation."""
        mean, var, count = self.numpy_views()
        n, c = x.shape[0], float(count)
        total = c + n
        if n == 1:  # one env: the batch's mean is its row and its variance 0 (exactly as torch)
            delta = x[0] - mean
            m2 = var * c + np.square(delta) * c * n / total
        else:  # torch's reductions, whose summation order NumPy's need not share
            xt = torch.from_numpy(x)
            delta = xt.mean(0).numpy() - mean
            m2 = var * c + xt.var(0, correction=0).numpy() * n + np.square(delta) * c * n / total
        mean += delta * n / total
        var[...] = m2 / total
        count[...] = total


class ObsNormalizer(nn.Module):
    """``{key: x}`` -> ``{key: clip((x - mu_key) / sqrt(var_key + eps), -clip, clip)}`` in float32
    (the module docstring); :meth:`update` folds a batch of observations into the statistics.
    Keys it has no statistics for pass unchanged."""

    def __init__(self, obs_shapes: dict[str, tuple[int, ...]], clip: float = CLIP,
                 epsilon: float = EPSILON) -> None:  # fmt: skip
        super().__init__()
        self.keys = tuple(sorted(obs_shapes))
        self.clip, self.epsilon = float(clip), float(epsilon)
        # a list in key order, not a ModuleDict: observation keys may hold characters that
        # module names may not (".")
        self.stats = nn.ModuleList(RunningMeanStd(tuple(obs_shapes[k])) for k in self.keys)

    def update(self, obs: dict[str, torch.Tensor]) -> None:
        for k, rms in zip(self.keys, self.stats, strict=True):
            rms.update(obs[k])

    def normalize(self, x: torch.Tensor, rms: RunningMeanStd) -> torch.Tensor:
        mean = rms.mean.to(x.dtype)
        std = torch.sqrt(rms.var + self.epsilon).to(x.dtype)
        return ((x - mean) / std).clamp(-self.clip, self.clip)

    def forward(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        out = dict(obs)
        for k, rms in zip(self.keys, self.stats, strict=True):
            out[k] = self.normalize(obs[k], rms)
        return out

    def env_side(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """:meth:`forward` for the training env: through NumPy where everything is on the CPU
        (the module docstring), the same values."""
        out = dict(obs)
        for k, rms in zip(self.keys, self.stats, strict=True):
            x = obs[k]
            if x.device.type != "cpu" or rms.mean.device.type != "cpu":
                with torch.no_grad():
                    out[k] = self.normalize(x, rms)
                continue
            xs = x.detach().numpy()
            mean, var, _ = rms.numpy_views()
            mean = mean.astype(xs.dtype)
            std = np.sqrt(var + self.epsilon).astype(xs.dtype)
            out[k] = torch.from_numpy(_clip((xs - mean) / std, self.clip))
        return out

    def meta(self) -> dict[str, float]:
        """What :func:`safenav.algos.policy.build_actor` needs to rebuild it (the policy meta's
        ``obs_normalization``)."""
        return {"clip": self.clip, "epsilon": self.epsilon}


class NormalizedActor(nn.Module):
    """A deterministic actor (observation tensors positional, in ``input_names`` order) that
    normalises its inputs first with the saved statistics of :class:`ObsNormalizer`."""

    def __init__(self, normalizer: ObsNormalizer, actor: nn.Module) -> None:
        super().__init__()
        self.normalizer = normalizer
        self.actor = actor
        self.input_names = tuple(actor.input_names)

    def _normalized(self, inputs: tuple[torch.Tensor, ...]) -> list[torch.Tensor]:
        obs = self.normalizer(dict(zip(self.input_names, inputs, strict=True)))
        return [obs[k] for k in self.input_names]

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.actor(*self._normalized(inputs))

    def gaussian(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The wrapped SAC-family actor's ``gaussian`` on the normalised inputs."""
        return self.actor.gaussian(*self._normalized(inputs))


class RewardScaler(nn.Module):
    """``r / sqrt(Var[R] + eps)`` clipped to ``[-clip, clip]``, ``R`` the discounted return of
    each env so far (the module docstring). ``returns`` is not saved: a resumed run resets its
    envs, so every return starts anew."""

    def __init__(self, num_envs: int, gamma: float, clip: float = CLIP,
                 epsilon: float = EPSILON) -> None:  # fmt: skip
        super().__init__()
        self.gamma, self.clip, self.epsilon = float(gamma), float(clip), float(epsilon)
        self.return_rms = RunningMeanStd(())
        self.register_buffer("returns", torch.zeros(num_envs, dtype=torch.float64),
                             persistent=False)  # fmt: skip

    def reset(self) -> None:
        self.returns.zero_()

    def forward(self, reward: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        """The scaled rewards of one vector step (and the statistics updated with it); ``done``
        ends the returns of the envs whose episode ended."""
        if reward.device.type == "cpu" and self.returns.device.type == "cpu":
            returns, r = self.returns.numpy(), reward.detach().numpy()
            returns *= self.gamma
            returns += r.astype(np.float64)
            self.return_rms._update_numpy(returns)
            std = np.sqrt(self.return_rms.numpy_views()[1] + self.epsilon)
            returns[done.numpy()] = 0.0
            return torch.from_numpy(_clip(r / std.astype(r.dtype), self.clip))
        with torch.no_grad():
            self.returns.mul_(self.gamma).add_(reward.to(torch.float64))
            self.return_rms.update(self.returns)
            std = torch.sqrt(self.return_rms.var + self.epsilon)
            self.returns[done] = 0.0
            return (reward / std.to(reward.dtype)).clamp(-self.clip, self.clip)


class EnvNormalization(nn.Module):
    """What a training env applies (either part may be None): the statistics are updated with
    every observation it returns, before it is normalised (SB3's order)."""

    def __init__(self, obs: ObsNormalizer | None, reward: RewardScaler | None) -> None:
        super().__init__()
        self.obs, self.reward = obs, reward

    def reset(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Observations of a reset (every env): returns start anew."""
        if self.reward is not None:
            self.reward.reset()
        if self.obs is None:
            return obs
        self.obs.update(obs)
        return self.obs.env_side(obs)

    def step(self, next_obs: dict[str, torch.Tensor], real_next_obs: dict[str, torch.Tensor],
             reward: torch.Tensor, done: torch.Tensor):  # fmt: skip
        """``(next_obs, real_next_obs, reward)`` of one vector step, normalised (``real_next_obs``
        may be ``next_obs`` itself, when no episode ended: then so is the result's)."""
        if self.obs is not None:
            self.obs.update(next_obs)
            same = real_next_obs is next_obs  # no episode ended: normalised once, the same values
            next_obs = self.obs.env_side(next_obs)
            real_next_obs = next_obs if same else self.obs.env_side(real_next_obs)
        if self.reward is not None:
            reward = self.reward(reward, done)
        return next_obs, real_next_obs, reward

    def policy(self, actor: nn.Module) -> nn.Module:
        """``actor`` behind the observation normaliser (``actor`` itself without one)."""
        return NormalizedActor(self.obs, actor) if self.obs is not None else actor

    def meta(self) -> dict[str, Any]:
        """The policy meta's entry: ``{"obs_normalization": ...}`` or nothing."""
        return {"obs_normalization": self.obs.meta()} if self.obs is not None else {}


def make_normalization(obs_shapes: dict[str, tuple[int, ...]], num_envs: int, gamma: float,
                       obs: bool, reward: bool) -> EnvNormalization | None:  # fmt: skip
    """The normalisation of a run (``RunConfig.normalize_obs`` / ``normalize_reward``), or None."""
    if not (obs or reward):
        return None
    return EnvNormalization(ObsNormalizer(obs_shapes) if obs else None,
                            RewardScaler(num_envs, gamma) if reward else None)  # fmt: skip


__all__ = ["CLIP", "EPSILON", "EnvNormalization", "NormalizedActor", "ObsNormalizer",
           "RewardScaler", "RunningMeanStd", "make_normalization"]  # fmt: skip
