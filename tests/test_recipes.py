"""Recipes: the shipped TOML files load, resolve their bases, and build valid configs; a user's
file by path works; mistakes are clear errors."""

from __future__ import annotations

import pytest

from conftest import PAPER_OBSERVATION
from safenav.algos.config import CSACConfig
from safenav.algos.ppo_config import PPOConfig
from safenav.common.config import RunConfig
from safenav.errors import SafenavError
from safenav.recipes import apply, available, default_recipe, load_recipe

REQUIRED = {"csac-paper", "csac", "sac", "sac-lag", "ppo", "ppo-lag"}


def test_the_required_recipes_ship_and_build_valid_configs():
    assert set(available()) >= REQUIRED
    for name in safenav_recipes():
        recipe = load_recipe(name)
        assert recipe.algo in ("csac", "sac", "ppo", "ppo_lag", "sac_lag"), name
        run = apply(RunConfig(), recipe.section("run"))
        apply(CSACConfig(), recipe.section("csac"))
        apply(PPOConfig(), recipe.section("ppo"))
        assert run.total_steps >= 1_000_000, name
        # every header says what it measured (or that it has not been measured yet)
        assert "Measured on SafeNav-v1" in _text(name), name


def safenav_recipes() -> list[str]:
    """The SafeNav recipes (the task-family ones: tests/test_gymnasium.py)."""
    return [n for n in available() if not n.startswith(("gym-", "classic-", "box2d-", "mujoco-"))]


def _text(name: str) -> str:
    from importlib import resources

    return (resources.files("safenav.recipes") / f"{name}.toml").read_text()


def test_csac_paper_is_the_papers_method_and_variants_say_how_they_depart():
    paper = apply(CSACConfig(), load_recipe("csac-paper").section("csac"))
    assert paper.cost_target == "mean" and paper.constrained
    assert (paper.actor_lr, paper.reward_critic_lr, paper.cost_critic_lr) == (5e-5, 5e-4, 1e-3)
    assert (paper.alpha_lr, paper.lambda_lr, paper.gamma) == (1e-5, 1e-5, 0.99)
    assert apply(RunConfig(), load_recipe("csac-paper").section("run")).num_envs == 16
    for name in available():
        cfg = apply(CSACConfig(), load_recipe(name).section("csac"))
        if load_recipe(name).algo == "csac" and cfg.cost_target != "mean":
            # a departure from Eq. 6 is named in the recipe's name or listed as a departure
            assert "maxcost" in name or "csac-maxcost" in _text(name), name


@pytest.mark.parametrize("name", ["csac", "sac", "ppo", "sac-lag", "ppo-lag"])
def test_the_tuned_recipes_are_what_safenav_tune_chose(name):
    """``NAME-tuned`` ships the values of ``results/tuning/NAME/best.toml`` (what ``safenav tune``
    wrote), so that ``safenav reproduce`` finds them from any working directory."""
    from pathlib import Path

    chosen = Path(__file__).parents[1] / "results" / "tuning" / name / "best.toml"
    shipped, tuned = load_recipe(f"{name}-tuned"), load_recipe(str(chosen))
    assert shipped.algo == tuned.algo == name.replace("-", "_")
    for section in ("run", "csac", "ppo"):
        assert shipped.section(section) == tuned.section(section), section


def test_bases_resolve_and_later_values_win():
    csac = load_recipe("csac")
    assert csac.section("csac")["cost_target"] == "max"  # from csac-maxcost
    assert csac.section("run")["keep_policies"] is True  # from csac-paper, two levels down
    assert csac.section("run")["num_envs"] == 256  # csac-maxcost overrides csac-paper's 16
    assert load_recipe("ppo-lag").algo == "ppo_lag"


def test_default_recipes_per_algorithm_on_safenav_only():
    assert default_recipe("csac", "SafeNav-v1") == "csac"
    assert default_recipe("sac_lag", "SafeNav-v1") == "sac-lag"
    assert default_recipe("sac", "Pendulum-v1") == "classic-sac"  # its task family's


