"""safenav plot: figures from synthetic run directories; resampling onto a common step grid."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from safenav.cli import main
from safenav.errors import SafenavError
from safenav.experiments import plots
from test_reproduce_synthetic import learning_run, write_eval


def synthetic_runs(root):
    """csac x3 (seeds of different lengths), sac x2, ppo x2 (unconstrained), ppo_lag x1."""
    spec = {"csac": (3, 0.95, True), "sac": (2, 0.85, False), "ppo": (2, 0.7, False),
            "ppo_lag": (1, 0.75, True)}  # fmt: skip
    for algo, (n, final, constrained) in spec.items():
        for seed in range(n):
            run = root / "runs" / algo / f"seed{seed}"
            learning_run(run, algo, seed, steps=20_000 + 2_000 * seed, final_success=final,
                         constrained=constrained, eval_every=5_000)  # fmt: skip
            write_eval(run, final - 0.02 * seed, (1 - final) / 2 + 0.01 * seed)
    return root


def test_resample_interpolates_and_leaves_nan_outside():
    grid = np.array([0.0, 50.0, 100.0, 150.0, 250.0])
    out = plots.resample(np.array([50.0, 150.0, 200.0]), np.array([1.0, 3.0, np.nan]), grid)
    assert np.isnan(out[0]) and np.isnan(out[4])
    assert out[1:4].tolist() == [1.0, 2.0, 3.0]


def test_mean_curve_over_seeds_of_different_length(tmp_path):
    for seed, (steps, slope) in enumerate([(4000, 1e-4), (2000, 3e-4)]):
        run = tmp_path / f"seed{seed}"
        run.mkdir()
        (run / "progress.csv").write_text(
            "global_step,charts/success_rate\n"
            + "".join(f"{s},{slope * s}\n" for s in range(1000, steps + 1, 1000))
        )
    runs = plots.find_runs([tmp_path])
    grid, mean, std, n = plots.mean_curve(runs, "charts/success_rate", points=3)
    # The grid ends where the shorter seed ends; seeds interpolated at 1000, 1500, 2000.
    assert n == 2 and grid.tolist() == [1000, 1500, 2000]
    a, b = 1e-4 * grid, 3e-4 * grid
    assert mean == pytest.approx((a + b) / 2)
    assert std == pytest.approx(np.abs(b - a) / np.sqrt(2))


def test_last_value_holds_to_the_last_logged_step():
    steps = np.array([100.0, 200.0, 300.0])
    values = np.array([0.5, 0.7, np.nan])  # no episode ended in the last interval
    grid = np.array([100.0, 250.0, 300.0, 350.0])
    out = plots.resample(steps, values, grid, until=300.0)
    assert out[:3].tolist() == [0.5, 0.7, 0.7] and np.isnan(out[3])


def test_smooth_is_a_trailing_nan_aware_mean():
    x = np.array([1.0, 3.0, np.nan, 5.0])
    assert plots.smooth(x, 2).tolist() == [1.0, 2.0, 3.0, 5.0]
    assert plots.smooth(x, 1) is x


def test_plot_writes_both_figures_and_lambda_d(tmp_path):
    root = synthetic_runs(tmp_path / "sweep")
    written = plots.plot_all([root], tmp_path / "fig")
    names = {p.name for p in written}
    assert set(plots.FIGURES.values()) == names
    for path in written:
        with Image.open(path) as im:
            assert im.size[0] >= 1000 and im.size[1] >= 500
            # Not a blank canvas: plenty of distinct colours.
            pixels = np.asarray(im.convert("RGB").resize((200, 100))).reshape(-1, 3)
            assert len(np.unique(pixels, axis=0)) > 50
    table = plots.eval_table(plots.group(plots.find_runs([root])))
    assert list(table) == ["csac", "sac", "ppo", "ppo_lag"]
    assert table["csac"]["success_rate"]["mean"] == pytest.approx(0.93)
    assert table["sac"]["seeds"] == 2


def test_plot_cli_accepts_run_dirs_and_skips_fig4_without_eval(tmp_path, capsys):
    root = synthetic_runs(tmp_path / "sweep")
    runs = [root / "runs" / "sac" / "seed0", root / "runs" / "sac" / "seed1"]
    for r in runs:
        (r / "eval.json").unlink()
    main(["plot", *map(str, runs), "--out", str(tmp_path / "figs"), "--smooth", "3"])
    out = capsys.readouterr().out
    assert "2 runs of sac" in out and "Fig. 4 needs" in out
    files = sorted(p.name for p in (tmp_path / "figs").iterdir())
    # SAC has no λ/d and no eval.json: only the curves.
    assert files == ["fig3_learning_curves.png", "fig3_validation_curves.png", "return_cost.png"]


def test_plot_cli_default_out_and_errors(tmp_path, capsys):
    root = synthetic_runs(tmp_path / "sweep")
    main(["plot", str(root)])
    assert (root / "figures" / "fig4_test_results.png").exists()
    with pytest.raises(SystemExit) as err:
        main(["plot", str(tmp_path / "nowhere")])
    assert err.value.code == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    with pytest.raises(SafenavError, match="no run directories"):
        plots.find_runs([tmp_path / "empty"])


def test_trial_records_stand_in_for_missing_run_dirs(tmp_path):
    """A fresh clone of a sweep has trials/*.json but no runs/: Fig. 3 (validation) and Fig. 4
    come from the records; a record whose run directory is there is not counted twice."""
    import json

    from safenav.experiments.aggregate import seed_record

    root = synthetic_runs(tmp_path / "sweep")
    (root / "trials").mkdir()
    for run in sorted((root / "runs").glob("*/seed*")):
        rec = seed_record(run)
        assert rec["validation_curve"][0]["env_steps"] == 5_000
        (root / "trials" / f"{rec['algo']}-s{rec['seed']}.json").write_text(json.dumps(rec))
    # An unfinished trial (a run directory, no record yet) is not one more seed of its algorithm.
    learning_run(root / "runs" / "csac" / "seed9", "csac", 9, steps=10_000, final_success=0.1,
                 constrained=True, eval_every=5_000)  # fmt: skip
    both = plots.find_runs([root])
    assert len(both) == 8 and all(r.run_dir.name.startswith("seed") for r in both)
    assert ("csac", 9) not in {(r.algo, r.seed) for r in both}
    # Given on its own (no sweep around it), the same directory is plotted.
    alone = plots.find_runs([root / "runs" / "csac" / "seed9"])
    assert [(r.algo, r.seed) for r in alone] == [("csac", 9)]
    import shutil

    shutil.rmtree(root / "runs")
    runs = plots.find_runs([root])
    assert len(runs) == 8
    assert sorted((r.algo, r.seed) for r in runs) == sorted((r.algo, r.seed) for r in both)
    csac0 = next(r for r in runs if (r.algo, r.seed) == ("csac", 0))
    assert csac0.progress["global_step"].tolist() == [5_000, 10_000, 15_000, 20_000]
    assert csac0.eval["success_rate"] == pytest.approx(0.95)
    written = {p.name for p in plots.plot_all([root], tmp_path / "fig")}
    assert written == {"fig3_validation_curves.png", "fig4_test_results.png"}
    # Some run directories back (a later sweep into the same OUT): the training-log figures
    # would show those alone, so they are not written either.
    learning_run(root / "runs" / "sac" / "seed0", "sac", 0, steps=20_000, final_success=0.85,
                 constrained=False, eval_every=5_000)  # fmt: skip
    mixed = plots.find_runs([root])
    assert len(mixed) == 8 and sum(r.run_dir.suffix != ".json" for r in mixed) == 1
    written = {p.name for p in plots.plot_all([root], tmp_path / "fig-mixed")}
    assert written == {"fig3_validation_curves.png", "fig4_test_results.png"}
    table = plots.eval_table(plots.group(runs))
    low, high = table["csac"]["ci95"]["success_rate"]
    assert low <= table["csac"]["success_rate"]["mean"] <= high


