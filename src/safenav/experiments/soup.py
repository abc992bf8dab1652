"""The greedy soup of a run's kept policies, decided on validation: ``safenav average --greedy``.

Greedy soup (Wortsman et al., 2022, "Model soups: averaging weights of multiple fine-tuned models
improves accuracy without increasing inference time", Recipe 1): rank the candidate policies by
their own validation score; start the soup with the best; try each next one in that order and
keep it in the soup when the soup's validation score with it does not drop. The soup is the
weight average of its members (:func:`~safenav.algos.averaging.average_policy_states`).

The validation set is the evaluation maps (``EVAL_SEED``, the maps of the periodic evaluations),
never the fixed test scenario (env seed 1): choosing on the test would overfit it. Why greedy
rather than a fixed window: a run whose late policies turn cautious (run s20: timeouts 0.4-0.6
after 4.5 M steps) drags a fixed average down, and the greedy soup leaves them out; over the
eight 60-minute CSAC runs it tests at 0.857 success on average, none below 0.835
(docs/csac.md, "Weight averaging of the late policies").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from safenav.algos.averaging import average_policy_states, check_snapshots
from safenav.errors import SafenavError

Score = Callable[[dict[str, Any]], float]


def greedy_soup(
    states: Sequence[dict[str, Any]],
    score: Score,
    on_step: Callable[[dict[str, Any]], None] | None = None,
    rank_scores: dict[int, float] | None = None,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Greedy soup of ``states`` (policy checkpoint dicts of one run) under ``score`` (a policy
    state -> validation score, higher is better). Returns the soup's policy state and the log:
    one row per policy scored alone, then one per candidate soup (``kept`` or not), each with its
    ``steps`` and ``score``. Ties in the ranking keep the earlier step first; a candidate that
    leaves the score unchanged is kept (as in the paper's ``>=``).

    ``rank_scores`` (global step -> a validation score already measured, e.g. the periodic
    evaluation's) orders the policies without flying each one: only the best-ranked policy alone
    and the candidate soups are scored (rows of kind ``rank`` record the given scores)."""
    if not states:
        raise SafenavError("no policies to make a soup of")
    check_snapshots(states)  # refuse policies of different networks or runs before flying
    log: list[dict[str, Any]] = []

    def record(row: dict[str, Any]) -> None:
        log.append(row)
        if on_step is not None:
            on_step(row)

    ranked = []
    for st in sorted(states, key=lambda s: int(s["global_step"])):
        step = int(st["global_step"])
        if rank_scores is not None:
            if step not in rank_scores:
                raise SafenavError(f"no ranking score for the policy of step {step}")
            value = float(rank_scores[step])
            record({"kind": "rank", "steps": [step], "score": value})
        else:
            value = float(score(st))
            record({"kind": "single", "steps": [step], "score": value})
        ranked.append((value, st))
    ranked.sort(key=lambda vs: -vs[0])  # stable: ties keep the earlier step first
    best, soup = ranked[0][0], [ranked[0][1]]
    if rank_scores is not None:  # the comparisons below are on score(), so score the first too
        best = float(score(soup[0]))
        record({"kind": "single", "steps": [int(soup[0]["global_step"])], "score": best})
    for _, st in ranked[1:]:
        members = sorted([*soup, st], key=lambda s: int(s["global_step"]))
        value = float(score(average_policy_states(members)))
        kept = value >= best
        record({"kind": "soup", "steps": [int(s["global_step"]) for s in members],
                "score": value, "kept": kept})  # fmt: skip
        if kept:
            best, soup = value, members
    return average_policy_states(soup), log


def policy_from_state(state: dict[str, Any], device: str = "cpu"):
    """``(policy, env_config)`` of a policy state in memory; SafeNav policies only."""
    from safenav.algos.policy import policy_from_state as build

    policy = build(state, f"the policy of step {state.get('global_step')}", device)
    cfg = policy.env_config()
    if cfg is None:
        raise SafenavError("--greedy validates on SafeNav's evaluation maps: these policies "
                           "were not trained on SafeNav")  # fmt: skip
    return policy, cfg


def validation_score(episodes: int, device: str = "cpu") -> Score:
    """Success rate of a policy state on ``episodes`` episodes of the evaluation map
    (``EVAL_SEED``; deterministic actions, the scenario of ``safenav eval``)."""
    from safenav.experiments.evaluate import evaluate
    from safenav.training.evaluation import EVAL_SEED

    def score(state: dict[str, Any]) -> float:
        from safenav.experiments.selection import own_shield

        fn, cfg = policy_from_state(state, device)
        return float(evaluate(fn, cfg, env_seed=EVAL_SEED, episodes=episodes, device=device,
                              shield=own_shield(fn))["success_rate"])  # fmt: skip

    return score


__all__ = ["greedy_soup", "policy_from_state", "validation_score"]
