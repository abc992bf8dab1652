"""Periodic evaluation during training: deterministic actions on a fixed set of episodes."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from safenav.envs.vector import TorchVecEnv

EVAL_SEED = 12345
"""Seed of the evaluation env: fixed, so that successive evaluations (and runs) see the same maps
and episodes; distinct from the training seeds and from the test scenario's env seed 1."""


@torch.no_grad()
def evaluate_episodes(env: TorchVecEnv, act: Callable[[dict[str, torch.Tensor]], torch.Tensor],
                      episodes: int, seed: int = EVAL_SEED, max_steps: int = 1_000_000) -> dict[str, float]:  # fmt: skip
    """Run every env of ``env`` for the same number of episodes (``ceil(episodes / num_envs)``, so
    short episodes are not over-represented) with actions ``act(obs)``; mean episode statistics."""
    quota = math.ceil(episodes / env.num_envs)
    done_count = torch.zeros(env.num_envs, dtype=torch.long, device=env.device)
    rows: dict[str, list[torch.Tensor]] = {}
    obs = env.reset(seed=seed)
    for _ in range(max_steps):
        if bool((done_count >= quota).all()):
            break
        step = env.step(act(obs))
        obs = step.next_obs
        if step.episodes is not None:
            ended = (step.terminated | step.truncated).nonzero().squeeze(-1)
            keep = done_count[ended] < quota
            done_count[ended] += 1
            for k, v in step.episodes.items():
                rows.setdefault(k, []).append(v[keep])
    out = {}
    for k, vs in rows.items():
        v = torch.cat(vs).float()
        v = v[~torch.isnan(v)]
        out[k] = float(v.mean()) if v.numel() else math.nan
    out["episodes"] = float(sum(len(v) for v in rows.get("return", [])))
    return out


class BestPolicy:
    """Keeps ``best.pt`` in a run directory: the policy of the periodic evaluation with the highest
    success rate (ties: the lower collision rate), as a policy-only checkpoint.

    Chosen on the evaluation maps (:data:`EVAL_SEED`), never on the fixed test scenario, so the
    test figures of ``best.pt`` stay an unbiased estimate. The score so far is part of the
    training checkpoint (:meth:`state_dict`), so a resumed run keeps comparing with it. With
    ``keep_dir`` (``--keep-policies``) every offered policy is also kept there as
    ``step_<global_step>.pt``, for a sweep over a run's policies (experiments/checkpoint_sweep.py).
    """

    def __init__(self, path: str | Path, state: dict[str, Any] | None = None,
                 keep_dir: str | Path | None = None) -> None:  # fmt: skip
        self.path = Path(path)
        self.keep_dir = Path(keep_dir) if keep_dir is not None else None
        self.score: tuple[float, float] | None = None
        if state and state.get("score") is not None:
            self.score = (float(state["score"][0]), float(state["score"][1]))

    @classmethod
    def for_run(
        cls, run_dir: Path, keep_policies: bool, checkpoint: dict[str, Any] | None
    ) -> BestPolicy:
        """A trainer's: ``run_dir/best.pt``, the score carried by a resumed ``checkpoint``, and
        ``run_dir/policies`` when ``--keep-policies``."""
        return cls(run_dir / "best.pt", checkpoint.get("best") if checkpoint is not None else None,
                   keep_dir=run_dir / "policies" if keep_policies else None)  # fmt: skip

    def offer(
        self, evaluation: dict[str, float], policy_state: Callable[[], dict[str, Any]]
    ) -> bool:
        """Save ``policy_state()`` (called only when needed) if ``evaluation`` (``eval/*`` keys) beats
        the best so far; True if it did."""
        from safenav.common.checkpoint import save_checkpoint

        success, collision = evaluation["eval/success_rate"], evaluation["eval/collision_rate"]
        score = (success, -collision)
        wins = not (math.isnan(success) or math.isnan(collision)) and (
            self.score is None or score > self.score
        )
        if not wins and self.keep_dir is None:
            return False
        state = policy_state() | {"policy_only": True, "evaluation": dict(evaluation)}
        if self.keep_dir is not None:
            self.keep_dir.mkdir(parents=True, exist_ok=True)
            save_checkpoint(self.keep_dir / f"step_{state['global_step']:09d}.pt", state)
        if wins:
            save_checkpoint(self.path, state)
            self.score = score
        return wins

    def state_dict(self) -> dict[str, Any]:
        return {"score": list(self.score) if self.score is not None else None}


def periodic_evaluation(
    env: TorchVecEnv,
    act: Callable[[dict[str, torch.Tensor]], torch.Tensor],
    episodes: int,
    global_step: int,
    logger: Any,
    best: BestPolicy,
    policy_state: Callable[[], dict[str, Any]],
) -> tuple[dict[str, float], str]:
    """A trainer's periodic evaluation: run it (:func:`evaluate_episodes` on :data:`EVAL_SEED`),
    log it as an ``eval`` event, offer it to ``best`` (a ``best`` event when it wins). Returns the
    ``eval/*`` row entries and a one-line note for the console."""
    res = evaluate_episodes(env, act, episodes, EVAL_SEED)
    ev = {f"eval/{k}": res.get(k, math.nan) for k in ("return", "cost", "length")}
    ev.update({f"eval/{k}_rate": res.get(k, math.nan) for k in ("success", "collision", "timeout")})
    logger.event(global_step, "eval", **ev)
    if best.offer(ev, policy_state):
        logger.event(global_step, "best", path=str(best.path), **ev)
    note = (
        f"step {global_step}: eval success {ev['eval/success_rate']:.2f} "
        f"collision {ev['eval/collision_rate']:.2f} return {ev['eval/return']:.1f}"
    )
    return ev, note


__all__ = ["EVAL_SEED", "BestPolicy", "evaluate_episodes", "periodic_evaluation"]
