"""CSAC's pure losses (Eqs. 5-11) against hand-computed values; the Lagrange multiplier's rule."""

from __future__ import annotations

import math

import pytest
import torch
from torch.distributions import Normal, TanhTransform, TransformedDistribution

from safenav.algos.losses import (
    actor_loss,
    alpha_loss,
    cost_target,
    critic_loss,
    lagrange_loss,
    reward_target,
)
from safenav.common.lagrange import Lagrange, PIDLagrange
from safenav.nn.networks import squashed_gaussian

T = torch.tensor


def test_reward_target_eq5_min_and_terminal_mask():
    # next_q (E=2, B=2): min over critics = [2, 1]
    y = reward_target(T([1.0, 0.5]), T([False, True]), T([[2.0, 5.0], [3.0, 1.0]]),
                      T([0.5, 0.2]), alpha=0.1, gamma=0.9)  # fmt: skip
    # y0 = 1 + 0.9 * (2 - 0.1 * 0.5) = 2.755; y1 is terminal: the reward alone
    torch.testing.assert_close(y, T([2.755, 0.5]))


def test_cost_target_eq6_uses_the_mean_not_the_min():
    next_q = T([[0.2, 0.4], [0.6, 0.8]])  # mean [0.4, 0.6], min [0.2, 0.4], max [0.6, 0.8]
    c, term = T([0.0, 1.0]), T([0.0, 0.0])
    torch.testing.assert_close(cost_target(c, term, next_q, 0.9), T([0.36, 1.54]))
    torch.testing.assert_close(cost_target(c, term, next_q, 0.9, reduce="min"), T([0.18, 1.36]))
    torch.testing.assert_close(cost_target(c, term, next_q, 0.9, reduce="max"), T([0.54, 1.72]))
    # terminal: the cost alone, no bootstrap
    torch.testing.assert_close(cost_target(c, T([1.0, 1.0]), next_q, 0.9), c)
    with pytest.raises(ValueError):
        cost_target(c, term, next_q, 0.9, reduce="median")


def test_reward_min_vs_cost_mean_asymmetry():
    """The same critic outputs give a min-based reward target and a mean-based cost target."""
    next_q = T([[1.0], [3.0]])
    zero = T([0.0])
    assert reward_target(zero, zero, next_q, zero, 0.0, 1.0).item() == pytest.approx(1.0)  # min
    assert cost_target(zero, zero, next_q, 1.0).item() == pytest.approx(2.0)  # mean


def test_critic_loss_eqs7_8_sum_of_per_critic_mse():
    # head 0: ((1-1)^2 + (2-1)^2) / 2 = 0.5; head 1: ((3-1)^2 + (4-1)^2) / 2 = 6.5
    assert critic_loss(T([[1.0, 2.0], [3.0, 4.0]]), T([1.0, 1.0])).item() == pytest.approx(7.0)


def test_critic_loss_does_not_differentiate_the_target():
    q = T([[1.0, 2.0]], requires_grad=True)
    y = T([0.0, 0.0], requires_grad=True)
    critic_loss(q, y).backward()
    assert y.grad is None
    torch.testing.assert_close(q.grad, T([[1.0, 2.0]]))  # d/dq mean((q - y)^2) = (q - y)


def test_actor_loss_eq9():
    log_prob = T([1.0, 2.0])
    q_r = T([[1.0, 4.0], [2.0, 3.0]])  # min [1, 3]
    q_c = T([[0.2, 0.4], [0.6, 0.0]])  # mean [0.4, 0.2]
    # sample 0: 0.5*1 - 1 + 2*0.4 = 0.3; sample 1: 0.5*2 - 3 + 2*0.2 = -1.6
    assert actor_loss(log_prob, q_r, 0.5, q_c, 2.0).item() == pytest.approx(-0.65)
    # SAC: no cost term
    assert actor_loss(log_prob, q_r, 0.5).item() == pytest.approx(-1.25)
    # lambda = 0 is SAC
    assert actor_loss(log_prob, q_r, 0.5, q_c, 0.0).item() == pytest.approx(-1.25)


