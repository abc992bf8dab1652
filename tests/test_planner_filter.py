"""``PlannerFilter``, the model-predictive safety filter (beyond the paper): the policy's action
flies bit for bit where a way out is left after it, the planner's choice where not, and a policy
that flies straight into the obstacles stops crashing behind it."""

from __future__ import annotations

import pytest
import torch

from safenav.envs.config import make_config
from safenav.envs.dynamics import goal_frame_to_world
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.planner import PlannerFilter, to_action
from safenav.envs.scripted import go_to_goal
from safenav.experiments.evaluate import evaluate


def _env(n: int = 16, **overrides) -> tuple[SafeNavVectorEnv, dict]:
    env = SafeNavVectorEnv(n, config=make_config("easy", **overrides), output="torch",
                           autoreset_mode="Disabled")  # fmt: skip
    obs, _ = env.reset(seed=12345)
    return env, obs


def test_it_keeps_safe_actions_bit_for_bit_and_replaces_the_others_by_a_planner_command():
    torch.manual_seed(0)
    env, obs = _env()
    filt = PlannerFilter()
    kept_some_overrode_some = False
    for _ in range(40):
        action = torch.rand(env.num_envs, 3) * 2 - 1
        out = filt(env, obs, action)
        kept = ~filt.overridden
        assert torch.equal(out[kept], action[kept])
        ids = filt.overridden.nonzero().squeeze(-1)
        if len(ids):
            kept_some_overrode_some |= bool(kept.any())
            flown = goal_frame_to_world(
                out[ids] * env.cfg.v_max, env.cos_yaw[ids], env.sin_yaw[ids]
            )
            cmds = filt.candidates(obs, env, ids)  # one of the planner's commands, as applied
            assert bool(((cmds - flown[:, None]).norm(dim=-1).amin(-1) < 1e-5).all())
        obs, *_ = env.step(out)
    assert kept_some_overrode_some and filt.steps > 0 and 0 < filt.overrides < filt.steps


def test_a_hover_in_open_space_is_left_alone():
    env, obs = _env(8, num_static=0, num_dynamic=0)
    filt = PlannerFilter()
    hover = to_action(torch.zeros(8, 3), env.cos_yaw, env.sin_yaw, env.cfg.v_max)
    for _ in range(5):
        out = filt(env, obs, hover)
        assert torch.equal(out, hover) and not filt.overridden.any()
        obs, *_ = env.step(out)
    assert filt.overrides == 0 and filt.steps == 40


def test_straight_to_the_goal_stops_crashing_behind_it():
    torch.set_num_threads(1)
    cfg = make_config("easy")
    straight = evaluate(go_to_goal, cfg, env_seed=12345, episodes=16)
    filt = PlannerFilter()
    filtered = evaluate(go_to_goal, cfg, env_seed=12345, episodes=16, shield=filt)
    assert straight["collision_rate"] >= 0.5
    assert filtered["collision_rate"] <= 0.1 and filtered["success_rate"] >= 0.8
    assert 0 < filt.overrides < filt.steps  # the straight flight flies where it can


@pytest.mark.parametrize("hold", [0, 20])
def test_hold_must_leave_room_for_a_way_out(hold):
    with pytest.raises(ValueError, match="hold"):
        PlannerFilter(hold=hold)


@pytest.mark.long
def test_eval_and_render_fly_behind_it(tmp_path, capsys):
    import json

    from conftest import run_cli

    out = tmp_path / "eval.json"
    code, _, err = run_cli(capsys, ["eval", "--policy", "straight", "--preset", "easy",
                                    "--env-seed", "12345", "--episodes", "4", "--planner-filter",
                                    "--planner-filter-view", "simulator",
                                    "--json", str(out)])  # fmt: skip
    assert code == 0, err
    result = json.loads(out.read_text())
    assert result["planner_filter"] is True
    assert 0 < result["planner_filter_override_share"] < 1 and result["collision_rate"] == 0
    assert 0 <= result["planner_filter_handover_share"] <= result["planner_filter_override_share"]
    gif = tmp_path / "ep.gif"
    code, printed, err = run_cli(capsys, ["render", "--policy", "straight", "--preset", "easy",
                                          "--env-seed", "12345", "--episode", "1",
                                          "--planner-filter", "--planner-filter-view", "simulator",
                                          "--out", str(gif)])  # fmt: skip
    assert code == 0, err
    assert gif.stat().st_size > 0 and "'collision': 0.0" in printed


