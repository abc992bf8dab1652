"""``safenav fly --demo``: start the vehicle simulator, fly a test episode, summarise, draw a GIF."""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import ImageDraw

from safenav.envs.config import EnvConfig, make_config
from safenav.envs.nav import fixed_scenario
from safenav.envs.world import generate_world
from safenav.errors import SafenavError

log = logging.getLogger("safenav.deploy.demo")


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A currently free port on 127.0.0.1 (UDP or TCP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def sim_vehicle_command(*args: str) -> list[str]:
    """The command line of ``safenav sim-vehicle ARGS`` with this interpreter."""
    return [sys.executable, "-c", "from safenav.cli import main; main()", "sim-vehicle", *args]


@contextlib.contextmanager
def sim_vehicle_process(*args: str, ready_timeout: float = 60.0):
    """Run ``safenav sim-vehicle ARGS`` in a subprocess until the block ends; yields the process
    once it has printed its ready line."""
    proc = subprocess.Popen(
        sim_vehicle_command(*args), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        if "sim-vehicle:" not in line:
            proc.kill()
            raise SafenavError(f"sim-vehicle did not start (exit {proc.poll()}): {line.strip()!r}")
        log.info("%s", line.strip())
        yield proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()


def resolve_onnx(
    policy: Path | None, checkpoint: Path, scripted: bool, cfg: EnvConfig, tmp: Path
) -> Path:
    """The ONNX policy to fly: ``policy`` as given, the scripted actor, or ``checkpoint`` exported."""
    from safenav.deploy.export import export_onnx, load_actor

    if policy is not None:
        return policy
    out = tmp / "policy.onnx"
    if scripted:
        from safenav.deploy.scripted import GoToGoalActor

        export_onnx(GoToGoalActor(cfg), cfg, out, checkpoint="scripted:GoToGoalActor")
        return out
    if not checkpoint.exists():
        raise SafenavError(f"{checkpoint} not found: train it (safenav train --algo csac ...), pass "
                           "--checkpoint PATH or --policy policy.onnx, or fly --scripted")  # fmt: skip
    actor, pcfg = load_actor(checkpoint)
    export_onnx(actor, pcfg, out, checkpoint=str(checkpoint))
    return out


def run_demo(
    policy: Path | None = None,
    checkpoint: Path = Path("checkpoints/csac.pt"),
    scripted: bool = False,
    preset: str = "paper",
    episode: int = 0,
    rate: float = 20.0,
    shield: bool = False,
    shield_memory: int | None = None,
    shield_map: bool = False,
    shield_mover_margin: float = 0.0,
    shield_brake: bool = False,
    gif: Path | None = Path("flight.gif"),
    max_flight_time: float = 120.0,
    world_seed: int = 1,
    record: Path | None = None,
    planner_filter: bool = False,
) -> dict[str, Any]:
    """Fly test episode ``episode`` of ``preset`` (world ``world_seed``) against a simulated PX4;
    ``record``: write the flight's MCAP log there (:mod:`safenav.deploy.mcap_log`, with the
    simulator's pillars in ``/safenav/map``); ``shield_memory``: the shield's memory in range
    images (default: 1 with ``shield``, the memoryless shield; see ``RuntimeConfig.for_flight``);
    ``shield_map``: with ``shield``, the map scan too; ``shield_mover_margin``: with ``shield``,
    metres more clearance from moving obstacles; ``shield_brake``: the braking cap;
    ``planner_filter``: the planner filter after the shield (``RuntimeConfig.planner_filter``)."""
    from safenav.deploy.export import OnnxPolicy, load_sidecar
    from safenav.deploy.fly import FlightAborted, FlightController, FlyConfig, MavsdkLink
    from safenav.deploy.runtime import OnboardRuntime, RuntimeConfig

    memory = max(1, shield_memory or 1) if shield else 0  # range images; 0: no shield
    cfg = make_config(preset)
    starts, goals = fixed_scenario(cfg, world_seed, episode + 1)
    start, goal = starts[episode].numpy().astype(float), goals[episode].numpy().astype(float)
    with tempfile.TemporaryDirectory(prefix="safenav-fly-") as tmp:
        onnx = resolve_onnx(policy, checkpoint, scripted, cfg, Path(tmp))
        _, pcfg = load_sidecar(onnx)
        from safenav.deploy.onboard_filter import check_planner_filter

        what = "scripted" if scripted else str(policy or checkpoint)
        check_planner_filter(planner_filter, pcfg, what)
        torch.set_num_threads(1)  # the runtime is single-threaded by design
        port, pport = free_port(), free_port(socket.SOCK_STREAM)
        with sim_vehicle_process(
            "--preset",
            preset,
            "--world-seed",
            str(world_seed),
            "--episode",
            str(episode),
            "--connect",
            f"127.0.0.1:{port}",
            "--perception-port",
            str(pport),
            "--quiet",
        ):
            runtime = OnboardRuntime(
                OnnxPolicy(onnx),
                pcfg,
                RuntimeConfig.for_flight(
                    pcfg,
                    memory,
                    rate,
                    shield_map and shield,
                    shield_mover_margin if shield else 0.0,
                    shield_brake and shield,
                    planner_filter,
                ),
            )
            link = MavsdkLink(f"udpin://127.0.0.1:{port}")
            recorder = None
            if record is not None:
                from safenav.deploy.mcap_log import McapRecorder, Scene

                recorder = McapRecorder(record, Scene.for_env(cfg, goal, start, world=generate_world(cfg, world_seed)),
                                        metadata={"verb": "fly --demo", "preset": preset, "world_seed": world_seed,
                                                  "episode": episode, "rate_hz": rate, "shield": shield, "shield_memory": memory, "shield_map": shield_map and shield,
                                                  "policy": str(policy) if policy else ("scripted" if scripted else str(checkpoint))})  # fmt: skip
            ctl = FlightController(runtime, link, FlyConfig(
                goal=tuple(goal), rate_hz=rate, takeoff_altitude=max(0.5, float(start[2])),
                goal_tolerance=cfg.goal_tolerance, max_flight_s=max_flight_time,
            ), perception=("127.0.0.1", pport), recorder=recorder)  # fmt: skip
            t0 = time.monotonic()
            aborted = None
            try:
                flight = ctl.fly()
            except FlightAborted as err:
                err.summary = {**ctl.log.summary(), "collisions": ctl.log.truth.get("collisions")}
                aborted = err
            finally:
                link.close()
                if recorder is not None:
                    recorder.close()  # never raises: a failure is in recorder.error
            wall = time.monotonic() - t0
    if aborted is not None:  # an aborted flight is one to watch too; the link is closed first
        if gif is not None and ctl.snapshots:
            try:
                render_flight_gif(gif, cfg, world_seed, ctl.snapshots, start, goal)
                aborted.summary["gif"] = str(gif)
            except Exception as gif_err:  # noqa: BLE001 -- the abort is what to report
                log.warning("no flight GIF: %s", gif_err)
        raise aborted
    truth = flight.truth
    summary = {
        "reached_goal": flight.reached_goal,
        "collisions": int(truth.get("collisions", -1)),
        "collisions_static": int(truth.get("collisions_static", -1)),
        "collisions_dynamic": int(truth.get("collisions_dynamic", -1)),
        "collisions_border": int(truth.get("collisions_border", -1)),
        "flight_time_s": round(flight.flight_time_s, 2),
        "min_clearance_m": round(float(truth.get("min_clearance", math.nan)), 3),
        "scenario": {"preset": preset, "world_seed": world_seed, "episode": episode,
                     "start": [round(x, 3) for x in start], "goal": [round(x, 3) for x in goal]},
        "policy": str(policy) if policy else ("scripted" if scripted else str(checkpoint)),
        "shield": shield, "shield_memory": memory, "shield_map": shield_map and shield, "shield_mover_margin": shield_mover_margin if shield else 0.0, "shield_brake": shield_brake and shield, "planner_filter": planner_filter, "rate_hz": rate, "wall_time_s": round(wall, 1),
        **{k: v for k, v in flight.summary().items() if k not in ("reached_goal", "flight_time_s")},
    }  # fmt: skip
    if gif is not None and ctl.snapshots:
        render_flight_gif(gif, cfg, world_seed, ctl.snapshots, start, goal)
        summary["gif"] = str(gif)
    if recorder is not None:
        summary["record"] = str(record)
        if recorder.error:
            summary["record_error"] = recorder.error
    return summary


def render_flight_gif(path: Path, cfg: EnvConfig, world_seed: int, snapshots: list[dict], start, goal,
                      size: int = 560, fps: int = 5) -> None:  # fmt: skip
    """Top-down GIF of a flight from the simulator's truth snapshots (the arena's wall, pillars,
    moving obstacles, the UAV's trail, start and goal), in the style of the env's renderer, with
    its legend and scale bar."""
    from safenav.envs.render import (
        PILLAR,
        PILLAR_LOW,
        START,
        TRAIL,
        UAV,
        decorate,
        draw_goal,
        draw_mover,
        map_canvas,
        write_gif,
    )

    world = generate_world(cfg, world_seed)
    ns, nd = cfg.active_static, cfg.active_dynamic
    base, px, scale = map_canvas(cfg.map_size, size)
    alt = float(np.median([s["pos"][2] for s in snapshots]))
    draw = ImageDraw.Draw(base)
    for (x, y), h, top in zip(
        world.pillar_xy[:ns], world.pillar_half[:ns], world.pillar_height[:ns], strict=True
    ):
        x0, y0 = px(x - h, y + h)
        x1, y1 = px(x + h, y - h)
        draw.rectangle([x0, y0, x1, y1], fill=PILLAR if top > alt else PILLAR_LOW)
    sx, sy = px(start[0], start[1])
    draw.rectangle([sx - 4, sy - 4, sx + 4, sy + 4], outline=START, width=2)
    draw_goal(draw, *px(goal[0], goal[1]), max(cfg.goal_tolerance * scale, 4))
    frames, trail = [], []
    for snap in snapshots:
        img = base.copy()
        d = ImageDraw.Draw(img)
        for (x, y), wd, cub in zip(snap.get("dyn_pos", [])[:nd], world.dyn_width[:nd], world.dyn_is_cuboid[:nd],
                                   strict=False):  # fmt: skip
            draw_mover(d, *px(x, y), wd / 2 * scale, bool(cub))
        p = snap["pos"]
        trail.append(px(p[0], p[1]))
        if len(trail) > 1:
            d.line(trail, fill=TRAIL, width=2)
        ux, uy = px(p[0], p[1])
        ur = max(cfg.uav_radius * scale, 3)
        d.ellipse([ux - ur, uy - ur, ux + ur, uy + ur], fill=UAV)
        status = (f"t={snap['t'] - snapshots[0]['t']:5.1f}s  z={p[2]:.2f}m  {snap.get('mode', '')}  "
                  f"collisions={snap.get('collisions', 0)}")  # fmt: skip
        frames.append(decorate(img, status, scale))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_gif(path, frames, fps)


__all__ = [
    "free_port",
    "render_flight_gif",
    "resolve_onnx",
    "run_demo",
    "sim_vehicle_command",
    "sim_vehicle_process",
]
