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

:class:`PIDLagrange` (beyond the paper, ``--csac.lambda-update pid``) sets lambda from the same
signal by a PID controller (Stooke, Achiam and Abbeel 2020, "Responsive Safety in Reinforcement
Learning by PID Lagrangian Methods", Algorithm 2): the gradient step above is its integral term
alone, and a Lagrangian that only integrates overshoots and oscillates around the limit; the
proportional term answers a violation at once and the derivative term a rising cost.
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


class PIDLagrange(nn.Module):
    """``lambda`` from a PID controller on the constraint violation ``e = J - d`` (Stooke et al.
    2020, Algorithm 2; OmniSafe's ``PIDLagrangian`` has the same terms), one step per
    :meth:`update`, ``J`` the mean of the signal it is given (CSAC: ``E[Q_C]`` of the batch against
    ``d_Q``, Eq. 11's signal; SAC-Lag: the episode cost against ``d``)::

        I      <- max(0, I + ki * e)                      integral (the gradient step of Eq. 11)
        P      <- ema * P + (1 - ema) * e                 proportional, smoothed
        J_s    <- ema * J_s + (1 - ema) * J               the smoothed signal (first step: J)
        lambda  = max(0, kp * P + I + kd * max(0, J_s - J_s[d_delay steps ago]))

    capped at ``max_value``. Gains are in units of the signal: lambda per unit of ``e``. The
    controller's state (``I``, the smoothed terms, the last ``d_delay`` smoothed signals) lives in
    buffers, so a checkpoint of the agent resumes it exactly. ``CSACConfig`` checks the gains."""

    def __init__(self, kp: float, ki: float, kd: float, d_delay: int, ema: float,
                 init: float = 0.0, max_value: float | None = None) -> None:  # fmt: skip
        super().__init__()
        if init < 0:
            raise ValueError(f"init={init}: the Lagrange multiplier must start >= 0")
        self.kp, self.ki, self.kd, self.ema, self.max_value = kp, ki, kd, ema, max_value
        self.register_buffer("integral", torch.tensor(float(init)))
        self.register_buffer("lam", torch.tensor(float(init)))
        self.register_buffer("p_smooth", torch.tensor(0.0))
        self.register_buffer("j_smooth", torch.tensor(0.0))
        # ring of the last d_delay smoothed signals (filled with the first); steps = updates so far
        self.register_buffer("j_history", torch.zeros(d_delay))
        self.register_buffer("steps", torch.tensor(0, dtype=torch.long))

    @property
    def value(self) -> torch.Tensor:
        """The current multiplier (a detached scalar tensor, >= 0)."""
        return self.lam.detach().clone()

    @torch.no_grad()
    def update(self, signal: torch.Tensor, d: float) -> torch.Tensor:
        """One controller step given samples of the constrained quantity ``(B,)``; returns Eq. 11's
        ``lambda * (d - J)`` at the new lambda, the quantity :class:`Lagrange` logs."""
        j = signal.detach().float().mean()
        if not torch.isfinite(j):
            raise ValueError(f"PID Lagrangian: the constraint signal is {float(j)}")
        e = j - d
        a, k = self.ema, int(self.steps)
        if k == 0:  # the smoothed terms start at the first signal, not at 0 (no false rise)
            self.p_smooth.fill_(float(e))
            self.j_smooth.fill_(float(j))
            self.j_history.fill_(float(j))
        self.integral.copy_(torch.clamp(self.integral + self.ki * e, min=0.0))
        self.p_smooth.copy_(a * self.p_smooth + (1 - a) * e)
        self.j_smooth.copy_(a * self.j_smooth + (1 - a) * j)
        slot = k % self.j_history.numel()
        oldest = self.j_history[slot].clone()  # the smoothed signal d_delay steps ago
        self.j_history[slot] = self.j_smooth
        self.steps += 1
        rise = torch.clamp(self.j_smooth - oldest, min=0.0)
        out = torch.clamp(self.kp * self.p_smooth + self.integral + self.kd * rise, min=0.0)
        self.lam.copy_(out if self.max_value is None else torch.clamp(out, max=self.max_value))
        return (self.lam * (d - j)).detach()


__all__ = ["Lagrange", "PIDLagrange", "lagrange_loss"]
