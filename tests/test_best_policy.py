"""BestPolicy: best.pt follows the best periodic evaluation (success first, then collision)."""

from __future__ import annotations

import math

from safenav.common.checkpoint import load_checkpoint
from safenav.training.evaluation import BestPolicy


def ev(success: float, collision: float) -> dict[str, float]:
    return {"eval/success_rate": success, "eval/collision_rate": collision}


def test_saves_only_improvements_and_survives_a_resume(tmp_path) -> None:
    path = tmp_path / "best.pt"
    best = BestPolicy(path)
    calls = []

    def state(step):
        return lambda: calls.append(step) or {"global_step": step}

    assert best.offer(ev(0.5, 0.4), state(1))
    assert not best.offer(ev(0.4, 0.0), state(2))  # lower success loses, whatever its collisions
    assert best.offer(ev(0.5, 0.3), state(3))  # same success, fewer collisions wins
    assert not best.offer(ev(0.5, 0.3), state(4))  # a tie keeps the earlier policy
    assert not best.offer(ev(math.nan, 0.0), state(5))  # no episodes finished: no judgement
    assert calls == [1, 3]  # the policy state is only built when it is saved
    saved = load_checkpoint(path)
    assert (
        saved["global_step"] == 3 and saved["policy_only"] and saved["evaluation"] == ev(0.5, 0.3)
    )

    resumed = BestPolicy(path, best.state_dict())  # what the training checkpoint carries
    assert not resumed.offer(ev(0.45, 0.1), state(6))
    assert resumed.offer(ev(0.6, 0.4), state(7)) and load_checkpoint(path)["global_step"] == 7
    assert BestPolicy(path, None).score is None and BestPolicy(path, {"score": None}).score is None


def test_keep_dir_holds_every_offered_policy(tmp_path) -> None:
    best = BestPolicy(tmp_path / "best.pt", keep_dir=tmp_path / "policies")
    for step, (success, collision) in ((10, (0.5, 0.4)), (20, (0.4, 0.1)), (30, (math.nan, 0.0))):
        best.offer(ev(success, collision), lambda step=step: {"global_step": step})
    kept = sorted(p.name for p in (tmp_path / "policies").iterdir())
    assert kept == ["step_000000010.pt", "step_000000020.pt", "step_000000030.pt"]
    assert load_checkpoint(tmp_path / "policies" / kept[1])["evaluation"] == ev(0.4, 0.1)
    assert load_checkpoint(tmp_path / "best.pt")["global_step"] == 10  # best.pt as before
