"""The comparison statistics of ``safenav reproduce`` (issue 21): IQM with a bootstrap CI,
McNemar's exact test on paired test episodes, and the difference of means over seeds."""

from __future__ import annotations

import pytest

from safenav.experiments import aggregate as agg
from safenav.experiments import stats


def test_outcomes_string_is_one_letter_per_episode():
    per_episode = {"success": [1, 0, 0, 1], "collision": [0, 1, 0, 0], "timeout": [0, 0, 1, 0]}
    assert stats.outcomes_string(per_episode) == "SCTS"
    assert stats.outcomes_string(None) is None


def test_iqm_trims_a_quarter_each_side():
    q = stats.iqm([0.0, 0.1, 0.5, 0.6, 0.9])
    assert q["iqm"] == pytest.approx((0.1 + 0.5 + 0.6) / 3) and q["seeds"] == 5
    low, high = q["ci95"]
    assert 0.0 <= low < q["iqm"] < high <= 0.9
    assert stats.iqm([0.4])["ci95"] is None and stats.iqm([]) is None
    # two seeds give no interval: their bootstrap would only span the two values
    assert stats.iqm([0.4, 0.9])["ci95"] is None
    assert stats.mean_difference([0.1, 0.2], [0.6, 0.7, 0.8]) is None


def test_mcnemar_counts_only_discordant_pairs():
    a = [True] * 10 + [False] * 10 + [True] * 5
    b = [False] * 10 + [False] * 10 + [True] * 5
    m = stats.mcnemar_exact(a, b)
    assert (m["only_a"], m["only_b"], m["pairs"]) == (10, 0, 25)
    assert m["p_value"] == pytest.approx(2 * 0.5**10)  # exact binomial, two-sided
    assert stats.mcnemar_exact([True, False], [True, False])["p_value"] == 1.0
    with pytest.raises(ValueError, match="differ in length"):
        stats.mcnemar_exact([True], [True, False])


def test_mean_difference_is_resolved_only_when_its_interval_excludes_zero():
    far = stats.mean_difference([0.1, 0.12, 0.11], [0.5, 0.52, 0.49])
    assert far["difference"] == pytest.approx(0.11 - 0.5033, abs=1e-3) and far["resolved"]
    assert far["ci95"][1] < 0
    near = stats.mean_difference([0.1, 0.5, 0.3], [0.2, 0.4, 0.35])
    assert not near["resolved"] and near["ci95"][0] < 0 < near["ci95"][1]
    assert stats.mean_difference([0.1], [0.2, 0.3]) is None


def test_welch_difference_and_the_mean_t_interval_match_their_textbook_values():
    """Welch's interval on two groups of seeds (the safe suite's target) against the formula with
    Welch-Satterthwaite degrees of freedom; the mean's t-interval against mean +- t * s / sqrt(n)."""
    import numpy as np
    from scipy.stats import t

    a, b = [497.4, 1060.6], [1685.0, 1460.0, 1061.0]
    w = stats.welch_difference(a, b)
    va, vb = np.var(a, ddof=1) / 2, np.var(b, ddof=1) / 3
    dof = (va + vb) ** 2 / (va**2 / 1 + vb**2 / 2)
    half = t.ppf(0.975, dof) * np.sqrt(va + vb)
    assert w["difference"] == pytest.approx(np.mean(a) - np.mean(b))
    assert w["ci95"] == pytest.approx([w["difference"] - half, w["difference"] + half])
    assert not w["resolved"] and 0.05 < w["p_value"] < 1
    assert stats.welch_difference([10.0, 11.0, 12.0], [1.0, 2.0, 1.5])["resolved"]
    assert stats.welch_difference([1.0], [1.0, 2.0]) is None
    exact = stats.welch_difference([3.0, 3.0], [1.0, 1.0])  # no spread: the difference is exact
    assert exact["ci95"] == [2.0, 2.0] and exact["resolved"]
    costs = [0.0, 44.0, 28.5]
    half = t.ppf(0.975, 2) * np.std(costs, ddof=1) / np.sqrt(3)
    assert stats.mean_t_interval(costs) == pytest.approx([np.mean(costs) - half,
                                                         np.mean(costs) + half])  # fmt: skip
    assert stats.mean_t_interval([5.0]) is None and stats.mean_t_interval([2.0, 2.0]) == [2.0, 2.0]


def record(algo, seed, outcomes):
    n = len(outcomes)
    return {"algo": algo, "seed": seed, "success_rate": outcomes.count("S") / n,
            "collision_rate": outcomes.count("C") / n, "timeout_rate": outcomes.count("T") / n,
            "eval_episodes": n, "test_outcomes": outcomes, "time_to_target": None}  # fmt: skip


