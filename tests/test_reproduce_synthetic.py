"""Synthetic run directories for the reproduce / plot tests: the files train and eval write.

Helpers only (imported by test_reproduce.py and test_plots.py); no tests of its own.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

COLUMNS = ["global_step", "charts/episodic_return", "charts/episodic_cost", "charts/success_rate",
           "charts/collision_rate", "constraint/lambda", "constraint/d", "perf/sps"]  # fmt: skip


def write_progress(run_dir: Path, rows: list[dict[str, float]], columns: list[str] | None = None):
    """``progress.csv`` with ``columns`` (default: the SPEC's); missing cells are left empty."""
    run_dir.mkdir(parents=True, exist_ok=True)
    columns = columns or sorted({k for r in rows for k in r}, key=_col_order)
    with (run_dir / "progress.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for r in rows:
            w.writerow(["" if r.get(c) is None else r[c] for c in columns])


def _col_order(name: str) -> tuple[int, str]:
    return (COLUMNS.index(name) if name in COLUMNS else len(COLUMNS), name)


def write_eval(run_dir: Path, success: float, collision: float, episodes: int = 200) -> None:
    """``eval.json`` as ``safenav eval --json`` writes it (the keys the results read)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    data = {"success_rate": success, "collision_rate": collision,
            "timeout_rate": round(1.0 - success - collision, 10), "mean_time_to_goal": 20.0,
            "min_clearance": 0.1, "episodes": episodes, "env_seed": 1}  # fmt: skip
    (run_dir / "eval.json").write_text(json.dumps(data))


def learning_run(run_dir: Path, algo: str, seed: int, steps: int = 20_000, every: int = 1_000,
                 final_success: float = 0.9, constrained: bool = True,
                 eval_every: int = 0) -> None:  # fmt: skip
    """A plausible run: success rises, collision falls, λ rises then settles, d tightens;
    with ``eval_every``, periodic evaluations (``eval/*`` columns) a little above training."""
    rows = []
    for i, step in enumerate(range(every, steps + 1, every)):
        frac = step / steps
        success = final_success * (1 - math.exp(-4 * frac)) + 0.01 * seed
        collision = max(0.0, 0.5 * math.exp(-3 * frac) + 0.01 * seed)
        row = {"global_step": step, "charts/episodic_return": 50 * success - 10 * collision,
               "charts/episodic_cost": collision, "charts/success_rate": round(success, 4),
               "charts/collision_rate": round(collision, 4), "perf/sps": 500.0}  # fmt: skip
        if constrained:
            row["constraint/lambda"] = round(2 * frac * math.exp(-2 * frac) + 0.1 * seed, 4)
            row["constraint/d"] = 0.5 / 2 ** min(i // 5, 3)
        if eval_every and step % eval_every == 0:
            row |= {"eval/success_rate": round(min(1.0, success + 0.05), 4),
                    "eval/collision_rate": round(max(0.0, collision - 0.05), 4),
                    "eval/timeout_rate": 0.0}  # fmt: skip
        rows.append(row)
    write_progress(run_dir, rows)
    (run_dir / "config.json").write_text(json.dumps({"algo": algo, "seed": seed}))
