"""What a policy's timeouts on one map look like behind its own flight shield and the
sliding planner filter (with ``--short-moves``, the filter adopted now): per timeout episode,
the path flown in its last 20 s, the net displacement over them, and the share of those steps
where the filter's planner flew. Frozen: < 0.5 m flown; dithering: flown > 4x the net
displacement; else still moving (a long route).
Validation maps only (12345-12348) for a diagnosis that guides a choice.

    .venv/bin/python experiments/timeout_kinds.py results/csac-v1/filter/policies/csac.pt \\
        --env-seed 12346 --episodes 100
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from safenav.algos.policy import load_policy
from safenav.envs.planner import behind_filter, filter_from_spec, filter_spec
from safenav.experiments.evaluate import evaluate
from safenav.experiments.selection import own_shield

LAST_STEPS = 200  # the last 20 s at 10 Hz


def kind(path_m: float, net_m: float) -> str:
    """``"frozen"``, ``"dithering"`` or ``"moving"`` from the last 20 s's path and net motion."""
    if path_m < 0.5:
        return "frozen"
    return "dithering" if path_m > 4 * net_m else "moving"


def timeouts(checkpoint: Path, env_seed: int, episodes: int,
             short_moves: bool = False) -> tuple[dict, list[dict]]:  # fmt: skip
    """The evaluation's result and one row per timeout episode."""
    fn = load_policy(checkpoint)
    the_filter = filter_from_spec(filter_spec(short_moves=short_moves))
    shielded = behind_filter(own_shield(fn), the_filter)  # as the policy's report flies
    track: list[tuple[torch.Tensor, torch.Tensor]] = []

    def flown(env, obs, action):
        out = shielded(env, obs, action)
        track.append((env.pos.clone(), the_filter.overridden.clone()))
        return out

    result = evaluate(fn, fn.env_config(), env_seed=env_seed, episodes=episodes, shield=flown)
    pos = torch.stack([p for p, _ in track])[-LAST_STEPS:]
    planner = torch.stack([o for _, o in track])[-LAST_STEPS:].float()
    ends = result["per_episode"]
    rows = []
    for i in range(episodes):
        if ends["success"][i] or ends["collision"][i]:
            continue
        path = float((pos[1:, i] - pos[:-1, i]).norm(dim=-1).sum())
        net = float((pos[-1, i] - pos[0, i]).norm())
        rows.append({"episode": i, "path_m": round(path, 2), "net_m": round(net, 2),
                     "planner_share": round(float(planner[:, i].mean()), 2),
                     "kind": kind(path, net),
                     "end": [round(x, 1) for x in pos[-1, i].tolist()]})  # fmt: skip
    return result, rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--env-seed", type=int, default=12346)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--short-moves", action="store_true")
    args = parser.parse_args()
    result, rows = timeouts(args.checkpoint, args.env_seed, args.episodes, args.short_moves)
    print(f"success {result['success_rate']:.3f} collision {result['collision_rate']:.3f} "
          f"timeout {result['timeout_rate']:.3f}")  # fmt: skip
    print("| episode | last 20 s flown (m) | net (m) | planner share | kind | end (m) |")
    print("|---:|---:|---:|---:|---|---|")
    for r in rows:
        print(f"| {r['episode']} | {r['path_m']} | {r['net_m']} | {r['planner_share']} | "
              f"{r['kind']} | {r['end']} |")  # fmt: skip


if __name__ == "__main__":
    main()
