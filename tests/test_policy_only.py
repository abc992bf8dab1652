"""``safenav export --policy-only``: the small policy file acts exactly as the full checkpoint."""

from __future__ import annotations

import pytest
import torch

from conftest import PAPER_OBSERVATION
from safenav.algos.policy import load_policy
from safenav.cli import main
from safenav.envs.nav import SafeNavVectorEnv


def test_policy_only_checkpoint_matches_the_full_one(tmp_path):
    run = tmp_path / "run"
    main(["train", *PAPER_OBSERVATION, "--preset", "easy", "--num-envs", "4", "--total-steps",
          "200", "--csac.learning-starts", "100", "--run-dir", str(run), "--no-progress",
          "--eval-every", "0", "--no-tensorboard", "--torch-threads", "1"])  # fmt: skip
    slim = tmp_path / "policy.pt"
    main(["export", str(run / "checkpoint.pt"), "--policy-only", str(slim)])
    assert slim.stat().st_size < (run / "checkpoint.pt").stat().st_size
    full, small = load_policy(run / "checkpoint.pt"), load_policy(slim)
    env = SafeNavVectorEnv(8, preset="easy", output="torch")
    obs, _ = env.reset(seed=3)
    assert torch.equal(full(obs), small(obs))
    with pytest.raises(SystemExit) as err:  # a policy file cannot be resumed
        main(["train", "--resume", str(slim), "--no-progress"])
    assert err.value.code == 2
