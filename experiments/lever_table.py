"""Validation curves of recipe levers, seed by seed (docs/csac-v1.md, "Levers on all five seeds").

Reads the periodic evaluations (validation maps only) from training runs' ``events.jsonl`` and
prints, per lever, each seed's success / collision / timeout at each evaluation, the mean over
seeds with a 95 % bootstrap CI (scipy), and how many seeds time out in at least a third of their
episodes (a policy that learned to stop, not to arrive); for every lever after the first, the
seed-paired difference from the first at the last evaluation (mean and 95 % bootstrap CI over the
seeds both ran: training seeds are shared, so the pairing removes the seed's own luck)::

    .venv/bin/python experiments/lever_table.py \
        recipe=results/csac-maxcost-crashloss/trials/csac-s{1,2,3,4,5}.json \
        rc50=results/csac-v1/levers/rc50-s{1,2,3,4,5}-events.jsonl --upto 510000

``LABEL=FILE [FILE ...]``: the files of one lever (one per seed; the seed is read from the
``config.json`` beside each). ``--json OUT`` writes the same figures.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from safenav.common.jsonout import write_json
from safenav.experiments.stats import bootstrap_ci

OUTCOMES = ("success", "collision", "timeout")  # the rates of each evaluation, in this order
HOVER = 1 / 3  # timeout share at which a seed counts as having learned to stop


def read_run(path: Path, upto: int) -> tuple[int | None, dict[int, tuple[float, float, float]]]:
    """The run's seed (from the ``config.json`` beside it: ``DIR/config.json`` or
    ``NAME-config.json`` for ``NAME-events.jsonl``) and its evaluations
    ``{env_steps: (success, collision, timeout)}``; or both from a committed trial file
    (``safenav reproduce``'s ``trials/ALGO-sSEED.json``, its ``validation_curve``)."""
    if path.suffix == ".json":
        trial = json.loads(path.read_text())
        return trial["seed"], {
            point["env_steps"]: tuple(float(point[f"{k}_rate"]) for k in OUTCOMES)
            for point in trial["validation_curve"]
            if point["env_steps"] <= upto
        }
    config = path.with_name(path.name.replace("events.jsonl", "config.json"))
    seed = json.loads(config.read_text())["run"]["seed"] if config.is_file() else None
    evals = {}
    for line in path.read_text().splitlines():
        event = json.loads(line)
        if event["event"] == "eval" and event["global_step"] <= upto:
            evals[event["global_step"]] = tuple(float(event[f"eval/{k}_rate"]) for k in OUTCOMES)
    return seed, evals


def ci95(values: list[float]) -> tuple[float, float]:
    """The project's bootstrap of the mean over seeds (NaN below two seeds)."""
    return tuple(bootstrap_ci(np.mean, values) or (float("nan"), float("nan")))


def paired_difference(base: dict, other: dict) -> dict | None:
    """``other`` minus ``base`` at the seeds both ran: per outcome the mean difference and its
    95 % bootstrap CI (None below two shared seeds)."""
    seeds = sorted(set(base) & set(other), key=str)
    if len(seeds) < 2:
        return None
    out: dict = {"seeds": seeds}
    for k, name in enumerate(OUTCOMES):
        diffs = [other[s][k] - base[s][k] for s in seeds]
        out[name] = {"mean": float(np.mean(diffs)), "ci95": list(ci95(diffs)), "per_seed": diffs}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("levers", nargs="+", help="LABEL=FILE or further FILEs of the last LABEL")
    parser.add_argument(
        "--upto", type=int, default=10**9, help="ignore evaluations after this step"
    )
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_intermixed_args(argv)

    files: dict[str, list[Path]] = defaultdict(list)
    label = None
    for item in args.levers:
        if "=" in item:
            label, item = item.split("=", 1)
        if label is None:
            parser.error(f"{item}: give LABEL=FILE first")
        files[label].append(Path(item))

    report = {}
    first: tuple[str, dict] | None = None  # the first label and {seed: its last evaluation}
    for label, paths in files.items():
        runs = {}
        for i, path in enumerate(paths):
            if not path.is_file():
                print(f"{label}: {path} missing, skipped", file=sys.stderr)
                continue
            seed, evals = read_run(path, args.upto)
            if evals:
                runs[seed if seed is not None else f"#{i}"] = evals
        if not runs:
            continue
        steps = sorted(set().union(*runs.values()))
        last = {s: ev[max(ev)] for s, ev in runs.items()}
        same_end = len({max(ev) for ev in runs.values()}) == 1
        print(f"\n## {label}: {len(runs)} seeds\n")
        print("| seed | " + " | ".join(f"{s / 1e6:.2f} M" for s in steps) + " |")
        print("|---:|" + "---|" * len(steps))
        for seed, ev in runs.items():
            cells = ["{:.3f} / {:.3f} / {:.3f}".format(*ev[s]) if s in ev else "" for s in steps]
            print(f"| {seed} | " + " | ".join(cells) + " |")
        summary = {}
        for k, name in enumerate(OUTCOMES):
            vals = [v[k] for v in last.values()]
            lo, hi = ci95(vals)
            summary[name] = {"mean": float(np.mean(vals)), "ci95": [lo, hi], "per_seed": vals}
        hover = sum(v[2] >= HOVER for v in last.values())
        summary["seeds_stopping"] = hover
        note = "" if same_end else " (runs end at different steps: last evaluation of each)"
        print(
            f"\nlast evaluation{note}: success {summary['success']['mean']:.3f} "
            f"(95 % CI {summary['success']['ci95'][0]:.3f}-{summary['success']['ci95'][1]:.3f}), "
            f"collision {summary['collision']['mean']:.3f} "
            f"({summary['collision']['ci95'][0]:.3f}-{summary['collision']['ci95'][1]:.3f}), "
            f"timeout {summary['timeout']['mean']:.3f}; "
            f"{hover} of {len(last)} seeds time out in >= 1/3 of episodes"
        )
        report[label] = {"seeds": {str(s): {str(k): v for k, v in ev.items()} for s, ev in runs.items()},
                         "last": summary}  # fmt: skip
        if first is None:
            first = (label, last)
        elif paired := paired_difference(first[1], last):
            report[label]["paired_vs"] = {"label": first[0], **paired}
            print(f"paired with {first[0]} on seeds {', '.join(map(str, paired['seeds']))}, "
                  f"{label} minus {first[0]}: " + ", ".join(
                      f"{name} {d['mean']:+.3f} ({d['ci95'][0]:+.3f} to {d['ci95'][1]:+.3f})"
                      for name, d in paired.items() if name != "seeds"))  # fmt: skip
    if args.json:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
