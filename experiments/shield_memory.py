"""The memory shield (``safenav eval --shield --shield-memory N``) on trained policies: success and
collision with no shield, the memoryless shield (N = 1) and shields that remember the range
images of the last N steps, on the validation maps (the choice of N is made there), then on the
test scenario and the held-out maps for the N chosen.

    .venv/bin/python experiments/shield_memory.py --policies checkpoints/csac-maxcost-crashloss-s1.pt ... \\
        --memory 0 1 5 10 20                       # validation: maps 12345-12348 x 100 episodes
    .venv/bin/python experiments/shield_memory.py --policies ... --memory 0 1 10 --maps test
    .venv/bin/python experiments/shield_memory.py --policies ... --memory 0 1 10 --maps heldout

``--memory 0`` is no shield; ``Nmap`` (e.g. ``1map``, ``20map``) adds the map scan
(``--shield-map``: ``MemoryShield(N, map_scan=True)``), and a suffix ``-moverX`` X metres more
clearance from the tracked moving obstacles (``ShieldConfig.mover_margin``), e.g. ``1map-mover0.3``,
and ``-lag`` a shield that models the env's velocity tracker (``ShieldConfig.response_time``:
candidates tested from where the vehicle really goes), e.g. ``1map-mover0.3-lag``, and ``-brake``
the braking cap (``--shield-brake``: ``ShieldConfig.brake_time``), e.g. ``1map-mover0.3-brake``,
or ``-slide`` its sliding form (``ShieldConfig.brake_slide``), e.g. ``1map-mover0.3-slide``,
and ``-keepK`` the candidate choice that keeps moving (``ShieldConfig.keep_moving`` = K, a
fraction of the policy's horizontal speed), e.g. ``1map-mover0.3-brake-keep0.5``, and a last
``-filter`` the model-predictive safety filter after that shield
(:class:`safenav.envs.planner.PlannerFilter`, the pillar planner's view of the simulator), e.g.
``1map-mover0.3-brake-filter``, or ``-filterobs`` the same filter seeing only what the vehicle
has on board (the observation's pillar list and movers: ``view="observation"``), either with
``-stall`` the planner's handover where a flight stalls (``stall=FILTER_STALL_TUMBLING``), or
``-stallP`` the same with P metres of progress in its window (e.g. ``-stall4``: ``(10, 4, 5)``), or
``-stallslide`` the handover's sliding test (``stall_test="sliding"``), ``-stallslideW`` the same
over a W s window with the same progress per second (e.g. ``-stallslide5``: ``(5, 1, 5)``);
``-short`` last: the filter's planner also weighs short moves (``short_moves=True``), and
``-mapped`` after it plans each stall handover on the pillars seen (``handover_map=True``), and
``-nearer`` after that ends each handover only nearer the goal (``handover_exit="nearer"``).
One JSON per
(policy, setting, map) in OUT
(a rerun skips those that exist), then a table of the mean over maps per (policy, setting) on
stdout and in OUT/table-MAPS.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import time
from pathlib import Path

import torch

from safenav.algos.policy import load_policy
from safenav.common.jsonout import write_json
from safenav.deploy.shield import shield_for_memory
from safenav.envs.planner import (
    FILTER_STALL_TUMBLING,
    PLANNER_PILLARS,
    PlannerFilter,
    behind_filter,
)
from safenav.experiments.evaluate import evaluate
from safenav.experiments.selection import HELDOUT_SEEDS, TEST_SEED, VALIDATION_SEEDS
from safenav.experiments.stats import outcomes_string

KEYS = ("success_rate", "collision_rate", "timeout_rate", "collision_static_rate",
        "collision_dynamic_rate", "mean_speed", "mean_time_to_goal", "collision_bounds_rate")  # fmt: skip


def label(path: Path) -> str:
    """A policy's short name: the file's stem, or for RUN/policy.pt the run's folder names."""
    return "-".join(path.parent.parts[-2:]) if path.stem == "policy" else path.stem


def _mean(values: list) -> float:
    """The mean of the values that exist (a time to goal is null where no episode arrived)."""
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else float("nan")


