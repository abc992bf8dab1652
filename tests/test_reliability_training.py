"""Reliability of ``safenav train`` / ``safenav eval`` (docs/reliability.md), in tiny runs:

1. kill-safety: a trainer SIGKILLed at random moments and resumed until done completes its steps,
   and checkpoint.pt is never half-written;
2. determinism: the same seed and config give the same progress.csv and eval JSON on CPU; a
   resumed run equals the uninterrupted one up to its checkpoint, and (measured) not after it;
3. one-line errors (exit code 2) for user mistakes, and NaN/Inf stopping a run that keeps its
   last good checkpoint;
4. SIGINT stops PPO and CSAC alike (checkpoint, ``interrupted`` event, exit code 130), also when
   the trainer inherited a blocked SIGINT from a Ray worker.
"""

from __future__ import annotations

import csv
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from safenav.algos import ppo
from safenav.algos.policy import check_fits_safenav, load_policy, save_policy_only
from safenav.cli import main
from safenav.common.checkpoint import load_checkpoint, save_checkpoint
from safenav.common.logger import RunLogger
from safenav.common.stopping import RunGuard
from safenav.envs.config import make_config
from safenav.errors import SafenavError

pytestmark = pytest.mark.usefixtures("one_thread")

TOTAL = 640
FAST = ["--preset", "easy", "--num-envs", "4", "--seed", "5", "--no-progress", "--no-tensorboard",
        "--torch-threads", "1", "--eval-every", "0"]  # fmt: skip
# A progress.csv row and a checkpoint every ROW[algo] steps: 8 vector steps of CSAC, one rollout
# of 16 vector steps of PPO.
ROW = {"csac": 32, "ppo": 64}
SMALL = {
    "csac": ["--csac.learning-starts", "64", "--csac.batch-size", "32", "--csac.buffer-size", "2000",
             "--csac.net.hidden", "32", "32", "--log-every", "32", "--checkpoint-every", "32"],
    "ppo": ["--ppo.rollout-steps", "16", "--ppo.epochs", "2", "--ppo.num-minibatches", "2",
            "--ppo.net.hidden", "32", "32", "--log-every", "64", "--checkpoint-every", "64"],
}  # fmt: skip
# Columns that measure wall-clock time, not training: they differ between identical runs.
WALL_CLOCK = ("time/elapsed_s", "perf/sps", "perf/updates_per_s")


def train_args(algo: str, run_dir: Path, total: int = TOTAL, *extra: str) -> list[str]:
    # --config none: the built-in defaults, which the step arithmetic of these tests counts on
    return ["train", "--algo", algo, "--config", "none", "--run-dir", str(run_dir), "--total-steps", str(total),
            *FAST, *SMALL[algo], *extra]  # fmt: skip


def resume_args(algo: str, run_dir: Path, *extra: str) -> list[str]:
    return ["train", "--algo", algo, "--resume", str(run_dir), "--no-progress", *extra]


def progress(run_dir: Path) -> list[dict[str, str]]:
    """progress.csv rows without the wall-clock columns."""
    with (run_dir / "progress.csv").open(newline="") as f:
        return [{k: v for k, v in r.items() if k not in WALL_CLOCK} for r in csv.DictReader(f)]


def events(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "events.jsonl").read_text().splitlines()]


def eval_json(run_dir: Path) -> dict:
    """``safenav eval`` of the run's checkpoint (4 episodes) as a dict, minus the path itself."""
    out = run_dir / "eval.json"
    main(["eval", str(run_dir / "checkpoint.pt"), "--episodes", "4", "--json", str(out)])
    result = json.loads(out.read_text())
    del result["checkpoint"]
    return result


def finite(state: dict) -> bool:
    return all(
        bool(torch.isfinite(t).all()) for t in state["agent"].values() if t.is_floating_point()
    )


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> dict[str, Path]:
    """One uninterrupted tiny run per trainer family (CSAC/SAC/SAC-Lag share one loop, PPO/PPO-Lag
    the other): what killed, interrupted and repeated runs are compared with."""
    root = tmp_path_factory.mktemp("reference")
    for algo in SMALL:
        main(train_args(algo, root / algo))
    return {algo: root / algo for algo in SMALL}


