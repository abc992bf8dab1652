"""The diagnostic scripts of ``experiments/`` that docs/csac.md and docs/csac-v1.md quote run on a
tiny CSAC run: ``checkpoint_sweep.py`` (with ``--sampled``), ``cost_critic_bias.py``,
``flight_grid.py``, ``speed_profile.py``, ``timeout_paths.py`` and ``altitude_profile.py``; and
``vecenv_overhead.py`` (docs/gymnasium.md) on Pendulum-v1; ``shield_memory.py`` (docs/deployment.md);
``finish_runs.py`` (docs/csac-v1.md); ``shield_collisions.py`` (docs/deployment.md);
``collision_rule.py`` (docs/csac-v1.md); ``cost_critic_preactivation.py`` and
``velocity_profile.py`` (docs/gymnasium-results.md) on a tiny CSAC run of SafetyHopperVelocity-v5."""

from __future__ import annotations

import ast
import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import PAPER_OBSERVATION
from safenav.cli import main

ROOT = Path(__file__).resolve().parents[1]


def script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "experiments" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    from tests.test_train_cli import FAST

    run_dir = tmp_path_factory.mktemp("runs") / "csac"
    main(["train", *PAPER_OBSERVATION, "--preset", "easy", "--seed", "2", "--total-steps", "400",
          "--keep-policies", "--run-dir", str(run_dir), *FAST])  # fmt: skip
    return run_dir


@pytest.mark.long
def test_checkpoint_sweep_flies_every_policy_and_sampled_actions(tiny_run, tmp_path, monkeypatch):
    out = tmp_path / "sweep.json"
    monkeypatch.setattr(sys, "argv", ["checkpoint_sweep.py", str(tiny_run / "policies"),
                                      "--val-episodes", "3", "--test-episodes", "2", "--sampled",
                                      "--greedy-soup", "--json", str(out)])  # fmt: skip
    script("checkpoint_sweep").main()
    rows = json.loads(out.read_text())
    assert [r["global_step"] for r in rows[:2]] == [200, 400]
    assert rows[2]["policy"].startswith("greedy soup") and set(rows[2]["soup_steps"]) <= {200, 400}
    for r in rows[:2]:
        for part in ("val", "test", "val_sampled"):
            rates = [r[part][k] for k in ("success_rate", "collision_rate", "timeout_rate")]
            assert sum(rates) == pytest.approx(1.0)


def test_cost_critic_bias_compares_prediction_with_the_realised_cost(tiny_run):
    bias = script("cost_critic_bias")
    res = bias.measure(tiny_run / "checkpoint.pt", num_envs=4, steps=120, seed=0)
    assert res["transitions"] > 0 and res["global_step"] == 400
    assert math.isfinite(res["predicted_qc"]) and 0.0 <= res["realised_qc"] <= 1.0
    assert "realised_qc_near_collision" in res and "realised_qc_cost_ahead" not in res
    assert res["episodes"] > 0 and 0.0 <= res["episode_cost"] <= res["episode_length"] <= 120
    with pytest.raises(SystemExit, match="policy-only"):
        bias.measure(tiny_run / "best.pt", num_envs=2, steps=5, seed=0)


def test_cost_critic_bias_sums_each_finished_episode_and_leaves_out_running_ones():
    t = torch.tensor
    # env 0: an episode of 2 steps (costs 1, 0), then one of 3 (1, 1, 1); env 1: 4 steps (cost
    # 0, 0, 1, 0), then one still running at the end (left out)
    steps = [
        (t([1.0, 0.0]), t([1.0, 2.0]), t([False, False])),
        (t([0.0, 0.0]), t([1.0, 2.0]), t([True, False])),
        (t([1.0, 1.0]), t([3.0, 2.0]), t([False, False])),
        (t([1.0, 0.0]), t([3.0, 2.0]), t([False, True])),
        (t([1.0, 5.0]), t([3.0, 9.0]), t([True, False])),
    ]
    episodes = script("cost_critic_bias").finished_episodes(steps)
    assert sorted(episodes) == [(1.0, 2.0, 2.0), (1.0, 8.0, 4.0), (3.0, 9.0, 3.0)]
    assert script("cost_critic_bias").finished_episodes([]) == []


def test_timeout_paths_splits_the_eval_episodes_by_outcome(tiny_run, tmp_path):
    result = tmp_path / "eval.json"
    main(["eval", str(tiny_run / "best.pt"), "--episodes", "6", "--json", str(result)])
    data = json.loads(result.read_text())
    rows = script("timeout_paths").summarise(data)
    assert sum(r["episodes"] for r in rows.values()) == 6
    per = data["per_episode"]
    for outcome, r in rows.items():
        paths = [p for p, hit in zip(per["path_length"], per[outcome], strict=True) if hit]
        assert r["path_m"] == pytest.approx([min(paths), float(np.median(paths)), max(paths)])
        lo, med, hi = r["path_over_distance"]
        assert 0 < lo <= med <= hi and r["distance_m"][0] > 0
    data["per_episode"] = {k: v[:3] for k, v in per.items()}
    with pytest.raises(SystemExit, match="differ in length"):
        script("timeout_paths").summarise(data)


