"""Observation and reward normalisation (``--normalize-obs``, ``--normalize-reward``; SB3's
VecNormalize): the statistics against NumPy on a known stream, the reward scale of the discounted
return, episode statistics and costs left raw, evaluation on frozen statistics, checkpoints and
resume, a loaded policy that acts as the training actor, SAC, the refusal on SafeNav, and the
default (off) unchanged."""

from __future__ import annotations

import hashlib
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from conftest import run_cli
from safenav.algos.ppo_config import PPOConfig
from safenav.common.checkpoint import load_checkpoint
from safenav.common.config import RunConfig
from safenav.common.normalize import (
    CLIP,
    EPSILON,
    NormalizedActor,
    ObsNormalizer,
    RewardScaler,
    make_normalization,
)
from safenav.envs.vector import TorchVecEnv, make_vec_env
from safenav.nn.config import NetConfig

pytestmark = pytest.mark.usefixtures("one_thread")

ROOT = Path(__file__).resolve().parents[1]
PRIOR = 1e-4  # the running statistics start as one pseudo-observation of this weight: mean 0, var 1


class Ramp(gym.Env):
    """``obs = [t, 100 + 10 t + offset]`` (``offset`` drawn at reset), reward ``t``, cost 0.5 per
    step, truncated at ``t = 5``: features of very different scales, a known return of 15."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.offset = 0, float(self.np_random.uniform(-5.0, 5.0))
        return self._obs(), {}

    def _obs(self):
        return np.array([self.t, 100.0 + 10.0 * self.t + self.offset], np.float32)

    def step(self, action):
        self.t += 1
        return self._obs(), float(self.t), False, self.t >= 5, {"cost": 0.5}


if "NormRamp-v0" not in gym.registry:
    gym.register("NormRamp-v0", entry_point=Ramp)


def reference_stats(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of the prior pseudo-observation and every row of ``x``, in closed form
    (``np.mean`` / ``np.var`` of the whole stream, however it was batched)."""
    n, m, v = len(x), x.mean(0), x.var(0)
    total = n + PRIOR
    return n * m / total, (PRIOR * 1.0 + n * v + m**2 * PRIOR * n / total) / total


def normalized(x: np.ndarray, mean: np.ndarray, var: np.ndarray) -> np.ndarray:
    return np.clip((x - mean) / np.sqrt(var + EPSILON), -CLIP, CLIP)


def tiny(run_dir: Path, *extra: str) -> list[str]:
    """A few-second PPO run of the ramp env (2 envs, 8-step rollouts, 16-unit networks)."""
    return ["train", "--algo", "ppo", "--env", "NormRamp-v0", "--config", "none", "--num-envs", "2",
            "--ppo.rollout-steps", "8", "--ppo.num-minibatches", "2", "--ppo.epochs", "1",
            "--ppo.net.hidden", "16", "16", "--ppo.net.flatten-hidden", "16", "--no-progress",
            "--no-tensorboard", "--torch-threads", "1", "--eval-episodes", "2",
            "--run-dir", str(run_dir), *extra]  # fmt: skip


