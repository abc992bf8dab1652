"""What a policy's timeouts on one map look like behind its own flight shield and the
sliding planner filter (with ``--short-moves``, the filter adopted now): per timeout episode,
the path flown in its last 20 s, the net displacement over them, and the share of those steps
where the filter's planner flew. Frozen: < 0.5 m flown; dithering: flown > 4x the net
displacement; else still moving (a long route). Beside them, when the successes arrive (10 s
bins of their flight time): how many flights finish near the 60 s limit; and where all the
flights' seconds go (``time_use``): each second of each episode as progressing (>= 0.5 m/s nearer
the goal), moving without progress (>= 0.5 m/s flown, less nearer) or hovering (< 0.5 m/s).
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
    # the stack these diagnoses were run on (2026-12-05/06): the shield keeps its braking cap
    the_filter = filter_from_spec(filter_spec(short_moves=short_moves, braking_cap=True))
    shielded = behind_filter(own_shield(fn), the_filter)
    track: list[tuple[torch.Tensor, torch.Tensor]] = []
    goal: list[torch.Tensor] = []

    def flown(env, obs, action):
        out = shielded(env, obs, action)
        track.append((env.pos.clone(), the_filter.overridden.clone()))
        goal[:] = [env.goal.clone()]
        return out

    result = evaluate(fn, fn.env_config(), env_seed=env_seed, episodes=episodes, shield=flown)
    whole = torch.stack([p for p, _ in track])
    planned = torch.stack([o for _, o in track]).float()
    result["time_use"] = time_use(whole, goal[0], result["per_episode"], planned)
    pos, planner = whole[-LAST_STEPS:], planned[-LAST_STEPS:]
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


def time_use(pos: torch.Tensor, goal: torch.Tensor, ends: dict, planner: torch.Tensor,
             steps_per_s: int = 10) -> dict[str, float]:  # fmt: skip
    """Shares of all flown seconds ``pos (T, N, 3)`` (a row per control step, ``ends["time"]``
    long per episode) that progress (>= 0.5 m/s nearer ``goal (N, 3)``), move without progress
    (>= 0.5 m/s flown) or hover; ``planner_share``: of the steps, where the filter's planner
    flew (``planner (T, N)``); ``progressing_speed`` / ``progressing_rate``: m/s flown / nearer
    the goal in the progressing seconds."""
    counts = {"progressing": 0, "moving_no_progress": 0, "hovering": 0}
    flown_m = nearer_m = 0.0
    flown_steps = planner_steps = 0
    for i, t in enumerate(ends["time"]):
        n = min(int(round(t * steps_per_s)), len(pos))
        p = pos[:n, i]
        flown_steps, planner_steps = flown_steps + n, planner_steps + float(planner[:n, i].sum())
        to_goal = (goal[i] - p).norm(dim=-1)
        for a in range(0, n - steps_per_s, steps_per_s):
            b = a + steps_per_s
            path = float((p[a + 1 : b + 1] - p[a:b]).norm(dim=-1).sum())
            if float(to_goal[a] - to_goal[b]) >= 0.5:
                counts["progressing"] += 1
                flown_m, nearer_m = flown_m + path, nearer_m + float(to_goal[a] - to_goal[b])
            else:
                counts["moving_no_progress" if path >= 0.5 else "hovering"] += 1
    total = max(1, sum(counts.values()))
    out = {k: round(v / total, 3) for k, v in counts.items()}
    out["planner_share"] = round(planner_steps / max(1, flown_steps), 3)
    out["progressing_speed"] = round(flown_m / max(1, counts["progressing"]), 2)
    out["progressing_rate"] = round(nearer_m / max(1, counts["progressing"]), 2)
    return out


def arrival_bins(result: dict, width: float = 10.0) -> dict[str, int]:
    """The successes' flight times counted in ``width``-second bins (``"50-60"``: ...)."""
    ends = result["per_episode"]
    times = [t for t, ok in zip(ends["time"], ends["success"], strict=True) if ok]
    top = int(max(times, default=0.0) // width) + 1
    counts = {f"{int(b * width)}-{int((b + 1) * width)}": 0 for b in range(top)}
    for t in times:
        b = int(t // width)
        counts[f"{int(b * width)}-{int((b + 1) * width)}"] += 1
    return counts


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
    print("successes by flight time (s):", arrival_bins(result))
    print("seconds flown:", result["time_use"])
    print("| episode | last 20 s flown (m) | net (m) | planner share | kind | end (m) |")
    print("|---:|---:|---:|---:|---|---|")
    for r in rows:
        print(f"| {r['episode']} | {r['path_m']} | {r['net_m']} | {r['planner_share']} | "
              f"{r['kind']} | {r['end']} |")  # fmt: skip


if __name__ == "__main__":
    main()
