"""CSAC/SAC mechanics: env adapter (costs, final observations, autoreset modes), truncation
bootstrap, target networks, gradient isolation of the shared extractor."""

from __future__ import annotations

import copy

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from conftest import CounterEnv
from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSAC
from safenav.algos.losses import reward_target
from safenav.common.buffer import ReplayBuffer
from safenav.envs.vector import TorchVecEnv, make_vec_env, obs_layout
from safenav.nn.config import NetConfig
from safenav.nn.networks import QEnsemble

NAV = {"state": (8,), "lidar": (4, 36), "dynamic": (5, 10)}
SMALL = NetConfig(hidden=(32, 32))


def counter_envs(mode: AutoresetMode) -> TorchVecEnv:
    return TorchVecEnv(
        SyncVectorEnv([lambda: CounterEnv(True), lambda: CounterEnv(False)], autoreset_mode=mode)
    )


def test_same_step_final_obs_cost_from_final_info_and_episode_stats():
    env = counter_envs(AutoresetMode.SAME_STEP)
    env.reset(seed=0)
    for _ in range(2):
        step = env.step(torch.zeros(2, 1))
        assert step.episodes is None and step.cost.tolist() == [0.0, 0.0]
    step = env.step(torch.zeros(2, 1))
    assert step.terminated.tolist() == [True, False] and step.truncated.tolist() == [False, True]
    assert step.next_obs["obs"].flatten().tolist() == [0.0, 0.0]  # already reset
    assert step.real_next_obs["obs"].flatten().tolist() == [3.0, 3.0]  # the true last observation
    assert step.cost.tolist() == [1.0, 1.0]  # read from final_info
    ep = step.episodes
    assert ep["return"].tolist() == [3.0, 3.0] and ep["cost"].tolist() == [1.0, 1.0]
    assert ep["length"].tolist() == [3.0, 3.0] and ep["timeout"].tolist() == [0.0, 1.0]
    assert ep["success"].tolist() == [1.0, 0.0] and ep["collision"].tolist() == [1.0, 1.0]


def test_next_step_autoreset_marks_the_reset_step_invalid():
    env = counter_envs(AutoresetMode.NEXT_STEP)
    env.reset(seed=0)
    steps = [env.step(torch.zeros(2, 1)) for _ in range(5)]
    assert steps[2].real_next_obs["obs"].flatten().tolist() == [3.0, 3.0]
    assert steps[2].cost.tolist() == [1.0, 1.0] and steps[2].episodes is not None
    assert steps[3].valid.tolist() == [False, False]  # the interleaved reset step: no transition
    assert steps[4].valid.tolist() == [True, True]
    assert steps[4].real_next_obs["obs"].flatten().tolist() == [1.0, 1.0]


def _vector(kind: str) -> SyncVectorEnv:
    if kind == "pendulum":  # random rewards, truncation at 200, normalised below
        return make_vec_env("Pendulum-v1", 3)
    cls = DictCounterEnv if kind == "dict" else CounterEnv
    mode = AutoresetMode.NEXT_STEP if kind == "next_step" else AutoresetMode.SAME_STEP
    return SyncVectorEnv([lambda: cls(True), lambda: cls(False)], autoreset_mode=mode)


@pytest.mark.parametrize("kind", ["same_step", "next_step", "dict", "pendulum"])
def test_numpy_step_is_the_torch_step_bit_for_bit(kind):
    """TorchVecEnv steps a NumPy vector env through NumPy (``numpy_step``): every field of every
    step, episodes included, equals the torch path's, with observation and reward normalisation
    (whose statistics must end equal too)."""
    from safenav.common.normalize import make_normalization

    def build(numpy_step: bool) -> TorchVecEnv:
        envs = _vector(kind)
        norm = make_normalization(obs_layout(envs.single_observation_space), envs.num_envs, 0.99,
                                  True, True)  # fmt: skip
        env = TorchVecEnv(envs, "cpu", norm)
        assert env.numpy_step
        env.numpy_step = numpy_step
        return env

    fast, slow = build(True), build(False)
    fast.reset(seed=3), slow.reset(seed=3)
    rng = np.random.default_rng(0)
    ended = 0
    for _ in range(450 if kind == "pendulum" else 12):
        action = torch.as_tensor(
            rng.uniform(-1.2, 1.2, (fast.num_envs, fast.action_dim)), dtype=torch.float32
        )
        a, b = fast.step(action), slow.step(action)
        for field in ("reward", "cost", "terminated", "truncated", "valid"):
            x, y = getattr(a, field), getattr(b, field)
            assert x.dtype == y.dtype and torch.equal(x, y), field
        for field in ("next_obs", "real_next_obs"):
            x, y = getattr(a, field), getattr(b, field)
            assert x.keys() == y.keys() and all(x[k].dtype == y[k].dtype and torch.equal(x[k], y[k])
                                                for k in x), field  # fmt: skip
        assert (a.episodes is None) == (b.episodes is None)
        if a.episodes is not None:
            ended += 1
            for k, x in a.episodes.items():
                assert x.dtype == b.episodes[k].dtype and torch.equal(x.nan_to_num(-7.0),
                                                                      b.episodes[k].nan_to_num(-7.0)), k  # fmt: skip
    assert ended >= 2
    for (k, x), y in zip(fast.normalization.state_dict().items(),
                         slow.normalization.state_dict().values(), strict=True):  # fmt: skip
        assert torch.equal(x, y), k