# ------------------------------------------------------------------------- 2. determinism
@pytest.mark.parametrize("algo", ["csac", "ppo"])
def test_same_seed_and_config_give_identical_progress_and_eval(reference, tmp_path, algo):
    again = tmp_path / "again"
    main(train_args(algo, again))
    first, second = progress(reference[algo]), progress(again)
    assert len(first) == TOTAL // ROW[algo] and first == second
    assert any(r["losses/actor"] for r in first)  # the runs did update (not just warm-up)
    assert json.loads((reference[algo] / "config.json").read_text()) == json.loads(
        (again / "config.json").read_text()
    )
    assert eval_json(reference[algo]) == eval_json(again)


UPDATE_COLUMNS = {"csac": ("losses/qr", "losses/actor", "values/qr"),
                  "ppo": ("losses/actor", "losses/value", "values/value")}  # fmt: skip


@pytest.mark.parametrize(("algo", "extra"), [("csac", ()), ("csac", ("--save-buffer",)), ("ppo", ())],
                         ids=["csac", "csac-save-buffer", "ppo"])  # fmt: skip
def test_resumed_run_equals_uninterrupted_run_only_up_to_its_checkpoint(
    reference, tmp_path, monkeypatch, algo, extra
):
    """Ctrl-C right after the row of step 320, then ``--resume``: measured, not assumed. The rows
    up to the checkpoint are the uninterrupted run's; after it the run goes on differently, with
    or without --save-buffer, because the env's state (episodes under way) is not checkpointed
    (docs/reliability.md). Steps, row count and config stay the same."""
    stop_at, log = 320, RunLogger.log

    def log_then_interrupt(self, step, metrics):
        log(self, step, metrics)
        if step == stop_at:
            raise KeyboardInterrupt

    run_dir = tmp_path / "resumed"
    monkeypatch.setattr(RunLogger, "log", log_then_interrupt)
    with pytest.raises(SystemExit) as exit_:
        main(train_args(algo, run_dir, TOTAL, *extra))
    assert exit_.value.code == 130 and load_checkpoint(run_dir)["global_step"] == stop_at
    monkeypatch.setattr(RunLogger, "log", log)
    main(resume_args(algo, run_dir))

    whole, resumed = progress(reference[algo]), progress(run_dir)
    assert [r["global_step"] for r in resumed] == [r["global_step"] for r in whole]
    before = [i for i, r in enumerate(whole) if int(r["global_step"]) <= stop_at]
    after = [i for i, r in enumerate(whole) if int(r["global_step"]) > stop_at]
    assert all(resumed[i] == whole[i] for i in before)
    differs = [i for i in after if any(resumed[i][c] != whole[i][c] for c in UPDATE_COLUMNS[algo])]
    assert differs, "resume became bit-exact: update docs/reliability.md and this test"
    if algo == "csac":  # without the buffer the resume refills it before updating again
        updates = lambda rows: int(float(rows[-1]["perf/updates"]))  # noqa: E731
        assert (updates(resumed) == updates(whole)) == bool(extra)
    assert load_checkpoint(run_dir)["global_step"] == TOTAL
    expected = json.loads((reference[algo] / "config.json").read_text())
    expected["run"]["save_buffer"] = bool(extra)
    assert json.loads((run_dir / "config.json").read_text()) == expected


# -------------------------------------------------------------------------- 1. kill-safety
def launch(args: list[str], block_sigint: bool = False) -> subprocess.Popen:
    """``python -m safenav ARGS`` with one OpenMP thread; ``block_sigint``: start it with SIGINT
    blocked, the signal mask a Ray worker's child inherits."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

    def preexec() -> None:
        # SIGINT as a terminal gives it, also when this test run inherited it ignored (a
        # background job of a script: ``make test &``), which the trainer would respect.
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        if block_sigint:
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})

    return subprocess.Popen([sys.executable, "-m", "safenav", *args], env=env, preexec_fn=preexec,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)  # fmt: skip


def logged_step(run_dir: Path) -> int:
    """The last step in progress.csv (read while the trainer writes it: partial lines skipped)."""
    try:
        lines = (run_dir / "progress.csv").read_text().splitlines()[1:]
    except FileNotFoundError:
        return -1
    steps = [int(line.split(",")[0]) for line in lines if line.split(",")[0].isdigit()]
    return max(steps, default=-1)


def resumes(run_dir: Path) -> int:
    try:
        return (run_dir / "events.jsonl").read_text().count('"event": "resume"')
    except FileNotFoundError:
        return 0


def wait_until(cond, proc: subprocess.Popen, timeout: float = 60.0) -> bool:
    """Poll ``cond()`` until true (True) or ``proc`` exits (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.01)
    proc.kill()
    raise AssertionError(f"timed out after {timeout} s: {proc.args}")


