"""PPO's categorical policy, for a ``Discrete(n)`` action space (CartPole-v1, Acrobot-v1,
LunarLander-v3, ...; beyond NavRL, whose quadrotor acts continuously): its distribution as pure
functions, the actor-critic and its deployable deterministic actor. It is the policy of
Stable-Baselines3's and CleanRL's PPO on discrete tasks (``CategoricalDistribution``,
``ppo.py``): the policy head gives one logit per action, ``pi(a|s) = softmax(logits)_a``.

An action travels through safenav as its index ``0 .. n-1`` in a float tensor of shape
``(N, 1)`` (the rollout's action storage is float for every policy);
:class:`safenav.envs.vector.TorchVecEnv` hands the env ``index + space.start``. The
deterministic action is the most probable one (``argmax``, SB3's ``predict(deterministic=True)``).

The body is :class:`safenav.nn.beta.Body`, as for the Beta and Gaussian policies.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from safenav.nn.beta import HeadActor, HeadsActorCritic, body_from_meta
from safenav.nn.config import NetConfig

POLICY_HEAD = "categorical"
"""``meta["policy_head"]`` of a PPO checkpoint with discrete actions:
:func:`safenav.algos.policy.build_actor` dispatches on it to :func:`build_categorical_actor`."""


# ------------------------------------------------------------ the categorical policy, as functions
def categorical_log_prob(logits: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """``log pi(a|s) = log_softmax(logits)_a`` of the action indices ``action`` ``(B, 1)`` (float);
    ``(B, n)`` logits -> ``(B,)``."""
    return torch.log_softmax(logits, -1).gather(-1, action.long()).squeeze(-1)


def categorical_entropy(logits: torch.Tensor) -> torch.Tensor:
    """``H = -sum_a pi(a|s) log pi(a|s)``, ``(B, n)`` -> ``(B,)``."""
    log_p = torch.log_softmax(logits, -1)
    return -(log_p.exp() * log_p).sum(-1)


def sample_categorical(logits: torch.Tensor) -> torch.Tensor:
    """An action index ``a ~ pi(.|s)`` per row, as a float ``(B, 1)`` (the global torch RNG)."""
    return torch.multinomial(torch.softmax(logits, -1), 1).float()


def greedy_action(logits: torch.Tensor) -> torch.Tensor:
    """The deterministic action: the index of the largest logit, as a float ``(B, 1)``."""
    return logits.argmax(-1, keepdim=True).float()


# ------------------------------------------------------------------------------------ networks
class CategoricalActorCritic(HeadsActorCritic):
    """Categorical policy (``num_actions`` logits) and ``num_values`` value heads over one shared
    body or two separate ones (``net.shared_extractor``), as
    :class:`~safenav.nn.beta.BetaActorCritic`."""

    def __init__(self, obs_shapes: dict[str, tuple[int, ...]], num_actions: int, net: NetConfig,
                 num_values: int = 1) -> None:  # fmt: skip
        super().__init__(obs_shapes, num_actions, net, num_values)

    def forward(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """``(logits, values)``: ``(N, n)`` and normalised values ``(N, K)``."""
        return self.heads(obs)


class CategoricalDeterministicActor(HeadActor):
    """The deployable policy of a discrete task: the most probable action's index, a float
    ``(B, 1)`` (:class:`~safenav.nn.beta.HeadActor`)."""

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return greedy_action(self.head(inputs))


def build_categorical_actor(meta: dict[str, Any]) -> CategoricalDeterministicActor:
    """An untrained :class:`CategoricalDeterministicActor` with the architecture ``meta``
    describes (the policy metadata of a PPO checkpoint with ``num_actions``)."""
    body, names = body_from_meta(meta)
    return CategoricalDeterministicActor(
        body, nn.Linear(body.out_features, int(meta["num_actions"])), names
    )


__all__ = ["POLICY_HEAD", "CategoricalActorCritic", "CategoricalDeterministicActor",
           "build_categorical_actor", "categorical_entropy", "categorical_log_prob",
           "greedy_action", "sample_categorical"]  # fmt: skip