def test_speed_profile_bins_every_step_and_probes_the_critics(tiny_run):
    prof = script("speed_profile")
    res = prof.profile(tiny_run / "checkpoint.pt", env_seed=12345, episodes=3)
    bins = res["speed_by_clearance"]
    assert res["critics"] and sum(b["steps"] for b in bins) == res["steps"] > 0
    for b in bins:
        assert (b["mean_speed"] is None) == (b["steps"] == 0)
        assert b["steps"] == 0 or all(math.isfinite(b[k]) for k in ("qc", "dqc_half", "dqr_half"))
    assert len(res["saturated"]) == 3 and all(0.0 <= s <= 1.0 for s in res["saturated"])
    policy_only = prof.profile(tiny_run / "best.pt", env_seed=12345, episodes=3)
    assert not policy_only["critics"] and "dqc_half" not in policy_only["speed_by_clearance"][0]
    with pytest.raises(SystemExit, match="test or held-out"):
        prof.profile(tiny_run / "best.pt", env_seed=1, episodes=3)


def test_train_profile_splits_a_run_into_disjoint_parts(tmp_path):
    from tests.test_train_cli import FAST

    prof = script("train_profile")
    # the default csac recipe: trained behind the shield
    total, parts = prof.profile(["--algo", "csac", "--preset", "easy", "--seed", "2",
                                 "--total-steps", "400", "--run-dir", str(tmp_path / "run"),
                                 *FAST])  # fmt: skip
    assert (tmp_path / "run" / "checkpoint.pt").exists()
    disjoint = sum(v for k, v in parts.items() if k != "of which sensing")
    assert disjoint == pytest.approx(total) and all(v >= 0 for v in parts.values())
    for part in (
        "env step",
        "shield (training)",
        "actor forward",
        "gradient updates",
        "periodic evaluation",
        "checkpoints",
    ):
        assert parts[part] > 0, part
    assert 0 < parts["of which sensing"] < parts["env step"]
    assert parts["selection (validation)"] == parts["report (test, held-out)"] == 0
    from safenav.algos.csac import CSAC

    assert not hasattr(CSAC.update, "__wrapped__")  # the timers are gone after the run


def test_lever_table_reads_each_seeds_validation_curve(tmp_path, capsys):
    """``lever_table.py`` takes the seed from the config beside each events file, keeps the
    evaluations up to ``--upto``, and counts the seeds that time out in a third of the episodes."""
    files = []
    for seed, last in ((1, (0.1, 0.4, 0.5)), (2, (0.5, 0.4, 0.1)), (3, (0.3, 0.5, 0.2))):
        (tmp_path / f"x-s{seed}-config.json").write_text(json.dumps({"run": {"seed": seed}}))
        events = [{"global_step": 0, "event": "start"}]
        for step, rates in ((250_112, (0.0, 0.9, 0.1)), (500_224, last), (750_336, (1, 0, 0))):
            keys = ("eval/success_rate", "eval/collision_rate", "eval/timeout_rate")
            events.append(
                {"global_step": step, "event": "eval", **dict(zip(keys, rates, strict=True))}
            )
        path = tmp_path / f"x-s{seed}-events.jsonl"
        path.write_text("\n".join(json.dumps(e) for e in events))
        files.append(str(path))
    out = tmp_path / "table.json"
    assert script("lever_table").main([f"lever={files[0]}", *files[1:], "--upto", "600000",
                                       "--json", str(out)]) == 0  # fmt: skip
    report = json.loads(out.read_text())["lever"]
    assert set(report["seeds"]) == {"1", "2", "3"}
    assert report["last"]["success"]["mean"] == pytest.approx(0.3)
    low, high = report["last"]["success"]["ci95"]
    assert low < 0.3 < high
    assert report["last"]["seeds_stopping"] == 1
    assert "| 1 | 0.000 / 0.900 / 0.100 | 0.100 / 0.400 / 0.500 |" in capsys.readouterr().out
    # the same seeds from committed trial files (reproduce's validation_curve) read the same
    trials = []
    for seed in (1, 2, 3):
        curve = [{"env_steps": e["global_step"], "success_rate": e["eval/success_rate"],
                  "collision_rate": e["eval/collision_rate"], "timeout_rate": e["eval/timeout_rate"]}
                 for e in map(json.loads, Path(files[seed - 1]).read_text().splitlines())
                 if e["event"] == "eval"]  # fmt: skip
        trials.append(tmp_path / f"csac-s{seed}.json")
        trials[-1].write_text(json.dumps({"seed": seed, "validation_curve": curve}))
    again = tmp_path / "again.json"
    assert script("lever_table").main([f"lever={trials[0]}", *map(str, trials[1:]), "--upto",
                                       "600000", "--json", str(again)]) == 0  # fmt: skip
    assert json.loads(again.read_text()) == json.loads(out.read_text())
    # a second lever is paired with the first on the seeds both ran (here 1 and 3)
    both = tmp_path / "both.json"
    assert script("lever_table").main([f"base={trials[0]}", str(trials[2]), f"lever={files[0]}",
                                       *files[1:], "--upto", "600000", "--json", str(both)]) == 0  # fmt: skip
    paired = json.loads(both.read_text())["lever"]["paired_vs"]
    assert paired["label"] == "base" and paired["seeds"] == [1, 3]
    assert paired["success"]["mean"] == 0.0 and paired["success"]["per_seed"] == [0.0, 0.0]
    assert paired["success"]["ci95"] == [None, None]  # no interval from 2 seeds: null, strict JSON
    assert (
        "paired with base on seeds 1, 3, lever minus base: success +0.000"
        in capsys.readouterr().out
    )
    shifted = script("lever_table").paired_difference(
        {1: (0.1, 0.5, 0.4), 2: (0.3, 0.4, 0.3), 4: (0.0, 0.0, 1.0)},
        {1: (0.3, 0.5, 0.2), 2: (0.4, 0.5, 0.1), 3: (1.0, 0.0, 0.0)},
    )
    assert shifted["seeds"] == [1, 2] and shifted["success"]["mean"] == pytest.approx(0.15)
    assert shifted["timeout"]["per_seed"] == pytest.approx([-0.2, -0.2])


