"""safenav reproduce: aggregation of results on synthetic runs, time to target, trial state.

Everything here runs on synthetic run directories (the files train and eval write), in well
under a second per test. The end-to-end sweep on Ray is in test_reproduce_e2e.py.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from safenav.errors import SafenavError
from safenav.experiments import aggregate as agg
from safenav.experiments import reproduce as rep
from safenav.recipes import load_recipe
from test_reproduce_synthetic import learning_run, write_eval, write_progress

# -- reading progress.csv --------------------------------------------------------------------------


def test_read_progress_empty_cells_are_nan_and_torn_rows_dropped(tmp_path):
    (tmp_path / "progress.csv").write_text(
        "global_step,charts/success_rate,eval/success_rate\n100,0.5,\n200,0.6,0.7\n300,0."
    )
    p = agg.read_progress(tmp_path)
    assert p["global_step"].tolist() == [100, 200]
    assert math.isnan(p["eval/success_rate"][0]) and p["eval/success_rate"][1] == 0.7
    assert agg.last_step(tmp_path) == 200
    assert agg.last_step(tmp_path / "missing") == 0


def test_last_step_reads_the_tail_of_a_long_file(tmp_path):
    rows = [{"global_step": s, "perf/sps": 1.0} for s in range(0, 300_000, 100)]
    write_progress(tmp_path, rows)
    assert (tmp_path / "progress.csv").stat().st_size > 8192
    assert agg.last_step(tmp_path) == 299_900


# -- statistics --------------------------------------------------------------------------------


def test_a_rerun_on_the_committed_comparison_runs_nothing(monkeypatch):
    """Issue 21: ``safenav reproduce --algos paper-observation`` on the committed
    ``results/paper-observation`` skips every trial (a fresh clone has the trial records, not
    the ignored run directories), and so does plain ``safenav reproduce`` on the committed
    ``results/paper`` (the paper plan: 33 trials)."""
    from safenav.cli import main

    repo = Path(__file__).resolve().parents[1]
    seen = {}
    monkeypatch.setattr(rep, "run_sweep", lambda cfg: seen.setdefault("cfg", cfg))
    monkeypatch.chdir(repo)
    main(["reproduce", "--algos", "paper-observation"])
    trials = rep.plan(seen["cfg"])
    left = [t.name for t in trials
            if rep.trial_state(t) != "done" and rep.committed_record(t) is None]  # fmt: skip
    assert len(trials) == 69 and not left, left  # 9 labels x 5 seeds, 8 x 3
    seen.clear()
    main(["reproduce"])
    trials = rep.plan(seen["cfg"])
    # a trial with its record is done: by its run directory here, by the record in a fresh clone
    left = [t.name for t in trials
            if rep.trial_state(t) != "done" and rep.committed_record(t) is None]  # fmt: skip
    assert len(trials) == 33 and not left, left  # csac, sac, ppo x 5 seeds; 6 labels x 3
    assert all(t.record_path.exists() for t in trials)


def test_report_only_aggregates_the_finished_trials_and_runs_nothing(tmp_path, monkeypatch):
    """``--report-only``: the results of the trials finished in OUT (here one committed record)
    while another is still training (a checkpoint, no report); nothing starts, nothing trains."""
    import ray

    monkeypatch.setattr(ray, "init", lambda *a, **k: pytest.fail("Ray started for nothing"))
    cfg = rep.SweepConfig(out=tmp_path / "out", algos=("csac", "sac"), seeds=1, first_seed=1,
                          total_steps=("1000",), preset="easy", eval_episodes=4, progress=False,
                          plots=False, report_only=True, command="safenav reproduce --report-only")  # fmt: skip
    csac, sac = rep.plan(cfg)
    csac.record_path.parent.mkdir(parents=True)
    csac.record_path.write_text(json.dumps(
        {"algo": "csac", "seed": 1, "success_rate": 0.75, "collision_rate": 0.25,
         "timeout_rate": 0.0, "eval_episodes": 4, "budget_env_steps": 1000,
         "selection": "validation", "test_outcomes": "SSSC", "time_to_target": None}))  # fmt: skip
    sac.run_dir.mkdir(parents=True)
    sac.checkpoint.write_bytes(b"training")
    results = rep.run_sweep(cfg)
    assert list(results["algos"]) == ["csac"] and results["algos"]["csac"]["seeds"] == 1
    assert results["ray"]["trials_run"] == 0 and results["failed"] == []
    assert (cfg.out / "results.md").exists() and sac.checkpoint.read_bytes() == b"training"


def test_mean_std_is_sample_std_and_skips_missing():
    assert agg.mean_std([0.8, 0.9, 1.0]) == pytest.approx({"mean": 0.9, "std": 0.1})
    assert agg.mean_std([0.7, None, 0.8, math.nan]) == pytest.approx(
        {"mean": 0.75, "std": math.sqrt(0.005)}
    )
    assert agg.mean_std([0.3]) == {"mean": 0.3, "std": 0.0}
    assert agg.mean_std([]) is None


def test_elapsed_seconds_integrates_sps_or_uses_the_runs_clock():
    p = {"global_step": np.array([1000.0, 2000, 3000]), "perf/sps": np.array([100.0, 100, 50])}
    assert agg.elapsed_seconds(p).tolist() == [10.0, 20.0, 40.0]
    p["time/elapsed_s"] = np.array([11.0, 22.0, 33.0])
    assert agg.elapsed_seconds(p).tolist() == [11.0, 22.0, 33.0]
    assert agg.elapsed_seconds({"global_step": np.array([1.0])}) is None


def test_time_to_target_on_training_rates(tmp_path):
    write_progress(tmp_path, [
        {"global_step": 1000, "charts/success_rate": 0.50, "charts/collision_rate": 0.30, "perf/sps": 100},
        {"global_step": 2000, "charts/success_rate": 0.86, "charts/collision_rate": 0.12, "perf/sps": 100},
        {"global_step": 3000, "charts/success_rate": 0.90, "charts/collision_rate": 0.08, "perf/sps": 50},
        {"global_step": 4000, "charts/success_rate": 0.95, "charts/collision_rate": 0.05, "perf/sps": 100},
    ])  # fmt: skip
    p = agg.read_progress(tmp_path)
    # Row 2 has the success but not the collision; row 3 is the first with both: 10+10+20 s.
    assert agg.time_to_target(p) == {"env_steps": 3000, "wall_clock_s": 40.0, "source": "train"}
    assert agg.time_to_target(p, agg.Target(success=0.99, collision=0.1)) is None
    # The boundary counts: >= 85 % and <= 10 %.
    assert agg.time_to_target(p, agg.Target(success=0.86, collision=0.12))["env_steps"] == 2000


def test_time_to_target_prefers_evaluation_columns(tmp_path):
    write_progress(tmp_path, [
        {"global_step": 1000, "charts/success_rate": 0.9, "charts/collision_rate": 0.0, "perf/sps": 100},
        {"global_step": 2000, "charts/success_rate": 0.9, "charts/collision_rate": 0.0, "perf/sps": 100,
         "eval/success_rate": 0.80, "eval/collision_rate": 0.05},
        {"global_step": 3000, "charts/success_rate": 0.9, "charts/collision_rate": 0.0, "perf/sps": 100},
        {"global_step": 4000, "charts/success_rate": 0.9, "charts/collision_rate": 0.0, "perf/sps": 100,
         "eval/success_rate": 0.85, "eval/collision_rate": 0.10},
    ])  # fmt: skip
    p = agg.read_progress(tmp_path)
    assert agg.time_to_target(p) == {"env_steps": 4000, "wall_clock_s": 40.0, "source": "eval"}


# -- aggregation ---------------------------------------------------------------------------------


def synthetic_sweep(root: Path) -> dict:
    """csac: 3 seeds (2 reach the target), sac: 2 seeds, ppo_lag: 1 seed; hand-picked rates."""
    plan = {
        "csac": [(0.8, 0.10, 5000), (0.9, 0.05, 3000), (1.0, 0.00, None)],
        "sac": [(0.7, 0.2, None), (0.8, 0.1, None)],
        "ppo_lag": [(0.6, 0.3, None)],
    }
    records = []
    for algo, seeds in plan.items():
        for seed, (success, collision, reach_at) in enumerate(seeds):
            run = root / "runs" / algo / f"seed{seed}"
            rows = [{"global_step": s, "charts/success_rate": 0.9 if s == reach_at else 0.5,
                     "charts/collision_rate": 0.05 if s == reach_at else 0.5, "perf/sps": 100.0}
                    for s in range(1000, 10_001, 1000)]  # fmt: skip
            write_progress(run, rows)
            write_eval(run, success, collision)
            records.append(agg.seed_record(run, algo=algo, seed=seed))
    return agg.aggregate(records, {"command": "safenav reproduce --out X", "machine": "test",
                                   "date": "2026-01-01"})  # fmt: skip


def test_aggregate_hand_computed(tmp_path):
    res = synthetic_sweep(tmp_path)
    assert list(res["algos"]) == ["csac", "sac", "ppo_lag"]
    csac, sac, lag = (res["algos"][k] for k in ("csac", "sac", "ppo_lag"))
    assert csac["seeds"] == 3 and sac["seeds"] == 2 and lag["seeds"] == 1
    assert csac["success_rate"] == pytest.approx({"mean": 0.9, "std": 0.1})
    assert csac["collision_rate"] == pytest.approx({"mean": 0.05, "std": 0.05})
    assert csac["timeout_rate"] == pytest.approx({"mean": 0.05, "std": 0.05})
    assert sac["success_rate"] == pytest.approx({"mean": 0.75, "std": math.sqrt(0.005)})
    assert lag["success_rate"] == {"mean": 0.6, "std": 0.0}
    # env steps / wall-clock: means per seed (10k steps at 100 sps = 100 s).
    assert csac["env_steps"] == 10_000 and csac["wall_clock_s"] == pytest.approx(100.0)
    # Time to target: seeds 0 and 1 reached it at 5000 and 3000 steps (50 s and 30 s).
    ttt = csac["time_to_target"]
    assert (ttt["reached"], ttt["of"], ttt["source"]) == (2, 3, "train")
    assert ttt["env_steps"] == pytest.approx({"mean": 4000, "std": math.sqrt(2) * 1000})
    assert ttt["wall_clock_s"] == pytest.approx({"mean": 40.0, "std": math.sqrt(200)})
    assert sac["time_to_target"]["reached"] == 0 and sac["time_to_target"]["env_steps"] is None
    assert csac["paper"] == {"success_rate": 0.847, "collision_rate": 0.111}
    assert lag["paper"] is None
    assert [r["seed"] for r in csac["per_seed"]] == [0, 1, 2]
    assert res["command"] == "safenav reproduce --out X" and res["machine"] == "test"


def test_results_files_have_the_documented_shape(tmp_path):
    res = synthetic_sweep(tmp_path)
    js, md = agg.write_results(res, tmp_path / "out")
    data = json.loads(js.read_text())
    for algo in data["algos"].values():
        for key in ("success_rate", "collision_rate", "timeout_rate"):
            assert set(algo[key]) == {"mean", "std"}
        for key in ("seeds", "env_steps", "wall_clock_s", "per_seed", "time_to_target"):
            assert key in algo
    assert {"command", "machine", "date"} <= set(data)
    text = md.read_text()
    assert "| CSAC | 3 | 90.0 ± 10.0 % | 84.7 % | 5.0 ± 5.0 % | 11.1 % |" in text
    assert "| SAC | 2 | 75.0 ± 7.1 % | 81.3 % | 15.0 ± 7.1 % | 14.0 % |" in text
    assert "| PPO-Lag | 1 | 60.0 ± 0.0 % | — | 30.0 ± 0.0 % | — |" in text
    assert "| CSAC | 2 / 3 | 4000 ± 1414 | 40 s ± 14 s | train |" in text
    assert "| SAC | 0 / 2 | — | — | — |" in text


def test_formatting():
    assert agg.fmt_rate({"mean": 0.847, "std": 0.0123}) == "84.7 ± 1.2 %"
    assert agg.fmt_rate(None) == "—"
    assert agg.fmt_seconds(42) == "42 s" and agg.fmt_seconds(750) == "12.5 min"
    assert agg.fmt_seconds(3 * 3600) == "3.00 h" and agg.fmt_seconds(None) == "—"
    assert agg.fmt_steps(350_000) == "350k" and agg.fmt_steps(1_200_000) == "1.20M"


def test_run_identity(tmp_path):
    learning_run(tmp_path / "a", "sac_lag", 3, steps=2000)
    assert agg.run_identity(tmp_path / "a") == ("sac_lag", 3)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "config.json").write_text(json.dumps({"train": {"algo": "ppo", "seed": 2}}))
    assert agg.run_identity(tmp_path / "b") == ("ppo", 2)
    (tmp_path / "csac" / "seed4").mkdir(parents=True)
    assert agg.run_identity(tmp_path / "csac" / "seed4") == ("csac", 4)
    # a reproduce trial stopped before its reproduce.json: its label, not its config's algo
    stopped = tmp_path / "out" / "runs" / "csac_paper" / "seed1"
    stopped.mkdir(parents=True)
    (stopped / "config.json").write_text(json.dumps({"train": {"algo": "csac", "seed": 1}}))
    assert agg.run_identity(stopped) == ("csac_paper", 1)


# -- the sweep's plan ---------------------------------------------------------------------------


def test_parse_steps():
    assert rep.parse_steps("300000") == rep.parse_steps("300_000") == rep.parse_steps("300k")
    assert rep.parse_steps("2M") == 2_000_000 and rep.parse_steps("1e6") == 1_000_000
    for bad in ("lots", "0", "-5", "1.5"):
        with pytest.raises(SafenavError):
            rep.parse_steps(bad)


def test_plan_total_steps_variants_and_order(tmp_path):
    cfg = rep.SweepConfig(out=tmp_path, algos=("csac", "ppo"), seeds=2, first_seed=7,
                          total_steps=("50k", "ppo=2M"), cpus_per_trial=1, preset="easy",
                          variants=("csac_min=csac --cost-target min",))  # fmt: skip
    trials = rep.plan(cfg)
    assert [t.name for t in trials] == ["csac-seed7", "ppo-seed7", "csac_min-seed7",
                                        "csac-seed8", "ppo-seed8", "csac_min-seed8"]  # fmt: skip
    by = {t.name: t for t in trials}
    assert by["csac-seed7"].total_steps == 50_000 and by["ppo-seed8"].total_steps == 2_000_000
    assert by["csac_min-seed7"].algo == "csac"
    assert by["csac_min-seed7"].run_dir == tmp_path.resolve() / "runs" / "csac_min" / "seed7"
    cmd = by["csac_min-seed7"].train_command(resume=False)
    assert cmd[:4] == [sys.executable, "-m", "safenav", "train"]
    assert cmd[cmd.index("--algo") + 1] == "csac" and cmd[-2:] == ["--cost-target", "min"]
    assert cmd[cmd.index("--preset") + 1] == "easy" and "--resume" not in cmd
    assert cmd[cmd.index("--torch-threads") + 1] == "1"  # the trial's CPUs, not its recipe's
    resumed = by["ppo-seed7"].train_command(resume=True)
    assert resumed[resumed.index("--resume") + 1] == str(by["ppo-seed7"].run_dir)
    # Defaults per algorithm when --total-steps names none.
    default = rep.plan(rep.SweepConfig(out=tmp_path, algos=("csac", "ppo"), seeds=1))
    assert [t.total_steps for t in default] == [rep.DEFAULT_TOTAL_STEPS["csac"],
                                                rep.DEFAULT_TOTAL_STEPS["ppo"]]  # fmt: skip


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"algos": ("dqn",)}, "unknown algorithm 'dqn'"),
        ({"total_steps": ("sac=1k",)}, "'sac' is not among"),
        ({"seeds": 0}, "at least one seed"),
        ({"cpus_per_trial": 0}, "at least one CPU"),
        ({"variants": ("nolabel",)}, "LABEL=ALGO"),
        ({"variants": ("x=dqn --a b",)}, "unknown algorithm 'dqn'"),
        ({"label_seeds": {"sac": (1, 2)}}, r"\['sac'\] name no algorithm or variant"),
    ],
)
def test_plan_rejects_mistakes_with_one_line(tmp_path, changes, message):
    cfg = rep.SweepConfig(out=tmp_path, algos=("csac",), seeds=1)
    for k, v in changes.items():
        setattr(cfg, k, v)
    with pytest.raises(SafenavError, match=message):
        rep.plan(cfg)


def test_no_flags_plan_the_papers_comparison(tmp_path, monkeypatch):
    """``safenav reproduce`` alone: CSAC, SAC, PPO on seeds 1-5, the Lagrangian baselines and the
    CSAC ablations on 1-3, 1M env steps each, every label but csac_paper on the default csac
    recipe's flight stack (its baselines' own recipes on it, reported behind the planner
    filter); ``--algos paper-observation``: the comparison on the paper's observation at 1M and
    3M, with each algorithm's tuned recipe at 3M."""
    from safenav.cli import main

    seen = {}
    monkeypatch.setattr(rep, "run_sweep", lambda cfg: seen.setdefault("cfg", cfg))
    monkeypatch.chdir(tmp_path)
    main(["reproduce", "--preset", "easy"])
    cfg = seen["cfg"]
    assert cfg.out == Path("results") / "paper"
    trials = rep.plan(cfg)
    seeds: dict[str, list[int]] = {}
    for t in trials:
        seeds.setdefault(t.label, []).append(t.seed)
    assert seeds == {"csac": [1, 2, 3, 4, 5], "sac": [1, 2, 3, 4, 5], "ppo": [1, 2, 3, 4, 5],
                     "sac_lag": [1, 2, 3], "ppo_lag": [1, 2, 3], "csac_paper": [1, 2, 3],
                     "csac_min": [1, 2, 3], "csac_fixed_d": [1, 2, 3],
                     "ppo_3m": [1, 2, 3]}  # fmt: skip
    # one budget for the comparison; PPO's larger one an extra row
    assert {t.label for t in trials if t.total_steps != 1_000_000} == {"ppo_3m"}
    assert {t.total_steps for t in trials} == {1_000_000, 3_000_000}
    by = {t.name: t for t in trials}
    # one evaluation protocol for all, whatever the recipe: every 250k, 400 validation episodes
    assert all(t.train_args[:6] == rep.PAPER_TRAIN_ARGS for t in trials)
    assert rep.trial_recipe(by["csac-seed1"]) is None  # the default csac recipe
    stack = load_recipe("csac").section("run")["env_kwargs"]
    for label in ("sac", "ppo", "sac_lag", "ppo_lag", "ppo_3m"):
        t = by[f"{label}-seed1"]
        assert t.algo == label.removesuffix("_3m") and t.train_args[-1] == "--flight-filter", label
        recipe = load_recipe(rep.trial_recipe(t))
        assert recipe.algo == t.algo and recipe.section("run")["shield"] is True, label
        assert recipe.section("run")["env_kwargs"] == stack, label
    assert load_recipe("csac").section("run")["flight_filter"] is True
    assert by["csac_paper-seed1"].train_args[-2:] == ("--config", "csac-paper")
    assert by["csac_fixed_d-seed2"].train_args[6:] == ("--csac.curriculum.no-enabled",)
    assert by["csac_min-seed2"].train_args[6:] == ("--csac.cost-target", "min")
    assert rep.REPORT_LABELS[:3] == ("csac", "sac", "ppo") and rep.REPORT_LABELS.count("csac") == 1

    seen.clear()
    main(["reproduce", "--preset", "easy", "--algos", "paper-observation"])
    cfg = seen["cfg"]
    assert cfg.out == Path("results") / "paper-observation"
    trials = rep.plan(cfg)
    seeds = {}
    for t in trials:
        seeds.setdefault(t.label, []).append(t.seed)
    assert seeds == {"csac": [1, 2, 3, 4, 5], "sac": [1, 2, 3, 4, 5], "ppo": [1, 2, 3, 4, 5],
                     "sac_lag": [1, 2, 3], "ppo_lag": [1, 2, 3],
                     "csac_min": [1, 2, 3], "csac_fixed_d": [1, 2, 3],
                     "csac_3m": [1, 2, 3, 4, 5], "sac_3m": [1, 2, 3, 4, 5],
                     "ppo_3m": [1, 2, 3, 4, 5], "sac_lag_3m": [1, 2, 3],
                     "ppo_lag_3m": [1, 2, 3], "csac_tuned_3m": [1, 2, 3, 4, 5],
                     "sac_tuned_3m": [1, 2, 3, 4, 5],
                     "ppo_tuned_3m": [1, 2, 3, 4, 5], "sac_lag_tuned_3m": [1, 2, 3],
                     "ppo_lag_tuned_3m": [1, 2, 3]}  # fmt: skip
    steps = {t.label: t.total_steps for t in trials}
    assert {k for k, v in steps.items() if v != 1_000_000} == {
        "csac_3m", "sac_3m", "ppo_3m", "sac_lag_3m", "ppo_lag_3m", "csac_tuned_3m", "sac_tuned_3m",
        "ppo_tuned_3m", "sac_lag_tuned_3m", "ppo_lag_tuned_3m"}  # fmt: skip
    assert {t.algo for t in trials if t.label.endswith("_3m")} == {
        "csac", "sac", "ppo", "sac_lag", "ppo_lag"}  # fmt: skip
    by = {t.name: t for t in trials}
    # every CSAC label on the baselines' observation and env (their recipes' base)
    crash = ("--config", "csac-maxcost-crashloss")
    for label in ("csac", "csac_min", "csac_fixed_d", "csac_3m"):
        assert by[f"{label}-seed1"].train_args[6:8] == crash, label
        assert rep.trial_recipe(by[f"{label}-seed1"]) == "csac-maxcost-crashloss"
    assert by["sac-seed1"].train_args[6:] == ()  # the sac recipe, no shield, no filter
    # the tuned baselines: each its packaged recipe, found from any working directory
    assert by["sac_lag_tuned_3m-seed3"].train_args[-2:] == ("--config", "sac-lag-tuned")
    assert by["ppo_tuned_3m-seed5"].algo == "ppo"
    with pytest.raises(SystemExit) as err:  # the CLI's clear error for a SafenavError
        main(["reproduce", "--algos", "paper-observation", "csac"])
    assert err.value.code == 2
    # named algorithms: results/<algos>, seeds per label where given
    seen.clear()
    main(["reproduce", "--preset", "easy", "--algos", "csac", "sac", "--seeds", "1-3 sac=4,5"])
    cfg = seen["cfg"]
    assert cfg.out == Path("results") / "csac+sac"
    assert [t.name for t in rep.plan(cfg)] == ["csac-seed1", "csac-seed2", "csac-seed3",
                                               "sac-seed4", "sac-seed5"]  # fmt: skip
    # a count starts at seed 1, as the comparison's seeds 1-5 and safenav bench: "--seeds 1" once
    # trained seed 0 beside finished seed-1 trials
    seen.clear()
    main(["reproduce", "--preset", "easy", "--algos", "sac", "--seeds", "2"])
    assert [t.name for t in rep.plan(seen["cfg"])] == ["sac-seed1", "sac-seed2"]


