"""``SafeNav-v1``: the batched CMDP simulator (world, sensors, dynamics, the env itself)."""

from safenav.envs.config import PRESETS, EnvConfig, make_config
from safenav.envs.nav import SafeNavEnv, SafeNavVectorEnv, fixed_scenario, sample_episodes

__all__ = ["PRESETS", "EnvConfig", "SafeNavEnv", "SafeNavVectorEnv", "make_config",
           "sample_episodes", "fixed_scenario"]  # fmt: skip
