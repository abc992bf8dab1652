"""One episode behind the planner filter, second by second: where the UAV is, how far from its
goal, whether the filter's planner flies (a way-out override or a stall handover, and how many
handover steps are left), the policy's action and the action flown. What a GIF of a timeout
shows, in numbers (docs/csac-v1.md, "The two-thread re-derivation, finished").

    .venv/bin/python experiments/filter_trace.py results/csac/runs/csac/seed1/policy.pt \\
        --env-seed 12345 --episode 62 --from-s 20 --to-s 56

The flight is ``safenav render``'s (the same frames and outcome): behind the recipe's flight
shield (memory 1, map scan, 0.3 m mover margin, braking cap) and the planner filter the policy
records (else, or with ``--adopted``, the sliding filter adopted before short moves, and with
``--short-moves`` the filter adopted now: the observed view with the stall handover
``FILTER_STALL``; ``--mapped`` and ``--nearer`` add the screened handover map and its leave
condition to it). Validation maps only (12345-12348) for a diagnosis that guides a choice.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

import safenav.experiments.flight as flight


def trace(checkpoint: Path, env_seed: int, episode: int, adopted: bool = False,
          short_moves: bool = False, mapped: bool = False,
          nearer: bool = False, no_cap: bool = False) -> tuple[dict, list[dict]]:  # fmt: skip
    """The episode's stats and one row per control step; ``adopted``: behind the sliding filter
    (``filter_spec(short_moves=False)``) whatever the policy records; ``short_moves``: the filter
    adopted now, with its planner's short moves (``filter_spec()``); ``mapped`` / ``nearer``:
    that filter with ``handover_map`` / also ``handover_exit="nearer"``; ``no_cap``: the shield
    without its braking cap (as the adopted filter flies it since 2026-12-06)."""
    from safenav.algos.policy import load_policy
    from safenav.envs.planner import filter_spec

    loaded = load_policy(checkpoint)
    short_moves = short_moves or mapped or nearer or no_cap
    spec = (None if adopted or short_moves else loaded.meta.get("flight_filter")) or filter_spec(
        short_moves=short_moves,
        handover_map=mapped or nearer,
        handover_exit="nearer" if nearer else "time",
        braking_cap=not no_cap,
    )
    rows: list[dict] = []
    build = flight.flight_filter

    def traced(spec, cfg):
        the_filter = build(spec, cfg)

        def call(env, obs, action):
            out = the_filter(env, obs, action)
            rows.append({"t": float(env.steps[0]) * env.cfg.dt,
                         "pos": [round(x, 2) for x in env.pos[0].tolist()],
                         "to_goal": round(float((env.goal[0] - env.pos[0]).norm()), 2),
                         "planner": bool(the_filter.overridden[0]),
                         "handover_left": int(the_filter._handover_left[0]),
                         "movers": movers_of(env),
                         "action": [round(x, 2) for x in action[0].tolist()],
                         "flown": [round(x, 2) for x in out[0].tolist()]})  # fmt: skip
            return out

        return call

    flight.flight_filter = traced
    try:
        _, stats = flight.fly_frames(checkpoint, env_seed=env_seed, episode=episode,
                                     shield_memory=1, shield_map=True, shield_mover_margin=0.3,
                                     shield_brake=not no_cap, loaded=loaded,
                                     planner_filter=spec)  # fmt: skip
    finally:
        flight.flight_filter = build
    return stats, rows


def movers_of(env) -> torch.Tensor | None:
    """Episode 0's moving obstacles: ``(D, 4)`` horizontal centre offset from the UAV and
    velocity, or None without any."""
    w, nd = int(env.world_idx[0]), env.n_dynamic
    if nd == 0:
        return None
    return torch.cat([env.dyn_pos[w, :nd, :2] - env.pos[0, :2], env.dyn_vel[w, :nd, :2]], -1)


def describe_mover(movers: torch.Tensor | None, i: int | None = None) -> str:
    """Mover ``i`` of a :func:`movers_of` row (default: the nearest): its horizontal centre
    distance (m) and velocity; ``"-"`` without movers."""
    if movers is None:
        return "-"
    dist = movers[:, :2].norm(dim=-1)
    i = int(dist.argmin()) if i is None else i
    vx, vy = movers[i, 2:].tolist()
    return f"{float(dist[i]):.2f} m, v ({vx:.1f}, {vy:.1f})"


def last_nearest(rows: list[dict]) -> list[str]:
    """Per row, the mover nearest at the last row (the one a collision with a mover struck), as
    :func:`describe_mover` says it, so a turn or its first approach shows."""
    if not rows or rows[-1]["movers"] is None:
        return ["-"] * len(rows)
    i = int(rows[-1]["movers"][:, :2].norm(dim=-1).argmin())
    return [f"#{i} {describe_mover(r['movers'], i)}" for r in rows]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--env-seed", type=int, default=12345)
    parser.add_argument("--episode", type=int, default=0)
    parser.add_argument("--from-s", type=float, default=0.0)
    parser.add_argument("--to-s", type=float, default=60.0)
    parser.add_argument("--adopted", action="store_true",
                        help="behind the sliding filter (adopted before short moves), not the "
                        "one the policy records")  # fmt: skip
    parser.add_argument("--short-moves", action="store_true",
                        help="behind the filter adopted now, with its planner's short "
                        "moves")  # fmt: skip
    parser.add_argument(
        "--mapped",
        action="store_true",
        help="that filter with the handover map (screened, not adopted)",
    )
    parser.add_argument(
        "--nearer",
        action="store_true",
        help="the map and the 'nearer' leave condition (screened, not adopted)",
    )
    parser.add_argument("--every-step", action="store_true", help="a row per 0.1 s step")
    parser.add_argument(
        "--no-cap",
        action="store_true",
        help="the filter adopted now with the shield's braking cap off",
    )
    args = parser.parse_args()
    stats, rows = trace(args.checkpoint, args.env_seed, args.episode, args.adopted,
                        args.short_moves, args.mapped, args.nearer, args.no_cap)  # fmt: skip
    print(stats)
    print(
        "| t (s) | position (m) | to goal (m) | planner flies | handover steps left | nearest mover "
        "| the mover nearest at the end | action | flown |"
    )
    print("|---:|---|---:|---|---:|---|---|---|---|")
    struck = last_nearest(rows)
    for r, last in zip(rows, struck, strict=True):
        whole = abs(r["t"] - round(r["t"])) < 1e-6
        if (whole or args.every_step) and args.from_s <= r["t"] <= args.to_s:
            print(f"| {r['t']:.1f} | {r['pos']} | {r['to_goal']} | {r['planner']} | "
                  f"{r['handover_left']} | {describe_mover(r['movers'])} | {last} | {r['action']} | {r['flown']} |")  # fmt: skip
    planner = sum(r["planner"] for r in rows)
    print(f"\nthe planner flew {planner} of {len(rows)} steps")


if __name__ == "__main__":
    main()