@pytest.mark.parametrize(
    "spec, message",
    [("sac=1-3", "start with the default seeds"), ("1-5 sac", "not LABEL=SEEDS"),
     ("1-5 sac=3", "as a range"), ("1-5 sac=3-1", "distinct seeds")],
)  # fmt: skip
def test_seed_spec_mistakes_are_refused(spec, message):
    from safenav.commands.reproduce import parse_seed_spec

    with pytest.raises(SafenavError, match=message):
        parse_seed_spec(spec)


# -- one trial: fresh, resumed, evaluated, skipped --------------------------------------------

# A stand-in for ``python -m safenav {train,eval}`` that writes what the real commands write.
FAKE_SAFENAV = """#!{python}
import json, sys, pathlib
verb, args = sys.argv[3], sys.argv[4:]
def arg(name):
    return args[args.index(name) + 1]
if verb == "eval":
    out = pathlib.Path(arg("--json"))
    ck = json.loads(pathlib.Path(args[0]).read_text())
    out.write_text(json.dumps({{"success_rate": ck["success"], "collision_rate": 0.05,
        "timeout_rate": 0.95 - ck["success"], "episodes": int(arg("--episodes")),
        "env_seed": int(arg("--env-seed"))}}))
    (out.parent.parent / "calls.txt").open("a").write("eval\\n")
    sys.exit(0)
run, total, seed = pathlib.Path(arg("--run-dir")), int(arg("--total-steps")), int(arg("--seed"))
if "--fail" in args:
    print("boom: something broke"); sys.exit(3)
if "--hang" in args:  # runs until stopped; answers SIGTERM as the trainer does (checkpoint, 143)
    import os, signal, time
    run.mkdir(parents=True, exist_ok=True)
    def stop(signum, frame):  # a real checkpoint (replay buffer and all) takes seconds to write
        time.sleep(float(arg("--stop-seconds")) if "--stop-seconds" in args else 0)
        (run.parent / f"stopped-{{seed}}").write_text(""); sys.exit(143)
    signal.signal(signal.SIGTERM, stop)
    (run.parent / f"hang-{{seed}}.pid").write_text(str(os.getpid()))
    time.sleep(600)
if "--interrupted" in args:  # the trainer's answer to Ctrl-C: a checkpoint, then exit 130
    run.mkdir(parents=True, exist_ok=True)
    (run / "checkpoint.pt").write_text(json.dumps({{"step": 100}})); sys.exit(130)
if "--killed-once" in args and not (run.parent / f"killed-{{seed}}").exists():
    run.parent.mkdir(parents=True, exist_ok=True)
    (run.parent / f"killed-{{seed}}").write_text("")  # as the OOM killer would: SIGKILL
    import os, signal; os.kill(os.getpid(), signal.SIGKILL)
run.mkdir(parents=True, exist_ok=True)
start = json.loads((run / "checkpoint.pt").read_text())["step"] if "--resume" in args else 0
with (run / "progress.csv").open("a" if start else "w") as f:
    if not start:
        f.write("global_step,charts/success_rate,charts/collision_rate,constraint/lambda,"
                "constraint/d,perf/sps,eval/success_rate,eval/collision_rate,eval/timeout_rate\\n")
    for step in range(start + 100, total + 1, 100):
        ev = (f"{{step / total * 0.9}},{{0.2 * (1 - step / total)}},0.1" if step % 500 == 0
              else ",,")  # the periodic evaluation on the validation maps, every 500 steps
        f.write(f"{{step}},{{step / total * 0.9}},{{0.3 * (1 - step / total)}},0.1,0.2,1000,{{ev}}\\n")
success = 0.8 + 0.05 * seed
(run / "config.json").write_text(json.dumps({{"algo": arg("--algo"), "seed": seed}}))
(run / "checkpoint.pt").write_text(json.dumps({{"step": total, "resumed_from": start,
                                                "success": success}}))
if "--select" in args:  # what train --select leaves: the validation choice and its report
    (run / "policy.pt").write_text((run / "checkpoint.pt").read_text())
    (run / "selection.json").write_text(json.dumps({{"selection": "validation",
                                                     "wall_clock_s": 12.5}}))
    (run / "final.json").write_text(json.dumps({{"heldout": {{"seeds": [2, 3, 4, 5, 6],
        "episodes_per_seed": 10, "success_rate": success - 0.1, "collision_rate": 0.1,
        "timeout_rate": 0.9 - success}}, "test_navrl_rule": {{"episodes": 10,
        "success_rate": success, "collision_rate": 0.05, "timeout_rate": 0.95 - success}},
        "flight_filter": {{"view": "observation", "stall": [10.0, 2.0, 5.0]}},
        "test_without_filter": {{"episodes": 10, "success_rate": success - 0.2,
        "collision_rate": 0.2, "timeout_rate": 1.0 - success}}}}))
(run.parent / "calls.txt").open("a").write(" ".join(args) + "\\n")
"""