def test_the_observed_view_is_the_simulators_pillars_and_movers():
    """``observed_scene`` rebuilds from the observation alone the pillars (centre, half side,
    top) and the tracked movers (centre, velocity, size) the simulator holds."""
    torch.manual_seed(0)
    env = SafeNavVectorEnv(6, config=make_config("paper", static_tracked=10), output="torch",
                           autoreset_mode="Disabled")  # fmt: skip
    obs, _ = env.reset(seed=12345)
    for _ in range(10):
        obs, *_ = env.step(torch.rand(6, 3) * 2 - 1)
    planner = PlannerFilter(view="observation")
    ids = torch.arange(6)
    scene = planner.observed_scene(obs, env, ids)
    w = env.world_idx
    present = scene["ph"] > -1e3
    assert present.any()
    for i in range(6):
        xy, half = env.pillar_xy[w[i], : env.n_static], env.pillar_half[w[i], : env.n_static]
        top = env.pillar_height[w[i], : env.n_static]
        for j in present[i].nonzero().squeeze(-1):
            match = (xy - scene["pxy"][i, j]).norm(dim=-1).argmin()
            assert (xy[match] - scene["pxy"][i, j]).norm() < 1e-4
            assert abs(half[match] - scene["phalf"][i, j]) < 1e-5
            assert abs(top[match] - scene["ph"][i, j]) < 1e-4
    seen = scene["future"][0, ..., 0] < 1e3
    assert seen.any()
    step = env.cfg.dt * env.dyn_vel[w]  # (n, D, 3): the constant-velocity forecast's first step
    for i in range(6):
        truth = env.dyn_pos[w[i]] + step[i]
        for j in seen[i].nonzero().squeeze(-1):
            got = scene["future"][0, i, j]
            d = (truth[:, :2] - got[:2]).norm(dim=-1)
            match = d.argmin()
            assert d[match] < 1e-4
            assert abs(env.dyn_width[w[i], match] - scene["width"][i, 0, j]) < 1e-5
            cuboid = bool(env.dyn_is_cuboid[w[i], match])
            assert cuboid == bool(scene["cuboid"][i, 0, j])
            if cuboid:  # a standing cylinder's height is its own, not its centre's
                assert abs(truth[match, 2] - got[2]) < 1e-4


def test_the_observed_view_needs_the_pillar_list():
    env, obs = _env(2)
    with pytest.raises(ValueError, match="static_tracked"):
        PlannerFilter(view="observation")(env, obs, torch.zeros(2, 3))
    with pytest.raises(ValueError, match="view"):
        PlannerFilter(view="lidar")


@pytest.mark.parametrize("stall_test", ["sliding", "tumbling"])
def test_a_stalled_flight_is_handed_to_the_planner_for_a_while(stall_test):
    env, obs = _env(4, num_static=0, num_dynamic=0)
    # < 1 m nearer in 2 s: the planner flies 1 s
    filt = PlannerFilter(stall=(2.0, 1.0, 1.0), stall_test=stall_test)
    hover = to_action(torch.zeros(4, 3), env.cos_yaw, env.sin_yaw, env.cfg.v_max)
    start = (env.goal - env.pos).norm(dim=-1)
    handed = []
    for _ in range(35):
        out = filt(env, obs, hover)
        handed.append(filt.overridden.clone())
        obs, *_ = env.step(out)
    handed = torch.stack(handed)  # (35, 4)
    # hovers for 2 s (20 steps), the planner flies steps 21-30, then the policy hovers again
    assert not handed[:20].any() and handed[20:30].all() and not handed[30:].any()
    assert filt.handovers == filt.overrides == 40
    assert bool(((env.goal - env.pos).norm(dim=-1) < start - 1.0).all())


