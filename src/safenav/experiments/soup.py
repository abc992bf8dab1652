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

import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from safenav.algos.averaging import average_policy_states, check_snapshots
from safenav.common.checkpoint import save_checkpoint
from safenav.errors import SafenavError

Score = Callable[[dict[str, Any]], float]


def greedy_soup(
    states: Sequence[dict[str, Any]],
    score: Score,
    on_step: Callable[[dict[str, Any]], None] | None = None,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Greedy soup of ``states`` (policy checkpoint dicts of one run) under ``score`` (a policy
    state -> validation score, higher is better). Returns the soup's policy state and the log:
    one row per policy scored alone, then one per candidate soup (``kept`` or not), each with its
    ``steps`` and ``score``. Ties in the ranking keep the earlier step first; a candidate that
    leaves the score unchanged is kept (as in the paper's ``>=``)."""
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
        value = float(score(st))
        ranked.append((value, st))
        record({"kind": "single", "steps": [int(st["global_step"])], "score": value})
    ranked.sort(key=lambda vs: -vs[0])  # stable: ties keep the earlier step first
    best, soup = ranked[0][0], [ranked[0][1]]
    for _, st in ranked[1:]:
        members = sorted([*soup, st], key=lambda s: int(s["global_step"]))
        value = float(score(average_policy_states(members)))
        kept = value >= best
        record({"kind": "soup", "steps": [int(s["global_step"]) for s in members],
                "score": value, "kept": kept})  # fmt: skip
        if kept:
            best, soup = value, members
    return average_policy_states(soup), log


def validation_score(episodes: int, device: str = "cpu") -> Score:
    """Success rate of a policy state on ``episodes`` episodes of the evaluation maps
    (deterministic actions, the scenario of ``safenav eval`` on ``EVAL_SEED``)."""
    from safenav.common.evaluation import EVAL_SEED
    from safenav.experiments.evaluate import evaluate
    from safenav.experiments.flight import resolve_policy

    def score(state: dict[str, Any]) -> float:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "policy.pt"
            save_checkpoint(path, state)
            fn, cfg = resolve_policy(path, "checkpoint", device)
        if cfg is None:
            raise SafenavError("--greedy validates on SafeNav's evaluation maps: these policies "
                               "were not trained on SafeNav")  # fmt: skip
        res = evaluate(fn, cfg, env_seed=EVAL_SEED, episodes=episodes, device=device)
        return float(res["success_rate"])

    return score


__all__ = ["greedy_soup", "validation_score"]
