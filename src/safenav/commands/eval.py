"""``safenav eval``: the fixed test scenario of paper IV-B, as JSON."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import tyro

from safenav.cli import app


@app.command(name="eval")
def eval_(
    checkpoint: tyro.conf.Positional[Path | None] = None,
    env_seed: int = 1,
    episodes: int = 200,
    shield: bool = False,
    shield_memory: int = 0,
    shield_map: bool = False,
    shield_mover_margin: float = 0.0,
    shield_brake: bool = False,
    planner_filter: bool = False,
    planner_filter_view: Literal["observation", "simulator"] = "observation",
    json_out: Annotated[Path | None, tyro.conf.arg(name="json")] = None,
    policy: Literal[
        "checkpoint", "scripted", "straight", "border", "random", "planner"
    ] = "checkpoint",
    preset: str | None = None,
    collision_rule: Literal["body", "navrl"] = "body",
    device: str = "cpu",
) -> None:
    """Evaluate a policy on the fixed test scenario (map of env seed 1, full density, 200 fixed
    start/goal episodes, deterministic actions) and print success / collision / timeout rates and
    how it flew (detour ratio, time near the border).

    ``--shield`` corrects actions with the velocity-obstacle safety shield; ``--planner-filter``
    then lets the pillar planner fly wherever the command leaves no way out. ``--preset`` overrides
    the checkpoint's env preset. ``--policy scripted`` evaluates the potential-field baseline,
    ``straight`` flies straight at the goal, ``border`` around the field along the border (the
    loophole probe: it must fail in the closed arena), ``planner`` the privileged planner B
    (docs/csac-v1.md: it reads the simulator's state; a reference for how hard a map is).

    Args:
        checkpoint: Policy or training checkpoint, or a run directory (its checkpoint.pt).
        env_seed: Env seed of the map to fly: 1 = the test scenario (the paper protocol's), 2-6 the
            held-out maps, 12345-12348 the validation maps (the title says which).
        episodes: Episodes to fly, all at once (one env each); the protocol flies 200.
        shield: Correct the actions with the velocity-obstacle safety shield.
        shield_memory: With --shield: its static obstacles are the range images of the last N
            steps, kept where they were seen (beyond NavRL's shield; 0 or 1: the current image).
        shield_map: With --shield: it also avoids every pillar the height map holds at the UAV's
            lower extent (a level scan of the map, beyond NavRL's shield).
        shield_mover_margin: With --shield: metres more clearance from tracked moving obstacles
            (0-2; beyond NavRL's shield).
        shield_brake: With --shield: the braking cap: near a static obstacle, the ground or the
            ceiling the shield slows the vehicle to a speed it can stop from (beyond NavRL's).
        planner_filter: After the shield (if any), the model-predictive safety filter: each
            command is rolled out 2 s through the vehicle's velocity response against the
            pillars, wall and moving obstacles within 4 m, and the pillar planner flies where it
            leaves no way out, and for 5 s where a flight came less than 1 m nearer its goal
            over the last 5 s (beyond the paper; docs/csac-v1.md). A policy trained with
            --flight-filter flies behind the filter it records unless --no-planner-filter.
        planner_filter_view: What the filter sees: observation (what the vehicle has on board:
            the observation's pillar list and tracked movers, for policies trained with it) or
            simulator (the pillars and movers within 4 m, read from the simulator: any policy).
        json_out: Also write the metrics here as JSON (no value: null); the directory must exist.
        policy: What flies: the checkpoint, or a baseline without one.
        preset: Env preset (easy, medium, paper); default: the checkpoint's, else paper.
        collision_rule: What counts as a static collision: body (the UAV's 0.3 m sphere touches
            a pillar, the default) or navrl (NavRL's rule: a range-image beam reads < 0.3 m, so
            a graze of a pillar top no beam sees flies on; for figures comparable with
            NavRL-based papers).
        device: Torch device of the env and the policy (cpu or cuda).
    """
    from rich.console import Console
    from rich.table import Table

    from safenav import ENV_ID
    from safenav.experiments.evaluate import evaluate
    from safenav.experiments.flight import flight_filter, resolve_policy, scenario_config

    check_eval_args(env_seed, episodes, json_out, device, preset)
    memory = check_shield_memory(shield, shield_memory, shield_map, shield_mover_margin,
                                 shield_brake)  # fmt: skip
    fn, cfg = resolve_policy(checkpoint, policy, device)
    cfg = scenario_config(cfg, preset).replace(collision_rule=collision_rule)
    if policy == "checkpoint":
        from safenav.algos.policy import check_fits_safenav

        check_fits_safenav(fn, cfg, checkpoint)
        trained_on = str(fn.meta.get("env_id", ""))
        if trained_on.split(":")[-1] != ENV_ID:
            # Same observations, another arena: SafeNav-v0 had no border and a free ring.
            Console(stderr=True).print(f"note: {checkpoint} was trained on {trained_on}; "
                                       f"evaluating it on {ENV_ID}")  # fmt: skip
        memory, shield_map, shield_mover_margin, shield_brake = own_shield_settings(
            fn, checkpoint, memory, shield_map, shield_mover_margin, shield_brake)  # fmt: skip
        shield = memory > 0
    spec = own_planner_filter(fn if policy == "checkpoint" else None, checkpoint, planner_filter,
                              planner_filter_view)  # fmt: skip
    shield_brake = brake_under_filter(spec, shield_brake)
    the_filter = flight_filter(spec, cfg) if spec else None
    shield_fn = None
    if memory:  # the shield's module loads Numba (~0.35 s): only when it flies
        from safenav.deploy.shield import shield_for_memory

        shield_fn = shield_for_memory(memory, shield_map, shield_mover_margin, brake=shield_brake)
    if the_filter is not None:
        from safenav.envs.planner import behind_filter

        shield_fn = behind_filter(shield_fn, the_filter)
    result = evaluate(fn, cfg, env_seed=env_seed, episodes=episodes, device=device,
                      shield=shield_fn, progress=True)  # fmt: skip
    result["checkpoint"] = str(checkpoint) if checkpoint else policy
    result["shield"] = shield
    if shield:
        result["shield_memory"] = memory
        result["shield_map"] = shield_map
        result["shield_mover_margin"] = shield_mover_margin
        result["shield_brake"] = shield_brake
    result["planner_filter"] = the_filter is not None
    if the_filter is not None:  # and the share of the flown steps where the planner flew
        result["planner_filter_view"] = spec["view"]
        result["planner_filter_spec"] = spec
        result["planner_filter_override_share"] = the_filter.override_share
        result["planner_filter_handover_share"] = the_filter.handover_share
    result["env"] = ENV_ID
    result["collision_rule"] = collision_rule
    if policy == "checkpoint":
        result["trained_on"] = str(fn.meta.get("env_id", ""))
    from safenav.experiments.selection import HELDOUT_SEEDS, TEST_SEED, VALIDATION_SEEDS

    role = ("the test scenario" if env_seed == TEST_SEED else "a held-out map"
            if env_seed in HELDOUT_SEEDS else "a validation map" if env_seed in VALIDATION_SEEDS
            else "the map")  # fmt: skip
    rule = "" if collision_rule == "body" else f", {collision_rule} collision rule"
    table = Table(title=f"{role}: env seed {env_seed}, {episodes} episodes{rule}")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for key in ("success_rate", "collision_rate", "timeout_rate", "mean_time_to_goal",
                "collision_static_rate", "collision_dynamic_rate", "collision_bounds_rate",
                "collision_border_rate", "detour_ratio", "border_time_fraction",
                "outside_time_fraction", "mean_path_length", "min_clearance", "mean_speed"):  # fmt: skip
        table.add_row(key, f"{result[key]:.3f}")
    if planner_filter:
        table.add_row(
            "planner_filter_override_share", f"{result['planner_filter_override_share']:.3f}"
        )
    Console().print(table)
    if json_out is not None:
        from safenav.common.jsonout import write_json

        write_json(json_out, result)  # NaN (no value) as null: valid JSON


def check_shield_memory(shield: bool, shield_memory: int, shield_map: bool = False,
                        shield_mover_margin: float = 0.0, shield_brake: bool = False) -> int:  # fmt: skip
    """``--shield-memory N``: 0-100 range images, and only with ``--shield``, as ``--shield-map``,
    ``--shield-mover-margin`` (0-2 m) and ``--shield-brake``. Returns the memory the flight gets:
    0 without the shield, 1 for the memoryless shield, else N."""
    from safenav.common.checks import in_range
    from safenav.errors import SafenavError

    in_range("--shield-memory", shield_memory, 0, 100)
    in_range("--shield-mover-margin", shield_mover_margin, 0.0, 2.0, "metres")
    if shield_mover_margin > 0 and not shield:
        raise SafenavError("--shield-mover-margin needs --shield (it is the shield's clearance)")
    if shield_memory > 1 and not shield:
        raise SafenavError(
            f"--shield-memory {shield_memory} needs --shield (it is the shield's memory)"
        )
    if shield_map and not shield:
        raise SafenavError("--shield-map needs --shield (it is what the shield sees)")
    if shield_brake and not shield:
        raise SafenavError("--shield-brake needs --shield (it is how the shield slows the vehicle)")
    return max(shield_memory, 1) if shield else 0


SHIELD_FLAGS = ("shield", "shield-memory", "shield-map", "shield-mover-margin", "shield-brake")


def own_shield_settings(policy, checkpoint, memory: int, shield_map: bool, mover_margin: float,
                        brake: bool = False) -> tuple[int, bool, float, bool]:  # fmt: skip
    """The shield a flight gets: a policy trained behind the shield (``safenav train --shield``)
    flies behind the shield it records for flight (``meta["flight_shield"]``, else
    ``meta["shield"]``) unless a shield option is given (``--no-shield``
    flies it alone); otherwise the options' ``(memory, shield_map, mover_margin, brake)`` as they
    are."""
    from safenav.cli import ARGS
    from safenav.commands.train import given_flag
    from safenav.common.config import flight_shield_spec

    spec = flight_shield_spec(policy.meta)
    if not spec or any(given_flag(f, ARGS.get()) for f in SHIELD_FLAGS):
        return memory, shield_map, mover_margin, brake
    from rich.console import Console

    from safenav.deploy.shield import brake_setting  # loads Numba: only for a shielded policy

    memory, shield_map, mover_margin, brake = (
        int(spec["memory"]),
        bool(spec["map"]),
        float(spec["mover_margin"]),
        brake_setting(spec.get("brake", False)),  # policies trained before the braking cap lack it
    )
    what = ", ".join([f"memory {memory}", *(["map scan"] if shield_map else []),
                      *([f"+{mover_margin:g} m from movers"] if mover_margin else []),
                      *(["braking cap"] if brake else [])])  # fmt: skip
    alone = "without the shield" if policy.meta.get("flight_filter") else "alone"
    Console(stderr=True).print(f"note: {checkpoint} trained behind the safety shield and flies "
                               f"behind it ({what}; --no-shield: {alone})")  # fmt: skip
    return memory, shield_map, mover_margin, brake


def brake_under_filter(spec: dict | None, brake):
    """The shield's braking cap before the planner filter ``spec``: off where the filter records
    ``"braking_cap": false`` (the adopted one: :data:`~safenav.envs.planner.FILTER_BRAKING_CAP`)
    and no shield option is given, else ``brake`` as it is."""
    from safenav.cli import ARGS
    from safenav.commands.train import given_flag
    from safenav.envs.planner import lifts_braking_cap

    if not brake or not lifts_braking_cap(spec):
        return brake
    if any(given_flag(f, ARGS.get()) for f in SHIELD_FLAGS):
        return brake
    from rich.console import Console

    Console(stderr=True).print("note: behind the planner filter the shield flies without its "
                               "braking cap (the filter's record; --shield-brake: with it)")  # fmt: skip
    return False


def own_planner_filter(policy, checkpoint, planner_filter: bool, view: str) -> dict | None:
    """The planner filter a flight gets, as a :func:`~safenav.envs.planner.filter_spec` (None:
    none): a policy that records one (``safenav train --flight-filter``: ``meta["flight_filter"]``)
    flies behind that one, as it was reported, unless ``--planner-filter`` /
    ``--no-planner-filter`` is given (``--planner-filter-view`` alone changes only what it sees);
    otherwise the options' filter: with ``--planner-filter``, the adopted one seeing ``view``."""
    from safenav.cli import ARGS
    from safenav.commands.train import given_flag
    from safenav.envs.planner import filter_from_spec, filter_spec

    spec = policy.meta.get("flight_filter") if policy is not None else None
    if not spec or given_flag("planner-filter", ARGS.get()):
        return filter_spec(view) if planner_filter else None
    from rich.console import Console

    from safenav.errors import SafenavError

    try:
        filter_from_spec(spec)
    except ValueError as err:
        raise SafenavError(f"{checkpoint} records {err}: pass --planner-filter (the adopted "
                           "filter) or --no-planner-filter") from None  # fmt: skip
    if given_flag("planner-filter-view", ARGS.get()):
        spec = {**spec, "view": view}
    Console(stderr=True).print(f"note: {checkpoint} flies behind the planner filter it records "
                               f"({describe_filter(spec)}; --no-planner-filter: without)")  # fmt: skip
    return spec


def describe_filter(spec: dict) -> str:
    """``"observation view, stall handover under 1 m in 5 s sliding, 5 s"``: a filter spec in
    words."""
    from safenav.envs.planner import lifts_braking_cap

    short = ", short moves" if spec.get("short_moves") else ""
    if lifts_braking_cap(spec):
        short += ", the shield's braking cap off"
    stall = spec.get("stall")
    if stall is None:
        return f"{spec['view']} view, no stall handover{short}"
    window, progress, handover = stall
    test = spec.get("stall_test", "tumbling")
    return (f"{spec['view']} view, stall handover under {progress:g} m in {window:g} s {test}, "
            f"{handover:g} s{short}")  # fmt: skip


def check_eval_args(env_seed: int, episodes: int, json_out: Path | None, device: str,
                    preset: str | None) -> None:  # fmt: skip
    """Refuse bad values before the policy flies a single episode."""
    from safenav.common.checks import (
        at_least,
        check_device,
        check_memory,
        check_output_file,
        in_range,
    )
    from safenav.common.config import MAX_SEED
    from safenav.common.memory import env_bytes
    from safenav.envs.config import make_config

    in_range("--env-seed", env_seed, 0, MAX_SEED)
    at_least("--episodes", episodes, 1)
    check_device(device)
    cfg = make_config(preset or "paper")  # ValueError for an unknown preset: exit 2
    if json_out is not None:
        check_output_file(json_out, "--json", "eval.json")
    # every episode is one env of a single vector env
    check_memory(env_bytes(episodes, cfg), f"--episodes {episodes:,} (one env each)",
                 "evaluate fewer episodes")  # fmt: skip
