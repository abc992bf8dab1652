"""Constraint curriculum (paper III-C) on synthetic cost sequences; density curriculum; d scaling."""

from __future__ import annotations

import pytest

from safenav.common.curriculum import (
    ConstraintCurriculum,
    ConstraintCurriculumConfig,
    DensityCurriculum,
    DensityCurriculumConfig,
    MeasuredCostScale,
    episode_cost_to_q_scale,
)


def run_epochs(cur: ConstraintCurriculum, epoch_costs, episodes=4, epoch_steps=100):
    """Feed one epoch per entry (``episodes`` episodes of that cost) from the curriculum's current
    epoch on; return d after each, and the changes."""
    ds, changes = [], []
    for cost in epoch_costs:
        cur.observe([cost] * episodes)
        change = cur.step((cur.epoch + 1) * epoch_steps)
        changes.append(change)
        ds.append(cur.d)
    return ds, changes


def test_tightens_after_patience_epochs_below_d_until_d_min():
    cfg = ConstraintCurriculumConfig(
        d_init=0.4, d_min=0.1, factor=0.5, patience=2, epoch_steps=100, min_episodes=1
    )
    cur = ConstraintCurriculum(cfg)
    assert (cur.d, cur.stage_name) == (0.4, "exploration")
    #            above  below  below->tighten  above(reset)  below  below->tighten  stays
    costs = [0.5, 0.2, 0.3, 0.25, 0.1, 0.05, 0.0, 0.0, 0.0]
    ds, changes = run_epochs(cur, costs)
    assert ds == pytest.approx([0.4, 0.4, 0.2, 0.2, 0.2, 0.1, 0.1, 0.1, 0.1])
    assert [c is not None for c in changes] == [
        False,
        False,
        True,
        False,
        False,
        True,
        False,
        False,
        False,
    ]
    assert changes[2]["stage"] == "balanced" and changes[2]["d_old"] == pytest.approx(0.4)
    assert changes[5]["stage"] == "safety"
    assert cur.stage == 2
    assert [h["d"] for h in cur.history] == pytest.approx([0.2, 0.1])


def test_equal_to_d_is_not_below_and_resets_the_streak():
    cfg = ConstraintCurriculumConfig(
        d_init=0.4, d_min=0.1, factor=0.5, patience=2, epoch_steps=100, min_episodes=1
    )
    ds, _ = run_epochs(ConstraintCurriculum(cfg), [0.3, 0.4, 0.3, 0.3])
    assert ds == pytest.approx([0.4, 0.4, 0.4, 0.2])


def test_epochs_with_too_few_episodes_do_not_count():
    cfg = ConstraintCurriculumConfig(
        d_init=0.4, d_min=0.1, factor=0.5, patience=2, epoch_steps=100, min_episodes=5
    )
    cur = ConstraintCurriculum(cfg)
    ds, _ = run_epochs(cur, [0.0, 0.0, 0.0], episodes=3)
    assert ds == pytest.approx([0.4, 0.4, 0.4])
    run_epochs(cur, [0.0, 0.0], episodes=5)  # epochs 4 and 5 count
    assert cur.d == pytest.approx(0.2)


def test_several_epochs_closed_in_one_call():
    cfg = ConstraintCurriculumConfig(
        d_init=0.4, d_min=0.1, factor=0.5, patience=1, epoch_steps=100, min_episodes=1
    )
    cur = ConstraintCurriculum(cfg)
    cur.observe([0.0] * 4)
    cur.step(250)  # closes epochs 1 and 2; the second has no episodes -> streak reset
    assert cur.epoch == 2 and cur.d == pytest.approx(0.2)


def test_disabled_fixes_d_at_d_min_and_state_round_trips():
    cfg = ConstraintCurriculumConfig(
        enabled=False, d_init=0.4, d_min=0.1, epoch_steps=100, min_episodes=1
    )
    cur = ConstraintCurriculum(cfg)
    ds, _ = run_epochs(cur, [0.0] * 5)
    assert ds == pytest.approx([0.1] * 5) and cur.stage_name == "safety"
    live = ConstraintCurriculum(ConstraintCurriculumConfig(d_init=0.4, d_min=0.1, factor=0.5, patience=2,
                                                           epoch_steps=100, min_episodes=1))  # fmt: skip
    run_epochs(live, [0.0, 0.0, 0.0])
    clone = ConstraintCurriculum(live.cfg)
    clone.load_state_dict(live.state_dict())
    assert clone.state_dict() == live.state_dict()


def test_config_validation():
    with pytest.raises(ValueError):
        ConstraintCurriculumConfig(d_init=0.1, d_min=0.2)
    with pytest.raises(ValueError):
        ConstraintCurriculumConfig(factor=1.0)