def test_a_users_recipe_file(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('[recipe]\nalgo = "csac"\nbase = "csac-paper"\n[csac]\nactor_lr = 1e-4\n'
                    "[csac.curriculum]\nd_min = 0.02\n")  # fmt: skip
    recipe = load_recipe(str(path))
    assert recipe.name == "mine" and recipe.source == str(path)
    cfg = apply(CSACConfig(), recipe.section("csac"))
    assert cfg.actor_lr == 1e-4 and cfg.curriculum.d_min == 0.02 and cfg.cost_target == "mean"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[run]\nnum_envs = 2\n", "needs a \\[recipe\\] table"),
        ('[recipe]\nalgo = "csac"\n[sac]\nx = 1\n', "unknown section"),
        ('[recipe]\nalgo = "csac"\nbase = "nope"\n', "unknown recipe"),
        ('[recipe]\nalgo = "csac"\n[run\n', "not valid TOML"),
    ],
)
def test_bad_recipe_files_are_clear_errors(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SafenavError, match=message):
        load_recipe(str(path))


def test_bad_fields_and_values_and_cycles(tmp_path):
    with pytest.raises(SafenavError, match="unknown field.*run.nope|nope"):
        apply(RunConfig(), {"nope": 1})
    with pytest.raises(SafenavError, match="density.ramp_fraction|invalid value"):
        apply(RunConfig(), {"density": {"ramp_fraction": -1.0}})
    with pytest.raises(SafenavError, match="invalid value"):
        apply(CSACConfig(), {"gamma": 2.0})
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.write_text(f'[recipe]\nalgo = "csac"\nbase = "{b}"\n')
    b.write_text(f'[recipe]\nalgo = "csac"\nbase = "{a}"\n')
    with pytest.raises(SafenavError, match="cycle"):
        load_recipe(str(a))
    with pytest.raises(SafenavError, match="unknown recipe"):
        load_recipe("no-such-recipe")


# ---------------------------------------------------------------- safenav train --config


def test_train_config_flags_override_the_recipe():
    from safenav.commands.train import parse_train_args

    paper = parse_train_args(["--config", "csac-paper"])
    assert paper["algo"] == "csac" and paper["csac"].cost_target == "mean"
    assert paper["run"].num_envs == 16 and paper["run"].total_steps == 5_000_000
    mine = parse_train_args(["--config", "csac-paper", "--num-envs", "8", "--csac.actor-lr=1e-3",
                             "--density.ramp-fraction", "0.3"])  # fmt: skip
    assert mine["run"].num_envs == 8 and mine["csac"].actor_lr == 1e-3
    assert mine["run"].density.ramp_fraction == 0.3 and mine["csac"].cost_target == "mean"


def test_train_default_recipe_per_algo_and_none():
    from safenav.commands.train import parse_train_args
    from safenav.common.config import RunConfig

    csac = parse_train_args(["--algo", "csac"])
    assert csac["csac"].cost_target == load_recipe("csac").section("csac")["cost_target"]
    ppo = parse_train_args(["--algo", "ppo_lag"])  # ppo-lag.toml, based on ppo.toml
    assert ppo["run"].num_envs == load_recipe("ppo").section("run")["num_envs"]
    builtin = parse_train_args(["--algo", "csac", "--config", "none"])
    assert builtin["run"] == RunConfig() and builtin["csac"].cost_target == "mean"
    gym = parse_train_args(["--algo", "sac", "--env", "Pendulum-v1"])  # its family's, not SafeNav's
    assert gym["run"].num_envs == 1 != load_recipe("csac").section("run")["num_envs"]


def test_train_config_from_a_users_file(tmp_path):
    from safenav.commands.train import parse_train_args

    path = tmp_path / "mine.toml"
    path.write_text('[recipe]\nalgo = "sac"\nbase = "csac-paper"\n[csac]\nbatch_size = 64\n')
    parsed = parse_train_args(["--config", str(path)])
    assert parsed["algo"] == "sac" and parsed["csac"].batch_size == 64
    assert parsed["run"].total_steps == 5_000_000  # from its base


def test_train_config_refusals(tmp_path):
    from safenav.commands.train import parse_train_args

    with pytest.raises(SafenavError, match="trains --algo ppo, not --algo csac"):
        parse_train_args(["--config", "ppo", "--algo", "csac"])
    with pytest.raises(SafenavError, match="unknown recipe"):
        parse_train_args(["--config", "csac-nonesuch"])
    bad = tmp_path / "bad.toml"
    bad.write_text('[recipe]\nalgo = "csac"\n[csac]\nactor_lr = -1.0\n')
    with pytest.raises(SafenavError, match="actor"):
        parse_train_args(["--config", str(bad)])


