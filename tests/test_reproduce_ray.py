"""safenav reproduce on a local Ray instance, with a stand-in trainer (seconds, no learning).

Checks the Ray side: trials as tasks with their CPUs, results.json/md and figures written, a
rerun skips finished trials without starting Ray, a failed trial is reported and the others kept,
a sweep stopped by SIGTERM stops its trainers.
The same sweep with the real ``safenav train`` is test_reproduce_e2e.py.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from safenav.common.stopping import process_running
from safenav.experiments import reproduce as rep
from test_reproduce import fake_python  # noqa: F401  (fixture)

pytest.importorskip("ray")


def sweep(tmp_path, python, **kw) -> rep.SweepConfig:
    return rep.SweepConfig(out=tmp_path / "out", algos=("csac", "sac"), seeds=2, first_seed=0,
                           total_steps=("1000",), preset="easy", cpus_per_trial=1, num_cpus=2,
                           eval_episodes=10, progress=False, python=python,
                           command="safenav reproduce (test)", **kw)  # fmt: skip


@pytest.mark.long
def test_sweep_on_local_ray_then_rerun_skips(tmp_path, fake_python, monkeypatch):  # noqa: F811
    cfg = sweep(tmp_path, fake_python)
    results = rep.run_sweep(cfg)
    out = cfg.out
    data = json.loads((out / "results.json").read_text())
    assert data == json.loads(json.dumps(results))
    assert list(data["algos"]) == ["csac", "sac"]
    csac = data["algos"]["csac"]
    # The stand-in's test success is 0.8 + 0.05 * seed: seeds 0, 1 -> 0.825 ± 0.0354.
    assert csac["seeds"] == 2 and csac["success_rate"]["mean"] == pytest.approx(0.825)
    assert csac["success_rate"]["std"] == pytest.approx(0.05 / 2**0.5)
    assert csac["env_steps"] == 1000 and csac["time_to_target"]["reached"] == 2
    assert data["ray"]["cpus_per_trial"] == 1 and data["ray"]["parallel_trials"] == 2
    assert data["ray"]["init_s"] > 0 and data["failed"] == []
    assert "| CSAC | 2 | 82.5 ± 3.5 % | 84.7 % |" in (out / "results.md").read_text()
    for name in ("fig3_validation_curves.png", "fig3_learning_curves.png",
                 "fig4_test_results.png", "constraint_lambda_d.png"):  # fmt: skip
        assert (out / "figures" / name).stat().st_size > 10_000
    record = json.loads((out / "trials" / "csac-s1.json").read_text())
    assert [p["env_steps"] for p in record["validation_curve"]] == [500, 1000]
    assert record["validation_curve"][-1]["success_rate"] == pytest.approx(0.9)
    assert (out / "logs" / "sac-seed1.train.log").exists()
    calls = (out / "runs" / "csac" / "calls.txt").read_text().splitlines()
    assert len(calls) == 4  # two seeds: train + eval each
    assert csac["per_seed"][0]["run_dir"] == "runs/csac/seed0"
    # the budget is declared on run-directory records too, as in the trial files: labels of
    # different budgets are never compared (ppo_3m was once set against 1M CSAC this way)
    assert {r["budget_env_steps"] for r in csac["per_seed"]} == {1000}
    # Rerun: everything is done, nothing runs again and Ray is not even started.
    import ray

    monkeypatch.setattr(ray, "init", lambda *a, **k: pytest.fail("Ray started for nothing"))
    again = rep.run_sweep(cfg)
    assert again["algos"]["csac"]["seeds"] == 2 and again["ray"] == data["ray"]
    assert (out / "runs" / "csac" / "calls.txt").read_text().splitlines() == calls
    # A fresh clone has the committed trial files, not the (ignored) run directories: the same
    # command reports them and runs nothing.
    import shutil

    shutil.rmtree(out / "runs")
    shutil.rmtree(out / "figures")
    cloned = rep.run_sweep(cfg)
    assert not (out / "runs").exists()
    # Fig. 3 (validation curves) and Fig. 4 are redrawn from the trial files alone
    for name in ("fig3_validation_curves.png", "fig4_test_results.png"):
        assert (out / "figures" / name).stat().st_size > 10_000
    for algo in ("csac", "sac"):
        ours, kept = data["algos"][algo], cloned["algos"][algo]
        assert kept["seeds"] == 2 and kept["success_rate"] == ours["success_rate"]
        assert kept["ci95"] == ours["ci95"]
    # A sweep of one label into the same OUT (a seed or a label at a time, as a session allows)
    # still reports every finished trial there, in the comparison's order, and says which.
    cfg.algos = ("sac",)
    one = rep.run_sweep(cfg)
    assert list(one["algos"]) == ["csac", "sac"] and one["algos"]["csac"]["seeds"] == 2
    assert one["algos"]["csac"]["success_rate"] == data["algos"]["csac"]["success_rate"]
    assert one["earlier_trials"] == ["csac-s0", "csac-s1"]
    assert one["total_steps"] == {"sac": 1000, "csac": 1000}
    assert "from earlier sweeps into the same directory" in (out / "results.md").read_text()


def test_failed_trial_is_reported_and_the_rest_aggregated(tmp_path, fake_python):  # noqa: F811
    cfg = sweep(tmp_path, fake_python, variants=("broken=sac --fail",))
    cfg.algos = ("csac",)
    with pytest.raises(rep.TrialFailed, match=r"2 of 4 trials stopped or failed: \['broken-seed0'"):
        rep.run_sweep(cfg)
    data = json.loads((cfg.out / "results.json").read_text())
    assert list(data["algos"]) == ["csac"] and data["failed"] == ["broken-seed0", "broken-seed1"]
    assert "boom: something broke" in (cfg.out / "logs" / "broken-seed0.train.log").read_text()


def test_a_killed_trial_is_retried_by_ray_and_completes(tmp_path, fake_python):  # noqa: F811
    cfg = sweep(tmp_path, fake_python, variants=("flaky=sac --killed-once",))
    cfg.algos, cfg.seeds = ("flaky",), 1
    data = rep.run_sweep(cfg)
    assert data["algos"]["flaky"]["seeds"] == 1 and data["failed"] == []
    assert (cfg.out / "runs" / "flaky" / "killed-0").exists()  # it was killed once


def test_cpus_per_trial_larger_than_any_node_is_refused(tmp_path, fake_python):  # noqa: F811
    from safenav.errors import SafenavError

    cfg = sweep(tmp_path, fake_python)
    cfg.cpus_per_trial = 3
    with pytest.raises(SafenavError, match="exceeds the 2 CPUs of the local Ray instance"):
        rep.run_sweep(cfg)


DRIVER = """
import sys
from pathlib import Path
from safenav.common.stopping import Terminated
from safenav.experiments import reproduce as rep
cfg = rep.SweepConfig(out=Path(sys.argv[1]), algos=("hang",), variants=("hang=sac --hang --stop-seconds 5",),
                      seeds=1, first_seed=0, total_steps=("1000",), preset="easy", cpus_per_trial=1, num_cpus=2,
                      eval_episodes=10, progress=False, python=sys.argv[2], command="test")
