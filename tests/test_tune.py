"""``safenav tune``: search spaces, the configuration sequence, the recipe it writes, scoring on
validation maps only, and a whole (tiny) tuning through the CLI that a rerun resumes."""

from __future__ import annotations

import json

import pytest

from conftest import run_cli
from safenav.algos.config import CSACConfig
from safenav.cli import main
from safenav.errors import SafenavError
from safenav.experiments.selection import RESERVED_SEEDS, VALIDATION_SEEDS
from safenav.experiments.tune import best_recipe, load_space, option_args, score_run, tune
from safenav.recipes import apply, load_recipe

SHIPPED = ("sac", "sac-lag", "csac", "ppo", "ppo-lag")


@pytest.mark.parametrize("name", SHIPPED)
def test_each_shipped_space_loads_and_its_options_are_real(name):
    space = load_space(name)
    # csac's space tuned the recipe that was csac until 2026-12-05
    assert space.recipe == {"csac": "csac-maxcost-crashloss"}.get(name, name) and space.params
    recipe = load_recipe(space.recipe)
    assert space.algo in recipe.algos
    for config in space.configurations(6)[1:]:  # every value applies to its config class
        csac = {k.split(".", 1)[1]: v for k, v in config.items() if k.startswith("csac.")}
        ppo = {k.split(".", 1)[1]: v for k, v in config.items() if k.startswith("ppo.")}
        if csac:
            apply(CSACConfig(), csac, "csac.")
        if ppo:
            from safenav.algos.ppo_config import PPOConfig

            apply(PPOConfig(), ppo, "ppo.")


def test_configurations_start_with_the_recipe_and_are_a_prefix_sequence_inside_the_space():
    space = load_space("sac-lag")
    eight, three = space.configurations(8), space.configurations(3)
    assert eight[0] == {} and eight[:3] == three  # trial 0 unchanged; a longer run adds trials
    assert len({json.dumps(c, sort_keys=True) for c in eight}) == 8
    for config in eight[1:]:
        for p in space.params:
            v = config[p.name]
            assert v in p.choices if p.choices else p.low <= v <= p.high, (p.name, v)
    # the same scramble seed: shared options take the same values in every algorithm's tuning
    sac = load_space("sac").configurations(8)
    assert all(sac[i]["csac.actor_lr"] == eight[i]["csac.actor_lr"] for i in range(1, 8))
    assert load_space("sac", seed=1).configurations(2)[1] != sac[1]


def test_bad_spaces_are_refused_with_the_reason(tmp_path):
    cases = {
        "no_recipe.toml": 'algo = "sac"\n',
        "bad_toml.toml": "algo = \n",
        "bad_name.toml": 'algo = "sac"\nrecipe = "sac"\n[params]\nactor_lr = { low = 1, high = 2 }\n',
        "bad_range.toml": 'algo = "sac"\nrecipe = "sac"\n[params]\n"csac.gamma" = { low = 2, high = 1 }\n',
        "bad_log.toml": 'algo = "sac"\nrecipe = "sac"\n[params]\n"csac.actor_lr" = { low = 0, high = 1, log = true }\n',
        "bad_key.toml": 'algo = "sac"\nrecipe = "sac"\n[params]\n"csac.gamma" = { choices = [0.9], step = 1 }\n',
        "empty_choices.toml": 'algo = "sac"\nrecipe = "sac"\n[params]\n"csac.gamma" = { choices = [] }\n',
    }
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(SafenavError, match="--space"):
            load_space(str(tmp_path / name))
    with pytest.raises(SafenavError, match="unknown; shipped: csac"):
        load_space("nope")


def test_option_args_and_the_best_recipe_round_trip(tmp_path):
    params = {"csac.actor_lr": 0.0007, "csac.net.hidden": (64, 64), "run.shield": True}
    assert option_args(params) == ["--csac.actor-lr", "0.0007", "--csac.net.hidden", "64", "64",
                                   "--shield"]  # fmt: skip
    assert option_args({"csac.constrained": False}) == ["--csac.no-constrained"]
    space = load_space("sac")
    best = {"index": 3, "params": {"csac.actor_lr": 0.0007, "csac.gamma": 0.98}, "seed": 101,
            "trials_planned": 8, "total_steps": 1000, "date": "2026-11-29",
            "validation": {"success_rate": 0.5, "collision_rate": 0.25, "episodes": 8}}  # fmt: skip
    path = tmp_path / "best.toml"
    path.write_text(best_recipe(space, best))
    recipe = load_recipe(str(path))
    assert recipe.algo == "sac" and recipe.section("csac")["actor_lr"] == 0.0007
    assert recipe.section("csac")["gamma"] == 0.98
    assert recipe.section("csac")["updates_per_step"] == 0.03125  # the base recipe's values stay
    assert "trial 3 of 8" in recipe.header


TINY = ("--num-envs 4 --log-every 100 --eval-every 200 --eval-episodes 2 --checkpoint-every 200 "
        "--csac.learning-starts 100 --csac.batch-size 32 --csac.buffer-size 2000 "
        "--csac.net.hidden 32 32")  # fmt: skip


