"""``safenav tune``: a validation-only hyperparameter search for one algorithm on SafeNav-v1.

The comparison (issue 21, docs/reproduce.md) asks each algorithm to get a comparable tuning
effort, every choice made on validation maps only. This is the tool that makes the effort the same
by construction: N configurations per algorithm, the same budget, training seed and score.

- **Space**: a TOML file (:func:`load_space`): the recipe it starts from and, per option, a range
  (``low``/``high``, ``log``) or ``choices``. One ships per algorithm
  (``safenav/experiments/spaces/<recipe>.toml``); a path gives your own.
- **Configurations**: trial 0 is the recipe unchanged (a tuning can only replace it with something
  better on validation); trials 1.. take the points of a scrambled Sobol sequence
  (``scipy.stats.qmc``) mapped into the space. A sequence, not a sample of N: the first k
  configurations are the same whatever N is, so a tuning grows by rerunning with a larger N.
- **Each trial**: ``safenav train --algo ALGO --config RECIPE --seed SEED --total-steps B
  --keep-policies`` plus its options, a child process that resumes from its checkpoint when
  interrupted; then its policy chosen on validation alone (the greedy soup of
  :func:`~safenav.experiments.selection.select_final_policy`, as ``--select`` does) and scored on
  ``episodes`` validation episodes (:data:`~safenav.experiments.selection.VALIDATION_SEEDS`):
  success and collision rate. No tuning path flies the test or held-out maps (seeds 1-6).
- **Output** (``OUT``): ``trials/tNNN.json`` per finished trial (to commit; a rerun skips it),
  ``runs/`` and ``logs/`` (not to commit), ``space.json`` (a rerun with another space is
  refused), ``results.md`` (every trial, best first) and ``best.toml``, a recipe file
  (``safenav train --config OUT/best.toml``) of the trial with the highest validation success
  (ties: lower collision, then the earlier trial).
"""

from __future__ import annotations

import json
import math
import sys
import time
import warnings
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from safenav.errors import SafenavError
from safenav.recipes import PPO_ALGOS, tomllib

SPACES = "safenav.experiments.spaces"
MAX_PARAMS = 16


@dataclass(frozen=True)
class Param:
    """One option of the search: ``name`` is its dotted config path (``csac.actor_lr``)."""

    name: str
    low: float | None = None
    high: float | None = None
    log: bool = False
    integer: bool = False
    choices: tuple[Any, ...] = ()

    def value(self, u: float) -> Any:
        """The option's value at ``u`` in [0, 1) (one coordinate of a Sobol point)."""
        if self.choices:
            return self.choices[min(int(u * len(self.choices)), len(self.choices) - 1)]
        lo, hi = float(self.low), float(self.high)  # type: ignore[arg-type]
        x = (
            math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))
            if self.log
            else lo + u * (hi - lo)
        )
        return int(round(x)) if self.integer else float(f"{x:.4g}")


@dataclass(frozen=True)
class Space:
    algo: str
    recipe: str
    params: tuple[Param, ...]
    source: str
    seed: int = 0

    def configurations(self, n: int) -> list[dict[str, Any]]:
        """The first ``n`` configurations: ``{}`` (the recipe as it is), then Sobol points."""
        try:
            from scipy.stats import qmc
        except ImportError:
            raise SafenavError(
                "safenav tune needs scipy: pip install 'safenav[experiments]'"
            ) from None

        if n <= 1 or not self.params:
            return [{}][:n]
        # always MAX_PARAMS dimensions, the space's options taking the first ones: so an option
        # at the same place in two spaces takes the same values (sac's and sac-lag's tunings
        # try the same learning rates; the scramble of a dimension depends on how many there are)
        sampler = qmc.Sobol(MAX_PARAMS, scramble=True, seed=self.seed)
        with warnings.catch_warnings():  # balance properties need 2^k points; a prefix is wanted
            warnings.simplefilter("ignore", UserWarning)
            points = sampler.random(n - 1)
        return [{}] + [{p.name: p.value(float(u)) for p, u in zip(self.params, row, strict=False)}
                       for row in points]  # fmt: skip

    def record(self) -> dict[str, Any]:
        return {"algo": self.algo, "recipe": self.recipe, "space_seed": self.seed, "source": self.source,
                "params": [p.__dict__ | {"choices": list(p.choices)} for p in self.params]}  # fmt: skip