def test_alpha_loss_eq10_value_and_direction():
    log_alpha = T(math.log(0.5), requires_grad=True)
    log_prob = T([1.0, -1.0])  # entropy estimate -E[log pi] = 0 > H_target = -3
    loss = alpha_loss(log_alpha, log_prob, target_entropy=-3.0)
    # -(0.5 * (1 - 3) + 0.5 * (-1 - 3)) / 2 = 1.5
    assert loss.item() == pytest.approx(1.5)
    loss.backward()
    assert log_alpha.grad.item() > 0  # descent lowers alpha: entropy is above its target


def test_lagrange_loss_eq11_value_and_direction():
    lam = T(2.0, requires_grad=True)
    loss = lagrange_loss(lam, T([0.1, 0.3]), d=0.1)  # E[Q_C] = 0.2 > d
    assert loss.item() == pytest.approx(2.0 * (0.1 - 0.2))
    loss.backward()
    assert lam.grad.item() == pytest.approx(-0.1)  # d - E[Q_C] < 0: descent raises lambda


def test_lagrange_rises_while_violated_falls_while_satisfied_never_negative():
    lag = Lagrange(init=0.0, lr=0.01)
    values = []
    for _ in range(50):  # E[Q_C] = 0.5 > d = 0.1: rises every step
        lag.update(torch.full((8,), 0.5), d=0.1)
        values.append(lag.value.item())
    assert all(b > a for a, b in zip(values, values[1:], strict=False))
    peak = values[-1]
    values = []
    for _ in range(500):  # E[Q_C] = 0.0 < d: falls, then sits at exactly 0
        lag.update(torch.zeros(8), d=0.1)
        values.append(lag.value.item())
    assert min(values) >= 0.0
    assert values[0] < peak
    assert all(b < a or b == 0.0 for a, b in zip(values, values[1:], strict=False))
    assert values[-1] == 0.0
    lag.update(torch.full((8,), 0.5), d=0.1)  # violated again: rises at once from 0
    assert lag.value.item() > 0.0


def test_lagrange_is_never_negative_from_any_start_and_respects_a_cap():
    lag = Lagrange(init=0.003, lr=0.01)
    for _ in range(30):
        lag.update(torch.zeros(4), d=1.0)
        assert lag.value.item() >= 0.0
    capped = Lagrange(init=0.0, lr=0.5, max_value=1.0)
    for _ in range(30):
        capped.update(torch.full((4,), 9.0), d=0.0)
    assert capped.value.item() == pytest.approx(1.0)
    with pytest.raises(ValueError):
        Lagrange(init=-1.0)


def pid_steps(pid, signals, d):
    """lambda after each of ``signals`` (each a batch of one)."""
    out = []
    for j in signals:
        pid.update(T([j]), d=d)
        out.append(pid.value.item())
    return out


def reference_pid(signals, d, kp, ki, kd, d_delay, ema, init=0.0, cap=None):
    """Stooke et al. 2020, Algorithm 2, written out in floats: the lambda after each signal."""
    integral, p, js, history, out = init, None, None, [], []
    for j in signals:
        e = j - d
        integral = max(0.0, integral + ki * e)
        p = e if p is None else ema * p + (1 - ema) * e
        js = j if js is None else ema * js + (1 - ema) * j
        history.append(js)
        oldest = history[-d_delay - 1] if len(history) > d_delay else history[0] if len(
            history) > 1 else js  # fmt: skip
        lam = max(0.0, kp * p + integral + kd * max(0.0, js - oldest))
        out.append(lam if cap is None else min(lam, cap))
    return out


@pytest.mark.parametrize("gains", [(0.0, 0.1, 0.0), (2.0, 0.0, 0.0), (0.0, 0.0, 3.0),
                                   (1.0, 0.05, 2.0)])  # fmt: skip
