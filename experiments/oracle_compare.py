"""Two sets of `experiments/oracle_planner.py --json` or `safenav eval --json` files (a planner
against a planner, or a learned policy against the planner) compared on the same episodes: pooled
success / collision / timeout of each, and per rate the paired difference (B - A) with its 95 %
bootstrap CI over episodes and McNemar's exact test (``safenav.experiments.stats``). The files
are matched by map (env seed) and each map's episodes by index, so both sets must have flown the
same maps with the same number of episodes (the planner's episodes are fixed by the map seed).

    .venv/bin/python experiments/oracle_compare.py \\
        results/csac-v1/oracle/h200-mem/mem10-1234?.json \\
        --against results/csac-v1/oracle/beams72/beams72-1234?.json [--json OUT]
    safenav eval POLICY --env-seed 12345 --episodes 36 --json policy-12345.json   # one per map
    .venv/bin/python experiments/oracle_compare.py results/csac-v1/oracle/h200-mem/mem10-1234?.json \\
        --against policy-1234?.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from safenav.common.jsonout import write_json
from safenav.experiments.stats import bootstrap_ci, mcnemar_exact

RATES = ("success", "collision", "timeout")


def episodes(paths: list[str]) -> dict[str, dict[str, list[float]]]:
    """``{map seed: per_episode}`` over the files (a map in two files is an error): the planner's
    ``per_map`` entries, or the one map of a ``safenav eval --json`` file."""
    out: dict[str, dict[str, list[float]]] = {}
    for path in paths:
        data = json.loads(Path(path).read_text())
        maps = data.get("per_map") or {str(data["env_seed"]): data}
        for seed, entry in maps.items():
            if seed in out:
                raise SystemExit(f"map {seed} appears twice (in {path})")
            out[seed] = entry["per_episode"]
    return out


def paired(a: dict, b: dict) -> dict:
    """Pooled rates of both sets and, per rate, the paired difference B - A on their episodes."""
    if sorted(a) != sorted(b):
        raise SystemExit(f"the sets fly different maps: {sorted(a)} vs {sorted(b)}")
    for seed in a:
        if len(a[seed]["success"]) != len(b[seed]["success"]):
            raise SystemExit(f"map {seed}: {len(a[seed]['success'])} vs "
                             f"{len(b[seed]['success'])} episodes")  # fmt: skip
    maps = sorted(a)
    result: dict = {"maps": maps, "episodes": sum(len(a[s]["success"]) for s in maps)}
    for rate in RATES:
        xa = np.concatenate([a[s][rate] for s in maps]).astype(bool)
        xb = np.concatenate([b[s][rate] for s in maps]).astype(bool)
        diff = xb.astype(float) - xa.astype(float)
        result[rate] = {
            "a": float(xa.mean()), "b": float(xb.mean()), "difference": float(diff.mean()),
            "ci95": bootstrap_ci(lambda x, axis: x.mean(axis=axis), diff),
            "mcnemar": mcnemar_exact(xa, xb),  # only_a: episodes where only A had the event
            "both": int((xa & xb).sum()),  # episodes where both had it
        }  # fmt: skip
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "files", nargs="+", help="set A: oracle_planner.py or safenav eval --json files"
    )
    parser.add_argument("--against", nargs="+", required=True, help="set B: the same maps")
    parser.add_argument("--json", help="write the comparison here")
    args = parser.parse_args(argv)
    result = paired(episodes(args.files), episodes(args.against))
    print(f"{result['episodes']} paired episodes on maps {', '.join(result['maps'])}")
    for rate in RATES:
        r = result[rate]
        lo, hi = r["ci95"] or (float("nan"), float("nan"))
        m = r["mcnemar"]
        print(f"  {rate:9s} A {r['a']:.3f}  B {r['b']:.3f}  B-A {r['difference']:+.3f} "
              f"(95 % CI {lo:+.3f} to {hi:+.3f}; both {r['both']}, only B {m['only_b']}, only A "
              f"{m['only_a']}, McNemar p = {m['p_value']:.3f})")  # fmt: skip
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