try:
    rep.run_sweep(cfg)
except Terminated:  # what the CLI turns into exit 143
    sys.exit(143)
"""


def test_a_sweep_stopped_by_sigterm_stops_its_trainers(tmp_path, fake_python):  # noqa: F811
    """`kill` of a running `safenav reproduce` (a background job's stop: SIGINT is ignored there)
    leaves no trainer running, and each trainer stops with its checkpoint: the driver cancels its
    trials as on Ctrl-C, each worker sends its trainer SIGTERM, and the driver waits for them
    before Ray shuts down (its cleanup SIGKILLs a worker's children). The stand-in trainer takes
    5 s to answer, as a checkpoint with a replay buffer does."""
    out = tmp_path / "out"
    runs = out / "runs" / "hang"
    log = (tmp_path / "driver.log").open("w")
    driver = subprocess.Popen([sys.executable, "-c", DRIVER, str(out), fake_python],
                              stdout=log, stderr=subprocess.STDOUT, start_new_session=True)  # fmt: skip
    try:
        deadline = time.time() + 180
        while not (runs / "hang-0.pid").exists():
            assert driver.poll() is None and time.time() < deadline, (
                tmp_path / "driver.log"
            ).read_text()
            time.sleep(0.5)
        time.sleep(0.5)  # the pid is written just after the SIGTERM handler is set
        trainer = int((runs / "hang-0.pid").read_text())
        driver.send_signal(signal.SIGTERM)
        assert driver.wait(timeout=120) == 143  # terminated, not interrupted (130)
        deadline = time.time() + 30
        while process_running(trainer) and time.time() < deadline:
            time.sleep(0.5)
        assert not process_running(trainer), "an orphan trainer runs on"
        assert (runs / "stopped-0").exists(), "the trainer was killed, not stopped by SIGTERM"
    finally:
        if driver.poll() is None:
            os.killpg(driver.pid, signal.SIGKILL)
        log.close()