# ------------------------------------------------------------------- the statistics themselves
def test_observation_statistics_match_numpy_on_a_known_stream():
    rng = np.random.default_rng(0)
    norm = ObsNormalizer({"a": (2,), "b": (3, 4)})
    seen: dict[str, list[np.ndarray]] = {"a": [], "b": []}
    for n in (1, 5, 2, 17, 3):  # batches of any size give the same statistics
        batch = {"a": rng.normal([3.0, -200.0], [0.1, 40.0], (n, 2)),
                 "b": rng.normal(1.0, 5.0, (n, 3, 4))}  # fmt: skip
        norm.update({k: torch.as_tensor(v, dtype=torch.float32) for k, v in batch.items()})
        for k, v in batch.items():
            seen[k].append(v.astype(np.float32))
    x = {"a": np.array([[3.05, -150.0], [2.0, 400.0]], np.float32),  # 2.0: far beyond the clip
         "b": rng.normal(1.0, 5.0, (2, 3, 4)).astype(np.float32)}  # fmt: skip
    out = norm({k: torch.as_tensor(v) for k, v in x.items()})
    for k, rms in zip(norm.keys, norm.stats, strict=True):
        mean, var = reference_stats(np.concatenate(seen[k]).astype(np.float64))
        np.testing.assert_allclose(rms.mean.numpy(), mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(rms.var.numpy(), var, rtol=1e-10)
        assert float(rms.count) == pytest.approx(28 + PRIOR, abs=1e-12)
        assert out[k].dtype == torch.float32
        np.testing.assert_allclose(
            out[k].numpy(), normalized(x[k], mean, var), rtol=1e-5, atol=1e-5
        )
    assert out["a"][1, 0] == -CLIP and out["a"][1, 1] == CLIP


def test_the_training_env_normalises_every_observation_and_scales_rewards_by_the_return():
    """A raw and a normalising env from the same seed, stepped alike: the normalised one gives
    NumPy's normalisation of the raw stream so far (reset included, the true final observation of
    a truncated episode too), rewards scaled by the std of the discounted return (reset at the
    episode's end), costs and episode statistics raw."""
    gamma, n = 0.9, 2
    raw = TorchVecEnv(make_vec_env("NormRamp-v0", n))
    env = TorchVecEnv(make_vec_env("NormRamp-v0", n),
                      normalization=make_normalization(raw.obs_shapes, n, gamma, True, True))  # fmt: skip
    r0, o0 = raw.reset(seed=3)["obs"].numpy(), env.reset(seed=3)["obs"].numpy()
    seen, returns, all_returns = [r0], np.zeros(n), []
    np.testing.assert_allclose(
        o0, normalized(r0, *reference_stats(np.concatenate(seen))), atol=1e-5
    )
    action = torch.zeros(n, 1)
    ended = 0
    for _ in range(12):
        a, b = raw.step(action), env.step(action)
        seen.append(a.next_obs["obs"].numpy())
        mean, var = reference_stats(np.concatenate(seen).astype(np.float64))
        np.testing.assert_allclose(b.next_obs["obs"].numpy(), normalized(seen[-1], mean, var),
                                   rtol=1e-5, atol=1e-5)  # fmt: skip
        np.testing.assert_allclose(b.real_next_obs["obs"].numpy(),
                                   normalized(a.real_next_obs["obs"].numpy(), mean, var),
                                   rtol=1e-5, atol=1e-5)  # fmt: skip
        r = a.reward.numpy().astype(np.float64)
        returns = gamma * returns + r
        all_returns.append(returns.copy())
        _, var_r = reference_stats(np.concatenate(all_returns))
        np.testing.assert_allclose(b.reward.numpy(), np.clip(r / np.sqrt(var_r + EPSILON), -CLIP, CLIP),
                                   rtol=1e-5)  # fmt: skip
        returns[(a.terminated | a.truncated).numpy()] = 0.0
        assert torch.equal(b.cost, a.cost) and bool((b.cost == 0.5).all())  # never scaled
        if a.episodes is not None:  # episode statistics in the env's own units
            ended += 1
            for k in ("return", "cost", "length"):
                assert torch.equal(b.episodes[k], a.episodes[k])
            assert bool((b.episodes["return"] == 15.0).all())
    assert ended == 2  # two truncations, at steps 5 and 10
    assert not torch.allclose(b.reward, a.reward)


def test_reward_scaler_divides_by_the_std_of_the_discounted_return_not_of_the_reward():
    gamma = 0.99
    rewards = [np.array([1.0, -2.0]), np.array([1.0, -2.0]), np.array([1.0, 8.0]),
               np.array([3.0, 0.5]), np.array([1.0, 1.0])]  # fmt: skip
    dones = [np.array([False, False]), np.array([False, True]), np.array([False, False]),
             np.array([True, False]), np.array([False, False])]  # fmt: skip
    scaler = RewardScaler(2, gamma)
    ret, rets = np.zeros(2), []
    for r, d in zip(rewards, dones, strict=True):
        got = scaler(torch.as_tensor(r, dtype=torch.float32), torch.as_tensor(d))
        ret = gamma * ret + r
        rets.append(ret.copy())
        _, var = reference_stats(np.concatenate(rets))
        np.testing.assert_allclose(got.numpy(), r / np.sqrt(var + EPSILON), rtol=1e-6)
        ret[d] = 0.0
    np.testing.assert_allclose(scaler.returns.numpy(), ret)
    # clipped at 10: the first reward after 300 steps without any
    quiet, no = RewardScaler(2, gamma), torch.tensor([False, False])
    for _ in range(300):
        quiet(torch.zeros(2), no)
    assert quiet(torch.tensor([1.0, 0.0]), no).tolist() == [CLIP, 0.0]


@pytest.mark.parametrize("num_envs", [1, 3])
def test_the_numpy_env_side_is_the_torch_computation_bit_for_bit(num_envs):
    """On the CPU the env side runs through NumPy views of the buffers (speed); it must give the
    float64 statistics and float32 outputs of the torch operations exactly, and follow buffers
    that ``.to()`` replaced or ``load_state_dict`` overwrote."""
    gen = torch.Generator().manual_seed(0)
    fast, slow = ObsNormalizer({"obs": (4,)}), ObsNormalizer({"obs": (4,)})
    fast_r, slow_r = RewardScaler(num_envs, 0.99), RewardScaler(num_envs, 0.99)
    for step in range(60):
        x = torch.randn(num_envs, 4, generator=gen) * torch.tensor([1.0, 10.0, 1e3, 1e-3]) + 5.0
        r = torch.randn(num_envs, generator=gen) * 3.0
        done = torch.rand(num_envs, generator=gen) < 0.1
        fast.update({"obs": x})
        for rms in slow.stats:
            with torch.no_grad():
                rms._update_torch(x.to(torch.float64))
        for a, b in zip(fast.stats, slow.stats, strict=True):
            for name in ("mean", "var", "count"):
                assert torch.equal(getattr(a, name), getattr(b, name)), (step, name)
        assert torch.equal(fast.env_side({"obs": x})["obs"], slow({"obs": x})["obs"])
        got = fast_r(r, done)
        with torch.no_grad():  # RewardScaler.forward's torch branch, written out
            slow_r.returns.mul_(0.99).add_(r.to(torch.float64))
            slow_r.return_rms._update_torch(slow_r.returns)
            std = torch.sqrt(slow_r.return_rms.var + EPSILON)
            slow_r.returns[done] = 0.0
            want = (r / std.to(r.dtype)).clamp(-CLIP, CLIP)
        assert torch.equal(got, want) and got.dtype == torch.float32
        assert torch.equal(fast_r.returns, slow_r.returns)
        if step == 20:  # buffers replaced: the cached views must follow
            fast = fast._apply(lambda t: t.clone())  # what .to(device) does to every buffer
        if step == 40:
            fast.load_state_dict(slow.state_dict())
    assert float(fast.stats[0].count) == pytest.approx(60 * num_envs + PRIOR)


# ------------------------------------------------------------------------ the run around them
def test_evaluation_uses_the_training_statistics_frozen_and_reports_raw_returns(tmp_path):
    from safenav.training import Trainer, algo_config

    run = RunConfig(env="NormRamp-v0", num_envs=2, total_steps=64, eval_every=16, eval_episodes=2,
                    log_every=16, checkpoint_every=64, tensorboard=False, torch_threads=1,
                    normalize_obs=True, normalize_reward=True)  # fmt: skip
    cfg = PPOConfig(rollout_steps=8, num_minibatches=2, epochs=1,
                    net=NetConfig(hidden=(16, 16), flatten_hidden=(16,)))  # fmt: skip
    trainer = Trainer("ppo", run, algo_config("ppo", cfg), tmp_path / "run", progress=False)
    assert trainer.eval_env.normalization is None  # the evaluation env gives raw observations
    trainer.run()
    norm = trainer.normalization
    # folded in: the reset and the 32 vector steps of the training env (2 envs), and nothing of
    # the 4 evaluations (2 envs x 5+ steps each)
    assert float(norm.obs.stats[0].count) == pytest.approx(2 * (1 + 32) + PRIOR, abs=1e-9)
    assert float(norm.reward.return_rms.count) == pytest.approx(2 * 32 + PRIOR, abs=1e-9)
    import json

    events = [json.loads(line) for line in (tmp_path / "run" / "events.jsonl").open()]
    evals = [e for e in events if e["event"] == "eval"]
    assert len(evals) == 4 and all(
        e["eval/return"] == 15.0 and e["eval/cost"] == 2.5 for e in evals
    )
    # the evaluation acts on normalised observations: the statistics as they are
    obs = {"obs": torch.tensor([[2.0, 120.0], [4.0, 143.0]])}
    before = {k: v.clone() for k, v in norm.state_dict().items()}
    act = trainer.eval_act(obs)
    assert torch.equal(act, trainer.learner.act(norm.obs(obs)))
    assert not torch.equal(act, trainer.learner.act(obs))
    after = norm.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)


