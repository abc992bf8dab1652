"""``safenav train --algo ppo|ppo_lag|sac_lag`` through the CLI in seconds: run directory, metrics,
checkpoint -> ``load_policy`` / ``safenav eval``, resume; SAC-Lag's switches on the CSAC path."""

from __future__ import annotations

import csv
import json

import pytest
import torch

from conftest import PAPER_OBSERVATION
from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSAC
from safenav.algos.policy import load_policy
from safenav.algos.sac_lag import sac_lag_config
from safenav.cli import main
from safenav.common.buffer import ReplayBuffer
from safenav.common.checkpoint import load_checkpoint
from safenav.nn.config import NetConfig

FAST = ["--no-progress", "--no-tensorboard", "--eval-every", "0", "--torch-threads", "1"]
PPO_SMALL = ["--ppo.rollout-steps", "8", "--ppo.epochs", "2", "--ppo.num-minibatches", "2",
             "--ppo.net.hidden", "32", "32"]  # fmt: skip
SAC_SMALL = ["--csac.learning-starts", "1024", "--csac.batch-size", "32", "--csac.lambda-every", "128",
             "--csac.net.hidden", "32", "32", "--csac.episode-lambda-lr", "0.1"]  # fmt: skip


def rows(run_dir) -> list[dict[str, str]]:
    with (run_dir / "progress.csv").open() as f:
        return list(csv.DictReader(f))


def train(
    tmp_path, algo: str, *args: str, env: str = "SafeNav-v1", steps: int = 512, envs: int = 16
):
    run_dir = tmp_path / algo
    preset = ["--preset", "easy"] if env == "SafeNav-v1" else []
    main(["train", "--algo", algo, "--env", env, *preset, "--num-envs", str(envs), "--total-steps",
          str(steps), "--log-every", "128", "--run-dir", str(run_dir), *FAST, *args])  # fmt: skip
    return run_dir


@pytest.mark.parametrize("algo", ["ppo", "ppo_lag"])
def test_ppo_family_on_safenav_run_dir_policy_and_resume(tmp_path, algo):
    run_dir = train(tmp_path, algo, *PPO_SMALL, "--eval-every", "256", "--eval-episodes", "2")
    for name in ("config.json", "progress.csv", "checkpoint.pt", "events.jsonl"):
        assert (run_dir / name).exists(), name
    config = json.loads((run_dir / "config.json").read_text())
    assert config["algo"] == algo and config["ppo"]["constrained"] == (algo == "ppo_lag")
    table = rows(run_dir)
    assert [int(r["global_step"]) for r in table] == [128, 256, 384, 512]
    for col in (
        "charts/episodic_return",
        "charts/episodic_cost",
        "charts/success_rate",
        "charts/collision_rate",
    ):  # fmt: skip  (filled once episodes end)
        assert col in table[0], col
    for col in ("perf/sps", "losses/actor", "losses/value", "losses/entropy", "losses/approx_kl"):
        assert table[-1][col] != "", col
    if algo == "ppo_lag":
        assert table[-1]["constraint/lambda"] != "" and table[-1]["constraint/d"] == "0.5"
        assert table[-1]["losses/value_cost"] != ""

    policy = load_policy(run_dir)
    assert policy.meta["algo"] == algo and policy.meta["policy_head"] == "beta"
    obs = {
        "state": torch.randn(4, 8),
        "lidar": torch.rand(4, 4, 36),
        "dynamic": torch.zeros(4, 5, 10),
    }
    action = policy(obs)
    assert action.shape == (4, 3) and bool((action.abs() <= 1).all())
    # the checkpoint's deterministic actor is the agent's Beta mean
    from safenav.algos.ppo import PPO
    from safenav.algos.ppo_config import PPOConfig
    from safenav.common.config import from_dict

    ckpt = load_checkpoint(run_dir)
    agent = PPO(policy.obs_shapes, 3, from_dict(PPOConfig, ckpt["config"]["ppo"]))
    agent.load_state_dict(ckpt["agent"])
    torch.testing.assert_close(policy(obs), agent.act(obs, deterministic=True)[0])

    main(["train", "--algo", algo, "--resume", str(run_dir), "--total-steps", "768", *FAST])
    table = rows(run_dir)
    assert int(table[-1]["global_step"]) == 768 and int(table[3]["global_step"]) == 512
    assert load_checkpoint(run_dir)["global_step"] == 768
    best = load_checkpoint(run_dir / "best.pt")  # the best periodic evaluation's policy
    assert best["policy_only"] and load_policy(run_dir / "best.pt").meta["algo"] == algo
    assert load_checkpoint(run_dir)["best"]["score"][0] == best["evaluation"]["eval/success_rate"]