def parse_setting(setting: str) -> tuple[int, bool, float, bool, bool | str, float, str | None]:
    """``"20"`` -> (20, False, 0.0, False, False, 0.0, False); ``"20map"`` -> (20, True, 0.0,
    False, False, 0.0, False); ``"1map-mover0.3-lag"`` -> (1, True, 0.3, True, False, 0.0, False)
    (``-lag``: the shield models the env's velocity tracker, ``ShieldConfig.response_time``);
    ``"1map-mover0.3-brake"`` -> (1, True, 0.3, False, True, 0.0, False) (the braking cap);
    ``-slide``: its sliding form, ``"slide"`` there; ``-keep0.5``: ``ShieldConfig.keep_moving``
    0.5; ``-filter``, last: the planner filter after the shield (its view last: ``"simulator"``;
    ``-filterobs``: ``"observation"``; None without; ``-stall`` or ``-stallP`` after either:
    ``"...-stall"``, ``"...-stallP"``; ``-short`` last: ``"...-short"``, ``-mapped`` and
    ``-nearer`` after it: ``"...-mapped"``, ``"...-nearer"``; ``-turnT`` last: the filter's
    ``OracleConfig.mover_turn`` T s, ``"...-turnT"``)."""
    found = re.fullmatch(
        r"(\d+)(map)?(?:-mover([0-9.]+))?(-lag)?(-brake|-slide)?(?:-keep([0-9.]+))?"
        r"(-filter(?:obs)?(?:-stall(?:slide)?(?:[0-9.]+)?)?(?:-short)?(?:-mapped)?(?:-nearer)?"
        r"(?:-turn[0-9.]+)?)?",
        setting,
    )
    if found is None:
        raise SystemExit(f"shield setting {setting!r}: N, Nmap or either with -moverX, -lag, "
                         "-brake or -slide, -keepK, -filter or -filterobs")  # fmt: skip
    brake = {None: False, "-brake": True, "-slide": "slide"}[found[5]]
    keep = float(found[6] or 0.0)
    if not 0.0 <= keep <= 1.0:
        raise SystemExit(f"shield setting {setting!r}: -keepK takes K in [0, 1]")
    filtered, short, mapped, nearer, turn = filter_suffixes(found[7] or "")
    head, stall, progress = filtered.partition("-stall")
    view = {"": None, "-filter": "simulator", "-filterobs": "observation"}[head]
    if (mapped or nearer) and not stall:
        raise SystemExit(f"shield setting {setting!r}: -mapped and -nearer shape the stall "
                         "handovers (-stall)")  # fmt: skip
    if stall:
        view += "-stall" + progress
    if short:
        view += "-short"
    if mapped:
        view += "-mapped"
    if nearer:
        view += "-nearer"
    if turn:
        view += "-turn" + turn
    return (int(found[1]), found[2] is not None, float(found[3] or 0.0), found[4] is not None,
            brake, keep, view)  # fmt: skip


def filter_suffixes(text: str) -> tuple[str, bool, bool, bool, str]:
    """A filter setting's head and its trailing ``-short``, ``-mapped``, ``-nearer``, ``-turnT``
    (in that order): ``"-filterobs-stallslide5-short-mapped"`` -> ``("-filterobs-stallslide5",
    True, True, False, "")``, ``T`` as written last; the same for :func:`parse_setting`'s view
    ``"observation-stallslide5-..."``."""
    text, _, turn = text.partition("-turn")
    flags = []
    for suffix in ("-nearer", "-mapped", "-short"):
        flags.append(text.endswith(suffix))
        text = text.removesuffix(suffix)
    nearer, mapped, short = flags
    return text, short, mapped, nearer, turn


def stall_of(setting: str) -> tuple[tuple[float, float, float] | None, str]:
    """The filter's ``(stall, stall_test)``: ``""`` -> None (no handover); ``"stall"`` ->
    ``FILTER_STALL_TUMBLING`` (the first handover, 2 m in tumbling 10 s windows, which these
    settings were named after); ``"stallP"`` -> its window and handover with P metres of progress;
    with ``"slide"`` after ``"stall"`` the sliding test, and its number the window W s (progress
    0.2 W m): ``"stallslide5"`` is the adopted ``FILTER_STALL``."""
    if not setting:
        return None, "tumbling"
    window, progress, handover = FILTER_STALL_TUMBLING
    number = setting.removeprefix("stall")
    if number.startswith("slide"):
        number = number.removeprefix("slide")
        if number:
            window, progress = float(number), float(number) * progress / window
        return (window, progress, handover), "sliding"
    return (window, float(number) if number else progress, handover), "tumbling"