def kill_and_resume(algo: str, run_dir: Path, kills: int, seed: int, *extra: str) -> list[int]:
    """Start a run, SIGKILL it ``kills`` times (each at a random step, plus up to a log
    interval's time), resuming after each kill, then let it finish. Checks the checkpoint after
    every kill; returns the step of the checkpoint each resume started from."""
    rng = random.Random(seed)
    targets = sorted(rng.sample(range(40, TOTAL - 40), kills))
    proc = launch(train_args(algo, run_dir, TOTAL, *extra))
    resumed_from = []
    for target in targets:
        # after a resume, progress.csv is the resumed run's once its "resume" event is out
        reached = wait_until(lambda t=target: resumes(run_dir) >= len(resumed_from)
                             and logged_step(run_dir) >= t, proc)  # fmt: skip
        time.sleep(rng.uniform(0.0, 0.05))
        if not reached or proc.poll() is not None:
            break  # it finished first
        proc.kill()
        proc.wait()
        ckpt = run_dir / "checkpoint.pt"
        # SIGKILL skips every handler: what is on disk must be a whole checkpoint (or none)
        step = load_checkpoint(ckpt)["global_step"] if ckpt.exists() else None
        assert step is not None, "killed after the first row but before any checkpoint"
        assert step >= max(resumed_from, default=0)  # never behind an earlier checkpoint
        resumed_from.append(step)
        proc = launch(resume_args(algo, run_dir))
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    return resumed_from


def check_completed(algo: str, run_dir: Path, reference_run: Path, resumed_from: list[int]) -> None:
    state = load_checkpoint(run_dir / "checkpoint.pt")
    assert state["global_step"] == TOTAL and finite(state)
    rows = progress(run_dir)
    steps = [int(r["global_step"]) for r in rows]
    assert steps == list(range(ROW[algo], TOTAL + 1, ROW[algo]))  # each row once, in order
    first = (resumed_from[0] if resumed_from else TOTAL) // ROW[algo]
    assert rows[:first] == progress(reference_run)[:first]  # up to the first kill's checkpoint
    kinds = [e["event"] for e in events(run_dir)]
    assert kinds.count("resume") == len(resumed_from) and kinds[-1] == "end"
    assert not list(run_dir.glob(".checkpoint.pt.*.tmp"))  # killed writers' temp files removed
    assert load_policy(run_dir).meta["global_step"] == TOTAL


@pytest.mark.long
@pytest.mark.parametrize("algo", ["csac", "ppo"])
def test_sigkilled_training_resumes_to_completion(reference, tmp_path, algo):
    run_dir = tmp_path / "killed"
    resumed_from = kill_and_resume(algo, run_dir, kills=3, seed={"csac": 11, "ppo": 12}[algo])
    assert resumed_from  # at least one kill landed before the run finished
    check_completed(algo, run_dir, reference[algo], resumed_from)


@pytest.mark.slow
@pytest.mark.parametrize(("algo", "extra", "seed"), [("csac", ("--save-buffer",), 1), ("ppo", (), 2),
                                                     ("csac", (), 3)],
                         ids=["csac-save-buffer", "ppo", "csac"])  # fmt: skip
def test_sigkilled_training_resumes_to_completion_many_kills(
    reference, tmp_path, algo, extra, seed
):
    """8 kills a run (about 45 s each on 2 loaded cores); with --save-buffer the checkpoint holds
    the replay buffer too."""
    run_dir = tmp_path / "killed"
    resumed_from = kill_and_resume(algo, run_dir, 8, seed, *extra)
    check_completed(algo, run_dir, reference[algo], resumed_from)