@pytest.mark.long
def test_scoring_flies_validation_maps_only(tmp_path, world_seeds):
    run_dir = tmp_path / "run"
    main(["train", "--algo", "sac", "--preset", "easy", "--total-steps", "600", "--keep-policies",
          "--run-dir", str(run_dir), "--no-progress", "--no-tensorboard", "--torch-threads", "1",
          *TINY.split()])  # fmt: skip
    world_seeds.clear()
    score = score_run(run_dir, episodes=8)
    assert set(world_seeds) >= set(VALIDATION_SEEDS), "the recorder saw no validation map"
    assert not set(world_seeds) & RESERVED_SEEDS
    assert score["episodes"] == 8 and [m["env_seed"] for m in score["per_map"]] == list(
        VALIDATION_SEEDS
    )
    assert 0 <= score["success_rate"] <= 1 and 0 <= score["collision_rate"] <= 1
    assert (run_dir / "policy.pt").exists() and (run_dir / "selection.json").exists()


@pytest.mark.long
def test_a_tiny_tuning_writes_trials_report_and_recipe_and_a_rerun_skips(tmp_path, capsys):
    out = tmp_path / "tune"
    args = ["tune", "--space", "sac", "--trials", "2", "--total-steps", "600", "--preset", "easy",
            "--episodes", "8", "--out", str(out), "--no-progress", "--torch-threads", "1",
            f"--train-args={TINY}"]  # fmt: skip
    main(args)
    trials = [json.loads(p.read_text()) for p in sorted((out / "trials").glob("t*.json"))]
    assert [t["index"] for t in trials] == [0, 1] and trials[0]["params"] == {}
    assert trials[1]["params"] == load_space("sac").configurations(2)[1]
    assert (
        "--csac.actor-lr" in trials[1]["command"] and "--eval-every 250000" in trials[1]["command"]
    )
    config = json.loads((out / "runs" / "t001" / "config.json").read_text())
    assert config["csac"]["actor_lr"] == trials[1]["params"]["csac.actor_lr"]
    assert config["recipe"]["name"] == "sac" and config["run"]["seed"] == 101
    assert (out / "results.md").read_text().count("\n| ") == 3  # header + 2 trials
    assert load_recipe(str(out / "best.toml")).algo == "sac"
    best = (out / "best.toml").read_text()  # it trains as the trials did: preset, --train-args
    assert 'preset = "easy"' in best and "num_envs = 4" in best and "hidden = [32, 32]" in best
    capsys.readouterr()
    main(args)  # nothing left to run
    assert "2 already done (skipped), 0 to run" in capsys.readouterr().err
    # a trial stopped after training, before its file: the rerun resumes its run (with its
    # --algo: sac, not train's default csac) and scores it
    (out / "trials" / "t001.json").unlink()
    main(args)
    assert "1 already done (skipped), 1 to run" in capsys.readouterr().err
    again = json.loads((out / "trials" / "t001.json").read_text())
    assert again["params"] == trials[1]["params"]
    assert '"resume"' in (out / "runs" / "t001" / "events.jsonl").read_text()
    with pytest.raises(SafenavError, match="another space"):
        tune(load_space("sac"), out, trials=2, total_steps=600, seed=7, progress=False)
    with pytest.raises(SafenavError, match="another space"):  # another Sobol scramble
        tune(load_space("sac", seed=3), out, trials=2, total_steps=600, progress=False)


@pytest.mark.parametrize(
    ("train_args", "message"),
    [("--select", "--select is tune's to set"), ("--seed 3", "--seed is tune's"),
     ("--csac.actor-lr 0.1", "--csac.actor_lr is tune's"), ("--nope", "unrecognized")],
)  # fmt: skip
def test_train_args_may_not_fly_the_test_maps_or_override_the_search(
    tmp_path, capsys, train_args, message
):
    code, _, err = run_cli(capsys, ["tune", "--space", "sac", "--out", str(tmp_path / "t"),
                                    f"--train-args={train_args}"])  # fmt: skip
    assert code == 2 and message in err, err
    assert not (tmp_path / "t").exists()


def test_a_space_of_the_other_family_or_without_options_is_refused(tmp_path, capsys):
    (tmp_path / "mixed.toml").write_text('algo = "sac"\nrecipe = "sac"\n[params]\n'
                                         '"ppo.lr" = { low = 1e-4, high = 1e-3 }\n')  # fmt: skip
    with pytest.raises(SafenavError, match="do nothing for --algo sac"):
        load_space(str(tmp_path / "mixed.toml"))
    (tmp_path / "none.toml").write_text('algo = "sac"\nrecipe = "sac"\n')
    code, _, err = run_cli(
        capsys, ["tune", "--space", str(tmp_path / "none.toml"), "--trials", "2"]
    )
    assert code == 2 and "searches no option" in err
    # run.* options reach train without a prefix
    assert option_args({"run.num_envs": 8}) == ["--num-envs", "8"]


def test_the_overall_bar_counts_each_finished_run_once(tmp_path):
    """The queue's overall bar ends at its total: a run that finishes is counted in the finished
    steps only, not also among the live ones (it read 5000000/4000000 after four trials)."""
    import io
    import sys

    from rich.console import Console

    from safenav.common.child_runs import ChildRun, run_queue

    runs = [ChildRun(name=f"r{i}", steps=10, command=lambda: [sys.executable, "-c", "pass"],
                     steps_done=lambda: 10, finish=lambda s: "done", log=tmp_path / f"r{i}.log")
            for i in range(3)]  # fmt: skip
    out = io.StringIO()
    assert run_queue(runs, 2, lambda line: None, True, Console(file=out, width=120)) == []
    final = [line for line in out.getvalue().splitlines() if "all trials" in line][-1]
    assert "30/30" in final, final
