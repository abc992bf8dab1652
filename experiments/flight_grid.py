"""The same validation flights, one row per algorithm: what a success rate hides, at a glance.

For each label of a ``safenav reproduce`` output (``OUT/runs/LABEL/seedS/policy.pt``) it takes the
seed whose last validation evaluation is the median of the label's seeds (``OUT/trials/*.json``:
chosen on validation maps only, never on the test), flies the given episodes of one validation map
with it, and writes

- ``--out PNG``: a grid of each flight's last frame (the trail shows the whole path, the corner
  the outcome), one row per label, one column per episode;
- ``--gif GIF`` (optional): the same flights side by side as they happen, one tile per label, for
  the first episode given.

    .venv/bin/python experiments/flight_grid.py results/paper-observation --labels csac sac ppo \\
        sac_lag ppo_lag --also results/csac-maxcost-crashloss --env-seed 12345 --episodes 0 1 2 3 \\
        --out results/paper-observation/figures/flights-val.png \\
        --gif results/paper-observation/figures/flights-val.gif

``--shield-memory 0 1 10`` flies each label three times: without the shield, behind it, and
behind the shield that remembers the last 10 range images (one row each). ``--as-recorded`` flies
each policy as ``safenav render`` does by default: behind the shield and the planner filter its
checkpoint records (the flight stack of results/paper since 2026-12-06), one row per label:

    .venv/bin/python experiments/flight_grid.py results/paper --labels csac sac ppo sac_lag \
        ppo_lag --as-recorded --env-seed 12345 --episodes 0 1 2 \
        --out results/paper/figures/flights-val.png --gif results/paper/figures/flights-val.gif

A label's policy is its run directory's ``policy.pt`` or, in a fresh clone, the policy its trial
committed (``OUT/trials/LABEL-sS.pt``).

Test and held-out maps (env seeds 1-6) are refused: this is a look at the policies, not a report.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from safenav.common.config import flight_shield_spec
from safenav.common.jsonout import write_json
from safenav.deploy.shield import brake_setting
from safenav.envs.planner import shield_under_filter
from safenav.experiments.flight import fly_frames, resolve_policy
from safenav.experiments.selection import RESERVED_SEEDS


def median_seed(out: Path, label: str) -> tuple[int, float]:
    """The seed of ``label`` whose last validation success is the (lower) median of its seeds."""
    finals = {}
    for path in sorted((out / "trials").glob(f"{label}-s*.json")):
        rec = json.loads(path.read_text())
        curve = rec.get("validation_curve") or []
        if rec.get("algo") == label and curve:
            finals[int(rec["seed"])] = float(curve[-1]["success_rate"])
    if not finals:
        raise SystemExit(f"{out}/trials: no trial of {label!r} with a validation curve")
    target = statistics.median_low(finals.values())
    seed = min(s for s, v in finals.items() if v == target)
    return seed, target


def recorded_flight(policy: Path) -> dict:
    """:func:`fly_frames`'s keywords that fly ``policy`` as its checkpoint records: behind its
    flight shield (``meta["flight_shield"]``, as it flies under its planner filter) and its
    planner filter (``meta["flight_filter"]``), what ``safenav render`` does by default."""
    fn, _ = resolve_policy(policy, "checkpoint")
    planner_filter = fn.meta.get("flight_filter")
    spec = shield_under_filter(flight_shield_spec(fn.meta), planner_filter)
    flight = {"planner_filter": planner_filter}
    if spec:
        flight |= {"shield_memory": int(spec["memory"]), "shield_map": bool(spec["map"]),
                   "shield_mover_margin": float(spec["mover_margin"]),
                   "shield_brake": brake_setting(spec.get("brake", False))}  # fmt: skip
    return flight


def caption(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` with a white band above it holding ``text``."""
    img = Image.fromarray(image)
    band = Image.new("RGB", (img.width, 22), "white")
    ImageDraw.Draw(band).text((6, 5), text, fill="black")
    out = Image.new("RGB", (img.width, img.height + band.height), "white")
    out.paste(band, (0, 0))
    out.paste(img, (0, band.height))
    return np.asarray(out)


