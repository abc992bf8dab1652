"""Top-down RGB rendering of one env of a :class:`~safenav.envs.nav.SafeNavVectorEnv`.

A frame is the arena (its border wall drawn as a dark frame) under a status line, above a legend
with a scale bar; :func:`decorate` adds the status line and the legend to any map image (also used
for the flight demo's GIF).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

BG = (245, 245, 240)
WALL = (40, 40, 45)
PILLAR = (95, 100, 110)
PILLAR_LOW = (150, 155, 165)
CYLINDER = (230, 140, 40)
CUBOID = (70, 130, 220)
CUBOID_FILL = (170, 200, 245)
UAV = (220, 30, 40)
GOAL = (30, 170, 60)
START = (40, 40, 200)
TRAIL = (220, 60, 80)
BEAM = (250, 170, 170)
BEAM_HIT = (230, 40, 40)
HEADER = 18  # px: status line above the map
LEGEND = 36  # px: legend and scale bar below it
WALL_PX = 4  # px: drawn thickness of the border wall
OUTCOME_COLOUR = {"goal": GOAL, "collision": UAV, "timeout": (200, 120, 0)}


def map_canvas(map_size: float, size: int):
    """A blank map of ``size`` px with its border wall, and ``px(x, y)``: world m -> pixels."""
    scale = (size - 2 * WALL_PX) / map_size
    half = map_size / 2

    def px(x: float, y: float) -> tuple[float, float]:
        return (WALL_PX + (x + half) * scale, WALL_PX + (half - y) * scale)

    img = Image.new("RGB", (size, size), WALL)
    ImageDraw.Draw(img).rectangle(
        [WALL_PX, WALL_PX, size - WALL_PX - 1, size - WALL_PX - 1], fill=BG
    )
    return img, px, scale


def draw_mover(draw: ImageDraw.ImageDraw, cx: float, cy: float, r: float, cuboid: bool) -> None:
    if cuboid:
        draw.rectangle([cx - r, cy - r, cx + r, cy + r], outline=CUBOID, fill=CUBOID_FILL)
    else:
        draw.ellipse([cx - r, cy - r, cx + r, cy + r], fill=CYLINDER)


def draw_goal(draw: ImageDraw.ImageDraw, gx: float, gy: float, gr: float) -> None:
    draw.ellipse([gx - gr, gy - gr, gx + gr, gy + gr], outline=GOAL, width=3)
    draw.line([gx - gr, gy, gx + gr, gy], fill=GOAL, width=2)
    draw.line([gx, gy - gr, gx, gy + gr], fill=GOAL, width=2)


def decorate(
    map_img: Image.Image, status: str, scale: float, outcome: str | None = None
) -> np.ndarray:
    """The map under a status line (and the episode's ``outcome`` once known: goal / collision /
    timeout), above a legend of the symbols and a scale bar; an RGB array."""
    w, h = map_img.size
    img = Image.new("RGB", (w, h + HEADER + LEGEND), (255, 255, 255))
    img.paste(map_img, (0, HEADER))
    d = ImageDraw.Draw(img)
    d.text((6, 3), status, fill=(0, 0, 0))
    if outcome:
        label = outcome.upper()
        x = w - 8 - d.textlength(label)
        d.rectangle([x - 4, 1, w - 4, HEADER - 2], fill=OUTCOME_COLOUR.get(outcome, (0, 0, 0)))
        d.text((x, 3), label, fill=(255, 255, 255))
    y = h + HEADER + 6
    x = 6
    items = (("drone", "uav"), ("pillar", "pillar"), ("low pillar", "pillar_low"),
             ("moving cylinder", "cylinder"), ("floating box", "cuboid"), ("start", "start"),
             ("goal", "goal"), ("wall", "wall"))  # fmt: skip
    for label, kind in items:
        c = (x + 5, y + 5)
        if kind == "uav":
            d.ellipse([c[0] - 4, c[1] - 4, c[0] + 4, c[1] + 4], fill=UAV)
        elif kind in ("pillar", "pillar_low", "wall"):
            colour = {"pillar": PILLAR, "pillar_low": PILLAR_LOW, "wall": WALL}[kind]
            d.rectangle([c[0] - 4, c[1] - 4, c[0] + 4, c[1] + 4], fill=colour)
        elif kind == "cylinder":
            d.ellipse([c[0] - 4, c[1] - 4, c[0] + 4, c[1] + 4], fill=CYLINDER)
        elif kind == "cuboid":
            d.rectangle([c[0] - 4, c[1] - 4, c[0] + 4, c[1] + 4], outline=CUBOID, fill=CUBOID_FILL)
        elif kind == "start":
            d.rectangle([c[0] - 4, c[1] - 4, c[0] + 4, c[1] + 4], outline=START, width=2)
        else:
            draw_goal(d, c[0], c[1], 5)
        d.text((x + 13, y), label, fill=(0, 0, 0))
        x += 13 + int(d.textlength(label)) + 10
        if x > w - 90:  # wrap to a second row on narrow images
            x, y = 6, y + 14
    # Scale bar: 5 m (10 m on wide maps), bottom right.
    metres = 10 if scale * 10 <= w / 4 else 5
    bar = metres * scale
    by = h + HEADER + LEGEND - 8
    d.line([w - 10 - bar, by, w - 10, by], fill=(0, 0, 0), width=3)
    d.text((w - 10 - bar, by - 13), f"{metres} m", fill=(0, 0, 0))
    return np.asarray(img)


def render_topdown(
    env,
    index: int = 0,
    trail: Sequence[np.ndarray] = (),
    size: int = 600,
    outcome: str | None = None,
) -> np.ndarray:
    """Render env ``index``: the border wall, pillars (dark = taller than the UAV), moving
    obstacles (orange cylinders, blue floating cuboids), the horizontal lidar beams, the trail,
    start and goal; a status line (with ``outcome`` when given), a legend and a scale bar."""
    cfg = env.cfg
    img, px, scale = map_canvas(cfg.map_size, size)
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
        draw_mover(draw, *px(x, y), wd / 2 * scale, bool(cub))
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
    draw_goal(draw, *px(goal[0], goal[1]), max(cfg.goal_tolerance * scale, 4))
    ux, uy = px(uav[0], uav[1])
    ur = max(cfg.uav_radius * scale, 3)
    draw.ellipse([ux - ur, uy - ur, ux + ur, uy + ur], fill=UAV)
    t = float(env.steps[index]) * cfg.dt
    speed = float(env.vel[index].norm())
    status = f"t={t:5.1f}s  z={uav[2]:.2f}m  |v|={speed:.2f}m/s  density={cfg.density:.2f}"
    return decorate(img, status, scale, outcome)


def write_gif(path: str | Path, frames: Sequence[np.ndarray], fps: float) -> None:
    """Write RGB ``frames`` (``(H, W, 3)`` uint8 arrays) as a looping GIF at ``fps``.

    Pillow alone (it was imageio's GIF writer too: this is the call imageio made, so the files
    are byte-identical). Pillow merges consecutive identical frames into one longer frame.
    """
    if not len(frames):
        raise ValueError("write_gif needs at least one frame")
    first, *rest = (Image.fromarray(np.asarray(f)) for f in frames)
    first.save(path, format="GIF", save_all=True, append_images=rest, duration=1000 / fps, loop=0)


__all__ = ["decorate", "draw_goal", "draw_mover", "map_canvas", "render_topdown", "write_gif"]