def test_pid_lagrange_follows_algorithm_2(gains):
    kp, ki, kd = gains
    signals = [0.5, 0.9, 1.4, 1.2, 0.3, 0.1, 0.0, 0.8, 2.0, 1.9, 0.2, 0.0]
    pid = PIDLagrange(kp, ki, kd, d_delay=3, ema=0.6)
    got = pid_steps(pid, signals, d=0.7)
    want = reference_pid(signals, 0.7, kp, ki, kd, d_delay=3, ema=0.6)
    assert got == pytest.approx(want, abs=1e-6)
    assert min(got) >= 0.0


def test_pid_lagrange_answers_a_violation_at_once_where_adam_creeps():
    """The proportional term: one violated step moves lambda by kp * e at once; the gradient
    step of Eq. 11 by about its learning rate. Met again, the proportional term pulls it back."""
    pid, adam = PIDLagrange(kp=1.0, ki=1e-3, kd=0.0, d_delay=10, ema=0.0), Lagrange(lr=1e-3)
    for lag in (pid, adam):
        lag.update(T([3.0]), d=1.0)
    assert pid.value.item() == pytest.approx(2.0 + 2e-3)
    assert adam.value.item() == pytest.approx(1e-3, rel=0.01)
    pid.update(T([0.0]), d=1.0)  # met by 1: kp * -1 + the integral 1e-3, projected to 0
    assert pid.value.item() == 0.0 and pid.integral.item() == pytest.approx(1e-3)


def test_pid_lagrange_derivative_only_on_a_rising_signal_and_a_cap():
    pid = PIDLagrange(kp=0.0, ki=0.0, kd=1.0, d_delay=2, ema=0.0)
    rising = pid_steps(pid, (1.0, 2.0, 4.0, 3.0), d=5.0)
    assert rising == pytest.approx([0.0, 1.0, 3.0, 1.0])  # J now minus J two steps back (or first)
    assert pid_steps(pid, (1.0, 0.5), d=5.0) == [0.0, 0.0]  # below 4.0 and 3.0: falling
    capped = PIDLagrange(kp=10.0, ki=1.0, kd=0.0, d_delay=1, ema=0.0, max_value=2.0)
    capped.update(T([9.0]), d=0.0)
    assert capped.value.item() == 2.0
    with pytest.raises(ValueError, match="constraint signal"):
        capped.update(T([float("nan")]), d=0.0)


def test_pid_lagrange_state_dict_resumes_the_controller_exactly():
    signals = torch.linspace(0.0, 3.0, 25).tolist()
    whole = PIDLagrange(kp=1.0, ki=0.1, kd=2.0, d_delay=4, ema=0.8)
    for j in signals:
        whole.update(T([j]), d=1.0)
    first = PIDLagrange(kp=1.0, ki=0.1, kd=2.0, d_delay=4, ema=0.8)
    for j in signals[:11]:
        first.update(T([j]), d=1.0)
    resumed = PIDLagrange(kp=1.0, ki=0.1, kd=2.0, d_delay=4, ema=0.8)
    resumed.load_state_dict(first.state_dict())
    for j in signals[11:]:
        resumed.update(T([j]), d=1.0)
    assert resumed.value.item() == whole.value.item()


def test_squashed_gaussian_log_prob_matches_torch_distributions():
    torch.manual_seed(0)
    mean, log_std = torch.randn(64, 3), torch.randn(64, 3).clamp(-2, 1)
    noise = torch.randn(64, 3)
    action, logp = squashed_gaussian(mean, log_std, noise)
    dist = TransformedDistribution(Normal(mean, log_std.exp()), [TanhTransform()])
    u = mean + log_std.exp() * noise
    ref = dist.log_prob(torch.tanh(u).clamp(-1 + 1e-6, 1 - 1e-6)).sum(-1)
    keep = u.abs().max(-1).values < 4  # away from tanh saturation, where the reference is inexact
    torch.testing.assert_close(logp[keep], ref[keep], atol=2e-3, rtol=1e-3)
    assert action.abs().max() <= 1.0