def _first_handover(stall_test: str) -> tuple[int, torch.Tensor]:
    """Fly 1 s at the goal, then hover, behind a (2 s, 1 m, 1 s) stall handover: the step of the
    first handover (the same in every env) and which steps were handed over."""
    env, obs = _env(4, num_static=0, num_dynamic=0)
    filt = PlannerFilter(stall=(2.0, 1.0, 1.0), stall_test=stall_test)
    to_goal = env.goal - env.pos
    go = to_action(to_goal / to_goal.norm(dim=-1, keepdim=True) * env.cfg.v_max, env.cos_yaw,
                   env.sin_yaw, env.cfg.v_max)  # fmt: skip
    hover = torch.zeros_like(go)
    handed = []
    for step in range(80):
        out = filt(env, obs, go if step < 10 else hover)
        handed.append(filt.overridden.clone())
        obs, *_ = env.step(out)
    handed = torch.stack(handed)  # (80, 4)
    first = handed.any(-1).nonzero()[0].item()
    assert bool(handed[first : first + 10].all()) and not handed[first + 10 : first + 20].any()
    return first, handed


def test_a_sliding_stall_test_hands_a_dither_over_sooner():
    tumbling, _ = _first_handover("tumbling")
    sliding, handed = _first_handover("sliding")
    # the first window (0-2 s) holds the 1 s of flight: the tumbling test waits for the second
    assert tumbling == 40 and 20 < sliding < 40
    # after a handover, a full window of the policy's flight before the next test
    again = handed[sliding + 10 :].any(-1).nonzero()
    assert len(again) == 0 or again[0].item() >= 20


def test_stall_settings_are_checked():
    with pytest.raises(ValueError, match="stall"):
        PlannerFilter(stall=(10.0, 0.0, 5.0))
    with pytest.raises(ValueError, match="stall_test"):
        PlannerFilter(stall=(10.0, 2.0, 5.0), stall_test="hourly")


def test_the_observed_view_refuses_a_flight_without_the_pillar_list(tmp_path, capsys):
    from conftest import run_cli

    for verb in (["eval", "--episodes", "2"], ["render", "--out", str(tmp_path / "e.gif")]):
        code, _, err = run_cli(capsys, [*verb, "--policy", "straight", "--preset", "easy",
                                        "--planner-filter"])  # fmt: skip
        assert code != 0 and "--planner-filter-view simulator" in err, (verb, err)


def test_a_spec_round_trips_and_refuses_an_unknown_view():
    from safenav.envs.planner import filter_from_spec, filter_spec

    # the adopted filter (docs/csac-v1.md, "A sliding stall test")
    assert filter_spec() == {"view": "observation", "stall": [5.0, 1.0, 5.0],
                             "stall_test": "sliding", "short_moves": True,
                             "braking_cap": False}  # fmt: skip
    the_filter = filter_from_spec(filter_spec())
    assert the_filter.view == "observation" and the_filter.stall == (5.0, 1.0, 5.0)
    assert the_filter.stall_test == "sliding"
    assert filter_from_spec(filter_spec("simulator", None)).stall is None
    tumbling = filter_spec(stall_test="tumbling")
    assert filter_from_spec(tumbling).stall_test == "tumbling"
    # a policy's record from before the sliding test (no "stall_test") flies as it was reported
    old = filter_from_spec({"view": "observation", "stall": [10.0, 2.0, 5.0]})
    assert old.stall == (10.0, 2.0, 5.0) and old.stall_test == "tumbling"
    with pytest.raises(ValueError, match="view"):
        filter_spec("camera")
    for bad in (
        {"view": "camera", "stall": None},
        {"view": "observation", "stall": [1.0]},
        {"view": "observation", "stall": None, "stall_test": "hourly"},
        "observation",
    ):
        with pytest.raises(ValueError):
            filter_from_spec(bad)


def test_one_predicate_says_whether_a_config_observes_the_pillar_list():
    from safenav.envs.planner import observes_pillars

    assert observes_pillars(make_config("paper", static_tracked=10))
    assert not observes_pillars(make_config("paper"))
    assert not observes_pillars(None)  # a Gymnasium task that is not SafeNav


def _train_with_filter(run_dir, *env_kwargs: str) -> list[str]:
    from conftest import PAPER_OBSERVATION

    return ["train", *PAPER_OBSERVATION, "--flight-filter", "--preset", "easy", "--seed", "1",
            "--num-envs", "4", "--total-steps", "200", "--csac.learning-starts", "64",
            "--csac.batch-size", "16", "--csac.net.hidden", "32", "32", "--eval-every", "0",
            "--no-progress", "--no-tensorboard", "--torch-threads", "1", "--run-dir", str(run_dir),
            *(["--env-kwargs", *env_kwargs] if env_kwargs else [])]  # fmt: skip


