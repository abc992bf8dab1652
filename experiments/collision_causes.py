"""Why does a policy collide on the fixed test scenario? (docs/csac.md, "Where the collisions come from")

Flies the 200 test episodes (env seed 1, full density, deterministic actions, as ``safenav eval``;
``--env-seed`` another map, e.g. a validation map to diagnose before a choice) and sorts every
collision:

- ``pillar, in view``: the struck pillar was in the range image at one of the last two steps (a
  beam within one column of its bearing returned its distance, +-0.3 m): the policy saw it and
  flew into it;
- ``pillar, lost from view``: in the image during the last second, but not at the last two steps:
  e.g. a low pillar whose top is less than ``0.18 r`` m below the UAV at horizontal range ``r``
  drops under the lowest (-10 deg) beam as the UAV closes in, or a 0.4 m pillar falls between
  two 10 deg beams; a policy without memory has forgotten it;
- ``pillar, never in view``: not in the image during the last second;
- ``moving, tracked`` / ``moving, untracked``: whether the obstacle was among the tracked ones
  (within 4 m, the 5 nearest) at the step before the collision;
- ``altitude band``: ground or ceiling.

``pillar_top`` counts the pillar collisions at the top of the pillar (the UAV centre above its
top less ``uav_radius``): a low pillar under the UAV, below the lowest beam as it closes in.

Run: ``.venv/bin/python experiments/collision_causes.py checkpoints/csac-paper.pt [--env-seed N]
[--json OUT]``.
"""

from __future__ import annotations

import argparse
import math
from collections import Counter
from pathlib import Path

import torch

from safenav.common.jsonout import write_json
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.sensors import moving_obstacle_clearance
from safenav.envs.world import CUBOID_HEIGHT, CYLINDER_HEIGHT
from safenav.experiments.evaluate import fixed_test_scenario
from safenav.experiments.flight import resolve_policy

LOOKBACK = 10  # steps = 1 s at 10 Hz


@torch.no_grad()
def classify(checkpoint: str, episodes: int = 200, env_seed: int = 1, planner=None) -> dict:
    """The causes of ``checkpoint``'s collisions, or of ``planner``'s (a callable
    ``(obs, env) -> actions``, e.g. ``oracle_planner.OraclePlanner``; ``checkpoint`` then names
    it in the output) on the paper preset."""
    if planner is None:
        policy, cfg = resolve_policy(Path(checkpoint), "checkpoint", "cpu")
    else:
        from safenav.envs.config import make_config

        cfg = make_config("paper")
    cfg, starts, goals = fixed_test_scenario(cfg, env_seed, episodes)
    env = SafeNavVectorEnv(episodes, config=cfg, output="torch", autoreset_mode="Disabled")
    obs, _ = env.reset(seed=env_seed, options={"starts": starts, "goals": goals})
    p = env.n_static
    pxy, phalf, ph = env.pillar_xy[0, :p], env.pillar_half[0, :p], env.pillar_height[0, :p]
    history: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []  # (pos, yaw, ranges)
    done = torch.zeros(episodes, dtype=torch.bool)
    causes: dict[int, str] = {}
    tops: set[int] = set()  # pillar collisions at the pillar's top
    for _ in range(cfg.max_episode_steps):
        ranges = (1.0 - obs["lidar"]) * cfg.lidar_range  # (N, V, H) metres
        history = [*history[-(LOOKBACK - 1) :], (env.pos.clone(), env.yaw.clone(), ranges)]
        before = (env.pos.clone(), env.dyn_pos[0, : env.n_dynamic].clone())
        act = planner(obs, env) if planner is not None else policy(obs)
        action = torch.where(done[:, None], torch.zeros(3), act.clamp(-1, 1))
        obs, _, term, trunc, info = env.step(action)
        ended = (term | trunc) & ~done
        for i in ended.nonzero().flatten().tolist():
            ep = info["episode"]
            if not bool(ep["collision"][i]):
                continue
            pos = env.pos[i]
            if bool(ep["out_of_bounds"][i]):
                causes[i] = "altitude band"
            elif bool(ep["hit_static"][i]):
                causes[i] = _pillar_cause(pos, pxy, phalf, ph, history, i, cfg)
                if _near_top(pos, pxy, phalf, ph, cfg):
                    tops.add(i)
            else:
                causes[i] = _moving_cause(env, pos, *before, i, cfg)
        done |= ended
        if bool(done.all()):
            break
    counts = Counter(causes.values())
    return {"checkpoint": checkpoint, "episodes": episodes, "env_seed": env_seed, "collisions": len(causes),
            "causes": dict(counts.most_common()), "pillar_top": len(tops), "per_episode": {str(k): v for k, v in sorted(causes.items())}}  # fmt: skip


