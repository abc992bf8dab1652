"""CSAC/SAC hyperparameters (torch-free, so that the CLI can build its parser without torch)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from safenav.common.curriculum import ConstraintCurriculumConfig
from safenav.nn.config import NetConfig


@dataclass(frozen=True)
class CSACConfig:
    """CSAC hyperparameters (paper IV where it gives them); SAC uses the same minus the cost side."""

    constrained: bool = True
    """Cost critics and Lagrange multiplier (CSAC); False is plain SAC (``--algo sac``)."""
    gamma: float = 0.99
    """Discount of reward and cost (paper IV)."""
    tau: float = 0.005
    """Polyak coefficient of the target networks (Algorithm 1, line 15)."""
    batch_size: int = 256
    """Minibatch size of every gradient update."""
    buffer_size: int = 1_000_000
    """Replay capacity in transitions."""
    learning_starts: int = 10_000
    """Warm-up env steps with uniform random actions before the first update (N_warmup)."""
    updates_per_step: float = 0.25
    """Gradient updates per env step (transition); fractions accumulate across vector steps."""
    actor_lr: float = 5e-5
    """Adam learning rate of the actor (paper IV)."""
    reward_critic_lr: float = 5e-4
    """Adam learning rate of the reward critics and of the shared extractor (paper IV)."""
    cost_critic_lr: float = 1e-3
    """Adam learning rate of the cost critics (paper IV)."""
    alpha_lr: float = 1e-5
    """Adam learning rate of log(alpha) (paper IV)."""
    lambda_lr: float = 1e-5
    """Adam learning rate of lambda (paper IV)."""
    init_alpha: float = 0.1
    """Entropy temperature at the start."""
    target_entropy: float | None = None
    """H_target of Eq. 10; None = -|A| (paper)."""
    init_lambda: float = 0.0
    """Lagrange multiplier at the start (>= 0)."""
    lambda_max: float | None = None
    """Optional cap on lambda; None = unbounded (paper)."""
    lambda_update: Literal["adam", "pid"] = "adam"
    """How lambda follows its signal (``lambda_from``): ``adam``, the projected Adam step of
    Eq. 11 at ``lambda_lr`` (``episode_lambda_lr``) (paper); ``pid``, beyond the paper, a PID
    controller on the same violation (Stooke et al. 2020, ``common.lagrange.PIDLagrange``), whose
    proportional and derivative terms answer a violation before the integral has built up: the
    gradient step alone is an integral controller, which overshoots and swings around the limit."""
    pid_kp: float = 1.0
    """``pid``: proportional gain, lambda per unit of the (smoothed) violation ``J - d``."""
    pid_ki: float = 1e-3
    """``pid``: integral gain per update; with a violation of 1 the step of ``lambda_lr`` 1e-3."""
    pid_kd: float = 1.0
    """``pid``: derivative gain on the rise of the smoothed signal over ``pid_d_delay`` updates."""
    pid_d_delay: int = 1000
    """``pid``: updates the derivative term looks back."""
    pid_ema: float = 0.95
    """``pid``: smoothing of the proportional and derivative terms (OmniSafe's 0.95)."""
    lambda_warmup_steps: int = 0
    """Beyond the paper: lambda stays at ``init_lambda`` (no Eq. 11 step, no episode-cost step)
    for the first this many env steps, so that the policy learns to move before the constraint
    binds; the critics, actor and alpha learn as usual. OmniSafe's Lagrangian algorithms hold
    lambda for their ``warmup_epochs`` (SACLag.yaml: the first fifth of the run). 0 = off (paper)."""
    num_critics: int = 2
    """Critics per kind (reward, cost); the paper uses 2 + 2."""
    num_cost_critics: int = 0
    """Cost critics; 0 = ``num_critics`` (CSAC: 2). SAC-Lag (OmniSafe) uses one."""
    lambda_from: Literal["q_cost", "episode_cost"] = "q_cost"
    """What drives lambda: ``q_cost`` = E[Q_C] against d on the Q_C scale at every update
    (Eq. 11, CSAC); ``episode_cost`` = the mean cost of the episodes that ended in the last
    ``lambda_every`` env steps (or of the last ``lambda_window`` episodes) against the episode
    budget d, every ``lambda_every`` env steps (OmniSafe SAC-Lag)."""
    lambda_every: int = 2000
    """``episode_cost``: env steps between lambda updates (OmniSafe's ``update_cycle``)."""
    lambda_window: int = 0
    """``episode_cost``: J_c is the mean cost of the last ``lambda_window`` episodes, kept across
    updates (OmniSafe's logger window, ``window_lens`` 10, read at every update); 0 = the episodes
    that ended since the last update, then forgotten."""
    episode_lambda_lr: float = 1e-3
    """``episode_cost``: Adam learning rate of lambda, one step per update (OmniSafe SAC-Lag)."""
    scale_actor_loss: bool = False
    """Divide the actor loss (Eq. 9) by ``1 + lambda`` (OmniSafe SAC-Lag)."""
    balance_critic_losses: bool = False
    """Beyond the paper: the shared extractor learns from Eq. 7 and Eq. 8 in equal measure, each
    critic loss divided by the square root of its running mean (``CSAC.update``). With the summed
    losses (paper) the reward critics' loss, ~10^4 times the cost critics' on SafeNav, alone
    shapes the features the cost critics read (docs/csac-v1.md). The critic heads are unaffected
    (Adam is invariant to a slowly varying loss scale). Only with cost critics and the shared
    extractor; elsewhere it changes nothing."""
    cost_target: Literal["mean", "min", "max"] = "mean"
    """Reduction of the target cost critics in Eq. 6: mean (paper); min/max are ablations."""
    cost_critic_output: Literal["linear", "softplus", "clipped"] = "linear"
    """Output of each cost critic: ``linear`` (paper), ``softplus`` (Q_C >= 0 as a sum of
    non-negative costs is) or ``clipped`` (the linear output, trained as the paper's, read as
    ``max(Q_C, 0)`` by Eq. 6's targets, the actor's Eq. 9 and Eq. 11). Beyond the paper: a linear
    Q_C extrapolates below 0 at actions the data never showed, the actor's ``lambda * Q_C`` term
    (Eq. 9) seeks them out, the negative values feed Eq. 6's targets and Eq. 11 reads a constraint
    met (docs/gymnasium-results.md, Hopper). A softplus critic pulled towards targets of 0 is
    driven far below 0 by Adam (whose step does not shrink with the vanishing gradient) and then
    cannot come back: on SafetyHopperVelocity-v5 its pre-activations reached -30 to -3,800 on
    every replayed transition, Q_C ~1e-18 while 7 to 9 steps in 10 after the first 10k cost 1.
    ``clipped`` keeps both properties apart: no reader sees a value below 0 (none seeks one: no
    gradient there), and the loss always has a gradient."""
    cost_n_step: int = 1
    """Steps of the cost target: 1 = Eq. 6; n > 1 = the n-step return of the behaviour policy's
    costs, then the target critics (beyond the paper, ``common.nstep``); reward stays one-step."""
    cost_gamma: float | None = None
    """Discount of the cost critics (Eq. 6, the n-step cost target and the mapping of d onto the
    Q_C scale); None = ``gamma`` (paper). Beyond the paper: a shorter cost horizon makes Q_C the
    risk of the next seconds, which one action changes more than the risk of the whole episode."""
    cost_horizon: int = 0
    """Horizon T mapping the episode budget d onto the Q_C scale; 0 = the env's time limit."""
    cost_scale: Literal["horizon", "measured"] = "horizon"
    """How d maps onto the Q_C scale of Eq. 11: ``horizon`` = cost spread evenly over T steps
    (``cost_horizon``); ``measured`` = d times the measured ratio E[Q_C] / episode cost, so that
    the constraint holds the episode cost at d (``common.curriculum.MeasuredCostScale``)."""
    cost_scale_episodes: int = 1000
    """``measured``: episodes the episode-cost mean runs over (an exact mean until then, then a
    moving one). 1000 spans ~150k env steps of a SafeNav ``paper`` run; a single-env Gymnasium
    task needs far fewer, or the warm-up's random episodes weigh on the ratio for the whole run."""
    action_noise_beta: float = 0.0
    """Exponent of the colored noise of the rollout actions: the standard-normal sample of
    ``a = tanh(mu + sigma * eps)`` becomes, per env and action dimension, a Gaussian sequence with
    power spectrum 1/f^beta over the episode (``common.colored_noise``); the updates are unchanged.
    0 = white noise (SAC as published, the default), 1 = pink (Eberhard et al. 2023), 2 = red.
    Beyond the paper."""
    planner_share: float = 0.0
    """Beyond the paper: the share of each minibatch drawn from a privileged planner's flights
    (``training.planner_flights``: planner B flown before training on maps of its own, kept
    apart from the replay buffer; RLPD's symmetric sampling, Ball et al. 2023, uses 0.5). The
    planner reads the simulator's state; the policy never sees it. 0 = off (paper). SafeNav only."""
    planner_steps: int = 20_000
    """Transitions the planner flies for ``planner_share`` (not counted in the run's env steps)."""
    planner_envs: int = 16
    """Envs the planner flies at once (its cost per transition grows with more)."""
    planner_keep_band: bool = False
    """The planner keeps the altitude band of NavRL's height penalty (``OracleConfig.keep_band``),
    so that the reward the critic learns agrees with its flights."""
    planner_view: Literal["range", "pillars"] = "range"
    """What the replayed planner sees (``envs.planner.PLANNERS``): ``range``, planner B (the range
    image's hits of the last second); ``pillars``, the pillars' exact geometry within 4 m (the
    information of the env's ``static_tracked`` entry)."""
    net: NetConfig = field(default_factory=NetConfig)
    """Network sizes and extractor sharing."""
    curriculum: ConstraintCurriculumConfig = field(default_factory=ConstraintCurriculumConfig)
    """Constraint curriculum on d (paper III-C); CSAC only."""

    def __post_init__(self) -> None:
        if not 0 < self.gamma <= 1 or not 0 < self.tau <= 1:
            raise ValueError(f"gamma={self.gamma} and tau={self.tau} must lie in (0, 1]")
        if self.batch_size < 1 or self.buffer_size < self.batch_size:
            raise ValueError(
                f"batch-size={self.batch_size} must be >= 1 and <= buffer-size={self.buffer_size}"
            )
        if self.updates_per_step <= 0 or self.learning_starts < 0 or self.num_critics < 1:
            raise ValueError(
                "updates-per-step > 0, learning-starts >= 0 and num-critics >= 1 are required"
            )
        if self.cost_n_step < 1:
            raise ValueError(f"cost-n-step={self.cost_n_step} must be >= 1")
        if not 0.0 <= self.planner_share < 1.0:
            raise ValueError(f"planner-share={self.planner_share} must lie in [0, 1) (0 = off)")
        if self.planner_envs < 1 or self.planner_steps < self.planner_envs:
            raise ValueError(f"planner-steps={self.planner_steps} must be >= planner-envs="
                             f"{self.planner_envs} >= 1")  # fmt: skip
        if self.cost_gamma is not None and not 0 < self.cost_gamma <= 1:
            raise ValueError(f"cost-gamma={self.cost_gamma} must lie in (0, 1] (or None: gamma)")
        if (self.num_cost_critics < 0 or self.lambda_every < 1 or self.episode_lambda_lr <= 0
                or self.lambda_window < 0):  # fmt: skip
            raise ValueError("num-cost-critics >= 0, lambda-every >= 1, episode-lambda-lr > 0 and "
                             "lambda-window >= 0 are required")  # fmt: skip
        if self.lambda_warmup_steps < 0:
            raise ValueError(
                f"lambda-warmup-steps={self.lambda_warmup_steps} must be >= 0 (0 = off)"
            )
        if self.lambda_update not in ("adam", "pid"):
            raise ValueError(f"lambda-update={self.lambda_update!r}: adam (Eq. 11) or pid")
        gains = (self.pid_kp, self.pid_ki, self.pid_kd)
        if not (all(math.isfinite(g) and g >= 0 for g in gains) and 0 <= self.pid_ema < 1
                and 1 <= self.pid_d_delay <= 1_000_000):  # fmt: skip
            raise ValueError(f"pid-kp={self.pid_kp}, pid-ki={self.pid_ki} and pid-kd={self.pid_kd}"
                             f" must be finite and >= 0, pid-ema={self.pid_ema} in [0, 1) and "
                             f"pid-d-delay={self.pid_d_delay} in [1, 1e6]")  # fmt: skip
        if self.init_alpha <= 0 or self.init_lambda < 0:
            raise ValueError("init-alpha must be > 0 and init-lambda >= 0")
        if self.lambda_max is not None and self.lambda_max < 0:
            raise ValueError(f"lambda-max={self.lambda_max} must be >= 0 (or None: no cap)")
        if self.updates_per_step > 1000:
            raise ValueError(f"updates-per-step={self.updates_per_step} must be <= 1000")
        if not (math.isfinite(self.action_noise_beta) and 0 <= self.action_noise_beta <= 2):
            raise ValueError(f"action-noise-beta={self.action_noise_beta} must be a finite number "
                             "in [0, 2] (0 = white noise, 1 = pink)")  # fmt: skip
        if self.net.trunk != "navrl":  # would be silently ignored: say so instead
            raise ValueError(f"net.trunk={self.net.trunk!r} sets PPO's hidden layers; the SAC "
                             "family's MLPs are Linear -> ReLU (leave it at navrl)")  # fmt: skip
        if self.cost_critic_output not in ("linear", "softplus", "clipped"):
            raise ValueError(f"cost-critic-output={self.cost_critic_output!r}: linear, softplus "
                             "or clipped")  # fmt: skip
        if self.cost_scale_episodes < 1:
            raise ValueError(f"cost-scale-episodes={self.cost_scale_episodes} must be >= 1")
        if self.cost_horizon < 0:
            raise ValueError(f"cost-horizon={self.cost_horizon} must be >= 0 (0 = the env's limit)")
        # 0 is allowed: it freezes that part (tests freeze the critics that way)
        for name in ("actor_lr", "reward_critic_lr", "cost_critic_lr", "alpha_lr", "lambda_lr"):
            lr = getattr(self, name)
            if not (math.isfinite(lr) and lr >= 0):
                raise ValueError(f"{name.replace('_', '-')}={lr} must be a finite number >= 0")

    @property
    def cost_discount(self) -> float:
        """The discount of the cost critics: ``cost_gamma``, else ``gamma`` (paper)."""
        return self.gamma if self.cost_gamma is None else self.cost_gamma


PAPER_EQUATION_FIELDS = (
    "cost_target", "cost_critic_output", "cost_scale", "cost_n_step", "cost_gamma",
    "lambda_warmup_steps", "lambda_update", "lambda_from", "scale_actor_loss",
    "balance_critic_losses", "action_noise_beta", "planner_share", "curriculum.enabled",
)  # fmt: skip
"""The ``CSACConfig`` fields (dotted) whose non-default values change the paper's equations
(Eqs. 6-11, the constraint curriculum, the rollout actions) rather than a hyperparameter of
them: the defaults are the paper's."""


def paper_departures(csac: dict) -> list[str]:
    """What a CSAC config (a ``config.json``'s ``csac`` section) changes in the paper's method,
    as ``field=value (paper: default)``: a result of such a config is a variant and is named so
    (``safenav bench safe``'s table marks its row). A field the config lacks (written before the
    field existed) ran with its default."""
    from dataclasses import asdict

    paper = asdict(CSACConfig())
    out = []
    for name in PAPER_EQUATION_FIELDS:
        head, _, tail = name.partition(".")
        default = paper[head][tail] if tail else paper[head]
        value = (csac.get(head) or {}).get(tail, default) if tail else csac.get(head, default)
        if value != default:
            out.append(f"{name}={value} (paper: {default})")
    return out


__all__ = ["PAPER_EQUATION_FIELDS", "CSACConfig", "paper_departures"]