def test_checkpoint_file_survives_sigkill_during_writes(tmp_path):
    """Kill a process that does nothing but write checkpoints (~4 MB each), at random moments:
    the file always loads, and the next write removes the dead writer's temp file."""
    path = tmp_path / "checkpoint.pt"
    rng = random.Random(0)
    for _ in range(8):
        pid = os.fork()
        if pid == 0:  # the child: write until killed
            try:
                for k in range(10_000):
                    save_checkpoint(path, {"k": k, "w": torch.full((1_000_000,), float(k))})
            finally:
                os._exit(0)
        time.sleep(rng.uniform(0.01, 0.3))
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        if path.exists():  # (absent only until some child finished a write)
            state = load_checkpoint(path)
            assert bool((state["w"] == state["k"]).all())
    assert path.exists()
    save_checkpoint(path, {"k": -1})
    assert not list(tmp_path.glob(".checkpoint.pt.*.tmp")) and load_checkpoint(path)["k"] == -1


# --------------------------------------------------------------------------- 4. SIGINT
def test_sigint_during_a_checkpoint_write_waits_for_the_write(tmp_path, monkeypatch):
    """A SIGINT inside ``torch.save`` (here: at its third write) used to surface as torch's
    ``RuntimeError: unexpected pos`` instead of ``KeyboardInterrupt``: the trainer crashed
    instead of checkpointing. ``RunGuard.save`` holds the signal back until the file is whole."""
    real_save = torch.save

    class InterruptingFile:
        def __init__(self, f):
            self.f, self.writes = f, 0

        def write(self, data):
            self.writes += 1
            if self.writes == 3:
                os.kill(os.getpid(), signal.SIGINT)
            return self.f.write(data)

        def flush(self):
            self.f.flush()

    monkeypatch.setattr(torch, "save", lambda obj, f: real_save(obj, InterruptingFile(f)))
    # Ctrl-C's usual handler, also when this test run inherited SIGINT ignored (``make test &``).
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    guard = RunGuard(tmp_path, logger=None, agent=torch.nn.Linear(2, 2))
    try:
        with pytest.raises(KeyboardInterrupt):
            guard.save(7, {"w": torch.ones(100_000)})
    finally:
        signal.signal(signal.SIGINT, previous)
    monkeypatch.setattr(torch, "save", real_save)
    assert guard.last_saved == 7 and float(load_checkpoint(tmp_path)["w"].sum()) == 100_000


@pytest.mark.parametrize(
    ("algo", "sig"), [("ppo", "SIGINT"), ("csac", "SIGINT"), ("csac", "SIGTERM")]
)
def test_sigint_stops_training_with_a_checkpoint_that_resumes(tmp_path, algo, sig):
    """With SIGINT blocked at start, as in a trainer a Ray worker started (``safenav
    reproduce``): that trainer used to ignore Ctrl-C and train on. SIGTERM (``kill PID``, Ray
    cancelling a trial, a cluster's preemption) stops the same way, with exit code 143."""
    run_dir = tmp_path / "interrupted"
    proc = launch(train_args(algo, run_dir, 10**7), block_sigint=True)
    assert wait_until(lambda: logged_step(run_dir) >= 64, proc), proc.communicate()[1]
    sent = time.monotonic()
    proc.send_signal(getattr(signal, sig))
    try:
        _, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError(f"the trainer kept training after {sig}") from None
    code, said = (
        (130, "safenav: interrupted") if sig == "SIGINT" else (143, "safenav: terminated (SIGTERM)")
    )
    assert time.monotonic() - sent < 20 and proc.returncode == code, err
    assert err.strip().splitlines()[-1] == said and "Traceback" not in err
    last = events(run_dir)[-1]
    assert last["event"] == "interrupted" and last["signal"] == sig
    state = load_checkpoint(run_dir / "checkpoint.pt")
    assert state["global_step"] == last["global_step"] >= 64
    end = state["global_step"] + 128
    main(resume_args(algo, run_dir, "--total-steps", str(end)))
    assert load_checkpoint(run_dir / "checkpoint.pt")["global_step"] >= end
    kinds = [e["event"] for e in events(run_dir)]
    assert kinds[-1] == "end" and "resume" in kinds


