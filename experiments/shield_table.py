"""The shield table of docs/deployment.md section 7: scripted policies on the fixed test scenario
(env seed 1, deterministic), plain and with the velocity-obstacle shield.

    python experiments/shield_table.py      # ~5 min on one CPU thread
"""

from __future__ import annotations

import torch

from safenav.deploy.scripted import GoToGoalActor
from safenav.deploy.shield import env_shield
from safenav.envs.config import make_config
from safenav.envs.scripted import go_to_goal, potential_field
from safenav.experiments.evaluate import evaluate

ROWS = [("go_to_goal", "easy", 100), ("potential_field", "easy", 100), ("GoToGoalActor", "easy", 100),
        ("potential_field", "paper", 200), ("GoToGoalActor", "paper", 200)]  # fmt: skip


def policy(name: str, preset: str):
    if name == "GoToGoalActor":
        actor = GoToGoalActor(make_config(preset)).eval()
        return lambda o: actor(o["state"], o["lidar"], o["dynamic"])
    return {"go_to_goal": go_to_goal, "potential_field": potential_field}[name]


def main() -> None:
    torch.set_num_threads(1)
    print(
        "| policy, preset | success plain -> shielded | collision plain -> shielded | timeout plain -> shielded |"
    )
    print("|---|---|---|---|")
    for name, preset, episodes in ROWS:
        cfg, pol = make_config(preset), policy(name, preset)
        plain, shielded = (
            evaluate(pol, cfg, episodes=episodes, shield=s) for s in (None, env_shield)
        )
        cells = [
            f"{plain[k]:.3g} -> {shielded[k]:.3g}"
            for k in ("success_rate", "collision_rate", "timeout_rate")
        ]
        print(
            f"| {name}, `{preset}`, {episodes} episodes | " + " | ".join(cells) + " |", flush=True
        )


if __name__ == "__main__":
    main()