def load_space(name_or_path: str, seed: int = 0) -> Space:
    """A search space: a shipped name (``sac``, ``sac-lag``, ``ppo``, ``ppo-lag``, ``csac``) or a
    TOML file::

        algo = "sac"
        recipe = "sac"                      # the recipe every trial starts from
        [params]
        "csac.actor_lr" = { low = 1e-4, high = 1e-3, log = true }
        "csac.updates_per_step" = { choices = [0.015625, 0.03125, 0.0625] }
    """
    path = Path(name_or_path)
    if name_or_path.endswith(".toml") or path.exists():
        if not path.is_file():
            raise SafenavError(f"--space {name_or_path}: no such file")
        text, source = path.read_text(), str(path.resolve())
    else:
        shipped = resources.files(SPACES) / f"{name_or_path}.toml"
        if not shipped.is_file():
            names = sorted(p.name[:-5] for p in resources.files(SPACES).iterdir()
                           if p.name.endswith(".toml"))  # fmt: skip
            raise SafenavError(f"--space {name_or_path}: unknown; shipped: {', '.join(names)} (or "
                               "a path to a .toml file)")  # fmt: skip
        text, source = shipped.read_text(), f"safenav/experiments/spaces/{name_or_path}.toml"
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise SafenavError(f"--space {name_or_path}: not valid TOML ({err})") from None
    if not isinstance(data.get("algo"), str) or not isinstance(data.get("recipe"), str):
        raise SafenavError(f'--space {name_or_path}: needs algo = "..." and recipe = "..."')
    params = [_param(name, spec, name_or_path) for name, spec in (data.get("params") or {}).items()]
    family = "ppo" if data["algo"] in PPO_ALGOS else "csac"
    alien = [p.name for p in params if p.name.split(".")[0] not in ("run", family)]
    if alien:
        raise SafenavError(f"--space {name_or_path}: {alien} do nothing for --algo {data['algo']} "
                           f"(its options are run.* and {family}.*)")  # fmt: skip
    if len(params) > MAX_PARAMS:
        raise SafenavError(f"--space {name_or_path}: {len(params)} options; at most {MAX_PARAMS}")
    return Space(data["algo"], data["recipe"], tuple(params), source, seed)


def _param(name: str, spec: Any, where: str) -> Param:
    if (
        not isinstance(spec, dict)
        or name.count(".") < 1
        or name.split(".")[0] not in ("csac", "ppo", "run")
    ):
        raise SafenavError(f"--space {where}: {name!r} must be a dotted option of run, csac or ppo "
                           "with a table { low, high[, log, integer] } or { choices = [...] }")  # fmt: skip
    unknown = set(spec) - {"low", "high", "log", "integer", "choices"}
    if unknown:
        raise SafenavError(f"--space {where}: {name}: unknown keys {sorted(unknown)}")
    if "choices" in spec:
        choices = spec["choices"]
        if not isinstance(choices, list) or not choices:
            raise SafenavError(f"--space {where}: {name}: choices must be a non-empty list")
        return Param(name, choices=tuple(tuple(c) if isinstance(c, list) else c for c in choices))
    lo, hi = spec.get("low"), spec.get("high")
    ok = all(
        isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
        for v in (lo, hi)
    )
    if not ok or not lo < hi or (spec.get("log") and lo <= 0):  # type: ignore[operator]
        raise SafenavError(f"--space {where}: {name}: needs finite low < high (> 0 with log)")
    return Param(name, float(lo), float(hi), bool(spec.get("log", False)),
                 bool(spec.get("integer", False)))  # fmt: skip


def option_args(params: dict[str, Any]) -> list[str]:
    """``safenav train`` options for a configuration (a list value gives several words):
    ``csac.actor_lr`` -> ``--csac.actor-lr``, ``run.num_envs`` -> ``--num-envs`` (the run options
    have no prefix)."""
    args: list[str] = []
    for name, value in params.items():
        flag = "--" + name.removeprefix("run.").replace("_", "-")
        if isinstance(value, bool):
            dotted, _, last = flag[2:].rpartition(".")
            args.append(f"--{dotted + '.' if dotted else ''}{'' if value else 'no-'}{last}")
        elif isinstance(value, list | tuple):
            args += [flag, *map(str, value)]
        else:
            args += [flag, str(value)]
    return args


def score_run(run_dir: Path, episodes: int = 400, device: str = "cpu") -> dict[str, Any]:
    """A finished tuning run's policy chosen on validation (``RUN_DIR/policy.pt``, as ``--select``
    does) and its success and collision rates on ``episodes`` validation episodes, spread over
    :data:`~safenav.experiments.selection.VALIDATION_SEEDS`. Validation maps only."""
    from safenav.experiments.evaluate import evaluate
    from safenav.experiments.flight import resolve_policy
    from safenav.experiments.selection import VALIDATION_SEEDS, own_shield, select_final_policy

    selection = select_final_policy(run_dir, device=device)
    fn, cfg = resolve_policy(run_dir / "policy.pt", "checkpoint", device)
    per_map = max(1, math.ceil(episodes / len(VALIDATION_SEEDS)))
    maps = []
    for seed in VALIDATION_SEEDS:
        res = evaluate(
            fn, cfg, env_seed=seed, episodes=per_map, device=device, shield=own_shield(fn)
        )
        maps.append({"env_seed": seed, "episodes": per_map, "success_rate": res["success_rate"],
                     "collision_rate": res["collision_rate"]})  # fmt: skip
    mean = {
        k: float(sum(m[k] for m in maps) / len(maps)) for k in ("success_rate", "collision_rate")
    }
    return {**mean, "episodes": per_map * len(maps), "per_map": maps,
            "chosen_steps": selection["chosen_steps"], "selection": selection["method"]}  # fmt: skip


