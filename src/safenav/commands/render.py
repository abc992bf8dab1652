"""``safenav render``: fly one episode of the fixed test scenario and write a GIF."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import tyro

from safenav.cli import app


@app.command(name="render")
def render(
    checkpoint: tyro.conf.Positional[Path | None] = None,
    out: Path = Path("episode.gif"),
    policy: Literal["checkpoint", "scripted", "straight", "border", "random"] = "checkpoint",
    preset: str | None = None,
    env_seed: int = 1,
    episode: int = 0,
    fps: int = 10,
) -> None:
    """Render one episode (top-down: pillars, moving obstacles, lidar beams, trail, goal) to a GIF.

    Flies episode ``episode`` of the fixed test scenario (env seed ``env_seed``, full density)
    with the checkpoint's deterministic policy, or a scripted potential-field controller
    (``--policy scripted``, the default without a checkpoint) or uniform random actions.
    """
    from safenav.experiments.flight import render_episode

    if checkpoint is None and policy == "checkpoint":
        policy = "scripted"
    stats = render_episode(out, checkpoint=checkpoint, policy=policy, preset=preset,
                           env_seed=env_seed, episode=episode, fps=fps)  # fmt: skip
    print(f"wrote {out}: {stats}")
