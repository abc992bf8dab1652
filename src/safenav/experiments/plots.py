"""The paper's figures from run directories: Fig. 3 (learning curves), Fig. 4 (test results),
and the Lagrange multiplier λ and cost threshold d over training.

Inputs are run directories of ``safenav train`` (``progress.csv``; ``eval.json`` from
``safenav eval`` for Fig. 4) or directories that contain them, e.g. a ``safenav reproduce``
output. Runs are grouped by algorithm (:func:`safenav.experiments.aggregate.run_identity`).

Curves of different seeds are logged at different steps; each seed is linearly interpolated onto
a common grid of env steps, and the mean ± std (sample std, ddof=1) is taken over the seeds that
cover each grid point, so a grid point beyond a short seed's last step averages the others.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import FuncFormatter, PercentFormatter  # noqa: E402

from safenav.errors import SafenavError  # noqa: E402
from safenav.experiments.aggregate import (  # noqa: E402
    PAPER_RESULTS,
    budget_label_algo,
    confidence_intervals,
    display_name,
    mean_std,
    read_json,
    read_progress,
    run_identity,
)
from safenav.experiments.stats import bootstrap_ci  # noqa: E402

COLORS: dict[str, str] = {
    "csac": "#d62728",
    "sac": "#1f77b4",
    "ppo": "#2ca02c",
    "ppo_lag": "#9467bd",
    "sac_lag": "#ff7f0e",
}
#: Labels with no algorithm colour of their own (ablations, tuned recipes), in order; distinct from
#: the algorithm colours and their dark shades, enough for results/paper's 8 such labels and more
#: (they once wrapped round after 5: ppo_tuned_3m and sac_tuned_3m shared a pink).
_EXTRA_COLORS = ("#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f", "#000000", "#e7ba52",
                 "#637939", "#5254a3", "#ad494a", "#6baed6", "#fd8d3c", "#9c9ede", "#e7969c")  # fmt: skip
LINESTYLES: dict[str, str] = {"csac": "-", "sac": "--", "ppo": "-.", "ppo_lag": ":", "sac_lag": ":"}
#: Algorithms without a Lagrange multiplier; their constraint columns (if any) are not plotted.
UNCONSTRAINED = frozenset({"sac", "ppo"})


@dataclass
class Run:
    """One training run: its algorithm label, seed, directory, progress table and test result."""

    algo: str
    seed: int | None
    run_dir: Path
    progress: dict[str, np.ndarray]
    eval: dict[str, Any] | None


def find_runs(paths: Sequence[str | Path]) -> list[Run]:
    """Every run directory (one holding ``progress.csv``) among or below ``paths``, and every
    trial record (``trials/*.json`` of a ``safenav reproduce`` output, or such a file given
    directly) whose algorithm and seed no run directory has: a fresh clone of a sweep has its
    committed trial files but not its (ignored) run directories.

    Below a directory that holds trial records (a ``safenav reproduce`` output), a run directory
    without a record is an unfinished (running or interrupted) trial and is left out: its curve
    would count as one more seed, cut short."""
    dirs: list[Path] = []
    records: list[Path] = []
    sweeps: set[Path] = set()
    for p in map(Path, paths):
        if not p.exists():
            raise SafenavError(f"{p} does not exist: pass run directories or a reproduce --out")
        if p.is_file() and p.suffix == ".json":
            records.append(p)
        elif (p / "progress.csv").exists():
            dirs.append(p)
        else:
            dirs += sorted(f.parent for f in p.rglob("progress.csv"))
            found = sorted(f for f in p.rglob("trials/*.json"))
            records += found
            sweeps.update(f.parent.parent for f in found)
    from_records = [r for r in map(run_from_record, dict.fromkeys(records)) if r is not None]
    recorded = {(r.algo, r.seed) for r in from_records}
    runs = []
    for d in dict.fromkeys(dirs):
        progress = read_progress(d)
        if not progress or len(progress.get("global_step", ())) == 0:
            continue
        algo, seed = run_identity(d)
        if (algo, seed) not in recorded and any(s in d.parents for s in sweeps):
            continue  # an unfinished trial of a sweep
        runs.append(Run(algo, seed, d, progress, read_json(d / "eval.json")))
    have = {(r.algo, r.seed) for r in runs}
    for run in from_records:
        if (run.algo, run.seed) not in have:
            runs.append(run)
            have.add((run.algo, run.seed))
    if not runs:
        raise SafenavError(f"no run directories with a non-empty progress.csv and no trial "
                           f"records in {[str(p) for p in paths]}")  # fmt: skip
    return runs


def run_from_record(path: Path) -> Run | None:
    """A :class:`Run` from a trial record of ``safenav reproduce`` (``trials/LABEL-sSEED.json``):
    its validation curve as the progress table (``eval/*`` columns and ``time/elapsed_s``) and its
    test result as the evaluation; None if the file is no such record."""
    rec = read_json(path)
    if not isinstance(rec, dict) or not isinstance(rec.get("algo"), str):
        return None
    curve = rec.get("validation_curve") or []
    progress: dict[str, np.ndarray] = {}
    if curve:

        def column(key: str) -> np.ndarray:
            return np.array([np.nan if p.get(key) is None else float(p[key]) for p in curve])

        progress = {"global_step": column("env_steps"), "time/elapsed_s": column("wall_clock_s")}
        for key in ("success", "collision", "timeout"):
            progress[f"eval/{key}_rate"] = column(f"{key}_rate")
    test = None
    if rec.get("success_rate") is not None:
        test = {k: rec.get(k) for k in ("success_rate", "collision_rate", "timeout_rate")}
        test["episodes"] = rec.get("eval_episodes")
    if not progress and test is None:
        return None
    return Run(rec["algo"], rec.get("seed"), path, progress, test)


#: A dark shade of each fixed colour, for the same algorithm at another budget (``csac_3m``).
DARK_COLORS: dict[str, str] = {
    "csac": "#7f0000",
    "sac": "#08306b",
    "ppo": "#00441b",
    "ppo_lag": "#3f007d",
    "sac_lag": "#a63603",
}


def budget_base(label: str) -> str | None:
    """``"csac_3m"`` -> ``"csac"``: the algorithm of a label that names another budget, where
    that algorithm has a fixed colour, else None."""
    algo = budget_label_algo(label)
    return algo if algo in COLORS else None


def color_of(algo: str, order: Sequence[str]) -> str:
    """The algorithm's fixed colour (CSAC red, SAC blue, PPO green, ...); at another budget
    (``csac_3m``) a dark shade of it, so that each algorithm keeps its hue across budgets."""
    if algo in COLORS:
        return COLORS[algo]
    if (base := budget_base(algo)) is not None:
        return DARK_COLORS[base]
    extras = [a for a in order if a not in COLORS and budget_base(a) is None]
    return _EXTRA_COLORS[extras.index(algo) % len(_EXTRA_COLORS)] if algo in extras else "#333"


def linestyle_of(algo: str) -> str:
    """The algorithm's line style, the same at every budget."""
    return LINESTYLES.get(algo, LINESTYLES.get(budget_base(algo) or "", "-"))


def group(runs: Sequence[Run]) -> dict[str, list[Run]]:
    """Runs by algorithm, the paper's algorithms first (CSAC, SAC, PPO), then in given order."""
    groups: dict[str, list[Run]] = {}
    for r in runs:
        groups.setdefault(r.algo, []).append(r)
    known = [a for a in ("csac", "sac", "ppo", "sac_lag", "ppo_lag") if a in groups]
    return {a: groups[a] for a in known + [a for a in groups if a not in known]}


def smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average over ``window`` logged rows (NaN-aware); 1 = unchanged."""
    if window <= 1:
        return values
    ok = np.isfinite(values)
    v = np.where(ok, values, 0.0)
    csum = np.cumsum(np.insert(v, 0, 0.0))
    cnt = np.cumsum(np.insert(ok.astype(float), 0, 0.0))
    idx = np.arange(1, len(values) + 1)
    lo = np.maximum(idx - window, 0)
    n = cnt[idx] - cnt[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (csum[idx] - csum[lo]) / n, np.nan)


def resample(
    steps: np.ndarray,
    values: np.ndarray,
    grid: np.ndarray,
    hold: bool = False,
    until: float | None = None,
) -> np.ndarray:
    """``values`` logged at ``steps`` interpolated onto ``grid``; NaN outside the logged range.

    ``hold``: keep the last logged value until the next (for step functions such as ``d``).
    ``until``: the last value holds up to this step (a run's last rows may have no value, e.g.
    no episode ended in that interval); default: the last step with a value.
    """
    ok = np.isfinite(steps) & np.isfinite(values)
    if ok.sum() == 0:
        return np.full(grid.shape, np.nan)
    s, v = steps[ok], values[ok]
    order = np.argsort(s, kind="stable")
    s, v = s[order], v[order]
    if hold:
        out = v[np.clip(np.searchsorted(s, grid, side="right") - 1, 0, len(s) - 1)]
    else:
        out = np.interp(grid, s, v)
    end = s[-1] if until is None else max(until, s[-1])
    out[(grid < s[0]) | (grid > end)] = np.nan
    return out


def mean_curve(
    runs: Sequence[Run], column: str, points: int = 200, window: int = 1, hold: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int] | None:
    """``(grid, mean, std, seeds)`` of ``column`` over ``runs``, or None if none logged it.

    The grid spans the steps every seed covers (from the earliest first value to the shortest
    seed's last logged step), so the mean never jumps where a seed ends.
    """
    series = []
    for r in runs:
        if column in r.progress and np.isfinite(r.progress[column]).any():
            steps = r.progress["global_step"]
            series.append((steps, smooth(r.progress[column], window), float(np.nanmax(steps))))
    if not series:
        return None
    lo = min(np.nanmin(s[np.isfinite(v)]) for s, v, _ in series)
    hi = min(last for _, _, last in series)
    grid = np.linspace(lo, hi, points) if hi > lo else np.array([hi])
    stack = np.stack([resample(s, v, grid, hold, last) for s, v, last in series])
    count = np.isfinite(stack).sum(axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: no seed covers them
        mean = np.nanmean(stack, axis=0)
        std = np.where(count > 1, np.nanstd(stack, axis=0, ddof=1), 0.0)
    keep = count > 0
    return grid[keep], mean[keep], std[keep], len(series)


def _fmt_step_tick(x: float, _pos: Any = None) -> str:
    if x >= 1e6:
        return f"{x / 1e6:g}M"
    if x >= 1e3:
        return f"{x / 1e3:g}k"
    return f"{x:g}"


def _steps_axis(ax: Any) -> None:
    ax.xaxis.set_major_formatter(FuncFormatter(_fmt_step_tick))
    ax.set_xlabel("environment steps")
    ax.grid(alpha=0.3)


def _curve_panel(ax, groups, column, ylabel, title, percent, window, hold=False) -> bool:
    drew = False
    order = list(groups)
    for algo, runs in groups.items():
        curve = mean_curve(runs, column, 400 if hold else 200, window, hold)
        if curve is None:
            continue
        grid, mean, std, n = curve
        scale = 100.0 if percent else 1.0
        color = color_of(algo, order)
        label = f"{display_name(algo)} ({n} seed{'s' if n != 1 else ''})"
        ax.plot(grid, mean * scale, color=color, lw=2, label=label, ls=linestyle_of(algo),
                drawstyle="steps-post" if hold else "default")  # fmt: skip
        ax.fill_between(grid, (mean - std) * scale, (mean + std) * scale, color=color, alpha=0.2,
                        lw=0, step="post" if hold else None)  # fmt: skip
        drew = True
    ax.set_title(title)
    ax.set_ylabel(ylabel)
    _steps_axis(ax)
    if percent:
        ax.set_ylim(-2, 102)
        ax.yaxis.set_major_formatter(PercentFormatter(100, decimals=0))
    if drew:
        ax.legend(loc="best", fontsize=9)
    return drew


def _curves(groups: dict[str, list[Run]], out: Path, window: int, title: str,
            panels: tuple[tuple[str, str, str, bool], ...]) -> Path | None:  # fmt: skip
    """One row of :func:`_curve_panel` figures, one per ``(column, ylabel, title, percent)``."""
    fig, axes = plt.subplots(1, len(panels), figsize=(13, 4.8), constrained_layout=True)
    drew = [
        _curve_panel(ax, groups, *panel, window) for ax, panel in zip(axes, panels, strict=True)
    ]
    fig.suptitle(title, fontsize=13)
    return _save(fig, out) if any(drew) else _discard(fig)


def plot_learning_curves(groups: dict[str, list[Run]], out: Path, window: int = 1) -> Path | None:
    """Fig. 3: training success rate and collision rate vs env steps, mean ± std over seeds."""
    return _curves(groups, out, window, "Learning curves (cf. paper Fig. 3): mean over seeds, "
                   "shading ± 1 std", (
        ("charts/success_rate", "success rate (% of episodes)", "Success rate during training", True),
        ("charts/collision_rate", "collision rate (% of episodes)", "Collision rate during training",
         True)))  # fmt: skip


def ci95_band(stack: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """95 % bootstrap interval of the mean over seeds (rows of ``stack``) at each grid point
    (column; :func:`safenav.experiments.stats.bootstrap_ci`); NaN cells (a seed that does not
    cover the point) are left out, and a point one seed covers gets that seed's value as both
    ends."""
    low, high = np.full(stack.shape[1], np.nan), np.full(stack.shape[1], np.nan)
    for j in range(stack.shape[1]):
        col = stack[:, j][np.isfinite(stack[:, j])]
        if len(col):
            low[j], high[j] = bootstrap_ci(np.mean, col) or (col[0], col[0])
    return low, high


def _validation_panel(ax, groups, column: str, x_column: str, title: str, ylabel: str) -> bool:
    """Mean over seeds of an evaluation rate against env steps or wall-clock, 95 % CI band."""
    drew, order = False, list(groups)
    for algo, runs in groups.items():
        series = []
        for r in runs:
            x, y = r.progress.get(x_column), r.progress.get(column)
            if x is None or y is None:
                continue
            ok = np.isfinite(x) & np.isfinite(y)
            if ok.any():
                series.append((x[ok], y[ok]))
        if not series:
            continue
        # the span every seed covers, so the mean never averages a changing set of seeds
        lo = max(float(x.min()) for x, _ in series)
        hi = min(float(x.max()) for x, _ in series)
        grid = np.linspace(lo, hi, 100) if hi > lo else np.array([hi])
        stack = np.stack([resample(x, y, grid) for x, y in series])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(stack, axis=0)
        low, high = ci95_band(stack)
        scale = 1 / 60 if x_column == "time/elapsed_s" else 1.0
        color = color_of(algo, order)
        n = len(series)
        ax.plot(grid * scale, mean * 100, color=color, lw=2, ls=linestyle_of(algo),
                label=f"{display_name(algo)} ({n} seed{'s' if n != 1 else ''})")  # fmt: skip
        for x, y in series:  # each seed's evaluations, so the reader sees where the band comes from
            ax.plot(x * scale, y * 100, "o", color=color, ms=3, alpha=0.5)
        ax.fill_between(grid * scale, low * 100, high * 100, color=color, alpha=0.2, lw=0)
        drew = True
    ax.set_title(title)
    ax.set_ylabel(ylabel)
    ax.set_ylim(-2, 102)
    ax.yaxis.set_major_formatter(PercentFormatter(100, decimals=0))
    ax.grid(alpha=0.3)
    if x_column == "time/elapsed_s":
        ax.set_xlabel("wall-clock of training (minutes)")
    else:
        _steps_axis(ax)
    if drew:
        ax.legend(loc="best", fontsize=9)
    return drew


def plot_validation_curves(groups: dict[str, list[Run]], out: Path) -> Path | None:
    """Fig. 3 from the periodic evaluations on the validation maps (the same episodes at every
    point, full density, deterministic policy): success and collision against env steps (top) and
    against training wall-clock (bottom), mean over seeds with a 95 % bootstrap CI band. Unlike the
    training-episode curves, a map redraw that resets every env at once cannot bias it."""
    fig, axes = plt.subplots(2, 2, figsize=(13, 9), constrained_layout=True)
    drew = [
        _validation_panel(axes[row, col], groups, f"eval/{key}_rate", x, title, f"{key} rate")
        for row, (x, when) in enumerate((("global_step", "env steps"),
                                         ("time/elapsed_s", "wall-clock")))
        for col, (key, title) in enumerate((("success", f"Validation success vs {when}"),
                                            ("collision", f"Validation collision vs {when}")))
    ]  # fmt: skip
    fig.suptitle("Learning curves on the validation maps (cf. paper Fig. 3): mean over seeds, "
                 "band = 95 % bootstrap CI, dots = each seed", fontsize=13)  # fmt: skip
    return _save(fig, out) if any(drew) else _discard(fig)


def plot_return_cost(groups: dict[str, list[Run]], out: Path, window: int = 1) -> Path | None:
    """Episodic return and episodic cost (collisions per episode) during training."""
    return _curves(groups, out, window, "Return and cost: mean over seeds, shading ± 1 std", (
        ("charts/episodic_return", "return per episode", "Episodic return during training", False),
        ("charts/episodic_cost", "cost per episode (collisions)", "Episodic cost during training",
         False)))  # fmt: skip


def plot_constraint(groups: dict[str, list[Run]], out: Path) -> Path | None:
    """λ (Lagrange multiplier) and d (cost threshold, curriculum) over training, CSAC family."""
    constrained = {a: r for a, r in groups.items() if a not in UNCONSTRAINED}
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), constrained_layout=True)
    ok = _curve_panel(axes[0], constrained, "constraint/lambda", "λ (dimensionless)",
                      "Lagrange multiplier λ", False, 1)  # fmt: skip
    ok |= _curve_panel(axes[1], constrained, "constraint/d", "d (cost threshold)",
                       "Cost threshold d (constraint curriculum)", False, 1, hold=True)  # fmt: skip
    d_values = [y for line in axes[1].get_lines() for y in line.get_ydata() if y > 0]
    if d_values and max(d_values) / min(d_values) > 20:
        axes[1].set_yscale("log")  # a curriculum down to d_min near 0 spans decades
    fig.suptitle("Constraint: λ and d over training, mean over seeds, shading ± 1 std",
                 fontsize=13)  # fmt: skip
    return _save(fig, out) if ok else _discard(fig)


def eval_table(groups: dict[str, list[Run]]) -> dict[str, dict[str, Any]]:
    """Per algorithm: mean/std of test success and collision rates over its evaluated seeds, and
    their 95 % intervals (``ci95``: bootstrap over seeds, else Wilson on the pooled episodes for
    a single seed; :func:`safenav.experiments.aggregate.confidence_intervals`)."""
    table = {}
    for algo, runs in groups.items():
        evals = [r.eval for r in runs if r.eval and r.eval.get("success_rate") is not None]
        if evals:
            table[algo] = {
                "success_rate": mean_std(e["success_rate"] for e in evals),
                "collision_rate": mean_std(e["collision_rate"] for e in evals),
                "seeds": len(evals),
                "episodes": evals[0].get("episodes"),
                "ci95": {},
            }
            for key in ("success_rate", "collision_rate"):
                ci = confidence_intervals([(e[key], e.get("episodes")) for e in evals])
                mean = table[algo][key]["mean"]
                bounds = (
                    (ci or {}).get("bootstrap_seeds") or (ci or {}).get("wilson") or [mean, mean]
                )
                table[algo]["ci95"][key] = bounds
    return table


def plot_test_results(groups: dict[str, list[Run]], out: Path) -> Path | None:
    """Fig. 4: test success and collision rates, ours (mean ± std bars) beside the paper's."""
    from matplotlib.patches import Patch

    table = eval_table(groups)
    if not table:
        return None
    algos = list(table)
    fig, axes = plt.subplots(1, 2, figsize=(max(10.0, 2.0 * len(algos) + 5), 5.0),
                             constrained_layout=True)  # fmt: skip
    x = np.arange(len(algos), dtype=float)
    width = 0.38
    colors = [color_of(a, algos) for a in algos]
    panels = (("success_rate", "Success rate", "higher is better"),
              ("collision_rate", "Collision rate", "lower is better"))  # fmt: skip
    for ax, (key, name, better) in zip(axes, panels, strict=True):
        paper = [PAPER_RESULTS.get(a, {}).get(key) for a in algos]
        has = np.array([p is not None for p in paper])
        ours = np.array([100 * table[a][key]["mean"] for a in algos])
        bounds = np.array([table[a]["ci95"][key] for a in algos]) * 100  # (algos, 2)
        err = np.stack([np.maximum(ours - bounds[:, 0], 0), np.maximum(bounds[:, 1] - ours, 0)])
        # Side by side where the paper has a figure; centred alone where it does not.
        xo = np.where(has, x - width / 2, x)
        ax.bar(xo, ours, width, yerr=err, capsize=5, color=colors, edgecolor="black", lw=0.8,
               error_kw={"elinewidth": 1.5})  # fmt: skip
        tops = list(ours + err[1])
        for xi, m, e in zip(xo, ours, err[1], strict=True):
            ax.annotate(f"{m:.1f}", (xi, m + e), xytext=(0, 3), textcoords="offset points",
                        ha="center", fontsize=10, fontweight="bold")  # fmt: skip
        if has.any():
            pv = np.array([100 * p for p in paper if p is not None])
            ax.bar(x[has] + width / 2, pv, width, color="white", hatch="///", lw=1.5,
                   edgecolor=[c for c, h in zip(colors, has, strict=True) if h])  # fmt: skip
            tops += list(pv)
            for xi, m in zip(x[has] + width / 2, pv, strict=True):
                ax.annotate(f"{m:.1f}", (xi, m), xytext=(0, 3), textcoords="offset points",
                            ha="center", fontsize=10, color="#444")  # fmt: skip
        n = [table[a]["seeds"] for a in algos]
        ax.set_xticks(x, [f"{display_name(a)}\n{k} seed{'s' if k != 1 else ''}"
                          for a, k in zip(algos, n, strict=True)])  # fmt: skip
        ax.set_ylim(0, min(112.0, max(max(tops) * 1.18, 10.0) + 3))
        ax.yaxis.set_major_formatter(PercentFormatter(100, decimals=0))
        ax.set_ylabel(f"{name.lower()} (% of test episodes)")
        ax.set_title(f"{name} ({better})")
        ax.grid(axis="y", alpha=0.3)
    handles = [Patch(facecolor="#999", edgecolor="black", label="ours: mean over seeds, whiskers "
                     "95 % CI (bootstrap over seeds; Wilson for one seed)")]  # fmt: skip
    if any(a in PAPER_RESULTS for a in algos):
        handles.append(Patch(facecolor="white", edgecolor="#555", hatch="///",
                             label="paper, Sec. IV-B (Isaac Sim, RTX 4090)"))  # fmt: skip
    fig.legend(handles=handles, loc="outside lower center", ncol=2, fontsize=10, frameon=False)
    episodes = next(iter(table.values())).get("episodes")
    fig.suptitle(
        "Fixed test scenario (cf. paper Fig. 4): env seed 1, full density"
        + (f", {episodes} episodes per policy" if episodes else ""),
        fontsize=13,
    )
    return _save(fig, out)


def _save(fig: Any, out: Path) -> Path:
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def _discard(fig: Any) -> None:
    plt.close(fig)
    return None


#: File names of the figures :func:`plot_all` writes.
FIGURES = {
    "validation_curves": "fig3_validation_curves.png",
    "learning_curves": "fig3_learning_curves.png",
    "test_results": "fig4_test_results.png",
    "constraint": "constraint_lambda_d.png",
    "return_cost": "return_cost.png",
}


def plot_all(
    paths: Sequence[str | Path],
    out_dir: str | Path,
    window: int = 1,
    runs: Sequence[Run] | None = None,
) -> list[Path]:
    """Write every figure the runs under ``paths`` support into ``out_dir``; returns the paths.

    Fig. 4 needs ``eval.json`` in the run directories; λ/d need a constrained algorithm that
    logged ``constraint/lambda``. Figures without data are not written. The figures of the
    training logs (learning curves, λ/d, return and cost) are written only when every run has
    its run directory: where some have only their trial file (a sweep whose earlier run
    directories are gone), they would show the others alone. ``runs`` (from
    :func:`find_runs`) saves reading ``paths`` again.
    """
    runs = list(runs if runs is not None else find_runs(paths))
    groups = group(runs)
    out_dir = Path(out_dir)
    written = [
        plot_validation_curves(groups, out_dir / FIGURES["validation_curves"]),
        plot_test_results(groups, out_dir / FIGURES["test_results"]),
    ]
    if not any(r.run_dir.suffix == ".json" for r in runs):  # a trial file stands for its run
        written += [
            plot_learning_curves(groups, out_dir / FIGURES["learning_curves"], window),
            plot_constraint(groups, out_dir / FIGURES["constraint"]),
            plot_return_cost(groups, out_dir / FIGURES["return_cost"], window),
        ]
    return [p for p in written if p is not None]


__all__ = [
    "FIGURES",
    "Run",
    "find_runs",
    "mean_curve",
    "plot_all",
    "plot_constraint",
    "plot_learning_curves",
    "plot_return_cost",
    "plot_test_results",
    "plot_validation_curves",
    "resample",
    "run_from_record",
    "smooth",
    "eval_table",
]
