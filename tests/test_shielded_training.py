"""``safenav train --shield``: the env executes the shield's correction, the learner keeps the
policy's own action, the policy records its shield and is chosen and reported behind it."""

from __future__ import annotations

import csv
import json

import pytest
import torch

from conftest import PAPER_OBSERVATION
from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSACLearner
from safenav.algos.policy import load_policy
from safenav.cli import main
from safenav.common.config import RunConfig
from safenav.deploy.shield import MemoryShield, env_shield, shield_from_spec
from safenav.envs.vector import TorchVecEnv, make_vec_env
from safenav.experiments.selection import own_shield
from safenav.training.shielded import ShieldedVecEnv

FAST = ["--num-envs", "4", "--log-every", "100", "--eval-every", "200", "--eval-episodes", "2",
        "--checkpoint-every", "200", "--no-progress", "--no-tensorboard", "--torch-threads", "1",
        "--csac.learning-starts", "100", "--csac.batch-size", "32", "--csac.buffer-size", "2000",
        "--csac.updates-per-step", "0.25", "--csac.net.hidden", "32", "32"]  # fmt: skip


def test_the_env_executes_the_shields_action_and_the_learner_keeps_its_own():
    env = TorchVecEnv(make_vec_env("SafeNav-v1", 4, "cpu", "easy"), "cpu")
    executed, seen = [], []
    inner_step = env.step
    env.step = lambda a: (executed.append(a.clone()), inner_step(a))[1]

    def halt(nav, obs, action):  # a "shield" that stops every UAV; it sees the env and the obs
        seen.append((nav, obs["lidar"].clone()))
        return torch.zeros_like(action)

    shielded = ShieldedVecEnv(env, halt)
    run = RunConfig(env="SafeNav-v1", preset="easy", num_envs=4, total_steps=1000)
    learner = CSACLearner(shielded, run, CSACConfig(buffer_size=100, batch_size=8))
    obs = shielded.reset(seed=3)
    first_lidar = obs["lidar"].clone()
    obs, _, steps = learner.collect(shielded, obs, 0, 0.5)  # warm-up: uniform random actions
    assert steps == 4 and len(executed) == 1
    assert torch.equal(executed[0], torch.zeros(4, 3))  # the env flew the shield's action
    stored = learner.buffer.actions[:4]
    assert stored.abs().sum() > 0  # the buffer holds the policy's own (random) actions
    nav, lidar = seen[0]
    assert nav is env.envs.unwrapped and torch.equal(lidar, first_lidar)
    learner.collect(shielded, obs, 4, 0.5)
    assert torch.equal(
        seen[1][1], obs["lidar"]
    )  # the shield reads the obs the action was chosen on
    assert (
        shielded.correction_rate() == 1.0
        and shielded.correction_rate() != shielded.correction_rate()
    )


def test_the_shield_penalty_charges_the_learner_for_each_correction():
    """``--shield-penalty K``: the reward falls by K per m/s of correction (halt: the whole
    commanded speed), nothing where the shield lets the action through."""
    rewards = []
    for shield, penalty in ((lambda nav, obs, a: torch.zeros_like(a), 0.0),
                            (lambda nav, obs, a: torch.zeros_like(a), 0.5),
                            (lambda nav, obs, a: a, 0.5)):  # fmt: skip
        env = TorchVecEnv(make_vec_env("SafeNav-v1", 4, "cpu", "easy"), "cpu")
        shielded = ShieldedVecEnv(env, shield, penalty)
        shielded.reset(seed=3)
        action = torch.tensor([[0.6, 0.8, 0.0]] * 4)
        rewards.append(shielded.step(action).reward)
    v_max = env.envs.unwrapped.cfg.v_max
    assert torch.allclose(rewards[0] - rewards[1], torch.full((4,), 0.5 * v_max))
    with pytest.raises(ValueError, match="penalty"):
        ShieldedVecEnv(env, env_shield, -1.0)
    free = TorchVecEnv(make_vec_env("SafeNav-v1", 4, "cpu", "easy"), "cpu")
    free.reset(seed=3)
    assert torch.equal(rewards[2], free.step(torch.tensor([[0.6, 0.8, 0.0]] * 4)).reward)


def test_step_before_reset_and_normalised_observations_are_refused():
    env = TorchVecEnv(make_vec_env("SafeNav-v1", 2, "cpu", "easy"), "cpu")
    with pytest.raises(RuntimeError, match="before reset"):
        ShieldedVecEnv(env, env_shield).step(torch.zeros(2, 3))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"shield_map": True}, "add --shield"), ({"shield_memory": 5}, "add --shield"),
     ({"shield_mover_margin": 0.3}, "add --shield"), ({"shield_brake": True}, "add --shield"),
     ({"shield_flight_brake": True}, "add --shield"), ({"shield_penalty": 0.5}, "add --shield"),
     ({"shield": True, "shield_penalty": -1.0}, r"\[0, 10\]"),
     ({"shield": True, "shield_penalty": True}, r"\[0, 10\]"),
     ({"shield": True, "shield_memory": 101}, r"\[0, 100\]"),
     ({"shield": True, "shield_mover_margin": -0.1}, r"\[0, 2\]"),
     ({"shield": True, "shield_mover_margin": 3.0}, r"\[0, 2\]"),
     ({"shield": True, "env": "Pendulum-v1"}, "flies SafeNav")],
)  # fmt: skip
def test_shield_options_are_checked(kwargs, message):
    with pytest.raises(ValueError, match=message):
        RunConfig(**kwargs)


