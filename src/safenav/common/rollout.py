"""On-policy rollout storage and the running return statistics of value normalisation.

:class:`Rollout` holds ``T`` vector steps of ``N`` envs as ``(T, N, ...)`` tensors on the training
device. Besides ``(s, a, log pi(a|s), r, c, terminated, truncated)`` and the values ``V(s)`` it
keeps ``next_values``: the value of the *true* next state of every transition. It is filled with
``V(s_{t+1})`` when the rollout is complete, except where the episode was truncated - there
the value of the episode's final observation (``info["final_obs"]``) is kept, so the time limit
bootstraps (:func:`safenav.algos.ppo_losses.gae`).
"""

from __future__ import annotations

import torch


class Rollout:
    """Fixed-size on-policy storage, ``T`` steps x ``N`` envs (see module docstring)."""

    def __init__(self, steps: int, num_envs: int, obs_shapes: dict[str, tuple[int, ...]],
                 action_dim: int, num_values: int = 1, device: str | torch.device = "cpu") -> None:  # fmt: skip
        self.steps, self.num_envs, self.device = steps, num_envs, torch.device(device)

        def z(*shape: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
            return torch.zeros((steps, num_envs, *shape), dtype=dtype, device=self.device)

        self.obs = {k: z(*s) for k, s in obs_shapes.items()}
        self.actions = z(action_dim)
        self.log_probs = z()
        self.rewards = z(num_values)  # reward (and cost) signals side by side, like the values
        self.values = z(num_values)  # V(s_t), denormalised
        self.next_values = z(num_values)  # V(true s'_t), denormalised (see module docstring)
        self.terminated = z(dtype=torch.bool)
        self.truncated = z(dtype=torch.bool)
        self.t = 0

    def add(self, obs: dict[str, torch.Tensor], actions: torch.Tensor, log_probs: torch.Tensor,
            values: torch.Tensor, rewards: torch.Tensor, terminated: torch.Tensor,
            truncated: torch.Tensor, final_values: torch.Tensor | None = None) -> None:  # fmt: skip
        """Store step ``t``; ``final_values`` ``(N, K)``: the value of the final observation
        where ``truncated`` (other rows are ignored)."""
        t = self.t
        for k, v in obs.items():
            self.obs[k][t] = v
        self.actions[t], self.log_probs[t], self.values[t] = actions, log_probs, values
        self.rewards[t] = rewards
        self.terminated[t], self.truncated[t] = terminated, truncated
        if final_values is not None:
            self.next_values[t] = final_values
        self.t += 1

    def finish(self, last_values: torch.Tensor) -> None:
        """Complete ``next_values`` with ``V(s_{t+1})`` (``last_values`` after the last step),
        keeping the final-observation values of truncated steps."""
        nxt = torch.cat([self.values[1:], last_values.unsqueeze(0)], 0)
        keep = (self.truncated & ~self.terminated).unsqueeze(-1)
        self.next_values = torch.where(keep, self.next_values, nxt)
        self.t = 0

    def flat_obs(self) -> dict[str, torch.Tensor]:
        return {k: v.flatten(0, 1) for k, v in self.obs.items()}


class ValueNorm(torch.nn.Module):
    """Running mean and standard deviation of value targets (NavRL's / MAPPO's ``ValueNorm``):
    debiased exponential moving averages of ``E[R]`` and ``E[R^2]`` per signal,

        m <- beta m + (1 - beta) mean(R),   s <- beta s + (1 - beta) mean(R^2),   w <- beta w + (1 - beta)
        mu = m / w,   sigma = sqrt(max(s / w - mu^2, 1e-2))

    updated once per rollout. Critics predict ``(R - mu) / sigma``; :meth:`denormalize` maps their
    output back to returns. Buffers, so they are saved in the checkpoint.
    """

    def __init__(self, num_values: int = 1, beta: float = 0.995, enabled: bool = True) -> None:
        super().__init__()
        self.beta, self.enabled = beta, enabled
        self.register_buffer("running_mean", torch.zeros(num_values))
        self.register_buffer("running_mean_sq", torch.zeros(num_values))
        self.register_buffer("debias", torch.zeros(()))

    def stats(self) -> tuple[torch.Tensor, torch.Tensor]:
        if not self.enabled or float(self.debias) == 0.0:
            return torch.zeros_like(self.running_mean), torch.ones_like(self.running_mean)
        mean = self.running_mean / self.debias
        var = (self.running_mean_sq / self.debias - mean.pow(2)).clamp(min=1e-2)
        return mean, var.sqrt()

    @torch.no_grad()
    def update(self, returns: torch.Tensor) -> None:
        """Fold in a batch of returns ``(..., K)``."""
        if not self.enabled:
            return
        flat = returns.reshape(-1, returns.shape[-1])
        b = self.beta
        self.running_mean.mul_(b).add_((1 - b) * flat.mean(0))
        self.running_mean_sq.mul_(b).add_((1 - b) * flat.pow(2).mean(0))
        self.debias.mul_(b).add_(1 - b)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        mean, std = self.stats()
        return (x - mean) / std

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        mean, std = self.stats()
        return x * std + mean


__all__ = ["Rollout", "ValueNorm"]
