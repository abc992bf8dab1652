"""A run's final policy, chosen without the test scenario, and its report.

The env seeds of SafeNav's fixed scenarios fall in three disjoint sets (``docs/reproduce.md``,
"Seeds"):

- :data:`TEST_SEED` (1): the paper's fixed test scenario (IV-B). Final reports only.
- :data:`HELDOUT_SEEDS` (2-6): five more maps of the same kind, reported beside the test, never
  used for a choice.
- :data:`VALIDATION_SEEDS` (12345-12348): every choice (a run's policy, soups, hyperparameters).
  The periodic evaluation during training flies maps 12345 + w too (``EVAL_SEED``).

Training maps are drawn from seeds >= 100000 (``RunConfig.train_env_seed``).

:func:`select_final_policy` is what a run does when it ends (``safenav train --select``): the
greedy soup (:func:`~safenav.experiments.soup.greedy_soup`) of the policies it kept in the last
half of training, ranked by their periodic evaluations and compared on validation episodes,
written to ``RUN_DIR/policy.pt``. :func:`report_policy` then flies it on the test and held-out
scenarios.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from safenav.common.config import flight_shield_spec
from safenav.common.jsonout import write_json
from safenav.errors import SafenavError
from safenav.training.evaluation import EVAL_SEED

TEST_SEED = 1
HELDOUT_SEEDS = (2, 3, 4, 5, 6)
VALIDATION_SEEDS = (EVAL_SEED, EVAL_SEED + 1, EVAL_SEED + 2, EVAL_SEED + 3)
RESERVED_SEEDS = frozenset((TEST_SEED, *HELDOUT_SEEDS))
"""Seeds no training or selection code may fly (tests/test_selection.py checks it)."""


def validation_score(episodes: int = 256, device: str = "cpu") -> Callable[[dict[str, Any]], float]:
    """Success rate of a policy state on ``episodes`` validation episodes, spread evenly over
    the :data:`VALIDATION_SEEDS` maps (deterministic actions, the protocol of ``safenav eval``)."""
    from safenav.experiments.soup import policy_from_state

    per_map = max(1, math.ceil(episodes / len(VALIDATION_SEEDS)))

    def score(state: dict[str, Any]) -> float:
        from safenav.experiments.evaluate import evaluate

        fn, cfg = policy_from_state(state, device)
        rates = [evaluate(fn, cfg, env_seed=s, episodes=per_map, device=device,
                          shield=own_shield(fn))["success_rate"]
                 for s in VALIDATION_SEEDS]  # fmt: skip
        return float(sum(rates) / len(rates))

    return score


def own_shield(policy, planner_filter: dict | None = None):
    """A fresh shield of the kind ``policy`` flies behind (``safenav train --shield``: its
    ``meta["flight_shield"]``, or ``meta["shield"]`` for policies from before it), or None: such a
    policy is chosen and reported flying behind it. With ``planner_filter`` (a filter spec) the
    shield as it flies before that filter (:func:`~safenav.envs.planner.shield_under_filter`)."""
    from safenav.envs.planner import shield_under_filter

    spec = shield_under_filter(flight_shield_spec(policy.meta), planner_filter)
    if not spec:
        return None
    from safenav.deploy.shield import shield_from_spec  # loads Numba: only for such a policy

    return shield_from_spec(spec)


def select_final_policy(
    run_dir: str | Path,
    episodes: int = 256,
    last_fraction: float = 0.5,
    device: str = "cpu",
    on_step: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Choose ``run_dir/policy.pt`` on validation alone: the greedy soup of the policies kept
    (``--keep-policies``) in the last ``last_fraction`` of the run, ranked by their periodic
    evaluation (validation maps) and each candidate soup compared on ``episodes`` validation
    episodes. A run too short for any periodic evaluation keeps no policy: its final policy is
    taken, and the record says so. Returns the record written to ``run_dir/selection.json``."""
    from safenav.algos.averaging import load_policy_states
    from safenav.common.checkpoint import save_checkpoint
    from safenav.experiments.soup import greedy_soup

    run_dir = Path(run_dir)
    t0 = time.perf_counter()
    kept = run_dir / "policies"
    states = load_policy_states([kept]) if kept.is_dir() and any(kept.glob("*.pt")) else []
    if not states:
        from safenav.algos.policy import save_policy_only

        if not (run_dir / "checkpoint.pt").exists():
            raise SafenavError(f"{run_dir}: no policy files in policies/ and no checkpoint.pt")

        save_policy_only(run_dir / "checkpoint.pt", run_dir / "policy.pt")
        final = load_checkpoint_step(run_dir / "policy.pt")
        record = {"selection": "validation", "method": "final policy (no policy kept)",
                  "validation_seeds": list(VALIDATION_SEEDS), "validation_episodes": 0,
                  "candidates": [final], "chosen_steps": [final], "log": [],
                  "wall_clock_s": round(time.perf_counter() - t0, 1)}  # fmt: skip
        write_json(run_dir / "selection.json", record)
        return record
    last = max(int(s["global_step"]) for s in states)
    late = [s for s in states if int(s["global_step"]) >= (1.0 - last_fraction) * last]
    ranks = {int(s["global_step"]): _periodic_success(s) for s in late}
    state, log = greedy_soup(late, validation_score(episodes, device), on_step, rank_scores=ranks)
    save_checkpoint(run_dir / "policy.pt", state)
    record = {"selection": "validation", "method": "greedy soup", "validation_seeds": list(VALIDATION_SEEDS),
              "validation_episodes": episodes, "candidates": sorted(ranks), "chosen_steps": state["averaged_steps"],
              "log": log, "wall_clock_s": round(time.perf_counter() - t0, 1)}  # fmt: skip
    write_json(run_dir / "selection.json", record)
    return record