def _rank_key(trial: dict[str, Any]) -> tuple[float, float, int]:
    v = trial["validation"]
    return (-v["success_rate"], v["collision_rate"], trial["index"])


def write_report(out: Path, space: Space, trials: list[dict[str, Any]],
                 fixed: dict[str, Any] | None = None) -> Path | None:  # fmt: skip
    """``OUT/results.md`` (every finished trial, best first) and ``OUT/best.toml``."""
    ranked = sorted(trials, key=_rank_key)
    names = [p.name for p in space.params]
    head = (
        "| trial | "
        + " | ".join(f"`{n}`" for n in names)
        + " | val. success | val. collision | wall clock |"
    )
    lines = [f"# safenav tune: {space.algo} from recipe `{space.recipe}`", "",
             f"Space: `{space.source}`. {len(trials)} trials finished; each trains "
             f"{trials[0]['total_steps'] if trials else '?'} env steps with training seed "
             f"{trials[0]['seed'] if trials else '?'}, its policy chosen and scored on validation maps "
             "only (success and collision rate). Trial 0 is the recipe unchanged.", "",
             head, "|" + "---|" * (len(names) + 4)]  # fmt: skip
    for t in ranked:
        cells = [_cell(t["params"].get(n, "recipe")) for n in names]
        v = t["validation"]
        lines.append(f"| {t['index']} | " + " | ".join(cells) + f" | {v['success_rate']:.3f} | "
                     f"{v['collision_rate']:.3f} | {t['wall_clock_s'] / 60:.1f} min |")  # fmt: skip
    (out / "results.md").write_text("\n".join(lines) + "\n")
    if not ranked:
        return None
    best = ranked[0]
    path = out / "best.toml"
    path.write_text(best_recipe(space, best, fixed))
    return path


def _cell(value: Any) -> str:
    return ", ".join(map(str, value)) if isinstance(value, list | tuple) else str(value)


def best_recipe(space: Space, best: dict[str, Any], fixed: dict[str, Any] | None = None) -> str:
    """A recipe file: the space's recipe with what every trial changed (``fixed``: the preset and
    ``--train-args``) and the best trial's values, dotted names as TOML sections."""
    v = best["validation"]
    what = ("its own values of the searched options (trial 0 was best)" if not best["params"]
            else "the best trial's values")  # fmt: skip
    lines = [f"# {space.algo}, tuned: recipe {space.recipe} with {what}, chosen by safenav tune",
             f"# ({space.source}) on validation maps only: trial {best['index']} of "
             f"{best['trials_planned']}, validation success {v['success_rate']:.3f} / collision "
             f"{v['collision_rate']:.3f} ({v['episodes']} episodes), {best['total_steps']} env steps,",
             f"# training seed {best['seed']}, {best['date']}.", "",
             "[recipe]", f"algo = {_toml(space.algo)}", f"base = {_toml(space.recipe)}"]  # fmt: skip
    sections: dict[str, list[str]] = {}
    for name, value in ({**(fixed or {}), **best["params"]}).items():
        section, _, key = name.rpartition(".")
        sections.setdefault(section, []).append(f"{key} = {_toml(value)}")
    for section, items in sections.items():
        lines += ["", f"[{section}]", *items]
    return "\n".join(lines) + "\n"


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(value)


