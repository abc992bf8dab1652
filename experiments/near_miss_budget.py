"""How often trained policies come within a margin of an obstacle: the units of a near-miss budget.

A cost that counts the first near miss of an episode (``EnvConfig.near_miss_margin``, a named
departure from the paper's Eq. 3) makes the constraint's budget d a probability of a near miss per
episode. Before a run uses it, d must be set against what policies do: this flies each policy on
the validation maps (12345-12348, 100 episodes each; never the test or held-out maps) behind a
shield setting of ``experiments/shield_memory.py`` (the training shield ``1map-mover0.3`` by
default) and reports, for each margin, the share of episodes whose least clearance fell under it
(a collision with an obstacle counts: its clearance is <= 0).

    .venv/bin/python experiments/near_miss_budget.py --policies runs/mover/g995-s*.pt \\
        --margins 0.1 0.2 0.3 0.5 --out results/csac-v1/near-miss-budget

One JSON per (policy, setting, map) in OUT with the episodes' least clearances (a rerun skips those
that exist), then a table on stdout and in OUT/table.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from shield_memory import label, parse_setting

from safenav.algos.policy import load_policy
from safenav.common.jsonout import write_json
from safenav.deploy.shield import shield_for_memory
from safenav.experiments.evaluate import evaluate
from safenav.experiments.selection import VALIDATION_SEEDS


def near_miss_share(clearances: list[float], margin: float) -> float:
    """The share of episodes whose least clearance (m) fell under ``margin``."""
    return sum(c < margin for c in clearances) / len(clearances)


def fly(path: Path, setting: str, out: Path, episodes: int) -> tuple[list[float], float]:
    """The least clearance of each validation episode of one policy behind one shield setting,
    and the collision rate over them."""
    clearances, collisions = [], 0.0
    fn = None
    for seed in VALIDATION_SEEDS:
        f = out / f"{label(path)}-m{setting}-seed{seed}-{episodes}.json"
        if not f.exists():
            fn = fn or load_policy(path)
            memory, scan, mover, lag, brake, keep, _ = parse_setting(setting)
            shield = (
                None if memory == 0 else shield_for_memory(memory, scan, mover, lag, brake, keep)
            )
            r = evaluate(fn, fn.env_config(), env_seed=seed, episodes=episodes, shield=shield)
            write_json(f, {"policy": str(path), "setting": setting, "env_seed": seed,
                           "success_rate": r["success_rate"], "collision_rate": r["collision_rate"],
                           "min_clearance": r["per_episode"]["min_clearance"]})  # fmt: skip
        r = json.loads(f.read_text())
        clearances += r["min_clearance"]
        collisions += r["collision_rate"] * len(r["min_clearance"])
    return clearances, collisions / len(clearances)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policies", nargs="+", type=Path, required=True)
    ap.add_argument("--settings", nargs="+", default=["1map-mover0.3"],
                    help="shield settings as in experiments/shield_memory.py (0: no shield)")  # fmt: skip
    ap.add_argument("--margins", nargs="+", type=float, default=[0.1, 0.2, 0.3, 0.5])
    ap.add_argument("--episodes", type=int, default=100, help="episodes per validation map")
    ap.add_argument("--out", type=Path, default=Path("results/csac-v1/near-miss-budget"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    head = " | ".join(f"< {m:g} m" for m in args.margins)
    lines = [f"Share of validation episodes (maps {', '.join(map(str, VALIDATION_SEEDS))}, "
             f"{args.episodes} each) whose least clearance fell under the margin:", "",
             f"| policy | shield | collision | {head} |",
             "|---|---|---:|" + "---:|" * len(args.margins)]  # fmt: skip
    totals: dict[str, list[list[float]]] = {}
    for setting in args.settings:
        for path in args.policies:
            c, collision = fly(path, setting, args.out, args.episodes)
            shares = [collision] + [near_miss_share(c, m) for m in args.margins]
            totals.setdefault(setting, []).append(shares)
            lines.append(
                f"| {label(path)} | {setting} | " + " | ".join(f"{s:.3f}" for s in shares) + " |"
            )
            print(lines[-1], flush=True)
    for setting, rows in totals.items():
        mean = [sum(col) / len(col) for col in zip(*rows, strict=True)]
        lines.append(
            f"| mean of {len(rows)} | {setting} | " + " | ".join(f"{s:.3f}" for s in mean) + " |"
        )
    (args.out / "table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
