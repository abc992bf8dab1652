"""Does a policy walk within the speed limit, stand, or sprint? Its forward-velocity profile.

On a Safety velocity task (``SafetyHopperVelocity-v5``, ``SafetyHalfCheetahVelocity-v5``) a step
costs 1 when the forward velocity exceeds the task's threshold (``safenav.common.costs``). A return
and an episode cost do not say *how* a policy keeps the limit: standing still (return ~1000 on the
Hopper, cost 0), a gait below the threshold (PPO-Lag's), or sprints cut short by a fall. This
flies ``--episodes`` deterministic episodes of each policy (reset seeds ``--seed``, ``--seed``+1,
...; ``--stochastic``: actions drawn as in training, ``Policy.sample``, the policy the constraint
binds) and counts the steps by forward velocity ``v``: standing (``|v| < --still``), moving forward
within the limit (``--still <= v <= threshold``), over the limit (``|v| > threshold``, the costly
ones: the cost compares the speed, backward too), and backward within it; with the mean velocity,
return, cost and length.

Run: ``.venv/bin/python experiments/velocity_profile.py RUN[/checkpoint.pt] [RUN ...]
[--episodes 5] [--seed 1] [--stochastic] [--json OUT]``. A run directory means its
``checkpoint.pt`` (as for ``safenav render``). Validation runs: use ``--seed 101``; seed 1 is the
test scenario.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import safenav  # noqa: F401  (registers the velocity tasks)
from safenav.algos.policy import load_policy
from safenav.common.costs import VELOCITY_TASKS, VELOCITY_THRESHOLDS
from safenav.common.jsonout import write_json
from safenav.envs.vector import policy_action_to_env


@torch.no_grad()
def profile(path: Path, episodes: int, seed: int, still: float, stochastic: bool = False) -> dict:
    policy = load_policy(path)  # a run directory: its checkpoint.pt, as safenav render reads it
    env_id = str(policy.meta.get("env_id", ""))
    if env_id not in VELOCITY_TASKS:
        raise SystemExit(f"{path}: trained on {env_id!r}, not a velocity task "
                         f"({', '.join(VELOCITY_TASKS)})")  # fmt: skip
    threshold = VELOCITY_THRESHOLDS[VELOCITY_TASKS[env_id]]
    env = gym.make(env_id)
    draws = torch.Generator().manual_seed(seed)  # the stochastic actions' noise, reproducible
    act = (lambda o: policy.sample(o, draws)) if stochastic else policy
    rows, speeds = [], []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed + k)
        ret = cost = 0.0
        v_ep: list[float] = []
        done = False
        while not done:
            action = policy_action_to_env(act(obs), policy.meta)
            obs, reward, terminated, truncated, info = env.step(action)
            ret, cost = ret + float(reward), cost + float(info.get("cost", 0.0))
            v_ep.append(float(info["x_velocity"]))
            done = terminated or truncated
        rows.append({"seed": seed + k, "return": ret, "cost": cost, "length": len(v_ep),
                     "fell": bool(terminated), "mean_velocity": float(np.mean(v_ep))})  # fmt: skip
        speeds.extend(v_ep)
    env.close()
    v = np.asarray(speeds)
    share = lambda mask: float(mask.mean())  # noqa: E731
    return {
        "policy": str(path), "env_id": env_id, "threshold": threshold, "still": still,
        "actions": "stochastic" if stochastic else "deterministic",
        "steps": int(v.size),
        "share_still": share(np.abs(v) < still),
        "share_forward_within": share((v >= still) & (v <= threshold)),
        "share_over": share(np.abs(v) > threshold),
        "share_backward": share((v <= -still) & (v >= -threshold)),
        "mean_velocity": float(v.mean()),
        "return": float(np.mean([r["return"] for r in rows])),
        "cost": float(np.mean([r["cost"] for r in rows])),
        "length": float(np.mean([r["length"] for r in rows])),
        "falls": int(sum(r["fell"] for r in rows)),
        "episodes": rows,
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("policies", nargs="+", type=Path)
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--still", type=float, default=0.1,
                        help="|v| below this (m/s) counts as standing")  # fmt: skip
    parser.add_argument("--stochastic", action="store_true",
                        help="actions drawn as in training (default: deterministic)")  # fmt: skip
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    if args.episodes < 1 or args.still <= 0:
        raise SystemExit("--episodes must be >= 1 and --still > 0")
    results = [
        profile(p, args.episodes, args.seed, args.still, args.stochastic) for p in args.policies
    ]
    print(f"{'policy':60s} {'return':>7s} {'cost':>6s} {'len':>6s} {'falls':>5s} {'v mean':>6s} "
          f"{'still':>6s} {'fwd<=lim':>8s} {'over':>6s} {'back':>6s}")  # fmt: skip
    for r in results:
        print(f"{r['policy'][-60:]:60s} {r['return']:7.0f} {r['cost']:6.1f} {r['length']:6.0f} "
              f"{r['falls']:5d} {r['mean_velocity']:6.2f} {r['share_still']:6.1%} "
              f"{r['share_forward_within']:8.1%} {r['share_over']:6.1%} {r['share_backward']:6.1%}")  # fmt: skip
    if args.json is not None:
        write_json(args.json, {"seed": args.seed, "episodes": args.episodes, "results": results})


if __name__ == "__main__":
    main()