def test_checkpoint_keeps_the_statistics_and_resume_continues_them(tmp_path, capsys):
    run_dir = tmp_path / "run"
    code, _, err = run_cli(capsys, tiny(run_dir, "--normalize-obs", "--normalize-reward",
                                        "--total-steps", "32", "--eval-every", "0"))  # fmt: skip
    assert code == 0, err
    first = load_checkpoint(run_dir / "checkpoint.pt")
    stats = first["normalization"]
    assert float(stats["obs.stats.0.count"]) == pytest.approx(2 * (1 + 16) + PRIOR)
    assert float(stats["reward.return_rms.count"]) == pytest.approx(2 * 16 + PRIOR)
    policy = first["policy"]
    assert policy["meta"]["obs_normalization"] == {"clip": CLIP, "epsilon": EPSILON}
    for part in ("mean", "var", "count"):  # the policy holds the same observation statistics
        assert torch.equal(policy["state_dict"][f"normalizer.stats.0.{part}"],
                           stats[f"obs.stats.0.{part}"])  # fmt: skip
    code, _, err = run_cli(capsys, ["train", "--algo", "ppo", "--resume", str(run_dir),
                                    "--total-steps", "64", "--no-progress"])  # fmt: skip
    assert code == 0, err
    second = load_checkpoint(run_dir / "checkpoint.pt")["normalization"]
    # continued: the first run's observations, the resumed run's reset and 16 more vector steps
    assert float(second["obs.stats.0.count"]) == pytest.approx(2 * (1 + 16) * 2 + PRIOR)
    assert float(second["reward.return_rms.count"]) == pytest.approx(2 * 32 + PRIOR)


