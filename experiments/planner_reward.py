"""What NavRL's reward says of planner B's flights (docs/csac-v1.md, "The planner's flights in the
replay"): each term of the env's reward summed over each episode of a validation map, flown by
the planner, and the share of its steps above or below the start-goal altitude band that the
height penalty keeps. The terms are recomputed from the env's state and observation as
``SafeNavVectorEnv.step`` computes them (velocity towards the goal, the range image's log
ranges, the height and smoothness penalties); what is left of the reward (moving obstacles,
goal, crash) is their difference from the env's own reward.

    .venv/bin/python experiments/planner_reward.py --env-seed 12345 --episodes 36 \
        --json results/csac-v1/oracle/planner-eval/reward-12345.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import torch

from safenav.common.jsonout import write_json
from safenav.envs.config import make_config
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.planner import PLANNER_B, PLANNER_B_BEAMS, OraclePlanner
from safenav.experiments.evaluate import fixed_test_scenario
from safenav.experiments.selection import RESERVED_SEEDS

TERMS = ("velocity", "static", "height", "smooth", "rest")


@torch.no_grad()
def reward_terms(env_seed: int, episodes: int, keep_band: bool = False) -> dict:
    """Per episode: each reward term's sum, the reward, the outcome and the share of steps
    outside the altitude band (planner B, the beams it was measured with; ``keep_band``: planner B
    keeping the band, ``OracleConfig.keep_band``)."""
    if env_seed in RESERVED_SEEDS:
        raise SystemExit(f"env seed {env_seed} is a test or held-out map: use a validation map")
    cfg, starts, goals = fixed_test_scenario(
        make_config("paper", lidar_v_angles=PLANNER_B_BEAMS), env_seed, episodes
    )
    env = SafeNavVectorEnv(episodes, config=cfg, output="torch", autoreset_mode="Disabled")
    obs, _ = env.reset(seed=env_seed, options={"starts": starts, "goals": goals})
    config = dataclasses.replace(PLANNER_B, keep_band=keep_band)
    planner, n, rows = OraclePlanner(config), episodes, len(cfg.lidar_v_angles)
    sums = {k: torch.zeros(n) for k in (*TERMS, "reward", "steps", "outside")}
    going = torch.ones(n, dtype=torch.bool)
    success = torch.zeros(n)
    for _ in range(cfg.max_episode_steps):
        prev_vel = env.vel.clone()
        obs, reward, term, trunc, info = env.step(planner(obs, env))
        ranges = cfg.lidar_range * (1 - obs["lidar"][:, :rows])
        to_goal = env.goal - env.pos
        unit = to_goal / to_goal.norm(dim=-1, keepdim=True).clamp(min=1e-6)
        z, lo, hi = env.pos[:, 2], env.band[:, 0], env.band[:, 1]
        parts = {
            "velocity": cfg.w_velocity * (env.vel * unit).sum(-1),
            "static": cfg.w_static
            * torch.log((ranges / cfg.lidar_range).clamp(1e-3, 1)).mean((1, 2)),
            "height": -cfg.w_height * ((z - hi).clamp(min=0) ** 2 + (lo - z).clamp(min=0) ** 2),
            "smooth": -cfg.w_smooth * (env.vel - prev_vel).norm(dim=-1),
        }
        parts["rest"] = reward - sum(parts.values())
        g = going.float()
        for k, v in parts.items():
            sums[k] += g * v
        sums["reward"] += g * reward
        sums["steps"] += g
        sums["outside"] += g * ((z > hi) | (z < lo)).float()
        done = (term | trunc) & going
        if done.any() and "episode" in info:
            success[done] = torch.as_tensor(info["episode"]["success"], dtype=torch.float32)[done]
        going &= ~(term | trunc)
        if not going.any():
            break
    per = {k: [round(float(x), 2) for x in v] for k, v in sums.items()}
    per["success"] = success.tolist()
    ok = success > 0.5
    mean = lambda v, m: round(float(v[m].mean()), 1) if m.any() else None  # noqa: E731
    summary = {
        f"{k}_mean": mean(sums[k], torch.ones(n, dtype=torch.bool)) for k in (*TERMS, "reward")
    }
    summary |= {"reward_mean_success": mean(sums["reward"], ok),
                "outside_band_share": round(float(sums["outside"].sum() / sums["steps"].sum()), 3),
                "success_rate": round(float(ok.float().mean()), 3)}  # fmt: skip
    return {
        "env_seed": env_seed,
        "episodes": episodes,
        "keep_band": keep_band,
        "summary": summary,
        "per_episode": per,
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--env-seed", type=int, default=12345)
    ap.add_argument("--episodes", type=int, default=36)
    ap.add_argument("--keep-band", action="store_true", help="planner B keeping the altitude band")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = reward_terms(args.env_seed, args.episodes, args.keep_band)
    print(json.dumps(out["summary"]))
    if args.json:
        write_json(args.json, out)
    return out


if __name__ == "__main__":
    main()
