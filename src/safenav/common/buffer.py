"""Uniform experience replay for off-policy algorithms, stored on the training device.

A transition is ``(s, a, r, c, s', terminated)``. ``s'`` is the *true* next observation: for an
env that just finished, the last observation of its episode (the vector env's ``final_obs``), not
the first of the next one. ``terminated`` alone masks bootstrapping; a time-limit truncation is
stored as not terminated, so its target bootstraps from ``s'`` (tests/test_csac.py).
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class Batch(NamedTuple):
    obs: dict[str, torch.Tensor]
    actions: torch.Tensor
    rewards: torch.Tensor
    costs: torch.Tensor
    next_obs: dict[str, torch.Tensor]
    terminated: torch.Tensor


class ReplayBuffer:
    """A ring buffer of ``capacity`` transitions; observations are dicts of float32 tensors."""

    def __init__(self, capacity: int, obs_shapes: dict[str, tuple[int, ...]], action_dim: int,
                 device: str | torch.device = "cpu") -> None:  # fmt: skip
        if capacity < 1:
            raise ValueError(f"capacity={capacity} must be >= 1")
        self.capacity, self.device = int(capacity), torch.device(device)

        def z(*shape: int) -> torch.Tensor:
            return torch.zeros((self.capacity, *shape), dtype=torch.float32, device=self.device)

        self.obs = {k: z(*s) for k, s in obs_shapes.items()}
        self.next_obs = {k: z(*s) for k, s in obs_shapes.items()}
        self.actions = z(action_dim)
        self.rewards, self.costs, self.terminated = z(), z(), z()
        self.pos, self.size = 0, 0

    def __len__(self) -> int:
        return self.size

    def add(self, obs: dict[str, torch.Tensor], actions: torch.Tensor, rewards: torch.Tensor,
            costs: torch.Tensor, next_obs: dict[str, torch.Tensor], terminated: torch.Tensor,
            valid: torch.Tensor | None = None) -> None:  # fmt: skip
        """Store a batch of ``N`` transitions (rows where ``valid`` is False are skipped)."""
        if valid is not None and not bool(valid.all()):
            keep = valid.nonzero().squeeze(-1)
            obs = {k: v[keep] for k, v in obs.items()}
            next_obs = {k: v[keep] for k, v in next_obs.items()}
            actions, rewards, costs, terminated = (
                actions[keep],
                rewards[keep],
                costs[keep],
                terminated[keep],
            )
        n = actions.shape[0]
        if n == 0:
            return
        idx = torch.arange(self.pos, self.pos + n, device=self.device) % self.capacity
        for k in self.obs:
            self.obs[k][idx] = obs[k].to(self.device, torch.float32)
            self.next_obs[k][idx] = next_obs[k].to(self.device, torch.float32)
        self.actions[idx] = actions.to(self.device, torch.float32)
        self.rewards[idx] = rewards.to(self.device, torch.float32)
        self.costs[idx] = costs.to(self.device, torch.float32)
        self.terminated[idx] = terminated.to(self.device, torch.float32)
        self.pos = (self.pos + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def sample(self, batch_size: int) -> Batch:
        """``batch_size`` transitions drawn uniformly with replacement (torch's global RNG)."""
        if self.size == 0:
            raise RuntimeError("cannot sample from an empty replay buffer")
        idx = torch.randint(0, self.size, (batch_size,), device=self.device)
        return Batch({k: v[idx] for k, v in self.obs.items()}, self.actions[idx], self.rewards[idx],
                     self.costs[idx], {k: v[idx] for k, v in self.next_obs.items()}, self.terminated[idx])  # fmt: skip

    def state_dict(self) -> dict:
        n = self.size
        return {"pos": self.pos, "size": n, "obs": {k: v[:n].cpu() for k, v in self.obs.items()},
                "next_obs": {k: v[:n].cpu() for k, v in self.next_obs.items()},
                "actions": self.actions[:n].cpu(), "rewards": self.rewards[:n].cpu(),
                "costs": self.costs[:n].cpu(), "terminated": self.terminated[:n].cpu()}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        n = min(int(state["size"]), self.capacity)
        for k in self.obs:
            self.obs[k][:n] = state["obs"][k][:n].to(self.device)
            self.next_obs[k][:n] = state["next_obs"][k][:n].to(self.device)
        for name in ("actions", "rewards", "costs", "terminated"):
            getattr(self, name)[:n] = state[name][:n].to(self.device)
        self.size, self.pos = n, int(state["pos"]) % self.capacity


__all__ = ["Batch", "ReplayBuffer"]