@pytest.fixture
def fake_python(tmp_path) -> str:
    """An executable that answers ``-m safenav train|eval ...`` like the real commands."""
    path = tmp_path / "fake-python"
    path.write_text(FAKE_SAFENAV.format(python=sys.executable))
    path.chmod(0o755)
    return str(path)


def make_trial(tmp_path, python, total=1000, **kw) -> rep.Trial:
    return rep.Trial(label="csac", algo="csac", seed=0, total_steps=total,
                     run_dir=tmp_path / "runs" / "csac" / "seed0", log_dir=tmp_path / "logs",
                     cpus=1, eval_episodes=10, python=python, **kw)  # fmt: skip


def test_trial_fresh_then_skipped_then_resumed_for_more_steps(tmp_path, fake_python):
    trial = make_trial(tmp_path, fake_python)
    calls = trial.run_dir.parent / "calls.txt"
    assert rep.trial_state(trial) == "fresh"
    info = rep.run_trial(trial)
    assert info["state"] == "fresh" and info["train_s"] > 0 and info["eval_s"] > 0
    assert rep.trial_state(trial) == "done"
    marker = json.loads((trial.run_dir / "reproduce.json").read_text())
    assert marker["trained"] and marker["total_steps"] == 1000 and len(marker["attempts"]) == 1
    assert trial.log("train.log").exists() and trial.log("status").read_text() == "done"
    n_calls = len(calls.read_text().splitlines())
    assert rep.run_trial(trial)["state"] == "done"  # a finished trial is skipped
    assert len(calls.read_text().splitlines()) == n_calls
    # Asking for more steps resumes the run from its checkpoint, then re-evaluates.
    longer = make_trial(tmp_path, fake_python, total=2000)
    assert rep.trial_state(longer) == "resume"
    rep.run_trial(longer)
    last_train = [c for c in calls.read_text().splitlines() if c != "eval"][-1]
    assert "--resume" in last_train
    # a resumed run keeps its recipe (safenav train refuses --config with --resume)
    recipe = make_trial(tmp_path, fake_python, train_args=("--config", "csac-paper", "--x"))
    assert "--config" not in recipe.train_command(resume=True)
    assert recipe.train_command(resume=False)[-3:] == ["--config", "csac-paper", "--x"]
    assert rep.without_config(["--config=a", "--y", "--config", "b", "--z"]) == ["--y", "--z"]
    assert json.loads(longer.checkpoint.read_text())["resumed_from"] == 1000
    assert rep.trial_state(longer) == "done"
    marker = json.loads((trial.run_dir / "reproduce.json").read_text())
    assert len(marker["attempts"]) == 2 and marker["attempts"][1]["resume"]
    rec = agg.seed_record(trial.run_dir)
    assert rec["algo"] == "csac" and rec["seed"] == 0 and rec["env_steps"] == 2000
    # the policy chosen on validation was the one evaluated; its held-out report is in the record
    assert "--select" in last_train and rec["selection"] == "validation"
    assert rec["heldout"]["success_rate"] == pytest.approx(0.7)
    # and the test episodes under NavRL's collision rule, in results.json and results.md
    assert rec["test_navrl_rule"]["success_rate"] == pytest.approx(0.8)
    results = agg.aggregate([rec])
    assert results["algos"]["csac"]["test_navrl_rule"]["success_rate"]["mean"] == pytest.approx(0.8)
    assert "## Under the paper's collision rule" in agg.render_markdown(results)
    # a policy reported behind the planner filter: the test behind its shield alone beside it
    assert rec["planner_filter"]["view"] == "observation" and rec["selection_wall_clock_s"] == 12.5
    unfiltered = results["algos"]["csac"]["test_without_filter"]
    assert unfiltered["success_rate"]["mean"] == pytest.approx(0.6) and unfiltered["seeds"] == 1
    assert unfiltered["ci95"]["collision_rate"]["episodes"] == 10
    assert "## Without the planner filter" in agg.render_markdown(results)
    # the time to the selected policy: training plus the selection on validation maps
    to_policy = results["algos"]["csac"]["to_policy_wall_clock_s"]
    assert to_policy["max"] == pytest.approx(rec["wall_clock_s"] + 12.5)
    assert " (+ " in agg.render_markdown(results)
    # each finished trial leaves OUT/trials/<label>-s<seed>.json, small enough to commit
    kept = json.loads(longer.record_path.read_text())
    assert longer.record_path == tmp_path / "trials" / "csac-s0.json"
    assert kept["env_steps"] == 2000 and kept["budget_env_steps"] == 2000
    assert "--select" in kept["train_command"] and kept["heldout"]["seeds"] == [2, 3, 4, 5, 6]
    assert kept["test_navrl_rule"]["collision_rate"] == pytest.approx(0.05)
    # with the evaluated policy beside it, so that a fresh clone can fly it again
    assert kept["policy"] == "trials/csac-s0.pt"
    assert (tmp_path / "trials" / "csac-s0.pt").read_bytes() == longer.policy.read_bytes()
    # Training wall-clock: the measured attempts (the run logged no elapsed-time column).
    assert rec["wall_clock_s"] == marker["train_wall_clock_s"] > 0
    # The trial's whole time (every attempt and the last eval), for the next sweep's estimate.
    assert marker["eval_wall_clock_s"] > 0
    total = marker["train_wall_clock_s"] + marker["eval_wall_clock_s"]
    assert kept["trial_wall_clock_s"] == pytest.approx(total, abs=0.02)


