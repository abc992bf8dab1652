"""PPO's Gaussian policy (``--ppo.distribution gaussian``; beyond NavRL, whose PPO has the Beta
policy of :mod:`safenav.nn.beta`): its distribution as pure functions, the actor-critic and its
deployable deterministic actor. It is Stable-Baselines3's PPO policy, for the RL Zoo's tuned
entries that explore with gSDE (Pendulum-v1, MountainCarContinuous-v0):

- ``use_sde=False``: a diagonal Gaussian ``a ~ N(mu(s), sigma^2)`` with a state-independent,
  learned ``log sigma`` (one per action dimension; SB3's ``DiagGaussianDistribution``).
- ``use_sde=True``: generalized State-Dependent Exploration, gSDE (Raffin, Kober and Stulp,
  "Smooth Exploration for Robotic Reinforcement Learning", CoRL 2021; SB3's
  ``StateDependentNoiseDistribution``). The noise is a linear function of the policy's last hidden
  features ``z(s)`` (the latent): ``a = mu(s) + z(s) W``, with an exploration matrix
  ``W ~ N(0, sigma^2)`` of shape ``(F, A)``, ``sigma = exp(log_sigma)`` learned per entry
  (SB3's ``full_std=True``). One ``W`` per env, drawn at the start of each rollout and every
  ``sde_sample_freq`` steps (:meth:`GaussianActorCritic.reset_noise`), so that within that time
  the same state gives the same action: smooth, state-dependent exploration. Given ``s``, ``a``
  is Gaussian with variance ``sum_j z_j^2 sigma_jk^2`` per dimension ``k``: that is its
  log-density and entropy (:func:`sde_std`, ``+ SDE_EPS`` under the root, as SB3).
  ``z`` enters the noise as data (SB3's ``learn_features=False``): only ``log_sigma`` learns
  from the spread; ``mu`` and the body learn from the mean as usual.

Not implemented: SB3's ``use_expln`` (``exp`` is used, SB3's default) and ``full_std=False``
(one ``sigma`` per feature), neither used by the zoo's PPO entries; ``squash_output`` (SB3's PPO
does not squash: the env gets the sample clipped to ``[-1, 1]``, the log-density is of the
unclipped sample, which the rollout stores).

The body is :class:`safenav.nn.beta.Body` (extractor, then ``Linear -> LeakyReLU -> LayerNorm``
per hidden layer), so ``z`` is LayerNorm's output, not SB3's tanh layer: the same
``log_std_init`` starts with a different action spread (about ``|z| exp(log_std_init)``).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

from safenav.nn.beta import Body, HeadActor, body_from_meta
from safenav.nn.config import NetConfig

POLICY_HEAD = "gaussian"
"""``meta["policy_head"]`` of PPO checkpoints with the Gaussian policy:
:func:`safenav.algos.policy.build_actor` dispatches on it to :func:`build_gaussian_actor`."""
SDE_EPS = 1e-6
"""Added to gSDE's variance under the square root (SB3's ``epsilon``)."""
HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


# -------------------------------------------------------------- the Gaussian policy, as functions
def gaussian_log_prob(mean: torch.Tensor, std: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """Log-density of ``action`` under independent Gaussians, summed over the action dimensions:

        log p(a) = sum_i [-(a_i - mu_i)^2 / (2 sigma_i^2) - log sigma_i - log(2 pi) / 2]

    ``action`` is the unclipped sample. ``(B, A)`` -> ``(B,)``."""
    return (-((action - mean) ** 2) / (2.0 * std**2) - std.log() - HALF_LOG_2PI).sum(-1)


def gaussian_entropy(std: torch.Tensor) -> torch.Tensor:
    """Differential entropy ``sum_i [1/2 + log(2 pi)/2 + log sigma_i]``. ``(B, A)`` -> ``(B,)``."""
    return (0.5 + HALF_LOG_2PI + std.log()).sum(-1)


def sde_std(latent: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """gSDE's action standard deviation given the state (Raffin et al. 2021, Sec. 3; SB3's
    ``StateDependentNoiseDistribution.proba_distribution``):

        sigma_k(s) = sqrt(sum_j z_j(s)^2 exp(log_sigma_jk)^2 + eps)

    ``latent`` ``z`` ``(B, F)`` (pass it detached: SB3's ``learn_features=False``), ``log_std``
    ``(F, A)`` -> ``(B, A)``."""
    return torch.sqrt(torch.mm(latent**2, log_std.exp() ** 2) + SDE_EPS)


def sample_exploration_matrices(log_std: torch.Tensor, n: int) -> torch.Tensor:
    """``n`` exploration matrices ``W ~ N(0, exp(log_sigma)^2)`` entry-wise, ``(n, F, A)``
    (global torch RNG)."""
    return torch.randn(n, *log_std.shape, device=log_std.device) * log_std.exp()


def sde_noise(latent: torch.Tensor, matrices: torch.Tensor) -> torch.Tensor:
    """gSDE's action noise ``z(s)_i W_i`` of row ``i`` under its own matrix: ``latent`` ``(B, F)``,
    ``matrices`` ``(B, F, A)`` -> ``(B, A)``."""
    return torch.bmm(latent.unsqueeze(1), matrices).squeeze(1)


# ------------------------------------------------------------------------------------ networks
class GaussianActorCritic(nn.Module):
    """Gaussian policy (plain or gSDE) and ``num_values`` value heads over one shared body or two
    separate ones (as :class:`safenav.nn.beta.BetaActorCritic`). The policy head outputs the mean;
    ``log_std`` is a parameter: ``(A,)``, or ``(F, A)`` with gSDE."""

    def __init__(self, obs_shapes: dict[str, tuple[int, ...]], action_dim: int, net: NetConfig,
                 num_values: int = 1, log_std_init: float = 0.0, use_sde: bool = False) -> None:  # fmt: skip
        super().__init__()
        self.actor_body = Body(obs_shapes, net)
        self.critic_body = None if net.shared_extractor else Body(obs_shapes, net)
        size = self.actor_body.out_features
        self.policy_head = nn.Linear(size, action_dim)
        self.value_head = nn.Linear(size, num_values)
        self.use_sde = use_sde
        shape = (size, action_dim) if use_sde else (action_dim,)
        self.log_std = nn.Parameter(torch.full(shape, float(log_std_init)))
        self.exploration: torch.Tensor | None = None
        """gSDE's exploration matrices, one per env ``(N, F, A)``: drawn, not learned, and not part
        of the state dict (a resumed run draws new ones at its first rollout)."""

    def forward(self, obs: dict[str, torch.Tensor]):
        """``(mean, std, values, latent)``: mean and standard deviation ``(N, A)``, normalised
        values ``(N, K)`` and the detached last hidden features ``(N, F)`` (gSDE's latent)."""
        x = self.actor_body(obs)
        mean = self.policy_head(x)
        latent = x.detach()  # SB3's learn_features=False: the noise does not train the body
        std = sde_std(latent, self.log_std) if self.use_sde else self.log_std.exp().expand_as(mean)
        y = x if self.critic_body is None else self.critic_body(obs)
        return mean, std, self.value_head(y), latent

    def reset_noise(self, n: int) -> None:
        """Draw gSDE's ``n`` exploration matrices (one per env)."""
        with torch.no_grad():
            self.exploration = sample_exploration_matrices(self.log_std, n)

    def sample(self, mean: torch.Tensor, std: torch.Tensor, latent: torch.Tensor) -> torch.Tensor:
        """An unclipped action ``(N, A)``: ``mean + std * eps`` (plain), or ``mean + z W_i`` with
        env ``i``'s exploration matrix (gSDE; drawn here if there are none for ``N`` envs)."""
        if not self.use_sde:
            return mean + std * torch.randn_like(mean)
        if self.exploration is None or self.exploration.shape[0] != mean.shape[0]:
            self.reset_noise(mean.shape[0])
        return mean + sde_noise(latent, self.exploration)

    def values(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """Normalised values ``(N, K)`` only."""
        body = self.critic_body if self.critic_body is not None else self.actor_body
        return self.value_head(body(obs))

    def actor_parameters(self) -> list[nn.Parameter]:
        """Parameters the actor loss trains (with a shared body: the body too), ``log_std``
        included."""
        return [*self.actor_body.parameters(), *self.policy_head.parameters(), self.log_std]

    def critic_parameters(self) -> list[nn.Parameter]:
        """Parameters only the value loss trains."""
        body = [] if self.critic_body is None else list(self.critic_body.parameters())
        return [*body, *self.value_head.parameters()]


class GaussianDeterministicActor(HeadActor):
    """The deployable Gaussian policy: the mean clipped to ``[-1, 1]^A`` (SB3's
    ``predict(deterministic=True)``; :class:`~safenav.nn.beta.HeadActor`)."""

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.head(inputs).clamp(-1.0, 1.0)


def build_gaussian_actor(meta: dict[str, Any]) -> GaussianDeterministicActor:
    """An untrained :class:`GaussianDeterministicActor` with the architecture ``meta`` describes
    (the policy metadata of a PPO checkpoint)."""
    body, names = body_from_meta(meta)
    return GaussianDeterministicActor(
        body, nn.Linear(body.out_features, int(meta["action_dim"])), names
    )


__all__ = ["POLICY_HEAD", "SDE_EPS", "GaussianActorCritic", "GaussianDeterministicActor",
           "build_gaussian_actor", "gaussian_entropy", "gaussian_log_prob",
           "sample_exploration_matrices", "sde_noise", "sde_std"]  # fmt: skip
