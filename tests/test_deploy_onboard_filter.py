"""The planner filter on board (``safenav fly --planner-filter``): over one vehicle's odometry,
goal and observation it decides as ``PlannerFilter``'s observed view does on the env, its stall
handover counted in seconds; the runtime flies it (after its shield, if any)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from safenav.deploy.onboard_filter import OnboardFilter, VehicleView, check_planner_filter
from safenav.deploy.runtime import OnboardRuntime, RuntimeConfig
from safenav.envs import SafeNavVectorEnv, make_config
from safenav.envs.planner import PlannerFilter
from safenav.envs.scripted import go_to_goal
from safenav.errors import SafenavError

pytestmark = pytest.mark.usefixtures("one_thread")

STALL = (2.0, 2.0, 1.0)  # short windows: a hovering flight is handed over within the test


def _view(env, cfg, i: int = 0) -> VehicleView:
    return VehicleView.of(cfg, env.pos[i].numpy(), env.vel[i].numpy(), env.goal[i].numpy(),
                          float(env.yaw[i]), float(env.start[i, 2]),
                          float(env.steps[i]) * cfg.dt)  # fmt: skip


@pytest.mark.parametrize("flight,stall_test,short", [("straight", "tumbling", False),
                                                     ("hover", "tumbling", False),
                                                     ("hover", "sliding", False),
                                                     ("straight", "sliding", True),
                                                     ("hover", "sliding", True)])  # fmt: skip
def test_it_decides_as_the_envs_observed_view_bit_for_bit(flight, stall_test, short):
    """Straight at the goal (overrides) and hovering (stall handovers, either test; the planner
    with and without short moves): the same actions, step by step, as
    ``PlannerFilter(view="observation")`` given the env."""
    cfg = make_config("paper", static_tracked=6)
    env = SafeNavVectorEnv(1, config=cfg, output="torch", autoreset_mode="Disabled")
    obs, _ = env.reset(seed=12345)
    on_env = PlannerFilter(view="observation", stall=STALL, stall_test=stall_test,
                           short_moves=short)  # fmt: skip
    on_board = OnboardFilter(stall=STALL, stall_test=stall_test, short_moves=short)
    for _ in range(80):
        action = go_to_goal(obs) if flight == "straight" else torch.zeros(1, 3)
        expected = on_env(env, obs, action.clone())
        got = on_board(_view(env, cfg), obs, action.clone())
        assert torch.equal(got, expected)
        assert bool(on_board.overridden[0]) == bool(on_env.overridden[0])
        obs, _, term, trunc, _ = env.step(expected)
        if bool(term[0] or trunc[0]):
            break
    assert on_board.overrides == on_env.overrides > 0
    assert on_board.handovers == on_env.handovers
    # (with short moves the straight flight is handed over too, in these 2 s windows)
    assert (on_board.handovers > 0) == (flight == "hover") or short


def test_a_new_goal_starts_a_new_flight():
    """Hovering hands over after the stall window; a new goal (its clock from 0) starts the
    window anew: no handover until it has passed again."""
    cfg = make_config("easy", static_tracked=6)
    env = SafeNavVectorEnv(1, config=cfg, output="torch", autoreset_mode="Disabled")
    obs, _ = env.reset(seed=12345)
    the_filter = OnboardFilter(stall=STALL)

    def hover(goal_shift: float, seconds: float) -> int:
        before = the_filter.handovers
        for t in range(round(seconds / cfg.dt)):
            view = _view(env, cfg)
            view.goal, view.time = view.goal + goal_shift, t * cfg.dt
            the_filter(view, obs, torch.zeros(1, 3))
        return the_filter.handovers - before

    assert hover(0.0, 2.5) > 0  # stalled 2 s: handed over
    assert hover(1.0, 1.9) == 0  # a new goal: a new window
    assert hover(1.0, 2.5) > 0


def test_the_runtime_flies_it():
    """Given the env's map and state each step, the runtime's setpoints behind the filter are the
    env's filter's actions (a near-tie of the float64 odometry may fall the other way now and
    then), its ``filtered`` flag the filter's override."""
    cfg = make_config("paper", static_tracked=6, static_source="map", num_dynamic=0)
    env = SafeNavVectorEnv(1, config=cfg, output="torch", autoreset_mode="Disabled")
    obs, _ = env.reset(seed=12345)
    on_env = PlannerFilter(view="observation")
    wanted, now = [np.zeros((1, 3), np.float32)], [0.0]
    rt = OnboardRuntime(lambda *arrays: wanted[0], cfg,
                        config=RuntimeConfig(require_tracker=False, planner_filter=True),
                        clock=lambda: now[0])  # fmt: skip
    g2 = env.grid.size**2
    rows = flips = apart = filtered = 0
    for _ in range(150):
        a = go_to_goal(obs).clamp(-1.0, 1.0)
        expected = on_env(env, obs, a.clone())
        now[0] = float(env.steps[0]) * cfg.dt
        w = int(env.world_idx[0])
        rt.map.cast_map = env.heights[w * g2 : (w + 1) * g2].clone()
        rt.update_points(np.zeros((0, 3)))
        rt.update_state(env.pos[0].numpy(), env.vel[0].numpy())
        if int(env.steps[0]) == 0:
            rt.set_goal(env.goal[0].numpy(), start=env.start[0].numpy())
        wanted[0] = a.numpy()
        sp = rt.step()
        assert not sp.hover, sp.reason
        assert "filter" in sp.timings_ms
        filtered += int(sp.filtered)
        flips += int(sp.filtered != bool(on_env.overridden[0]))
        apart += int(np.abs(sp.action - expected[0].numpy()).max() > 1e-3)
        rows += 1
        obs, _, term, trunc, _ = env.step(expected)
        if bool(term[0] or trunc[0]):
            break
    assert filtered > 5, filtered
    assert flips <= 0.05 * rows and apart <= 0.05 * rows, (flips, apart, filtered, rows)