def test_a_loaded_policy_acts_as_the_training_actor_on_raw_observations(tmp_path):
    from safenav.algos.policy import load_policy
    from safenav.training import Trainer, algo_config

    run = RunConfig(env="NormRamp-v0", num_envs=2, total_steps=32, eval_every=0, log_every=16,
                    checkpoint_every=32, tensorboard=False, torch_threads=1, normalize_obs=True)  # fmt: skip
    cfg = PPOConfig(rollout_steps=8, num_minibatches=2, epochs=1,
                    net=NetConfig(hidden=(16, 16), flatten_hidden=(16,)))  # fmt: skip
    trainer = Trainer("ppo", run, algo_config("ppo", cfg), tmp_path / "run", progress=False)
    trainer.run()
    policy = load_policy(tmp_path / "run")
    assert isinstance(policy.actor, NormalizedActor)
    raw = torch.tensor([[0.0, 97.0], [2.0, 121.0], [5.0, 153.0], [1.0, 500.0]])
    in_training = trainer.learner.act(trainer.normalization.obs({"obs": raw}))
    assert torch.equal(policy(raw), in_training)
    assert not torch.equal(policy(raw), trainer.learner.act({"obs": raw}))  # it matters
    # the normalisation is part of the exported graph: ONNX Runtime on raw observations
    ort = pytest.importorskip("onnxruntime")
    path = tmp_path / "policy.onnx"
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(policy.actor, (raw,), str(path), input_names=["obs"], output_names=["action"],
                          dynamic_axes={"obs": {0: "batch"}}, opset_version=17, dynamo=False)  # fmt: skip
    out = ort.InferenceSession(str(path)).run(None, {"obs": raw.flip(0).numpy()})[0]
    np.testing.assert_allclose(out, policy(raw.flip(0)).numpy(), atol=1e-6, rtol=0)


def test_a_policy_without_statistics_loads_as_before():
    from safenav.algos.policy import load_policy

    for name in ("csac-paper.pt", "ppo-paper.pt"):
        policy = load_policy(ROOT / "checkpoints" / name)
        assert "obs_normalization" not in policy.meta
        assert not isinstance(policy.actor, NormalizedActor)