def test_a_run_dir_in_use_by_another_trainer_is_refused(tmp_path, capsys):
    """Two trainers on one run dir (a rerun while the first still trains) would both write its
    checkpoint and logs: the second is refused, and the dir is free again once the first ends."""
    run_dir = tmp_path / "busy"
    proc = launch(train_args("csac", run_dir, 10**7))
    try:
        assert wait_until(lambda: logged_step(run_dir) >= 0, proc), proc.communicate()[1]
        err = fails(capsys, resume_args("csac", run_dir), "is in use by another safenav process",
                    f"pid {proc.pid}")  # fmt: skip
        assert "kill -TERM" in err
        fails(capsys, train_args("csac", run_dir, 640, "--overwrite"), "in use")
        assert (run_dir / "checkpoint.pt").exists() or proc.poll() is None  # nothing deleted
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert proc.returncode == 143 and events(run_dir)[-1]["event"] == "interrupted"
    step = load_checkpoint(run_dir / "checkpoint.pt")["global_step"]
    main(resume_args("csac", run_dir, "--total-steps", str(step + 64)))  # free again
    assert events(run_dir)[-1]["event"] == "end"


def test_run_dir_lock_leaves_nothing_when_refused_and_works_without_flock(tmp_path, monkeypatch):
    import errno
    import fcntl

    from safenav.common.logger import LOCK_FILE, run_dir_lock, wait_for_run_dir

    fresh = tmp_path / "fresh"
    with pytest.raises(SafenavError), run_dir_lock(fresh):
        raise SafenavError("refused before writing")  # e.g. by prepare_run_dir
    assert not fresh.exists()  # neither the lock file nor the directory it made
    kept = tmp_path / "kept"
    with pytest.raises(SafenavError), run_dir_lock(kept) as lock:
        lock.accepted = True  # past the refusals: a run that then failed (diverged)
        (kept / "config.json").write_text("{}")
        raise SafenavError("diverged")
    assert (kept / LOCK_FILE).exists() and wait_for_run_dir(kept, timeout_s=0)

    # a file system without flock (NFS without lockd): the run goes on without a lock
    def no_flock(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_flock)
    with run_dir_lock(tmp_path / "nfs"), run_dir_lock(tmp_path / "nfs"):
        pass