def test_it_needs_the_policys_pillar_list():
    with pytest.raises(ValueError, match="static_tracked"):
        OnboardRuntime(lambda *a: np.zeros((1, 3), np.float32), make_config("easy"),
                       config=RuntimeConfig(planner_filter=True))  # fmt: skip
    with pytest.raises(SafenavError, match="--planner-filter"):
        check_planner_filter(True, make_config("easy"), "policy.onnx")
    check_planner_filter(False, make_config("easy"), "policy.onnx")  # no filter asked: fine
    check_planner_filter(True, make_config("easy", static_tracked=4), "policy.onnx")
    assert RuntimeConfig.for_flight(
        make_config("easy"), 0, 20.0, planner_filter=True
    ).planner_filter


def test_the_same_goal_flown_again_is_a_new_flight():
    """A handover left from a stalled flight does not carry into the next flight to the same goal
    (``OnboardRuntime.set_goal`` calls ``new_flight``; its clock restarts)."""
    cfg = make_config("easy", static_tracked=6)
    env = SafeNavVectorEnv(1, config=cfg, output="torch", autoreset_mode="Disabled")
    obs, _ = env.reset(seed=12345)
    the_filter = OnboardFilter(stall=STALL)

    def hover(seconds: float) -> int:
        before = the_filter.handovers
        for t in range(round(seconds / cfg.dt)):
            view = _view(env, cfg)
            view.time = t * cfg.dt
            the_filter(view, obs, torch.zeros(1, 3))
        return the_filter.handovers - before

    assert hover(2.5) > 0  # its handover runs to 3 s of that flight's clock
    the_filter.new_flight()
    assert hover(1.9) == 0
    config = RuntimeConfig(require_tracker=False, planner_filter=True)
    rt = OnboardRuntime(lambda *a: np.zeros((1, 3), np.float32), cfg, config=config)
    rt.update_state([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    rt._filter._goals = torch.zeros(1, 3)
    rt.set_goal([0.0, 5.0, 1.0])
    assert rt._filter._goals is None and rt._flight_t0 is None
