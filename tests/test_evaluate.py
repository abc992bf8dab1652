"""The evaluation protocol's metrics (safenav.experiments.evaluate)."""

from __future__ import annotations

import numpy as np

from safenav.envs import make_config
from safenav.envs.scripted import go_to_goal
from safenav.experiments.evaluate import evaluate


def test_outcomes_and_collision_kinds_add_up() -> None:
    """Every episode ends one way; every collision says what it hit, and the rates agree."""
    result = evaluate(go_to_goal, make_config("easy"), episodes=24)
    ep = {
        k: np.asarray(v) > 0.5
        for k, v in result["per_episode"].items()
        if k in ("success", "collision", "timeout", "hit_static", "hit_dynamic", "out_of_bounds")
    }
    assert (ep["success"].astype(int) + ep["collision"] + ep["timeout"] == 1).all()
    kinds = ep["hit_static"] | ep["hit_dynamic"] | ep["out_of_bounds"]
    assert (kinds == ep["collision"]).all()
    assert result["collision_static_rate"] == ep["hit_static"].mean()
    assert result["collision_dynamic_rate"] == ep["hit_dynamic"].mean()
    # Flying straight at the goal through a pillar field hits pillars.
    assert result["collision_static_rate"] > 0
    assert result["collision_rate"] <= (
        result["collision_static_rate"]
        + result["collision_dynamic_rate"]
        + result["collision_bounds_rate"]
        + 1e-9
    )
