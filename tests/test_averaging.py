"""``safenav average``: the weight average of a run's kept policies (stochastic weight averaging)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
import torch

from conftest import PAPER_OBSERVATION
from safenav.algos.averaging import average_policies, average_policy_states
from safenav.algos.policy import load_policy
from safenav.cli import main
from safenav.common.checkpoint import load_checkpoint
from safenav.envs.nav import SafeNavVectorEnv
from safenav.errors import SafenavError
from safenav.experiments.soup import greedy_soup


@pytest.fixture(scope="module")
def kept(tmp_path_factory) -> Path:
    """A tiny CSAC run's ``policies/``: snapshots at steps 200 and 400."""
    from tests.test_train_cli import FAST

    run_dir = tmp_path_factory.mktemp("runs") / "csac"
    main(["train", *PAPER_OBSERVATION, "--preset", "easy", "--seed", "4", "--total-steps", "400",
          "--keep-policies", "--run-dir", str(run_dir), *FAST])  # fmt: skip
    return run_dir / "policies"


def synthetic(
    step: int, weight: list[float], count: int = 7, algo: str = "csac", seed: int = 1
) -> dict:
    meta = {"algo": algo, "net": {"hidden": [4]}, "global_step": step}
    return {"algo": algo, "global_step": step, "updates": step // 10, "elapsed_s": step / 100.0,
            "config": {"run": {"seed": seed}}, "policy": {"meta": meta, "state_dict": {
                "w": torch.tensor(weight), "n": torch.tensor(count)}}}  # fmt: skip


def test_the_average_is_the_elementwise_mean_and_keeps_the_last_counters():
    out = average_policy_states([synthetic(100, [1.0, 2.0]), synthetic(200, [3.0, 5.0]),
                                 synthetic(300, [2.0, -1.0])])  # fmt: skip
    assert torch.equal(out["policy"]["state_dict"]["w"], torch.tensor([2.0, 2.0]))
    assert (
        out["policy"]["state_dict"]["n"].item() == 7
    )  # an integer buffer is carried, not averaged
    assert out["global_step"] == 300 and out["updates"] == 30 and out["policy_only"]
    assert out["averaged_steps"] == out["policy"]["meta"]["averaged_steps"] == [100, 200, 300]


def test_policies_that_are_not_snapshots_of_one_network_are_refused():
    a = synthetic(100, [1.0, 2.0])
    with pytest.raises(SafenavError, match="no policies"):
        average_policy_states([])
    with pytest.raises(SafenavError, match="shape"):
        average_policy_states([a, synthetic(200, [1.0, 2.0, 3.0])])
    with pytest.raises(SafenavError, match="sac"):
        average_policy_states([a, synthetic(200, [1.0, 2.0], algo="sac")])
    other_net = copy.deepcopy(a)
    other_net["policy"]["meta"]["net"] = {"hidden": [8]}
    with pytest.raises(SafenavError, match="'net'"):
        average_policy_states([other_net, synthetic(200, [1.0, 2.0])])
    with pytest.raises(SafenavError, match="non-float"):
        average_policy_states([a, synthetic(200, [1.0, 2.0], count=8)])
    extra = copy.deepcopy(a)
    extra["policy"]["state_dict"]["b"] = torch.zeros(1)
    with pytest.raises(SafenavError, match="other parameters"):
        average_policy_states([extra, synthetic(200, [1.0, 2.0])])
    with pytest.raises(SafenavError, match="two policies of step 100"):
        average_policy_states([a, synthetic(100, [1.0, 2.0])])
    with pytest.raises(SafenavError, match="different seeds"):
        average_policy_states([a, synthetic(200, [1.0, 2.0], seed=2)])
    with pytest.raises(SafenavError, match="holds no policy"):
        average_policy_states([a, {"algo": "csac", "global_step": 5}])


