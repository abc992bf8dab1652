"""Results of a multi-seed sweep: read run directories, aggregate mean ± std across seeds.

The inputs are what ``safenav train`` and ``safenav eval`` leave behind, so every number here can
be recomputed from a sweep's output directory alone:

- ``progress.csv`` of each run (one row per log interval; ``global_step`` = env steps so far),
- ``eval.json`` of each run (``safenav eval`` on the fixed test scenario, paper IV-B).

Conventions
- ``std`` is the sample standard deviation across seeds (``ddof=1``; 0 for a single seed), the
  spread of "the standard deviation across training runs" of the paper's Fig. 4.
- Rates are fractions in [0, 1] in JSON; the Markdown table prints percent.
- *Time to target* is the first logged point where success >= 85 % **and** collision <= 10 %,
  measured on the run's periodic evaluation columns when the run logged them, else on its
  training-episode rates; wall-clock comes from the run's own elapsed-time column when present,
  else it is integrated from ``perf/sps`` (env steps / second) between log rows.
"""

from __future__ import annotations

import csv
import json
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from safenav.common.atomic import write_text_atomic
from safenav.common.jsonout import write_json
from safenav.experiments.stats import bootstrap_ci, compare, iqm, outcomes_string

#: The paper's Fig. 4 / Section IV-B figures (test success and collision rates), as fractions.
PAPER_RESULTS: dict[str, dict[str, float]] = {
    "csac": {"success_rate": 0.847, "collision_rate": 0.111},
    "sac": {"success_rate": 0.813, "collision_rate": 0.140},
    "ppo": {"success_rate": 0.711, "collision_rate": 0.246},
}

#: Display names of the algorithms ``safenav train --algo`` knows; others print as given.
DISPLAY_NAMES: dict[str, str] = {
    "csac": "CSAC",
    "sac": "SAC",
    "ppo": "PPO",
    "ppo_lag": "PPO-Lag",
    "sac_lag": "SAC-Lag",
}

#: Column pairs (success, collision) that hold *evaluation* rates, in order of preference.
EVAL_RATE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("eval/success_rate", "eval/collision_rate"),
    ("evaluation/success_rate", "evaluation/collision_rate"),
    ("test/success_rate", "test/collision_rate"),
)
#: The training-episode rates every run logs (SPEC §3).
TRAIN_RATE_COLUMNS: tuple[str, str] = ("charts/success_rate", "charts/collision_rate")
#: Columns holding seconds since the start of training, in order of preference.
ELAPSED_COLUMNS: tuple[str, ...] = (
    "time/elapsed_s",
    "time/elapsed",
    "perf/elapsed_s",
    "perf/wall_clock_s",
    "charts/wall_clock_s",
    "wall_clock_s",
    "elapsed_s",
    "time",
)


@dataclass(frozen=True)
class Target:
    """The time-to-target threshold: success >= ``success`` and collision <= ``collision``."""

    success: float = 0.85
    """Least success rate (fraction)."""
    collision: float = 0.10
    """Largest collision rate (fraction)."""


def display_name(algo: str) -> str:
    """``"csac"`` -> ``"CSAC"``; unknown labels are returned unchanged."""
    return DISPLAY_NAMES.get(algo, algo)


# -- reading run directories ---------------------------------------------------------------------