def test_train_records_the_recipe_in_config_json(tmp_path, capsys):
    import json

    from safenav.cli import main

    run_dir = tmp_path / "run"
    main(["train", "--config", "csac-paper", "--preset", "easy", "--total-steps", "64",
          "--num-envs", "4", "--eval-every", "0", "--no-progress", "--no-tensorboard",
          "--csac.learning-starts", "32", "--csac.batch-size", "16", "--run-dir", str(run_dir)])  # fmt: skip
    config = json.loads((run_dir / "config.json").read_text())
    assert config["recipe"]["name"] == "csac-paper" and config["csac"]["cost_target"] == "mean"
    assert "recipe csac-paper" in capsys.readouterr().out


def test_env_kwargs_from_the_command_line_and_a_recipe(tmp_path, capsys):
    import json

    from safenav.cli import main
    from safenav.commands.train import parse_train_args

    crash = list(PAPER_OBSERVATION)
    parsed = parse_train_args([*crash, "--env-kwargs", "reward_collision", "-100"])
    assert parsed["run"].env_kwargs == {"reward_collision": -100.0}
    # The command line's env kwargs add to the recipe's (csac-maxcost-crashloss:
    # reward_collision = -100), key by key, and win where both name one.
    added = parse_train_args([*crash, "--env-kwargs", "lidar_memory", "10"])
    assert added["run"].env_kwargs == {"reward_collision": -100, "lidar_memory": 10}
    mine = parse_train_args([*crash, "--env-kwargs", "reward_collision", "-50"])
    assert mine["run"].env_kwargs == {"reward_collision": -50.0}
    # --algo csac takes the csac recipe's kwargs (its bases' merged), the command line's on top
    default = parse_train_args(["--algo", "csac", "--env-kwargs", "reward_collision", "-50"])
    assert default["run"].env_kwargs["reward_collision"] == -50.0
    assert default["run"].env_kwargs["static_tracked"] == 10
    path = tmp_path / "mine.toml"
    path.write_text(
        '[recipe]\nalgo = "sac"\nbase = "sac"\n[run.env_kwargs]\nreward_collision = -50.0\n'
    )
    assert parse_train_args(["--config", str(path)])["run"].env_kwargs == {
        "reward_collision": -50.0
    }
    with pytest.raises(ValueError, match="density is the curriculum's"):
        RunConfig(env_kwargs={"density": 0.5})
    common = ["--preset", "easy", "--num-envs", "4", "--eval-every", "0", "--no-progress",
              "--no-tensorboard", "--csac.learning-starts", "32", "--csac.batch-size", "16"]  # fmt: skip
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--algo", "sac", "--total-steps", "64", *common, "--env-kwargs", "nonesuch",
              "1", "--run-dir", str(tmp_path / "bad")])  # fmt: skip
    assert exit_.value.code == 2
    assert "--env-kwargs: unknown EnvConfig field(s) ['nonesuch']" in capsys.readouterr().err
    run_dir = tmp_path / "run"
    main(["train", "--algo", "sac", "--total-steps", "64", *common, "--env-kwargs",
          "reward_collision", "-100", "--run-dir", str(run_dir)])  # fmt: skip
    config = json.loads((run_dir / "config.json").read_text())
    assert config["run"]["env_kwargs"] == {"reward_collision": -100.0}
    assert config["env_config"]["reward_collision"] == -100.0


def test_the_comparison_recipes_share_one_env_reward():
    """csac-maxcost-crashloss, sac, sac-lag, ppo and ppo-lag train on the same env reward (issue 21
    compares them), and so does csac (with its observation's kwargs beside it); csac-paper keeps
    the env's own."""
    from safenav.commands.train import parse_train_args

    kwargs = {name: parse_train_args(["--config", name])["run"].env_kwargs
              for name in ("csac-maxcost-crashloss", "sac", "sac-lag", "ppo", "ppo-lag")}  # fmt: skip
    assert all(k == {"reward_collision": -100} for k in kwargs.values()), kwargs
    assert parse_train_args(["--config", "csac"])["run"].env_kwargs["reward_collision"] == -100
    assert parse_train_args(["--config", "csac-paper"])["run"].env_kwargs == {}
    mine = parse_train_args(["--algo", "csac", "--env-kwargs", "reward_collision", "0"])
    assert mine["run"].env_kwargs["reward_collision"] == 0
