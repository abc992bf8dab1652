"""The planner filter's report (docs/csac-v1.md, "A model-predictive safety filter at flight
time"): the default recipe's five policies on the test scenario and the held-out maps, behind
their flight shield and behind it then the filter, from the files of ``shield_memory.py --maps
test`` / ``--maps heldout`` in DIR.

    .venv/bin/python experiments/filter_report.py results/csac-v1/filter \\
        --setting 1map-mover0.3-brake-filter --trials results/csac/trials

Per policy and pooled (1,000 test episodes, Wilson 95 % CIs, scipy), McNemar's exact test on
the paired test episodes (the same starts and goals behind either), and the held-out maps
(seeds 2-6 x 200): the filter's files, beside the trial records' ``heldout`` for the shield
alone (the same flights: ``safenav reproduce`` reports them behind the same flight shield).
Writes DIR/report-SETTING.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from safenav.experiments.aggregate import confidence_intervals
from safenav.experiments.selection import HELDOUT_SEEDS, TEST_SEED
from safenav.experiments.stats import mcnemar_exact

POLICIES = {"csac": 1, "default-s2": 2, "default-s3": 3, "default-s4": 4, "default-s5": 5}
"""Label in shield_memory.py's files -> training seed (checkpoints/csac.pt is seed 1)."""
BASE = "1map-mover0.3-brake"


def wilson(k: int, n: int) -> str:
    low, high = confidence_intervals([(k / n, n)])["wilson"]
    return f"{k / n:.3f} ({low:.3f}-{high:.3f})"


def load(directory: Path, label: str, setting: str, seed: int) -> dict:
    return json.loads((directory / f"{label}-m{setting}-seed{seed}-200.json").read_text())


def report(directory: Path, setting: str, trials: Path) -> list[str]:
    lines = [f"Test scenario (env seed {TEST_SEED}, 200 episodes a policy): `{BASE}` (the flight "
             f"shield) against `{setting}`", "",
             "| policy (seed) | success | collision | timeout | success, filter | collision, "
             "filter | timeout, filter | planner's steps |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    pooled = {BASE: "", setting: ""}
    for label, seed in POLICIES.items():
        a, b = load(directory, label, BASE, TEST_SEED), load(directory, label, setting, TEST_SEED)
        pooled[BASE] += a["outcomes"]
        pooled[setting] += b["outcomes"]
        lines.append(f"| {label} ({seed}) | {a['success_rate']:.3f} | {a['collision_rate']:.3f} | "
                     f"{a['timeout_rate']:.3f} | {b['success_rate']:.3f} | "
                     f"{b['collision_rate']:.3f} | {b['timeout_rate']:.3f} | "
                     f"{b.get('filter_override_share', float('nan')):.3f} |")  # fmt: skip
    n = len(pooled[BASE])
    row = [wilson(pooled[s].count(ch), n) for ch in "SCT" for s in (BASE, setting)]
    lines += ["", f"Pooled ({n} episodes, Wilson 95 % CI):", "",
              "| | shield | shield + filter |", "|---|---:|---:|",
              f"| success | {row[0]} | {row[1]} |", f"| collision | {row[2]} | {row[3]} |",
              f"| timeout | {row[4]} | {row[5]} |", ""]  # fmt: skip
    for name, ch in (("success", "S"), ("collision", "C")):
        m = mcnemar_exact([c == ch for c in pooled[setting]], [c == ch for c in pooled[BASE]])
        lines.append(f"McNemar ({name}, paired episodes): only with the filter {m['only_a']}, "
                     f"only without {m['only_b']}, p = {m['p_value']:.2g}")  # fmt: skip
    lines += ["", f"Held-out maps (env seeds {HELDOUT_SEEDS[0]}-{HELDOUT_SEEDS[-1]}, 200 "
              "episodes each): the shield alone (trial records) against the filter", "",
              "| policy (seed) | success | collision | success, filter | collision, filter |",
              "|---|---:|---:|---:|---:|"]  # fmt: skip
    for label, seed in POLICIES.items():
        record = json.loads((trials / f"csac-s{seed}.json").read_text())["heldout"]
        files = [load(directory, label, setting, s) for s in HELDOUT_SEEDS]
        mean = {
            k: sum(f[k] for f in files) / len(files) for k in ("success_rate", "collision_rate")
        }
        lines.append(f"| {label} ({seed}) | {record['success_rate']:.3f} | "
                     f"{record['collision_rate']:.3f} | {mean['success_rate']:.3f} | "
                     f"{mean['collision_rate']:.3f} |")  # fmt: skip
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("directory", type=Path)
    ap.add_argument("--setting", default=f"{BASE}-filter")
    ap.add_argument("--trials", type=Path, default=Path("results/csac/trials"))
    args = ap.parse_args(argv)
    lines = report(args.directory, args.setting, args.trials)
    (args.directory / f"report-{args.setting}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
