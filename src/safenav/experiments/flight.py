"""One rendered flight: an episode of the fixed test scenario, written as a GIF (and, with
``record``, as an MCAP log with ROS 2 messages: :mod:`safenav.deploy.mcap_log`)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import torch

from safenav.envs.config import EnvConfig, make_config
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.render import render_topdown, write_gif
from safenav.envs.scripted import BorderFollower, go_to_goal, potential_field
from safenav.errors import SafenavError, SafenavRuntimeError
from safenav.experiments.evaluate import fixed_test_scenario

POLICIES = ("checkpoint", "scripted", "straight", "border", "random", "planner")


def resolve_policy(checkpoint: Path | None, policy: str, device: str = "cpu", loaded=None):
    """``(policy_fn, env_config)`` for a checkpoint (its env config) or a baseline: ``scripted``
    (potential field), ``straight`` (straight at the goal), ``border`` (around the field along
    the border: the loophole probe), ``random``, ``planner`` (the privileged planner B,
    :data:`~safenav.envs.planner.PLANNER_B`, which reads the simulator's state, with the tilted
    beams it was measured with: a reference, not a policy). ``loaded``: the checkpoint's
    :class:`~safenav.algos.policy.Policy` when the caller has read it already (a SAC checkpoint
    holds its replay buffer: read it once)."""
    if policy == "checkpoint":
        if loaded is None:
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
    if policy == "planner":
        from safenav.envs.planner import PLANNER_B, PLANNER_B_BEAMS, OraclePlanner

        return OraclePlanner(PLANNER_B), make_config("paper", lidar_v_angles=PLANNER_B_BEAMS)
    if policy == "random":
        gen = torch.Generator().manual_seed(0)
        return (lambda obs: torch.rand(obs["state"].shape[0], 3, generator=gen) * 2 - 1), None
    raise SafenavError(f"unknown policy {policy!r}: choose one of {', '.join(POLICIES)}")


SENSOR_FIELDS = ("lidar_range", "lidar_h_beams", "lidar_v_angles", "lidar_history",
                 "lidar_memory", "num_tracked", "static_tracked")  # fmt: skip
"""The env config's fields that make a policy's observation: a preset's scenario keeps the
policy's own (beams tilted otherwise give an image of the same shape, read wrongly)."""


def scenario_config(cfg: EnvConfig | None, preset: str | None) -> EnvConfig:
    """The env config a policy flies in: the ``preset``'s scenario when one is given, else the
    policy's own ``cfg`` (else the paper's). A preset keeps what the policy reads beyond the
    scenario: its sensor (:data:`SENSOR_FIELDS`: range, beams and their elevations, range-image
    history, memory image, tracked moving obstacles)."""
    if preset is None and cfg is not None:
        return cfg
    scenario = make_config(preset or "paper")
    if cfg is None:
        return scenario
    return scenario.replace(**{k: getattr(cfg, k) for k in SENSOR_FIELDS})


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
    record: Path | None = None,
    shield_memory: int = 0,
    shield_map: bool = False,
    shield_mover_margin: float = 0.0,
    shield_brake: bool = False,
    loaded=None,
    planner_filter: dict | None = None,
) -> dict:
    """Fly episode ``episode`` of the fixed scenario and write ``out`` (GIF), and ``record``
    (MCAP, stamped with the simulation time) when given; returns its stats. ``loaded``: the
    checkpoint's policy, when already read; ``planner_filter``: behind the model-predictive safety
    filter (:class:`~safenav.envs.planner.PlannerFilter`) after the shield, the one this
    :func:`~safenav.envs.planner.filter_spec` names (None: none)."""
    frames, stats = fly_frames(checkpoint, policy, preset, env_seed, episode, record, shield_memory,
                               shield_map, shield_mover_margin, shield_brake, loaded,
                               planner_filter)  # fmt: skip
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    # Hold the last frame for a second so the outcome is visible.
    frames += [frames[-1]] * fps
    write_gif(out, frames, fps)
    return stats


