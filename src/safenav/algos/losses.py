"""The losses of Constrained SAC (paper III-B, Eqs. 5-11) as pure functions of tensors.

No module, optimiser or global state is touched here: each function maps tensors to a tensor, so
each is unit-tested against a hand-computed value (tests/test_losses.py). Shapes: ``B`` is the
batch; critic outputs are ``(E, B)`` with ``E`` the number of critics of one kind (2 in the paper).
The caller detaches what must not be differentiated (targets; ``alpha`` and ``lambda`` in the
actor loss; ``log_prob`` in the temperature loss; ``Q_C`` in the multiplier loss, Eq. 11, which is
:func:`safenav.common.lagrange.lagrange_loss`).
"""

from __future__ import annotations

import torch

# Eq. 11 lives with the multiplier it trains, one layer down (no upward import); one of the losses
from safenav.common.lagrange import lagrange_loss


def reward_target(reward: torch.Tensor, terminated: torch.Tensor, next_q: torch.Tensor,
                  next_log_prob: torch.Tensor, alpha: torch.Tensor | float, gamma: float) -> torch.Tensor:  # fmt: skip
    """Eq. 5: ``y_R = r + gamma (1 - terminated) (min_j Q_R_j(s', a') - alpha log pi(a'|s'))``.

    ``next_q`` ``(E, B)``: the *target* reward critics at ``(s', a')``, ``a' ~ pi(.|s')``. The
    minimum over critics is clipped double-Q (it counters over-estimation). ``terminated`` masks
    the bootstrap: a true terminal state has no future; a time-limit truncation is *not*
    terminated and bootstraps from the true final observation ``s'``.
    """
    soft_value = next_q.min(0).values - alpha * next_log_prob
    return reward + gamma * (1.0 - terminated.float()) * soft_value


def cost_target(cost: torch.Tensor, terminated: torch.Tensor, next_q: torch.Tensor, gamma: float,
                reduce: str = "mean") -> torch.Tensor:  # fmt: skip
    """Eq. 6: ``y_C = c + gamma (1 - terminated) (1/2 sum_j Q_C_j(s', a'))``.

    The **mean** of the target cost critics (paper: under-estimating cost is the dangerous error;
    the mean is less biased low than the minimum). ``reduce="min"`` / ``"max"`` are the ablations.
    No entropy term: the cost value is a plain discounted sum of costs.
    """
    return cost + gamma * (1.0 - terminated.float()) * _reduce_critics(next_q, reduce)


def n_step_cost_target(cost_n: torch.Tensor, discount_n: torch.Tensor, next_q: torch.Tensor,
                       reduce: str = "mean") -> torch.Tensor:  # fmt: skip
    """Eq. 6 over ``m <= n`` steps (beyond the paper, :mod:`safenav.common.nstep`):
    ``y_C = sum_{k<m} gamma^k c_{t+k} + gamma^m (1 - terminated) (1/2 sum_j Q_C_j(s_{t+m}, a'))``.

    ``cost_n`` is the discounted cost sum, ``discount_n`` ``gamma^m (1 - terminated)`` (0 after a
    collision), ``next_q`` ``(E, B)`` the target cost critics at ``(s_{t+m}, a' ~ pi)``. With
    ``m = 1`` it is :func:`cost_target`.
    """
    return cost_n + discount_n * _reduce_critics(next_q, reduce)


def _reduce_critics(q: torch.Tensor, reduce: str) -> torch.Tensor:
    """The ``(E, B)`` critics' mean (Eq. 6), or min / max (ablations), over ``E``."""
    if reduce == "mean":
        return q.mean(0)
    if reduce == "min":
        return q.min(0).values
    if reduce == "max":
        return q.max(0).values
    raise ValueError(f"reduce={reduce!r}: choose mean, min or max")


def critic_loss(q: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Eqs. 7-8: mean squared Bellman error, summed over the critics:
    ``sum_j E_B[(Q_j(s, a) - y)^2]``. ``q`` ``(E, B)``, ``target`` ``(B,)`` (no gradient)."""
    return (q - target.detach()).pow(2).mean(-1).sum()


def actor_loss(log_prob: torch.Tensor, q_reward: torch.Tensor, alpha: torch.Tensor | float,
               q_cost: torch.Tensor | None = None, lam: torch.Tensor | float = 0.0) -> torch.Tensor:  # fmt: skip
    """Eq. 9: ``E[alpha log pi(a|s) - min_j Q_R_j(s, a) + lambda (1/2 sum_j Q_C_j(s, a))]``,
    ``a ~ pi(.|s)`` reparameterised. ``q_cost=None`` is plain SAC (no cost term).

    The reward side takes the minimum, the cost side the mean (the asymmetric double critic).
    """
    loss = alpha * log_prob - q_reward.min(0).values
    if q_cost is not None:
        loss = loss + lam * q_cost.mean(0)
    return loss.mean()


def alpha_loss(
    log_alpha: torch.Tensor, log_prob: torch.Tensor, target_entropy: float
) -> torch.Tensor:
    """Eq. 10: ``E[-alpha (log pi(a|s) + H_target)]`` with ``alpha = exp(log_alpha)``.

    Its gradient raises alpha while the policy's entropy ``-E[log pi]`` is below ``H_target``
    (``-|A|`` by default) and lowers it above. ``log_prob`` must be detached.
    """
    return -(log_alpha.exp() * (log_prob.detach() + target_entropy)).mean()


__all__ = [
    "actor_loss",
    "alpha_loss",
    "cost_target",
    "critic_loss",
    "lagrange_loss",
    "n_step_cost_target",
    "reward_target",
]