def test_flight_grid_flies_the_median_seed_of_each_label(tiny_run, tmp_path):
    import shutil

    out = tmp_path / "sweep"
    for seed, final in ((1, 0.1), (2, 0.5), (3, 0.9)):
        run = out / "runs" / "csac" / f"seed{seed}"
        run.mkdir(parents=True)
        shutil.copy(tiny_run / "checkpoint.pt", run / "policy.pt")
        (out / "trials").mkdir(exist_ok=True)
        (out / "trials" / f"csac-s{seed}.json").write_text(json.dumps(
            {"algo": "csac", "seed": seed, "validation_curve": [{"success_rate": final}]}))  # fmt: skip
    grid = script("flight_grid")
    assert grid.median_seed(out, "csac") == (2, 0.5)
    png, gif = tmp_path / "grid.png", tmp_path / "grid.gif"
    grid.main([str(out), "--labels", "csac", "--env-seed", "12345", "--episodes", "0", "1",
               "--out", str(png), "--gif", str(gif), "--gif-seconds", "2"])  # fmt: skip
    from PIL import Image

    assert Image.open(png).size[0] == 2 * 300  # two episodes, tiles of half the 600 px frame
    tile_height = Image.open(png).size[1]  # one row
    assert Image.open(gif).n_frames <= 10  # 2 s of flight, every third step, held at the end
    summary = json.loads(png.with_suffix(".json").read_text())
    assert summary["csac"]["seed"] == 2 and set(summary["csac"]) >= {"0", "1"}
    # --shield-memory: one row per value, named after the shield
    grid.main([str(out), "--labels", "csac", "--env-seed", "12345", "--episodes", "0",
               "--shield-memory", "0", "1", "20", "--out", str(png)])  # fmt: skip
    assert Image.open(png).size == (300, 3 * tile_height)  # three rows of one episode each
    assert set(json.loads(png.with_suffix(".json").read_text())) == {
        "csac", "csac + shield", "csac + shield (memory 20)"}  # fmt: skip
    # --as-recorded: one row, the policy as its checkpoint records (this one: no shield, no
    # filter); a fresh clone's policy is the one its trial committed
    shutil.move(out / "runs" / "csac" / "seed2" / "policy.pt", out / "trials" / "csac-s2.pt")
    grid.main([str(out), "--labels", "csac", "--env-seed", "12345", "--episodes", "0",
               "--as-recorded", "--out", str(png)])  # fmt: skip
    assert set(json.loads(png.with_suffix(".json").read_text())) == {"csac"}
    # the committed default-recipe policy flies behind its shield and filter, cap off under it
    flight = grid.recorded_flight(ROOT / "results" / "paper" / "trials" / "csac-s1.pt")
    assert flight["planner_filter"]["braking_cap"] is False
    assert (flight["shield_memory"], flight["shield_map"], flight["shield_mover_margin"],
            flight["shield_brake"]) == (1, True, 0.3, False)  # fmt: skip
    with pytest.raises(SystemExit, match="test or held-out"):
        grid.main([str(out), "--labels", "csac", "--env-seed", "1", "--out", str(png)])
    with pytest.raises(SystemExit, match="no trial of 'sac'"):
        grid.main([str(out), "--labels", "sac", "--out", str(png)])


def test_altitude_profile_counts_only_the_steps_flown_far_from_the_goal(tiny_run, tmp_path):
    alt = script("altitude_profile")
    near = alt.profile(tiny_run / "best.pt", env_seed=12345, episodes=4, far=0.0)
    far = alt.profile(tiny_run / "best.pt", env_seed=12345, episodes=4, far=100.0)
    result = tmp_path / "eval.json"
    main(["eval", str(tiny_run / "best.pt"), "--episodes", "4", "--env-seed", "12345",
          "--json", str(result)])  # fmt: skip
    times = json.loads(result.read_text())["per_episode"]["time"]
    # every step each episode flew, none of the hovering after its end; far=0: all of them
    assert near["flown_steps"] == near["far_steps"] == round(sum(times) / 0.1)
    assert far["far_steps"] == 0 and far["flown_steps"] == near["flown_steps"] > 0
    assert math.isnan(far["far_z_mean"]) and math.isnan(far["far_below_1m"])  # no step that far
    assert 0.2 <= near["far_z_p10"] <= near["far_z_p50"] <= near["far_z_p90"] <= 4.0
    assert 0.0 <= near["far_below_1m"] <= 1.0
    with pytest.raises(SystemExit):
        alt.main([str(tiny_run / "best.pt"), "--env-seed", "1"])