def load_checkpoint_step(path: Path) -> int:
    from safenav.common.checkpoint import load_checkpoint

    return int(load_checkpoint(path).get("global_step", 0))


def _periodic_success(state: dict[str, Any]) -> float:
    ev = state.get("evaluation") or {}
    value = float(ev.get("eval/success_rate", math.nan))
    return -1.0 if math.isnan(value) else value


def report_policy(
    policy: str | Path,
    episodes: int = 200,
    device: str = "cpu",
    heldout: Sequence[int] = HELDOUT_SEEDS,
) -> dict[str, Any]:
    """The final report of a chosen policy: the test scenario (:data:`TEST_SEED`) and each
    held-out map, ``episodes`` episodes each (success / collision / timeout and the arena
    metrics), plus the held-out episodes pooled, and the test scenario once more under NavRL's
    collision rule (``test_navrl_rule``: a static collision only where a beam reads it,
    ``EnvConfig.collision_rule``), the rule behind the paper's figures. A policy that records a
    planner filter (``meta["flight_filter"]``, ``safenav train --flight-filter``) flies every one
    of them behind it (the shares of steps the planner flew beside each), and the test scenario
    once more behind its shield alone (``test_without_filter``)."""
    from safenav.envs.planner import behind_filter, filter_from_spec, shield_under_filter
    from safenav.experiments.evaluate import evaluate
    from safenav.experiments.flight import resolve_policy

    fn, cfg = resolve_policy(Path(policy), "checkpoint", device)
    if cfg is None:
        raise SafenavError(f"{policy}: not a SafeNav policy, no test scenario to report on")
    keys = ("success_rate", "collision_rate", "timeout_rate", "detour_ratio",
            "border_time_fraction", "collision_static_rate", "collision_dynamic_rate",
            "collision_border_rate", "mean_time_to_goal", "min_clearance")  # fmt: skip

    filter_meta = fn.meta.get("flight_filter")

    def summary(seed: int, rule: str = "body", planner_filter: bool = True) -> dict[str, Any]:
        flies_filter = bool(filter_meta) and planner_filter
        shield, the_filter = own_shield(fn, filter_meta if flies_filter else None), None
        if flies_filter:
            the_filter = filter_from_spec(filter_meta)
            shield = behind_filter(shield, the_filter)
        res = evaluate(fn, cfg.replace(collision_rule=rule), env_seed=seed, episodes=episodes,
                       device=device, shield=shield)  # fmt: skip
        per_episode = {k: res["per_episode"][k] for k in ("success", "collision")}
        out = {k: res.get(k) for k in keys} | {"env_seed": seed, "episodes": episodes,
                                               "per_episode": per_episode}  # fmt: skip
        if the_filter is not None:  # the share of the flown steps where the planner flew
            out |= {"planner_filter_override_share": the_filter.override_share,
                    "planner_filter_handover_share": the_filter.handover_share}  # fmt: skip
        return out

    test = summary(TEST_SEED)
    held = [summary(s) for s in heldout]
    pooled = {k: float(sum(h[k] for h in held) / len(held)) for k in ("success_rate", "collision_rate",
                                                                     "timeout_rate")}  # fmt: skip
    report = {"test": test, "heldout": {"seeds": list(heldout), "episodes_per_seed": episodes,
                                        **pooled, "per_seed": held},
              "test_navrl_rule": summary(TEST_SEED, "navrl"),
              "shield": fn.meta.get("shield"),
              "flight_shield": flight_shield_spec(fn.meta)}  # fmt: skip
    if filter_meta:  # the system is reported; the policy behind its shield alone beside it
        report |= {"flight_filter": filter_meta,
                   "shield_under_filter": shield_under_filter(flight_shield_spec(fn.meta),
                                                              filter_meta),
                   "test_without_filter": summary(TEST_SEED, planner_filter=False)}  # fmt: skip
    return report


__all__ = ["HELDOUT_SEEDS", "RESERVED_SEEDS", "TEST_SEED", "VALIDATION_SEEDS", "own_shield", "report_policy",
           "select_final_policy", "validation_score"]  # fmt: skip