def test_ppo_on_a_gymnasium_env(tmp_path):
    run_dir = train(tmp_path, "ppo", *PPO_SMALL, env="Pendulum-v1", steps=1024, envs=4)
    assert load_policy(run_dir)({"obs": torch.zeros(3)}).shape == (1,)
    ended = [r for r in rows(run_dir) if r["charts/episodic_return"]]
    assert ended  # the 200-step episodes ended (truncated) at step 800
    assert (
        float(ended[0]["charts/episodic_cost"]) == 0.0
        and float(ended[0]["charts/timeout_rate"]) == 1.0
    )


def test_sac_lag_on_safenav(tmp_path):
    run_dir = train(tmp_path, "sac_lag", *SAC_SMALL, steps=2048, envs=64)
    config = json.loads((run_dir / "config.json").read_text())["csac"]
    assert config["num_cost_critics"] == 1 and config["lambda_from"] == "episode_cost"
    assert config["scale_actor_loss"] is True
    ckpt = load_checkpoint(run_dir)
    assert ckpt["agent"]["qc.mlp.layers.0.weight"].shape[0] == 1  # one cost critic
    table = rows(run_dir)
    lam = [float(r["constraint/lambda"]) for r in table if r["constraint/lambda"]]
    assert lam and lam[-1] > 0  # random warm-up flights collide: J_c > d raises lambda
    assert any(r["constraint/episode_cost"] for r in table)
    assert load_policy(run_dir).meta["algo"] == "sac_lag"


def test_eval_reads_a_ppo_checkpoint(tmp_path):
    run_dir = train(tmp_path, "ppo", *PPO_SMALL, steps=256)
    out = tmp_path / "eval.json"
    main(["eval", str(run_dir / "checkpoint.pt"), "--episodes", "4", "--json", str(out)])
    result = json.loads(out.read_text())
    assert result["success_rate"] + result["collision_rate"] + result[
        "timeout_rate"
    ] == pytest.approx(1.0)


def test_sac_lag_update_leaves_lambda_to_the_episode_cost_and_scales_the_actor_loss():
    shapes = {"obs": (3,)}
    cfg = sac_lag_config(CSACConfig(net=NetConfig(hidden=(16, 16)), batch_size=8, init_lambda=1.0))
    buf = ReplayBuffer(64, shapes, 1)
    g = torch.Generator().manual_seed(0)
    obs, nxt = {"obs": torch.randn(64, 3, generator=g)}, {"obs": torch.randn(64, 3, generator=g)}
    buf.add(obs, torch.rand(64, 1, generator=g), torch.randn(64, generator=g), torch.ones(64), nxt,
            torch.zeros(64, dtype=torch.bool))  # fmt: skip
    torch.manual_seed(0)
    agent = CSAC(shapes, 1, cfg)
    torch.manual_seed(1)
    batch = buf.sample(8)
    metrics = agent.update(batch, d_q=0.0)  # cost 1 everywhere: Eq. 11 would raise lambda
    assert float(agent.lam) == 1.0 and "losses/lambda" not in metrics
    assert agent.qc.ensemble_size == 1
    # the same agent unscaled: actor loss (1 + lambda) = 2 times larger
    torch.manual_seed(0)
    plain = CSAC(shapes, 1, CSACConfig(**{**cfg.__dict__, "scale_actor_loss": False}))
    torch.manual_seed(1)
    unscaled = plain.update(buf.sample(8), d_q=0.0)
    assert unscaled["losses/actor"].item() == pytest.approx(
        2 * metrics["losses/actor"].item(), rel=1e-5
    )
    agent.lagrange.update(torch.tensor([0.9]), 0.1)  # J_c > d: lambda rises
    assert float(agent.lam) > 1.0


