"""Property tests (hypothesis): random valid configs and actions never break the simulator."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from safenav.envs.config import make_config
from safenav.envs.nav import SafeNavVectorEnv

configs = st.fixed_dictionaries(
    {
        "preset": st.sampled_from(["easy", "medium"]),
        "density": st.floats(0.0, 1.0),
        "v_max": st.floats(0.2, 5.0),
        "control_hz": st.sampled_from([5.0, 10.0, 20.0]),
        "max_episode_seconds": st.floats(2.0, 8.0),
        "terminate_on_collision": st.booleans(),
        "velocity_time_constant": st.floats(0.05, 1.0),
    }
)
# Extreme but finite actions: out-of-range values are clipped to [-1, 1].
actions = st.lists(
    st.tuples(
        *[st.one_of(st.floats(-1e6, 1e6), st.sampled_from([-1.0, 0.0, 1.0, 1e30, -1e30]))] * 3
    ),
    min_size=2,
    max_size=2,
)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cfg=configs, seed=st.integers(0, 2**31 - 1), acts=st.lists(actions, min_size=5, max_size=30))
def test_random_configs_and_actions_stay_finite(cfg, seed, acts):
    preset = cfg.pop("preset")
    env = SafeNavVectorEnv(2, preset=preset, output="torch", **cfg)
    obs, _ = env.reset(seed=seed)
    half = env.cfg.half
    for a in acts:
        obs, reward, term, trunc, info = env.step(np.asarray(a, dtype=np.float32))
        for key, value in obs.items():
            assert torch.isfinite(value).all(), key
        assert torch.isfinite(reward).all() and torch.isfinite(info["cost"]).all()
        assert set(info["cost"].unique().tolist()) <= {0.0, 1.0}
        # moving obstacles never leave the map
        active = env.dyn_pos[:, : env.n_dynamic]
        assert (active[..., :2].abs() <= half).all()
        assert (active[..., 2] >= 0).all()
        assert env.observation_space["lidar"].low.min() <= float(obs["lidar"].min())
        assert float(obs["lidar"].max()) <= 1.0


@settings(max_examples=10, deadline=None)
@given(preset=st.sampled_from(["easy", "medium", "paper"]), seed=st.integers(0, 10_000))
def test_every_episode_ends(preset, seed):
    """With any behaviour, the time limit ends an episode after ``max_episode_steps``."""
    env = SafeNavVectorEnv(3, preset=preset, output="torch", max_episode_seconds=3.0)
    env.reset(seed=seed)
    gen = torch.Generator().manual_seed(seed)
    ended = torch.zeros(3, dtype=torch.bool)
    for _ in range(env.cfg.max_episode_steps):
        _, _, term, trunc, _ = env.step(torch.rand(3, 3, generator=gen) * 2 - 1)
        ended |= term | trunc
    assert bool(ended.all())


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_actions_raise(bad):
    env = SafeNavVectorEnv(2, preset="easy")
    env.reset(seed=0)
    a = np.zeros((2, 3), dtype=np.float32)
    a[1, 2] = bad
    with pytest.raises(ValueError, match="NaN or Inf"):
        env.step(a)


@settings(max_examples=30, deadline=None)
@given(
    field=st.sampled_from(["v_max", "map_size", "control_hz", "lidar_range", "uav_radius"]),
    value=st.one_of(st.floats(max_value=0.0), st.just(float("nan")), st.just(float("inf"))),
)
def test_invalid_positive_fields_are_rejected(field, value):
    with pytest.raises(ValueError, match=field):
        make_config("easy", **{field: value})
