"""Where policies fly: their altitude far from the goal, and what they collide with.

NavRL's height penalty holds a policy in the start-goal altitude band, where the tops of low
pillars fall below the lowest beam as the UAV closes in (docs/csac-v1.md, "Altitude, not
memory"); the ``noheight`` and ``cruise06`` levers change that penalty. This script flies each
policy on one validation map (the episodes of ``safenav eval``, deterministic actions) and reports,
over the steps flown more than ``--far`` metres (horizontally) from the goal, the altitude's
mean, 10/50/90th percentiles and the share below 1 m, beside success, collision and what the
collisions were with. Validation maps only: the test and held-out scenarios are refused.

    .venv/bin/python experiments/altitude_profile.py runs/levers/cruise06-s2/policies/*.pt \\
        checkpoints/csac-v1-rc100-s2.pt --env-seed 12345 --episodes 104 --json alt.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from safenav.common.jsonout import write_json
from safenav.experiments.evaluate import evaluate
from safenav.experiments.flight import resolve_policy
from safenav.experiments.selection import RESERVED_SEEDS, VALIDATION_SEEDS


class AltitudeRecorder:
    """Wraps a policy; before each action records every env's altitude and whether it is farther
    than ``far`` metres from its goal (horizontally)."""

    needs_env = True

    def __init__(self, policy, far: float):
        self.policy, self.far = policy, far
        self.z: list[torch.Tensor] = []
        self.is_far: list[torch.Tensor] = []

    def __call__(self, obs, env):
        horizontal = (env.goal[:, :2] - env.pos[:, :2]).norm(dim=-1)
        self.z.append(env.pos[:, 2].clone())
        self.is_far.append(horizontal > self.far)
        return self.policy(obs)


def profile(path: Path, env_seed: int, episodes: int, far: float) -> dict:
    fn, cfg = resolve_policy(path, "checkpoint", "cpu")
    if cfg is None:
        raise SystemExit(f"{path}: not a SafeNav policy")
    rec = AltitudeRecorder(fn, far)
    res = evaluate(rec, cfg, env_seed=env_seed, episodes=episodes)
    z, is_far = torch.stack(rec.z), torch.stack(rec.is_far)  # (steps, episodes)
    # Only the steps each episode flew (ended episodes hover with zero actions until all end).
    flown = torch.tensor(res["per_episode"]["time"]) / cfg.dt
    flying = torch.arange(z.shape[0])[:, None] < flown.round()[None, :]
    zf = z[is_far & flying].numpy()
    p10, p50, p90 = np.percentile(zf, [10, 50, 90]) if zf.size else (np.nan,) * 3
    keys = ("success_rate", "collision_rate", "timeout_rate", "collision_static_rate",
            "collision_dynamic_rate", "collision_bounds_rate")  # fmt: skip
    return {"policy": str(path), "env_seed": env_seed, "episodes": episodes, "far_m": far,
            **{k: res[k] for k in keys}, "flown_steps": int(flying.sum()), "far_steps": int(zf.size),
            "far_z_mean": float(zf.mean()) if zf.size else float("nan"),
            "far_z_p10": float(p10), "far_z_p50": float(p50), "far_z_p90": float(p90),
            "far_below_1m": float((zf < 1.0).mean()) if zf.size else float("nan")}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("policies", type=Path, nargs="+", help="checkpoints or policy files")
    ap.add_argument("--env-seed", type=int, default=VALIDATION_SEEDS[0], help="a validation map")
    ap.add_argument("--episodes", type=int, default=104)
    ap.add_argument("--far", type=float, default=5.0, help="horizontal distance to the goal (m)")
    ap.add_argument("--json", type=Path, help="write the rows here")
    args = ap.parse_args(argv)
    if args.env_seed in RESERVED_SEEDS:
        ap.error(f"env seed {args.env_seed} is a test or held-out scenario; use a validation "
                 f"map ({', '.join(map(str, VALIDATION_SEEDS))})")  # fmt: skip
    if args.episodes < 1 or not args.far >= 0:
        ap.error("--episodes must be >= 1 and --far >= 0")
    torch.set_num_threads(min(2, torch.get_num_threads()))
    rows = []
    print("| policy | success / collision / timeout | collision static / moving / bounds | "
          "z far from goal: mean (p10-p50-p90) | below 1 m |\n|---|---|---|---|---|")  # fmt: skip
    for path in args.policies:
        r = profile(path, args.env_seed, args.episodes, args.far)
        rows.append(r)
        print(f"| `{path}` | {r['success_rate']:.3f} / {r['collision_rate']:.3f} / "
              f"{r['timeout_rate']:.3f} | {r['collision_static_rate']:.3f} / "
              f"{r['collision_dynamic_rate']:.3f} / {r['collision_bounds_rate']:.3f} | "
              f"{r['far_z_mean']:.2f} ({r['far_z_p10']:.2f}-{r['far_z_p50']:.2f}-"
              f"{r['far_z_p90']:.2f}) | {r['far_below_1m']:.2f} |", flush=True)  # fmt: skip
    if args.json:  # strict JSON: null where no step was that far from the goal
        write_json(args.json, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