def test_vecenv_overhead_times_the_three_ways(tmp_path, monkeypatch, capsys):
    out = tmp_path / "overhead.json"
    monkeypatch.setattr(sys, "argv", ["vecenv_overhead.py", "--env", "Pendulum-v1", "--steps", "20",
                                      "--repeats", "2", "--json", str(out)])  # fmt: skip
    script("vecenv_overhead").main()
    figures = json.loads(out.read_text())
    assert figures["env"] == "Pendulum-v1" and figures["normalize"] is True
    printed = capsys.readouterr().out
    for way in ("raw", "numpy", "torch"):
        assert len(figures[way]["repeats_ms"]) == 2 and figures[way]["median_ms"] > 0
        assert f"{way}: " in printed


def test_shield_memory_flies_each_memory_and_pairs_them_by_policy(tiny_run, tmp_path):
    """experiments/shield_memory.py: one JSON per (policy, setting, map), reused on a rerun, and
    the paired differences against no shield and the memoryless shield; ``1map`` adds the map
    scan, ``-mover0.3`` clearance from moving obstacles."""
    sm = script("shield_memory")
    policy = tiny_run / "best.pt"
    settings = ["0", "1", "3", "1map", "1map-mover0.3"]
    rows = sm.run([policy], settings, [(12345, 3)], tmp_path)
    assert [r["memory"] for r in rows] == settings
    files = [f"best-m{m}-seed12345-3.json" for m in settings]
    assert sorted(f.name for f in tmp_path.glob("*.json")) == sorted(files)
    assert json.loads((tmp_path / files[2]).read_text())["shield_memory"] == 3
    scanned = json.loads((tmp_path / files[3]).read_text())
    assert scanned["shield_memory"] == 1 and scanned["shield_map"] is True
    assert json.loads((tmp_path / files[4]).read_text())["mover_margin"] == 0.3
    before = {f: (tmp_path / f).stat().st_mtime_ns for f in files}
    again = sm.run([policy], settings, [(12345, 3)], tmp_path)  # nothing flown again
    assert json.dumps(again) == json.dumps(rows)  # (NaN, the time to goal of no arrival, != NaN)
    assert {f: (tmp_path / f).stat().st_mtime_ns for f in files} == before
    table = "\n".join(sm.paired_differences(rows, settings))
    for m, base in (("1", "0"), ("3", "0"), ("3", "1"), ("1map", "1"), ("1map-mover0.3", "1")):
        d = rows[settings.index(m)]["collision_rate"] - rows[settings.index(base)]["collision_rate"]
        assert f"| {m} | {base} |" in table and f"{d:+.3f}" in table
    # --against: the later settings paired against another one, and only against it
    table = "\n".join(sm.paired_differences(rows, settings, ["1map"]))
    d = rows[4]["success_rate"] - rows[3]["success_rate"]
    assert f"| 1map-mover0.3 | 1map | {d:+.3f}" in table
    assert "| 1 | 0 |" not in table and "| 1map | 1 |" not in table