def test_cli_writes_a_policy_file_that_acts_with_the_mean_weights(kept, tmp_path):
    out = tmp_path / "avg.pt"
    main(["average", str(kept), "--out", str(out)])
    a, b = (load_checkpoint(kept / f"step_{s:09d}.pt") for s in (200, 400))
    avg = load_checkpoint(out)
    assert avg["averaged_steps"] == [200, 400] and avg["global_step"] == 400
    sd_a, sd_b = a["policy"]["state_dict"], b["policy"]["state_dict"]
    for key, value in avg["policy"]["state_dict"].items():
        assert torch.allclose(value, (sd_a[key] + sd_b[key]) / 2, atol=1e-7), key
    # the file is an ordinary policy: it acts, and differs from both snapshots it averages
    env = SafeNavVectorEnv(8, preset="easy", output="torch")
    obs, _ = env.reset(seed=5)
    act = load_policy(out)(obs)
    assert act.shape == (8, 3) and torch.isfinite(act).all()
    assert not torch.equal(act, load_policy(kept / "step_000000400.pt")(obs))
    res = tmp_path / "eval.json"
    main(["eval", str(out), "--episodes", "2", "--json", str(res)])
    assert json.loads(res.read_text())["episodes"] == 2


def test_steps_select_the_snapshots(kept):
    only_last = average_policies([kept], steps=(300, 400))
    last = load_checkpoint(kept / "step_000000400.pt")
    assert only_last["averaged_steps"] == [400]
    for key, value in only_last["policy"]["state_dict"].items():
        assert torch.equal(value, last["policy"]["state_dict"][key])
    with pytest.raises(SafenavError, match="no policy with 500 <= step <= 600"):
        average_policies([kept], steps=(500, 600))
    with pytest.raises(SafenavError, match="must not exceed"):
        average_policies([kept], steps=(400, 200))


def test_cli_errors_are_one_line_and_write_nothing(kept, tmp_path, capsys):
    out = tmp_path / "avg.pt"
    for argv in (["average", str(tmp_path / "missing"), "--out", str(out)],
                 ["average", str(tmp_path), "--out", str(out)],
                 ["average", str(kept), "--steps", "500", "600", "--out", str(out)]):  # fmt: skip
        with pytest.raises(SystemExit) as err:
            main(argv)
        assert err.value.code == 2
        assert capsys.readouterr().err.startswith("safenav: error:")
    assert not out.exists()


def test_greedy_soup_keeps_a_policy_only_when_the_soup_does_not_get_worse():
    # score: closeness of the averaged weight to 2.4; alone: w=2 scores best, then 3, then 0
    def score(state):
        return -((state["policy"]["state_dict"]["w"].item() - 2.4) ** 2)

    states = [synthetic(100, [3.0]), synthetic(200, [2.0]), synthetic(300, [0.0])]
    soup, log = greedy_soup(states, score)
    # {2} -> {2, 3}: mean 2.5, better, kept -> {0, 2, 3}: mean 1.67, worse, dropped
    assert soup["averaged_steps"] == [100, 200]
    assert soup["policy"]["state_dict"]["w"].item() == pytest.approx(2.5)
    assert [(r["kind"], r["steps"], r.get("kept")) for r in log] == [
        ("single", [100], None), ("single", [200], None), ("single", [300], None),
        ("soup", [100, 200], True), ("soup", [100, 200, 300], False)]  # fmt: skip
    with pytest.raises(SafenavError, match="no policies"):
        greedy_soup([], score)
    with pytest.raises(SafenavError, match="shape"):  # refused before anything is flown
        greedy_soup([synthetic(100, [1.0]), synthetic(200, [1.0, 2.0])], lambda s: pytest.fail())


def test_cli_greedy_soup_validates_on_the_evaluation_maps(kept, tmp_path, capsys):
    out = tmp_path / "soup.pt"
    main(["average", str(kept), "--greedy", "--val-episodes", "2", "--out", str(out)])
    text = capsys.readouterr().out
    assert "greedy soup" in text and text.count("alone") == 2 and "wrote" in text
    soup = load_checkpoint(out)
    assert set(soup["averaged_steps"]) <= {200, 400} and load_policy(out).meta["algo"] == "csac"