def _struck_pillar(pos, pxy, phalf, ph) -> int:
    """Index of the pillar nearest to ``pos`` (footprint and top): the one a collision struck."""
    dx = ((pos[0] - pxy[:, 0]).abs() - phalf).clamp(min=0)
    dy = ((pos[1] - pxy[:, 1]).abs() - phalf).clamp(min=0)
    dz = (pos[2] - ph).clamp(min=0)
    return int((dx * dx + dy * dy + dz * dz).argmin())


def _near_top(pos, pxy, phalf, ph, cfg) -> bool:
    """Did the UAV strike the pillar's top (its centre within ``uav_radius`` of the top's height
    or above it), rather than its side?"""
    return bool(pos[2] > ph[_struck_pillar(pos, pxy, phalf, ph)] - cfg.uav_radius)


def _pillar_cause(pos, pxy, phalf, ph, history, i, cfg) -> str:
    j = _struck_pillar(pos, pxy, phalf, ph)
    step = 2 * math.pi / cfg.lidar_h_beams
    seen = []  # per step of the last second, oldest first: was the pillar in the range image?
    for q, yaw, ranges in history:
        qx, qy = float(q[i, 0]), float(q[i, 1])
        hx = max(abs(qx - float(pxy[j, 0])) - float(phalf[j]), 0.0)
        hy = max(abs(qy - float(pxy[j, 1])) - float(phalf[j]), 0.0)
        dist = math.hypot(hx, hy)
        bearing = math.atan2(float(pxy[j, 1]) - qy, float(pxy[j, 0]) - qx) - float(yaw[i])
        col = round(bearing / step) % cfg.lidar_h_beams
        cols = [(col + c) % cfg.lidar_h_beams for c in (-1, 0, 1)]
        seen.append(
            dist < cfg.lidar_range and bool(((ranges[i][:, cols] - dist).abs() < 0.3).any())
        )
    if any(seen[-2:]):
        return "pillar, in view"
    if any(seen):
        return "pillar, lost from view"
    return "pillar, never in view"


def _moving_cause(env, pos, pos_before, dyn_before, i, cfg) -> str:
    """Was the obstacle hit at this step among the tracked ones (the ``num_tracked`` horizontally
    nearest centres within range) at the step before?"""
    n = env.n_dynamic
    width, cuboid = env.dyn_width[0, :n], env.dyn_is_cuboid[0, :n]
    j = int(moving_obstacle_clearance(env.dyn_pos[0, :n] - pos, width, cuboid, pos[2],
                                      CUBOID_HEIGHT, CYLINDER_HEIGHT).argmin())  # fmt: skip
    horiz = (dyn_before[:, :2] - pos_before[i, :2]).norm(dim=-1)
    rank = int((horiz < horiz[j]).sum())
    tracked = rank < cfg.num_tracked and float(horiz[j]) <= cfg.lidar_range
    return "moving, tracked" if tracked else "moving, untracked"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--env-seed", type=int, default=1,
                    help="1 = the test scenario (a final report); a validation map (12345-12348) to "
                         "diagnose before a choice")  # fmt: skip
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(1)
    result = classify(args.checkpoint, args.episodes, args.env_seed)
    print(f"{args.checkpoint}: {result['collisions']} collisions in {result['episodes']} episodes")
    for cause, n in result["causes"].items():
        print(f"  {cause:22s} {n:4d}  ({n / result['episodes']:.1%} of episodes)")
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