def flight_filter(spec: dict, cfg: EnvConfig):
    """The planner filter ``safenav eval`` and ``render`` fly behind: ``spec``, a
    :func:`~safenav.envs.planner.filter_spec` (the policy's own record, or the adopted filter of
    ``--planner-filter``); refused before the flight where its observed view would find no
    pillar list in this config's observation."""
    from safenav.envs.planner import filter_from_spec, observes_pillars

    if spec["view"] == "observation" and not observes_pillars(cfg):
        raise SafenavError("--planner-filter sees the observation's pillar list, which this "
                           "flight's observation lacks (EnvConfig.static_tracked 0): add "
                           "--planner-filter-view simulator")  # fmt: skip
    return filter_from_spec(spec)


BATCH_ROWS = 8
"""Torch's CPU matrix products round a batch of 1-3 rows differently from a larger one (~1e-7 in
the actions of a trained policy, measured), and a flight amplifies that within seconds: a
network flying one episode alone is given at least this many rows (:func:`in_batch_rows`)."""


def in_batch_rows(fn, rows: int = BATCH_ROWS):
    """``fn`` called on at least ``rows`` rows (the observation's first row repeated), its
    actions for the real rows returned, so that a policy network flying one episode rounds as it
    does in ``safenav eval``'s batch: ``safenav render --episode K`` is then episode K of that
    batch, bit for bit (a validation timeout otherwise arrived when rendered, 2026-12-04)."""

    def call(obs: dict[str, torch.Tensor]) -> torch.Tensor:
        n = obs["state"].shape[0]
        if n >= rows:
            return fn(obs)
        idx = torch.cat([torch.arange(n), torch.zeros(rows - n, dtype=torch.long)])
        return fn({k: v[idx.to(v.device)] for k, v in obs.items()})[:n]

    return call


@torch.no_grad()
def fly_frames(
    checkpoint: Path | None = None,
    policy: str = "checkpoint",
    preset: str | None = None,
    env_seed: int = 1,
    episode: int = 0,
    record: Path | None = None,
    shield_memory: int = 0,
    shield_map: bool = False,
    shield_mover_margin: float = 0.0,
    shield_brake: bool = False,
    loaded=None,
    planner_filter: dict | None = None,
) -> tuple[list, dict]:
    """The rendered frames (top-down RGB arrays, the last with the outcome) and the stats of
    episode ``episode`` of the fixed scenario of map ``env_seed``, flown by the policy, behind
    the safety shield when ``shield_memory`` is 1 (the memoryless shield) or more (a
    :class:`~safenav.deploy.shield.MemoryShield` of that many range images), with the map scan
    when ``shield_map``, ``shield_mover_margin`` metres more clearance from moving obstacles, the
    braking cap when ``shield_brake``, then the planner filter ``planner_filter`` (a
    :func:`~safenav.envs.planner.filter_spec`) when given;
    ``loaded``: the checkpoint's policy, when already read."""
    fn, cfg = resolve_policy(checkpoint, policy, loaded=loaded)
    cfg, starts, goals = fixed_test_scenario(scenario_config(cfg, preset), env_seed, episode + 1)
    env = SafeNavVectorEnv(1, config=cfg, output="torch", autoreset_mode="Disabled",
                           render_mode="rgb_array")  # fmt: skip
    obs, _ = env.reset(
        seed=env_seed, options={"starts": starts[episode:], "goals": goals[episode:]}
    )
    if getattr(fn, "needs_env", False):
        act = lambda o: fn(o, env)  # noqa: E731
    else:
        act = in_batch_rows(fn) if policy == "checkpoint" else fn
    arithmetic = contextlib.nullcontext()
    if shield_memory > 0 or shield_map:  # the shield's module loads Numba: only when it flies
        from safenav.deploy.shield import batched_arithmetic, shield_for_memory

        shield = shield_for_memory(shield_memory, shield_map, shield_mover_margin,
                                   brake=shield_brake)  # fmt: skip
        act = lambda o, a=act: shield(env, o, a(o))  # noqa: E731
        arithmetic = batched_arithmetic()  # the episode as safenav eval's batch flies it
    if planner_filter:
        the_filter = flight_filter(planner_filter, cfg)
        act = lambda o, a=act: the_filter(env, o, a(o))  # noqa: E731
    frames = [env.render()]
    recorder = None
    if record is not None:
        from safenav.deploy.mcap_log import McapRecorder

        recorder = McapRecorder(record, episode_scene(env), clock="sim", threaded=False,
                                metadata={"verb": "render", "policy": policy, "checkpoint": checkpoint,
                                          "preset": preset or "the checkpoint's",
                                          "env_seed": env_seed, "episode": episode})  # fmt: skip
    try:
        with arithmetic:
            stats = _fly_episode(env, act, cfg, frames, recorder, obs)
    finally:
        if recorder is not None:
            recorder.close()
    if recorder is not None and recorder.error:
        raise SafenavRuntimeError(f"--record {record}: {recorder.error}")
    return frames, stats


