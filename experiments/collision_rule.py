"""The same policies under both collision rules (docs/csac-v1.md, "The paper's collision rule"):
``body``, the UAV's 0.3 m sphere against the obstacles' geometry (SafeNav's), and ``navrl``,
NavRL's rule behind the paper's figures (a static collision only where a range-image beam reads
it). Validation maps first (100 episodes each), then the test scenario (200, a report only).
Each flight is one ``safenav eval --collision-rule RULE --json`` file in OUT, reused on a rerun;
the summary goes to OUT/summary.json and a markdown table to stdout.

    .venv/bin/python experiments/collision_rule.py checkpoints/csac-maxcost-crashloss-s1.pt checkpoints/csac-v1-rc100-s2.pt
    # ~7 min on one thread; OUT = results/csac-v1/collision-rule
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from safenav.common.jsonout import write_json
from safenav.experiments.selection import TEST_SEED, VALIDATION_SEEDS

RULES = ("body", "navrl")
KEYS = ("success_rate", "collision_rate", "timeout_rate", "collision_static_rate",
        "collision_dynamic_rate")  # fmt: skip


def flight(policy: Path, rule: str, seed: int, episodes: int, out: Path) -> dict:
    """One ``safenav eval`` flight, from its JSON file when a run left it."""
    label = "test" if seed == TEST_SEED else str(seed)
    path = out / f"{policy.stem}-{rule}-{label}.json"
    if not path.exists():
        cmd = [sys.executable, "-m", "safenav", "eval", str(policy), "--env-seed", str(seed),
               "--episodes", str(episodes), "--collision-rule", rule, "--json", str(path)]  # fmt: skip
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
    return json.loads(path.read_text())


def pooled(results: list[dict]) -> dict:
    """The rates of several flights, weighted by their episodes."""
    n = sum(r["episodes"] for r in results)
    return {"episodes": n, **{k: sum(r[k] * r["episodes"] for r in results) / n for k in KEYS}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("policies", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, default=Path("results/csac-v1/collision-rule"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {}
    for policy in args.policies:
        for rule in RULES:  # validation for every policy and rule before any test flight
            val = [flight(policy, rule, s, 100, args.out) for s in VALIDATION_SEEDS]
            summary.setdefault(policy.stem, {})[rule] = {"validation": pooled(val)}
    for policy in args.policies:
        for rule in RULES:
            test = flight(policy, rule, TEST_SEED, 200, args.out)
            summary[policy.stem][rule]["test"] = pooled([test])
    write_json(args.out / "summary.json", summary)
    print("| policy | maps | rule | success | collision (static / moving) | timeout |")
    print("|---|---|---|---:|---:|---:|")
    for name, rules in summary.items():
        for maps in ("validation", "test"):
            for rule in RULES:
                r = rules[rule][maps]
                print(f"| `{name}` | {maps} ({r['episodes']}) | {rule} | {r['success_rate']:.3f} "
                      f"| {r['collision_rate']:.3f} ({r['collision_static_rate']:.3f} / "
                      f"{r['collision_dynamic_rate']:.3f}) | {r['timeout_rate']:.3f} |")  # fmt: skip


if __name__ == "__main__":
    main()
