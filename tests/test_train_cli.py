"""``safenav train`` end to end in seconds: run directory, resume, refusal, any Gymnasium env;
``load_policy`` and its errors."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import PAPER_OBSERVATION
from safenav.algos.policy import load_policy, save_policy_only
from safenav.cli import main
from safenav.common.checkpoint import load_checkpoint, save_checkpoint
from safenav.envs.config import EnvConfig, make_config
from safenav.errors import SafenavError

FAST = ["--num-envs", "4", "--log-every", "100", "--eval-every", "200", "--eval-episodes", "2",
        "--checkpoint-every", "200", "--no-progress", "--no-tensorboard", "--torch-threads", "1",
        "--csac.learning-starts", "100", "--csac.batch-size", "32", "--csac.buffer-size", "2000",
        "--csac.updates-per-step", "0.25", "--csac.net.hidden", "32", "32"]  # fmt: skip
REQUIRED = ["global_step", "charts/episodic_return", "charts/episodic_cost", "charts/success_rate",
            "charts/collision_rate", "constraint/lambda", "constraint/d", "perf/sps", "losses/qr",
            "losses/qc", "losses/actor", "eval/success_rate"]  # fmt: skip


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def csac_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("runs") / "csac"
    # the paper's observation (the csac recipe adds the memory image and the pillar list)
    main(["train", *PAPER_OBSERVATION, "--env", "SafeNav-v1", "--preset", "easy", "--seed", "3",
          "--total-steps", "300", "--keep-policies", "--run-dir", str(run_dir), *FAST])  # fmt: skip
    return run_dir


def test_cli_smoke_run_directory(csac_run):
    assert {"config.json", "progress.csv", "checkpoint.pt", "events.jsonl"} <= {
        p.name for p in csac_run.iterdir()
    }
    rows = read_csv(csac_run / "progress.csv")
    assert set(REQUIRED) <= set(rows[0]) and len(rows) >= 3
    assert [int(r["global_step"]) for r in rows] == sorted(int(r["global_step"]) for r in rows)
    last = rows[-1]
    assert float(last["constraint/lambda"]) >= 0 and float(last["constraint/d"]) == pytest.approx(
        0.5
    )
    assert math.isfinite(float(last["losses/qc"]))
    config = json.loads((csac_run / "config.json").read_text())
    assert config["algo"] == "csac" and config["run"]["preset"] == "easy"
    # the shipped recipe's values are recorded; options given win
    from safenav.recipes import load_recipe

    recipe = load_recipe("csac-maxcost-crashloss")
    assert (
        config["recipe"]["name"] == "csac-maxcost-crashloss"
        and config["env_config"]["map_size"] == 20.0
    )
    assert config["csac"]["actor_lr"] == pytest.approx(recipe.section("csac")["actor_lr"])
    assert config["run"]["num_envs"] == 4 != recipe.section("run")["num_envs"]
    state = load_checkpoint(csac_run / "checkpoint.pt")
    assert state["global_step"] == 300 and state["updates"] > 0
    for key in ("agent", "optimizers", "curriculum", "density", "rng", "policy"):
        assert key in state
    events = [
        json.loads(line)["event"] for line in (csac_run / "events.jsonl").read_text().splitlines()
    ]
    assert events[0] == "start" and "eval" in events and events[-1] == "end"
    # best.pt: the policy of the best periodic evaluation, loadable like any policy checkpoint
    best = load_checkpoint(csac_run / "best.pt")
    assert best["policy_only"] and "agent" not in best and best["global_step"] % 200 == 0
    exported = load_checkpoint(
        save_policy_only(csac_run / "checkpoint.pt", csac_run.parent / "exported.pt")
    )
    assert set(best) == {*exported, "evaluation"}  # what `safenav export --policy-only` keeps
    assert best["evaluation"]["eval/success_rate"] == max(
        float(r["eval/success_rate"]) for r in rows if r["eval/success_rate"]
    )
    assert load_policy(csac_run / "best.pt").meta["algo"] == "csac"
    assert state["best"]["score"][0] == best["evaluation"]["eval/success_rate"]
    # --keep-policies: every evaluated policy, best.pt's among them
    kept = {int(p.stem.split("_")[1]): p for p in (csac_run / "policies").glob("step_*.pt")}
    assert sorted(kept) == [int(r["global_step"]) for r in rows if r["eval/success_rate"]]
    assert load_checkpoint(kept[best["global_step"]])["evaluation"] == best["evaluation"]


def test_existing_run_dir_is_refused_then_overwritten(csac_run, tmp_path, capsys):
    run_dir = tmp_path / "again"
    args = [
        "train",
        "--algo",
        "sac",
        "--preset",
        "easy",
        "--total-steps",
        "120",
        "--run-dir",
        str(run_dir),
        *FAST,
    ]
    main(args)
    with pytest.raises(SystemExit) as err:
        main(args)
    assert err.value.code == 2 and "already holds a run" in capsys.readouterr().err
    main([*args, "--overwrite"])
    assert json.loads((run_dir / "config.json").read_text())["algo"] == "sac"


def test_resume_continues_the_run(tmp_path):
    run_dir = tmp_path / "resume"
    base = ["train", "--algo", "csac", "--preset", "easy", "--run-dir", str(run_dir), *FAST]
    main([*base, "--total-steps", "200"])
    before = load_checkpoint(run_dir / "checkpoint.pt")
    main(
        [
            "train",
            "--algo",
            "csac",
            "--resume",
            str(run_dir),
            "--total-steps",
            "400",
            "--no-progress",
        ]
    )
    after = load_checkpoint(run_dir / "checkpoint.pt")
    assert before["global_step"] == 200 and after["global_step"] == 400
    assert after["updates"] > before["updates"]
    assert (
        json.loads((run_dir / "config.json").read_text())["run"]["total_steps"] == 200
    )  # as started
    steps = [int(r["global_step"]) for r in read_csv(run_dir / "progress.csv")]
    assert steps == sorted(set(steps)) and steps[-1] == 400
    events = [
        json.loads(line)["event"] for line in (run_dir / "events.jsonl").read_text().splitlines()
    ]
    assert "resume" in events
    with pytest.raises(SystemExit):  # resuming as another algorithm
        main(["train", "--algo", "sac", "--resume", str(run_dir), "--no-progress"])


def test_resume_refuses_an_algorithm_option_it_would_ignore(tmp_path, capsys):
    """A resumed run keeps its config.json: an option with another value is refused (exit 2,
    nothing written), the same value passes (reproduce resumes with the trial's options)."""
    run_dir = tmp_path / "resume"
    base = ["train", "--algo", "csac", "--preset", "easy", "--run-dir", str(run_dir), *FAST]
    main([*base, "--total-steps", "200"])
    resume = ["train", "--algo", "csac", "--resume", str(run_dir), "--no-progress",
              "--total-steps", "300"]  # fmt: skip
    before = (run_dir / "progress.csv").read_text()
    for option in (["--csac.cost-critic-output", "softplus"], ["--csac.net.hidden", "8", "8"],
                   ["--csac.curriculum.no-enabled"]):  # fmt: skip
        with pytest.raises(SystemExit) as err:
            main([*resume, *option])
        assert err.value.code == 2
        message = capsys.readouterr().err
        assert option[0].replace("no-", "") in message and "keeps the configuration" in message
    assert (run_dir / "progress.csv").read_text() == before
    main([*resume, "--csac.cost-critic-output", "linear"])  # the run's own value
    assert load_checkpoint(run_dir / "checkpoint.pt")["global_step"] == 300


def test_any_gymnasium_box_env_trains(tmp_path):
    run_dir = tmp_path / "pendulum"
    main(
        [
            "train",
            "--algo",
            "sac",
            "--env",
            "Pendulum-v1",
            "--total-steps",
            "300",
            "--run-dir",
            str(run_dir),
            *FAST,
        ]
    )
    rows = read_csv(run_dir / "progress.csv")
    assert (
        float(rows[-1]["perf/updates"]) > 0 and rows[-1]["charts/success_rate"] == ""
    )  # Pendulum has none
    policy = load_policy(run_dir)
    action = policy(torch.zeros(5, 3))
    assert (
        action.shape == (5, 1) and policy.meta["env_config"] is None and policy.env_config() is None
    )
    with pytest.raises(SystemExit):  # --preset is SafeNav's
        main(["train", "--algo", "sac", "--env", "Pendulum-v1", "--preset", "easy", "--total-steps", "100",
              "--run-dir", str(tmp_path / "bad"), *FAST])  # fmt: skip


def test_load_policy(csac_run):
    policy = load_policy(csac_run / "checkpoint.pt")
    assert policy.meta["algo"] == "csac" and policy.meta["env_id"] == "SafeNav-v1"
    cfg = policy.env_config()
    assert isinstance(cfg, EnvConfig) and cfg.map_size == 20.0 and cfg.density == 1.0
    g = torch.Generator().manual_seed(0)
    obs = {"state": torch.rand(7, 8, generator=g), "lidar": torch.rand(7, 4, 36, generator=g),
           "dynamic": torch.rand(7, 5, 10, generator=g)}  # fmt: skip
    a = policy(obs)
    assert (
        a.shape == (7, 3) and a.abs().max() <= 1.0 and torch.equal(a, policy(obs))
    )  # deterministic
    one = policy({k: v[0].numpy() for k, v in obs.items()})  # unbatched NumPy
    torch.testing.assert_close(one, a[0])
    # Policy.actor: positional state, lidar, dynamic; traceable
    torch.testing.assert_close(policy.actor(obs["state"], obs["lidar"], obs["dynamic"]), a)
    traced = torch.jit.trace(policy.actor, (obs["state"], obs["lidar"], obs["dynamic"]))
    torch.testing.assert_close(traced(obs["state"], obs["lidar"], obs["dynamic"]), a)
    with pytest.raises(SafenavError, match="lidar"):
        policy({**obs, "lidar": torch.rand(7, 4, 30)})
    with pytest.raises(SafenavError, match="lacks"):
        policy({"state": obs["state"]})


def test_policy_sample_draws_the_training_gaussian(csac_run):
    from safenav.algos.policy import Policy
    from safenav.common.normalize import NormalizedActor, ObsNormalizer

    policy = load_policy(csac_run / "checkpoint.pt")
    g = torch.Generator().manual_seed(1)
    obs = {"state": torch.rand(7, 8, generator=g), "lidar": torch.rand(7, 4, 36, generator=g),
           "dynamic": torch.rand(7, 5, 10, generator=g)}  # fmt: skip
    a = policy.sample(obs, torch.Generator().manual_seed(3))
    assert a.shape == (7, 3) and a.abs().max() <= 1.0 and not torch.equal(a, policy(obs))
    torch.testing.assert_close(a, policy.sample(obs, torch.Generator().manual_seed(3)))
    # the draw is tanh(mean + std * eps), eps the generator's standard normals (SAC's sampling)
    det = policy.actor
    mean, log_std = det.actor(det.encoder(obs))
    eps = torch.randn(mean.shape, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(a, torch.tanh(mean + log_std.exp() * eps))
    one = policy.sample({k: v[0].numpy() for k, v in obs.items()}, torch.Generator().manual_seed(3))
    assert one.shape == (3,)
    # behind --normalize-obs statistics: the same draw as the bare actor on normalised inputs
    norm = ObsNormalizer(policy.obs_shapes)
    norm.update({k: 3.0 * v + 1.0 for k, v in obs.items()})
    wrapped = Policy(NormalizedActor(norm, policy.actor), policy.meta)
    torch.testing.assert_close(wrapped.sample(obs, torch.Generator().manual_seed(3)),
                               policy.sample(norm(obs), torch.Generator().manual_seed(3)))  # fmt: skip
    with pytest.raises(SafenavError, match="PPO policy"):
        Policy(policy.actor, {**policy.meta, "policy_head": "beta"}).sample(obs)


def test_load_policy_errors(csac_run, tmp_path):
    with pytest.raises(SafenavError, match="not found"):
        load_policy(tmp_path / "missing.pt")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint at all")
    with pytest.raises(SafenavError, match="corrupt"):
        load_policy(garbage)
    state = load_checkpoint(csac_run / "checkpoint.pt")
    other = tmp_path / "other.pt"
    torch.save({"weights": 1}, other)
    with pytest.raises(SafenavError, match="not a safenav"):
        load_policy(other)
    old = tmp_path / "old.pt"
    torch.save({**state, "format_version": 0}, old)
    with pytest.raises(SafenavError, match="format version"):
        load_policy(old)
    bad_meta = dict(
        state["policy"]["meta"], obs_shapes={"state": [8], "lidar": [4, 30], "dynamic": [5, 10]}
    )
    inconsistent = tmp_path / "inconsistent.pt"
    save_checkpoint(inconsistent, {**state, "policy": {**state["policy"], "meta": bad_meta}})
    with pytest.raises(SafenavError, match="does not match"):
        load_policy(inconsistent)
    wrong_net = dict(
        state["policy"]["meta"], net={**state["policy"]["meta"]["net"], "hidden": [64, 64]}
    )
    mismatch = tmp_path / "mismatch.pt"
    save_checkpoint(mismatch, {**state, "policy": {**state["policy"], "meta": wrong_net}})
    with pytest.raises(SafenavError, match="do not fit"):
        load_policy(mismatch)
    assert np.isfinite(load_policy(csac_run).actor.actor.head.weight.detach().numpy()).all()


def test_map_refresh_gives_each_env_a_full_episode(tmp_path, capsys):
    """--map-refresh-every counts the steps of all envs, and a redraw ends every episode: with
    many envs it is raised to num_envs x the time limit, so an episode can end on its own (at
    1024 envs the recipes' 200 000 left 195 steps per env for 600-step episodes), and said."""
    from safenav.training.trainer import map_refresh_interval

    assert map_refresh_interval(200_000, 256, 600) == 200_000  # the recipes: unchanged
    assert map_refresh_interval(200_000, 1024, 600) == 614_400
    assert map_refresh_interval(0, 1024, 600) == 0  # never redraw stays never
    run_dir = tmp_path / "refresh"
    main(["train", "--algo", "csac", "--preset", "easy", "--run-dir", str(run_dir), *FAST,
          "--total-steps", "200", "--map-refresh-every", "100"])  # fmt: skip
    horizon = make_config("easy").max_episode_steps
    num_envs = json.loads((run_dir / "config.json").read_text())["run"]["num_envs"]
    out = capsys.readouterr().out
    assert f"maps redrawn every {num_envs * horizon} env steps instead" in out
    start = json.loads((run_dir / "events.jsonl").read_text().splitlines()[0])
    assert start["event"] == "start" and start["map_refresh_every"] == num_envs * horizon
