"""Pieces of a training run: episode charts, the final summary, config.json.

Kept apart from the loop (:mod:`safenav.training.trainer`) as plain functions of plain values.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from safenav.common.config import RunConfig, to_dict
from safenav.common.logger import write_json_atomic
from safenav.envs.vector import is_safenav


def nanmean(values: Iterable[float]) -> float:
    """Mean of the non-NaN values; NaN when there are none."""
    vals = [v for v in values if not math.isnan(v)]
    return sum(vals) / len(vals) if vals else math.nan


def episode_charts(window: Mapping[str, list[float]]) -> dict[str, float]:
    """The ``charts/*`` episode columns: means over the episodes that ended in the interval."""
    row = {f"charts/{name}": nanmean(window.get(key, [])) for name, key in (
        ("episodic_return", "return"), ("episodic_cost", "cost"), ("episodic_length", "length"),
        ("success_rate", "success"), ("collision_rate", "collision"), ("timeout_rate", "timeout"),
    )}  # fmt: skip
    row["charts/episodes"] = len(window.get("return", []))
    return row


def run_summary(
    global_step: int, updates: int, recent: Mapping[str, Iterable[float]]
) -> dict[str, Any]:
    """What ``train`` returns: step and update counts, and the rates and mean return of the
    recent (up to 100) training episodes, ``episodes`` of them."""
    return {"global_step": global_step, "updates": updates,
            "success_rate": nanmean(recent["success"]), "collision_rate": nanmean(recent["collision"]),
            "return": nanmean(recent["return"]), "episodes": len(list(recent["return"]))}  # fmt: skip


def write_run_config(
    run_dir: Path,
    algo: str,
    run: RunConfig,
    section: str,
    cfg: Any,
    recipe: dict[str, Any] | None = None,
) -> None:
    """``config.json``: the resolved configuration, the recipe it started from (``safenav train
    --config``) and the SafeNav env config, for reference."""
    data: dict[str, Any] = {"algo": algo, "run": to_dict(run), section: to_dict(cfg)}
    if recipe is not None:
        data["recipe"] = recipe
    if is_safenav(run.env):
        from safenav.envs.config import make_config

        data["env_config"] = to_dict(make_config(run.preset or "paper", **run.env_kwargs))
    write_json_atomic(Path(run_dir) / "config.json", data)


__all__ = ["episode_charts", "nanmean", "run_summary", "write_run_config"]
