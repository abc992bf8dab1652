"""Curricula: the constraint curriculum on ``d`` (paper III-C) and the obstacle-density one (Fig. 2).

Constraint curriculum
---------------------
``d`` is an **episode-cost budget**: with SafeNav's cost (1 at a collision, and a collision ends
the episode) the average episode cost is the collision rate, so ``d = 0.1`` reads "at most 10 % of
episodes end in a collision". Training is cut into epochs of ``epoch_steps`` env steps; after each
epoch (with at least ``min_episodes`` finished episodes) the average episode cost is compared with
``d``. When it has stayed **below** ``d`` for ``patience`` consecutive epochs, ``d <- max(d_min,
factor * d)`` and the count restarts. Stages (logged as ``constraint/stage``):

- 0 *exploration*: ``d == d_init`` (a lenient budget for mistakes),
- 1 *balanced*: ``d_min < d < d_init`` (tightening),
- 2 *safety*: ``d == d_min`` (the strict final budget).

Eq. 11 compares ``d`` with ``E[Q_C]``, a replay-averaged *discounted* sum of future cost. The
budget is mapped onto that scale by :func:`episode_cost_to_q_scale`: spread over a horizon of ``T``
steps (``CSACConfig.cost_horizon``, by default the env's time limit) the budget is a cost rate
``d / T`` per step; its discounted value from a state, averaged over the states of an episode, is
``d_Q``; ``constraint/d_q`` logs it. The mapping is exact for cost spread evenly over episodes of
length ``T``; for SafeNav, whose episodes end earlier (success, collision), it is an approximation.
:class:`MeasuredCostScale` (``--csac.cost-scale measured``) measures the ratio instead.

Density curriculum
------------------
The fraction of active obstacles grows linearly in env steps from ``start`` to ``end`` over the
first ``ramp_fraction`` of training (``mode="linear"``, default: the same schedule for every
algorithm and seed, so runs stay comparable and resumable), or by ``increment`` after each epoch
whose success rate reached ``success_threshold`` (``mode="success"``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

STAGES = ("exploration", "balanced", "safety")


def episode_cost_to_q_scale(d: float, gamma: float, horizon: int) -> float:
    """An episode-cost budget ``d`` on the scale of ``E_{s~D}[Q_C(s, a)]``, the replay-averaged
    discounted cost value Eq. 11 compares with the threshold.

    Spread over an episode of ``T`` steps the budget is a cost rate ``c = d / T``; from a state
    ``r`` steps before the end its discounted value is ``c (1 - gamma^r) / (1 - gamma)``; averaged
    over the ``T`` states of the episode (what the replay buffer holds):

        d_Q = d / T * (T - gamma (1 - gamma^T) / (1 - gamma)) / (T (1 - gamma))

    which tends to ``d (T + 1) / (2 T)`` (the mean remaining cost) as ``gamma -> 1`` and to the
    stationary ``c / (1 - gamma)`` for ``T >> 1 / (1 - gamma)``.
    """
    if horizon < 1:
        raise ValueError(f"horizon={horizon} must be >= 1")
    t = float(horizon)
    if gamma >= 1.0:
        return d * (t + 1.0) / (2.0 * t)
    return d / t * (t - gamma * (1.0 - gamma**t) / (1.0 - gamma)) / (t * (1.0 - gamma))


class MeasuredCostScale:
    """``d -> d_Q`` by measurement instead of a modelled horizon: ``d_Q = d * rho`` with ``rho`` the
    ratio of running means ``E[Q_C(s, a ~ pi)] / (average episode cost)``, both as training sees
    them now.

    Why: :func:`episode_cost_to_q_scale` assumes cost spread evenly over ``T`` steps, while
    SafeNav's cost is one terminal event whose discounted value depends on *when* episodes collide;
    the measured ratio drifted between ~0.03 and ~0.1 in training, so a fixed ``T`` held the
    episode cost anywhere between ~0.7 d and ~1.5 d, and the curriculum (judging episode cost
    against ``d``) stalled. With the measured ratio, λ meeting Eq. 11's threshold means an average
    episode cost at ``d``, the quantity the curriculum tightens. Eq. 11 itself is unchanged.

    Running means are exponential with weight ``max(1 / n, 1 / span)`` per observation (an exact
    average until ``span`` observations, then a moving one); the defaults, 1000 episodes and 5000
    updates, both span ~150k env steps of a ``paper`` run. Until ``min_episodes`` episodes have
    ended ``fallback`` is used; while the episode cost is ~0 or the mean Q_C is not positive (no
    ratio to measure), the last ratio; and never more than a factor ``BAND`` from ``fallback``.
    """

    BAND = 10.0
    """The measured ratio stays within this factor of ``fallback``."""

    def __init__(self, fallback: float, span_episodes: int = 1000, span_updates: int = 5000,
                 min_episodes: int = 100) -> None:  # fmt: skip
        if fallback <= 0 or span_episodes < 1 or span_updates < 1 or min_episodes < 1:
            raise ValueError("MeasuredCostScale: fallback > 0, spans >= 1, min_episodes >= 1")
        self.fallback, self.min_episodes = fallback, min_episodes
        self.span_episodes, self.span_updates = span_episodes, span_updates
        self.q_mean, self.q_n = 0.0, 0
        self.cost_mean, self.cost_n = 0.0, 0
        self.last = fallback

    def observe_episodes(self, episode_costs) -> None:
        """Record the costs of episodes that just finished."""
        for c in episode_costs:
            self.cost_n += 1
            self.cost_mean += (float(c) - self.cost_mean) * max(
                1.0 / self.cost_n, 1.0 / self.span_episodes
            )

    def observe_q(self, q_cost_mean: float) -> None:
        """Record one measurement of the replay-averaged ``E[Q_C(s, a ~ pi)]`` (an update's)."""
        if math.isfinite(q_cost_mean):
            self.q_n += 1
            self.q_mean += (q_cost_mean - self.q_mean) * max(
                1.0 / self.q_n, 1.0 / self.span_updates
            )

    @property
    def ratio(self) -> float:
        """``rho``: Q_C-scale value per unit of episode cost (the last valid one while unmeasurable),
        held within ``[fallback / BAND, fallback * BAND]``."""
        if (self.cost_n >= self.min_episodes and self.q_n > 0 and self.q_mean > 0
                and self.cost_mean > 1e-3):  # fmt: skip
            self.last = self.q_mean / self.cost_mean
        if self.cost_n < self.min_episodes:
            return self.fallback
        # Why a band: a cost critic sliding below its floor (Hopper, docs/gymnasium-results.md)
        # took the ratio, hence d_Q, to ~0, and every Q_C then read as a violation; the modelled
        # ratio (cost spread evenly) is within a factor 6 of every ratio measured (SafeNav
        # 0.03-0.1 vs 0.062, Hopper 0.036-0.54 vs 0.090)
        return min(max(self.last, self.fallback / self.BAND), self.fallback * self.BAND)

    def d_q(self, d: float) -> float:
        return d * self.ratio

    def state_dict(self) -> dict[str, Any]:
        return {"q_mean": self.q_mean, "q_n": self.q_n, "cost_mean": self.cost_mean,
                "cost_n": self.cost_n, "last": self.last}  # fmt: skip

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.q_mean, self.q_n = float(state["q_mean"]), int(state["q_n"])
        self.cost_mean, self.cost_n = float(state["cost_mean"]), int(state["cost_n"])
        self.last = float(state["last"])


@dataclass(frozen=True)
class ConstraintCurriculumConfig:
    """Constraint curriculum (paper III-C): tighten ``d`` while the agent keeps within it."""

    enabled: bool = True
    """Tighten ``d`` during training; False fixes ``d = d_min`` from the start (the ablation)."""
    d_init: float = 0.5
    """Lenient starting budget, in expected cost per episode (collision rate)."""
    d_min: float = 0.05
    """Strict final budget (near zero)."""
    factor: float = 0.7
    """Multiplier applied to ``d`` at each tightening (0 < factor < 1)."""
    patience: int = 3
    """Consecutive epochs with average episode cost below ``d`` before tightening (K)."""
    epoch_steps: int = 20_000
    """Env steps per curriculum epoch."""
    min_episodes: int = 10
    """Epochs with fewer finished episodes do not count (too noisy) and reset the streak."""

    def __post_init__(self) -> None:
        if not 0 < self.d_min <= self.d_init:
            raise ValueError(f"curriculum: need 0 < d_min ({self.d_min}) <= d_init ({self.d_init})")
        if not 0 < self.factor < 1:
            raise ValueError(f"curriculum: factor={self.factor} must lie in (0, 1)")
        if self.patience < 1 or self.epoch_steps < 1 or self.min_episodes < 1:
            raise ValueError("curriculum: patience, epoch_steps and min_episodes must be >= 1")


class ConstraintCurriculum:
    """The state machine of the constraint curriculum; feed it finished episodes and env steps."""

    def __init__(self, cfg: ConstraintCurriculumConfig) -> None:
        self.cfg = cfg
        self.d = cfg.d_init if cfg.enabled else cfg.d_min
        self.streak = 0
        self.epoch = 0
        self.next_epoch_step = cfg.epoch_steps
        self._cost_sum, self._episodes = 0.0, 0
        self.history: list[dict[str, Any]] = []

    @property
    def stage(self) -> int:
        """0 exploration, 1 balanced, 2 safety (see module docstring)."""
        if self.d <= self.cfg.d_min:
            return 2
        return 0 if self.d >= self.cfg.d_init else 1

    @property
    def stage_name(self) -> str:
        return STAGES[self.stage]

    def observe(self, episode_costs) -> None:
        """Record the costs of episodes that just finished."""
        for c in episode_costs:
            self._cost_sum += float(c)
            self._episodes += 1

    def step(self, global_step: int) -> dict[str, Any] | None:
        """Close every epoch ending at or before ``global_step``; returns a record when ``d``
        changed (also appended to :attr:`history`), else None."""
        change = None
        while global_step >= self.next_epoch_step:
            self.epoch += 1
            self.next_epoch_step += self.cfg.epoch_steps
            n, mean = (
                self._episodes,
                (self._cost_sum / self._episodes if self._episodes else math.nan),
            )
            self._cost_sum, self._episodes = 0.0, 0
            if not self.cfg.enabled or self.d <= self.cfg.d_min:
                continue
            if n >= self.cfg.min_episodes and mean < self.d:
                self.streak += 1
            else:
                self.streak = 0
            if self.streak >= self.cfg.patience:
                old, self.d, self.streak = self.d, max(self.cfg.d_min, self.d * self.cfg.factor), 0
                change = {"global_step": int(global_step), "epoch": self.epoch, "d_old": old, "d": self.d,
                          "stage": self.stage_name, "epoch_cost": mean}  # fmt: skip
                self.history.append(change)
        return change

    def state_dict(self) -> dict[str, Any]:
        return {"d": self.d, "streak": self.streak, "epoch": self.epoch,
                "next_epoch_step": self.next_epoch_step, "cost_sum": self._cost_sum,
                "episodes": self._episodes, "history": list(self.history)}  # fmt: skip

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.d, self.streak, self.epoch = (
            float(state["d"]),
            int(state["streak"]),
            int(state["epoch"]),
        )
        self.next_epoch_step = int(state["next_epoch_step"])
        self._cost_sum, self._episodes = float(state["cost_sum"]), int(state["episodes"])
        self.history = list(state["history"])


@dataclass(frozen=True)
class DensityCurriculumConfig:
    """Obstacle-density curriculum (paper Fig. 2); applies to envs with ``set_density`` (SafeNav)."""

    enabled: bool = True
    """Raise the density during training; False trains at ``end`` throughout."""
    start: float = 0.2
    """Fraction of active obstacles at the start."""
    end: float = 1.0
    """Fraction of active obstacles at the end of the ramp."""
    mode: Literal["linear", "success"] = "linear"
    """``linear`` in env steps, or ``success``-gated (see module docstring)."""
    ramp_fraction: float = 0.5
    """Linear mode: fraction of ``total_steps`` over which the density reaches ``end``."""
    success_threshold: float = 0.7
    """Success mode: an epoch with at least this success rate raises the density."""
    increment: float = 0.1
    """Success mode: density added per qualifying epoch."""
    epoch_steps: int = 20_000
    """Success mode: env steps per epoch."""
    quantum: float = 0.05
    """Density changes are applied in steps of this size (each change rebuilds height maps)."""

    def __post_init__(self) -> None:
        if not (0.0 <= self.start <= 1.0 and 0.0 <= self.end <= 1.0):
            raise ValueError(
                f"density curriculum: start={self.start}, end={self.end} must lie in [0, 1]"
            )
        if (
            self.ramp_fraction <= 0
            or self.increment <= 0
            or self.epoch_steps < 1
            or self.quantum <= 0
        ):
            raise ValueError(
                "density curriculum: ramp_fraction, increment, quantum > 0 and epoch_steps >= 1"
            )
        if not (0.0 <= self.success_threshold <= 1.0 and self.increment <= 1 and self.quantum <= 1):
            raise ValueError("density curriculum: success_threshold in [0, 1], increment and "
                             "quantum <= 1 (fractions of the obstacles)")  # fmt: skip


class DensityCurriculum:
    """Density as a function of training progress; :meth:`step` returns a new value to apply."""

    def __init__(self, cfg: DensityCurriculumConfig, total_steps: int) -> None:
        self.cfg = cfg
        self.total_steps = total_steps
        self.density = cfg.start if cfg.enabled else cfg.end
        self.next_epoch_step = cfg.epoch_steps
        self._succ, self._episodes = 0.0, 0

    def observe(self, successes) -> None:
        for s in successes:
            if not math.isnan(float(s)):
                self._succ += float(s)
                self._episodes += 1

    def target(self, global_step: int) -> float:
        cfg = self.cfg
        if not cfg.enabled:
            return cfg.end
        if cfg.mode == "linear":
            frac = min(1.0, global_step / max(1.0, cfg.ramp_fraction * self.total_steps))
            return cfg.start + frac * (cfg.end - cfg.start)
        value = self.density
        while global_step >= self.next_epoch_step:
            self.next_epoch_step += cfg.epoch_steps
            if self._episodes and self._succ / self._episodes >= cfg.success_threshold:
                value = (
                    min(cfg.end, value + cfg.increment)
                    if cfg.end >= cfg.start
                    else max(cfg.end, value - cfg.increment)
                )
            self._succ, self._episodes = 0.0, 0
        return value

    def step(self, global_step: int) -> float | None:
        """The new density when it moved by at least ``quantum`` (or reached ``end``), else None."""
        target = self.target(global_step)
        if abs(target - self.density) >= self.cfg.quantum - 1e-9 or (
            target == self.cfg.end != self.density
        ):
            self.density = target
            return target
        return None

    def state_dict(self) -> dict[str, Any]:
        return {"density": self.density, "next_epoch_step": self.next_epoch_step,
                "succ": self._succ, "episodes": self._episodes}  # fmt: skip

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.density = float(state["density"])
        self.next_epoch_step = int(state["next_epoch_step"])
        self._succ, self._episodes = float(state["succ"]), int(state["episodes"])


__all__ = ["STAGES", "ConstraintCurriculum", "ConstraintCurriculumConfig", "DensityCurriculum",
           "DensityCurriculumConfig", "MeasuredCostScale", "episode_cost_to_q_scale"]  # fmt: skip