# -------------------------------------------------------------------- 3. one-line errors
def fails(capsys, args: list[str], *words: str) -> str:
    """``safenav ARGS`` exits with code 2 and one ``safenav: error:`` line naming ``words``."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        main(args)
    err = capsys.readouterr().err.strip()
    assert exit_.value.code == 2, err
    assert len(err.splitlines()) == 1 and err.startswith("safenav: error: "), err
    for word in words:
        assert word in err, (word, err)
    return err


def test_bad_training_options_are_one_line_errors_and_create_no_run_dir(tmp_path, capsys):
    run_dir = tmp_path / "run"
    base = ["train", "--run-dir", str(run_dir), "--preset", "easy", "--no-progress"]
    fails(capsys, [*base, "--algo", "foo"], "unknown algorithm 'foo'", "csac, sac, ppo")
    fails(capsys, ["train", "--run-dir", str(run_dir), "--env", "NoSuchEnv-v0"], "unknown env id")
    fails(capsys, ["train", "--run-dir", str(run_dir), "--preset", "hard"], "unknown preset 'hard'")
    fails(capsys, [*base, "--env", "Pendulum-v1"], "--preset applies to SafeNav-v1 only")
    fails(capsys, [*base, "--csac.actor-lr", "-1"], "actor-lr=-1.0")
    fails(capsys, [*base, "--algo", "ppo", "--ppo.lr", "nan"], "lr=nan")
    fails(capsys, [*base, "--num-envs", "0"], "num-envs=0")
    fails(capsys, [*base, "--num-envs", "many"], "--num-envs", "'many'")
    fails(capsys, [*base, "--csac.net.hidden", "0", "0"], "network sizes")
    fails(capsys, [*base, "--density.start", "2"], "density")
    assert not run_dir.exists()
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    fails(
        capsys,
        [*base[:1], "--run-dir", str(blocker / "run"), *base[3:]],
        "cannot create run directory",
    )
    fails(capsys, [*base[:1], "--run-dir", str(blocker), *base[3:]], "cannot create run directory")


def test_run_dir_holding_a_run_is_refused(reference, tmp_path, capsys):
    run_dir = tmp_path / "taken"
    shutil.copytree(reference["csac"], run_dir)
    fails(capsys, train_args("csac", run_dir), "already holds a run", "--resume", "--overwrite")


def test_unusable_checkpoints_for_resume_are_one_line_errors(reference, tmp_path, capsys):
    def run_dir_with(name: str, algo: str = "csac", checkpoint: bytes | None = None) -> Path:
        run_dir = tmp_path / name
        shutil.copytree(reference[algo], run_dir)
        if checkpoint is None:
            (run_dir / "checkpoint.pt").unlink()
        else:
            (run_dir / "checkpoint.pt").write_bytes(checkpoint)
        return run_dir

    good = (reference["csac"] / "checkpoint.pt").read_bytes()
    state = load_checkpoint(reference["csac"])
    fails(capsys, resume_args("csac", tmp_path / "nowhere"), "no config.json")
    fails(capsys, resume_args("csac", run_dir_with("none")), "no checkpoint.pt", "--overwrite")
    noise = random.Random(0).randbytes(50_000)
    fails(capsys, resume_args("csac", run_dir_with("noise", checkpoint=noise)), "corrupt")
    cut = run_dir_with("cut", checkpoint=good[: len(good) // 2])
    fails(capsys, resume_args("csac", cut), "corrupt or truncated")
    fails(capsys, resume_args("ppo", run_dir_with("as-ppo")), "the run is --algo csac, not ppo")
    ppo_ckpt = (reference["ppo"] / "checkpoint.pt").read_bytes()
    fails(capsys, resume_args("csac", run_dir_with("ppo-ckpt", checkpoint=ppo_ckpt)),
          "holds a 'ppo' run, not 'csac'")  # fmt: skip
    # the same algorithm on another observation layout: a Pendulum-v1 CSAC checkpoint
    pendulum = tmp_path / "pendulum"
    main(["train", "--algo", "csac", "--env", "Pendulum-v1", "--num-envs", "2", "--total-steps", "96",
          "--run-dir", str(pendulum), *FAST[4:], *SMALL["csac"]])  # fmt: skip
    other = run_dir_with("layout", checkpoint=(pendulum / "checkpoint.pt").read_bytes())
    fails(capsys, resume_args("csac", other), "does not fit the networks", "observation layout")
    newer = run_dir_with("newer", checkpoint=b"")
    torch.save({**state, "format_version": 99}, newer / "checkpoint.pt")
    fails(capsys, resume_args("csac", newer), "format version 99", "newer safenav")
    policy_only = run_dir_with("policy-only", checkpoint=b"")
    save_policy_only(reference["csac"] / "checkpoint.pt", policy_only / "checkpoint.pt")
    fails(capsys, resume_args("csac", policy_only), "policy-only")


def test_unusable_checkpoints_for_eval_are_one_line_errors(reference, tmp_path, capsys):
    good = (reference["csac"] / "checkpoint.pt").read_bytes()
    state = load_checkpoint(reference["csac"])
    fails(capsys, ["eval", str(tmp_path / "missing.pt")], "not found")
    (tmp_path / "noise.pt").write_bytes(random.Random(1).randbytes(50_000))
    fails(capsys, ["eval", str(tmp_path / "noise.pt")], "corrupt")
    (tmp_path / "cut.pt").write_bytes(good[: len(good) // 3])
    fails(capsys, ["eval", str(tmp_path / "cut.pt")], "corrupt or truncated")
    torch.save({**state, "format_version": 2}, tmp_path / "newer.pt")
    fails(capsys, ["eval", str(tmp_path / "newer.pt")], "format version 2", "newer safenav")
    # another algorithm's policy head on these weights: PPO's Beta actor on CSAC's
    meta = {**state["policy"]["meta"], "policy_head": "beta"}
    save_checkpoint(tmp_path / "beta.pt", {**state, "policy": {**state["policy"], "meta": meta}})
    fails(capsys, ["eval", str(tmp_path / "beta.pt")], "do not fit")
    # a policy of another env (observation layout {"obs": (3,)})
    pendulum = tmp_path / "pendulum"
    main(["train", "--algo", "sac", "--env", "Pendulum-v1", "--num-envs", "2", "--total-steps", "96",
          "--run-dir", str(pendulum), *FAST[4:], *SMALL["csac"]])  # fmt: skip
    fails(capsys, ["eval", str(pendulum), "--episodes", "2"], "Pendulum-v1", "not SafeNav")
    # a SafeNav policy on a scenario with another sensor layout
    with pytest.raises(SafenavError, match="reads observations"):
        check_fits_safenav(
            load_policy(reference["csac"]), make_config("easy", lidar_h_beams=40), "x"
        )


# ------------------------------------------------------------------ 3. NaN/Inf stops a run
def test_absurd_learning_rate_stops_csac_and_keeps_the_last_good_checkpoint(tmp_path, capsys):
    """Warm-up (no updates) until step 120 writes good checkpoints; the first updates at a
    learning rate of 1e30 blow the critics up to NaN/Inf."""
    run_dir = tmp_path / "diverged"
    err = fails(capsys, train_args("csac", run_dir, TOTAL, "--csac.learning-starts", "120",
                                   "--csac.reward-critic-lr", "1e30", "--csac.cost-critic-lr", "1e30"),
                "training diverged at step", "NaN/Inf", "keeps the last good state (step 96)")  # fmt: skip
    state = load_checkpoint(run_dir / "checkpoint.pt")
    assert state["global_step"] == 96 and finite(state)
    last = events(run_dir)[-1]
    assert last["event"] == "diverged" and last["error"] in err
    load_policy(run_dir)  # the kept checkpoint is still a usable policy


def test_nan_loss_stops_ppo_and_keeps_the_last_good_checkpoint(tmp_path, capsys, monkeypatch):
    """A policy loss that turns NaN from the third rollout's update (4 minibatch steps each)."""
    calls, loss = [0], ppo.clipped_policy_loss

    def poisoned(*args, **kwargs):
        calls[0] += 1
        out = loss(*args, **kwargs)
        return out * float("nan") if calls[0] > 8 else out

    monkeypatch.setattr(ppo, "clipped_policy_loss", poisoned)
    run_dir = tmp_path / "diverged"
    fails(capsys, train_args("ppo", run_dir), "training diverged at step 192", "losses/actor",
          "keeps the last good state (step 128)")  # fmt: skip
    state = load_checkpoint(run_dir / "checkpoint.pt")
    assert state["global_step"] == 128 and finite(state)
    assert events(run_dir)[-1]["event"] == "diverged"
    monkeypatch.setattr(ppo, "clipped_policy_loss", loss)  # fixed: the run resumes from there
    main(resume_args("ppo", run_dir, "--total-steps", "256"))
    assert load_checkpoint(run_dir / "checkpoint.pt")["global_step"] == 256