def test_a_record_reported_again_since_its_run_is_not_overwritten_by_the_run(tmp_path):
    """``experiments/rereport_filter.py`` flies a committed record's policy again: that record is
    newer than its run directory's report, and a later sweep keeps it (the run directory's files
    would bring the older report back); a record reported before the run's is not kept."""
    import json
    import os
    from datetime import datetime, timezone

    trial = make_trial(tmp_path, sys.executable)
    trial.run_dir.mkdir(parents=True)
    evaluated = trial.run_dir / "eval.json"
    evaluated.write_text("{}")
    os.utime(evaluated, (1.0e9, 1.0e9))  # the run's report: 2001
    trial.record_path.parent.mkdir(parents=True)
    assert rep.rereported_record(trial) is None  # no record
    now = datetime.now(timezone.utc).isoformat(timespec="seconds")
    rec = {"algo": "csac", "seed": 0, "success_rate": 0.9, "rereported": {"date": now}}
    trial.record_path.write_text(json.dumps(rec))
    assert rep.rereported_record(trial) == rec
    os.utime(evaluated, None)  # the run reported again after it
    trial.record_path.write_text(
        json.dumps({**rec, "rereported": {"date": "2001-01-01T00:00:00+00:00"}})
    )
    assert rep.rereported_record(trial) is None
    trial.record_path.write_text(json.dumps({"algo": "csac", "seed": 0}))
    assert rep.rereported_record(trial) is None  # never reported again