def test_actions_are_mapped_onto_the_env_box():
    env = counter_envs(AutoresetMode.SAME_STEP)
    torch.testing.assert_close(
        env.scale_action(torch.tensor([[-1.0], [1.0]])), torch.tensor([[-2.0], [2.0]])
    )


def test_truncated_transition_bootstraps_terminated_does_not():
    """Through env adapter and replay buffer into Eq. 5: the truncated env's target includes the
    discounted value of its true final observation; the terminated env's target is its reward."""
    env = counter_envs(AutoresetMode.SAME_STEP)
    buf = ReplayBuffer(16, env.obs_shapes, 1)
    obs = env.reset(seed=0)
    for _ in range(3):
        action = torch.zeros(2, 1)
        step = env.step(action)
        buf.add(
            obs, action, step.reward, step.cost, step.real_next_obs, step.terminated, step.valid
        )
        obs = step.next_obs
    last = slice(4, 6)  # the third vector step
    assert buf.terminated[last].tolist() == [1.0, 0.0]
    assert buf.next_obs["obs"][last].flatten().tolist() == [3.0, 3.0]
    next_q = buf.next_obs["obs"][last].flatten().expand(2, 2) * 10.0  # any critic of s'
    y = reward_target(buf.rewards[last], buf.terminated[last], next_q, torch.zeros(2), 0.0, 0.9)
    assert y.tolist() == pytest.approx([1.0, 1.0 + 0.9 * 30.0])


def test_safenav_vector_env_adapter_keeps_torch_and_reports_cost():
    env = TorchVecEnv(make_vec_env("SafeNav-v1", 4, preset="easy"))
    obs = env.reset(seed=3)
    assert {k: tuple(v.shape) for k, v in obs.items()} == {
        "state": (4, 8),
        "lidar": (4, 4, 36),
        "dynamic": (4, 5, 10),
    }
    ended = 0
    for _ in range(200):
        step = env.step(torch.ones(4, 3))  # full speed, straight: collisions or success soon
        if step.episodes is not None:
            ended += len(step.episodes["return"])
            done = (step.terminated | step.truncated).nonzero().squeeze(-1)
            assert not torch.equal(step.real_next_obs["state"][done], step.next_obs["state"][done])
            assert set(step.episodes["collision"].tolist()) <= {0.0, 1.0}
    assert ended > 0


