"""``--csac.planner-share``: the planner's flights (``training.planner_flights``), kept apart from
the replay buffer and mixed into each minibatch at their share (``CSACLearner.sample``)."""

from __future__ import annotations

import csv
import dataclasses
import json

import pytest
import torch

from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSACLearner
from safenav.cli import main
from safenav.common.buffer import Batch
from safenav.common.config import RunConfig
from safenav.envs.planner import PLANNER_B, PLANNER_PILLARS, PLANNERS, AutoresetPlanner
from safenav.envs.vector import TorchVecEnv, make_vec_env
from safenav.experiments.selection import RESERVED_SEEDS, VALIDATION_SEEDS
from safenav.training.planner_flights import fly_planner

EASY = RunConfig(env="SafeNav-v1", preset="easy", seed=3)
PAPER = RunConfig(env="SafeNav-v1", preset="paper", seed=3)


@pytest.mark.long
def test_flights_are_the_planners_and_leave_the_rng_alone():
    torch.set_num_threads(1)
    torch.manual_seed(0)
    expected = torch.rand(3)
    torch.manual_seed(0)
    flights, stats = fly_planner(EASY, {}, 600, 4, "cpu", progress=False)
    assert torch.equal(torch.rand(3), expected)  # a run draws as it would without the flights
    assert len(flights) == 150 and stats["transitions"] == 600
    assert stats["episodes"] >= 1 and 0.0 <= stats["success_rate"] <= 1.0
    batch, truncated, valid = flights[0]
    assert batch.actions.shape == (4, 3) and batch.actions.abs().max() <= 1.0
    assert truncated.shape == valid.shape == (4,)
    # each step's observations are its own (the env does not write over stored ones)
    assert not torch.equal(flights[0][0].obs["state"], flights[10][0].obs["state"])
    go_on = ~(flights[10][0].terminated.bool() | flights[10][1])  # a step's next is the next's own
    assert torch.equal(flights[10][0].next_obs["state"][go_on], flights[11][0].obs["state"][go_on])
    # the planner flew them: replaying its actions from the same maps gives the same ones
    env = TorchVecEnv(make_vec_env("SafeNav-v1", 4, "cpu", "easy"), "cpu")
    nav, planner = env.envs.unwrapped, AutoresetPlanner(PLANNER_B)
    obs = env.reset(seed=EASY.planner_env_seed())
    for t in range(3):
        action = planner(obs, nav)
        assert torch.allclose(action, flights[t][0].actions)
        obs = env.step(action).next_obs


def test_the_pillar_planner_flies_them_with_the_pillar_list():
    """``--csac.planner-view pillars``: the flights are the pillar-geometry planner's (kept in the
    band when asked), with the observation's ``static`` entry stored like the others."""
    assert PLANNERS == {"range": PLANNER_B, "pillars": PLANNER_PILLARS}
    torch.set_num_threads(1)
    flights, stats = fly_planner(PAPER, {"static_tracked": 4}, 12, 4, "cpu", progress=False,
                                 keep_band=True, view="pillars")  # fmt: skip
    assert len(flights) == 3 and stats["transitions"] == 12
    assert flights[0][0].obs["static"].shape == (4, 4, 7)
    env = TorchVecEnv(make_vec_env("SafeNav-v1", 4, "cpu", "paper", static_tracked=4), "cpu")
    nav = env.envs.unwrapped
    planner = AutoresetPlanner(dataclasses.replace(PLANNER_PILLARS, keep_band=True))
    other = AutoresetPlanner(dataclasses.replace(PLANNER_B, keep_band=True))
    obs = env.reset(seed=PAPER.planner_env_seed())
    differs = False
    for t in range(3):
        action = planner(obs, nav)
        assert torch.allclose(action, flights[t][0].actions)
        differs |= not torch.allclose(other(obs, nav), action)
        obs = env.step(action).next_obs
    assert differs  # the view chose the planner: planner B would have flown otherwise


def test_planner_maps_are_none_of_the_runs_or_the_reports():
    for seed in range(1, 21):
        run = RunConfig(seed=seed)
        planner = set(range(run.planner_env_seed(), run.planner_env_seed() + 256))
        training = {run.train_env_seed(r) + w for r in range(200) for w in range(256)}
        assert not planner & training
        assert not planner & (set(RESERVED_SEEDS) | set(VALIDATION_SEEDS))