@pytest.mark.long
def test_a_run_trained_with_flight_filter_is_reported_and_evaluated_behind_it(tmp_path, capsys):
    """``safenav train --flight-filter``: the policy records the filter, its report flies the test
    scenario and held-out maps behind it (and the test once more without), and ``safenav eval``
    flies it behind the filter unless ``--no-planner-filter``."""
    import json

    from conftest import run_cli
    from safenav.envs.planner import filter_spec
    from safenav.experiments.selection import report_policy

    run = tmp_path / "run"
    code, _, err = run_cli(capsys, _train_with_filter(run, "static_tracked", "4"))
    assert code == 0, err
    policy = run / "checkpoint.pt"
    report = report_policy(policy, episodes=2, heldout=(2,))
    assert report["flight_filter"] == filter_spec()
    for flight in (report["test"], report["heldout"]["per_seed"][0], report["test_navrl_rule"]):
        assert 0 <= flight["planner_filter_override_share"] <= 1
    assert "planner_filter_override_share" not in report["test_without_filter"]
    for extra, expected in (([], True), (["--no-planner-filter"], False),
                            (["--planner-filter-view", "simulator"], True)):  # fmt: skip
        out = tmp_path / f"eval{len(extra)}.json"
        code, _, err = run_cli(capsys, ["eval", str(policy), "--env-seed", "12345", "--episodes",
                                        "2", *extra, "--json", str(out)])  # fmt: skip
        assert code == 0, err
        result = json.loads(out.read_text())
        assert result["planner_filter"] is expected, extra
        assert ("planner_filter_override_share" in result) is expected
        assert ("flies behind the planner filter" in err) is expected
        view = extra[-1] if len(extra) == 2 else "observation" if expected else None
        assert result.get("planner_filter_view") == view
        assert result.get("planner_filter_spec") == (filter_spec(view) if expected else None)


def test_flight_filter_needs_the_pillar_list_and_a_safenav_env(tmp_path, capsys):
    from conftest import run_cli
    from safenav.common.config import RunConfig

    code, _, err = run_cli(capsys, _train_with_filter(tmp_path / "run"))
    assert code != 0 and "static_tracked" in err, err
    with pytest.raises(ValueError, match="flight-filter"):
        RunConfig(env="Pendulum-v1", flight_filter=True)


@pytest.mark.parametrize("rule", ["body", "navrl"])
def test_a_graze_no_beam_reads_ends_an_episode_only_under_the_body_rule(rule):
    """Under NavRL's collision rule the env flies on after touching a pillar no beam reads: so
    does the planner (and the filter), rather than leaving the episode to the shield alone."""
    env, _ = _env(1, collision_rule=rule)
    w = int(env.world_idx[0])
    tallest = int(env.pillar_height[w, : env.n_static].argmax())
    env.pos[0, :2] = env.pillar_xy[w, tallest]  # inside the tallest pillar, well below its top
    env.pos[0, 2] = 1.0
    env.steps[0] = 5
    env._beam_reads_pillar = lambda ids: torch.zeros(len(ids), dtype=torch.bool)
    planner = PlannerFilter()
    planner._start(env)
    planner._update_finished(env)
    assert bool(planner.finished[0]) is (rule == "body")


def _pocket() -> tuple[SafeNavVectorEnv, dict]:
    """Env 0's UAV boxed in by four tall pillars 1 m from it on each side (none elsewhere): every
    command held 2 s collides but a hover."""
    env, obs = _env(2, num_dynamic=0)
    w, p, half = int(env.world_idx[0]), env.pos[0, :2], 0.5
    env.pillar_xy[w, : env.n_static] = 1e3
    for i, side in enumerate([(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)]):
        env.pillar_xy[w, i] = p + torch.tensor(side, dtype=p.dtype) * (1.0 + half)
        env.pillar_half[w, i], env.pillar_height[w, i] = half, 10.0
    return env, obs


