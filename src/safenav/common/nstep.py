"""n-step cost returns for the cost critics (beyond the paper: ``--csac.cost-n-step N``).

SafeNav's cost is one terminal event (SPEC: 1 at the collision step, which ends the episode). A
one-step target (Eq. 6) moves that event back one state per target refresh, and the critics
measured on the paper preset predict 3-8x less cost than the policy pays (docs/csac.md, "Three
runs"). The n-step target hands the collision to the ``n`` states before it at once:

    y_C^(n) = sum_{k<m} gamma^k c_{t+k} + gamma^m (1 - terminated_{t+m-1}) Q_C'(s_{t+m}, a'),

with ``m = n``, or fewer when the episode ends (terminated or truncated) at step ``t+m-1``; a
truncation bootstraps from the true final observation, as the one-step target does.

:class:`NStepWindow` holds the last ``n`` vector steps of every env and, once full, releases the
oldest step's transition together with ``(cost_n, next_obs_n, discount_n)``, the three inputs of
that target, so the replay buffer stores them beside the one-step fields (the reward target,
Eq. 5, stays one-step). The sum uses the costs the *behaviour* policy paid: with older policies
that collided more, it errs towards more cost, the safe side.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import torch


class WindowStep(NamedTuple):
    obs: dict[str, torch.Tensor]
    actions: torch.Tensor
    rewards: torch.Tensor
    costs: torch.Tensor
    next_obs: dict[str, torch.Tensor]
    terminated: torch.Tensor
    done: torch.Tensor
    valid: torch.Tensor


class NStepTransition(NamedTuple):
    """One vector step's transitions (the arguments of ``ReplayBuffer.add``) plus the n-step
    cost target's inputs."""

    obs: dict[str, torch.Tensor]
    actions: torch.Tensor
    rewards: torch.Tensor
    costs: torch.Tensor
    next_obs: dict[str, torch.Tensor]
    terminated: torch.Tensor
    valid: torch.Tensor
    costs_n: torch.Tensor
    next_obs_n: dict[str, torch.Tensor]
    discount_n: torch.Tensor


class NStepWindow:
    """The last ``n`` vector steps of ``N`` envs; :meth:`push` returns the step that left the window
    with its n-step cost return (``None`` while the window fills)."""

    def __init__(self, n: int, gamma: float) -> None:
        if n < 1:
            raise ValueError(f"n={n} must be >= 1")
        self.n, self.gamma = int(n), float(gamma)
        self.steps: deque[WindowStep] = deque()

    def __len__(self) -> int:
        return len(self.steps)

    def push(self, obs: dict[str, torch.Tensor], actions: torch.Tensor, rewards: torch.Tensor,
             costs: torch.Tensor, next_obs: dict[str, torch.Tensor], terminated: torch.Tensor,
             truncated: torch.Tensor, valid: torch.Tensor) -> NStepTransition | None:  # fmt: skip
        """Add one vector step (``next_obs`` the true ``s'``); release the oldest once ``n`` are held."""
        terminated, truncated, valid = terminated.bool(), truncated.bool(), valid.bool()
        self.steps.append(WindowStep({k: v.clone() for k, v in obs.items()}, actions.clone(),
                                     rewards.clone(), costs.clone(),
                                     {k: v.clone() for k, v in next_obs.items()},
                                     terminated.clone(), (terminated | truncated).clone(), valid.clone()))  # fmt: skip
        return self.pop() if len(self.steps) >= self.n else None

    def cut(self) -> None:
        """Every env's episode ends after the last pushed step (the trainer reset the envs, e.g. to
        new maps): later steps must not count towards earlier ones. Treated as a truncation."""
        if self.steps:
            last = self.steps[-1]
            self.steps[-1] = last._replace(done=torch.ones_like(last.done))

    def pop(self) -> NStepTransition:
        """The oldest held step with its n-step cost return over the steps held after it."""
        steps = list(self.steps)
        first = self.steps.popleft()
        done = torch.stack([s.done for s in steps])  # (m, N)
        costs = torch.stack([s.costs.float() for s in steps])
        m, n_envs = done.shape
        # step j still belongs to the first step's episode iff no episode end before j
        ends_before = done.int().cumsum(0) - done.int()
        alive = (ends_before == 0).float()
        powers = self.gamma ** torch.arange(m, dtype=torch.float32, device=costs.device)
        costs_n = (powers[:, None] * alive * costs).sum(0)
        # the bootstrap step: the episode's end within the window, else the last held step
        last = torch.where(
            done.any(0), done.int().argmax(0), torch.full_like(done[0], m - 1, dtype=torch.long)
        )
        rows = torch.arange(n_envs, device=last.device)
        terminated = torch.stack([s.terminated for s in steps])[last, rows]
        discount_n = (self.gamma ** (last.float() + 1.0)) * (~terminated).float()
        next_obs_n = {
            k: torch.stack([s.next_obs[k] for s in steps])[last, rows] for k in first.next_obs
        }
        return NStepTransition(first.obs, first.actions, first.rewards, first.costs, first.next_obs,
                               first.terminated, first.valid, costs_n, next_obs_n, discount_n)  # fmt: skip

    def state_dict(self) -> dict:
        return {"n": self.n, "steps": [tuple(s) for s in self.steps]}

    def load_state_dict(self, state: dict) -> None:
        if int(state["n"]) != self.n:
            raise ValueError(f"the saved n-step window has n={state['n']}, this run n={self.n}")
        self.steps = deque(WindowStep(*s) for s in state["steps"])


__all__ = ["NStepTransition", "NStepWindow"]
