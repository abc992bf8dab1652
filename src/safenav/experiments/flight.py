"""One rendered flight: an episode of the fixed test scenario, written as a GIF."""

from __future__ import annotations

from pathlib import Path

import torch

from safenav.envs.config import make_config
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.render import render_topdown, write_gif
from safenav.envs.scripted import BorderFollower, go_to_goal, potential_field
from safenav.errors import SafenavError
from safenav.experiments.evaluate import fixed_test_scenario

POLICIES = ("checkpoint", "scripted", "straight", "border", "random")


def resolve_policy(checkpoint: Path | None, policy: str, device: str = "cpu"):
    """``(policy_fn, env_config)`` for a checkpoint (its env config) or a baseline: ``scripted``
    (potential field), ``straight`` (straight at the goal), ``border`` (around the field along
    the border: the loophole probe), ``random``."""
    if policy == "checkpoint":
        if checkpoint is None:
            raise SafenavError("no checkpoint given: pass CHECKPOINT or --policy scripted")
        from safenav.algos.policy import load_policy

        loaded = load_policy(checkpoint, device=device)
        return loaded, loaded.env_config()
    if policy == "scripted":
        return potential_field, None
    if policy == "straight":
        return go_to_goal, None
    if policy == "border":
        return BorderFollower(), None
    if policy == "random":
        gen = torch.Generator().manual_seed(0)
        return (lambda obs: torch.rand(obs["state"].shape[0], 3, generator=gen) * 2 - 1), None
    raise SafenavError(f"unknown policy {policy!r}: choose one of {', '.join(POLICIES)}")


@torch.no_grad()
def render_episode(
    out: Path,
    checkpoint: Path | None = None,
    policy: str = "checkpoint",
    preset: str | None = None,
    env_seed: int = 1,
    episode: int = 0,
    fps: int = 10,
    size: int = 600,
) -> dict:
    """Fly episode ``episode`` of the fixed scenario and write ``out`` (GIF); returns its stats."""
    fn, cfg = resolve_policy(checkpoint, policy)
    if preset is not None or cfg is None:
        cfg = make_config(preset or "paper")
    cfg, starts, goals = fixed_test_scenario(cfg, env_seed, episode + 1)
    env = SafeNavVectorEnv(1, config=cfg, output="torch", autoreset_mode="Disabled",
                           render_mode="rgb_array")  # fmt: skip
    obs, _ = env.reset(
        seed=env_seed, options={"starts": starts[episode:], "goals": goals[episode:]}
    )
    act = (lambda o: fn(o, env)) if getattr(fn, "needs_env", False) else fn
    frames = [env.render()]
    stats: dict = {}
    for _ in range(cfg.max_episode_steps):
        obs, _, term, trunc, info = env.step(act(obs))
        if bool(term[0] or trunc[0]):
            ep = info["episode"]
            stats = {k: round(float(ep[k][0]), 3) for k in ("success", "collision", "timeout", "time",
                                                           "return", "min_clearance", "detour_ratio",
                                                           "border_time")}  # fmt: skip
            outcome = (
                "goal" if stats["success"] else "collision" if stats["collision"] else "timeout"
            )
            frames.append(render_topdown(env, 0, trail=env._trail, outcome=outcome))
            break
        frames.append(env.render())
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    # Hold the last frame for a second so the outcome is visible.
    frames += [frames[-1]] * fps
    write_gif(out, frames, fps)
    return stats


__all__ = ["POLICIES", "render_episode", "resolve_policy"]
