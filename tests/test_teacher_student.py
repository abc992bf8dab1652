"""``experiments/teacher_student.py``: the planner labels auto-resetting envs episode by episode,
and a tiny DAgger run writes students that ``load_policy`` reads and its log."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest
import torch

from safenav.algos.policy import load_policy
from safenav.envs.nav import SafeNavVectorEnv

ROOT = Path(__file__).resolve().parents[1]


def _module(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "experiments" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


_module("oracle_planner")  # teacher_student imports it by name
ts = _module("teacher_student")


def test_teacher_restarts_only_the_envs_whose_episode_changed(monkeypatch) -> None:
    env = SafeNavVectorEnv(4, preset="easy", output="torch")
    obs, _ = env.reset(seed=200_000)
    teacher = ts.Teacher(ts.OracleConfig(privileged_range=4.0))
    first = teacher(obs, env)
    assert first.shape == (4, 3) and first.abs().max() <= 1.0
    assert teacher.prev_cmd.abs().sum(-1).gt(0).all()  # every env got a command
    kept = teacher.prev_cmd.clone()
    seen = {}

    def planner_call(self, obs, env):  # what the planner finds when Teacher hands over
        seen["prev_cmd"], seen["finished"] = self.prev_cmd.clone(), self.finished.clone()
        return torch.zeros(env.num_envs, 3)

    monkeypatch.setattr(ts.OraclePlanner, "__call__", planner_call)
    env.goal[1] += 0.5  # as if env 1 had been reset to a new episode
    teacher.finished[:] = True
    teacher(obs, env)
    assert not seen["finished"].any()  # SAME_STEP autoreset: nothing is left finished
    assert torch.equal(seen["prev_cmd"][1], torch.zeros(3))  # env 1's memory restarted
    assert torch.equal(seen["prev_cmd"][[0, 2, 3]], kept[[0, 2, 3]])  # the others kept theirs
    assert torch.equal(teacher._goals, env.goal)


@pytest.mark.long
def test_tiny_dagger_run_writes_readable_students(tmp_path: Path) -> None:
    log = ts.main(["--out", str(tmp_path), "--iterations", "2", "--envs", "4", "--steps", "6",
                   "--updates", "3", "--val-episodes", "4", "--threads", "1",
                   "--agreement-steps", "3"])  # fmt: skip
    assert [r["iteration"] for r in log] == [0, 1]
    assert log[0]["beta"] == 1.0 and log[1]["beta"] == 0.5
    assert log[1]["samples"] == 2 * 4 * 6
    record = json.loads((tmp_path / "dagger.json").read_text())
    assert len(record["iterations"]) == 2
    v = record["iterations"][1]["validation"]
    assert abs(v["success_rate"] + v["collision_rate"] + v["timeout_rate"] - 1.0) < 1e-6
    policy = load_policy(tmp_path / "student-i1.pt")
    obs, _ = SafeNavVectorEnv(2, preset="paper", output="torch").reset(seed=200_001)
    action = policy(obs)
    assert action.shape == (2, 3) and action.abs().max() <= 1.0
    agree = record["agreement"]
    assert agree["samples"] == 64 * 3 and len(agree["r2"]) == 3
    var, mse = torch.tensor(agree["label_var"]), torch.tensor(agree["mse"])
    assert torch.allclose(torch.tensor(agree["r2"]), 1 - mse / var)