def test_sac_normalises_what_it_stores_and_its_policy_carries_the_statistics(tmp_path):
    from safenav.algos.config import CSACConfig
    from safenav.algos.policy import load_policy
    from safenav.training import Trainer, algo_config

    run = RunConfig(env="NormRamp-v0", num_envs=2, total_steps=120, eval_every=60, eval_episodes=2,
                    log_every=60, checkpoint_every=120, tensorboard=False, torch_threads=1,
                    normalize_obs=True, normalize_reward=True)  # fmt: skip
    cfg = CSACConfig(
        learning_starts=40, batch_size=16, net=NetConfig(hidden=(16, 16), flatten_hidden=(16,))
    )
    trainer = Trainer("sac", run, algo_config("sac", cfg), tmp_path / "run", progress=False)
    trainer.run()
    buf = trainer.learner.buffer
    obs, rewards = buf.obs["obs"][: len(buf)], buf.rewards[: len(buf)]
    assert obs[:, 1].abs().max() < 5.0  # the raw feature lies around 100-150
    assert rewards.abs().max() <= CLIP and not torch.equal(rewards, rewards.round())  # raw: 1..5
    assert bool((buf.costs[: len(buf)] == 0.5).all())
    assert float(trainer.normalization.obs.stats[0].count) == pytest.approx(2 * 61 + PRIOR)
    policy = load_policy(tmp_path / "run")
    raw = torch.tensor([[1.0, 108.0], [3.0, 131.0]])
    assert torch.equal(policy(raw), trainer.learner.act(trainer.normalization.obs({"obs": raw})))


# ----------------------------------------------------------------------------- refusals, default
def test_safenav_is_refused_in_one_line(tmp_path, capsys):
    for flags in (["--normalize-obs"], ["--normalize-reward"]):
        run_dir = tmp_path / "run"
        code, _, err = run_cli(capsys, ["train", "--preset", "easy", *flags, "--total-steps", "64",
                                        "--run-dir", str(run_dir), "--no-progress"])  # fmt: skip
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert flags[0].lstrip("-") in err and "SafeNav" in err
        assert not run_dir.exists()
    with pytest.raises(ValueError, match="normalize-obs / normalize-reward applies to Gymnasium"):
        RunConfig(normalize_obs=True, normalize_reward=True)


def weights_digest(state: dict) -> str:
    h = hashlib.sha256()
    for k in sorted(state):
        h.update(k.encode())
        h.update(state[k].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def test_off_by_default_and_then_nothing_changes(tmp_path, capsys):
    """Without the options: no statistics anywhere (env, checkpoint, policy), and the agent's
    weights bit for bit those of the same run before the options existed: the digest recorded
    with the ``src/`` of commit 1dbca58 (``git archive``), which the working tree then matched.
    Float results depend on torch's version and the CPU's vector kernels, so the digest is
    compared where it was recorded and the rest skips saying so."""
    assert not RunConfig().normalize_obs and not RunConfig().normalize_reward
    run_dir = tmp_path / "run"
    code, _, err = run_cli(capsys, tiny(run_dir, "--total-steps", "32", "--eval-every", "16",
                                        "--seed", "7"))  # fmt: skip
    assert code == 0, err
    ckpt = load_checkpoint(run_dir / "checkpoint.pt")
    assert "normalization" not in ckpt and "obs_normalization" not in ckpt["policy"]["meta"]
    assert not any(k.startswith("normalizer.") for k in ckpt["policy"]["state_dict"])
    where = (torch.__version__, torch.backends.cpu.get_cpu_capability())
    if where not in OFF_DIGESTS:
        pytest.skip(f"no weights digest recorded for torch {where[0]} with {where[1]} kernels")
    assert weights_digest(ckpt["agent"]) in OFF_DIGESTS[where]


#: The digests 1dbca58's src gives, per torch version and vector kernels. Two Xeons with the same
#: AVX-512 kernels give two digests (the same code; both recorded with 1dbca58's src on that
#: host): the hosts' float paths differ in a way neither AMX in /proc/cpuinfo nor the capability
#: string tells apart (2026-11-28: a Xeon listing amx_tile gave the second, with the src of that
#: day), so either is accepted. A change to the off path would give a third.
OFF_DIGESTS: dict[tuple[str, str], set[str]] = {
    ("2.13.0+cpu", "AVX512"): {
        "7dbeec2a8fdc8a67a26b0ec02c14ec7e2b5d46044561bea5a6d22afc6fb9faad",  # Sapphire Rapids
        "28ecd0c453b1c78fae2a6eb7835f13cddcbf2e82a361271938e57812d0bb0f6d",  # 2026-11-27, -28 Xeons
    },
    # recorded 2026-11-27 on an AMD EPYC host with 1dbca58's src (the same weights as AVX-512)
    ("2.13.0+cpu", "AVX2"): {"7dbeec2a8fdc8a67a26b0ec02c14ec7e2b5d46044561bea5a6d22afc6fb9faad"},
}
