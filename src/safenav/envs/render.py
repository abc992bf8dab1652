"""Top-down RGB rendering of one env of a :class:`~safenav.envs.nav.SafeNavVectorEnv`."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from PIL import Image, ImageDraw

BG = (245, 245, 240)
PILLAR = (95, 100, 110)
PILLAR_LOW = (150, 155, 165)
CYLINDER = (230, 140, 40)
CUBOID = (70, 130, 220)
UAV = (220, 30, 40)
GOAL = (30, 170, 60)
START = (40, 40, 200)
TRAIL = (220, 60, 80)
BEAM = (250, 170, 170)
BEAM_HIT = (230, 40, 40)


def render_topdown(
    env, index: int = 0, trail: Sequence[np.ndarray] = (), size: int = 600
) -> np.ndarray:
    """Render env ``index``: pillars (dark = taller than the UAV), moving obstacles (orange
    cylinders, blue floating cuboids), the horizontal lidar beams, the trail, start and goal."""
    cfg = env.cfg
    half = cfg.half
    scale = size / cfg.map_size

    def px(x: float, y: float) -> tuple[float, float]:
        return ((x + half) * scale, (half - y) * scale)

    img = Image.new("RGB", (size, size), BG)
    draw = ImageDraw.Draw(img)
    w = int(env.world_idx[index])
    uav = env.pos[index].detach().cpu().numpy()
    ns, nd = env.n_static, env.n_dynamic
    xy = env.pillar_xy[w, :ns].cpu().numpy()
    hs = env.pillar_half[w, :ns].cpu().numpy()
    hh = env.pillar_height[w, :ns].cpu().numpy()
    for (x, y), h, top in zip(xy, hs, hh, strict=True):
        x0, y0 = px(x - h, y + h)
        x1, y1 = px(x + h, y - h)
        draw.rectangle([x0, y0, x1, y1], fill=PILLAR if top > uav[2] else PILLAR_LOW)
    dpos = env.dyn_pos[w, :nd].cpu().numpy()
    dwid = env.dyn_width[w, :nd].cpu().numpy()
    dcub = env.dyn_is_cuboid[w, :nd].cpu().numpy()
    for (x, y, _z), wd, cub in zip(dpos, dwid, dcub, strict=True):
        r = wd / 2 * scale
        cx, cy = px(x, y)
        if cub:
            draw.rectangle([cx - r, cy - r, cx + r, cy + r], outline=CUBOID, fill=(170, 200, 245))
        else:
            draw.ellipse([cx - r, cy - r, cx + r, cy + r], fill=CYLINDER)
    # Horizontal (0 degree) beams of the range image.
    if env._last_ranges is not None:
        v_row = min(range(len(cfg.lidar_v_angles)), key=lambda i: abs(cfg.lidar_v_angles[i]))
        ranges = env._last_ranges[index, v_row].detach().cpu().numpy()
        yaw = float(env.yaw[index])
        for j, d in enumerate(ranges):
            a = yaw + 2 * math.pi * j / cfg.lidar_h_beams
            end = px(uav[0] + d * math.cos(a), uav[1] + d * math.sin(a))
            draw.line(
                [px(uav[0], uav[1]), end], fill=BEAM_HIT if d < cfg.lidar_range else BEAM, width=1
            )
    start = env.start[index].cpu().numpy()
    goal = env.goal[index].cpu().numpy()
    sx, sy = px(start[0], start[1])
    draw.rectangle([sx - 4, sy - 4, sx + 4, sy + 4], outline=START, width=2)
    if len(trail) > 1:
        draw.line([px(p[0], p[1]) for p in trail], fill=TRAIL, width=2)
    gx, gy = px(goal[0], goal[1])
    gr = max(cfg.goal_tolerance * scale, 4)
    draw.ellipse([gx - gr, gy - gr, gx + gr, gy + gr], outline=GOAL, width=3)
    draw.line([gx - gr, gy, gx + gr, gy], fill=GOAL, width=2)
    draw.line([gx, gy - gr, gx, gy + gr], fill=GOAL, width=2)
    ux, uy = px(uav[0], uav[1])
    ur = max(cfg.uav_radius * scale, 3)
    draw.ellipse([ux - ur, uy - ur, ux + ur, uy + ur], fill=UAV)
    t = float(env.steps[index]) * cfg.dt
    speed = float(env.vel[index].norm())
    draw.rectangle([0, 0, size, 18], fill=(255, 255, 255))
    draw.text((6, 3), f"t={t:5.1f}s  z={uav[2]:.2f}m  |v|={speed:.2f}m/s  density={cfg.density:.2f}",
              fill=(0, 0, 0))  # fmt: skip
    return np.asarray(img)


__all__ = ["render_topdown"]