def test_trial_evaluates_only_when_trained_but_not_evaluated(tmp_path, fake_python):
    trial = make_trial(tmp_path, fake_python)
    rep.run_trial(trial)
    (trial.run_dir / "eval.json").unlink()
    assert rep.trial_state(trial) == "evaluate"
    more = dataclasses.replace(trial, eval_episodes=20)
    assert rep.trial_state(more) == "evaluate"  # different episode count: evaluate again
    rep.run_trial(more)
    assert json.loads((trial.run_dir / "eval.json").read_text())["episodes"] == 20
    assert rep.trial_state(more) == "done"


def test_failed_trial_raises_with_the_log_tail(tmp_path, fake_python):
    trial = make_trial(tmp_path, fake_python, train_args=("--fail",))
    with pytest.raises(rep.TrialFailed, match="boom: something broke"):
        rep.run_trial(trial)
    assert rep.trial_state(trial) == "fresh"


def test_a_trainer_stopped_by_sigint_is_reported_as_stopped_not_retried(tmp_path, fake_python):
    """``kill -INT`` of one trainer (exit 130, checkpoint written): no retry, and the sweep's
    report says it can be resumed instead of showing a bare exit code."""
    trial = make_trial(tmp_path, fake_python, train_args=("--interrupted",))
    with pytest.raises(rep.TrialFailed, match="stopped by SIGINT with a checkpoint") as err:
        rep.run_trial(trial)
    assert not isinstance(err.value, rep.TrialKilled)
    assert rep.trial_state(trial) == "resume"
    assert trial.log("status").read_text() == "stopped"


