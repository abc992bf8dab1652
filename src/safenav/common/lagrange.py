"""The Lagrange multiplier ``lambda >= 0`` of the cost constraint (paper Eqs. 4 and 11).

The rule, one step per gradient update, with ``Q_C`` the mean of the cost critics at
``(s, a ~ pi(.|s))`` over the batch and ``d`` the threshold on the same (discounted) scale:

    L(lambda)  = lambda * (d - E[Q_C])                     (Eq. 11)
    lambda    <- max(0, lambda - lr * Adam(dL/dlambda)),   dL/dlambda = d - E[Q_C]

so lambda **rises while E[Q_C] > d** (the constraint is violated), **falls while E[Q_C] < d**, and
the projection ``max(0, .)`` keeps it a valid multiplier: exactly 0 when the constraint has been
slack for long (the policy is then plain SAC). Adam (paper IV) runs with ``beta1 = 0``: without
momentum, lambda turns the moment the sign of ``E[Q_C] - d`` turns (momentum would keep raising it
after the constraint is met, the overshoot Lagrangian methods are known for), and the step is
about ``lr`` scaled by the violation relative to its running RMS. The caller passes the quantity constrained (``E[Q_C]``); the
multiplier never reads it back from a logger.
"""

from __future__ import annotations

import torch
from torch import nn


def lagrange_loss(lam: torch.Tensor, q_cost_mean: torch.Tensor, d: float) -> torch.Tensor:
    """Eq. 11: ``E[lambda (d - 1/2 sum_j Q_C_j(s, a))]``, ``a ~ pi(.|s)``.

    ``d(loss)/d(lambda) = d - E[Q_C]``: gradient *descent* raises lambda while the expected cost
    ``E[Q_C]`` exceeds the threshold ``d`` and lowers it below. ``q_cost_mean`` ``(B,)`` is the
    mean over the cost critics, detached; ``d`` is on the scale of ``Q_C`` (a discounted sum, see
    :func:`safenav.common.curriculum.episode_cost_to_q_scale`). Keeping ``lambda >= 0`` is the
    caller's projection (:class:`Lagrange`).
    """
    return (lam * (d - q_cost_mean.detach())).mean()


class Lagrange(nn.Module):
    """``lambda`` as a projected Adam parameter; ``max_value`` optionally caps it."""

    def __init__(self, init: float = 0.0, lr: float = 1e-5, max_value: float | None = None) -> None:
        super().__init__()
        if init < 0:
            raise ValueError(f"init={init}: the Lagrange multiplier must start >= 0")
        self.raw = nn.Parameter(torch.tensor(float(init)))
        self.max_value = max_value
        # beta1 = 0: no momentum, so lambda moves with the *current* sign of the violation
        self.optimizer = torch.optim.Adam([self.raw], lr=lr, betas=(0.0, 0.999))

    @property
    def value(self) -> torch.Tensor:
        """The current multiplier (a detached scalar tensor, >= 0)."""
        return self.raw.detach()

    def update(self, q_cost_mean: torch.Tensor, d: float) -> torch.Tensor:
        """One step of Eq. 11 given ``E[Q_C]`` samples ``(B,)``; returns the (detached) loss."""
        loss = lagrange_loss(self.raw, q_cost_mean, d)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        with torch.no_grad():
            self.raw.clamp_(min=0.0, max=self.max_value)
        return loss.detach()


__all__ = ["Lagrange", "lagrange_loss"]