def _learner(**csac) -> tuple[CSACLearner, TorchVecEnv]:
    env = TorchVecEnv(make_vec_env("SafeNav-v1", 2, "cpu", "easy"), "cpu")
    cfg = CSACConfig(batch_size=32, buffer_size=500, learning_starts=0, **csac)
    return CSACLearner(env, RunConfig(env="SafeNav-v1", preset="easy", total_steps=500), cfg), env


@pytest.mark.parametrize("n_step", [1, 3])
def test_minibatches_mix_the_flights_at_their_share(n_step):
    torch.manual_seed(0)
    learner, env = _learner(planner_share=0.25, cost_n_step=n_step)
    obs = env.reset(seed=100_000)
    for _ in range(20):  # the learner's own transitions
        obs, _, _ = learner.collect(env, obs, 10_000, 0.1)
    flights = []
    for _ in range(10):  # flights whose reward marks them
        step = env.step(torch.zeros(2, 3))
        batch = Batch(obs, torch.full((2, 3), 0.5), torch.full((2,), 7.0), step.cost,
                      step.real_next_obs, step.terminated)  # fmt: skip
        flights.append((batch, step.truncated, step.valid))
        obs = step.next_obs
    learner.set_planner_flights(flights)
    assert len(learner.planner_buffer) == 20 - 2 * (n_step - 1)  # the window holds the last ones
    mixed = learner.sample(32)
    assert mixed.actions.shape == (32, 3)
    assert (mixed.rewards[24:] == 7.0).all() and (mixed.rewards[:24] != 7.0).all()
    assert (mixed.actions[24:] == 0.5).all()
    assert (mixed.costs_n is not None) == (n_step > 1)
    metrics = [m for i in range(4) for m in learner.update(10_040 + 2 * i, 0.1)[1]]
    assert metrics and all(torch.isfinite(m["losses/qr"]) for m in metrics)  # on mixed batches
    # without flights, minibatches are the replay buffer's alone
    plain, _ = _learner()
    assert plain.planner_buffer is None


@pytest.mark.parametrize(
    "kwargs, message",
    [({"planner_share": 1.0}, "planner-share"), ({"planner_share": -0.1}, "planner-share"),
     ({"planner_share": 0.25, "planner_steps": 2, "planner_envs": 4}, "planner-steps"),
     ({"planner_envs": 0}, "planner-envs")],
)  # fmt: skip
def test_planner_options_are_checked(kwargs, message):
    with pytest.raises(ValueError, match=message):
        CSACConfig(**kwargs)


def test_train_with_the_planners_flights_end_to_end(tmp_path):
    run_dir = tmp_path / "run"
    args = ["--num-envs", "4", "--log-every", "100", "--eval-every", "0", "--checkpoint-every",
            "200", "--no-progress", "--no-tensorboard", "--torch-threads", "1",
            "--csac.learning-starts", "100", "--csac.batch-size", "32", "--csac.buffer-size",
            "2000", "--csac.net.hidden", "32", "32"]  # fmt: skip
    main(["train", "--algo", "csac", "--env", "SafeNav-v1", "--preset", "easy", "--seed", "3",
          "--total-steps", "300", "--shield", "--csac.planner-share", "0.25", "--csac.planner-keep-band",
          "--csac.planner-steps", "64", "--csac.planner-envs", "4", "--run-dir", str(run_dir), *args])  # fmt: skip
    config = json.loads((run_dir / "config.json").read_text())
    assert config["csac"]["planner_share"] == 0.25 and config["csac"]["planner_steps"] == 64
    assert config["csac"]["planner_keep_band"] is True and config["csac"]["planner_view"] == "range"
    events = [json.loads(line) for line in (run_dir / "events.jsonl").read_text().splitlines()]
    flown = [e for e in events if e["event"] == "planner_flights"]
    assert len(flown) == 1 and flown[0]["transitions"] == 64
    with (run_dir / "progress.csv").open(newline="") as f:  # its minutes count in the run's
        elapsed = [float(r["time/elapsed_s"]) for r in csv.DictReader(f)]
    assert elapsed and min(elapsed) >= flown[0]["wall_s"]
    # a resumed run flies them again (they are not in the checkpoint)
    main(["train", "--resume", str(run_dir), "--total-steps", "400", "--no-progress"])
    events = [json.loads(line) for line in (run_dir / "events.jsonl").read_text().splitlines()]
    assert sum(e["event"] == "planner_flights" for e in events) == 2
    # the planner flies SafeNav only
    with pytest.raises(SystemExit):
        main(["train", "--algo", "sac", "--env", "Pendulum-v1", "--total-steps", "1000",
              "--csac.planner-share", "0.25", "--run-dir", str(tmp_path / "p"), "--no-progress"])  # fmt: skip