def test_a_killed_trial_raises_trial_killed_which_ray_retries(tmp_path, fake_python):
    """A signal (here SIGKILL) is TrialKilled, which Ray retries; an exit code is not."""
    trial = make_trial(tmp_path, fake_python, train_args=("--killed-once",))
    with pytest.raises(rep.TrialKilled, match="exit code -9"):
        rep.run_trial(trial)
    assert rep.run_trial(trial)["state"] == "fresh"  # the retry (nothing saved before the kill)
    assert rep.trial_state(trial) == "done"
    assert not issubclass(rep.TrialFailed, rep.TrialKilled)


def test_cpu_hours_estimate_and_eta(tmp_path, fake_python):
    def states(trials):
        return {t.name: rep.trial_state(t) for t in trials}

    def total(*args):  # CPU-seconds of all the trials, and the rate's source
        per_trial, source = rep.estimate_cpu_seconds(*args)
        return sum(per_trial.values()), source

    todo = [make_trial(tmp_path, fake_python, total=1_000_000),
            dataclasses.replace(make_trial(tmp_path, fake_python, total=2_000_000), algo="ppo",
                                label="ppo", run_dir=tmp_path / "runs" / "ppo" / "seed0")]  # fmt: skip
    cpu_s, source = total(todo, [], states(todo))
    rates = rep.CPU_S_PER_STEP
    assert cpu_s == pytest.approx(1e6 * rates["csac"] + 2e6 * rates["ppo"])
    assert "development machine" in source
    # rows left by an attempt that never checkpointed are run again (the trial starts afresh) ...
    todo[0].run_dir.mkdir(parents=True)
    (todo[0].run_dir / "progress.csv").write_text("global_step,x\n250000,1\n")
    assert total(todo[:1], [], states(todo[:1]))[0] == pytest.approx(1e6 * rates["csac"])
    # ... a trial that resumes from its checkpoint counts the steps it has left
    (todo[0].run_dir / "checkpoint.pt").write_text("")
    assert total(todo[:1], [], states(todo[:1]))[0] == pytest.approx(7.5e5 * rates["csac"])
    # finished trials of the sweep give the rate: 1000 s x 1 CPU for 1000 steps = 1 s per step
    done = make_trial(tmp_path, fake_python, total=1000)
    done = dataclasses.replace(done, run_dir=tmp_path / "runs" / "csac" / "seed9", seed=9)
    done.record_path.parent.mkdir(parents=True, exist_ok=True)
    done.record_path.write_text(json.dumps({"wall_clock_s": 1000.0, "env_steps": 1000}))
    cpu_s, source = total(todo[:1], [done], states(todo[:1]))
    assert cpu_s == pytest.approx(7.5e5) and source == (
        "the report after training not counted; this sweep's finished trials"
    )
    # ... plus what a finished trial took beyond training (selection, report): 300 s x 1 CPU,
    # by label, else from any finished trial of the same kind (behind the planner filter or not)
    done.record_path.write_text(
        json.dumps({"wall_clock_s": 1000.0, "env_steps": 1000, "trial_wall_clock_s": 1300.0})
    )
    cpu_s, source = total(todo[:1], [done], states(todo[:1]))
    assert cpu_s == pytest.approx(7.5e5 + 300) and "report after training measured" in source
    other = todo[1]  # label ppo: no finished trial of its own
    assert total([other], [done], states([other]))[0] == pytest.approx(2e6 * rates["ppo"] + 300)
    filtered = dataclasses.replace(other, train_args=(*other.train_args, "--flight-filter"))
    assert total([filtered], [done], states([filtered]))[0] == pytest.approx(2e6 * rates["ppo"])
    # a trial of another recipe (a --variants label) costs what that recipe was measured at
    paper = dataclasses.replace(todo[0], label="csac_paper", run_dir=tmp_path / "runs" / "p" / "s0",
                                train_args=("--eval-every", "1000", "--config", "csac-paper"))  # fmt: skip
    assert rep.trial_recipe(paper) == "csac-paper" and rep.trial_recipe(todo[0]) is None
    assert rep.trial_recipe(dataclasses.replace(paper, train_args=("--config=csac",))) == "csac"
    cpu_s, _ = total([paper], [done], states([paper]))
    assert cpu_s == pytest.approx(1e6 * rep.CPU_S_PER_STEP_BY_RECIPE["csac-paper"] + 300)
    by_recipe = rep.CPU_S_PER_STEP_BY_RECIPE
    assert by_recipe["csac-paper"] > 10 * by_recipe["csac-maxcost-crashloss"]
    line = rep.eta_line(1, 4, 250, 1000, 600.0, now=0.0)
    assert line == "1 of 4 trials done; about 30.0 min left (ETA 00:30 UTC)"
    assert rep.eta_line(0, 4, 0, 1000, 5.0) == "0 of 4 trials done"
    # per trial, for the sweep to schedule on its slots
    per_trial, _ = rep.estimate_cpu_seconds(todo, [], states(todo))
    assert per_trial == {todo[0].name: pytest.approx(7.5e5 * rates["csac"]),
                         todo[1].name: pytest.approx(2e6 * rates["ppo"])}  # fmt: skip