def test_short_moves_take_the_planner_out_of_a_pocket_where_it_would_hover():
    env, obs = _pocket()
    filt = PlannerFilter()
    filt._start(env)
    ids = torch.tensor([0])
    scene, cmds = filt.scene(obs, env, ids), filt.candidates(obs, env, ids)
    assert torch.equal(filt.choose(scene, cmds), torch.zeros(1, 3))  # held 2 s: only a hover
    short = filt.short_move_candidates(env, ids)
    chosen = filt.choose(scene, cmds, short)
    assert chosen.norm() > 0.4 and bool((short[0] - chosen).norm(dim=-1).amin() < 1e-6)
    to_goal = env.goal[0, :2] - env.pos[0, :2]
    assert float(chosen[0, :2] @ to_goal) > 0  # a step towards the goal
    # each short move is held 0.5 s and then stopped: no collision in the pocket
    n, k = short.shape[:2]
    start = (scene["pos"][:, None].expand(n, k, 3).contiguous(),
             scene["vel"][:, None].expand(n, k, 3).contiguous())  # fmt: skip
    brief = filt.move_then_stop(scene, short, *start, 5)
    assert bool((brief["first_hit"] == filt.cfg.horizon + 1).all())
    assert float(brief["v"].norm(dim=-1).amax()) < 0.05  # stopped by the horizon's end


def test_short_moves_are_recorded_in_the_spec_only_where_set():
    from safenav.envs.planner import filter_from_spec, filter_spec

    assert "short_moves" not in filter_spec(short_moves=False)
    spec = filter_spec()  # adopted (docs/csac-v1.md, "Short moves for the filter's planner")
    assert spec["short_moves"] is True and filter_from_spec(spec).short_moves
    assert not filter_from_spec(filter_spec(short_moves=False)).short_moves
    assert not filter_from_spec({"view": "observation", "stall": None}).short_moves


def test_behind_the_adopted_filter_the_shield_flies_without_its_braking_cap():
    """``"braking_cap": false`` (adopted: docs/csac-v1.md, "The braking cap behind the filter")
    takes the cap off the flight shield before the filter, in the report and in ``safenav eval``
    / ``render`` unless a shield option is given; a record without it keeps the cap."""
    from types import SimpleNamespace

    from safenav.cli import ARGS
    from safenav.commands.eval import brake_under_filter, describe_filter
    from safenav.envs.planner import filter_from_spec, filter_spec, shield_under_filter
    from safenav.experiments.selection import own_shield

    assert "braking_cap" not in filter_spec(braking_cap=True)
    with pytest.raises(ValueError, match="braking_cap"):
        filter_from_spec({**filter_spec(), "braking_cap": "no"})
    shield = {"memory": 1, "map": True, "mover_margin": 0.3, "brake": True}
    assert shield_under_filter(shield, filter_spec()) == {**shield, "brake": False}
    assert shield_under_filter(shield, filter_spec(braking_cap=True)) == shield
    assert shield_under_filter(shield, None) == shield and shield["brake"] is True
    assert shield_under_filter(None, filter_spec()) is None
    policy = SimpleNamespace(meta={"flight_shield": shield, "flight_filter": filter_spec()})
    assert own_shield(policy).brake is True  # alone (the selection): the cap flies
    assert own_shield(policy, filter_spec()).brake is False
    assert "braking cap off" in describe_filter(filter_spec())
    for args, expected in (((), False), (("--shield-brake",), True)):
        token = ARGS.set(args)
        try:
            assert brake_under_filter(filter_spec(), True) is expected, args
            assert brake_under_filter(filter_spec(braking_cap=True), True) is True
            assert brake_under_filter(None, True) is True
        finally:
            ARGS.reset(token)


def test_a_flight_flies_the_filter_its_policy_records_unless_told_otherwise():
    """``safenav eval`` / ``render``: the recorded filter (a record from before the sliding test
    flies tumbling windows, as it was reported); ``--planner-filter`` the adopted one;
    ``--no-planner-filter`` none; an unreadable record is refused."""
    from types import SimpleNamespace

    from safenav.cli import ARGS
    from safenav.commands.eval import describe_filter, own_planner_filter
    from safenav.envs.planner import filter_spec
    from safenav.errors import SafenavError

    old = {"view": "observation", "stall": [10.0, 2.0, 5.0]}
    policy = SimpleNamespace(meta={"flight_filter": old})
    cases = [((), old), (("--planner-filter",), filter_spec()), (("--no-planner-filter",), None),
             (("--planner-filter-view", "simulator"), {**old, "view": "simulator"})]  # fmt: skip
    for args, expected in cases:
        token = ARGS.set(args)
        try:
            given = "--planner-filter" in args
            view = args[-1] if "--planner-filter-view" in args else "observation"
            assert own_planner_filter(policy, "p.pt", given, view) == expected, args
        finally:
            ARGS.reset(token)
    assert own_planner_filter(SimpleNamespace(meta={}), "p.pt", False, "observation") is None
    assert "under 2 m in 10 s tumbling" in describe_filter(old)
    token = ARGS.set(())
    try:
        with pytest.raises(SafenavError, match="--no-planner-filter"):
            own_planner_filter(SimpleNamespace(meta={"flight_filter": {"view": "x"}}), "p.pt",
                               False, "observation")  # fmt: skip
    finally:
        ARGS.reset(token)


