"""PPO / PPO-Lag hyperparameters (torch-free, so that the CLI can build its parser without torch).

Defaults marked (NavRL) are NavRL's ``cfg/ppo.yaml`` and ``scripts/ppo.py``; (OmniSafe) are
OmniSafe's PPO-Lag; (SB3) Stable-Baselines3's PPO, for the Gaussian policy and gSDE that go beyond
NavRL; docs/algorithms.md gives the source of every value and what was measured here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from safenav.common.curriculum import ConstraintCurriculumConfig
from safenav.nn.config import NetConfig


@dataclass(frozen=True)
class PPOConfig:
    """PPO as NavRL trains it (Beta policy, GAE, clipped actor and value losses, value
    normalisation); with ``constrained=True`` PPO-Lag (cost value head, Lagrange multiplier).
    Beyond NavRL: ``distribution="gaussian"`` (SB3's policy), optionally with gSDE."""

    constrained: bool = False
    """Cost value head, cost GAE and a Lagrange multiplier (PPO-Lag, ``--algo ppo_lag``)."""
    gamma: float = 0.99
    """Discount of reward and cost (NavRL)."""
    gae_lambda: float = 0.95
    """GAE lambda of reward and cost advantages (NavRL)."""
    rollout_steps: int = 32
    """Vector steps per rollout; a rollout holds ``rollout_steps * num_envs`` transitions (NavRL's
    ``training_frame_num``)."""
    epochs: int = 4
    """Passes over each rollout (NavRL's ``training_epoch_num``)."""
    num_minibatches: int = 16
    """Minibatches per pass (NavRL)."""
    clip: float = 0.1
    """Clip range of the probability ratio in the actor loss (NavRL's ``actor.clip_ratio``)."""
    value_clip: float = 0.1
    """Clip range of the value change in the value loss, on the normalised scale (NavRL's
    ``critic.clip_ratio``); 0 disables value clipping."""
    lr: float = 5e-4
    """Adam learning rate of actor, critic and feature extractor (NavRL: 5e-4 for all three)."""
    anneal_lr: bool = False
    """Decay ``lr`` linearly to 0 over the run's ``--total-steps``, set before each rollout's
    update to ``lr (1 - steps before this rollout / total steps)`` (CleanRL's ``anneal_lr``;
    beyond NavRL, whose rate is constant). ``--resume`` with a larger ``--total-steps`` stretches
    the schedule: the rate jumps back up to the new fraction left."""
    entropy_coef: float = 1e-3
    """Weight of the entropy bonus (NavRL's ``entropy_loss_coefficient``)."""
    max_grad_norm: float = 5.0
    """Gradient-norm clip, applied to the actor and to the critic parameters separately (NavRL)."""
    value_norm: bool = True
    """Critics predict returns normalised by a running mean/std of the returns (NavRL's ValueNorm)."""
    value_norm_beta: float = 0.995
    """EMA factor of the running return statistics, per rollout (NavRL's ValueNorm default)."""
    normalize_advantages: bool = True
    """Standardise reward advantages over the rollout (NavRL); cost advantages are only centred
    (OmniSafe), so that lambda trades them on their own scale."""
    distribution: Literal["beta", "gaussian"] = "beta"
    """The policy's action distribution: ``beta`` (NavRL: a Beta per action dimension mapped onto
    ``[-1, 1]``) or ``gaussian`` (beyond NavRL: SB3's PPO policy, a diagonal Gaussian whose
    samples the env gets clipped to ``[-1, 1]``; ``safenav.nn.gaussian``). Continuous actions
    only: on a ``Discrete(n)`` action space the policy is categorical (``safenav.nn.categorical``)."""
    use_sde: bool = False
    """gaussian only: explore with generalized State-Dependent Exploration (gSDE; Raffin et al.,
    "Smooth Exploration for Robotic Reinforcement Learning", CoRL 2021; beyond NavRL): noise
    linear in the policy's last hidden features, ``a = mu(s) + z(s) W`` with one exploration matrix
    ``W`` per env held for ``sde-sample-freq`` steps (SB3's ``use_sde``). False: a
    state-independent std (SB3)."""
    sde_sample_freq: int = -1
    """gSDE: draw new exploration matrices every this many vector steps of a rollout as well as at
    its start; <= 0 (-1): only at the start of each rollout (SB3's ``sde_sample_freq``)."""
    log_std_init: float = 0.0
    """gaussian only: initial log standard deviation of the actions (with use-sde: of the
    exploration matrix entries) (SB3's ``log_std_init``)."""
    target_kl: float | None = None
    """Stop a rollout's epochs early once the approximate KL exceeds this; None = never (NavRL)."""
    lambda_lr: float = 0.035
    """Adam learning rate of lambda, one step per rollout (OmniSafe PPO-Lag)."""
    init_lambda: float = 0.001
    """Lagrange multiplier at the start (OmniSafe)."""
    lambda_max: float | None = None
    """Optional cap on lambda; None = unbounded (OmniSafe)."""
    net: NetConfig = field(default_factory=NetConfig)
    """Network sizes; ``shared_extractor`` True is NavRL's actor-critic (one extractor and MLP
    trunk feeding the policy and value heads, trained by the summed loss), False gives the actor
    and the critic each their own."""
    curriculum: ConstraintCurriculumConfig = field(default_factory=ConstraintCurriculumConfig)
    """Schedule of the episode-cost limit ``d`` (PPO-Lag): the same constraint curriculum as
    CSAC by default; ``--ppo.curriculum.no-enabled`` fixes ``d = d_min`` (OmniSafe)."""

    def __post_init__(self) -> None:
        if not 0 < self.gamma <= 1 or not 0 <= self.gae_lambda <= 1:
            raise ValueError(f"gamma={self.gamma} must lie in (0, 1], gae-lambda in [0, 1]")
        if self.rollout_steps < 1 or self.epochs < 1 or self.num_minibatches < 1:
            raise ValueError("rollout-steps, epochs and num-minibatches must be >= 1")
        if self.clip <= 0 or self.value_clip < 0 or self.lr <= 0 or self.max_grad_norm <= 0:
            raise ValueError("clip, lr and max-grad-norm must be > 0 and value-clip >= 0")
        if not (math.isfinite(self.lr) and math.isfinite(self.lambda_lr)):
            raise ValueError(f"lr={self.lr} and lambda-lr={self.lambda_lr} must be finite")
        if not 0 < self.value_norm_beta < 1:
            raise ValueError(f"value-norm-beta={self.value_norm_beta} must lie in (0, 1)")
        if self.init_lambda < 0 or self.lambda_lr <= 0:
            raise ValueError("init-lambda must be >= 0 and lambda-lr > 0")
        if self.epochs > 1000:
            raise ValueError(f"epochs={self.epochs} must be <= 1000")
        if self.entropy_coef < 0:
            raise ValueError(f"entropy-coef={self.entropy_coef} must be >= 0")
        if self.target_kl is not None and self.target_kl <= 0:
            raise ValueError(f"target-kl={self.target_kl} must be > 0 (or None: never stop early)")
        if self.distribution not in ("beta", "gaussian"):
            raise ValueError(f"distribution={self.distribution!r} must be 'beta' or 'gaussian'")
        if self.use_sde and self.distribution != "gaussian":
            raise ValueError(f"use-sde needs distribution='gaussian' (got {self.distribution!r}): "
                             "gSDE perturbs a Gaussian policy's mean; the Beta policy has none "
                             "(--ppo.no-use-sde turns it off)")  # fmt: skip
        if not (math.isfinite(self.log_std_init) and -20 <= self.log_std_init <= 20):
            raise ValueError(
                f"log-std-init={self.log_std_init} must be a finite number in [-20, 20]"
            )
        if self.lambda_max is not None and self.lambda_max < 0:
            raise ValueError(f"lambda-max={self.lambda_max} must be >= 0 (or None: no cap)")


__all__ = ["PPOConfig"]