def test_wall_clock_counts_the_trials_that_run_with_slots_idle():
    """Three 2-hour trials on two slots take 4 h (the third runs alone), not 3 h; the ETA of a
    last trial running alone is its own length, not half of it (csac_tuned_3m seed 5,
    2026-12-03: "about 60 min left" for a trial that took 2 h)."""
    assert rep.schedule_seconds([7200, 7200, 7200], 2) == 14400
    assert rep.schedule_seconds([3000, 1000, 1000, 1000], 2) == 3000
    assert rep.schedule_seconds([100, 200], 8) == 200
    assert rep.schedule_seconds([], 2) == 0.0
    assert rep.schedule_seconds([5, 5], 0) == 10  # no slot reported: one at a time
    # trials of 2000 and 4000 steps ran together for 2 h, 2000 steps each: the first is done,
    # the second has 2000 steps left at one slot's rate (7200 s x 2 slots / 4000 steps)
    line = rep.eta_line(1, 2, 4000, 6000, 7200.0, now=0.0, steps_left=[2000], slots=2)
    assert line == "1 of 2 trials done; about 2.00 h left (ETA 02:00 UTC)"
    # the old estimate (the steps left at both slots' rate) said half of it
    assert "about 60.0 min left" in rep.eta_line(1, 2, 4000, 6000, 7200.0, now=0.0)


def test_confidence_intervals_wilson_by_hand_and_bootstrap_over_seeds():
    import math

    ci = agg.confidence_intervals([(0.85, 200), (0.95, 200), (0.9, 200), (None, 200)])
    k, n, z = 540, 600, 1.959963984540054
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    assert ci["pooled"] == pytest.approx(p) and ci["episodes"] == n and ci["seeds"] == 3
    assert ci["wilson"] == pytest.approx([centre - half, centre + half], abs=1e-9)
    low, high = ci["bootstrap_seeds"]  # resampling 3 seeds: the mean lies in [0.85, 0.95]
    assert 0.85 <= low < 0.9 < high <= 0.95
    assert agg.confidence_intervals([(0.5, 10)])["bootstrap_seeds"] is None  # one seed
    # two seeds: no interval (their bootstrap could only span the two values)
    assert agg.confidence_intervals([(0.85, 200), (0.95, 200)])["bootstrap_seeds"] is None
    assert agg.confidence_intervals([(None, 10)]) is None
