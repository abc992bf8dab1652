"""End to end: ``safenav reproduce`` with the real ``safenav train`` and ``safenav eval`` on a
local Ray instance — 2 algorithms x 2 seeds, 2000 env steps, easy preset, 1 CPU per trial —
produces results.json, results.md and both of the paper's figures.

Budget: about 60 s on the 2-core development machine (Ray start ~5 s, 4 trials 2 at a time).
"""

from __future__ import annotations

import importlib.util
import json

import pytest

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("safenav.commands.train") is None,
    reason="safenav train is not part of this checkout yet",
)


def test_tiny_reproduce_end_to_end(tmp_path):
    pytest.importorskip("ray")
    from safenav.cli import main

    out = tmp_path / "repro"
    # 2000 steps (16 envs) logged every 250 give Fig. 3 a few points; a warm-up of 1000 steps
    # (a budget within the warm-up is refused) leaves a few gradient updates.
    main(["reproduce", "--algos", "csac", "sac", "--seeds", "2", "--total-steps", "2000",
          "--preset", "easy", "--cpus-per-trial", "1", "--num-cpus", "2", "--eval-episodes",
          "10", "--train-args=--log-every 250 --csac.learning-starts 1000", "--out", str(out)])  # fmt: skip
    data = json.loads((out / "results.json").read_text())
    assert list(data["algos"]) == ["csac", "sac"]
    for name, algo in data["algos"].items():
        assert algo["seeds"] == 2, name
        rates = [algo[k]["mean"] for k in ("success_rate", "collision_rate", "timeout_rate")]
        assert sum(rates) == pytest.approx(1.0, abs=1e-6)
        assert all(0.0 <= r <= 1.0 for r in rates)
        assert algo["env_steps"] >= 2000 and algo["wall_clock_s"] > 0
        assert [r["seed"] for r in algo["per_seed"]] == [0, 1]
        assert all(r["eval_episodes"] == 10 for r in algo["per_seed"])
    assert data["ray"]["parallel_trials"] == 2 and data["failed"] == []
    assert data["command"].startswith("safenav reproduce")
    assert "| CSAC | 2 |" in (out / "results.md").read_text()
    for fig in ("fig3_learning_curves.png", "fig4_test_results.png"):
        assert (out / "figures" / fig).stat().st_size > 10_000
    for run in (out / "runs").glob("*/seed*"):
        assert (run / "checkpoint.pt").exists() and (run / "eval.json").exists()