def test_export_writes_an_onnx_ppo_policy_equal_to_torch(tmp_path):
    pytest.importorskip("onnxruntime")
    run_dir = train(tmp_path, "ppo", *PPO_SMALL, steps=128)
    out = tmp_path / "policy.onnx"
    main(["export", str(run_dir), "--onnx", str(out)])
    import numpy as np
    import onnxruntime as ort

    policy = load_policy(run_dir)
    obs = {
        "state": torch.randn(2, 8),
        "lidar": torch.rand(2, 4, 36),
        "dynamic": torch.zeros(2, 5, 10),
    }
    sess = ort.InferenceSession(str(out))
    feeds = {i.name: obs[i.name].numpy() for i in sess.get_inputs()}
    onnx_action = sess.run(None, feeds)[0]
    np.testing.assert_allclose(onnx_action, policy(obs).numpy(), atol=1e-5)


def test_csac_ablation_switches_reach_the_run(tmp_path):
    """min cost target, no curriculum (fixed d = d_min), separate extractors: one run."""
    run_dir = train(tmp_path, "csac", "--csac.cost-target", "min", "--csac.curriculum.no-enabled",
                    "--csac.net.no-shared-extractor", "--csac.learning-starts",
                    "128", "--csac.batch-size", "32", "--csac.net.hidden", "32", "32", steps=384)  # fmt: skip
    cfg = json.loads((run_dir / "config.json").read_text())["csac"]
    assert cfg["cost_target"] == "min" and cfg["curriculum"]["enabled"] is False
    assert cfg["net"]["shared_extractor"] is False
    assert {r["constraint/d"] for r in rows(run_dir)} == {"0.05"}  # d_min throughout
    state = load_checkpoint(run_dir)["agent"]
    assert not any(k.startswith("encoder.") for k in state)  # no shared extractor
    assert any(k.startswith("qc.extractor.") for k in state)  # the cost critics own one


@pytest.mark.long
def test_csac_measured_cost_scale_logs_its_threshold_and_resumes(tmp_path, monkeypatch):
    """``--csac.cost-scale measured``: d_Q = d * E[Q_C] / episode cost from the run's own data,
    logged, carried in the checkpoint, restored by --resume."""
    import functools

    import safenav.algos.csac as csac_module

    # measure from 20 episodes on (100 by default: more than a run of seconds finishes)
    measured = functools.partial(csac_module.MeasuredCostScale, min_episodes=20)
    monkeypatch.setattr(csac_module, "MeasuredCostScale", measured)
    small = ["--csac.cost-scale", "measured", "--csac.learning-starts", "128", "--csac.batch-size", "32",
             "--csac.net.hidden", "32", "32", "--csac.updates-per-step", "0.0625", "--preset", "paper"]  # fmt: skip
    # the paper's observation, no shield: random flights crash often enough
    run_dir = train(tmp_path, "csac", *PAPER_OBSERVATION, *small, steps=8192, envs=64)
    ckpt = load_checkpoint(run_dir)
    scale = ckpt["cost_scale"]
    assert scale["cost_n"] >= 20 and scale["q_n"] > 0  # random flights crash: enough episodes
    last = rows(run_dir)[-1]
    ratio = max(scale["q_mean"], 0.0) / scale["cost_mean"]
    assert float(last["constraint/d_q"]) == pytest.approx(
        float(last["constraint/d"]) * ratio, rel=1e-4
    )
    # 8192 more steps (128 per env): enough finished episodes to count whatever the policy learned
    main(["train", "--resume", str(run_dir), "--total-steps", "16384", *FAST])
    resumed = load_checkpoint(run_dir)["cost_scale"]
    assert resumed["cost_n"] > scale["cost_n"] and resumed["q_n"] > scale["q_n"]