def _cup() -> tuple[SafeNavVectorEnv, dict]:
    """Env 0's UAV at the arena's centre, its goal 8 m ahead (+x), inside a cup of tall pillars
    that opens away from the goal: a row across the way 2 m ahead (y from -3 to 3) and an arm
    back along each side (x from -1 to 2); no other pillar. The straight distance to the goal
    has its minimum at the cup's bottom."""
    env, obs = _env(2, num_dynamic=0, map_size=50.0, num_static=40)
    w, z = int(env.world_idx[0]), float(env.pos[0, 2])
    env.pos[0] = torch.tensor([0.0, 0.0, z])
    env.vel[0] = 0.0
    env.goal[0] = torch.tensor([8.0, 0.0, z])
    spots = [(2.0, 0.8 * k) for k in range(-4, 5)]
    spots += [(x, side * 3.2) for x in (-1.2, -0.4, 0.4, 1.2) for side in (-1, 1)]
    env.pillar_xy[w, : env.n_static] = 1e3
    for i, xy in enumerate(spots):
        env.pillar_xy[w, i] = torch.tensor(xy, dtype=env.pillar_xy.dtype)
        env.pillar_half[w, i], env.pillar_height[w, i] = 0.5, 10.0
    return env, obs


def _fly_the_cup(handover_map: bool, seconds: float = 40.0) -> torch.Tensor:
    """Hover behind a (1 s, 1 m, 3 s) stall handover in the cup; env 0's path (T, 3)."""
    env, obs = _cup()
    filt = PlannerFilter(stall=(1.0, 1.0, 3.0), stall_test="sliding", short_moves=True,
                         handover_map=handover_map)  # fmt: skip
    hover = torch.zeros(env.num_envs, 3)
    path = []
    for _ in range(int(seconds / env.cfg.dt)):
        obs, *_ = env.step(filt(env, obs, to_action(hover, env.cos_yaw, env.sin_yaw,
                                                     env.cfg.v_max)))  # fmt: skip
        path.append(env.pos[0].clone())
        if bool(filt.finished[0]):
            break
    return torch.stack(path)


def test_a_map_of_the_pillars_seen_takes_the_handover_out_of_a_cup():
    straight = _fly_the_cup(handover_map=False)
    # the straight distance's planner flies to the cup's bottom and stays in the cup
    assert float(straight[:, 0].amax()) < 2.0 and float(straight[:, 1].abs().amax()) < 3.2
    mapped = _fly_the_cup(handover_map=True)
    # around an arm and past the row: at the goal (the episode ends there)
    assert float((mapped[-1] - torch.tensor([8.0, 0.0, float(mapped[0, 2])])).norm()) < 1.0
    assert float(mapped[:, 0].amin()) < -1.2  # out by the cup's open end


def test_the_handover_map_is_recorded_in_the_spec_only_where_set():
    from safenav.envs.planner import filter_from_spec, filter_spec

    assert "handover_map" not in filter_spec()
    spec = filter_spec(handover_map=True)
    assert spec["handover_map"] is True and filter_from_spec(spec).handover_map
    assert not filter_from_spec(filter_spec()).handover_map
    with pytest.raises(ValueError, match="stall"):
        filter_spec(stall=None, handover_map=True)
    with pytest.raises(ValueError, match="stall"):
        PlannerFilter(handover_map=True)
    assert "handover_exit" not in filter_spec()
    spec = filter_spec(handover_map=True, handover_exit="nearer")
    assert spec["handover_exit"] == "nearer" and filter_from_spec(spec).handover_exit == "nearer"
    assert filter_from_spec(filter_spec()).handover_exit == "time"
    with pytest.raises(ValueError, match="handover_exit"):
        filter_spec(handover_exit="later")
    with pytest.raises(ValueError, match="stall"):
        PlannerFilter(handover_exit="nearer")


