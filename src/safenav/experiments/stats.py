"""Statistics of a multi-seed comparison (issue 21): IQM with bootstrap CIs, and paired tests of
CSAC against each baseline on the identical test episodes.

Every figure comes from scipy (no hand-written distribution):

- **IQM** (interquartile mean, Agarwal et al. 2021, "Deep RL at the edge of the statistical
  precipice"): ``scipy.stats.trim_mean(x, 0.25)`` of the per-seed rates, with a 95 % percentile
  bootstrap over seeds (``scipy.stats.bootstrap``). rliable's *stratified* bootstrap resamples
  runs within each task; with one task (the test scenario) that is this bootstrap over seeds.
- **McNemar's exact test** on paired episodes: every test episode of seed ``s`` of one algorithm
  is paired with the same episode (same env seed, same index, so the same map, start, goal and
  obstacle motion) of seed ``s`` of the other. Only discordant pairs count; under the null each
  is equally likely either way, so the two-sided p-value is ``scipy.stats.binomtest(b, b + c,
  0.5)``. It speaks to episode-level noise given these policies, not to the spread of training
  seeds.
- **Difference of means over seeds** with a 95 % bootstrap CI (two independent samples of seeds,
  ``scipy.stats.bootstrap``): the seed-to-seed uncertainty, the one a claim about the algorithm
  must survive. A difference is *resolved* only where this interval excludes 0.
- **Welch's t-interval** on a difference of means over seeds (``scipy.stats.ttest_ind``,
  ``equal_var=False``) and the t-interval of one mean (``scipy.stats.ttest_1samp``): the
  ``safenav bench safe`` target on rows of 2-3 seeds, where a bootstrap has too few values.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

#: The fewest values (seeds) a bootstrap interval is computed from. Two seeds' resampled means
#: take three values (each seed twice, or one of each), so the 95 % "interval" is the span of the
#: two seeds, far narrower than the seed-to-seed spread: on 2026-12-06 it called CSAC vs PPO
#: "resolved" on PPO's first two seeds. Three is the fewest the comparison's plan runs.
MIN_BOOTSTRAP_SAMPLES = 3

#: One letter per test episode in a trial record's ``test_outcomes``.
OUTCOME_LETTERS = {"success": "S", "collision": "C", "timeout": "T"}


def outcomes_string(per_episode: dict[str, Sequence[Any]] | None) -> str | None:
    """``safenav eval``'s ``per_episode`` lists as one letter per episode (``S`` success, ``C``
    collision, ``T`` timeout): 200 characters for a test report, small enough to commit, and
    what the paired test reads. None without per-episode data."""
    if not per_episode or "success" not in per_episode or "collision" not in per_episode:
        return None
    success, collision = per_episode["success"], per_episode["collision"]
    return "".join("S" if s else "C" if c else "T" for s, c in zip(success, collision, strict=True))


def bootstrap_ci(statistic: Callable[..., Any], *samples: Sequence[float]) -> list[float] | None:
    """95 % percentile-bootstrap interval of ``statistic(*samples, axis=...)`` (scipy's
    ``bootstrap``, 10,000 resamples, ``random_state`` 0; each sample resampled on its own): the
    one bootstrap of the project's results. None when a sample has fewer than
    :data:`MIN_BOOTSTRAP_SAMPLES` values; the statistic itself as both ends when no sample varies
    (every resample would give it)."""
    from scipy import stats

    xs = [np.asarray(sample, dtype=float) for sample in samples]
    if any(len(x) < MIN_BOOTSTRAP_SAMPLES for x in xs):
        return None
    if all(np.ptp(x) == 0 for x in xs):
        value = float(statistic(*xs, axis=-1))
        return [value, value]
    res = stats.bootstrap(tuple(xs), statistic, confidence_level=0.95, n_resamples=10_000,
                          method="percentile", random_state=0)  # fmt: skip
    return [float(res.confidence_interval.low), float(res.confidence_interval.high)]


def iqm(values: Sequence[float]) -> dict[str, Any] | None:
    """Interquartile mean of per-seed values and its 95 % percentile-bootstrap CI over seeds
    (None below :data:`MIN_BOOTSTRAP_SAMPLES` values for the interval)."""
    from scipy import stats

    xs = np.asarray([v for v in values if v is not None and np.isfinite(v)], dtype=float)
    if len(xs) == 0:
        return None
    value = float(stats.trim_mean(xs, 0.25))
    ci = bootstrap_ci(lambda x, axis: stats.trim_mean(x, 0.25, axis=axis), xs)
    return {"iqm": value, "ci95": ci, "seeds": int(len(xs))}


def mcnemar_exact(a: Sequence[bool], b: Sequence[bool]) -> dict[str, Any]:
    """McNemar's exact test on paired binary outcomes (``a[i]`` and ``b[i]`` the same episode):
    ``only_a`` episodes where only ``a`` had the event, ``only_b`` the reverse, two-sided p."""
    from scipy import stats

    a, b = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    if a.shape != b.shape:
        raise ValueError(f"paired outcomes differ in length: {a.shape} vs {b.shape}")
    only_a, only_b = int((a & ~b).sum()), int((~a & b).sum())
    n = only_a + only_b
    p = 1.0 if n == 0 else float(stats.binomtest(only_a, n, 0.5).pvalue)
    return {"pairs": int(a.size), "only_a": only_a, "only_b": only_b, "p_value": p}


def mean_difference(a: Sequence[float], b: Sequence[float]) -> dict[str, Any] | None:
    """``mean(a) - mean(b)`` over seeds and its 95 % percentile-bootstrap CI, the two groups of
    seeds resampled independently; None when either group has fewer than
    :data:`MIN_BOOTSTRAP_SAMPLES` seeds."""
    xa = np.asarray([v for v in a if v is not None], dtype=float)
    xb = np.asarray([v for v in b if v is not None], dtype=float)
    ci = bootstrap_ci(lambda x, y, axis: x.mean(axis=axis) - y.mean(axis=axis), xa, xb)
    if ci is None:
        return None
    diff = float(xa.mean() - xb.mean())
    return {"difference": diff, "ci95": ci, "resolved": bool(ci[0] > 0 or ci[1] < 0)}


def welch_difference(a: Sequence[float], b: Sequence[float]) -> dict[str, Any] | None:
    """``mean(a) - mean(b)`` with Welch's 95 % t-interval and two-sided p
    (``scipy.stats.ttest_ind``, ``equal_var=False``): two small groups of seeds whose spreads
    differ, as the safe suite's rows of 2-3 seeds are (the percentile bootstrap of 3 values is far
    narrower than their spread). None when a group has fewer than 2 values; a difference is
    *resolved* only where the interval excludes 0."""
    from scipy import stats

    xa, xb = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if len(xa) < 2 or len(xb) < 2:
        return None
    diff = float(xa.mean() - xb.mean())
    if np.ptp(xa) == 0 and np.ptp(xb) == 0:  # no spread: t is undefined, the difference exact
        return {"difference": diff, "ci95": [diff, diff], "p_value": float(diff == 0),
                "resolved": diff != 0}  # fmt: skip
    res = stats.ttest_ind(xa, xb, equal_var=False)
    ci = res.confidence_interval(0.95)
    low, high = float(ci.low), float(ci.high)
    return {"difference": diff, "ci95": [low, high], "p_value": float(res.pvalue),
            "resolved": bool(low > 0 or high < 0)}  # fmt: skip


def mean_t_interval(values: Sequence[float]) -> list[float] | None:
    """95 % t-interval of the mean of ``values`` (``scipy.stats.ttest_1samp``); None below 2
    values, the mean itself as both ends when they do not vary."""
    from scipy import stats

    x = np.asarray(values, dtype=float)
    if len(x) < 2:
        return None
    if np.ptp(x) == 0:
        return [float(x[0]), float(x[0])]
    ci = stats.ttest_1samp(x, 0.0).confidence_interval(0.95)
    return [float(ci.low), float(ci.high)]


def compare(reference: Sequence[dict[str, Any]], other: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """``reference`` (CSAC's seed records) against ``other`` (a baseline's): per rate, the
    difference of means over seeds with its CI and McNemar's exact test on the episodes of the
    seeds both have with ``test_outcomes`` of equal length (same test episodes)."""
    out: dict[str, Any] = {}
    by_seed_a = {r.get("seed"): r.get("test_outcomes") for r in reference}
    by_seed_b = {r.get("seed"): r.get("test_outcomes") for r in other}
    seeds = sorted(s for s in by_seed_a if by_seed_a[s] and by_seed_b.get(s)
                   and len(by_seed_a[s]) == len(by_seed_b[s]))  # fmt: skip
    for key, letter in (("success_rate", "S"), ("collision_rate", "C")):
        entry: dict[str, Any] = {
            "mean_difference": mean_difference([r.get(key) for r in reference],
                                               [r.get(key) for r in other]),
            "mcnemar": None,
        }  # fmt: skip
        if seeds:
            a = [ch == letter for s in seeds for ch in by_seed_a[s]]
            b = [ch == letter for s in seeds for ch in by_seed_b[s]]
            entry["mcnemar"] = mcnemar_exact(a, b) | {"seeds": seeds}
        out[key] = entry
    return out


__all__ = ["OUTCOME_LETTERS", "bootstrap_ci", "compare", "iqm", "mcnemar_exact", "mean_difference",
           "outcomes_string"]  # fmt: skip