def random_batch(n=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    obs = {k: torch.rand(n, *s, generator=g) for k, s in NAV.items()}
    nxt = {k: torch.rand(n, *s, generator=g) for k, s in NAV.items()}
    from safenav.common.buffer import Batch

    return Batch(obs, torch.rand(n, 3, generator=g) * 2 - 1, torch.randn(n, generator=g),
                 (torch.rand(n, generator=g) < 0.3).float(), nxt, (torch.rand(n, generator=g) < 0.2).float())  # fmt: skip


@pytest.mark.parametrize("shared", [True, False])
def test_targets_hard_copied_then_polyak_averaged(shared):
    torch.manual_seed(0)
    agent = CSAC(
        NAV, 3, CSACConfig(tau=0.1, net=NetConfig(hidden=(32, 32), shared_extractor=shared))
    )
    for p, q in zip(agent._online, agent._target, strict=True):
        assert torch.equal(p, q)  # line 2: hard copy
    before = [p.detach().clone() for p in agent._target]
    metrics = agent.update(random_batch(), d_q=0.1)
    assert all(torch.isfinite(v) for v in metrics.values())
    for old, online, target in zip(before, agent._online, agent._target, strict=True):
        torch.testing.assert_close(target, 0.9 * old + 0.1 * online.detach())  # line 15


def test_actor_step_leaves_critics_and_shared_extractor_alone():
    torch.manual_seed(0)
    cfg = CSACConfig(reward_critic_lr=0.0, cost_critic_lr=0.0, actor_lr=1e-3, net=SMALL)
    agent = CSAC(NAV, 3, cfg)
    critics = [
        p.detach().clone() for m in (agent.qr, agent.qc, agent.encoder) for p in m.parameters()
    ]
    actor = [p.detach().clone() for p in agent.actor.parameters()]
    agent.update(random_batch(), d_q=0.1)
    after = [p for m in (agent.qr, agent.qc, agent.encoder) for p in m.parameters()]
    assert all(torch.equal(a, b) for a, b in zip(critics, after, strict=True))
    assert any(not torch.equal(a, b) for a, b in zip(actor, agent.actor.parameters(), strict=True))


def test_sac_has_no_cost_side_and_csac_lambda_moves():
    sac = CSAC(NAV, 3, CSACConfig(constrained=False, net=SMALL))
    assert sac.qc is None and sac.lagrange is None and sac.lam.item() == 0.0
    assert "losses/qc" not in sac.update(random_batch(), 0.0)
    csac = CSAC(NAV, 3, CSACConfig(lambda_lr=0.01, net=SMALL))
    m = csac.update(random_batch(), d_q=-1.0)  # any Q_C exceeds a negative threshold
    assert csac.lam.item() > 0.0 and "constraint/qc_pi" in m
    state = copy.deepcopy(csac.state_dict())
    clone = CSAC(NAV, 3, CSACConfig(lambda_lr=0.01, net=SMALL))
    clone.load_state_dict(state)
    clone.load_optimizer_state(csac.optimizer_state())
    assert clone.lam.item() == csac.lam.item()


def test_softplus_cost_critics_cannot_go_below_zero():
    """``cost_critic_output="softplus"``: however the weights move, Q_C >= 0 (online and target),
    and the update still fits it; the default is the paper's linear output."""
    assert not CSAC(NAV, 3, CSACConfig(net=SMALL)).qc.nonnegative
    torch.manual_seed(0)
    agent = CSAC(NAV, 3, CSACConfig(cost_critic_output="softplus", cost_critic_lr=1e-2, net=SMALL))
    assert agent.qc.nonnegative and agent.qc_target.nonnegative
    with torch.no_grad():  # drive the last layer's bias far below 0: a linear Q_C would be ~-100
        agent.qc.mlp.layers[-1].bias.fill_(-100.0)
    batch = random_batch()
    x = agent.encoder(batch.obs)
    assert (agent.qc(x, batch.actions) >= 0).all()
    agent.qc.mlp.layers[-1].bias.data.fill_(0.0)
    before = agent.qc(x, batch.actions).detach()
    for _ in range(20):
        agent.update(batch, d_q=0.1)
    after = agent.qc(agent.encoder(batch.obs), batch.actions).detach()
    assert (after >= 0).all() and not torch.equal(before, after)
    with pytest.raises(ValueError):
        CSACConfig(cost_critic_output="relu")
    with pytest.raises(ValueError, match="clipped"):
        QEnsemble(None, 3, 1, (4,), 2, "relu")


def test_clipped_cost_critics_read_max_q_0_and_train_the_linear_output():
    """``cost_critic_output="clipped"``: every reader sees ``max(Q_C, 0)`` (no actor gradient
    below 0), the loss the linear output, so a critic driven below 0 still learns."""
    torch.manual_seed(0)
    agent = CSAC(NAV, 3, CSACConfig(cost_critic_output="clipped", net=SMALL))
    assert agent.qc.nonnegative and agent.qc_target.output == "clipped"
    with torch.no_grad():
        agent.qc.mlp.layers[-1].bias.fill_(-100.0)
        agent.qc_target.mlp.layers[-1].bias.fill_(-100.0)
    batch = random_batch()
    x = agent.encoder(batch.obs).detach()
    action = batch.actions.clone().requires_grad_(True)
    q = agent.qc(x, action)
    assert (q == 0).all() and (agent.qc(x, batch.actions, raw=True) < -50).all()
    q.sum().backward()
    assert (action.grad == 0).all()  # the actor is not led further below 0
    before = agent.qc(x, batch.actions, raw=True).detach()
    agent.update(batch, d_q=0.1)  # targets >= cost >= 0: the raw output rises towards them
    assert (agent.qc(agent.encoder(batch.obs), batch.actions, raw=True) > before).all()


def test_a_cost_critic_driven_far_below_0_comes_back_clipped_but_not_through_softplus():
    """What killed the softplus cost critics on SafetyHopperVelocity-v5 (pre-activations -30 to
    -3,800 on every replayed transition): through ``softplus`` the gradient at such values is
    ~0, so targets of 1 never bring Q_C back from ~0; the ``clipped`` critic's loss trains the
    linear output and does."""
    g = torch.Generator().manual_seed(0)
    x, a = torch.randn(64, 8, generator=g), torch.rand(64, 2, generator=g) * 2 - 1
    values = {}
    for output in ("softplus", "clipped"):
        torch.manual_seed(0)
        q = QEnsemble(None, 8, 2, (16, 16), 2, output)
        with torch.no_grad():
            q.mlp.layers[-1].bias.fill_(-40.0)
        opt = torch.optim.Adam(q.parameters(), lr=3e-3)
        for _ in range(300):  # cost 1 in every step now
            loss = ((q(x, a, raw=True) - 1.0) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        values[output] = float(q(x, a).detach().mean())
    assert values["clipped"] > 0.5
    assert values["softplus"] < 1e-6


class DictCounterEnv(CounterEnv):
    """CounterEnv with a Dict observation (``t`` and a constant vector)."""

    observation_space = gym.spaces.Dict(
        {
            "t": gym.spaces.Box(-np.inf, np.inf, (1,), np.float32),
            "v": gym.spaces.Box(0, 1, (2, 2), np.float32),
        }
    )

    def reset(self, *, seed=None, options=None):
        obs, info = super().reset(seed=seed)
        return {"t": obs, "v": np.ones((2, 2), np.float32)}, info

    def step(self, action):
        obs, r, term, trunc, info = super().step(action)
        return {"t": obs, "v": np.ones((2, 2), np.float32)}, r, term, trunc, info


def test_dict_observation_env_final_obs_and_agent():
    env = TorchVecEnv(SyncVectorEnv([lambda: DictCounterEnv(True), lambda: DictCounterEnv(False)],
                                    autoreset_mode=AutoresetMode.SAME_STEP))  # fmt: skip
    assert env.obs_shapes == {"t": (1,), "v": (2, 2)}
    obs = env.reset(seed=0)
    for _ in range(3):
        step = env.step(torch.zeros(2, 1))
    assert step.real_next_obs["t"].flatten().tolist() == [3.0, 3.0]
    assert step.next_obs["t"].flatten().tolist() == [0.0, 0.0]
    agent = CSAC(env.obs_shapes, 1, CSACConfig(net=SMALL))
    assert agent.act(obs).shape == (2, 1)
    buf = ReplayBuffer(8, env.obs_shapes, 1)
    buf.add(obs, torch.zeros(2, 1), step.reward, step.cost, step.real_next_obs, step.terminated)
    assert all(torch.isfinite(v) for v in agent.update(buf.sample(4), 0.1).values())


def test_balanced_critic_losses_weigh_each_by_its_own_rms():
    """balance_critic_losses: L_R / sqrt(m_R) + L_C / sqrt(m_C) with running means m (first call:
    the losses themselves), kept in a checkpointed buffer; absent without the option."""
    assert not hasattr(CSAC(NAV, 3, CSACConfig(net=SMALL)), "critic_loss_scale")
    agent = CSAC(NAV, 3, CSACConfig(balance_critic_losses=True, net=SMALL))
    w = torch.tensor([1.0, 2.0], requires_grad=True)
    l_r, l_c = 400.0 * w[0] ** 2, 0.01 * w[1] ** 2  # losses 400 and 0.04: a 10^4 ratio
    agent._balanced(l_r, l_c).backward()
    expected = torch.tensor([800.0 / 20.0, 0.04 / 0.2])  # grad L / sqrt(L) at the first call
    torch.testing.assert_close(w.grad, expected)
    torch.testing.assert_close(agent.critic_loss_scale, torch.tensor([400.0, 0.04]))
    agent._balanced(torch.tensor(500.0), torch.tensor(0.14))
    torch.testing.assert_close(agent.critic_loss_scale, torch.tensor([401.0, 0.041]))
    metrics = agent.update(random_batch(), d_q=0.1)
    assert all(torch.isfinite(v) for v in metrics.values())
    clone = CSAC(NAV, 3, CSACConfig(balance_critic_losses=True, net=SMALL))
    clone.load_state_dict(agent.state_dict())
    assert torch.equal(clone.critic_loss_scale, agent.critic_loss_scale)