def read_progress(path: str | Path) -> dict[str, np.ndarray]:
    """``progress.csv`` as ``{column: float array}``; empty or non-numeric cells become NaN.

    Rows shorter than the header (a run killed mid-write) are dropped.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "progress.csv"
    with path.open(newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            return {}
        rows = [r for r in reader if len(r) == len(header)]

    def num(cell: str) -> float:
        try:
            return float(cell)
        except ValueError:
            return math.nan

    table = np.array([[num(c) for c in r] for r in rows], dtype=float).reshape(-1, len(header))
    return {name: table[:, i] for i, name in enumerate(header)}


def last_step(path: str | Path) -> int:
    """The last ``global_step`` in a ``progress.csv`` (0 when missing or empty), read cheaply."""
    path = Path(path)
    if path.is_dir():
        path = path / "progress.csv"
    try:
        with path.open("rb") as f:
            header = f.readline().decode().strip().split(",")
            if "global_step" not in header:
                return 0
            col = header.index("global_step")
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - 8192))
            lines = f.read().decode(errors="replace").splitlines()
    except (OSError, UnicodeDecodeError):
        return 0
    for line in reversed(lines[1:] if size <= 8192 else lines):
        cells = line.split(",")
        if len(cells) == len(header):
            try:
                return int(float(cells[col]))
            except ValueError:
                continue
    return 0


def elapsed_seconds(progress: dict[str, np.ndarray]) -> np.ndarray | None:
    """Seconds since the start of training at each row, or ``None`` if it cannot be known.

    Uses the run's own elapsed-time column (see :data:`ELAPSED_COLUMNS`) when present; otherwise
    integrates ``Δglobal_step / perf/sps`` row by row (the first row from step 0).
    """
    for name in ELAPSED_COLUMNS:
        col = progress.get(name)
        if col is not None and np.isfinite(col).any():
            return col
    steps, sps = progress.get("global_step"), progress.get("perf/sps")
    if steps is None or sps is None or len(steps) == 0:
        return None
    delta = np.diff(steps, prepend=0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        dt = np.where((sps > 0) & np.isfinite(sps), delta / sps, 0.0)
    return np.cumsum(dt)


def rate_columns(progress: dict[str, np.ndarray]) -> tuple[str, str, str] | None:
    """``(source, success column, collision column)`` to judge a run by: evaluation if logged."""
    for succ, coll in EVAL_RATE_COLUMNS:
        if succ in progress and coll in progress:
            ok = np.isfinite(progress[succ]) & np.isfinite(progress[coll])
            if ok.any():
                return "eval", succ, coll
    succ, coll = TRAIN_RATE_COLUMNS
    if succ in progress and coll in progress:
        return "train", succ, coll
    return None


def time_to_target(
    progress: dict[str, np.ndarray], target: Target = Target()
) -> dict[str, Any] | None:
    """The first logged point where the run meets ``target``, or ``None`` if it never does.

    Returns ``{"env_steps", "wall_clock_s" (None if unknown), "source": "eval"|"train"}``.
    """
    cols = rate_columns(progress)
    if cols is None or "global_step" not in progress:
        return None
    source, succ, coll = cols
    s, c = progress[succ], progress[coll]
    hit = np.isfinite(s) & np.isfinite(c) & (s >= target.success) & (c <= target.collision)
    if not hit.any():
        return None
    i = int(np.argmax(hit))
    elapsed = elapsed_seconds(progress)
    wall = float(elapsed[i]) if elapsed is not None and np.isfinite(elapsed[i]) else None
    return {"env_steps": int(progress["global_step"][i]), "wall_clock_s": wall, "source": source}


def validation_curve(progress: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """The run's periodic evaluations (validation maps), one entry per evaluation:
    ``{"env_steps", "wall_clock_s", "success_rate", "collision_rate", "timeout_rate"}``.

    Small enough for a trial record, so the learning curves of a sweep (issue 21's Fig. 3) can be
    drawn from its committed trial files alone. Empty if the run logged no evaluation."""
    steps = progress.get("global_step")
    succ, coll, tout = (progress.get(f"eval/{k}_rate") for k in ("success", "collision", "timeout"))
    if steps is None or succ is None or coll is None:
        return []
    elapsed = elapsed_seconds(progress)
    curve = []
    for i in np.flatnonzero(np.isfinite(succ) & np.isfinite(coll)):
        wall = elapsed[i] if elapsed is not None and np.isfinite(elapsed[i]) else None
        timeout = tout[i] if tout is not None and np.isfinite(tout[i]) else None
        curve.append({"env_steps": int(steps[i]),
                      "wall_clock_s": None if wall is None else round(float(wall), 1),
                      "success_rate": float(succ[i]), "collision_rate": float(coll[i]),
                      "timeout_rate": None if timeout is None else float(timeout)})  # fmt: skip
    return curve


def read_json(path: Path) -> dict[str, Any] | None:
    """A JSON file as a dict, or ``None`` if missing or unreadable."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def run_identity(run_dir: Path) -> tuple[str, int | None]:
    """``(algo label, seed)`` of a run directory.

    Read from ``reproduce.json`` (written by ``safenav reproduce``), then the layout of a
    ``reproduce`` output (``runs/<label>/seed<S>``: a trial stopped before it wrote
    ``reproduce.json`` is still its label's, not its algorithm's: ``csac_paper``, not ``csac``),
    then ``config.json`` (keys ``algo``/``seed`` at the top level or one level down), then the
    directory names (``.../<algo>/seed<S>``).
    """
    dir_seed = (
        int(run_dir.name[4:]) if run_dir.name[:4] == "seed" and run_dir.name[4:].isdigit() else None
    )
    in_sweep = dir_seed is not None and run_dir.parent.parent.name == "runs"
    for name in ("reproduce.json",) if in_sweep else ("reproduce.json", "config.json"):
        data = read_json(run_dir / name) or {}
        candidates = [data] + [v for v in data.values() if isinstance(v, dict)]
        algo = next((d["label"] for d in candidates if isinstance(d.get("label"), str)), None)
        algo = algo or next((d["algo"] for d in candidates if isinstance(d.get("algo"), str)), None)
        seed = next((d["seed"] for d in candidates if isinstance(d.get("seed"), int)), None)
        if algo:
            return algo, seed
    if dir_seed is not None:
        return run_dir.parent.name, dir_seed
    return run_dir.name, None


def seed_record(
    run_dir: Path,
    algo: str | None = None,
    seed: int | None = None,
    eval_result: dict[str, Any] | None = None,
    wall_clock_s: float | None = None,
    target: Target = Target(),
) -> dict[str, Any]:
    """One seed's row of ``results.json`` from its run directory.

    ``algo`` and ``seed`` default to :func:`run_identity`.
    ``eval_result`` defaults to ``run_dir/eval.json``; ``wall_clock_s`` (training time) to the
    run's elapsed-time column, else ``reproduce.json``'s measured training time.
    """
    run_dir = Path(run_dir)
    ev = eval_result if eval_result is not None else read_json(run_dir / "eval.json") or {}
    progress = read_progress(run_dir) if (run_dir / "progress.csv").exists() else {}
    steps = progress.get("global_step")
    env_steps = int(np.nanmax(steps)) if steps is not None and np.isfinite(steps).any() else None
    if wall_clock_s is None and progress:
        elapsed = elapsed_seconds(progress)
        if elapsed is not None and len(elapsed) and np.isfinite(elapsed[-1]):
            wall_clock_s = float(elapsed[-1])
    marker = read_json(run_dir / "reproduce.json") or {}
    if marker.get("train_wall_clock_s") is not None and not any(
        n in progress for n in ELAPSED_COLUMNS
    ):
        wall_clock_s = float(marker["train_wall_clock_s"])
    if algo is None or seed is None:
        ident_algo, ident_seed = run_identity(run_dir)
        algo = algo or ident_algo
        seed = ident_seed if seed is None else seed

    final = read_json(run_dir / "final.json") or {}
    selection = read_json(run_dir / "selection.json") or {}
    report = report_fields(ev, final)
    return {
        "algo": algo,
        "seed": seed,
        "run_dir": str(run_dir),
        **{k: report[k] for k in REPORT_FIELDS[:8]},
        "selection": "validation" if (run_dir / "selection.json").exists() else "final checkpoint",
        **{k: report[k] for k in REPORT_FIELDS[8:-1]},
        "env_steps": env_steps,
        "wall_clock_s": wall_clock_s,
        "selection_wall_clock_s": selection.get("wall_clock_s"),
        "time_to_target": time_to_target(progress, target) if progress else None,
        "validation_curve": validation_curve(progress) if progress else [],
        "test_outcomes": report["test_outcomes"],
    }


REPORT_FIELDS = ("success_rate", "collision_rate", "timeout_rate", "mean_time_to_goal",
                 "min_clearance", "eval_episodes", "detour_ratio", "border_time_fraction",
                 "heldout", "test_navrl_rule", "planner_filter", "planner_filter_override_share",
                 "test_without_filter", "test_outcomes")  # fmt: skip
"""The fields of a :func:`seed_record` that the policy's reports decide (``safenav eval``'s
test and ``final.json``'s held-out and side reports): what flying the same policy again behind
another filter changes (``experiments/rereport_filter.py``)."""


def report_fields(ev: dict[str, Any], final: dict[str, Any]) -> dict[str, Any]:
    """:data:`REPORT_FIELDS` of a seed's record from its test evaluation ``ev`` (``safenav
    eval --json``) and its ``--select`` report ``final`` (``final.json``; ``{}`` without)."""

    def metric(key: str) -> float | None:
        value = ev.get(key)
        ok = isinstance(value, (int, float)) and math.isfinite(value)
        return float(value) if ok else None

    held = final.get("heldout")
    heldout = None
    if isinstance(held, dict):
        heldout = {k: held.get(k) for k in ("seeds", "episodes_per_seed", "success_rate",
                                            "collision_rate", "timeout_rate")}  # fmt: skip
    side = ("episodes", "success_rate", "collision_rate", "timeout_rate", "collision_static_rate")
    navrl = final.get("test_navrl_rule")  # reports before 2026-12-01 lack it
    navrl = {k: navrl.get(k) for k in side} if isinstance(navrl, dict) else None
    unfiltered = final.get("test_without_filter")  # policies reported behind the planner filter
    if isinstance(unfiltered, dict):  # with its episodes, for the paired test without the filter
        unfiltered = {k: unfiltered.get(k) for k in side} | {
            "test_outcomes": outcomes_string(unfiltered.get("per_episode"))}  # fmt: skip
    else:
        unfiltered = None
    return {
        "success_rate": metric("success_rate"),
        "collision_rate": metric("collision_rate"),
        "timeout_rate": metric("timeout_rate"),
        "mean_time_to_goal": metric("mean_time_to_goal"),
        "min_clearance": metric("min_clearance"),
        "eval_episodes": ev.get("episodes"),
        "detour_ratio": metric("detour_ratio"),
        "border_time_fraction": metric("border_time_fraction"),
        "heldout": heldout,
        "test_navrl_rule": navrl,
        "planner_filter": final.get("flight_filter"),
        "planner_filter_override_share": ev.get("planner_filter_override_share"),
        "test_without_filter": unfiltered,
        "test_outcomes": outcomes_string(ev.get("per_episode")),
    }


# -- aggregation -------------------------------------------------------------------------------


def confidence_intervals(rates: Sequence[tuple[float | None, int | None]]) -> dict[str, Any] | None:
    """95 % intervals of a rate from its per-seed ``(rate, episodes)``: ``wilson`` on the pooled
    episodes (scipy's ``binomtest(...).proportion_ci(method="wilson")``; the episode-level
    uncertainty of these maps) and ``bootstrap`` of the mean over seeds (scipy's ``bootstrap``,
    percentile, 10,000 resamples; the seed-to-seed spread; None below 3 seeds)."""
    from scipy import stats

    pairs = [(float(r), int(n)) for r, n in rates if r is not None and n and math.isfinite(r)]
    if not pairs:
        return None
    k = sum(round(r * n) for r, n in pairs)
    n = sum(n for _, n in pairs)
    wilson = stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    boot = bootstrap_ci(np.mean, [r for r, _ in pairs])
    return {"pooled": k / n, "episodes": n, "wilson": [float(wilson.low), float(wilson.high)],
            "bootstrap_seeds": boot, "seeds": len(pairs)}  # fmt: skip


def mean_std(values: Iterable[float | None]) -> dict[str, float] | None:
    """``{"mean", "std"}`` of the finite values (sample std, ddof=1; 0 for one value), or None."""
    xs = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    if xs.size == 0:
        return None
    std = float(xs.std(ddof=1)) if xs.size > 1 else 0.0
    return {"mean": float(xs.mean()), "std": std}


def time_cell(rec: dict[str, Any]) -> str:
    """A seed's training time, and its selection's after a + where it has one."""
    sel = rec.get("selection_wall_clock_s")
    return fmt_seconds(rec.get("wall_clock_s")) + (f" (+ {fmt_seconds(sel)})" if sel else "")


def side_report(reports: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """Per-seed reports of one more flight of the test scenario (``{"episodes", "success_rate",
    ...}`` each; e.g. under NavRL's collision rule): their seeds, means and 95 % intervals; None
    where no seed has one."""
    if not reports:
        return None
    return {"seeds": len(reports),
            **{key: mean_std(n.get(key) for n in reports)
               for key in ("success_rate", "collision_rate", "timeout_rate")},
            "ci95": {key: confidence_intervals([(n.get(key), n.get("episodes")) for n in reports])
                     for key in ("success_rate", "collision_rate")}}  # fmt: skip


def aggregate_algo(
    name: str, per_seed: Sequence[dict[str, Any]], target: Target = Target()
) -> dict[str, Any]:
    """Algorithm ``name``'s entry of ``results.json`` from its seeds' records (:func:`seed_record`).

    ``env_steps`` and ``wall_clock_s`` are means per seed (one training run).
    """
    evaluated = [r for r in per_seed if r.get("success_rate") is not None]
    reached = [r["time_to_target"] for r in per_seed if r.get("time_to_target")]
    sources = sorted({t["source"] for t in reached})
    steps = mean_std(r.get("env_steps") for r in per_seed)
    wall = mean_std(r.get("wall_clock_s") for r in per_seed)
    to_policy = [r["wall_clock_s"] + r["selection_wall_clock_s"] for r in per_seed
                 if r.get("wall_clock_s") is not None
                 and r.get("selection_wall_clock_s") is not None]  # fmt: skip
    held = [r["heldout"] for r in evaluated if isinstance(r.get("heldout"), dict)]
    navrl = [r["test_navrl_rule"] for r in evaluated if isinstance(r.get("test_navrl_rule"), dict)]
    unfiltered = [r["test_without_filter"] for r in evaluated
                  if isinstance(r.get("test_without_filter"), dict)]  # fmt: skip
    return {
        "success_rate": mean_std(r["success_rate"] for r in evaluated),
        "collision_rate": mean_std(r["collision_rate"] for r in evaluated),
        "timeout_rate": mean_std(r["timeout_rate"] for r in evaluated),
        "mean_time_to_goal": mean_std(r.get("mean_time_to_goal") for r in evaluated),
        "detour_ratio": mean_std(r.get("detour_ratio") for r in evaluated),
        "border_time_fraction": mean_std(r.get("border_time_fraction") for r in evaluated),
        "ci95": {
            "test": {
                key: confidence_intervals([(r[key], r.get("eval_episodes")) for r in evaluated])
                for key in ("success_rate", "collision_rate")
            },
            "heldout": {
                key: confidence_intervals(
                    [
                        (h[key], len(h.get("seeds") or []) * (h.get("episodes_per_seed") or 0))
                        for h in held
                    ]
                )
                for key in ("success_rate", "collision_rate")
            }
            if held
            else None,
        },  # fmt: skip
        "heldout": {
            key: mean_std(h.get(key) for h in held)
            for key in ("success_rate", "collision_rate", "timeout_rate")
        }
        if held
        else None,  # fmt: skip
        # The test scenario under NavRL's collision rule, the paper's (seeds that report it).
        "test_navrl_rule": side_report(navrl),
        # Policies reported behind the planner filter: the test scenario behind the shield alone.
        "test_without_filter": side_report(unfiltered),
        "seeds": len(evaluated),
        "env_steps": steps["mean"] if steps else None,
        "wall_clock_s": wall["mean"] if wall else None,
        # Training plus the selection on validation maps: the time to the selected policy.
        "to_policy_wall_clock_s": mean_std(to_policy) | {"max": max(to_policy)}
        if to_policy
        else None,
        "time_to_target": {
            "success_min": target.success,
            "collision_max": target.collision,
            "reached": len(reached),
            "of": len(per_seed),
            "env_steps": mean_std(t["env_steps"] for t in reached),
            "wall_clock_s": mean_std(t["wall_clock_s"] for t in reached),
            "source": sources[0] if len(sources) == 1 else ("mixed" if sources else None),
        },
        "iqm": {
            key: iqm([r[key] for r in evaluated]) for key in ("success_rate", "collision_rate")
        },
        "paper": PAPER_RESULTS.get(name),
        "per_seed": sorted(per_seed, key=lambda r: (r.get("seed") is None, r.get("seed") or 0)),
    }


def aggregate(
    records: Sequence[dict[str, Any]],
    meta: dict[str, Any] | None = None,
    target: Target = Target(),
) -> dict[str, Any]:
    """``results.json``: records (each with an ``"algo"`` label) grouped and aggregated per algo.

    Algorithms appear in the order of their first record. ``meta`` (command, machine, date, ...)
    is merged in at the top level.
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for rec in records:
        groups.setdefault(rec["algo"], []).append(rec)
    algos = {name: aggregate_algo(name, recs, target) for name, recs in groups.items()}
    # CSAC against each other label of its budget: difference over seeds (bootstrap CI) and
    # McNemar's exact test on the paired test episodes (safenav.experiments.stats). A label at a
    # larger budget (ppo_3m) is compared with the CSAC of that budget (csac_3m), if any.
    budget = {name: label_budget(recs) for name, recs in groups.items()}
    pairs = [(ref, name) for ref in groups if is_reference(ref) for name in groups
             if not is_reference(name)
             and (None in (budget[ref], budget[name]) or budget[ref] == budget[name])]  # fmt: skip
    comparisons = {f"{ref}_vs_{name}": compare(groups[ref], groups[name]) for ref, name in pairs}
    # The same where both fly behind the planner filter: their policies behind the shield alone
    unfiltered = {name: [without_filter(r) for r in recs] for name, recs in groups.items()}
    comparisons_without_filter = {
        f"{ref}_vs_{name}": compare(unfiltered[ref], unfiltered[name])
        for ref, name in pairs
        if all(unfiltered[ref]) and all(unfiltered[name])
    }
    return {"algos": algos, "comparisons": comparisons,
            "comparisons_without_filter": comparisons_without_filter, "paper": PAPER_RESULTS,
            **(meta or {})}  # fmt: skip


def without_filter(rec: dict[str, Any]) -> dict[str, Any] | None:
    """A seed record reported behind the planner filter as the record of its test behind the
    shield alone (``test_without_filter``: rates, and per-episode outcomes where recorded), for
    :func:`~safenav.experiments.stats.compare`; None for a record without it."""
    side = rec.get("test_without_filter")
    if not isinstance(side, dict):
        return None
    return {"seed": rec.get("seed"), "success_rate": side.get("success_rate"),
            "collision_rate": side.get("collision_rate"),
            "test_outcomes": side.get("test_outcomes")}  # fmt: skip


def is_reference(label: str) -> bool:
    """CSAC's own labels, what the others are compared with: ``csac``, and ``csac_3m`` style
    labels (the csac recipe at another budget)."""
    return label == "csac" or budget_label_algo(label) == "csac"


def budget_label_algo(label: str) -> str | None:
    """``"csac_3m"`` -> ``"csac"``: the algorithm part of a label that names another budget
    (``ALGO_<steps>[km]``, as in the paper plan's 3M rows), else None."""
    m = re.fullmatch(r"(.+)_\d+(\.\d+)?[km]", label)
    return m.group(1) if m else None


def label_budget(records: Sequence[dict[str, Any]]) -> int | None:
    """The declared env-step budget of a label's trials (``budget_env_steps``), None if the
    records do not say or disagree."""
    budgets = {r.get("budget_env_steps") for r in records}
    return budgets.pop() if len(budgets) == 1 else None


# -- Markdown ------------------------------------------------------------------------------------


def fmt_rate(stat: dict[str, float] | None) -> str:
    """``{"mean": .847, "std": .012}`` -> ``"84.7 ± 1.2 %"``; None -> ``"—"``."""
    if not stat:
        return "—"
    return f"{100 * stat['mean']:.1f} ± {100 * stat['std']:.1f} %"


def fmt_seconds(seconds: float | None) -> str:
    """Seconds as ``"42 s"``, ``"12.5 min"`` or ``"3.2 h"``; None -> ``"—"``."""
    if seconds is None or not math.isfinite(seconds):
        return "—"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 2 * 3600:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.2f} h"


def fmt_steps(steps: float | None) -> str:
    """Env steps as ``"350k"`` / ``"1.20M"``; None -> ``"—"``."""
    if steps is None or not math.isfinite(steps):
        return "—"
    if steps >= 1e6:
        return f"{steps / 1e6:.2f}M"
    if steps >= 1e4:
        return f"{steps / 1e3:.0f}k"
    return f"{steps:.0f}"


def pct(value: float | None) -> str:
    """A fraction as ``"84.7 %"``; None -> ``"—"``."""
    return "—" if value is None else f"{100 * value:.1f} %"


def held_cell(held: dict[str, Any] | None) -> str:
    """Held-out success / collision of one seed, or —."""
    if not held:
        return "—"
    return f"{pct(held.get('success_rate'))} / {pct(held.get('collision_rate'))}"


def ratio(value: float | None) -> str:
    return "—" if value is None else f"{value:.2f}"


def summary_table(results: dict[str, Any]) -> list[str]:
    """The compact table the README quotes: per label its budget, test success and collision
    (mean over seeds with the 95 % bootstrap CI over seeds), held-out means, training time,
    and whether CSAC's (or its budget's CSAC's) difference from it is resolved."""
    algos: dict[str, dict[str, Any]] = results["algos"]
    comparisons = results.get("comparisons") or {}

    def rate(a: dict[str, Any], key: str) -> str:
        mean = (a.get(key) or {}).get("mean")
        boot = (((a.get("ci95") or {}).get("test") or {}).get(key) or {}).get("bootstrap_seeds")
        return f"{pct(mean)} ({100 * boot[0]:.1f}–{100 * boot[1]:.1f})" if boot else pct(mean)

    def versus(name: str) -> str:
        key = next((k for k in comparisons if k.split("_vs_", 1)[1] == name), None)
        if key is None:
            return "—"
        cells = []
        for rate_key, word in (("success_rate", "success"), ("collision_rate", "collision")):
            d = (comparisons[key].get(rate_key) or {}).get("mean_difference")
            if d:
                verdict = "resolved" if d["resolved"] else "not resolved"
                cells.append(f"{word} {100 * d['difference']:+.0f} pp, {verdict}")
        return f"{display_name(key.split('_vs_')[0])}: " + "; ".join(cells) if cells else "—"

    lines = ["| algorithm | seeds | env steps | test success (95 % CI) | test collision (95 % CI) "
             "| held-out success / collision | training / seed | CSAC − it (seeds' means) |",
             "|---|---:|---:|---:|---:|---:|---:|---|"]  # fmt: skip
    for name, a in algos.items():
        held = a.get("heldout") or {}
        held_s = (held.get("success_rate") or {}).get("mean")
        held_c = (held.get("collision_rate") or {}).get("mean")
        lines.append(
            f"| {display_name(name)} | {a['seeds']} | {fmt_steps(a.get('env_steps'))} "
            f"| {rate(a, 'success_rate')} | {rate(a, 'collision_rate')} "
            f"| {pct(held_s)} / {pct(held_c)} | {fmt_seconds(a.get('wall_clock_s'))} | {versus(name)} |"
        )
    return lines


def comparison_table(comparisons: dict[str, Any], title: str, why: str = "") -> list[str]:
    """The markdown section of ``results.json``'s ``comparisons`` (or the same without the
    planner filter): per baseline and rate, the difference over seeds and McNemar's test."""
    lines = ["", f"## {title}", "",
             why + "Difference CSAC − baseline of the mean over seeds, 95 % bootstrap CI (the "
             "seeds of each resampled): *resolved* only where the interval excludes 0. McNemar's "
             "exact test pairs each test episode with the same episode (same map, start, goal, "
             "obstacle motion) of the other algorithm's seed of the same number: episodes where "
             "only CSAC / only the baseline had the event, and the two-sided p-value "
             "(episode-level noise, not the spread of training seeds).", "",
             "| CSAC vs | rate | difference | 95 % CI | resolved | McNemar: only CSAC / only "
             "baseline (pairs) | p |", "|---|---|---:|---:|---|---:|---:|"]  # fmt: skip
    for key_name, comp in comparisons.items():
        ref, other = (display_name(part) for part in key_name.split("_vs_", 1))
        other = other if ref == "CSAC" else f"{other} (against {ref})"
        for key, label in (("success_rate", "success"), ("collision_rate", "collision")):
            c = comp.get(key) or {}
            d, m = c.get("mean_difference"), c.get("mcnemar")
            diff = f"{100 * d['difference']:+.1f} pp" if d else "—"
            ci = f"{100 * d['ci95'][0]:+.1f} – {100 * d['ci95'][1]:+.1f} pp" if d else "—"
            res = ("yes" if d["resolved"] else "no") if d else "—"
            mc = f"{m['only_a']} / {m['only_b']} ({m['pairs']})" if m else "—"
            pv = f"{m['p_value']:.3g}" if m else "—"
            lines.append(f"| {other} | {label} | {diff} | {ci} | {res} | {mc} | {pv} |")
    return lines


def render_markdown(results: dict[str, Any]) -> str:
    """``results.md``: ours beside the paper's figures, time to target, and every seed."""
    algos: dict[str, dict[str, Any]] = results["algos"]
    paper: dict[str, dict[str, float]] = results.get("paper", PAPER_RESULTS)
    lines = ["# Results: the fixed test scenario (paper IV-B)", ""]
    ev = results.get("evaluation", {})
    lines.append(
        f"Every final policy flown on the fixed test scenario (map of env seed "
        f"{ev.get('env_seed', 1)}, full density, {ev.get('episodes', 200)} fixed start/goal "
        "episodes, deterministic actions), the policy of each seed chosen on validation maps; "
        "the mean over seeds with its 95 % bootstrap CI over seeds; held-out: env seeds 2-6. "
        "Last column: CSAC's mean minus the row's (the CSAC of the row's budget), *resolved* "
        "where its 95 % CI excludes 0 (section *CSAC against each baseline*)."
    )
    lines += ["", *summary_table(results), "", "## Beside the paper", "",
              "Mean ± sample std across seeds. The paper's figures are its Section IV-B values "
              "(Isaac Sim, RTX 4090); — where the paper did not run the algorithm.", ""]  # fmt: skip
    lines.append(
        "| algorithm | seeds | success (ours) | success (paper) | collision (ours) "
        "| collision (paper) | timeout (ours) | env steps / seed | training time / seed |"
    )
    lines.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|")

    def beside_paper(name: str, ours: dict[str, Any]) -> str:
        """``| algorithm | seeds | success (ours) | (paper) | collision (ours) | (paper) | timeout``."""
        p = paper.get(name)
        return (f"| {display_name(name)} | {ours['seeds']} | {fmt_rate(ours['success_rate'])} "
                f"| {pct(p['success_rate']) if p else '—'} | {fmt_rate(ours['collision_rate'])} "
                f"| {pct(p['collision_rate']) if p else '—'} | {fmt_rate(ours['timeout_rate'])} ")  # fmt: skip

    for name, a in algos.items():
        lines.append(beside_paper(name, a) + f"| {fmt_steps(a['env_steps'])} "
                     f"| {fmt_seconds(a['wall_clock_s'])} |")  # fmt: skip
    with_rule = {name: a for name, a in algos.items() if a.get("test_navrl_rule")}
    if with_rule:
        lines += ["", "## Under the paper's collision rule", "",
                  "The same policies on the same test episodes, a static collision counted only "
                  "where a range-image beam reads it (NavRL's rule, the paper's simulator; "
                  "`EnvConfig.collision_rule`): a UAV that grazes a pillar's top no beam sees "
                  "flies on. Mean ± std over the seeds whose report has it.", "",
                  "| algorithm | seeds | success (ours) | success (paper) | collision (ours) "
                  "| collision (paper) | timeout (ours) |", "|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
        lines += [beside_paper(name, a["test_navrl_rule"]) + "|" for name, a in with_rule.items()]
    filtered = {name: a for name, a in algos.items() if a.get("test_without_filter")}
    if filtered:
        lines += ["", "## Without the planner filter", "",
                  "Policies reported behind the planner filter (`safenav train --flight-filter`): "
                  "the same test episodes flown behind their shield alone, the policy's own part. "
                  "Mean ± std over the seeds whose report has it.", "",
                  "| algorithm | seeds | success (ours) | success (paper) | collision (ours) "
                  "| collision (paper) | timeout (ours) |",
                  "|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
        lines += [beside_paper(name, a["test_without_filter"]) + "|"
                  for name, a in filtered.items()]  # fmt: skip
    lines += ["", "## 95 % confidence intervals", "",
              "Wilson: the episodes of every seed pooled (episode-level uncertainty); bootstrap: "
              "the mean over seeds resampled (seed-to-seed spread; none below 3 seeds). Held-out: "
              "env seeds 2-6, never used for a choice.", "",
              "| algorithm | scenario | success | Wilson | bootstrap | collision | Wilson | bootstrap |",
              "|---|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for name, a in algos.items():
        for scenario, cis in (a.get("ci95") or {}).items():
            if not cis or not cis.get("success_rate"):
                continue
            cells = []
            for key in ("success_rate", "collision_rate"):
                c = cis[key]
                boot = c["bootstrap_seeds"]
                cells += [pct(c["pooled"]), f"{pct(c['wilson'][0])} – {pct(c['wilson'][1])}",
                          f"{pct(boot[0])} – {pct(boot[1])}" if boot else "—"]  # fmt: skip
            lines.append(f"| {display_name(name)} | {scenario} | " + " | ".join(cells) + " |")
    lines += ["", "## Interquartile mean (IQM)", "",
              "Mean of the middle half of the seeds (scipy `trim_mean`, 25 % cut each side), robust "
              "to one seed that fails or excels; 95 % bootstrap CI over seeds.", "",
              "| algorithm | seeds | success IQM | 95 % CI | collision IQM | 95 % CI |",
              "|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    for name, a in algos.items():
        cells = []
        for key in ("success_rate", "collision_rate"):
            q = (a.get("iqm") or {}).get(key)
            ci = q and q.get("ci95")
            cells += [pct(q["iqm"]) if q else "—", f"{pct(ci[0])} – {pct(ci[1])}" if ci else "—"]
        lines.append(f"| {display_name(name)} | {a['seeds']} | " + " | ".join(cells) + " |")
    for key, title, why in (
        ("comparisons", "CSAC against each baseline", ""),
        ("comparisons_without_filter", "CSAC against each baseline, without the planner filter",
         "The same where both were reported behind the planner filter, on their test behind the "
         "shield alone (the policies' own part; McNemar where the records hold its episodes). "),
    ):  # fmt: skip
        if results.get(key):
            lines += comparison_table(results[key], title, why)
    lines += ["", "## Time to target", ""]
    first = next(iter(algos.values()), None)
    ttt0 = first["time_to_target"] if first else {"success_min": 0.85, "collision_max": 0.10}
    lines.append(
        f"Env steps and training wall-clock until a run first logged success >= "
        f"{100 * ttt0['success_min']:.0f} % and collision <= {100 * ttt0['collision_max']:.0f} % "
        "(its periodic evaluation when logged — *eval* — else its training episodes — *train*); "
        "mean ± std over the seeds that reached it."
    )
    lines += [
        "",
        "| algorithm | seeds that reached it | env steps | wall-clock | measured on |",
        "|---|---:|---:|---:|---|",
    ]
    for name, a in algos.items():
        t = a["time_to_target"]
        steps = t["env_steps"]
        wall = t["wall_clock_s"]
        steps_s = f"{fmt_steps(steps['mean'])} ± {fmt_steps(steps['std'])}" if steps else "—"
        wall_s = f"{fmt_seconds(wall['mean'])} ± {fmt_seconds(wall['std'])}" if wall else "—"
        lines.append(
            f"| {display_name(name)} | {t['reached']} / {t['of']} | {steps_s} | {wall_s} "
            f"| {t['source'] or '—'} |"
        )
    lines += [
        "",
        "## Every seed",
        "",
        "| algorithm | seed | success | collision | timeout | held-out success / collision "
        "| detour | policy | env steps | training (+ selection) | run |",
        "|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---|",
    ]
    for name, a in algos.items():
        for r in a["per_seed"]:
            lines.append(
                f"| {display_name(name)} | {r.get('seed')} | {pct(r.get('success_rate'))} "
                f"| {pct(r.get('collision_rate'))} | {pct(r.get('timeout_rate'))} "
                f"| {held_cell(r.get('heldout'))} | {ratio(r.get('detour_ratio'))} "
                f"| {r.get('selection', '—')} | {fmt_steps(r.get('env_steps'))} | {time_cell(r)} "
                f"| `{r.get('run_dir')}` |"
            )
    lines.append("")
    for key, label in (("command", "Command"), ("machine", "Machine"), ("date", "Date")):
        if results.get(key):
            lines.append(f"{label}: `{results[key]}`  " if key == "command" else
                         f"{label}: {results[key]}  ")  # fmt: skip
    if results.get("earlier_trials"):
        lines.append(f"Also reported, from earlier sweeps into the same directory (each trial's "
                     f"file in `trials/` holds its commands): "
                     f"{', '.join(results['earlier_trials'])}  ")  # fmt: skip
    return "\n".join(lines).rstrip() + "\n"


def write_results(results: dict[str, Any], out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``results.json`` and ``results.md`` into ``out_dir``; returns their paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    js, md = out_dir / "results.json", out_dir / "results.md"
    write_json(js, results, default=_json_default)  # atomic and fsynced, strict JSON
    write_text_atomic(md, render_markdown(results))
    return js, md


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


__all__ = [
    "DISPLAY_NAMES",
    "PAPER_RESULTS",
    "REPORT_FIELDS",
    "Target",
    "aggregate",
    "aggregate_algo",
    "display_name",
    "elapsed_seconds",
    "fmt_rate",
    "fmt_seconds",
    "fmt_steps",
    "last_step",
    "mean_std",
    "pct",
    "read_progress",
    "render_markdown",
    "report_fields",
    "run_identity",
    "seed_record",
    "side_report",
    "time_to_target",
    "validation_curve",
    "write_results",
]
