"""A run's final policy is chosen on validation alone, then reported on the test and held-out
scenarios; no training or selection code path flies the test or held-out maps."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import PAPER_OBSERVATION
from safenav.cli import main
from safenav.common.checkpoint import load_checkpoint
from safenav.experiments import selection
from safenav.experiments.selection import (
    HELDOUT_SEEDS,
    RESERVED_SEEDS,
    TEST_SEED,
    VALIDATION_SEEDS,
    report_policy,
    select_final_policy,
)
from safenav.experiments.soup import greedy_soup


def test_the_seed_sets_are_disjoint():
    assert TEST_SEED == 1 and set(HELDOUT_SEEDS) == {2, 3, 4, 5, 6}
    assert not RESERVED_SEEDS & set(VALIDATION_SEEDS)


FAST = ["--num-envs", "4", "--log-every", "100", "--eval-every", "200", "--eval-episodes", "2",
        "--checkpoint-every", "200", "--no-progress", "--no-tensorboard", "--torch-threads", "1",
        "--csac.learning-starts", "100", "--csac.batch-size", "32", "--csac.buffer-size", "2000",
        "--csac.updates-per-step", "0.25", "--csac.net.hidden", "32", "32"]  # fmt: skip


@pytest.mark.long
def test_training_and_selection_never_fly_the_test_or_heldout_maps(tmp_path, world_seeds):
    run_dir = tmp_path / "run"
    main(["train", "--algo", "csac", "--preset", "easy", "--seed", "2", "--total-steps", "600",
          "--keep-policies", "--run-dir", str(run_dir), *FAST])  # fmt: skip
    assert world_seeds, "the recorder saw no world: the check would pass vacuously"
    trained = len(world_seeds)
    record = select_final_policy(run_dir, episodes=8)
    assert set(VALIDATION_SEEDS) <= set(world_seeds[trained:])
    assert not set(world_seeds) & RESERVED_SEEDS, sorted(set(world_seeds) & RESERVED_SEEDS)
    # the record and the policy it describes
    assert record["selection"] == "validation"
    written = json.loads((run_dir / "selection.json").read_text())
    assert written["chosen_steps"] == record["chosen_steps"]
    policy = load_checkpoint(run_dir / "policy.pt")
    assert policy["averaged_steps"] == record["chosen_steps"]
    assert set(record["chosen_steps"]) <= set(record["candidates"])
    # only the late half of the run is a candidate
    assert min(record["candidates"]) >= 300
    # then the report flies exactly the test and held-out maps
    world_seeds.clear()
    report = report_policy(run_dir / "policy.pt", episodes=4, heldout=(2, 3))
    assert set(world_seeds) == {TEST_SEED, 2, 3}
    assert report["test"]["env_seed"] == TEST_SEED and report["test"]["episodes"] == 4
    assert [h["env_seed"] for h in report["heldout"]["per_seed"]] == [2, 3]
    for key in ("success_rate", "collision_rate", "timeout_rate"):
        assert 0.0 <= report["heldout"][key] <= 1.0
    # the test episodes once more under NavRL's rule: never more collisions than the body's
    navrl = report["test_navrl_rule"]
    assert navrl["env_seed"] == TEST_SEED and navrl["episodes"] == 4
    body_hits = report["test"]["per_episode"]["collision"]
    assert all(
        b or not n for b, n in zip(body_hits, navrl["per_episode"]["collision"], strict=True)
    )


def test_ranking_scores_spare_the_single_flights():
    """With periodic-evaluation scores given, only the top-ranked policy alone and the candidate
    soups are scored; the ranking follows the given scores."""
    states = [_fake_state(step, value) for step, value in ((100, 0.0), (200, 1.0), (300, 2.0))]
    calls = []

    def score(state):
        calls.append(tuple(state.get("averaged_steps", [state["global_step"]])))
        return float(state["policy"]["state_dict"]["w"].mean())

    soup, log = greedy_soup(states, score, rank_scores={100: 0.9, 200: 0.1, 300: 0.5})
    assert calls[0] == (100,)  # the best-ranked alone, scored once
    assert len(calls) == 3  # + two candidate soups, no single flight of 200 or 300
    assert [r["kind"] for r in log] == ["rank", "rank", "rank", "single", "soup", "soup"]
    # 100 (w = 0) first, then 300 (the soup's mean rises to 1: kept), then 200 (mean 1: kept)
    assert soup["averaged_steps"] == [100, 200, 300]


def _fake_state(step: int, value: float) -> dict:
    import torch

    meta = {"algo": "csac", "format_version": 1, "net": {}, "global_step": step}
    return {"algo": "csac", "global_step": step, "config": {"run": {"seed": 0}},
            "policy": {"meta": meta, "state_dict": {"w": torch.full((2,), value)}}}  # fmt: skip


def test_selection_refuses_a_run_without_kept_policies(tmp_path):
    from safenav.errors import SafenavError

    (tmp_path / "policies").mkdir()
    with pytest.raises(SafenavError, match="no policy files"):
        select_final_policy(tmp_path)


def test_report_needs_a_safenav_policy(tmp_path):
    path = Path(tmp_path / "missing.pt")
    with pytest.raises(Exception, match="missing.pt"):
        report_policy(path, episodes=1)
    assert selection.TEST_SEED == 1


@pytest.mark.long
def test_train_select_ends_with_a_validation_choice_and_its_report(tmp_path, monkeypatch, capsys):
    """``safenav train --select``: policy.pt chosen on validation, final.json with the test and
    held-out report (fewer episodes here to stay fast)."""
    import functools

    from safenav.experiments import selection

    monkeypatch.setattr(selection, "select_final_policy",
                        functools.partial(selection.select_final_policy, episodes=4))  # fmt: skip
    monkeypatch.setattr(selection, "report_policy",
                        functools.partial(selection.report_policy, episodes=2, heldout=(2,)))  # fmt: skip
    run_dir = tmp_path / "run"
    # the paper's observation without the shield: the default recipe's flights behind it made
    # this test 121 s instead of 15 (its selection behind the shield: test_shielded_training)
    main(["train", *PAPER_OBSERVATION, "--preset", "easy", "--seed", "4",
          "--total-steps", "400", "--select", "--run-dir", str(run_dir), *FAST])  # fmt: skip
    config = json.loads((run_dir / "config.json").read_text())
    assert config["run"]["select"] and config["run"]["keep_policies"]  # --select keeps them
    final = json.loads((run_dir / "final.json").read_text())
    assert final["selection"]["selection"] == "validation"
    assert final["test"]["env_seed"] == TEST_SEED and final["heldout"]["seeds"] == [2]
    assert (run_dir / "policy.pt").is_file()
    assert "policy chosen on validation" in capsys.readouterr().out


def test_a_run_too_short_to_keep_a_policy_is_reported_on_its_final_one(tmp_path):
    """A run that kept no policy (--no-keep-policies): its final policy becomes policy.pt and
    the record says it was not a validation choice among several."""
    run_dir = tmp_path / "run"
    main(["train", "--algo", "csac", "--preset", "easy", "--seed", "4", "--total-steps", "400",
          "--no-keep-policies", "--run-dir", str(run_dir), *FAST])  # fmt: skip
    assert not any((run_dir / "policies").glob("*.pt"))
    record = select_final_policy(run_dir, episodes=2)
    assert record["method"] == "final policy (no policy kept)" and record["chosen_steps"] == [400]
    assert json.loads((run_dir / "selection.json").read_text()) == record
    assert (run_dir / "policy.pt").is_file()


def test_report_episodes_is_a_whole_number_and_needs_select():
    """A recipe or config.json is not typed like the command line: 2.5 or true used to pass the
    checks and fail (or report 1 episode) only after the whole training."""
    from safenav.common.config import RunConfig

    assert RunConfig(report_episodes=5, select=True).report_episodes == 5
    for kw, why in (({"report_episodes": 2.5, "select": True}, "must be an integer"),
                    ({"report_episodes": True, "select": True}, "must be an integer"),
                    ({"report_episodes": 0, "select": True}, r"must lie in \[1, "),
                    ({"report_episodes": 5}, "add --select"), ({"seed": 3.0}, "seed=3.0")):  # fmt: skip
        with pytest.raises(ValueError, match=why):
            RunConfig(**kw)