def tile(rows: list[list[np.ndarray]], scale: float) -> np.ndarray:
    """One image of equally sized ``rows`` of frames, each frame scaled by ``scale``."""
    h, w = rows[0][0].shape[:2]
    size = (int(w * scale), int(h * scale))
    grid = Image.new("RGB", (size[0] * len(rows[0]), size[1] * len(rows)), "white")
    for r, row in enumerate(rows):
        for c, frame in enumerate(row):
            grid.paste(
                Image.fromarray(frame).resize(size, Image.LANCZOS), (c * size[0], r * size[1])
            )
    return np.asarray(grid)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out_dir", type=Path, help="a safenav reproduce output directory")
    parser.add_argument("--labels", nargs="+", required=True)
    parser.add_argument("--env-seed", type=int, default=12345, help="a validation map")
    parser.add_argument("--episodes", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--out", type=Path, required=True, help="the grid (PNG)")
    parser.add_argument("--gif", type=Path, help="the first episode's flights side by side (GIF)")
    parser.add_argument("--scale", type=float, default=0.5, help="size of each tile (of 600 px)")
    parser.add_argument(
        "--gif-seconds", type=float, default=30.0, help="how much of each flight the GIF shows (s)"
    )
    parser.add_argument("--shield-memory", type=int, nargs="+", default=[0],
                        help="one row per value for each label: 0 no shield, 1 the shield, N > 1 "
                             "the shield with the range images of the last N steps")  # fmt: skip
    parser.add_argument("--also", type=Path, nargs="*", default=[],
                        help="other reproduce outputs whose runs/ may hold a label's run "
                             "(e.g. results/csac-maxcost-crashloss, whose trials results/paper copied)")  # fmt: skip
    parser.add_argument("--as-recorded", action="store_true",
                        help="one row per label, each policy behind the shield and the planner "
                             "filter its checkpoint records (as safenav render flies it)")  # fmt: skip
    args = parser.parse_args(argv)
    if args.env_seed in RESERVED_SEEDS:
        raise SystemExit(f"env seed {args.env_seed} is a test or held-out map: look at the "
                         "policies on validation maps")  # fmt: skip
    rows, movies, summary = [], [], {}
    for label in args.labels:
        seed, final = median_seed(args.out_dir, label)
        candidates = [
            d / "runs" / label / f"seed{seed}" / "policy.pt" for d in (args.out_dir, *args.also)
        ] + [d / "trials" / f"{label}-s{seed}.pt" for d in (args.out_dir, *args.also)]
        policy = next((c for c in candidates if c.exists()), candidates[0])
        if not policy.exists():
            raise SystemExit(f"{policy}: missing (the run directories are not committed; "
                             "rerun the trial or point at the machine that ran it)")  # fmt: skip
        flights = [(label + (" + shield" if memory else "") + (f" (memory {memory})" if memory > 1
                    else ""), {"shield_memory": memory}) for memory in args.shield_memory]  # fmt: skip
        if args.as_recorded:
            flight = recorded_flight(policy)
            flown = [*(["shield"] if "shield_map" in flight else []),
                     *(["filter"] if flight.get("planner_filter") else [])]  # fmt: skip
            flights = [(label + (f" ({' + '.join(flown)})" if flown else ""), flight)]
        for name, flight in flights:
            row = []
            for i, episode in enumerate(args.episodes):
                frames, stats = fly_frames(policy, env_seed=args.env_seed, episode=episode,
                                           **flight)  # fmt: skip
                outcome = (
                    "goal" if stats["success"] else "collision" if stats["collision"] else "timeout"
                )
                title = f"{name} seed {seed} (median of validation, {final:.2f}): episode {episode}, {outcome}"
                row.append(caption(frames[-1], title))
                summary.setdefault(name, {"seed": seed, "validation_success": final})[episode] = (
                    stats
                )
                if i == 0:
                    movies.append([caption(f, f"{name} seed {seed}") for f in frames])
                print(f"{name} seed {seed} episode {episode}: {outcome}, {stats['time']:.1f} s")
            rows.append(row)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(tile(rows, args.scale)).save(args.out, optimize=True)
    print(f"wrote {args.out}")
    if args.gif is not None:
        # the first --gif-seconds of each flight (a timeout's last half-minute of hovering shows
        # nothing new), every third 0.1 s step at 10 frames a second: three times real time
        length = min(max(len(m) for m in movies), int(args.gif_seconds * 10)) + 9
        frames = [
            tile([[m[min(t, len(m) - 1)] for m in movies]], args.scale) for t in range(0, length, 3)
        ]
        # one fixed palette for every frame (web colours keep the trail's red and the goal's
        # green, which an adaptive palette merges away) and no dithering: a few MB, not tens
        images = [Image.fromarray(f).convert("P", palette=Image.Palette.WEB, dither=Image.Dither.NONE)
                  for f in frames]  # fmt: skip
        images[0].save(args.gif, save_all=True, append_images=images[1:], duration=100, loop=0,
                       optimize=True)  # fmt: skip
        print(f"wrote {args.gif} ({len(frames)} frames)")
    write_json(args.out.with_suffix(".json"), summary)


if __name__ == "__main__":
    main()