@pytest.mark.parametrize("window", [0, 3])
def test_sac_lag_lambda_reads_the_episodes_since_its_last_step_or_a_window_of_the_last_ones(window):
    """``lambda_window`` 0: J_c is the mean over the episodes that ended since lambda's last step
    (then forgotten); N: over the last N episodes, kept across steps (OmniSafe's logger window)."""
    from safenav.algos.csac import CSACLearner
    from safenav.common.config import RunConfig
    from safenav.envs.vector import TorchVecEnv, make_vec_env

    env = TorchVecEnv(make_vec_env("Pendulum-v1", 1, "cpu"), "cpu")
    cfg = sac_lag_config(CSACConfig(learning_starts=10_000, batch_size=8, lambda_every=1,
                                    lambda_window=window, episode_lambda_lr=0.1,
                                    net=NetConfig(hidden=(8, 8))))  # fmt: skip
    learner = CSACLearner(env, RunConfig(env="Pendulum-v1", total_steps=20_000), cfg)
    learner.warmup_until = 0  # lambda steps from the start; no gradient update (empty buffer)
    seen = []
    for step, costs in enumerate([[40.0], [], [10.0, 30.0], [], [0.0]], start=1):
        learner.observe({"cost": costs})
        learner.update(step, 25.0)
        seen.append(learner.pending.pop("constraint/episode_cost", None))
    if window:  # every step once an episode has ended, over the last (up to) 3 episodes
        assert seen == [40.0, 40.0, pytest.approx(80 / 3), pytest.approx(80 / 3), 40 / 3]
    else:  # only at steps where episodes ended, each over those episodes alone
        assert seen == [40.0, None, 20.0, None, 0.0]
    env.close()


def test_sac_lag_lambda_held_by_its_warmup_forgets_the_episodes_of_the_hold():
    """``lambda_window`` 0 with a lambda warm-up: the first step after the hold reads only the
    episodes since the last due step, not every episode of the hold (the warm-up's random ones)."""
    from safenav.algos.csac import CSACLearner
    from safenav.common.config import RunConfig
    from safenav.envs.vector import TorchVecEnv, make_vec_env

    env = TorchVecEnv(make_vec_env("Pendulum-v1", 1, "cpu"), "cpu")
    cfg = sac_lag_config(CSACConfig(learning_starts=10_000, batch_size=8, lambda_every=1,
                                    lambda_window=0, lambda_warmup_steps=3,
                                    net=NetConfig(hidden=(8, 8))))  # fmt: skip
    learner = CSACLearner(env, RunConfig(env="Pendulum-v1", total_steps=20_000), cfg)
    learner.warmup_until = 0
    seen = []
    for step, costs in enumerate([[400.0], [300.0], [10.0, 30.0], [0.0]], start=1):
        learner.observe({"cost": costs})
        learner.update(step, 25.0)
        seen.append(learner.pending.pop("constraint/episode_cost", None))
    assert seen == [None, None, 20.0, 0.0]
    assert learner.state_dict()["lambda_costs"] == []  # nor does a checkpoint keep them
    env.close()