def run(
    policies: list[Path], memories: list[str], maps: list[tuple[int, int]], out: Path
) -> list[dict]:
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for path in policies:
        fn = load_policy(path)
        cfg = fn.env_config()
        for m in memories:
            per_map = []
            for seed, episodes in maps:
                f = out / f"{label(path)}-m{m}-seed{seed}-{episodes}.json"
                if not f.exists():
                    memory, scan, mover, lag, brake, keep, filtered = parse_setting(m)
                    shield = shield_for_memory(memory, scan, mover, lag, brake, keep)
                    extra = {"keep_moving": keep} if keep else {}
                    if filtered:
                        head, short, mapped, nearer, turn = filter_suffixes(filtered)
                        view, _, stall = head.partition("-")
                        stall_setting, stall_test = stall_of(stall)
                        config = (dataclasses.replace(PLANNER_PILLARS, mover_turn=float(turn))
                                  if turn else None)  # fmt: skip
                        planner_filter = PlannerFilter(config, view=view, stall=stall_setting,
                                                       stall_test=stall_test, short_moves=short,
                                                       handover_map=mapped,
                                                       handover_exit="nearer" if nearer
                                                       else "time")  # fmt: skip
                        shield = behind_filter(shield, planner_filter)
                    started = time.perf_counter()
                    r = evaluate(fn, cfg, env_seed=seed, episodes=episodes, shield=shield)
                    extra["outcomes"] = outcomes_string(r.pop("per_episode", None))
                    if filtered:  # the share of the flown steps where the planner flew
                        extra["filter_override_share"] = planner_filter.override_share
                        if stall:
                            extra["filter_handover_share"] = planner_filter.handover_share
                    write_json(f, {**r, "policy": str(path), "shield_memory": memory,
                                   "shield_map": scan, "mover_margin": mover,
                                   "response": lag, "brake": brake, **extra,
                                   "eval_wall_clock_s": round(time.perf_counter() - started, 1),
                                   })  # fmt: skip
                per_map.append(json.loads(f.read_text()))
            mean = {k: _mean([r[k] for r in per_map]) for k in KEYS}
            rows.append({"policy": label(path), "memory": m, **mean})
            print(f"{label(path):28s} m={m:>6s}  " + "  ".join(f"{k.split('_rate')[0]} {mean[k]:.3f}"
                  for k in KEYS[:5]), flush=True)  # fmt: skip
    return rows


def paired_differences(
    rows: list[dict], memories: list[str], against: list[str] | None = None
) -> list[str]:
    """Per setting, its success and collision minus those of each setting in ``against`` listed
    before it (default: without the shield, 0, and behind the memoryless shield, 1), paired by
    policy: the mean and a 95 % percentile bootstrap CI over the policies (scipy), a table in
    markdown."""
    from scipy.stats import bootstrap

    out = ["Paired by policy (mean difference, 95 % bootstrap CI over the policies):", "",
           "| memory N | against | success | collision |", "|---:|---:|---|---|"]  # fmt: skip
    by = {(r["policy"], r["memory"]): r for r in rows}
    policies = list(dict.fromkeys(r["policy"] for r in rows))
    for base in (b for b in (against or ["0", "1"]) if b in memories):
        for m in memories[memories.index(base) + 1 :]:
            cells = []
            for k in ("success_rate", "collision_rate"):
                d = [by[p, m][k] - by[p, base][k] for p in policies]
                mean = sum(d) / len(d)
                if len(d) > 1 and len(set(d)) > 1:
                    ci = bootstrap((d,), lambda x: x.mean(), method="percentile", n_resamples=10000,
                                   random_state=0).confidence_interval  # fmt: skip
                    cells.append(f"{mean:+.3f} ({ci.low:+.3f} to {ci.high:+.3f})")
                else:
                    cells.append(f"{mean:+.3f}")
            out.append(f"| {m} | {base} | " + " | ".join(cells) + " |")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policies", nargs="+", type=Path, required=True)
    ap.add_argument(
        "--memory",
        nargs="+",
        default=["0", "1", "5", "10", "20"],
        help="shield settings: N range images (0: no shield), Nmap with the map scan",
    )
    ap.add_argument(
        "--maps",
        choices=("validation", "test", "heldout"),
        default="validation",
        help="validation: maps 12345-12348 x 100 episodes; test: env seed 1 x 200; "
        "heldout: seeds 2-6 x 200",
    )
    ap.add_argument("--out", type=Path, default=Path("results/shield-memory"))
    ap.add_argument(
        "--against",
        nargs="+",
        default=None,
        help="settings the later ones are paired against (default: 0 and 1)",
    )
    args = ap.parse_args()
    torch.set_num_threads(1)
    maps = {
        "validation": [(s, 100) for s in VALIDATION_SEEDS],
        "test": [(TEST_SEED, 200)],
        "heldout": [(s, 200) for s in HELDOUT_SEEDS],
    }[args.maps]
    rows = run(args.policies, args.memory, maps, args.out)
    lines = [f"Mean over the {args.maps} maps ({', '.join(f'seed {s} x {e}' for s, e in maps)}):", "",
             "| policy | shield memory (0: none) | " + " | ".join(KEYS) + " |",
             "|---|---:|" + "---:|" * len(KEYS)]  # fmt: skip
    lines += [f"| {r['policy']} | {r['memory']} | " + " | ".join(f"{r[k]:.3f}" for k in KEYS) + " |"
              for r in rows]  # fmt: skip
    # the choice of N is made on the validation maps' mean over the policies
    lines += ["", "Mean over the policies:", "",
              "| shield memory (0: none) | " + " | ".join(KEYS[:5]) + " |", "|---:|" + "---:|" * 5]  # fmt: skip
    for m in args.memory:
        sel = [r for r in rows if r["memory"] == m]
        means = (_mean([r[k] for r in sel]) for k in KEYS[:5])
        lines.append(f"| {m} | " + " | ".join(f"{v:.3f}" for v in means) + " |")
    lines += ["", *paired_differences(rows, args.memory, args.against)]
    (args.out / f"table-{args.maps}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
