"""How hard is SafeNav-v1 itself? A privileged planner flies the validation episodes
(docs/csac-v1.md, "A privileged planner: how hard is the scenario?").

The planner (:class:`~safenav.envs.planner.OraclePlanner`, described in its module) reads the
simulator's true state; this script flies it on validation maps and writes the figures.
``privileged_range`` and ``sense="lidar"`` limit its view to what a policy's observation holds.

Validation maps only (the test and held-out seeds are refused). Run:
``.venv/bin/python experiments/oracle_planner.py --env-seeds 12345 12346 12347 12348
--episodes 104 [--horizon 20 --margin 0.1 --privileged-range 4 --forecast exact]
--json results/csac-v1/oracle/val.json``.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import math
import platform
import time
from pathlib import Path

import numpy as np
import torch

from safenav.common.jsonout import write_json
from safenav.envs.config import make_config
from safenav.envs.dynamics import goal_frame_to_world
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.planner import (  # noqa: F401 (re-exported for the experiments and tests)
    FAR,
    W_MARGIN,
    OracleConfig,
    OraclePlanner,
    beam_hits,
    geodesic_fields,
    mover_clearance,
    sample_field,
    to_action,
)
from safenav.experiments.evaluate import evaluate
from safenav.experiments.selection import RESERVED_SEEDS, VALIDATION_SEEDS


def scan_columns(env: SafeNavVectorEnv, ids: torch.Tensor) -> torch.Tensor:
    """World ``(x, y)`` ``(n, K, 2)`` of the flight shield's map-scan hits for envs ``ids``
    (``safenav.deploy.shield.map_scan_hits`` with the env's shield config: columns in the heading
    frame, whose column 0 lies along ``yaw``); scan beams without a hit are put ``FAR`` away."""
    from safenav.deploy.shield import ShieldConfig, map_scan_hits

    pos, yaw = env.pos[ids], env.yaw[ids]
    rel, valid, _, _ = map_scan_hits(env.heights, env.grid.origin, env.grid.size,
                                     env.cfg.grid_resolution, pos, yaw,
                                     ShieldConfig.for_env(env.cfg), env.world_idx[ids])  # fmt: skip
    world = goal_frame_to_world(rel, torch.cos(yaw)[:, None], torch.sin(yaw)[:, None])
    return torch.where(valid[..., None], pos[:, None, :2] + world[..., :2], FAR)


# ------------------------------------------------------------------ command line
SUMMARY = ("success_rate", "collision_rate", "timeout_rate", "collision_static_rate",
           "collision_dynamic_rate", "collision_bounds_rate", "mean_speed", "mean_time_to_goal",
           "mean_min_clearance", "detour_ratio")  # fmt: skip


def run(config: OracleConfig, env_seeds: list[int], episodes: int, preset: str = "paper",
        env_overrides: dict | None = None) -> dict:  # fmt: skip
    """Fly the oracle on ``episodes`` episodes of each validation map; per map and pooled."""
    per_map, pooled = {}, {k: [] for k in ("success", "collision", "timeout", "hit_static",
                                           "hit_dynamic", "out_of_bounds", "time", "mean_speed")}  # fmt: skip
    for seed in env_seeds:
        if seed in RESERVED_SEEDS:
            raise SystemExit(f"env seed {seed} is a test or held-out map: use validation maps "
                             f"({', '.join(map(str, VALIDATION_SEEDS))})")  # fmt: skip
        t0 = time.perf_counter()
        res = evaluate(
            OraclePlanner(config, scan=scan_columns if config.map_scan else None),
            make_config(preset, **(env_overrides or {})),
            env_seed=seed,
            episodes=episodes,
        )
        per_ep = res.pop("per_episode")
        per_map[str(seed)] = {**{k: res[k] for k in SUMMARY}, "wall_s": round(time.perf_counter() - t0, 1),
                              "per_episode": {k: per_ep[k] for k in pooled}}  # fmt: skip
        for k in pooled:
            pooled[k] += per_ep[k]
        m = per_map[str(seed)]
        print(f"  map {seed}: success {m['success_rate']:.3f} collision {m['collision_rate']:.3f} "
              f"timeout {m['timeout_rate']:.3f} ({m['wall_s']:.0f} s)", flush=True)  # fmt: skip
    a = {k: np.asarray(v) for k, v in pooled.items()}
    ok = a["success"] > 0.5
    total = {
        "episodes": len(ok),
        "success_rate": float(ok.mean()),
        "collision_rate": float((a["collision"] > 0.5).mean()),
        "timeout_rate": float((a["timeout"] > 0.5).mean()),
        "collision_static_rate": float((a["hit_static"] > 0.5).mean()),
        "collision_dynamic_rate": float((a["hit_dynamic"] > 0.5).mean()),
        "collision_bounds_rate": float((a["out_of_bounds"] > 0.5).mean()),
        "mean_speed": float(a["mean_speed"].mean()),
        "mean_time_to_goal": float(a["time"][ok].mean()) if ok.any() else math.nan,
    }
    return {"pooled": total, "per_map": per_map}


def main(argv: list[str] | None = None) -> dict:
    d = OracleConfig()
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--env-seeds", type=int, nargs="+", default=list(VALIDATION_SEEDS))
    ap.add_argument(
        "--episodes", type=int, default=104, help="per map (104 x 4 = 416, as validation)"
    )
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--horizon", type=int, default=d.horizon, help="control steps (10 Hz)")
    ap.add_argument("--headings", type=int, default=d.headings)
    ap.add_argument("--speeds", type=float, nargs="+", default=list(d.speeds))
    ap.add_argument("--climbs", type=float, nargs="+", default=list(d.climbs))
    ap.add_argument("--margin", type=float, default=d.margin, help="m beyond the UAV radius")
    ap.add_argument(
        "--mover-margin",
        type=float,
        default=d.mover_margin,
        help="m of extra margin from moving obstacles",
    )
    ap.add_argument("--w-clear", type=float, default=d.w_clear)
    ap.add_argument("--w-smooth", type=float, default=d.w_smooth)
    ap.add_argument(
        "--privileged-range",
        type=float,
        default=d.privileged_range,
        help="m: see pillars, wall and moving obstacles only this close (default: all)",
    )
    ap.add_argument("--progress", choices=("auto", "geodesic", "euclid"), default=d.progress)
    ap.add_argument("--forecast", choices=("constant", "exact"), default=d.forecast)
    ap.add_argument(
        "--sense",
        choices=("exact", "lidar"),
        default=d.sense,
        help="pillars and wall as exact geometry or as the range image's hit points",
    )
    ap.add_argument(
        "--fill-gaps",
        action="store_true",
        help="with --sense lidar: treat the space between neighbouring beams as solid",
    )
    ap.add_argument(
        "--memory",
        type=int,
        default=d.memory,
        help="with --sense lidar: range images remembered (1 = the current one)",
    )
    ap.add_argument(
        "--map-scan",
        action="store_true",
        help="with --sense lidar: also the flight shield's map-scan hits, as columns",
    )
    ap.add_argument(
        "--env",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="EnvConfig overrides of the preset (e.g. lidar_h_beams=72)",
    )
    ap.add_argument(
        "--causes",
        type=int,
        default=None,
        metavar="ENV_SEED",
        help="instead: sort the collisions of --episodes episodes of this validation "
        "map (experiments/collision_causes.py) and write them to --json",
    )
    ap.add_argument("--cruise", type=float, default=d.cruise,
                    help="m: altitude to hold until --cruise-until m from the goal")  # fmt: skip
    ap.add_argument("--cruise-until", type=float, default=d.cruise_until)
    ap.add_argument("--ignore-ground", action="store_true",
                    help="with --sense lidar: ground hits are not obstacles")  # fmt: skip
    ap.add_argument("--keep-band", action="store_true",
                    help="keep NavRL's altitude band (the height penalty's) as a margin")  # fmt: skip
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    config = OracleConfig(horizon=args.horizon, headings=args.headings, speeds=tuple(args.speeds),
                          climbs=tuple(args.climbs), margin=args.margin,
                          mover_margin=args.mover_margin, w_clear=args.w_clear,
                          w_smooth=args.w_smooth, privileged_range=args.privileged_range,
                          progress=args.progress, forecast=args.forecast, sense=args.sense,
                          memory=args.memory, fill_gaps=args.fill_gaps, cruise=args.cruise,
                          map_scan=args.map_scan,
                          cruise_until=args.cruise_until,
                          ignore_ground=args.ignore_ground, keep_band=args.keep_band)  # fmt: skip
    if args.causes is not None:
        if args.causes in RESERVED_SEEDS:
            raise SystemExit(f"env seed {args.causes} is a test or held-out map")
        from collision_causes import classify

        out = classify(f"oracle planner {dataclasses.asdict(config)}", args.episodes, args.causes,
                       planner=OraclePlanner(config, scan=scan_columns if config.map_scan else None))  # fmt: skip
        print(json.dumps(out["causes"]))
        if args.json:
            write_json(args.json, out)
        return out
    k = config.headings * len(config.speeds) * len(config.climbs) + 2
    print(f"oracle: {k} candidates x {config.horizon} steps, margin {config.margin} m, "
          f"range {config.privileged_range} m, {config.sense} sensing, {config.progress_kind} progress, "
          f"{config.forecast} forecast", flush=True)  # fmt: skip
    t0 = time.perf_counter()
    overrides = {}
    for item in args.env:
        key, _, value = item.partition("=")
        try:
            overrides[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            overrides[key] = value
    out = run(config, args.env_seeds, args.episodes, args.preset, overrides)
    p = out["pooled"]
    print(f"pooled ({p['episodes']} episodes): success {p['success_rate']:.3f} collision "
          f"{p['collision_rate']:.3f} (static {p['collision_static_rate']:.3f}, dynamic "
          f"{p['collision_dynamic_rate']:.3f}, bounds {p['collision_bounds_rate']:.3f}) timeout "
          f"{p['timeout_rate']:.3f}; mean speed {p['mean_speed']:.2f} m/s, time to goal "
          f"{p['mean_time_to_goal']:.1f} s; {time.perf_counter() - t0:.0f} s")  # fmt: skip
    settings = dataclasses.asdict(config)  # privileged_range inf (everything in view) -> null
    record = {"settings": {**settings, "progress_kind": config.progress_kind,
                           "candidates": k, "env_seeds": args.env_seeds, "episodes": args.episodes,
                           "preset": args.preset, "env_overrides": overrides, "threads": args.threads,
                           "machine": platform.node(), "date": time.strftime("%Y-%m-%d")},
              **out, "wall_s": round(time.perf_counter() - t0, 1)}  # fmt: skip
    if args.json:
        write_json(args.json, record)
        print(f"wrote {args.json}")
    return record


if __name__ == "__main__":
    main()