def test_sac_lag_lambda_window_survives_a_resume():
    """The J_c window is learner state: a resumed run reads the same last episodes."""
    from safenav.algos.csac import CSACLearner
    from safenav.common.config import RunConfig
    from safenav.envs.vector import TorchVecEnv, make_vec_env

    env = TorchVecEnv(make_vec_env("Pendulum-v1", 1, "cpu"), "cpu")
    cfg = sac_lag_config(CSACConfig(batch_size=8, lambda_every=1, lambda_window=3,
                                    net=NetConfig(hidden=(8, 8))))  # fmt: skip
    run = RunConfig(env="Pendulum-v1", total_steps=20_000)
    learner = CSACLearner(env, run, cfg)
    learner.observe({"cost": [1.0, 2.0, 3.0, 4.0]})
    state = learner.state_dict() | {"global_step": 100}
    assert state["lambda_costs"] == [2.0, 3.0, 4.0]
    resumed = CSACLearner(env, run, cfg)
    resumed.load_state_dict(json.loads(json.dumps(state)))  # what a checkpoint keeps: plain values
    assert list(resumed.lam_costs) == [2.0, 3.0, 4.0] and resumed.lam_costs.maxlen == 3
    resumed.observe({"cost": [5.0]})
    assert list(resumed.lam_costs) == [3.0, 4.0, 5.0]
    env.close()


def test_cost_scale_episodes_sets_the_measured_scale_span():
    from safenav.algos.csac import CSACLearner
    from safenav.common.config import RunConfig
    from safenav.envs.vector import TorchVecEnv, make_vec_env

    env = TorchVecEnv(make_vec_env("Pendulum-v1", 1, "cpu"), "cpu")
    cfg = CSACConfig(batch_size=8, cost_scale="measured", cost_scale_episodes=7,
                     net=NetConfig(hidden=(8, 8)))  # fmt: skip
    learner = CSACLearner(env, RunConfig(env="Pendulum-v1", total_steps=1000), cfg)
    assert learner.measured_scale.span_episodes == 7
    with pytest.raises(ValueError, match="cost-scale-episodes"):
        CSACConfig(cost_scale_episodes=0)
    env.close()


@pytest.mark.parametrize("lambda_from", ["q_cost", "episode_cost"])
def test_lambda_warmup_holds_lambda_then_lets_it_rise(lambda_from):
    """``lambda_warmup_steps``: no lambda step (Eq. 11, or SAC-Lag's episode-cost step) before that
    env step, while the critics and actor learn; from it on, a violated constraint raises lambda."""
    from safenav.algos.csac import CSACLearner
    from safenav.common.config import RunConfig
    from safenav.envs.vector import TorchVecEnv, make_vec_env

    env = TorchVecEnv(make_vec_env("Pendulum-v1", 1, "cpu"), "cpu")
    cfg = CSACConfig(learning_starts=0, updates_per_step=1.0, batch_size=8, lambda_lr=0.1,
                     lambda_warmup_steps=100, lambda_from=lambda_from, lambda_every=1,
                     episode_lambda_lr=0.1,
                     cost_critic_output="softplus", net=NetConfig(hidden=(8, 8)))  # fmt: skip
    learner = CSACLearner(env, RunConfig(env="Pendulum-v1", total_steps=1000), cfg)
    g = torch.Generator().manual_seed(0)
    obs, nxt = {"obs": torch.randn(64, 3, generator=g)}, {"obs": torch.randn(64, 3, generator=g)}
    learner.buffer.add(obs, torch.rand(64, 1, generator=g) * 2 - 1, torch.randn(64, generator=g),
                       torch.ones(64), nxt, torch.zeros(64, dtype=torch.bool))  # fmt: skip
    actor_before = [p.clone() for p in learner.agent.actor.parameters()]
    for step in (1, 50, 99):  # cost 1 everywhere against d = 0: every lambda step would raise it
        learner.observe({"cost": [40.0]})
        n, metrics = learner.update(step, 0.0)
        assert n == 1 and "losses/lambda" not in metrics[0]
        assert "constraint/episode_cost" not in learner.pending
    assert float(learner.agent.lam) == 0.0
    assert any(not torch.equal(a, b) for a, b in
               zip(actor_before, learner.agent.actor.parameters(), strict=True))  # fmt: skip
    learner.observe({"cost": [40.0]})
    learner.update(100, 0.0)
    assert float(learner.agent.lam) > 0.0
    with pytest.raises(ValueError, match="lambda-warmup-steps"):
        CSACConfig(lambda_warmup_steps=-1)
    env.close()