def test_shield_memory_parses_the_braking_and_filter_settings():
    sm = script("shield_memory")
    assert sm.parse_setting("1map-mover0.3-brake") == (1, True, 0.3, False, True, 0.0, None)
    assert sm.parse_setting("1map-mover0.3-slide") == (1, True, 0.3, False, "slide", 0.0, None)
    assert sm.parse_setting("1map-mover0.3-brake-keep0.5") == (1, True, 0.3, False, True, 0.5, None)
    assert sm.parse_setting("1map-mover0.3-brake-filter")[-1] == "simulator"
    assert sm.parse_setting("1map-mover0.3-brake-filterobs")[-1] == "observation"
    assert sm.parse_setting("1map-mover0.3-brake-filterobs-stall")[-1] == "observation-stall"
    assert sm.parse_setting("1map-mover0.3-brake-filterobs-stall4")[-1] == "observation-stall4"
    assert sm.stall_of("") == (None, "tumbling")
    assert sm.stall_of("stall") == ((10.0, 2.0, 5.0), "tumbling")
    assert sm.stall_of("stall4") == ((10.0, 4.0, 5.0), "tumbling")
    assert sm.parse_setting("1map-mover0.3-brake-filterobs-stallslide5")[-1] == (
        "observation-stallslide5"
    )
    assert sm.stall_of("stallslide") == ((10.0, 2.0, 5.0), "sliding")
    assert sm.stall_of("stallslide5") == ((5.0, 1.0, 5.0), "sliding")
    tk = script("timeout_kinds")
    assert [tk.kind(0.3, 0.2), tk.kind(8.6, 0.1), tk.kind(6.6, 3.6)] == ["frozen", "dithering",
                                                                          "moving"]  # fmt: skip
    ends = {"time": [12.0, 55.5, 60.0, 51.0, 9.9], "success": [1.0, 1.0, 0.0, 1.0, 1.0]}
    assert tk.arrival_bins({"per_episode": ends}) == {"0-10": 1, "10-20": 1, "20-30": 0,
                                                     "30-40": 0, "40-50": 0, "50-60": 2}  # fmt: skip
    # 3 s at 10 Hz: 1 s straight at the goal (1 m/s), 1 s sideways (1 m/s), 1 s still.
    xs = [0.1 * i for i in range(11)] + [1.0] * 20
    ys = [0.0] * 11 + [0.1 * i for i in range(1, 11)] + [1.0] * 10
    track = torch.tensor([[[x, y, 1.0]] for x, y in zip(xs, ys, strict=True)])
    use = tk.time_use(track, torch.tensor([[10.0, 0.0, 1.0]]), {"time": [3.1]},
                      torch.zeros(31, 1))  # fmt: skip
    assert use == {"progressing": 0.333, "moving_no_progress": 0.333,
                   "hovering": 0.333, "planner_share": 0.0, "progressing_speed": 1.0,
                   "progressing_rate": 1.0}  # fmt: skip
    assert sm.parse_setting("1map-mover0.3-brake-filterobs-stallslide5-short")[-1] == (
        "observation-stallslide5-short"
    )
    assert sm.parse_setting("1map-mover0.3-brake-filterobs-stallslide5-short-mapped")[-1] == (
        "observation-stallslide5-short-mapped"
    )
    assert (
        sm.parse_setting("1map-mover0.3-brake-filterobs-stallslide5-short-mapped-nearer")[-1]
        == "observation-stallslide5-short-mapped-nearer"
    )
    assert sm.parse_setting("1map-mover0.3-filterobs-stallslide5-short-turn0.5")[-1] == (
        "observation-stallslide5-short-turn0.5"
    )
    assert sm.parse_setting("1map-mover0.3-filterobs-stallslide5-short-turn0.5")[4] is False
    with pytest.raises(SystemExit, match="-mapped"):
        sm.parse_setting("1map-mover0.3-brake-filterobs-mapped")
    with pytest.raises(SystemExit, match="-filterobs"):
        sm.parse_setting("1map-stall")
    with pytest.raises(SystemExit, match="-slide"):
        sm.parse_setting("1map-brake-slide")
    with pytest.raises(SystemExit, match=r"\[0, 1\]"):
        sm.parse_setting("1map-keep1.5")


def test_shield_collisions_says_how_each_episode_ended(tiny_run, monkeypatch, capsys):
    """experiments/shield_collisions.py (docs/deployment.md): the outcome count, a line per
    collision and per timeout, behind the braking cap."""
    monkeypatch.setattr(sys, "argv", ["shield_collisions.py", str(tiny_run / "best.pt"), "12345",
                                      "3", '{"brake": true}'])  # fmt: skip
    script("shield_collisions").main()
    lines = [x for x in capsys.readouterr().out.splitlines() if x.strip()]
    outcomes = ast.literal_eval(lines[0])  # the script prints a dict of counts
    assert sum(outcomes.values()) == 3
    collided = sum(outcomes.get(k, 0) for k in ("static", "moving", "band"))
    assert len([x for x in lines if x.startswith("timeout")]) == outcomes.get("timeout", 0)
    assert len(lines) == 2 + collided + outcomes.get("timeout", 0)


