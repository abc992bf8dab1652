"""n-step cost returns for the cost critics (beyond the paper: ``--csac.cost-n-step N``).

SafeNav's cost is one terminal event (SPEC: 1 at the collision step, which ends the episode). A
one-step target (Eq. 6) moves that event back one state per target refresh, and the critics
measured on the paper preset predict 3-8x less cost than the policy pays (docs/csac.md, "Three
runs"). The n-step target hands the collision to the ``n`` states before it at once:

    y_C^(n) = sum_{k<m} gamma^k c_{t+k} + gamma^m (1 - terminated_{t+m-1}) Q_C'(s_{t+m}, a'),

with ``m = n``, or fewer when the episode ends (terminated or truncated) at step ``t+m-1``; a
truncation bootstraps from the true final observation, as the one-step target does.

:class:`NStepWindow` holds the last ``n`` vector steps of every env and, once full, releases the
oldest step's transition (a :class:`~safenav.common.buffer.Batch`) with its n-step fields
``(costs_n, next_obs_n, discount_n)`` set, the three inputs of that target, so the replay buffer
stores them beside the one-step fields (the reward target,
Eq. 5, stays one-step). The sum uses the costs the *behaviour* policy paid: with older policies
that collided more, it errs towards more cost, the safe side.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import torch

from safenav.common.buffer import Batch


class WindowStep(NamedTuple):
    transition: Batch
    """One vector step's one-step fields (its n-step fields None until it leaves the window)."""
    done: torch.Tensor
    """Terminated or truncated: the episode ends after this step."""
    valid: torch.Tensor
    """``ReplayBuffer.add``'s mask of real transitions."""


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

    def push(self, transition: Batch, truncated: torch.Tensor,
             valid: torch.Tensor) -> tuple[Batch, torch.Tensor] | None:  # fmt: skip
        """Add one vector step (``transition.next_obs`` the true ``s'``); once ``n`` are held,
        release the oldest: its transition with the n-step fields set, and its ``valid`` mask."""
        t = transition
        terminated = t.terminated.bool()
        held = Batch({k: v.clone() for k, v in t.obs.items()}, t.actions.clone(), t.rewards.clone(),
                     t.costs.clone(), {k: v.clone() for k, v in t.next_obs.items()}, terminated.clone())  # fmt: skip
        self.steps.append(WindowStep(held, terminated | truncated.bool(), valid.bool().clone()))
        return self.pop() if len(self.steps) >= self.n else None

    def cut(self) -> None:
        """Every env's episode ends after the last pushed step (the trainer reset the envs, e.g. to
        new maps): later steps must not count towards earlier ones. Treated as a truncation."""
        if self.steps:
            last = self.steps[-1]
            self.steps[-1] = last._replace(done=torch.ones_like(last.done))

    def pop(self) -> tuple[Batch, torch.Tensor]:
        """The oldest held step with its n-step cost return over the steps held after it."""
        steps = [s.transition for s in self.steps]
        done = torch.stack([s.done for s in self.steps])  # (m, N)
        first, valid = steps[0], self.steps.popleft().valid
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
        return first._replace(costs_n=costs_n, next_obs_n=next_obs_n, discount_n=discount_n), valid

    def state_dict(self) -> dict:
        return {"n": self.n, "steps": [(tuple(s.transition), s.done, s.valid) for s in self.steps]}

    def load_state_dict(self, state: dict) -> None:
        if int(state["n"]) != self.n:
            raise ValueError(f"the saved n-step window has n={state['n']}, this run n={self.n}")
        self.steps = deque(WindowStep(Batch(*t), done, valid) for t, done, valid in state["steps"])


__all__ = ["NStepWindow", "WindowStep"]
