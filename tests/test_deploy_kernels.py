"""The compiled per-vehicle kernels (safenav.deploy.kernels) compute what their batched originals do."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from safenav.deploy import kernels
from safenav.deploy.mapping import HeightMap
from safenav.deploy.shield import ShieldConfig, shield_action, velocity_obstacle_shield
from safenav.envs import SafeNavVectorEnv, make_config
from safenav.envs.world import GridSpec

pytestmark = [
    pytest.mark.usefixtures("one_thread"),
    pytest.mark.skipif(not kernels.AVAILABLE, reason="needs Numba (safenav[deploy])"),
]


@pytest.fixture(scope="module")
def paper_frames():
    from safenav.bench.latency import _sensor_frames

    cfg = make_config("paper")
    frames, _ = _sensor_frames(cfg, 8)
    return cfg, frames


def obstacle_boxes(frame) -> np.ndarray:
    ob = np.array([[*o.p, o.width, o.height] for o in frame.obstacles], np.float32)
    half = np.stack([ob[:, 3] / 2, ob[:, 3] / 2, ob[:, 4] / 2], -1)
    return np.stack([ob[:, :3] - half, ob[:, :3] + half], 1)


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_depth_kernel_builds_the_numpy_paths_map(paper_frames, stride) -> None:
    cfg, frames = paper_frames
    numpy_map = HeightMap(GridSpec.for_config(cfg), compiled=False)
    compiled_map = HeightMap(GridSpec.for_config(cfg), compiled=True)
    rng = np.random.default_rng(stride)
    for i, (_, frame) in enumerate(frames):
        images = list(frame.depth)
        if i % 2:  # garbage pixels: NaN, Inf, 0 and negative depths are "no return"
            img = images[0]
            depth = np.array(img.depth, dtype=np.float32)
            bad = rng.random(depth.shape) < 0.1
            depth[bad] = rng.choice([np.nan, np.inf, 0.0, -1.0], size=int(bad.sum()))
            images[0] = type(img)(**{**img.__dict__, "depth": depth})
        boxes = obstacle_boxes(frame) if i % 3 else None
        n_np = numpy_map.insert_depth(images, stride, 8.0, boxes)
        n_c = compiled_map.insert_depth(images, stride, 8.0, boxes)
        assert n_np == n_c > 0
    assert torch.equal(numpy_map.heights, compiled_map.heights)
    assert torch.equal(numpy_map.cast_map, compiled_map.cast_map)
    assert int((compiled_map.heights > 0).sum()) > 100


def random_scene(g: torch.Generator, i: int):
    m = int(torch.randint(1, 30, (1,), generator=g))
    rel = (torch.rand(1, m, 3, generator=g) - 0.5) * 6
    if i % 3 == 0:
        rel[..., 2] = 0
    moving = torch.rand(1, m, 1, generator=g) < 0.3
    ovel = (torch.rand(1, m, 3, generator=g) - 0.5) * 3 * moving
    radius = 0.4 + torch.rand(1, m, generator=g)
    valid = torch.rand(1, m, generator=g) < 0.8
    planar = torch.rand(1, m, generator=g) < 0.6
    v = (torch.rand(1, 3, generator=g) - 0.5) * 4
    return v, rel, ovel, radius, valid, planar


def test_shield_kernel_equals_the_batched_shield_on_random_scenes() -> None:
    cfg, g = ShieldConfig(), torch.Generator().manual_seed(0)
    corrected = 0
    for i in range(1500):
        scene = random_scene(g, i)
        a, ca = velocity_obstacle_shield(*scene, cfg, compiled=False)
        b, cb = velocity_obstacle_shield(*scene, cfg, compiled=True)
        assert bool(ca) == bool(cb), i
        torch.testing.assert_close(b, a, atol=1e-4, rtol=0)
        if bool(ca):
            corrected += 1
        else:
            assert torch.equal(b, scene[0])  # unchanged actions pass bit for bit
    assert 300 < corrected < 1400  # both branches exercised


def test_shield_kernel_equals_the_batched_shield_in_the_paper_scenario() -> None:
    """Env observations (range images with tied distances, tracked movers): row by row through the
    kernel == the whole batch through torch."""
    cfg = make_config("paper")
    env = SafeNavVectorEnv(64, config=cfg, output="torch")
    obs, _ = env.reset(seed=5)
    scfg = ShieldConfig.for_env(cfg)
    g = torch.Generator().manual_seed(1)
    corrected = 0
    for _ in range(10):
        action = torch.rand(64, 3, generator=g) * 2 - 1
        batch, cb = shield_action(obs, action, scfg)
        for j in range(64):
            one = {k: v[j : j + 1] for k, v in obs.items()}
            out, c1 = shield_action(one, action[j : j + 1], scfg)
            assert bool(c1[0]) == bool(cb[j])
            torch.testing.assert_close(out[0], batch[j], atol=1e-4, rtol=0)
        corrected += int(cb.sum())
        obs, *_ = env.step(action)
    assert corrected > 20