@pytest.mark.long
def test_finish_runs_selects_on_validation_and_reports(tiny_run, tmp_path):
    """``finish_runs.py``: ``--select``'s ending on a run kept with ``--keep-policies``."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    script("finish_runs").main([str(run), "--out", str(tmp_path / "out"), "--report-episodes", "2"])
    final = json.loads((tmp_path / "out" / "run-final.json").read_text())
    selection = json.loads((tmp_path / "out" / "run-selection.json").read_text())
    assert selection["selection"] == "validation" and (run / "policy.pt").exists()
    assert final["test"]["episodes"] == 2 and final["shield"] is None
    assert len(final["heldout"]["per_seed"]) == 5


def test_compare_trials_pairs_the_test_episodes_of_two_labels(tmp_path, monkeypatch, capsys):
    """experiments/compare_trials.py (docs/csac-v1.md): the seed means' difference and McNemar's
    exact test on the episodes of the seeds both labels have."""
    for label, outcomes in (("a", ["SSSC", "SSTS", "SSSS"]), ("b", ["SCCC", "CSTC", "SSSS"])):
        for seed, o in enumerate(outcomes, start=1):
            record = {"seed": seed, "test_outcomes": o, "success_rate": o.count("S") / len(o),
                      "collision_rate": o.count("C") / len(o)}  # fmt: skip
            (tmp_path / f"{label}-s{seed}.json").write_text(json.dumps(record))
    out = tmp_path / "cmp.json"
    monkeypatch.setattr(sys, "argv", ["compare_trials.py", str(tmp_path / "a"),
                                      str(tmp_path / "b"), "--json", str(out)])  # fmt: skip
    script("compare_trials").main()
    text = capsys.readouterr().out
    assert "seeds [1, 2, 3]" in text
    result = json.loads(out.read_text())
    # seeds 1-3 paired: B collides at s1 episodes 1-2 and s2 episodes 0, 3 where A does not;
    # A's one collision (s1 episode 3) is B's too
    m = result["collision_rate"]["mcnemar"]
    assert (m["pairs"], m["only_a"], m["only_b"]) == (12, 0, 4)
    assert result["success_rate"]["mean_difference"]["difference"] == pytest.approx(
        (0.75 + 0.75 + 1.0) / 3 - (0.25 + 0.25 + 1.0) / 3
    )
    monkeypatch.setattr(
        sys, "argv", ["compare_trials.py", str(tmp_path / "none"), str(tmp_path / "b")]
    )
    with pytest.raises(SystemExit, match="no trial files"):
        script("compare_trials").main()


def test_compare_trials_reads_finish_runs_reports_and_keeps_the_seeds_named(
    tmp_path, monkeypatch, capsys
):
    """compare_trials.py on ``PREFIX-s<seed>-final.json`` reports (experiments/finish_runs.py):
    their per-episode test outcomes are paired with a label's trial files, only on --seeds."""
    for seed, (success, collision) in ((1, ([1, 0, 0], [0, 1, 0])), (2, ([1, 1, 0], [0, 0, 1]))):
        final = {"test": {"success_rate": sum(success) / 3, "collision_rate": sum(collision) / 3,
                          "per_episode": {"success": success, "collision": collision}}}  # fmt: skip
        (tmp_path / f"lever-s{seed}-final.json").write_text(json.dumps(final))
    for seed, o in ((1, "CCS"), (2, "SSS"), (3, "CCC")):
        record = {"seed": seed, "test_outcomes": o, "success_rate": o.count("S") / 3,
                  "collision_rate": o.count("C") / 3}  # fmt: skip
        (tmp_path / f"trial-s{seed}.json").write_text(json.dumps(record))
    out = tmp_path / "cmp.json"
    monkeypatch.setattr(sys, "argv", ["compare_trials.py", str(tmp_path / "lever"),
                                      str(tmp_path / "trial"), "--seeds", "1", "--json", str(out)])  # fmt: skip
    script("compare_trials").main()
    assert "seeds [1]; B:" in capsys.readouterr().out
    m = json.loads(out.read_text())["collision_rate"]["mcnemar"]
    # seed 1 only: the lever collides at episode 1, the trial at episodes 0 and 1 -> 0 / 1
    assert (m["pairs"], m["only_a"], m["only_b"], m["seeds"]) == (3, 0, 1, [1])


def test_collision_rule_flies_validation_first_and_pools_by_episodes(tmp_path, monkeypatch, capsys):
    """experiments/collision_rule.py (docs/csac-v1.md): every policy and rule on the validation
    maps before any test flight; rates pooled by episodes; a flight's JSON file is reused."""
    mod = script("collision_rule")
    flown = []

    def fake_eval(cmd, check, env, stdout):
        seed, rule = int(cmd[cmd.index("--env-seed") + 1]), cmd[cmd.index("--collision-rule") + 1]
        flown.append(seed)
        n = int(cmd[cmd.index("--episodes") + 1])
        rate = 0.5 if rule == "body" else 0.25
        Path(cmd[cmd.index("--json") + 1]).write_text(json.dumps(
            {"episodes": n, "success_rate": 1 - rate, "collision_rate": rate, "timeout_rate": 0.0,
             "collision_static_rate": rate if seed == 12345 else 0.0,
             "collision_dynamic_rate": 0.0 if seed == 12345 else rate}))  # fmt: skip

    monkeypatch.setattr(mod.subprocess, "run", fake_eval)
    out = tmp_path / "out"
    monkeypatch.setattr(sys, "argv", ["collision_rule.py", "a.pt", "b.pt", "--out", str(out)])
    mod.main()
    assert len(flown) == 2 * 2 * 5 and set(flown[:16]) == {12345, 12346, 12347, 12348}
    assert flown[16:] == [1, 1, 1, 1]
    summary = json.loads((out / "summary.json").read_text())
    val = summary["a"]["navrl"]["validation"]
    assert val["episodes"] == 400 and val["collision_static_rate"] == pytest.approx(0.25 / 4)
    assert summary["b"]["body"]["test"]["episodes"] == 200
    assert "| `a` | test (200) | navrl | 0.750 |" in capsys.readouterr().out
    flown.clear()
    mod.main()  # every file is there: nothing flies again
    assert flown == []


