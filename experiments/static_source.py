"""Does a policy trained on the drawn pillar list fly on the list its height map shows?

Policies with a ``static`` entry (``EnvConfig.static_tracked``) trained with the drawn footprints
(``static_source = "exact"``) fly the same validation episodes twice: with the drawn list and with
the list the height map shows (``static_source = "map"``:
:func:`safenav.envs.sensors.map_footprints`, what the onboard runtime builds). Each flies behind its
own flight shield, as it is chosen and reported. Per policy and pooled: success / collision /
timeout of both, and the paired difference (map − exact) with a 95 % bootstrap interval over
episodes (``experiments.stats.bootstrap_ci``). Validation maps only: the test and held-out scenarios
are refused.

    .venv/bin/python experiments/static_source.py results/csac-v1/levers/policies/static10-s1/step_001000192.pt \
        ... --json results/csac-v1/levers/static-source.json
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from safenav.common.jsonout import write_json
from safenav.experiments.evaluate import evaluate
from safenav.experiments.flight import resolve_policy
from safenav.experiments.selection import RESERVED_SEEDS, VALIDATION_SEEDS, own_shield
from safenav.experiments.stats import bootstrap_ci

SOURCES = ("exact", "map")


def fly(path: Path, env_seeds: list[int], episodes: int) -> dict:
    fn, cfg = resolve_policy(path, "checkpoint", "cpu")
    if cfg is None or not cfg.static_tracked:
        raise SystemExit(f"{path}: not a SafeNav policy with a static entry (static_tracked > 0)")
    out: dict = {"policy": str(path), "trained_with": cfg.static_source}
    for source in SOURCES:
        success, collision = [], []
        for seed in env_seeds:
            res = evaluate(fn, cfg.replace(static_source=source), env_seed=seed,
                           episodes=episodes, shield=own_shield(fn))  # fmt: skip
            success += res["per_episode"]["success"]
            collision += res["per_episode"]["collision"]
        out[source] = {"success": [bool(s) for s in success],
                       "collision": [bool(c) for c in collision]}  # fmt: skip
    return out


def paired(rows: list[dict], key: str) -> dict:
    exact = np.concatenate([np.asarray(r["exact"][key], float) for r in rows])
    mapped = np.concatenate([np.asarray(r["map"][key], float) for r in rows])
    diff = mapped - exact
    return {"exact": float(exact.mean()), "map": float(mapped.mean()), "diff": float(diff.mean()),
            "ci95": bootstrap_ci(lambda x, axis: x.mean(axis=axis), diff),
            "episodes": int(diff.size)}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("policies", type=Path, nargs="+", help="checkpoints or policy files")
    ap.add_argument("--env-seeds", type=int, nargs="+", default=list(VALIDATION_SEEDS))
    ap.add_argument("--episodes", type=int, default=100, help="per map")
    ap.add_argument("--json", type=Path, help="write the episodes and the summary here")
    args = ap.parse_args(argv)
    if set(args.env_seeds) & RESERVED_SEEDS:
        ap.error(f"env seeds {sorted(set(args.env_seeds) & RESERVED_SEEDS)} are test or held-out "
                 f"scenarios; use validation maps ({', '.join(map(str, VALIDATION_SEEDS))})")  # fmt: skip
    if args.episodes < 1:
        ap.error("--episodes must be >= 1")
    torch.set_num_threads(1)
    rows = []
    print("| policy | exact: success / collision | map: success / collision |\n|---|---|---|")
    for path in args.policies:
        r = fly(path, args.env_seeds, args.episodes)
        rows.append(r)
        e, m = ({k: np.mean(r[s][k]) for k in ("success", "collision")} for s in SOURCES)
        print(f"| `{path}` | {e['success']:.3f} / {e['collision']:.3f} | "
              f"{m['success']:.3f} / {m['collision']:.3f} |", flush=True)  # fmt: skip
    summary = {k: paired(rows, k) for k in ("success", "collision")}
    for k, s in summary.items():
        print(f"pooled {k}: exact {s['exact']:.3f}, map {s['map']:.3f}, map - exact "
              f"{s['diff']:+.3f} (95 % CI {s['ci95'][0]:+.3f} to {s['ci95'][1]:+.3f}, "
              f"{s['episodes']} paired episodes)")  # fmt: skip
    if args.json:
        write_json(args.json, {"env_seeds": args.env_seeds, "episodes_per_map": args.episodes,
                               "summary": summary, "policies": rows})  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
