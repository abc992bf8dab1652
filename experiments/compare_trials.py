"""Two `safenav reproduce` labels compared on the same test episodes, from their committed trial
files: per rate (success, collision) the difference of the per-seed means with its 95 %
bootstrap CI (scipy) and McNemar's exact test on the paired test episodes of the seeds both have
(``safenav.experiments.stats.compare``, the statistics of the paper comparison's results.json).

    .venv/bin/python experiments/compare_trials.py results/csac_shielded/trials/csac_shielded \\
        results/csac-maxcost-crashloss/trials/csac [--json OUT]

Each argument is a trial-file prefix: ``PREFIX-s<seed>.json`` are that label's trials, or, for
runs ended by ``experiments/finish_runs.py``, ``PREFIX-s<seed>-final.json`` (e.g.
``results/csac-v1/levers/shieldml``). ``--seeds`` keeps only the seeds named, in both labels:

    .venv/bin/python experiments/compare_trials.py results/csac-v1/levers/shieldml \\
        results/csac_shielded/trials/csac_shielded --seeds 1 5 2
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from safenav.common.jsonout import write_json
from safenav.experiments.stats import compare, outcomes_string


def trials(prefix: str) -> list[dict]:
    """The trial records ``PREFIX-s<seed>.json`` (or records made from ``PREFIX-s<seed>-final.json``
    reports), by seed."""
    base = Path(prefix)
    if found := files_by_seed(base, ".json"):
        return [json.loads(p.read_text()) for _, p in found]
    if finals := files_by_seed(base, "-final.json"):
        return [final_record(seed, json.loads(p.read_text())) for seed, p in finals]
    raise SystemExit(f"no trial files {prefix}-s<seed>.json or {prefix}-s<seed>-final.json")


def files_by_seed(base: Path, suffix: str) -> list[tuple[int, Path]]:
    """``(seed, path)`` of the files ``BASE-s<seed>SUFFIX``, by seed."""
    pattern = rf"{re.escape(base.name)}-s(\d+){re.escape(suffix)}"
    return sorted((int(m[1]), p) for p in base.parent.glob(f"{base.name}-s*{suffix}")
                  if (m := re.fullmatch(pattern, p.name)))  # fmt: skip


def final_record(seed: int, final: dict) -> dict:
    """A trial-like record from a ``final.json`` report: test rates and per-episode outcomes."""
    test = final["test"]
    return {"seed": seed, "success_rate": test["success_rate"],
            "collision_rate": test["collision_rate"],
            "test_outcomes": outcomes_string(test.get("per_episode"))}  # fmt: skip


def table(a_label: str, b_label: str, result: dict) -> list[str]:
    """The comparison as markdown rows."""
    rows = [f"| {a_label} minus {b_label} | difference of seed means (95 % bootstrap CI) | McNemar "
            "exact p (episodes only A / only B) |", "|---|---|---|"]  # fmt: skip
    for key, entry in result.items():
        d, m = entry["mean_difference"], entry["mcnemar"]
        means = "- (fewer than 2 seeds)" if d is None else (
            f"{d['difference']:+.3f} ({d['ci95'][0]:+.3f} to {d['ci95'][1]:+.3f})")  # fmt: skip
        paired = "-" if m is None else f"{m['p_value']:.2g} ({m['only_a']} / {m['only_b']})"
        rows.append(f"| {key} | {means} | {paired} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "a", help="trial-file prefix of label A, e.g. results/csac-maxcost-crashloss/trials/csac"
    )
    parser.add_argument("b", help="trial-file prefix of label B")
    parser.add_argument("--json", type=Path, default=None, help="write the comparison here too")
    parser.add_argument("--seeds", type=int, nargs="+", default=None,
                        help="compare only these seeds (both labels)")  # fmt: skip
    args = parser.parse_args()
    a, b = trials(args.a), trials(args.b)
    if args.seeds:
        a = [r for r in a if r["seed"] in args.seeds]
        b = [r for r in b if r["seed"] in args.seeds]
    result = compare(a, b)
    print(f"A: {args.a} seeds {[r['seed'] for r in a]}; B: {args.b} seeds {[r['seed'] for r in b]}")
    print("\n".join(table(Path(args.a).name, Path(args.b).name, result)))
    if args.json:
        write_json(args.json, {"a": args.a, "b": args.b, **result})


if __name__ == "__main__":
    main()