def test_filter_report_pools_the_test_episodes_and_pairs_them(tmp_path, capsys):
    fr = script("filter_report")
    setting = f"{fr.BASE}-filter"
    trials = tmp_path / "trials"
    trials.mkdir()

    def write(label, which, seed, outcomes, share=None):
        rates = {f"{k}_rate": outcomes.count(ch) / len(outcomes)
                 for k, ch in (("success", "S"), ("collision", "C"), ("timeout", "T"))}  # fmt: skip
        data = {**rates, "outcomes": outcomes,
                **({"filter_override_share": share} if share is not None else {})}  # fmt: skip
        (tmp_path / f"{label}-m{which}-seed{seed}-200.json").write_text(json.dumps(data))

    for label, seed in fr.POLICIES.items():
        write(label, fr.BASE, 1, "C" * 20 + "S" * 160 + "T" * 20)
        write(label, setting, 1, "S" * 20 + "S" * 160 + "T" * 20, share=0.08)  # crashes -> goals
        for s in fr.HELDOUT_SEEDS:
            write(label, setting, s, "S" * 190 + "C" * 10)
        heldout = {"success_rate": 0.8, "collision_rate": 0.1}
        (trials / f"csac-s{seed}.json").write_text(json.dumps({"heldout": heldout}))
    fr.main([str(tmp_path), "--setting", setting, "--trials", str(trials)])
    out = capsys.readouterr().out
    assert "| success | 0.800 (0.774-0.824) | 0.900 (0.880-0.917) |" in out
    assert "McNemar (collision, paired episodes): only with the filter 0, only without 100" in out
    assert "| default-s5 (5) | 0.800 | 0.100 | 0.950 | 0.050 |" in out
    assert (tmp_path / f"report-{setting}.md").exists()


def test_rereport_filter_rerecords_the_adopted_filter_once(tiny_run, tmp_path):
    """experiments/rereport_filter.py (docs/csac-v1.md, "The sliding test in the default
    recipe"): a policy recording the first (tumbling) filter records the adopted one after it,
    the earlier kept beside it; a second call leaves it; a policy without a filter is refused."""
    from safenav.algos.policy import load_policy, save_policy_only
    from safenav.common.checkpoint import load_checkpoint, save_checkpoint
    from safenav.envs.planner import filter_spec
    from safenav.errors import SafenavError

    rr = script("rereport_filter")
    policy = save_policy_only(tiny_run / "best.pt", tmp_path / "policy.pt")
    with pytest.raises(SafenavError, match="no planner filter"):
        rr.rerecord(policy)
    old = {"view": "observation", "stall": [10.0, 2.0, 5.0]}
    state = load_checkpoint(policy)
    state["policy"]["meta"]["flight_filter"] = old
    save_checkpoint(policy, state)
    assert rr.rerecord(policy) == (old, filter_spec())
    meta = load_policy(policy).meta
    assert meta["flight_filter"] == filter_spec() and meta["flight_filter_before"] == old
    assert rr.rerecord(policy) is None
    with pytest.raises(SafenavError, match="no --select report"):
        rr.rereport(tmp_path, episodes=1, device="cpu")


def test_rereport_filter_refolds_a_committed_trial_record(tiny_run, tmp_path, monkeypatch):
    """A fresh clone has the trial records and their policies, not the run directories: the
    record's report fields are flown again behind the adopted filter (here the flights are
    stand-ins that say what they flew), the earlier ones kept under "report_before"."""
    from safenav.algos.policy import save_policy_only
    from safenav.common.checkpoint import load_checkpoint, save_checkpoint
    from safenav.envs.planner import filter_spec
    from safenav.errors import SafenavError
    from safenav.experiments.aggregate import REPORT_FIELDS

    rr = script("rereport_filter")
    trials = tmp_path / "trials"
    policy = save_policy_only(tiny_run / "best.pt", trials / "csac-s3.pt")
    old = {"view": "observation", "stall": [10.0, 2.0, 5.0]}
    state = load_checkpoint(policy)
    state["policy"]["meta"]["flight_filter"] = old
    save_checkpoint(policy, state)
    record = trials / "csac-s3.json"
    record.write_text(json.dumps({"algo": "csac", "seed": 3, "success_rate": 0.5,
                                  "collision_rate": 0.1, "planner_filter": old,
                                  "wall_clock_s": 900.0, "policy": "trials/csac-s3.pt"}))  # fmt: skip
    flights = []

    def report(path, episodes, device):
        flights.append("report")
        (trials / "rereport").rmdir()  # another record's run, finished meanwhile, tidies up
        return {"flight_filter": filter_spec(), "heldout": {"seeds": [2, 3, 4, 5, 6],
                "success_rate": 0.9, "collision_rate": 0.02, "timeout_rate": 0.08}}  # fmt: skip

    def safenav_eval(cmd, check):
        flights.append("eval")
        out = Path(cmd[cmd.index("--json") + 1])
        out.write_text(json.dumps({"success_rate": 0.8, "collision_rate": 0.05,
                                   "timeout_rate": 0.15, "episodes": 200,
                                   "planner_filter_spec": filter_spec()}))  # fmt: skip

    monkeypatch.setattr(rr, "report_policy", report)
    monkeypatch.setattr(rr.subprocess, "run", safenav_eval)
    rr.rereport_record(record, episodes=200, device="cpu")
    rec = json.loads(record.read_text())
    assert flights == ["report", "eval"] and set(REPORT_FIELDS) <= set(rec)
    assert rec["success_rate"] == 0.8 and rec["heldout"]["success_rate"] == 0.9
    assert rec["planner_filter"] == filter_spec() and rec["wall_clock_s"] == 900.0
    assert rec["report_before"]["success_rate"] == 0.5
    assert rec["rereported"]["flight_filter_before"] == old
    assert not (trials / "rereport").exists()  # the side files folded in and removed
    rr.rereport_record(record, episodes=200, device="cpu")  # done: nothing flies again
    assert flights == ["report", "eval"]
    record.write_text(json.dumps({"algo": "csac", "seed": 4}))
    with pytest.raises(SafenavError, match="naming its policy"):
        rr.rereport_record(record, episodes=200, device="cpu")