def test_aggregate_compares_csac_with_each_baseline_on_paired_episodes():
    records = [record("csac", 1, "SSSSSSSSTC"), record("csac", 2, "SSSSSSSSCC"),
               record("csac", 4, "SSSSSSSSTT"),
               record("sac", 1, "SSSSSCCCCC"), record("sac", 2, "SSSSCCCCCC"),
               record("sac", 3, "SSSSSSSSSS")]  # fmt: skip
    results = agg.aggregate(records)
    comp = results["comparisons"]["csac_vs_sac"]
    mc = comp["collision_rate"]["mcnemar"]
    # seeds 1 and 2 are paired (seed 3 of SAC and seed 4 of CSAC have no partner): 20 pairs
    assert mc["seeds"] == [1, 2] and mc["pairs"] == 20
    assert (mc["only_a"], mc["only_b"]) == (0, 8)  # CSAC collides where SAC does, not more
    diff = comp["collision_rate"]["mean_difference"]
    assert diff["difference"] == pytest.approx(0.1 - 1.1 / 3)
    assert results["algos"]["csac"]["iqm"]["success_rate"]["iqm"] == pytest.approx(0.8)
    text = agg.render_markdown(results)
    assert "## CSAC against each baseline" in text and "| SAC | collision |" in text
    assert "## Interquartile mean (IQM)" in text
    # the summary the README quotes: mean with the bootstrap CI over seeds, and the verdict
    summary = next(line for line in text.splitlines() if line.startswith("| SAC | 3 |"))
    assert "CSAC: success" in summary and "collision -27 pp, not resolved" in summary


def test_aggregate_compares_the_policies_without_the_planner_filter_too():
    """Labels reported behind the planner filter are also compared on their test behind the
    shield alone (``test_without_filter``), the policies' own part; a label without it is not."""

    def behind_filter(rec, unfiltered):
        n = len(unfiltered)
        side = {"success_rate": unfiltered.count("S") / n, "collision_rate": unfiltered.count("C") / n,
                "test_outcomes": unfiltered}  # fmt: skip
        return rec | {"test_without_filter": side}

    records = [behind_filter(record("csac", 1, "SSSS"), "SSTC"),
               behind_filter(record("csac", 2, "SSSC"), "SCCC"),
               behind_filter(record("sac", 1, "SSSC"), "CCCC"),
               behind_filter(record("sac", 2, "SSCC"), "CCCC"),
               behind_filter(record("csac", 3, "SSSS"), "SSCC"),
               behind_filter(record("sac", 3, "SSSS"), "CCCC"),
               record("ppo", 1, "SCCC"), record("ppo", 2, "CCCC")]  # fmt: skip
    results = agg.aggregate(records)
    assert set(results["comparisons"]) == {"csac_vs_sac", "csac_vs_ppo"}
    assert set(results["comparisons_without_filter"]) == {"csac_vs_sac"}
    comp = results["comparisons_without_filter"]["csac_vs_sac"]["collision_rate"]
    assert comp["mean_difference"]["difference"] == pytest.approx((0.25 + 0.75 + 0.5) / 3 - 1.0)
    assert (comp["mcnemar"]["only_a"], comp["mcnemar"]["only_b"]) == (0, 6)  # unfiltered episodes
    assert results["comparisons"]["csac_vs_sac"]["collision_rate"]["mcnemar"]["only_b"] == 2
    text = agg.render_markdown(results)
    assert "## CSAC against each baseline, without the planner filter" in text


def test_aggregate_compares_only_labels_of_the_same_budget():
    def at(budget, rec):
        return rec | {"budget_env_steps": budget}

    records = [at(10**6, record("csac", 1, "SSSC")), at(10**6, record("sac", 1, "SSCC")),
               at(3 * 10**6, record("ppo_3m", 1, "SCCC")),
               at(3 * 10**6, record("csac_3m", 1, "SSSS")),
               at(3 * 10**6, record("sac_3m", 1, "SSSC"))]  # fmt: skip
    comparisons = agg.aggregate(records)["comparisons"]
    # the 1M CSAC against the 1M baseline only; the 3M rows against the 3M CSAC
    assert set(comparisons) == {"csac_vs_sac", "csac_3m_vs_ppo_3m", "csac_3m_vs_sac_3m"}
    text = agg.render_markdown(agg.aggregate(records))
    assert "| SAC | success |" in text and "| ppo_3m (against csac_3m) | success |" in text
    # records without a declared budget (older sweeps) are compared as before
    assert set(
        agg.aggregate([record("csac", 1, "SC"), record("ppo_3m", 1, "CC")])["comparisons"]
    ) == {"csac_vs_ppo_3m"}
