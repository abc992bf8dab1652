"""``safenav bench gym`` and ``safenav bench safe``: safenav's algorithms on Gymnasium tasks whose
answer is published (:mod:`safenav.bench.suites`), Stable-Baselines3 beside them on the same
budget, then a table and learning curves.

Each trial (task, algorithm, implementation, seed, budget) is one ``safenav train`` run (its
family recipe, one torch thread, periodic deterministic evaluations) or one SB3 run
(:mod:`safenav.bench.sb3_trial`), in a child process. A finished trial writes
``OUT/trials/<task>-<algo>-<impl>-<steps>-s<seed>.json`` (spec, final and periodic evaluations,
training returns, wall clock, versions); a rerun skips every trial that has its file, continues
an interrupted safenav run from its checkpoint (``OUT/runs/``), and finally writes
``OUT/table.md``, ``OUT/curves.png`` and ``OUT/summary.json`` from all the suite's trial files
in OUT (those of earlier selections too). Child logs: ``OUT/logs/``.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from safenav.algos.config import paper_departures
from safenav.bench import zoo_curves
from safenav.bench.suites import DEFAULT_SB3, SUITES, Reference, Task
from safenav.common.families import CONSTRAINED, PPO_ALGOS, algo_family
from safenav.errors import SafenavError, SafenavRuntimeError

EVAL_POINTS = 10
"""Evaluations per trial (every budget / 10 steps), the last at the end of training."""
EVAL_EPISODES = 10


@dataclass(frozen=True)
class Trial:
    suite: str
    env: str
    algo: str
    impl: str  # "safenav" or "sb3"
    seed: int
    steps: int

    @property
    def name(self) -> str:
        return f"{self.env}-{self.algo}-{self.impl}-{self.steps}-s{self.seed}"

    @property
    def eval_every(self) -> int:
        return max(1, self.steps // EVAL_POINTS)


def plan_trials(suite: str, tasks: tuple[str, ...], algos: tuple[str, ...], seeds: int, steps: int,
                sb3: tuple[str, ...] | None, first_seed: int = 1) -> list[Trial]:  # fmt: skip
    """The trials of a selection (seeds ``first_seed`` .. ``first_seed + seeds - 1``), checked:
    ``SafenavError`` for unknown tasks or algorithms."""
    table = SUITES[suite]
    tasks = tasks or tuple(table)
    unknown = [t for t in tasks if t not in table]
    if unknown:
        raise SafenavError(f"--tasks {' '.join(unknown)}: not in the {suite} suite; choose from "
                           f"{', '.join(table)}")  # fmt: skip
    all_algos = tuple(dict.fromkeys(a for t in table.values() for a in t.steps))
    algos = algos or all_algos
    bad = [a for a in algos if a not in all_algos]
    if bad:
        raise SafenavError(
            f"--algos {' '.join(bad)}: the {suite} suite runs {', '.join(all_algos)}"
        )
    sb3 = DEFAULT_SB3[suite] if sb3 is None else sb3
    if suite == "safe" and sb3:
        raise SafenavError(
            "--sb3: Stable-Baselines3 has no constrained algorithms (bench gym only)"
        )
    bad = [t for t in sb3 if t not in table]
    if bad:
        raise SafenavError(f"--sb3 {' '.join(bad)}: not in the {suite} suite; choose from "
                           f"{', '.join(table)}")  # fmt: skip
    out = []
    for env in tasks:
        for algo in algos:
            if algo not in table[env].steps:  # SAC on a discrete task
                continue
            budget = steps or table[env].steps[algo]
            for seed in range(first_seed, first_seed + seeds):
                out.append(Trial(suite, env, algo, "safenav", seed, budget))
                if env in sb3 and algo in ("sac", "ppo"):
                    out.append(Trial(suite, env, algo, "sb3", seed, budget))
    if not out:
        raise SafenavError(f"--tasks {' '.join(tasks)} --algos {' '.join(algos)}: no such pair in "
                           f"the {suite} suite (the discrete tasks run PPO only)")  # fmt: skip
    return out


# ------------------------------------------------------------------------------ running


def train_command(trial: Trial, out: Path, cost_limit: float,
                  extra: tuple[str, ...] = ()) -> list[str]:  # fmt: skip
    """The child command line of a trial (a safenav run resumes from its checkpoint)."""
    run_dir = out / "runs" / trial.name
    if trial.impl == "sb3":
        if (run_dir / "result.json").is_file():  # trained; only its trial file is missing
            return [sys.executable, "-c", ""]
        return [sys.executable, "-m", "safenav.bench.sb3_trial", trial.env, trial.algo,
                str(trial.seed), str(trial.steps), str(trial.eval_every), str(EVAL_EPISODES),
                str(run_dir)]  # fmt: skip
    cmd = [sys.executable, "-m", "safenav", "train", "--algo", trial.algo, "--no-progress",
           "--no-tensorboard", "--torch-threads", "1", "--total-steps", str(trial.steps)]  # fmt: skip
    if (run_dir / "checkpoint.pt").is_file():
        return [*cmd, "--resume", str(run_dir)]
    cmd += ["--env", trial.env, "--seed", str(trial.seed), "--run-dir",
            str(run_dir), "--overwrite", "--eval-every", str(trial.eval_every), "--eval-episodes",
            str(EVAL_EPISODES), "--log-every", str(max(1, trial.steps // 100)),
            "--checkpoint-every", str(max(1, trial.steps // 10))]  # fmt: skip
    if trial.algo not in PPO_ALGOS:  # an off-policy trial resumes with its replay buffer
        cmd.append("--save-buffer")  # (else it would refill it first)
    if trial.algo in CONSTRAINED:  # the cost limit: a fixed episode-cost budget d
        family = algo_family(trial.algo)
        cmd += [f"--{family}.curriculum.no-enabled", f"--{family}.curriculum.d-init",
                str(cost_limit), f"--{family}.curriculum.d-min", str(cost_limit)]  # fmt: skip
    return [*cmd, *extra]


def steps_done(trial: Trial, out: Path) -> int:
    """How far a running trial has come (its last progress row or SB3's progress file)."""
    from safenav.experiments.aggregate import last_step

    run_dir = out / "runs" / trial.name
    if trial.impl == "sb3":
        try:
            return int((run_dir / "progress.txt").read_text() or 0)
        except (OSError, ValueError):
            return 0
    return last_step(run_dir)


def resumed_at(run_dir: Path) -> list[int]:
    """The env steps at which a safenav run was resumed (its ``events.jsonl``): a resumed run
    continues from its checkpoint but not bit for bit as an uninterrupted one (the envs' states
    are not checkpointed; docs/reliability.md), so the trial file says where it happened."""
    path = run_dir / "events.jsonl"
    if not path.is_file():
        return []
    steps = []
    for line in path.read_text().splitlines():
        with contextlib.suppress(ValueError, TypeError):
            record = json.loads(line)
            if record.get("event") == "resume":
                steps.append(int(record["global_step"]))
    return steps


def collect(trial: Trial, out: Path, wall_s: float) -> dict[str, Any]:
    """The trial file's content from a finished child's outputs."""
    from safenav.common.machine import machine_description
    from safenav.experiments.aggregate import read_progress

    run_dir = out / "runs" / trial.name
    if trial.impl == "sb3":
        res = json.loads((run_dir / "result.json").read_text())
        curve, train_curve, wall, done = (res["curve"], res["train_curve"], res["wall_clock_s"],
                                          res["steps"])  # fmt: skip
        extra = {"hyperparameters": res["hyperparameters"], "n_envs": res["n_envs"],
                 "normalize": res["normalize"]}  # fmt: skip
    else:
        log = read_progress(run_dir) if (run_dir / "progress.csv").is_file() else {}
        step = log.get("global_step", [])  # empty: the child wrote no progress (refused below)
        none = [math.nan] * len(step)  # a column the run did not log

        def points(ret_key: str, cost_key: str) -> list[list[float]]:
            """[step, return, cost] of each row that logged ``ret_key``."""
            columns = (step, log.get(ret_key, none), log.get(cost_key, none))
            return [[int(s), float(r), float(c)]
                    for s, r, c in zip(*columns, strict=True) if not math.isnan(r)]  # fmt: skip

        curve = points("eval/return", "eval/cost")
        train_curve = points("charts/episodic_return", "charts/episodic_cost")
        wall = float(log["time/elapsed_s"][-1]) if len(step) else wall_s
        done = int(step[-1]) if len(step) else 0
        config = json.loads((run_dir / "config.json").read_text())
        extra = {"recipe": (config.get("recipe") or {}).get("name"), "config": config,
                 # a resume past the budget (a rerun after the end) trained nothing
                 "resumed_at": [s for s in resumed_at(run_dir) if s < trial.steps]}  # fmt: skip
    if not curve:
        raise SafenavRuntimeError(f"trial {trial.name}: no evaluation recorded ({run_dir})")
    if done < trial.steps:  # a trial file stands for its whole budget
        raise SafenavRuntimeError(f"trial {trial.name}: ended at step {done:,} of its "
                                  f"{trial.steps:,} ({run_dir})")  # fmt: skip
    return {
        "trial": trial.__dict__ | {"name": trial.name}, "steps_done": done,
        "final": {"return": curve[-1][1], "cost": curve[-1][2], "step": curve[-1][0]},
        "curve": curve, "train_curve": train_curve, "wall_clock_s": wall,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version(), "description": machine_description()},
        "versions": versions(), "date": time.strftime("%Y-%m-%d"),
        "eval_episodes": EVAL_EPISODES, **extra,
    }  # fmt: skip


def versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in ("safenav", "torch", "gymnasium", "mujoco", "box2d", "stable-baselines3"):
        with contextlib.suppress(PackageNotFoundError):
            out[name] = version(name)
    return out


def say(text: str) -> None:
    """One plain line on stderr (not wrapped, whatever the terminal)."""
    print(f"safenav bench: {text}", file=sys.stderr, flush=True)


def run_trials(trials: list[Trial], out: Path, cost_limit: float, jobs: int = 1,
               progress: bool = True, extra: tuple[str, ...] = (),
               max_trials: int = 0) -> list[str]:  # fmt: skip
    """Run the trials that have no trial file yet (the first ``max_trials`` of them, 0 = all),
    ``jobs`` at a time (each a child process, :func:`safenav.common.child_runs.run_queue`);
    returns the failures."""
    from rich.console import Console

    from safenav.common.child_runs import ChildRun, run_queue
    from safenav.common.jsonout import write_json

    for sub in ("trials", "runs", "logs"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    pending = [t for t in trials if not (out / "trials" / f"{t.name}.json").is_file()]
    todo = pending[:max_trials] if max_trials else pending
    left = len(pending) - len(todo)
    later = f" ({left} left for a later run: --max-trials)" if left else ""
    say(f"{len(trials)} trials, {len(trials) - len(pending)} already done (skipped), {len(todo)} "
        f"to run{later}; results in {out}")  # fmt: skip

    def child(trial: Trial) -> ChildRun:
        def finish(wall_s: float) -> str:
            result = collect(trial, out, wall_s)
            write_json(out / "trials" / f"{trial.name}.json", result)
            return (f"{trial.name} done: return {result['final']['return']:.1f}, "
                    f"{result['wall_clock_s']:.0f} s")  # fmt: skip

        return ChildRun(trial.name, trial.steps, lambda: train_command(trial, out, cost_limit, extra),
                        lambda: steps_done(trial, out), finish, out / "logs" / f"{trial.name}.log")  # fmt: skip

    return run_queue([child(t) for t in todo], jobs, say, progress, Console(stderr=True))


# ------------------------------------------------------------------------------ the report


def load_results(suite: str, out: Path) -> list[dict[str, Any]]:
    """Every finished trial of ``suite`` in ``OUT/trials``, whichever run wrote it: the table is
    the suite's, so running one task again does not drop the others' rows."""
    found = []
    for path in sorted((out / "trials").glob("*.json")):
        result = json.loads(path.read_text())
        trial = result.get("trial", {})
        if trial.get("suite") == suite and trial.get("env") in SUITES[suite]:
            found.append(result)
    return found


def within(value: float, ref: float, tolerance: float = 0.1) -> bool:
    """At least the reference minus ``tolerance`` of its magnitude (returns may be negative)."""
    return value >= ref - tolerance * abs(ref)


def _ref_text(ref: Reference | None, steps: int) -> str:
    if ref is None:
        return "-"
    at = "" if ref.steps == steps else f" at {_count(ref.steps)}"
    std = f" ± {ref.std:.0f}" if ref.std is not None else ""
    return f"{ref.value:.0f}{std}{at} ({ref.source})"


def _count(n: int) -> str:
    return (
        f"{n // 1_000_000}M" if n % 1_000_000 == 0 else f"{n // 1000}k" if n % 1000 == 0 else str(n)
    )


# what may differ between the seeds of one row: run settings that are not hyperparameters, and
# the recipe's text (its header is rewritten as results come in; its name is compared)
# run.save_buffer only decides what a checkpoint holds, not what an uninterrupted run learns
PER_TRIAL_KEYS = ("run.seed", "run.torch_threads", "run.save_buffer", "recipe.header",
                  "recipe.source")  # fmt: skip
CONSTRAINT_ONLY = ("lambda_", "init_lambda", "episode_lambda_lr", "cost_", "curriculum.",
                   "scale_actor_loss", "balance_critic_losses", "pid_",
                   "num_cost_critics")  # fmt: skip
"""Field names (after ``csac.`` / ``ppo.``) that only the constrained algorithms read: SAC and
PPO build no cost critic and no multiplier, so their rows do not count these as differences."""


def _defaults() -> dict[str, Any]:
    """Today's default of every config key: a trial written before a key existed ran with it."""
    from dataclasses import asdict

    from safenav.algos.config import CSACConfig
    from safenav.algos.ppo_config import PPOConfig
    from safenav.common.config import RunConfig

    defaults = {
        "run": asdict(RunConfig()),
        "csac": asdict(CSACConfig()),
        "ppo": asdict(PPOConfig()),
    }
    return _flat(json.loads(json.dumps(defaults)))  # as a trial file holds them: tuples -> lists


def _flat(config: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(config, dict):
        return {prefix: config}
    out: dict[str, Any] = {}
    for k, v in config.items():
        out.update(_flat(v, f"{prefix}.{k}" if prefix else k))
    return out


def config_differences(results: list[dict[str, Any]]) -> list[str]:
    """The config keys (dotted) on which the trials of one row differ, seed aside: a row that
    mixes configurations (an interrupted trial resumed after its recipe changed, trial files of
    two commands) says so instead of averaging them silently. Trials without a config (SB3's)
    are left out; a key a trial lacks (written before the key existed) reads as its default. An
    unconstrained row ignores the constraint's keys (``CONSTRAINT_ONLY``)."""
    flats = [_flat(r["config"]) for r in results if r.get("config")]
    keys = set().union(*flats) - set(PER_TRIAL_KEYS) if flats else set()
    if results and results[0]["trial"]["algo"] not in CONSTRAINED:  # run.cost_fn still counts
        keys = {k for k in keys
                if not (k.partition(".")[0] in ("csac", "ppo")
                        and k.partition(".")[2].startswith(CONSTRAINT_ONLY))}  # fmt: skip
    default = _defaults() if keys else {}
    return sorted(k for k in keys
                  if len({repr(f.get(k, default.get(k, "<missing>"))) for f in flats}) > 1)  # fmt: skip


def summarize(suite: str, results: list[dict[str, Any]], cost_limit: float) -> list[dict[str, Any]]:
    """One row per (task, algo, budget): mean ± std over seeds, safenav beside SB3 and the
    published reference."""
    from safenav.experiments.aggregate import mean_std

    groups: dict[tuple[str, str, int], dict[str, list[dict]]] = {}
    for r in results:
        t = r["trial"]
        groups.setdefault((t["env"], t["algo"], t["steps"]), {}).setdefault(t["impl"], []).append(r)
    rows = []
    for (env, algo, steps), impls in groups.items():
        task: Task = SUITES[suite][env]
        ref = task.references.get(algo)
        row: dict[str, Any] = {"env": env, "algo": algo, "steps": steps,
                               "reference": ref.__dict__ if ref else None}  # fmt: skip
        for impl, rs in impls.items():
            ret, cost, wall = (mean_std(x["final"]["return"] for x in rs),
                               mean_std(x["final"]["cost"] for x in rs),
                               mean_std(x["wall_clock_s"] for x in rs))  # fmt: skip
            by_seed = sorted(rs, key=lambda x: x["trial"]["seed"])
            row[impl] = {"return": ret["mean"], "return_std": ret["std"], "cost": cost["mean"],
                         "cost_std": cost["std"], "wall_clock_s": wall["mean"],
                         "seeds": [x["trial"]["seed"] for x in by_seed],
                         "returns": [x["final"]["return"] for x in by_seed],
                         "costs": [x["final"]["cost"] for x in by_seed]}  # fmt: skip
            if differ := config_differences(rs):
                row[impl]["config_differs"] = differ
            config = next((x["config"] for x in rs if x.get("config")), {})
            if algo == "csac" and (departs := paper_departures(config.get("csac", {}))):
                row[impl]["paper_departures"] = departs  # a variant: named so in the table
            if resumed := {x["trial"]["seed"]: x["resumed_at"] for x in rs if x.get("resumed_at")}:
                row[impl]["resumed"] = resumed  # seed -> the steps it was resumed at
        if len(impls) > 1:  # wall clocks compare only on one machine on one day
            hosts = {(json.dumps(x.get("machine"), sort_keys=True), x.get("date"))
                     for rs in impls.values() for x in rs}  # fmt: skip
            row["same_machine"] = len(hosts) == 1
        # the published agent's own evaluation at this budget (zoo_curves), where it has one
        same = zoo_curves.at(env, algo, steps) if suite == "gym" else None
        if same is not None and (ref is None or ref.steps != steps):
            row["reference_at_budget"] = same.__dict__
        if "safenav" in row and ref is not None and suite == "gym":
            compare = row.get("reference_at_budget") or ref.__dict__
            row["within_10pct"] = within(row["safenav"]["return"], compare["value"])
        if "safenav" in row and suite == "safe":
            row["under_limit"] = row["safenav"]["cost"] <= cost_limit  # the mean over seeds
            row["seeds_under_limit"] = sum(
                x["final"]["cost"] <= cost_limit for x in impls["safenav"]
            )
        rows.append(row)
    order = list(SUITES[suite])
    rows.sort(key=lambda x: (order.index(x["env"]), x["algo"], x["steps"]))
    return rows


def safe_targets(rows: list[dict[str, Any]], cost_limit: float) -> list[dict[str, Any]]:
    """The safe suite's target per task, from the rows' final evaluations: CSAC's mean episode
    cost within the limit, with the highest return of the constrained algorithms. Each part with
    its 95 % interval (the mean cost's t-interval; Welch's interval on CSAC's return minus each
    other constrained row's). ``verdict``: ``shown`` where the intervals support both parts (the
    cost interval under the limit, every return interval above 0), ``not shown`` where only the
    means do, ``not met`` where a mean does not (CSAC's mean cost, or its mean return against any
    row's); otherwise None while a row has fewer than two seeds."""
    from safenav.experiments.stats import mean_t_interval, welch_difference

    targets = []
    for csac in (r for r in rows if r["algo"] == "csac" and "safenav" in r):
        c = csac["safenav"]
        if "returns" not in c:  # a summary written before the rows kept their seeds' finals
            continue
        others = [r for r in rows if r["env"] == csac["env"] and r["algo"] in CONSTRAINED
                  and r["algo"] != "csac" and "safenav" in r]  # fmt: skip
        versus = [{"algo": r["algo"], "steps": r["steps"],
                   "difference": c["return"] - r["safenav"]["return"],  # of the means
                   **(welch_difference(c["returns"], r["safenav"]["returns"]) or {})}
                  for r in others]  # fmt: skip
        cost_ci = mean_t_interval(c["costs"])
        if c["cost"] > cost_limit or any(v["difference"] < 0 for v in versus):
            verdict = "not met"  # whatever more seeds of the other rows give
        elif cost_ci is None or not all("ci95" in v for v in versus):
            verdict = None
        elif cost_ci[1] <= cost_limit and all(v["ci95"][0] > 0 for v in versus):
            verdict = "shown"
        else:
            verdict = "not shown"
        targets.append({"env": csac["env"], "steps": csac["steps"], "cost": c["cost"],
                        "cost_ci95": cost_ci, "seeds_under_limit": csac.get("seeds_under_limit"),
                        "seeds": len(c["seeds"]), "versus": versus, "verdict": verdict})  # fmt: skip
    return targets


def _target_lines(targets: list[dict[str, Any]], cost_limit: float) -> list[str]:
    def ci(pair: list[float] | None, digits: int = 0) -> str:
        if pair is None:
            return "n/a (one seed)"
        low, high = (round(x, digits) + 0.0 for x in pair)  # + 0.0: no "-0"
        return f"{low:.{digits}f} to {high:.{digits}f}"

    lines = []
    for t in targets:
        versus = "; ".join(
            f"against {v['algo']} ({_count(v['steps'])}) {v['difference']:+.0f} (Welch 95 % CI "
            f"{ci(v['ci95'])}, p = {v['p_value']:.2f})" if "ci95" in v else
            f"against {v['algo']} ({_count(v['steps'])}) {v['difference']:+.0f} (one seed: no interval)"
            for v in t["versus"]
        ) or "not compared (no other constrained row)"  # fmt: skip
        lines.append(f"\n**Target on {t['env']}** (CSAC's mean episode cost <= {cost_limit:g} "
                     f"with the highest constrained return): **{t['verdict'] or 'not yet (one seed)'}**"
                     f". CSAC's cost {t['cost']:.1f} (95 % t-interval {ci(t['cost_ci95'], 1)}, "
                     f"{t['seeds_under_limit']}/{t['seeds']} seeds within); its return: {versus}.")  # fmt: skip
    return lines


def markdown_table(
    suite: str, rows: list[dict[str, Any]], cost_limit: float, notes: list[str] | None = None
) -> str:
    """The suite's table, then the lines under it (``notes``: :func:`_notes`, computed here
    unless the caller has them)."""
    notes = _notes(suite, rows, cost_limit) if notes is None else notes

    def pm(d: dict | None, key: str) -> str:
        if d is None:
            return "-"
        if len(d["seeds"]) == 1:  # one seed has no spread to show
            return f"{d[key]:.0f} (n=1)"
        return f"{d[key]:.0f} ± {d[key + '_std']:.0f} (n={len(d['seeds'])})"

    if suite == "gym":
        lines = ["| task | algo | steps | safenav return | reference (published; **bold**: the same "
                 "agent at this budget) | within 10 % (of the bold one where there is one) "
                 "| SB3 here | wall clock safenav / SB3 |",
                 "|---|---|---:|---:|---|:---:|---:|---:|"]  # fmt: skip
        for r in rows:
            s, b = r.get("safenav"), r.get("sb3")
            ref = Reference(**r["reference"]) if r["reference"] else None
            ok = {True: "yes", False: "no"}.get(r.get("within_10pct"), "-")
            wall = f"{s['wall_clock_s']:.0f} s" if s else "-"
            if s and b:
                wall += f" / {b['wall_clock_s']:.0f} s"
                wall += "" if r.get("same_machine") else " (other machine or day)"
            refs = _ref_text(ref, r["steps"])
            if same := r.get("reference_at_budget"):
                refs += f"; **{_ref_text(Reference(**same), r['steps'])}**"
            lines.append(f"| {r['env']} | {r['algo']} | {_count(r['steps'])} | {pm(s, 'return')} | "
                         f"{refs} | {ok} | {pm(b, 'return')} | {wall} |")  # fmt: skip
        return "\n".join(lines + notes) + "\n"
    lines = [f"| task | algo | steps | return | episode cost | mean cost <= {cost_limit:g} | OmniSafe "
             "(published): return / cost | wall clock |", "|---|---|---:|---:|---:|:---:|---|---:|"]  # fmt: skip
    for r in rows:
        s = r.get("safenav")
        ref = Reference(**r["reference"]) if r["reference"] else None
        ok = {True: "yes", False: "no"}.get(r.get("under_limit"), "-")
        if s is not None and "seeds_under_limit" in r:  # the mean can hide a seed over it
            ok += f" ({r['seeds_under_limit']}/{len(s['seeds'])} seeds)"
        refs = "-"
        if ref is not None:
            at = "" if ref.steps == r["steps"] else f" at {_count(ref.steps)}"
            refs = f"{ref.value:.0f} / {ref.cost:.1f}{at} ({ref.source})"
        wall = f"{s['wall_clock_s']:.0f} s" if s else "-"
        algo = r["algo"] + (" (variant)" if (s or {}).get("paper_departures") else "")
        lines.append(f"| {r['env']} | {algo} | {_count(r['steps'])} | {pm(s, 'return')} | "
                     f"{pm(s, 'cost')} | {ok} | {refs} | {wall} |")  # fmt: skip
    return "\n".join(lines + notes) + "\n"


def _notes(
    suite: str,
    rows: list[dict[str, Any]],
    cost_limit: float,
    targets: list[dict[str, Any]] | None = None,
) -> list[str]:
    """The lines under a suite's table (and on the terminal): the rows' notes, then the safe
    suite's target per task (``targets``: :func:`safe_targets`, computed here if not given)."""
    if targets is None:
        targets = safe_targets(rows, cost_limit) if suite == "safe" else []
    return _row_notes(rows) + _target_lines(targets, cost_limit)


def _row_notes(rows: list[dict[str, Any]]) -> list[str]:
    """A line under the table for each CSAC row whose config departs from the paper's equations
    (``paper_departures``), each row whose seeds ran with different configurations, and
    for each row with a seed that was stopped and resumed (its figure would not replay bit for
    bit from the command: the envs' states are not checkpointed)."""
    notes = []
    for r in rows:
        if departs := (r.get("safenav") or {}).get("paper_departures"):
            notes.append(f"\n{r['env']} {r['algo']} (variant): not the paper's CSAC, its config "
                         f"departs from the paper's equations in {', '.join(departs)}.")  # fmt: skip
        for impl in ("safenav", "sb3"):
            if resumed := (r.get(impl) or {}).get("resumed"):
                where = "; ".join(f"seed {seed} at {', '.join(f'{n:,}' for n in steps)} steps"
                                  for seed, steps in sorted(resumed.items()))  # fmt: skip
                notes.append(f"\n{r['env']} {r['algo']} ({impl}): resumed from a checkpoint "
                             f"({where}); a rerun of the command, uninterrupted, continues "
                             "differently from there.")  # fmt: skip
            if differ := (r.get(impl) or {}).get("config_differs"):
                shown = ", ".join(differ[:6]) + (
                    f" and {len(differ) - 6} more" if len(differ) > 6 else ""
                )
                notes.append(f"\n**{r['env']} {r['algo']} ({impl}): its seeds ran with different "
                             f"configurations** ({shown}); the row averages them.")  # fmt: skip
    return notes


def plot_curves(suite: str, results: list[dict[str, Any]], path: Path, cost_limit: float) -> None:
    """Evaluation return (and, for the safe suite, episode cost below it) against env steps: mean
    over seeds, shaded between the seeds' lowest and highest; one panel (pair) per task in the
    suite's order, three to a row for the gym suite."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    import numpy as np

    order = list(SUITES[suite])
    envs = sorted({r["trial"]["env"] for r in results}, key=order.index)
    nrows = 2 if suite == "safe" else 1  # return, and cost below it
    cols = min(len(envs), 3) if suite == "gym" else len(envs)
    blocks = -(-len(envs) // cols)
    fig, grid = plt.subplots(nrows * blocks, cols, figsize=(4.2 * cols, 3.4 * nrows * blocks),
                             squeeze=False)  # fmt: skip
    for k in range(len(envs), blocks * cols):  # the last row's empty places
        for i in range(nrows):
            grid[(k // cols) * nrows + i][k % cols].set_visible(False)
    for j, env in enumerate(envs):
        axes = [grid[(j // cols) * nrows + i] for i in range(nrows)]  # this task's: axes[i][col]
        col = j % cols
        lines: dict[str, list[dict]] = {}
        for r in results:
            t = r["trial"]
            if t["env"] == env:
                lines.setdefault(f"{t['algo']} ({t['impl']}, {_count(t['steps'])})", []).append(r)
        for label, rs in sorted(lines.items()):
            for i, field in enumerate((1, 2)[:nrows]):
                steps = sorted({p[0] for r in rs for p in r["curve"]})
                values = np.array([[dict((p[0], p[field]) for p in r["curve"]).get(s, np.nan)
                                    for s in steps] for r in rs])  # fmt: skip
                ax = axes[i][col]
                mean = np.nanmean(values, axis=0)
                ax.plot(steps, mean, label=label, ls="--" if "sb3" in label else "-")
                ax.fill_between(steps, np.nanmin(values, axis=0), np.nanmax(values, axis=0),
                                alpha=0.15)  # fmt: skip
        if suite == "gym":  # the published zoo agent's own curve, up to our longest budget
            for algo in sorted({r["trial"]["algo"] for r in results if r["trial"]["env"] == env}):
                zoo = zoo_curves.curve(env, algo)
                if zoo is None:
                    continue
                end = max(r["trial"]["steps"] for r in results
                          if r["trial"]["env"] == env and r["trial"]["algo"] == algo)  # fmt: skip
                pts = [(x, y) for x, y in zip(zoo["steps"], zoo["mean"], strict=True) if x <= end]
                if pts:
                    axes[0][col].plot(*zip(*pts, strict=True), color="0.45", lw=0.9,
                                      ls=":" if algo == "sac" else "-.",
                                      label=f"{algo} (SB3 zoo agent, published, 1 seed)")  # fmt: skip
        for row in axes:  # 100k, 1M: plain integers run into each other on a narrow panel
            row[col].xaxis.set_major_formatter(
                matplotlib.ticker.FuncFormatter(lambda x, _: _count(int(x)) if x else "0")
            )
        axes[0][col].set_title(env, fontsize=10)
        axes[0][col].set_ylabel("evaluation return")
        axes[-1][col].set_xlabel("env steps")
        axes[0][col].legend(fontsize=7)
        if suite == "safe":
            axes[1][col].axhline(cost_limit, color="k", lw=0.8, ls=":")
            axes[1][col].set_ylabel("evaluation episode cost")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report(suite: str, trials: list[Trial], out: Path, cost_limit: float) -> list[dict[str, Any]]:
    """``OUT/table.md``, ``OUT/curves.png`` and ``OUT/summary.json`` from the trial files."""
    from safenav.common.atomic import write_text_atomic
    from safenav.common.jsonout import write_json

    results = load_results(suite, out)
    if not results:
        raise SafenavRuntimeError(f"no finished trial of the {suite} suite in {out / 'trials'}")
    rows = summarize(suite, results, cost_limit)
    targets = safe_targets(rows, cost_limit) if suite == "safe" else []
    notes = _notes(suite, rows, cost_limit, targets)  # under the table and on the terminal
    for note in notes:
        say(note.strip().replace("**", ""))
    write_text_atomic(out / "table.md", markdown_table(suite, rows, cost_limit, notes))
    summary = {"suite": suite, "cost_limit": cost_limit, "rows": rows, "trials": len(results),
               "selected": len(trials)}  # fmt: skip
    if suite == "safe":
        summary["targets"] = targets
    write_json(out / "summary.json", summary)
    plot_curves(suite, results, out / "curves.png", cost_limit)
    return rows


def bench_suite(suite: str, out: Path, tasks: tuple[str, ...] = (), algos: tuple[str, ...] = (),
                seeds: int = 3, steps: int = 0, sb3: tuple[str, ...] | None = None,
                jobs: int = 1, cost_limit: float = 25.0, report_only: bool = False,
                progress: bool = True, extra: tuple[str, ...] = (),
                first_seed: int = 1, max_trials: int = 0) -> list[dict[str, Any]]:  # fmt: skip
    """Run (or, with ``report_only``, only report) a suite; see the module docstring. ``extra``:
    more ``safenav train`` options for every safenav trial (not part of a trial's name: give a
    new ``out`` when they change). ``first_seed``: 101 and up screen on seeds that no reported
    row uses (those are 1..N). ``max_trials``: run only the first that many pending trials."""
    trials = plan_trials(suite, tasks, algos, seeds, steps, sb3, first_seed)
    failures = [] if report_only else run_trials(trials, out, cost_limit, jobs, progress, extra,
                                                 max_trials)  # fmt: skip
    rows = report(suite, trials, out, cost_limit)
    print((out / "table.md").read_text(), end="")
    print(
        f"safenav bench {suite}: {out / 'table.md'}, {out / 'curves.png'}, {out / 'summary.json'}"
    )
    if failures:
        raise SafenavRuntimeError(f"{len(failures)} trial(s) failed: {'; '.join(failures)}")
    return rows


__all__ = ["Trial", "bench_suite", "plan_trials", "report", "run_trials", "summarize", "within"]
