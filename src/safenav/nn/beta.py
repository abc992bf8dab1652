"""PPO's Beta policy (NavRL): its distribution as pure functions (concentrations, log-density,
entropy, mean, sampling; tests/test_ppo.py checks them against hand-computed values), the
actor-critic (the shared feature extractor, an MLP trunk, a Beta policy head and value heads) and
its deployable deterministic actor.

- ``NetConfig.shared_extractor=True`` (default, NavRL): **one** body (extractor + MLP trunk)
  feeds the policy head and the value heads and is trained by the summed PPO loss.
- ``False``: the actor and the critic each own a body (CleanRL's separate networks).

The trunk is NavRL's ``make_mlp``: ``Linear -> LeakyReLU -> LayerNorm`` per hidden layer. The
policy head outputs the raw Beta parameters (``alpha = 1 + softplus``, see
:func:`beta_concentrations`); the value head outputs one value per signal (reward, and cost for
PPO-Lag), on the normalised scale.
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from safenav.nn.config import NetConfig
from safenav.nn.networks import input_order, make_extractor

LOG2 = math.log(2.0)
UNIT_EPS = 1e-6
"""Beta samples are kept in ``[eps, 1 - eps]`` so that their log-density stays finite."""


# ------------------------------------------------------------------ the Beta policy, as functions
def beta_concentrations(raw_alpha: torch.Tensor,
                        raw_beta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """NavRL's ``BetaActor``: ``alpha = 1 + softplus(raw_alpha)``, ``beta = 1 + softplus(raw_beta)``.

    Both exceed 1, so every Beta is unimodal with a finite density on ``[0, 1]``."""
    return 1.0 + F.softplus(raw_alpha), 1.0 + F.softplus(raw_beta)


def unit_to_action(x: torch.Tensor) -> torch.Tensor:
    """``[0, 1] -> [-1, 1]``: ``a = 2 x - 1``."""
    return 2.0 * x - 1.0


def action_to_unit(action: torch.Tensor) -> torch.Tensor:
    """``[-1, 1] -> [0, 1]``: ``x = (a + 1) / 2``, kept in ``[eps, 1 - eps]``."""
    return ((action + 1.0) * 0.5).clamp(UNIT_EPS, 1.0 - UNIT_EPS)


def beta_log_prob(alpha: torch.Tensor, beta: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """Log-density of ``action`` in ``[-1, 1]^A`` under independent Betas mapped by ``a = 2x - 1``:

        log p(a) = sum_i [(alpha_i - 1) log x_i + (beta_i - 1) log(1 - x_i) - log B(alpha_i, beta_i)]
                   - A log 2,          x = (a + 1) / 2,   log B(a, b) = lgamma(a) + lgamma(b) - lgamma(a + b)

    (``- A log 2`` is the Jacobian of the affine map; it cancels in PPO's ratio.) ``(B, A)`` -> ``(B,)``.
    """
    x = action_to_unit(action)
    log_b = torch.lgamma(alpha) + torch.lgamma(beta) - torch.lgamma(alpha + beta)
    log_unit = (alpha - 1.0) * torch.log(x) + (beta - 1.0) * torch.log1p(-x) - log_b
    return log_unit.sum(-1) - action.shape[-1] * LOG2


def beta_entropy(alpha: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
    """Differential entropy of the action distribution on ``[-1, 1]^A``:

        H = sum_i [log B(a, b) - (a - 1) psi(a) - (b - 1) psi(b) + (a + b - 2) psi(a + b)] + A log 2

    with ``psi`` the digamma function. ``(B, A)`` -> ``(B,)``."""
    log_b = torch.lgamma(alpha) + torch.lgamma(beta) - torch.lgamma(alpha + beta)
    h = (log_b - (alpha - 1.0) * torch.digamma(alpha) - (beta - 1.0) * torch.digamma(beta)
         + (alpha + beta - 2.0) * torch.digamma(alpha + beta))  # fmt: skip
    return h.sum(-1) + alpha.shape[-1] * LOG2


def beta_mean_action(alpha: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
    """The deterministic action: the Beta mean mapped to ``[-1, 1]``, ``2 alpha / (alpha + beta) - 1``
    (NavRL deploys ``ExplorationType.MEAN``)."""
    return unit_to_action(alpha / (alpha + beta))


def sample_beta_action(alpha: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
    """A sample ``a = 2 x - 1``, ``x ~ Beta(alpha, beta)`` (torch's gamma-ratio sampler; uses the
    global torch RNG), kept where its log-density is finite."""
    x = torch.distributions.Beta(alpha, beta).sample().clamp(UNIT_EPS, 1.0 - UNIT_EPS)
    return unit_to_action(x)


# ------------------------------------------------------------------------------------ networks
POLICY_HEAD = "beta"
"""``meta["policy_head"]`` of PPO checkpoints: :func:`safenav.algos.policy.build_actor` dispatches
on it to :func:`build_beta_actor`."""


class Body(nn.Module):
    """Observation dict -> features: :func:`~safenav.nn.networks.make_extractor` (the SafeNav CNN
    + MLP + state, or flatten), then per hidden layer ``Linear -> LeakyReLU -> LayerNorm``
    (NavRL's), or ``Linear -> ReLU`` / ``Linear -> tanh`` (``net.trunk``: SB3's)."""

    def __init__(self, obs_shapes: dict[str, tuple[int, ...]], net: NetConfig) -> None:
        super().__init__()
        self.extractor = make_extractor(obs_shapes, net)
        layers: list[nn.Module] = []
        size = self.extractor.out_features
        for h in net.hidden:
            layers.append(nn.Linear(size, h))
            if net.trunk == "navrl":
                layers += [nn.LeakyReLU(), nn.LayerNorm(h)]
            else:
                layers.append(nn.ReLU() if net.trunk == "relu" else nn.Tanh())
            size = h
        self.trunk = nn.Sequential(*layers)
        self.out_features = size

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        x = self.extractor(obs)
        if x.dim() == 3:  # a one-member extractor returns (1, N, F)
            x = x[0]
        return self.trunk(x)


class HeadsActorCritic(nn.Module):
    """A policy head of ``head_size`` outputs and ``num_values`` value heads over one shared body
    or two separate ones: what the Beta and categorical actor-critics share (each maps the policy
    head's output to its distribution in ``forward``)."""

    def __init__(self, obs_shapes: dict[str, tuple[int, ...]], head_size: int, net: NetConfig,
                 num_values: int = 1) -> None:  # fmt: skip
        super().__init__()
        self.actor_body = Body(obs_shapes, net)
        self.critic_body = None if net.shared_extractor else Body(obs_shapes, net)
        size = self.actor_body.out_features
        self.policy_head = nn.Linear(size, head_size)
        self.value_head = nn.Linear(size, num_values)

    def heads(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """``(policy head output, normalised values (N, K))``."""
        x = self.actor_body(obs)
        y = x if self.critic_body is None else self.critic_body(obs)
        return self.policy_head(x), self.value_head(y)

    def values(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """Normalised values ``(N, K)`` only."""
        body = self.critic_body if self.critic_body is not None else self.actor_body
        return self.value_head(body(obs))

    def actor_parameters(self) -> list[nn.Parameter]:
        """Parameters the actor loss trains (with a shared body: the body too)."""
        return [*self.actor_body.parameters(), *self.policy_head.parameters()]

    def critic_parameters(self) -> list[nn.Parameter]:
        """Parameters only the value loss trains."""
        body = [] if self.critic_body is None else list(self.critic_body.parameters())
        return [*body, *self.value_head.parameters()]


class BetaActorCritic(HeadsActorCritic):
    """Beta policy (``2 A`` raw concentrations) and ``num_values`` value heads."""

    def __init__(self, obs_shapes: dict[str, tuple[int, ...]], action_dim: int, net: NetConfig,
                 num_values: int = 1) -> None:  # fmt: skip
        super().__init__(obs_shapes, 2 * action_dim, net, num_values)

    def forward(self, obs: dict[str, torch.Tensor]):
        """``(alpha, beta, values)``: concentrations ``(N, A)`` and normalised values ``(N, K)``."""
        raw, values = self.heads(obs)
        alpha, beta = beta_concentrations(*raw.chunk(2, -1))
        return alpha, beta, values


class HeadActor(nn.Module):
    """A deployable PPO actor's shared part: observation tensors (positional, in ``input_names``
    order) -> the policy head's raw output; subclasses map it to an action. Shares its modules
    with the training model; traceable (``torch.jit.trace``, ONNX export)."""

    def __init__(self, body: Body, policy_head: nn.Linear, input_names: tuple[str, ...]) -> None:
        super().__init__()
        self.body = body
        self.policy_head = policy_head
        self.input_names = tuple(input_names)

    def head(self, inputs: tuple[torch.Tensor, ...]) -> torch.Tensor:
        return self.policy_head(self.body(dict(zip(self.input_names, inputs, strict=True))))


class BetaDeterministicActor(HeadActor):
    """The deployable PPO policy: the Beta mean mapped to ``[-1, 1]^A`` (:class:`HeadActor`)."""

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        alpha, beta = beta_concentrations(*self.head(inputs).chunk(2, -1))
        return beta_mean_action(alpha, beta)


def body_from_meta(meta: dict[str, Any]) -> tuple[Body, tuple[str, ...]]:
    """An untrained actor :class:`Body` with the architecture ``meta`` describes (the policy
    metadata of a PPO checkpoint) and its input order."""
    from safenav.common.config import from_dict

    net: NetConfig = from_dict(NetConfig, meta["net"])
    shapes = {k: tuple(v) for k, v in meta["obs_shapes"].items()}
    return Body(shapes, net), input_order(shapes)


def build_beta_actor(meta: dict[str, Any]) -> BetaDeterministicActor:
    """An untrained :class:`BetaDeterministicActor` with the architecture ``meta`` describes
    (the policy metadata of a PPO checkpoint)."""
    body, names = body_from_meta(meta)
    return BetaDeterministicActor(
        body, nn.Linear(body.out_features, 2 * int(meta["action_dim"])), names
    )


__all__ = ["LOG2", "POLICY_HEAD", "UNIT_EPS", "BetaActorCritic", "BetaDeterministicActor", "Body", "HeadActor",
           "HeadsActorCritic",
           "action_to_unit", "beta_concentrations", "beta_entropy", "beta_log_prob",
           "beta_mean_action", "body_from_meta", "build_beta_actor", "sample_beta_action", "unit_to_action"]  # fmt: skip
