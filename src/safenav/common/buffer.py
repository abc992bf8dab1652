"""Uniform experience replay for off-policy algorithms, stored on the training device.

A transition is ``(s, a, r, c, s', terminated)``. ``s'`` is the *true* next observation: for an
env that just finished, the last observation of its episode (the vector env's ``final_obs``), not
the first of the next one. ``terminated`` alone masks bootstrapping; a time-limit truncation is
stored as not terminated, so its target bootstraps from ``s'`` (tests/test_csac.py).
"""

from __future__ import annotations

import math
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
        # One (capacity, D) storage; every field is a view of some of its columns, so that a
        # minibatch is one gather (``storage[idx]``) instead of one per field.
        fields = [(("obs", k), s) for k, s in obs_shapes.items()]
        fields += [(("next_obs", k), s) for k, s in obs_shapes.items()]
        fields += [
            (("actions",), (action_dim,)),
            (("rewards",), ()),
            (("costs",), ()),
            (("terminated",), ()),
        ]
        self._layout: list[tuple[tuple[str, ...], int, int, tuple[int, ...]]] = []
        width = 0
        for name, shape in fields:
            n = math.prod(shape)
            self._layout.append((name, width, n, tuple(shape)))
            width += n
        self.storage = torch.zeros((self.capacity, width), dtype=torch.float32, device=self.device)
        views = self._views(self.storage)
        self.obs, self.next_obs = views.obs, views.next_obs
        self.actions, self.rewards, self.costs, self.terminated = (
            views.actions, views.rewards, views.costs, views.terminated)  # fmt: skip
        self.pos, self.size = 0, 0

    def _views(self, rows: torch.Tensor) -> Batch:
        """The fields of ``rows`` (``(M, D)``, storage layout) as views."""
        out: dict[str, dict[str, torch.Tensor] | torch.Tensor] = {"obs": {}, "next_obs": {}}
        for name, start, n, shape in self._layout:
            v = rows[:, start : start + n].view(rows.shape[0], *shape) if shape else rows[:, start]
            if len(name) == 2:
                out[name[0]][name[1]] = v  # type: ignore[index]
            else:
                out[name[0]] = v
        return Batch(
            out["obs"],
            out["actions"],
            out["rewards"],
            out["costs"],
            out["next_obs"],
            out["terminated"],
        )  # type: ignore[arg-type]

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
        return self._views(self.storage[idx])

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