def _fly_episode(env, act, cfg, frames: list, recorder, obs) -> dict:
    """Step env 0 until its episode ends, appending rendered frames (and recording each step)."""
    stats: dict = {}
    for _ in range(cfg.max_episode_steps):
        action = act(obs)
        if recorder is not None:
            record_step(recorder, env, action)
        obs, _, term, trunc, info = env.step(action)
        if bool(term[0] or trunc[0]):
            if recorder is not None:
                record_step(recorder, env, None)
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
    return stats


def episode_scene(env, index: int = 0):
    """The :class:`~safenav.deploy.mcap_log.Scene` of env ``index``'s episode: its world's active
    pillars, the arena border, start and goal."""
    import dataclasses

    import numpy as np

    from safenav.deploy.mcap_log import Scene

    w, ns = int(env.world_idx[index]), env.n_static
    pillars = np.column_stack([env.pillar_xy[w, :ns].cpu().numpy(), env.pillar_half[w, :ns].cpu().numpy(),
                               env.pillar_height[w, :ns].cpu().numpy()]).astype(float)  # fmt: skip
    scene = Scene.for_env(env.cfg, env.goal[index].cpu().numpy(), env.start[index].cpu().numpy(),
                          goal_yaw=float(env.yaw[index]))  # fmt: skip
    return dataclasses.replace(scene, pillars=pillars)


def record_step(recorder, env, action, index: int = 0) -> None:
    """Record env ``index`` now (simulation time): its state, the range image it observed, the
    moving obstacles, and ``action`` (normalised, goal frame) as the world velocity it commands
    (None: no command, the episode's last state)."""
    from safenav.envs.dynamics import goal_frame_to_world
    from safenav.envs.world import CUBOID_HEIGHT, CYLINDER_HEIGHT

    cfg = env.cfg
    setpoint = None
    if action is not None:
        a = torch.as_tensor(action, dtype=torch.float32)[index].clamp(-1.0, 1.0) * cfg.v_max
        setpoint = goal_frame_to_world(a, env.cos_yaw[index], env.sin_yaw[index]).cpu().numpy()
    w, nd = int(env.world_idx[index]), env.n_dynamic
    pos, width = env.dyn_pos[w, :nd].cpu(), env.dyn_width[w, :nd].cpu()
    cuboid = env.dyn_is_cuboid[w, :nd].cpu()
    # cylinders stand on the ground; cuboids float, centred at their position
    z = torch.where(cuboid, pos[:, 2], torch.full_like(pos[:, 2], CYLINDER_HEIGHT / 2))
    height = torch.where(cuboid, CUBOID_HEIGHT, CYLINDER_HEIGHT)
    movers = torch.stack([pos[:, 0], pos[:, 1], z, width, height, cuboid.float()], -1)
    ranges = env._last_ranges[index].cpu().numpy() if env._last_ranges is not None else None
    recorder.record(float(env.steps[index]) * cfg.dt, env.pos[index].cpu().numpy(),
                    env.vel[index].cpu().numpy(), float(env.yaw[index]), setpoint=setpoint,
                    ranges=ranges, movers=movers.numpy())  # fmt: skip


__all__ = ["POLICIES", "episode_scene", "fly_frames", "record_step", "render_episode",
           "resolve_policy"]  # fmt: skip