def tune(space: Space, out: Path, trials: int = 8, total_steps: int = 1_000_000, seed: int = 101,
         episodes: int = 400, jobs: int = 1, torch_threads: int = 2, preset: str = "paper",
         extra: tuple[str, ...] = (), fixed: dict[str, Any] | None = None,
         progress: bool = True) -> list[dict[str, Any]]:  # fmt: skip
    """Run (or resume) ``trials`` configurations of ``space`` into ``out``; returns the finished
    trial records. ``extra``: more ``safenav train`` options for every trial; ``fixed``: what
    they and ``preset`` change in the recipe's values (dotted names), written into ``best.toml``
    so that it trains as the trials did. See the module docstring."""
    from rich.console import Console

    from safenav.common.child_runs import ChildRun, run_queue
    from safenav.common.jsonout import write_json
    from safenav.common.machine import machine_description
    from safenav.experiments.aggregate import last_step

    for sub in ("trials", "runs", "logs"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    configs = space.configurations(trials)  # first: a missing scipy is refused before any write
    record = space.record() | {"total_steps": total_steps, "train_seed": seed, "episodes": episodes,
                               "preset": preset, "train_args": list(extra),
                               "fixed": fixed or {}}  # fmt: skip
    record_path = out / "space.json"
    if record_path.exists():
        before = json.loads(record_path.read_text())
        if before != json.loads(json.dumps(record)):
            raise SafenavError(f"{out} holds a tuning with another space, budget, seed or options "
                               f"({record_path}); give a new --out")  # fmt: skip
    else:
        write_json(record_path, record)
    for i, params in enumerate(configs):  # a finished trial must be the configuration asked for
        path = out / "trials" / f"t{i:03d}.json"
        if path.exists() and json.loads(path.read_text())["params"] != json.loads(
            json.dumps(params)
        ):
            raise SafenavError(f"{path} tried other values than configuration {i} of this space "
                               "(another scipy's Sobol sequence?); give a new --out")  # fmt: skip

    def child(index: int, params: dict[str, Any]) -> ChildRun:
        name = f"t{index:03d}"
        run_dir = out / "runs" / name
        train = [sys.executable, "-m", "safenav", "train", "--no-progress", "--no-tensorboard",
                 "--torch-threads", str(torch_threads), "--total-steps", str(total_steps)]  # fmt: skip
        args = ["--algo", space.algo, "--config", space.recipe, "--preset", preset, "--seed",
                str(seed), "--keep-policies", "--run-dir", str(run_dir), "--overwrite",
                *option_args(params), *extra]  # fmt: skip

        def command() -> list[str]:
            if (run_dir / "checkpoint.pt").is_file():  # its config.json holds the rest
                return [*train, "--algo", space.algo, "--resume", str(run_dir)]
            return [*train, *args]

        def finish(wall_s: float) -> str:
            import torch

            t0 = time.perf_counter()
            torch.set_num_threads(torch_threads)  # beside the other running trials, not over them
            validation = score_run(run_dir, episodes)
            train_s = max(wall_s, _elapsed(run_dir))  # all sessions of a resumed run
            trial = {"index": index, "name": name, "algo": space.algo, "recipe": space.recipe,
                     "params": params, "args": option_args(params), "seed": seed,
                     "total_steps": total_steps, "trials_planned": trials, "validation": validation,
                     "wall_clock_s": round(train_s + time.perf_counter() - t0, 1),
                     "command": " ".join(["safenav", "train", *train[4:], *args]),
                     "machine": machine_description(), "date": time.strftime("%Y-%m-%d")}  # fmt: skip
            write_json(out / "trials" / f"{name}.json", trial)
            return (f"{name} done: validation success {validation['success_rate']:.3f}, collision "
                    f"{validation['collision_rate']:.3f}, {trial['wall_clock_s'] / 60:.1f} min")  # fmt: skip

        return ChildRun(name, total_steps, command, lambda: last_step(run_dir), finish,
                        out / "logs" / f"{name}.log")  # fmt: skip

    todo = [
        (i, p) for i, p in enumerate(configs) if not (out / "trials" / f"t{i:03d}.json").exists()
    ]
    _say(f"{space.algo}: {len(configs)} configurations, {len(configs) - len(todo)} already done "
        f"(skipped), {len(todo)} to run, {total_steps} env steps each; results in {out}")  # fmt: skip
    failures = run_queue([child(i, p) for i, p in todo], jobs, _say, progress, Console(stderr=True))
    done = [json.loads(p.read_text()) for p in sorted((out / "trials").glob("t*.json"))]
    done = [t for t in done if t["index"] < trials]
    best = write_report(out, space, done, fixed or {})
    _say(f"{out / 'results.md'}" + (f", {best} (safenav train --config {best})" if best else ""))
    if failures:
        raise SafenavError(f"{len(failures)} trial(s) failed: {'; '.join(failures)}; rerun the "
                           "same command to resume or retry them")  # fmt: skip
    return done


def _elapsed(run_dir: Path) -> float:
    """The run's training wall clock from its last progress row (it adds up resumed sessions)."""
    from safenav.experiments.aggregate import elapsed_seconds, read_progress

    try:
        elapsed = elapsed_seconds(read_progress(run_dir))
    except OSError:
        return 0.0
    return float(elapsed[-1]) if elapsed is not None and len(elapsed) else 0.0


def _say(text: str) -> None:
    print(f"safenav tune: {text}", file=sys.stderr, flush=True)


__all__ = [
    "Param",
    "Space",
    "best_recipe",
    "load_space",
    "option_args",
    "score_run",
    "tune",
    "write_report",
]