def test_the_spec_rebuilds_the_shield():
    assert RunConfig().shield_spec() is None and shield_from_spec(None) is None
    spec = RunConfig(shield=True).shield_spec()
    assert spec == {"memory": 1, "map": False, "mover_margin": 0.0, "brake": False}
    assert shield_from_spec(spec) is env_shield  # NavRL's memoryless shield
    spec = RunConfig(
        shield=True, shield_memory=5, shield_map=True, shield_mover_margin=0.3
    ).shield_spec()
    shield = shield_from_spec(spec)
    assert isinstance(shield, MemoryShield)
    assert (shield.memory, shield.map_scan, shield.mover_margin, shield.brake) == (
        5,
        True,
        0.3,
        False,
    )
    braking = shield_from_spec(RunConfig(shield=True, shield_brake=True).shield_spec())
    assert isinstance(braking, MemoryShield) and braking.brake and braking.memory == 1
    # a policy trained before the braking cap records no "brake": it flies without it
    assert not shield_from_spec({"memory": 1, "map": True, "mover_margin": 0.3}).brake
    slide = shield_from_spec({"memory": 1, "brake": "slide"})
    assert slide.brake and slide.brake_slide
    for bad in ("off", "sliding", 1):
        with pytest.raises(ValueError, match="brake must be"):
            shield_from_spec({"memory": 1, "brake": bad})
    # the flight shield is recorded only where it differs from the training one
    assert RunConfig(shield=True).flight_shield_spec() == RunConfig(shield=True).shield_spec()


def test_train_behind_the_shield_end_to_end(tmp_path):
    run_dir = tmp_path / "run"
    main(["train", *PAPER_OBSERVATION, "--env", "SafeNav-v1", "--preset", "easy", "--seed", "3",
          "--total-steps", "400", "--shield", "--shield-map", "--shield-mover-margin", "0.3",
          "--shield-flight-brake", "--shield-penalty", "0.2", "--keep-policies", "--run-dir", str(run_dir), *FAST])  # fmt: skip
    config = json.loads((run_dir / "config.json").read_text())
    assert config["run"]["shield"] and config["run"]["shield_mover_margin"] == 0.3
    assert config["run"]["shield_penalty"] == 0.2
    with (run_dir / "progress.csv").open(newline="") as f:
        rates = [
            float(r["charts/shield_rate"]) for r in csv.DictReader(f) if r["charts/shield_rate"]
        ]
    assert rates and all(0.0 <= r <= 1.0 for r in rates)
    policy = load_policy(run_dir / "best.pt")
    # it trained behind the shield without the braking cap and flies with it
    assert policy.meta["shield"] == {"memory": 1, "map": True, "mover_margin": 0.3, "brake": False}
    assert policy.meta["flight_shield"] == {**policy.meta["shield"], "brake": True}
    shield = own_shield(policy)  # what its selection and report fly behind
    assert isinstance(shield, MemoryShield) and shield.map_scan and shield.mover_margin == 0.3
    assert shield.brake
    # safenav eval flies it behind its flight shield unless a shield option says otherwise
    for extra, expected in (([], (True, 1, True, 0.3, True)),
                            (["--no-shield"], (False, None, None, None, None)),
                            (["--shield"], (True, 1, False, 0.0, False))):  # fmt: skip
        out = tmp_path / "eval.json"
        main(["eval", str(run_dir / "best.pt"), "--episodes", "2", "--json", str(out), *extra])
        got = json.loads(out.read_text())
        assert (got["shield"], got.get("shield_memory"), got.get("shield_map"),
                got.get("shield_mover_margin"), got.get("shield_brake")) == expected, extra  # fmt: skip
    # resumed, it goes on behind the same shield
    main(["train", "--resume", str(run_dir), "--total-steps", "600", "--no-progress"])
    assert load_policy(run_dir / "best.pt").meta["shield"]["mover_margin"] == 0.3
    # a policy trained without one flies alone
    plain = tmp_path / "plain"
    main(["train", *PAPER_OBSERVATION, "--env", "SafeNav-v1", "--preset", "easy", "--seed", "3",
          "--total-steps", "200", "--run-dir", str(plain), *FAST])  # fmt: skip
    assert own_shield(load_policy(plain / "checkpoint.pt")) is None