def test_process_running_tells_a_live_process_from_an_exited_one():
    """What `safenav reproduce` waits on when it stops its trainers: an exited child that nobody
    has reaped yet (a zombie, which `kill(pid, 0)` still finds) counts as stopped."""
    from safenav.common.stopping import process_running

    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        assert process_running(child.pid)
        child.terminate()
        deadline = time.time() + 10
        while process_running(child.pid) and time.time() < deadline:
            time.sleep(0.05)  # not reaped (no wait/poll) until the assertion below
        assert not process_running(child.pid)
        assert child.poll() is not None
    finally:
        child.kill()
        child.wait()
    assert not process_running(child.pid)


def test_an_evaluation_a_stop_cut_short_runs_on_resume(tmp_path, monkeypatch):
    """A stop lands mostly inside a periodic evaluation (the slow part of a step that has one):
    the resumed run evaluates the checkpoint's weights at that step first, so the validation
    curve keeps every point (``safenav reproduce``'s records lost one per such stop)."""
    from safenav.training.trainer import Trainer

    run_dir = tmp_path / "cut"
    real = Trainer.evaluate

    def stopped_inside(self):  # Ctrl-C while the first evaluation flies its episodes
        raise KeyboardInterrupt

    monkeypatch.setattr(Trainer, "evaluate", stopped_inside)
    args = ["--eval-every", "128", "--eval-episodes", "2"]
    with pytest.raises((SystemExit, KeyboardInterrupt)):
        main(train_args("ppo", run_dir, 256, *args))
    stop = events(run_dir)[-1]
    assert stop["event"] == "interrupted" and stop["global_step"] == 128
    assert load_checkpoint(run_dir / "checkpoint.pt")["next_eval_step"] == 128
    monkeypatch.setattr(Trainer, "evaluate", real)
    main(resume_args("ppo", run_dir))
    evals = [e["global_step"] for e in events(run_dir) if e["event"] == "eval"]
    assert evals == [128, 256]
    assert load_checkpoint(run_dir / "checkpoint.pt")["next_eval_step"] == 384
