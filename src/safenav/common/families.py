"""The task family of a Gymnasium env id (what ``safenav train`` picks a recipe by) and the
algorithm family of an ``--algo`` (which options and learner it takes)."""

from __future__ import annotations

FAMILIES = {
    "gymnasium.envs.classic_control": ("classic", "Gymnasium classic control"),
    "gymnasium.envs.box2d": ("box2d", "Gymnasium Box2D"),
    "gymnasium.envs.mujoco": ("mujoco", "Gymnasium MuJoCo locomotion"),
}
"""Entry-point package of a Gymnasium env -> (recipe family, its name in words)."""

PPO_ALGOS = ("ppo", "ppo_lag")
"""The on-policy algorithms; every other ``--algo`` is of the SAC family."""

CONSTRAINED = ("csac", "sac_lag", "ppo_lag")
"""The algorithms that read a cost (``info["cost"]``) against a limit."""


def algo_family(algo: str) -> str:
    """``"ppo"`` for PPO and PPO-Lag (their options are ``--ppo.*``), ``"csac"`` for the SAC
    family (``--csac.*``)."""
    return "ppo" if algo in PPO_ALGOS else "csac"


def task_family(env_id: str) -> tuple[str, str]:
    """``(family, description)`` of a Gymnasium id: ``safenav`` for SafeNav, ``classic``,
    ``box2d`` or ``mujoco`` for Gymnasium's own envs (by their entry point's package; an env
    registered with ``kwargs={"base": ID}``, such as the velocity tasks, takes the family of
    ``ID``), else ``gym`` (any other env). An unknown id is ``gym`` too (checked elsewhere)."""
    import gymnasium as gym

    if env_id.split(":")[-1].startswith("SafeNav-"):
        return "safenav", "SafeNav"
    try:
        spec = gym.spec(env_id)
    except gym.error.Error:
        return "gym", "a Gymnasium env"
    base = (spec.kwargs or {}).get("base")
    if isinstance(base, str) and base != env_id:
        return task_family(base)
    entry = spec.entry_point if isinstance(spec.entry_point, str) else ""
    for package, family in FAMILIES.items():
        if entry.startswith(package):
            return family
    return "gym", "a Gymnasium env outside the classic control, Box2D and MuJoCo families"


__all__ = ["CONSTRAINED", "FAMILIES", "PPO_ALGOS", "algo_family", "task_family"]
