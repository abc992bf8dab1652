"""Uniform experience replay for off-policy algorithms, stored on the training device.

A transition is ``(s, a, r, c, s', terminated)``. ``s'`` is the *true* next observation: for an
env that just finished, the last observation of its episode (the vector env's ``final_obs``), not
the first of the next one. ``terminated`` alone masks bootstrapping; a time-limit truncation is
stored as not terminated, so its target bootstraps from ``s'`` (tests/test_csac.py).

With ``n_step=True`` each row also keeps the inputs of the n-step cost target
(:mod:`safenav.common.nstep`): ``costs_n``, ``next_obs_n`` (``s_{t+m}``) and ``discount_n``
(``gamma^m (1 - terminated)``).
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
    costs_n: torch.Tensor | None = None
    next_obs_n: dict[str, torch.Tensor] | None = None
    discount_n: torch.Tensor | None = None


class ReplayBuffer:
    """A ring buffer of ``capacity`` transitions; observations are dicts of float32 tensors."""

    def __init__(self, capacity: int, obs_shapes: dict[str, tuple[int, ...]], action_dim: int,
                 device: str | torch.device = "cpu", n_step: bool = False) -> None:  # fmt: skip
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
        if n_step:
            fields += [(("next_obs_n", k), s) for k, s in obs_shapes.items()]
            fields += [(("costs_n",), ()), (("discount_n",), ())]
        self.n_step = n_step
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
        self.costs_n, self.next_obs_n, self.discount_n = (
            views.costs_n, views.next_obs_n, views.discount_n)  # fmt: skip
        self.pos, self.size = 0, 0

    def _views(self, rows: torch.Tensor) -> Batch:
        """The fields of ``rows`` (``(M, D)``, storage layout) as views."""
        out: dict[str, dict[str, torch.Tensor] | torch.Tensor | None] = {
            "obs": {}, "next_obs": {}, "next_obs_n": {} if self.n_step else None,
            "costs_n": None, "discount_n": None}  # fmt: skip
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
            out["costs_n"],
            out["next_obs_n"],
            out["discount_n"],
        )  # type: ignore[arg-type]

    def __len__(self) -> int:
        return self.size

    def add(self, obs: dict[str, torch.Tensor], actions: torch.Tensor, rewards: torch.Tensor,
            costs: torch.Tensor, next_obs: dict[str, torch.Tensor], terminated: torch.Tensor,
            valid: torch.Tensor | None = None, costs_n: torch.Tensor | None = None,
            next_obs_n: dict[str, torch.Tensor] | None = None,
            discount_n: torch.Tensor | None = None) -> None:  # fmt: skip
        """Store a batch of ``N`` transitions (rows where ``valid`` is False are skipped); an
        ``n_step`` buffer also takes the n-step cost target's inputs."""
        if self.n_step and (costs_n is None or next_obs_n is None or discount_n is None):
            raise ValueError("an n_step buffer needs costs_n, next_obs_n and discount_n")
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
            if self.n_step:
                next_obs_n = {k: v[keep] for k, v in next_obs_n.items()}
                costs_n, discount_n = costs_n[keep], discount_n[keep]
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
        if self.n_step:
            for k in self.next_obs_n:
                self.next_obs_n[k][idx] = next_obs_n[k].to(self.device, torch.float32)
            self.costs_n[idx] = costs_n.to(self.device, torch.float32)
            self.discount_n[idx] = discount_n.to(self.device, torch.float32)
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
                "costs": self.costs[:n].cpu(), "terminated": self.terminated[:n].cpu()} | (
                    {"next_obs_n": {k: v[:n].cpu() for k, v in self.next_obs_n.items()},
                     "costs_n": self.costs_n[:n].cpu(), "discount_n": self.discount_n[:n].cpu()}
                    if self.n_step else {})  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        if self.n_step and "costs_n" not in state:
            raise ValueError(
                "the saved replay buffer has no n-step cost fields (saved without "
                "--csac.cost-n-step); resume without --save-buffer's buffer"
            )
        n = min(int(state["size"]), self.capacity)
        for k in self.obs:
            self.obs[k][:n] = state["obs"][k][:n].to(self.device)
            self.next_obs[k][:n] = state["next_obs"][k][:n].to(self.device)
        for name in ("actions", "rewards", "costs", "terminated"):
            getattr(self, name)[:n] = state[name][:n].to(self.device)
        if self.n_step:
            for k in self.next_obs_n:
                self.next_obs_n[k][:n] = state["next_obs_n"][k][:n].to(self.device)
            self.costs_n[:n] = state["costs_n"][:n].to(self.device)
            self.discount_n[:n] = state["discount_n"][:n].to(self.device)
        self.size, self.pos = n, int(state["pos"]) % self.capacity


def cat_batches(a: Batch, b: Batch) -> Batch:
    """The rows of ``a`` then those of ``b`` (a minibatch drawn from two buffers)."""

    def cat(x, y):
        if x is None:
            return None
        if isinstance(x, dict):
            return {k: torch.cat([x[k], y[k]]) for k in x}
        return torch.cat([x, y])

    return Batch(*(cat(x, y) for x, y in zip(a, b, strict=True)))


__all__ = ["Batch", "ReplayBuffer", "cat_batches"]
