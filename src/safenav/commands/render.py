"""``safenav render``: fly one episode of the fixed test scenario and write a GIF."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Literal

import tyro

from safenav.cli import app

MAX_EPISODE = 999_999  # the scenario draws episode + 1 start/goal pairs


@app.command(name="render")
def render(
    checkpoint: tyro.conf.Positional[Path | None] = None,
    out: Path = Path("episode.gif"),
    policy: Literal[
        "checkpoint", "scripted", "straight", "border", "random", "planner"
    ] = "checkpoint",
    preset: str | None = None,
    env_seed: int = 1,
    episode: int = 0,
    fps: int = 10,
    record: Path | None = None,
    shield: bool = False,
    shield_memory: int = 0,
    shield_map: bool = False,
    shield_mover_margin: float = 0.0,
    shield_brake: bool = False,
    planner_filter: bool = False,
    planner_filter_view: Literal["observation", "simulator"] = "observation",
) -> None:
    """Render one episode (top-down: pillars, moving obstacles, lidar beams, trail, goal) to a GIF.

    A checkpoint trained on another Gymnasium task flies episode ``episode`` after
    ``reset(seed=env_seed)`` of that task, in its own rendering, with the running return and cost
    on each frame and a red frame around each step that costs (``--fps 25`` or so plays a MuJoCo
    task near real time); the SafeNav-only options do not apply there.

    Flies episode ``episode`` of the fixed test scenario (env seed ``env_seed``, full density)
    with the checkpoint's deterministic policy, or a scripted potential-field controller
    (``--policy scripted``, the default without a checkpoint), uniform random actions, or the
    privileged planner B (``--policy planner``: it reads the simulator's state).
    ``--record episode.mcap`` also logs it in MCAP with ROS 2 messages, in simulation time, for
    Foxglove or ``ros2 bag`` (docs/deployment.md, "Flight logs").

    Args:
        checkpoint: Policy or training checkpoint, or a run directory.
        out: The GIF to write (*.gif; its directory must exist).
        policy: What flies: the checkpoint, or a baseline without one.
        preset: Env preset (easy, medium, paper); default: the checkpoint's, else paper.
        env_seed: Env seed of the test scenario's map (a Gymnasium task: the reset seed).
        episode: Which episode of the fixed scenario (start and goal), from 0.
        fps: Frames per second of the GIF (1-100).
        record: Also log the episode here (*.mcap: ROS 2 messages, for Foxglove / ros2 bag).
        shield: Correct the actions with the velocity-obstacle safety shield.
        shield_memory: With --shield: its static obstacles are the range images of the last N
            steps, kept where they were seen (beyond NavRL's shield; 0 or 1: the current image).
        shield_map: With --shield: it also avoids every pillar the height map holds at the UAV's
            lower extent (a level scan of the map, beyond NavRL's shield).
        shield_mover_margin: With --shield: metres more clearance from tracked moving obstacles
            (0-2; beyond NavRL's shield).
        shield_brake: With --shield: the braking cap: near a static obstacle, the ground or the
            ceiling the shield slows the vehicle to a speed it can stop from (beyond NavRL's).
        planner_filter: After the shield (if any), the model-predictive safety filter: the
            pillar planner flies where the command leaves no way out, and 5 s where a flight
            stalls (beyond the paper; docs/csac-v1.md). A policy trained with --flight-filter
            flies behind the filter it records unless --no-planner-filter.
        planner_filter_view: What the filter sees: observation (the observation's pillar list
            and tracked movers) or simulator (the pillars and movers within 4 m).
    """
    from safenav.commands.eval import check_shield_memory
    from safenav.common.checks import check_output_file, in_range
    from safenav.common.config import MAX_SEED
    from safenav.envs.config import make_config
    from safenav.errors import SafenavError
    from safenav.experiments.flight import render_episode

    # Before the flight, so that a typo costs a second, not the episode.
    in_range("--fps", fps, 1, 100, "GIF frame times are whole 1/100 s")
    in_range("--episode", episode, 0, MAX_EPISODE, "the fixed scenario's episodes count from 0")
    in_range("--env-seed", env_seed, 0, MAX_SEED)
    if preset is not None:
        make_config(preset)  # ValueError for an unknown preset: exit 2
    check_output_file(out, "--out", "episode.gif")
    if out.suffix.lower() != ".gif":
        raise SafenavError(f"--out {out}: a GIF is written; name it *.gif, e.g. --out episode.gif")
    if record is not None:
        from safenav.deploy.mcap_log import check_record_path

        check_record_path(record, "--record")
    memory = check_shield_memory(shield, shield_memory, shield_map, shield_mover_margin,
                                 shield_brake)  # fmt: skip
    if checkpoint is None and policy == "checkpoint":
        policy = "scripted"
    safenav_only = {"--preset": preset is not None, "--record": record is not None,
                    "--shield": shield, "--planner-filter": planner_filter}  # fmt: skip
    loaded = None
    if policy == "checkpoint":
        loaded = _load_or_render_gymnasium(checkpoint, out, env_seed, episode, fps,
                                           [k for k, v in safenav_only.items() if v])  # fmt: skip
        if loaded is None:
            return
        from safenav.commands.eval import own_shield_settings

        # a policy trained behind the shield flies behind it, and behind its planner filter
        memory, shield_map, shield_mover_margin, shield_brake = own_shield_settings(
            loaded, checkpoint, memory, shield_map, shield_mover_margin, shield_brake)  # fmt: skip
    from safenav.commands.eval import brake_under_filter, own_planner_filter

    spec = own_planner_filter(loaded, checkpoint, planner_filter, planner_filter_view)
    shield_brake = brake_under_filter(spec, shield_brake)
    stats = render_episode(out, checkpoint=checkpoint, policy=policy, preset=preset,
                           env_seed=env_seed, episode=episode, fps=fps, record=record,
                           shield_memory=memory, shield_map=shield_map,
                           shield_mover_margin=shield_mover_margin,
                           shield_brake=shield_brake, loaded=loaded,
                           planner_filter=spec)  # fmt: skip
    print(f"wrote {out}{f' and {record}' if record is not None else ''}: {stats}")


def _load_or_render_gymnasium(checkpoint: Path, out: Path, seed: int, episode: int, fps: int,
                              safenav_options: list[str]):  # fmt: skip
    """The checkpoint's policy when it flies SafeNav; a checkpoint of another task is rendered
    here (and said so), and None returned. The file is read once: a SAC checkpoint holds its
    replay buffer."""
    from safenav.algos.policy import policy_from_state
    from safenav.common.checkpoint import load_checkpoint
    from safenav.envs.vector import is_safenav
    from safenav.errors import SafenavError
    from safenav.experiments.gym_render import render_gym_episode

    state = load_checkpoint(checkpoint)  # read once: a SAC checkpoint holds its replay buffer
    loaded = policy_from_state(state, checkpoint)
    env_id = str(loaded.meta.get("env_id", ""))
    if not env_id or is_safenav(env_id):
        return loaded
    if safenav_options:
        raise SafenavError(f"{', '.join(safenav_options)}: SafeNav options; {checkpoint} is a "
                           f"policy for {env_id}")  # fmt: skip
    run = state.get("config", {}).get("run", {})  # the run's --cost-fn, if it had one
    stats = render_gym_episode(out, loaded, seed=seed, episode=episode, fps=fps,
                               cost_fn=run.get("cost_fn"))  # fmt: skip
    print(f"wrote {out}: {stats}")
    if not stats["ended"]:
        print(f"safenav render: note: the episode had not ended after {stats['length']:,} steps "
              f"({stats['frames']:,} frames); the GIF shows them", file=sys.stderr)  # fmt: skip
    return None