@pytest.mark.parametrize("lambda_from", ["q_cost", "episode_cost"])
def test_pid_lambda_update_answers_either_signal_at_once_and_is_named_a_variant(lambda_from):
    """``lambda_update="pid"``: the PID Lagrangian reads the signal ``lambda_from`` names (CSAC's
    E[Q_C] against d_Q, SAC-Lag's episode cost against d); its proportional term moves lambda on
    the first violated step; its state lives in the agent (no optimiser); a run is a variant."""
    from dataclasses import asdict

    from safenav.algos.config import paper_departures
    from safenav.algos.csac import CSACLearner
    from safenav.common.config import RunConfig
    from safenav.common.lagrange import PIDLagrange
    from safenav.envs.vector import TorchVecEnv, make_vec_env

    env = TorchVecEnv(make_vec_env("Pendulum-v1", 1, "cpu"), "cpu")
    cfg = CSACConfig(learning_starts=0, updates_per_step=1.0, batch_size=8, lambda_from=lambda_from,
                     lambda_every=1, lambda_update="pid", pid_kp=0.5, pid_ki=0.01, pid_kd=0.0,
                     net=NetConfig(hidden=(8, 8)))  # fmt: skip
    learner = CSACLearner(env, RunConfig(env="Pendulum-v1", total_steps=1000), cfg)
    assert isinstance(learner.agent.lagrange, PIDLagrange)
    g = torch.Generator().manual_seed(0)
    obs, nxt = {"obs": torch.randn(64, 3, generator=g)}, {"obs": torch.randn(64, 3, generator=g)}
    learner.buffer.add(obs, torch.rand(64, 1, generator=g) * 2 - 1, torch.randn(64, generator=g),
                       torch.ones(64), nxt, torch.zeros(64, dtype=torch.bool))  # fmt: skip
    learner.warmup_until = 0
    learner.observe({"cost": [40.0]})
    d = -100.0 if lambda_from == "q_cost" else 25.0  # q_cost: d_Q far below any E[Q_C] at init
    _, metrics = learner.update(1, d)
    lam = float(learner.agent.lam)
    if lambda_from == "episode_cost":  # J_c 40 against d 25: kp * 15 + ki * 15
        assert lam == pytest.approx(0.5 * 15 + 0.01 * 15)
    else:  # E[Q_C] of the batch against d_Q (d on the Q_C scale): kp * e + ki * e
        e = float(metrics[0]["constraint/qc_pi"]) - learner.d_q(d)
        assert e > 0 and lam == pytest.approx(0.51 * e, rel=1e-4)
    assert "lambda" not in learner.agent.optimizer_state()
    assert "lagrange.integral" in learner.agent.state_dict()
    assert paper_departures(asdict(cfg))[0] == "lambda_update=pid (paper: adam)"
    with pytest.raises(ValueError, match="pid-kp"):
        CSACConfig(pid_kp=-1.0)
    env.close()


def test_csac_with_a_pid_lagrangian_trains_and_resumes_through_the_cli(tmp_path):
    small = ["--csac.learning-starts", "128", "--csac.batch-size", "32", "--csac.net.hidden", "32",
             "32", "--csac.lambda-update", "pid", "--csac.pid-kp", "0.5"]  # fmt: skip
    run_dir = train(tmp_path, "csac", *small, env="Pendulum-v1", steps=256, envs=1)
    cfg = json.loads((run_dir / "config.json").read_text())["csac"]
    assert cfg["lambda_update"] == "pid" and cfg["pid_kp"] == 0.5
    state = load_checkpoint(run_dir)["agent"]
    steps = int(state["lagrange.steps"])
    assert steps > 0
    main(["train", "--resume", str(run_dir), "--total-steps", "384", *FAST])
    assert int(load_checkpoint(run_dir)["agent"]["lagrange.steps"]) > steps
