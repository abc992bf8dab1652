"""Do timed-out episodes hover or wander? (docs/csac.md, "Not done / open")

Reads the per-episode lists of a ``safenav eval --json`` result and the start-goal pairs of the
same fixed test scenario (``experiments.evaluate.fixed_test_scenario`` with the result's env seed
and episode count and the checkpoint's env config), and prints, per outcome (success, collision,
timeout), the start-goal distance, the flown path length, their ratio and the mean speed
(minimum / median / maximum). A hovering policy times out with a short path; a wandering one with
a path far longer than the distance.

Run: ``.venv/bin/python experiments/timeout_paths.py results/paper/csac-paper-eval.json [--json OUT]``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from safenav.common.jsonout import write_json
from safenav.experiments.evaluate import fixed_test_scenario
from safenav.experiments.flight import resolve_policy

OUTCOMES = ("success", "collision", "timeout")


def summarise(result: dict) -> dict[str, dict[str, list[float]]]:
    per = result["per_episode"]
    _, cfg = resolve_policy(Path(result["checkpoint"]), "checkpoint", "cpu")
    _, starts, goals = fixed_test_scenario(cfg, int(result["env_seed"]), int(result["episodes"]))
    distance = np.linalg.norm(np.asarray(goals) - np.asarray(starts), axis=-1)
    path = np.asarray(per["path_length"], dtype=float)
    speed = np.asarray(per["mean_speed"], dtype=float)
    if not len(distance) == len(path) == len(speed):
        raise SystemExit("per-episode lists and the scenario differ in length: not an eval result of this scenario")  # fmt: skip
    out = {}
    for outcome in OUTCOMES:
        mask = np.asarray(per[outcome], dtype=bool)
        if mask.any():
            cols = {"distance_m": distance[mask], "path_m": path[mask],
                    "path_over_distance": path[mask] / distance[mask], "speed_m_s": speed[mask]}  # fmt: skip
            out[outcome] = {"episodes": int(mask.sum()),
                            **{k: [float(v.min()), float(np.median(v)), float(v.max())] for k, v in cols.items()}}  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "result", type=Path, help="a `safenav eval --json` file (with per_episode lists)"
    )
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = summarise(json.loads(args.result.read_text()))
    table = Table(title=f"{args.result}: min / median / max per outcome")
    for col in ("outcome", "episodes", "start-goal distance (m)", "path (m)", "path / distance", "mean speed (m/s)"):  # fmt: skip
        table.add_column(col, justify="right")
    for outcome, r in rows.items():
        fmt = lambda v, p: " / ".join(f"{x:.{p}f}" for x in v)  # noqa: E731
        table.add_row(outcome, str(r["episodes"]), fmt(r["distance_m"], 1), fmt(r["path_m"], 1),
                      fmt(r["path_over_distance"], 2), fmt(r["speed_m_s"], 2))  # fmt: skip
    Console(width=150).print(table)
    if args.json:
        write_json(args.json, rows)


if __name__ == "__main__":
    main()