def test_episode_budget_to_q_scale():
    # brute force: cost d/T at every step of a T-step episode, discounted value averaged over states
    for d, gamma, horizon in ((0.3, 0.99, 300), (4.0, 0.99, 20), (1.0, 0.9, 7)):
        rate = d / horizon
        values = [sum(rate * gamma**k for k in range(r)) for r in range(1, horizon + 1)]
        assert episode_cost_to_q_scale(d, gamma, horizon) == pytest.approx(sum(values) / horizon)
    assert episode_cost_to_q_scale(0.3, 1.0, 300) == pytest.approx(0.3 * 301 / 600)
    # a long horizon: the stationary rate / (1 - gamma)
    assert episode_cost_to_q_scale(1.0, 0.99, 100_000) == pytest.approx(1e-5 / 0.01, rel=1e-3)


def test_measured_cost_scale_holds_the_episode_cost_at_d():
    scale = MeasuredCostScale(fallback=0.14, span_episodes=4, span_updates=4, min_episodes=4)
    scale.observe_q(0.03)
    scale.observe_episodes([1.0, 0.0, 0.0])
    assert scale.d_q(0.5) == pytest.approx(0.5 * 0.14)  # too few episodes: the modelled mapping
    scale.observe_episodes([0.0])  # 4 episodes, mean cost 0.25; E[Q_C] 0.03: rho = 0.12
    assert scale.ratio == pytest.approx(0.12)
    # so E[Q_C] = d_Q at d = 0.25 is the measured E[Q_C] when episodes cost 0.25 on average
    assert scale.d_q(0.25) == pytest.approx(0.03)
    # moving means after `span` observations: old values fade with weight 1 / span
    for _ in range(50):
        scale.observe_q(0.01)
        scale.observe_episodes([0.5])
    assert scale.ratio == pytest.approx(0.02, rel=1e-3)
    # no cost to measure against: the last ratio stays; NaN measurements are ignored
    for _ in range(50):
        scale.observe_episodes([0.0])
        scale.observe_q(float("nan"))
    assert scale.ratio == pytest.approx(0.02, rel=1e-3)
    # a cost critic sliding below its floor, read at every step as training does: the ratio
    # follows it down to fallback / BAND, never to 0 (d_Q = 0 made every Q_C a violation)
    assert 0.14 / MeasuredCostScale.BAND < 0.02
    ratios = []
    for k in range(200):
        scale.observe_episodes([0.5])
        scale.observe_q(0.01 - 0.001 * k)
        ratios.append(scale.ratio)
    assert scale.q_mean < 0 and min(ratios) == pytest.approx(0.14 / MeasuredCostScale.BAND)
    state = scale.state_dict()
    # and a checkpoint whose kept ratio is 0 (written before the band) resumes at the band's edge
    restored = MeasuredCostScale(fallback=0.14, span_episodes=4, span_updates=4, min_episodes=4)
    restored.load_state_dict({**state, "last": 0.0})
    assert restored.ratio == pytest.approx(0.014)
    for _ in range(50):  # a sane critic again: the measured ratio comes back
        scale.observe_episodes([0.5])
        scale.observe_q(0.01)
    assert scale.ratio == pytest.approx(0.02, rel=1e-3)
    restored = MeasuredCostScale(fallback=0.14, span_episodes=4, span_updates=4, min_episodes=4)
    restored.load_state_dict(scale.state_dict())
    assert restored.state_dict() == scale.state_dict() and restored.ratio == scale.ratio
    with pytest.raises(ValueError):
        MeasuredCostScale(fallback=0.0)


def test_density_linear_ramp():
    cfg = DensityCurriculumConfig(start=0.2, end=1.0, ramp_fraction=0.5, quantum=0.1)
    cur = DensityCurriculum(cfg, total_steps=1000)
    assert cur.density == 0.2
    assert cur.target(250) == pytest.approx(0.6)
    assert cur.target(500) == pytest.approx(1.0) and cur.target(900) == pytest.approx(1.0)
    assert cur.step(10) is None  # moved less than the quantum
    assert cur.step(150) == pytest.approx(0.44)
    assert cur.step(600) == pytest.approx(1.0)
    assert cur.step(700) is None
    off = DensityCurriculum(DensityCurriculumConfig(enabled=False, end=0.8), 1000)
    assert off.density == 0.8 and off.step(500) is None


def test_density_success_gated():
    cfg = DensityCurriculumConfig(start=0.2, end=0.5, mode="success", success_threshold=0.6,
                                  increment=0.1, epoch_steps=100, quantum=0.05)  # fmt: skip
    cur = DensityCurriculum(cfg, total_steps=10_000)
    cur.observe([1, 0, 0])  # 33 % success: no change
    assert cur.step(100) is None
    cur.observe([1, 1, 0, float("nan")])  # 67 %, the NaN (unknown) ignored
    assert cur.step(200) == pytest.approx(0.3)
    for k in range(3, 8):
        cur.observe([1, 1])
        cur.step(k * 100)
    assert cur.density == pytest.approx(0.5)  # capped at end