def test_filter_trace_names_the_nearest_mover_and_its_velocity():
    from types import SimpleNamespace

    ft = script("filter_trace")
    env = SimpleNamespace(world_idx=torch.tensor([1]), n_dynamic=2,
                          pos=torch.tensor([[0.0, 0.0, 1.0]]),
                          dyn_pos=torch.tensor([[[9.0, 9.0, 1.0], [9.0, 9.0, 1.0]],
                                                [[3.0, 4.0, 1.0], [1.0, 0.0, 1.0]]]),
                          dyn_vel=torch.tensor([[[0.0, 0.0, 0.0]] * 2,
                                                [[1.0, 0.0, 0.0], [-0.5, 1.25, 0.0]]]))  # fmt: skip
    assert ft.describe_mover(ft.movers_of(env)) == "1.00 m, v (-0.5, 1.2)"
    assert ft.describe_mover(ft.movers_of(SimpleNamespace(world_idx=torch.tensor([0]),
                                                          n_dynamic=0))) == "-"  # fmt: skip
    rows = [{"movers": ft.movers_of(env)}, {"movers": ft.movers_of(env)}]
    assert ft.last_nearest(rows) == ["#1 1.00 m, v (-0.5, 1.2)"] * 2


@pytest.fixture(scope="module")
def tiny_hopper_run(tmp_path_factory) -> Path:
    """CSAC with clipped cost critics on SafetyHopperVelocity-v5, 300 steps (its recipe, the warm-up
    cut to 100 steps; the replay buffer kept in checkpoint.pt)."""
    run_dir = tmp_path_factory.mktemp("runs") / "hopper"
    main(["train", "--algo", "csac", "--env", "SafetyHopperVelocity-v5", "--total-steps", "300",
          "--csac.learning-starts", "100", "--csac.cost-critic-output", "clipped",
          "--save-buffer", "--torch-threads", "1", "--run-dir", str(run_dir)])  # fmt: skip
    return run_dir


def test_cost_critic_preactivation_slices_the_replay_buffer(tiny_hopper_run):
    pre = script("cost_critic_preactivation")
    res = pre.measure(tiny_hopper_run / "checkpoint.pt", [100, 250, 10_000])
    assert res["cost_critic_output"] == "clipped" and res["transitions"] == 300
    assert [(s["from"], s["to"]) for s in res["slices"]] == [(0, 100), (100, 250), (250, 300)]
    for s in res["slices"]:
        assert s["z_min"] <= s["z_mean"] <= s["z_max"] and 0.0 <= s["cost_rate"] <= 1.0
        # clipped read-out: Q_C = max(z, 0), so its mean lies between max(z_min, 0) and max(z_max, 0)
        assert max(s["z_min"], 0.0) - 1e-6 <= s["q_c_mean"] <= max(s["z_max"], 0.0) + 1e-6


def test_velocity_profile_counts_every_step_once_and_its_costly_ones(tiny_hopper_run, tmp_path,
                                                                     monkeypatch, capsys):  # fmt: skip
    out = tmp_path / "profile.json"
    monkeypatch.setattr(sys, "argv", ["velocity_profile.py", str(tiny_hopper_run), "--episodes",
                                      "2", "--seed", "101", "--json", str(out)])  # fmt: skip
    script("velocity_profile").main()
    (res,) = json.loads(out.read_text())["results"]
    assert "hopper" in capsys.readouterr().out
    assert res["threshold"] == 0.7402 and [e["seed"] for e in res["episodes"]] == [101, 102]
    assert res["steps"] == sum(e["length"] for e in res["episodes"])
    shares = ("share_still", "share_forward_within", "share_over", "share_backward")
    assert sum(res[k] for k in shares) == pytest.approx(1.0)  # the four bins partition the steps
    # a step costs 1 exactly when its speed is over the threshold: the two counts agree
    total_cost = sum(e["cost"] for e in res["episodes"])
    assert res["share_over"] * res["steps"] == pytest.approx(total_cost)


def test_velocity_profile_stochastic_draws_reproducibly(tiny_hopper_run):
    vp = script("velocity_profile")
    first = vp.profile(tiny_hopper_run, 1, 101, 0.1, stochastic=True)
    assert first["actions"] == "stochastic" and first["episodes"] == vp.profile(
        tiny_hopper_run, 1, 101, 0.1, stochastic=True)["episodes"]  # fmt: skip
    assert vp.profile(tiny_hopper_run, 1, 101, 0.1)["actions"] == "deterministic"


def test_velocity_profile_refuses_a_policy_of_another_task(tiny_run):
    with pytest.raises(SystemExit, match="not a velocity task"):
        script("velocity_profile").profile(tiny_run / "checkpoint.pt", 1, 101, 0.1)
