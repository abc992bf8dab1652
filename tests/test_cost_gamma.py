"""The cost critics' own discount (``--csac.cost-gamma``, beyond the paper): None is the paper's
single gamma, a value is refused outside (0, 1], and the cost critics converge to the fixed point
of Eq. 6 under that discount while the reward side keeps ``gamma``."""

from __future__ import annotations

import pytest
import torch

from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSAC
from safenav.common.buffer import ReplayBuffer
from safenav.common.curriculum import episode_cost_to_q_scale


def test_default_is_the_papers_single_discount_and_bad_values_are_refused():
    assert CSACConfig().cost_discount == CSACConfig().gamma == 0.99
    assert CSACConfig(gamma=0.98, cost_gamma=0.9).cost_discount == 0.9
    for bad in (0.0, -0.5, 1.5):
        with pytest.raises(ValueError, match="cost-gamma"):
            CSACConfig(cost_gamma=bad)


def fixed_point(cost_gamma: float | None) -> float:
    """Q_C after fitting a state that returns to itself with cost 1 at every step (never
    terminated): Eq. 6's fixed point is 1 / (1 - cost discount)."""
    cfg = CSACConfig(cost_gamma=cost_gamma, gamma=0.99, actor_lr=0.0, reward_critic_lr=0.0,
                     alpha_lr=0.0, lambda_lr=0.0, cost_critic_lr=3e-2, tau=0.05)  # fmt: skip
    torch.manual_seed(0)
    agent = CSAC({"x": (4,)}, 2, cfg)
    buf = ReplayBuffer(64, {"x": (4,)}, 2)
    x = torch.rand(64, 4)
    buf.add({"x": x}, torch.rand(64, 2) * 2 - 1, torch.zeros(64), torch.ones(64), {"x": x},
            torch.zeros(64))  # fmt: skip
    for _ in range(400):
        agent.update(buf.sample(64))
    with torch.no_grad():
        return float(agent.qc(x, buf.actions).mean())


@pytest.mark.long
def test_cost_critics_converge_under_their_own_discount():
    # 1 / (1 - 0.5) = 2; under the reward's 0.99 the same data would say 100
    assert fixed_point(0.5) == pytest.approx(2.0, abs=0.2)
    assert fixed_point(None) > 5.0


def test_the_budget_maps_onto_the_cost_critics_scale():
    """d on the Q_C scale (Eq. 11's threshold) uses the cost discount: a shorter horizon, a
    smaller threshold for the same episode budget."""
    assert episode_cost_to_q_scale(0.5, 0.9, 600) < episode_cost_to_q_scale(0.5, 0.99, 600)
