"""The pieces of PPO / PPO-Lag as pure functions of tensors (tests/test_ppo.py checks each
against hand-computed values).

Shapes: ``T`` rollout steps, ``N`` envs, ``B`` a minibatch, ``A`` action dimensions. Nothing here
holds state or touches an optimiser; the caller detaches what is data (old log-probabilities, old
values, advantages, returns).

The policy is NavRL's: a Beta distribution per action dimension on ``[0, 1]``, mapped affinely
onto the normalised command ``a = 2 x - 1`` in ``[-1, 1]`` (the env scales by ``v_max``); its
functions (log-density, entropy, mean, sampling) are in :mod:`safenav.nn.beta`, re-exported here.
"""

from __future__ import annotations

import torch

# The Beta policy's functions live with its network, one layer down (no upward import)
from safenav.nn.beta import (
    LOG2,
    UNIT_EPS,
    action_to_unit,
    beta_concentrations,
    beta_entropy,
    beta_log_prob,
    beta_mean_action,
    sample_beta_action,
    unit_to_action,
)


# ------------------------------------------------------------------------------- advantages
def gae(rewards: torch.Tensor, values: torch.Tensor, next_values: torch.Tensor,
        terminated: torch.Tensor, truncated: torch.Tensor, gamma: float,
        lam: float) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Generalised advantage estimation (Schulman et al. 2016) with time limits handled apart:

        delta_t = r_t + gamma (1 - term_t) V(s'_t) - V(s_t)
        A_t     = delta_t + gamma lam (1 - done_t) A_{t+1},     done_t = term_t or trunc_t
        R_t     = A_t + V(s_t)                                   (the value target)

    All arguments are ``(T, N)``. ``next_values[t]`` is the value of the *true* next state
    ``s'_t``: ``values[t + 1]`` inside an episode, the value of the final observation
    (``info["final_obs"]``) where the episode was truncated, and the value of the observation
    after the rollout at ``t = T - 1``. A termination has no future (``V(s') = 0``); a
    truncation bootstraps from ``V(s')`` but, like a termination, stops the trace: the next
    row belongs to a new episode. Returns ``(advantages, returns)``, each ``(T, N)``.
    """
    term, done = terminated.float(), (terminated | truncated).float()
    deltas = rewards + gamma * (1.0 - term) * next_values - values
    advantages = torch.zeros_like(rewards)
    running = torch.zeros_like(rewards[0])
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = deltas[t] + gamma * lam * (1.0 - done[t]) * running
        advantages[t] = running
    return advantages, advantages + values


def lagrangian_advantage(adv_reward: torch.Tensor, adv_cost: torch.Tensor,
                         lam: torch.Tensor | float) -> torch.Tensor:  # fmt: skip
    """PPO-Lag's advantage (OmniSafe): ``A = (A_R - lambda A_C) / (1 + lambda)``.

    Used in the clipped surrogate below, the actor minimises ``(L_R + lambda L_C) / (1 + lambda)``
    with ``L_R`` the reward and ``L_C`` the cost surrogate (the two coincide wherever the ratio
    is unclipped). Dividing by ``1 + lambda`` keeps the step size bounded as lambda grows.
    """
    return (adv_reward - lam * adv_cost) / (1.0 + lam)


def normalize(x: torch.Tensor, scale: bool = True, eps: float = 1e-8) -> torch.Tensor:
    """``(x - mean) / (std + eps)`` over all entries (``scale=False``: only ``x - mean``)."""
    x = x - x.mean()
    return x / (x.std(correction=0) + eps) if scale else x


# ------------------------------------------------------------------------------------ losses
def clipped_policy_loss(log_prob: torch.Tensor, old_log_prob: torch.Tensor,
                        advantages: torch.Tensor, clip: float) -> torch.Tensor:  # fmt: skip
    """PPO's clipped surrogate (Schulman et al. 2017, Eq. 7), as a loss to minimise:

        rho = exp(log pi(a|s) - log pi_old(a|s))
        L   = -E[min(rho A, clip(rho, 1 - eps, 1 + eps) A)]

    ``(B,)`` tensors; ``old_log_prob`` and ``advantages`` are data (no gradient).
    """
    ratio = torch.exp(log_prob - old_log_prob)
    surrogate = torch.min(ratio * advantages, ratio.clamp(1.0 - clip, 1.0 + clip) * advantages)
    return -surrogate.mean()


def clipped_value_loss(values: torch.Tensor, old_values: torch.Tensor, returns: torch.Tensor,
                       clip: float) -> torch.Tensor:  # fmt: skip
    """The clipped value loss of PPO implementations (OpenAI baselines, NavRL):

        V_clip = V_old + clip(V - V_old, -eps, eps)
        L      = 1/2 E[max((V - R)^2, (V_clip - R)^2)]

    ``clip = 0`` gives the plain ``1/2 E[(V - R)^2]``. On NavRL's normalised targets this equals
    its ``HuberLoss(delta=10)`` wherever ``|V - R| < 10``, i.e. everywhere in practice.
    """
    loss = (values - returns).pow(2)
    if clip > 0:
        clipped = old_values + (values - old_values).clamp(-clip, clip)
        loss = torch.max(loss, (clipped - returns).pow(2))
    return 0.5 * loss.mean()


__all__ = [
    "LOG2",
    "UNIT_EPS",
    "action_to_unit",
    "beta_concentrations",
    "beta_entropy",
    "beta_log_prob",
    "beta_mean_action",
    "clipped_policy_loss",
    "clipped_value_loss",
    "gae",
    "lagrangian_advantage",
    "normalize",
    "sample_beta_action",
    "unit_to_action",
]
