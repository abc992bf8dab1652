"""The external benchmark suites of ``safenav bench gym`` and ``safenav bench safe``: tasks,
budgets and the published figures beside which the results are shown.

Every reference is a published figure of another implementation, copied with its source and the
step count it was measured at; where that differs from the budget here, the table says so. The
sources:

- SB3 zoo: rl-baselines3-zoo's benchmark.md (one trained agent per task, its deterministic
  return over ~150k evaluation steps, Gymnasium's v2/v3 MuJoCo models and LunarLander(Continuous)-v2);
- CleanRL: docs/rl-algorithms/sac.md and rpo.md (training episodic return, 3 seeds, MuJoCo v4);
- OmniSafe: benchmarks/off-policy/README.md (1e6 steps) and benchmarks/on-policy/README.md (1e7
  steps), Safety-Gymnasium's velocity tasks v1 (MuJoCo v4 models), cost limit 25, Tables 2.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Reference:
    """A published return (and episode cost) with the budget it was measured at."""

    value: float
    std: float | None
    steps: int
    source: str
    cost: float | None = None
    cost_std: float | None = None


@dataclass(frozen=True)
class Task:
    """One env of a suite: its budget per algorithm and the references."""

    env: str
    steps: dict[str, int]
    references: dict[str, Reference] = field(default_factory=dict)


ZOO = "SB3 zoo benchmark.md"
CLEANRL_SAC = "CleanRL docs sac.md (v4)"
CLEANRL_PPO = "CleanRL docs rpo.md, ppo_continuous_action_8M (v4)"
OMNI_OFF = "OmniSafe off-policy README Table 2 (v1 tasks)"
OMNI_ON = "OmniSafe on-policy README Table 2 (v1 tasks)"

GYM_SUITE: dict[str, Task] = {
    t.env: t
    for t in (
        Task("Pendulum-v1", {"sac": 20_000, "ppo": 100_000},
             {"sac": Reference(-156.995, 88.714, 20_000, ZOO),
              "ppo": Reference(-172.225, 104.159, 100_000, ZOO)}),
        Task("MountainCarContinuous-v0", {"sac": 50_000, "ppo": 20_000},
             {"sac": Reference(94.679, 1.134, 50_000, ZOO),
              "ppo": Reference(88.343, 2.572, 20_000, ZOO)}),
        Task("LunarLanderContinuous-v3", {"sac": 300_000, "ppo": 1_000_000},
             {"sac": Reference(260.390, 65.467, 500_000, ZOO + " (v2)"),
              "ppo": Reference(270.863, 32.072, 1_000_000, ZOO + " (v2)")}),
        Task("InvertedPendulum-v5", {"sac": 100_000, "ppo": 300_000},
             {"sac": Reference(909.37, 55.66, 1_000_000, CLEANRL_SAC),
              "ppo": Reference(888.83, 34.66, 8_000_000, CLEANRL_PPO)}),
        Task("Hopper-v5", {"sac": 300_000, "ppo": 1_000_000},
             {"sac": Reference(2325.547, 1129.676, 1_000_000, ZOO + " (v3)"),
              "ppo": Reference(2410.435, 10.026, 1_000_000, ZOO + " (v3)")}),
        Task("HalfCheetah-v5", {"sac": 300_000, "ppo": 1_000_000},
             {"sac": Reference(9535.451, 100.470, 1_000_000, ZOO + " (v3)"),
              "ppo": Reference(5819.099, 663.530, 1_000_000, ZOO + " (v3)")}),
        # discrete actions: PPO only (SAC acts continuously)
        Task("CartPole-v1", {"ppo": 100_000}, {"ppo": Reference(500.000, 0.000, 100_000, ZOO)}),
        Task("Acrobot-v1", {"ppo": 1_000_000}, {"ppo": Reference(-73.506, 18.201, 1_000_000, ZOO)}),
        Task("LunarLander-v3", {"ppo": 1_000_000},
             {"ppo": Reference(242.119, 31.823, 1_000_000, ZOO + " (v2)")}),
    )
}  # fmt: skip
"""``safenav bench gym``: SAC and PPO on classic control, Box2D and MuJoCo tasks with
continuous actions, PPO on three with discrete ones."""

SAFE_SUITE: dict[str, Task] = {
    t.env: t
    for t in (
        Task("SafetyHopperVelocity-v5",
             {"csac": 300_000, "sac_lag": 300_000, "sac": 300_000, "ppo_lag": 1_000_000},
             {"sac_lag": Reference(963.49, 291.64, 1_000_000, OMNI_OFF, 20.23, 28.47),
              "sac": Reference(3537.70, 32.23, 1_000_000, OMNI_OFF, 975.23, 2.39),
              "ppo_lag": Reference(961.92, 752.87, 10_000_000, OMNI_ON, 13.96, 19.33)}),
        Task("SafetyHalfCheetahVelocity-v5",
             {"csac": 300_000, "sac_lag": 300_000, "sac": 300_000, "ppo_lag": 1_000_000},
             {"sac_lag": Reference(2833.72, 3.62, 1_000_000, OMNI_OFF, 0.00, 0.00),
              "sac": Reference(11488.86, 513.09, 1_000_000, OMNI_OFF, 981.93, 0.33),
              "ppo_lag": Reference(2946.15, 306.35, 10_000_000, OMNI_ON, 3.44, 4.77)}),
    )
}  # fmt: skip
"""``safenav bench safe``: CSAC, SAC-Lag, PPO-Lag and SAC on Safety-Gymnasium's velocity tasks
(:mod:`safenav.common.costs`) at the cost limit of 25."""

SUITES = {"gym": GYM_SUITE, "safe": SAFE_SUITE}
DEFAULT_SB3 = {"gym": ("Pendulum-v1", "Hopper-v5"), "safe": ()}
"""Tasks on which Stable-Baselines3 runs beside safenav by default (same budget, same machine)."""

__all__ = ["DEFAULT_SB3", "GYM_SUITE", "SAFE_SUITE", "SUITES", "Reference", "Task"]
