"""The ``static`` observation entry (``EnvConfig.static_tracked``; beyond the paper): the nearest
pillars' geometry in the goal frame. Features on a hand-built map, the env's entry against them,
the default's absence, the extractor, training, evaluation and deployment (export, a runtime
step; the runtime's rows against the env's: tests/test_deploy_runtime.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from conftest import train_tiny_csac
from safenav.cli import main
from safenav.envs.config import STATIC_FEATURES, make_config, observation_shapes
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.sensors import (
    FAR_FOOTPRINT,
    HEIGHT_QUANTUM,
    dequantize_heights,
    map_footprints,
    pillar_clearance,
    pillar_clearances,
    quantize_heights,
    static_obstacle_features,
)
from safenav.envs.world import GridSpec, border_walls, height_map, world_from_obstacles


def _features(yaw: float, k: int = 3) -> torch.Tensor:
    pos = torch.tensor([[0.0, 0.0, 1.0]])
    xy = torch.tensor([[[2.0, 0.0], [0.0, 3.0], [10.0, 0.0]]])  # A, B, C (beyond range)
    half = torch.tensor([[0.2, 0.4, 0.2]])
    height = torch.tensor([[3.0, 0.5, 3.0]])
    return static_obstacle_features(pos, xy, half, height, torch.tensor([math.cos(yaw)]),
                                     torch.tensor([math.sin(yaw)]), k, 4.0)[0]  # fmt: skip


def test_rows_are_the_nearest_pillars_in_the_goal_frame():
    rows = _features(0.0)
    assert rows.shape == (3, STATIC_FEATURES)
    # A: 1.8 m ahead, 0.2 m half side, top 2 m above; B: its top 0.5 m below, 2.6 m to the left
    torch.testing.assert_close(rows[0], torch.tensor([0.45, 0.0, 0.5, 0.0, 0.5, 0.5, 1.0]))
    torch.testing.assert_close(rows[1], torch.tensor([0.0, 0.65, 0.0, 0.75, 1.0, -0.125, 1.0]))
    assert rows[2].eq(0).all()  # C lies beyond the 4 m range: a zero row
    # the goal frame: facing +y (yaw 90 degrees), A lies to the right (-y), B ahead
    turned = _features(math.pi / 2)
    torch.testing.assert_close(turned[0, :4], torch.tensor([0.0, -0.45, 0.0, -0.5]), atol=1e-6,
                               rtol=0)  # fmt: skip
    torch.testing.assert_close(turned[1, :4], torch.tensor([0.65, 0.0, 0.75, 0.0]), atol=1e-6,
                               rtol=0)  # fmt: skip
    assert _features(0.0, k=1).shape == (1, STATIC_FEATURES)  # fewer slots: the nearest only


def test_no_pillars_give_zero_rows():
    out = static_obstacle_features(torch.zeros(2, 3), torch.zeros(2, 0, 2), torch.zeros(2, 0),
                                   torch.zeros(2, 0), torch.ones(2), torch.zeros(2), 4, 4.0)  # fmt: skip
    assert out.shape == (2, 4, STATIC_FEATURES) and out.eq(0).all()


def test_default_observation_has_no_static_entry_and_bad_counts_are_refused():
    assert "static" not in observation_shapes(make_config("paper"))
    assert observation_shapes(make_config("paper", static_tracked=6))["static"] == (6, 7)
    for bad in (-1, 33, 2.5):
        with pytest.raises(ValueError, match="static_tracked"):
            make_config("paper", static_tracked=bad)


def test_env_entry_matches_the_pillars_of_its_map():
    cfg = make_config("paper", static_tracked=8)
    env = SafeNavVectorEnv(8, config=cfg, output="torch")
    obs, _ = env.reset(seed=12345)
    for _ in range(3):  # autoresets and moves included
        obs, *_ = env.step(torch.rand(8, 3) * 2 - 1)
    assert env.single_observation_space["static"].shape == (8, 7)
    static = obs["static"]
    assert static.shape == (8, 8, 7) and torch.isfinite(static).all()
    w, ps = env.world_idx, env.n_static
    for i in range(8):
        pos = env.pos[i]
        xy, half, h = (
            env.pillar_xy[w[i], :ps],
            env.pillar_half[w[i], :ps],
            env.pillar_height[w[i], :ps],
        )
        want = static_obstacle_features(pos, xy, half, h, env.cos_yaw[i], env.sin_yaw[i], 8, 4.0)
        torch.testing.assert_close(static[i], want)
        present = static[i, :, 6] == 1
        # as many rows as pillars within range (up to 8), nearest first
        clear = pillar_clearances(pos, xy, half, h)
        assert torch.equal(clear.amin(), pillar_clearance(pos, xy, half, h))
        assert int(present.sum()) == min(8, int((clear <= 4.0).sum()))
        near = static[i, present, :2].norm(dim=-1)  # horizontal part of each clearance
        assert (near <= 1.0 + 1e-6).all()
    plain = SafeNavVectorEnv(8, preset="paper", output="torch")
    assert set(plain.reset(seed=12345)[0]) == {"state", "lidar", "dynamic"}


def _footprints(pillars, maps_like: int = 1):
    cfg = make_config("easy", static_tracked=4)
    grid = GridSpec.for_config(cfg)
    walls = border_walls(grid, cfg.half)
    world = world_from_obstacles(cfg, pillars)
    tops = dequantize_heights(quantize_heights(height_map(world, len(pillars), walls)))
    tops = tops.expand(maps_like, -1, -1)
    return map_footprints(tops, (tops > 0) & ~walls, grid.origin, grid.resolution)


def test_map_footprints_are_the_pillars_within_half_a_cell():
    pillars = [(1.03, -2.47, 0.4, 2.3), (-3.21, 0.55, 0.8, 1.1), (2.5, 2.5, 0.4, 3.0)]
    xy, half, top = _footprints(pillars, maps_like=2)  # a batch of two maps
    assert xy.shape == (2, 3, 2) and half.shape == top.shape == (2, 3)
    for x, y, side, height in pillars:
        i = int((xy[0] - torch.tensor([x, y])).norm(dim=-1).argmin())
        assert (xy[0, i] - torch.tensor([x, y])).abs().max() <= 0.05 + 1e-6  # half a cell
        assert half[0, i] == pytest.approx(side / 2, abs=1e-6)  # the rasterised side is the side
        assert top[0, i] == pytest.approx(height, abs=HEIGHT_QUANTUM / 2 + 1e-6)
    assert torch.equal(xy[1], xy[0])
    # the border wall is not a pillar; an empty map has none
    xy, half, _ = _footprints([])
    assert xy.shape == (1, 0, 2) and half.shape == (1, 0)


def test_touching_pillars_make_one_footprint_over_both():
    # two 0.4 m pillars side by side (their cells adjacent) and one apart
    xy, half, top = _footprints(
        [(0.0, 0.0, 0.4, 1.0), (0.4, 0.0, 0.4, 2.0), (-3.0, -3.0, 0.4, 1.5)]
    )
    real = half[0] > 0
    assert int(real.sum()) == 2
    merged = int((xy[0] - torch.tensor([0.2, 0.0])).norm(dim=-1).argmin())
    assert half[0, merged] == pytest.approx(0.4, abs=1e-6)  # the square over the 0.8 x 0.4 pair
    assert top[0, merged] == pytest.approx(2.0, abs=HEIGHT_QUANTUM)  # the taller one's top
    # maps with fewer footprints are padded with ones of no size, far away (beyond any range)
    pad = map_footprints(torch.zeros(1, 8, 8), torch.zeros(1, 8, 8, dtype=torch.bool), 0.0, 0.1)
    assert pad[0].shape == (1, 0, 2)
    two = torch.zeros(2, 8, 8)
    two[0, 2, 2] = 1.0
    xy2, half2, _ = map_footprints(two, two > 0, 0.0, 0.1)
    assert xy2.shape == (2, 1, 2) and half2[1, 0] == 0 and xy2[1, 0, 0] == FAR_FOOTPRINT


def test_env_entry_from_the_map_is_the_exact_one_within_half_a_cell():
    with pytest.raises(ValueError, match="static_source"):
        make_config("paper", static_tracked=4, static_source="lidar")
    shared = {"static_tracked": 6, "num_worlds": 2}
    exact = SafeNavVectorEnv(4, config=make_config("paper", **shared), output="torch")
    mapped = SafeNavVectorEnv(4, config=make_config("paper", static_source="map", **shared),
                              output="torch")  # fmt: skip
    obs_e, _ = exact.reset(seed=12345)
    obs_m, _ = mapped.reset(seed=12345)
    for _ in range(3):
        action = torch.rand(4, 3) * 2 - 1
        (obs_e, *_), (obs_m, *_) = exact.step(action), mapped.step(action)
    for k in ("state", "lidar", "dynamic"):  # nothing else changes
        torch.testing.assert_close(obs_m[k], obs_e[k])
    # the same pillars in range: rows within half a cell per axis (0.05 m, turned into the goal
    # frame up to 0.05 * sqrt(2), / 4 m) and a height quantum, up to order among pillars at
    # nearly the same clearance and the few touching ones
    e, m = obs_e["static"], obs_m["static"]
    assert e[..., 6].sum() > 0
    close = (m[:, :, None, :6] - e[:, None, :, :6]).abs().amax(-1) <= 0.05 * 2**0.5 / 4 + 1e-4
    matched = close.any(-1) & (m[..., 6] == 1)
    assert matched.sum() >= 0.9 * (m[..., 6] == 1).sum()


def test_extractor_embeds_the_static_entry():
    from safenav.nn.config import NetConfig
    from safenav.nn.networks import input_order, is_nav_layout, make_extractor

    shapes = observation_shapes(make_config("paper", static_tracked=10))
    assert is_nav_layout(shapes) and input_order(shapes) == ("state", "lidar", "dynamic", "static")
    plain = make_extractor(observation_shapes(make_config("paper")), NetConfig())
    ex = make_extractor(shapes, NetConfig(), ensemble_size=2)
    assert ex.out_features == plain.out_features + 64
    obs = {k: torch.rand(5, *s) for k, s in shapes.items()}
    out = ex(obs)
    assert out.shape == (2, 5, ex.out_features)
    obs2 = {**obs, "static": torch.rand(5, *shapes["static"])}
    assert not torch.equal(ex(obs2), out)  # the entry reaches the features


@pytest.fixture(scope="module")
def static_run(tmp_path_factory) -> Path:
    torch.set_num_threads(1)
    run_dir = tmp_path_factory.mktemp("runs") / "static"
    return train_tiny_csac(run_dir, "static_tracked", "4", "static_source", "map")


def test_train_eval_export_and_a_runtime_step(static_run, tmp_path):
    import numpy as np

    from safenav.algos.policy import load_policy
    from safenav.deploy.export import OnnxPolicy, TorchPolicy, check_deployable, load_sidecar
    from safenav.deploy.runtime import OnboardRuntime, RuntimeConfig

    env_config = json.loads((static_run / "config.json").read_text())["env_config"]
    assert env_config["static_tracked"] == 4 and env_config["static_source"] == "map"
    policy = load_policy(static_run / "checkpoint.pt")
    assert policy.obs_shapes["static"] == (4, 7)
    for extra in ([], ["--preset", "paper"]):  # a preset keeps the policy's pillar list
        out = tmp_path / f"eval{len(extra)}.json"
        main(["eval", str(static_run), "--episodes", "2", "--json", str(out), *extra])
        assert json.loads(out.read_text())["episodes"] == 2
    check_deployable(make_config("easy", static_tracked=4), "p")  # either source deploys
    onnx = tmp_path / "p.onnx"
    main(["export", str(static_run / "checkpoint.pt"), "--onnx", str(onnx)])
    meta, cfg = load_sidecar(onnx)
    assert cfg.static_tracked == 4 and meta["inputs"][-1] == "static"
    # the onboard runtime flies it: a pillar 1.5 m ahead in its map is the first row
    runtime = OnboardRuntime(OnnxPolicy(onnx), cfg, RuntimeConfig(require_tracker=False))
    runtime.update_state([0.0, -6.0, 1.5], [0.0, 0.0, 0.0])
    side = np.linspace(-0.19, 0.19, 5)
    pillar = [[x, -4.3 + y, z] for x in side for y in side for z in (0.5, 1.0, 2.0)]
    runtime.update_points(np.array(pillar))
    runtime.set_goal([0.0, 6.0, 1.5])
    setpoint = runtime.step()
    assert not setpoint.hover, setpoint.reason
    static = setpoint.observation["static"]
    assert static.shape == (4, 7) and static[0, 6] == 1 and static[1:].sum() == 0
    assert static[0, 0] == pytest.approx(1.5 / 4, abs=1e-5)  # near face 1.5 m ahead (goal-frame x)
    obs = [setpoint.observation[k][None] for k in ("state", "lidar", "dynamic", "static")]
    np.testing.assert_allclose(setpoint.policy_action, TorchPolicy(policy.actor)(*obs)[0],
                               atol=1e-5)  # fmt: skip


def test_pillars_recipe_is_the_memory_recipe_plus_the_list():
    from safenav.recipes import load_recipe

    base = load_recipe("csac-shielded-memory").section("run")
    pillars = load_recipe("csac-shielded-memory-pillars").section("run")
    assert pillars["env_kwargs"] == {**base["env_kwargs"], "static_tracked": 10}
    assert {k: v for k, v in pillars.items() if k != "env_kwargs"} == {
        k: v for k, v in base.items() if k != "env_kwargs"
    }
    assert load_recipe("csac-shielded-memory-pillars").section("csac") == load_recipe(
        "csac-shielded-memory"
    ).section("csac")


def test_static_source_script_flies_both_lists_on_validation_only(static_run, tmp_path):
    """experiments/static_source.py (docs/csac-v1.md, "The pillar list from the map"): the same
    episodes with the drawn list and the map's, paired; the test and held-out maps refused."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "experiments" / "static_source.py"
    spec = importlib.util.spec_from_file_location("static_source", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out = tmp_path / "s.json"
    assert script.main([str(static_run / "checkpoint.pt"), "--env-seeds", "12345",
                        "--episodes", "3", "--json", str(out)]) == 0  # fmt: skip
    data = json.loads(out.read_text())
    (row,) = data["policies"]
    assert row["trained_with"] == "map"
    assert len(row["exact"]["success"]) == len(row["map"]["collision"]) == 3
    for key in ("success", "collision"):
        s = data["summary"][key]
        assert s["episodes"] == 3 and s["diff"] == pytest.approx(s["map"] - s["exact"])
        assert s["ci95"][0] <= s["diff"] <= s["ci95"][1]
    with pytest.raises(SystemExit):
        script.main([str(static_run / "checkpoint.pt"), "--env-seeds", "1"])


def test_dequantize_heights_inverts_the_map_quantum():
    heights = torch.tensor([0.0, 0.01, 1.2345, 6.0, 9.0])
    back = dequantize_heights(quantize_heights(heights))
    assert back.dtype == torch.float32
    torch.testing.assert_close(back[:4], heights[:4], atol=HEIGHT_QUANTUM / 2 + 1e-6, rtol=0)
    assert back[4] == pytest.approx(255 * HEIGHT_QUANTUM)  # clipped at 6.375 m
    metres = torch.tensor([0.5, 2.0], dtype=torch.float64)  # an onboard float map passes through
    torch.testing.assert_close(dequantize_heights(metres), metres.float())