@pytest.mark.parametrize("exit_rule", ["time", "nearer"])
def test_a_handover_that_ends_nearer_goes_on_until_the_uav_is_nearer(exit_rule):
    env, obs = _env(4, num_static=0, num_dynamic=0)
    # < 1 m nearer in 2 s: the planner flies 0.5 s ("time"), or until 1 m nearer ("nearer")
    filt = PlannerFilter(stall=(2.0, 1.0, 0.5), stall_test="sliding", handover_exit=exit_rule)
    hover = to_action(torch.zeros(4, 3), env.cos_yaw, env.sin_yaw, env.cfg.v_max)
    handed, dist = [], []
    for _ in range(60):
        out = filt(env, obs, hover)
        handed.append(filt.overridden.clone())
        dist.append((env.goal - env.pos).norm(dim=-1))
        obs, *_ = env.step(out)
    handed, dist = torch.stack(handed), torch.stack(dist)  # (60, 4)
    first = int(handed.any(-1).nonzero()[0])
    length = int(handed[first:].all(-1).int().cumprod(0).sum())
    if exit_rule == "time":
        assert length == 5
    else:  # from a hover, 0.5 s of flight leaves it less than 1 m nearer: it goes on
        assert 5 < length <= 15
        assert bool((dist[first + length] <= dist[first] - 1.0).all())
        assert not handed[first + length : first + length + 20].any()  # a window before the next


def test_mover_turn_grows_each_movers_reach_over_the_first_seconds():
    """``OracleConfig.mover_turn``: a mover 1.6 m beside a hovering UAV, flying past it at
    1.3 m/s, never comes near under the constant-velocity forecast; allowed to turn for 0.5 s it
    may reach 0.65 m further, into the UAV's margin."""
    import dataclasses
    from types import SimpleNamespace

    from safenav.envs.planner import PLANNER_PILLARS, OraclePlanner

    cfg = make_config("paper")
    h = PLANNER_PILLARS.horizon
    t = torch.arange(1, h + 1, dtype=torch.float32)[:, None, None, None]
    mover = torch.tensor([0.0, 1.6, 1.0]) + t * cfg.dt * torch.tensor([1.3, 0.0, 0.0])
    scene = {"env": SimpleNamespace(cfg=cfg), "pxy": torch.zeros(1, 0, 2),
             "phalf": torch.zeros(1, 0), "ph": torch.zeros(1, 0), "nd": 1, "hits": None,
             "columns": None, "hit_r": None, "wall_seen": torch.zeros(1, 1, 4, dtype=torch.bool),
             "band": (torch.tensor([0.3]), torch.tensor([2.7])),
             "goal": torch.tensor([[20.0, 0.0, 1.0]]), "future": mover.expand(h, 1, 1, 3),
             "width": torch.tensor([[[0.4]]]), "cuboid": torch.tensor([[[False]]])}  # fmt: skip
    start = (torch.tensor([[[0.0, 0.0, 1.0]]]), torch.zeros(1, 1, 3))
    hover = torch.zeros(1, 1, 3)
    plain = OraclePlanner(PLANNER_PILLARS).simulate(scene, hover, *start)
    turning = OraclePlanner(dataclasses.replace(PLANNER_PILLARS, mover_turn=0.5)).simulate(
        scene, hover, *start
    )
    # clearance after the 0.2 m radius and the UAV's 0.3 m, at each step's forecast
    steps = torch.arange(1, h + 1, dtype=torch.float32)
    gap = torch.sqrt((1.3 * cfg.dt * steps) ** 2 + 1.6**2) - 0.2 - cfg.uav_radius
    assert float(plain["least"]) == pytest.approx(float(gap.min()), abs=1e-4)  # 1.105 m, at once
    assert float(plain["intrude"]) == 0.0  # beyond the 0.7 m margin
    reach = 1.3 * torch.clamp(steps * cfg.dt, max=0.5)
    assert float(turning["least"]) == pytest.approx(float((gap - reach).min()), abs=1e-4)
    assert float(turning["intrude"]) > 0.1  # 0.577 m at 0.5 s: inside the margin