def test_ci95_band_is_the_bootstrap_interval_of_the_mean():
    stack = np.array([[0.1, 0.5, np.nan], [0.3, 0.5, 0.2], [0.5, 0.5, np.nan]])
    low, high = plots.ci95_band(stack)
    assert 0.1 <= low[0] < 0.3 < high[0] <= 0.5
    assert low[1] == high[1] == 0.5 and low[2] == high[2] == 0.2  # no spread / one seed


def test_an_algorithm_at_another_budget_keeps_its_hue_and_line_style():
    """csac_3m and ppo_3m once shared one brown (extra colours wrapped round): a label naming
    another budget takes a dark shade of its algorithm's colour and its line style."""
    order = ["csac", "sac", "ppo", "csac_paper", "csac_min", "csac_fixed_d", "csac_3m", "sac_3m",
             "ppo_3m", "sac_lag_3m", "ppo_lag_3m", "my_variant"]  # fmt: skip
    colors = {label: plots.color_of(label, order) for label in order}
    assert len(set(colors.values())) == len(order)
    assert colors["csac_3m"] == plots.DARK_COLORS["csac"] != colors["csac"]
    assert plots.linestyle_of("sac_3m") == plots.linestyle_of("sac") == "--"
    assert plots.budget_base("csac_paper") is None and plots.budget_base("ppo_lag_3m") == "ppo_lag"
    assert plots.linestyle_of("my_variant") == "-"


def test_the_committed_comparison_labels_get_distinct_colours():
    """results/paper's labels (the tuned recipes beside the ablations) each get their own colour."""
    order = ["csac", "sac", "ppo", "sac_lag", "ppo_lag", "sac_lag_tuned_3m", "sac_tuned_3m",
             "csac_3m", "csac_fixed_d", "csac_min", "csac_paper", "ppo_3m", "ppo_lag_3m",
             "ppo_lag_tuned_3m", "ppo_tuned_3m", "sac_3m", "sac_lag_3m", "csac_tuned_3m", "a", "b", "c", "d", "e"]  # fmt: skip
    colors = [plots.color_of(label, order) for label in order]
    assert len(set(colors)) == len(order)
