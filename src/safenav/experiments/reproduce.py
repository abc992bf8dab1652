"""``safenav reproduce``: the paper's Section IV as one command, every trial a Ray task.

A *trial* is one algorithm × one seed: ``safenav train`` into its run directory, then
``safenav eval`` of the final checkpoint on the fixed test scenario (env seed 1, paper IV-B).
Each trial is a Ray task that reserves ``cpus_per_trial`` CPUs and runs both commands as
subprocesses with that many torch threads, logging to ``OUT/logs/``. Ray is the only scheduler:
``ray.init()`` starts a local instance (all cores of this machine) or, with ``address``, joins an
existing cluster, and runs as many trials at once as the CPUs allow.

Layout of ``OUT`` (the trial state lives in the files, so rerunning the same command resumes):

```
OUT/runs/<algo>/seed<S>/   the run directory of safenav train (config.json, progress.csv, tb/,
                           checkpoint.pt) plus eval.json (safenav eval) and reproduce.json
                           (what this module ran: total steps, attempts, training wall-clock)
OUT/logs/<algo>-seed<S>.{train,eval}.log   the subprocesses' output
OUT/results.json, OUT/results.md           mean ± std across seeds (safenav.experiments.aggregate)
OUT/figures/*.png                          safenav plot OUT
```

A trial whose ``reproduce.json`` says it trained to ``total_steps`` and whose ``eval.json`` is
newer than its checkpoint is skipped; one with a checkpoint but unfinished is resumed with
``--resume``; one trained but not evaluated is only evaluated.
"""

from __future__ import annotations

import contextlib
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from safenav.common.jsonout import write_json
from safenav.common.machine import machine_description
from safenav.errors import SafenavError
from safenav.experiments.aggregate import (
    aggregate,
    display_name,
    fmt_rate,
    fmt_seconds,
    last_step,
    read_json,
    seed_record,
    write_results,
)

#: The algorithms ``safenav train --algo`` accepts (SPEC §3).
KNOWN_ALGOS: tuple[str, ...] = ("csac", "sac", "ppo", "ppo_lag", "sac_lag")
#: Env steps per trial when ``--total-steps`` names no figure for an algorithm.
DEFAULT_TOTAL_STEPS: dict[str, int] = {
    "csac": 1_000_000,
    "sac": 1_000_000,
    "sac_lag": 1_000_000,
    "ppo": 3_000_000,
    "ppo_lag": 3_000_000,
}
FALLBACK_TOTAL_STEPS = 1_000_000

#: ``safenav reproduce`` with no --algos and no --variants: the paper's comparison (issue 21), on
#: the flight stack of the default csac recipe. CSAC, SAC and PPO (the paper's Fig. 4) with 5
#: seeds; the Lagrangian baselines and the CSAC ablations with 3; one env-step budget (1M) for
#: every label (the paper's x-axis is env steps). Every label but csac_paper sees the observation
#: of the csac recipe (one second of range-image memory, beams tilted down, the 10 nearest
#: pillars), trains behind its velocity-obstacle shield and is reported behind its planner filter
#: (``--flight-filter``) and, in the same record, without it (``test_without_filter``): each
#: baseline's recipe is its own on that stack (``*-shielded-memory-pillars``). csac_paper is the
#: paper's method exactly (its observation, no shield, no filter).
PAPER_ALGOS: tuple[str, ...] = ("csac", "sac", "ppo", "sac_lag", "ppo_lag")
PAPER_VARIANTS: tuple[str, ...] = (
    "csac=csac",  # the default recipe: csac-shielded-memory-pillars + the planner filter
    "sac=sac --config sac-shielded-memory-pillars --flight-filter",
    "ppo=ppo --config ppo-shielded-memory-pillars --flight-filter",
    "sac_lag=sac_lag --config sac-lag-shielded-memory-pillars --flight-filter",
    "ppo_lag=ppo_lag --config ppo-lag-shielded-memory-pillars --flight-filter",
    "csac_paper=csac --config csac-paper",  # the paper's equations and values exactly
    "csac_min=csac --csac.cost-target min",  # min over the target cost critics
    "csac_fixed_d=csac --csac.curriculum.no-enabled",  # no curriculum: d = d_min
    # PPO's validation success still rose steeply at 1M (seed 1: 0.18, 0.48, 0.62 at 0.5, 0.75,
    # 1M): its own larger budget, an extra row compared with no label of the 1M budget
    "ppo_3m=ppo --config ppo-shielded-memory-pillars --flight-filter",
)
PAPER_SEEDS = ("1-5 sac_lag=1-3 ppo_lag=1-3 csac_paper=1-3 csac_min=1-3 csac_fixed_d=1-3 "
               "ppo_3m=1-3")  # fmt: skip
PAPER_TOTAL_STEPS: tuple[str, ...] = ("1M", "ppo_3m=3M")

#: ``safenav reproduce --algos paper-observation``: the comparison as it ran 2026-11-26 to 12-03,
#: on the paper's observation (no memory, no pillar list) and without shield or filter, every
#: CSAC label from csac-maxcost-crashloss, the recipe the sac, sac-lag and csac-tuned recipes are
#: built on (results/paper-observation; docs/reproduce.md): the five algorithms and two
#: ablations at 1M, the same at 3M where their curves flatten, and each algorithm's tuned recipe
#: at 3M. Its csac_paper row is the paper plan's (results/paper), not repeated here.
OBSERVATION_CSAC = "csac --config csac-maxcost-crashloss"
OBSERVATION_VARIANTS: tuple[str, ...] = (
    f"csac={OBSERVATION_CSAC}",
    f"csac_min={OBSERVATION_CSAC} --csac.cost-target min",
    f"csac_fixed_d={OBSERVATION_CSAC} --csac.curriculum.no-enabled",
    f"csac_3m={OBSERVATION_CSAC}",
    "sac_3m=sac",
    "ppo_3m=ppo",
    "sac_lag_3m=sac_lag",
    "ppo_lag_3m=ppo_lag",
    # Each algorithm with the values `safenav tune` chose for it on validation maps (8 trials
    # each; docs/reproduce.md counts them), at the same 3M budget.
    "csac_tuned_3m=csac --config csac-tuned",
    "sac_tuned_3m=sac --config sac-tuned",
    "ppo_tuned_3m=ppo --config ppo-tuned",
    "sac_lag_tuned_3m=sac_lag --config sac-lag-tuned",
    "ppo_lag_tuned_3m=ppo_lag --config ppo-lag-tuned",
)
OBSERVATION_SEEDS = ("1-5 sac_lag=1-3 ppo_lag=1-3 csac_min=1-3 csac_fixed_d=1-3 "
                     "sac_lag_3m=1-3 ppo_lag_3m=1-3 sac_lag_tuned_3m=1-3 ppo_lag_tuned_3m=1-3")  # fmt: skip
OBSERVATION_TOTAL_STEPS: tuple[str, ...] = (
    "1M", "csac_3m=3M", "sac_3m=3M", "ppo_3m=3M", "sac_lag_3m=3M", "ppo_lag_3m=3M",
    "csac_tuned_3m=3M", "sac_tuned_3m=3M", "ppo_tuned_3m=3M", "sac_lag_tuned_3m=3M",
    "ppo_lag_tuned_3m=3M")  # fmt: skip


@dataclass(frozen=True)
class Plan:
    """A named comparison that ``safenav reproduce --algos NAME`` runs: its labels (algorithms,
    then ``--variants`` lines), seeds, budgets and output directory."""

    algos: tuple[str, ...]
    variants: tuple[str, ...]
    seeds: str
    total_steps: tuple[str, ...]
    out: str


PLANS: dict[str, Plan] = {
    "paper": Plan(PAPER_ALGOS, PAPER_VARIANTS, PAPER_SEEDS, PAPER_TOTAL_STEPS, "results/paper"),
    "paper-observation": Plan(PAPER_ALGOS, OBSERVATION_VARIANTS, OBSERVATION_SEEDS,
                              OBSERVATION_TOTAL_STEPS, "results/paper-observation"),
}  # fmt: skip
#: One evaluation protocol for every label of the comparison, whatever its recipe says: the
#: validation curves of Fig. 3 at the same points, and the same policies for --select to choose
#: from (the csac and sac recipes already do this; ppo's evaluates every 1M of its 30M).
PAPER_TRAIN_ARGS: tuple[str, ...] = ("--eval-every", "250000", "--eval-episodes", "400",
                                     "--checkpoint-every", "250000")  # fmt: skip


@dataclass(frozen=True)
class Trial:
    """One algorithm × one seed: what to train, where, with which resources."""

    label: str
    """Name in the results (an algorithm, or a ``--variants`` label)."""
    algo: str
    """``safenav train --algo``."""
    seed: int
    total_steps: int
    run_dir: Path
    log_dir: Path
    preset: str | None = "paper"
    device: str = "cpu"
    cpus: int = 2
    """CPUs reserved in Ray and torch threads of the subprocesses."""
    gpus: float = 0.0
    eval_episodes: int = 200
    env_seed: int = 1
    train_args: tuple[str, ...] = ()
    """Extra arguments appended to ``safenav train`` (config overrides)."""
    python: str | None = None
    """Interpreter that runs ``-m safenav`` (default: the Ray worker's own ``sys.executable``)."""
    select: bool = True
    """Train with ``--select``: the run ends by choosing ``policy.pt`` on validation maps only
    and reporting it on the held-out maps (``final.json``); the test evaluation flies that
    policy. False: the final checkpoint's policy, as before."""

    @property
    def name(self) -> str:
        return f"{self.label}-seed{self.seed}"

    @property
    def checkpoint(self) -> Path:
        return self.run_dir / "checkpoint.pt"

    @property
    def policy(self) -> Path:
        """The policy the test evaluation flies: ``policy.pt`` (chosen on validation) or the
        final checkpoint."""
        return self.run_dir / "policy.pt" if self.select else self.checkpoint

    @property
    def record_path(self) -> Path:
        """``OUT/trials/<label>-s<S>.json``: the finished trial's record, small enough to commit."""
        return self.log_dir.parent / "trials" / f"{self.label}-s{self.seed}.json"

    @property
    def kept_policy_path(self) -> Path:
        """``OUT/trials/<label>-s<S>.pt``: the evaluated policy without optimisers or critics,
        committed with the record so that a fresh clone can evaluate it again (behind another
        filter, on other maps) without training it again."""
        return self.record_path.with_suffix(".pt")

    def log(self, kind: str) -> Path:
        """``OUT/logs/<label>-seed<S>.<kind>``."""
        return self.log_dir / f"{self.name}.{kind}"

    def train_command(self, resume: bool, overwrite: bool = False) -> list[str]:
        """``python -m safenav train ...`` for this trial."""
        cmd = [self.python or sys.executable, "-m", "safenav", "train", "--algo", self.algo,
               "--env", "SafeNav-v1", "--seed", str(self.seed), "--total-steps",
               str(self.total_steps), "--run-dir", str(self.run_dir),
               "--device", self.device,
               # the trial's CPUs, over a recipe's own torch_threads (csac's is 2): two trials
               # of 2 threads on 2 cores ran 12x slower than two of one (54 vs 675 env steps/s)
               "--torch-threads", str(self.cpus)]  # fmt: skip
        if self.preset is not None:
            cmd += ["--preset", self.preset]
        if self.select:
            cmd += ["--select"]
        args = list(self.train_args)
        if resume:
            cmd += ["--resume", str(self.run_dir)]
            # the run's config.json holds its recipe, and train refuses --config with --resume
            args = without_config(args)
        elif overwrite:
            cmd += ["--overwrite"]
        return cmd + args

    def eval_command(self) -> list[str]:
        """``python -m safenav eval CHECKPOINT ...`` writing ``eval.json`` into the run dir."""
        return [self.python or sys.executable, "-m", "safenav", "eval", str(self.policy),
                "--env-seed", str(self.env_seed), "--episodes", str(self.eval_episodes),
                "--device", self.device, "--json", str(self.run_dir / "eval.json")]  # fmt: skip


def without_config(args: list[str]) -> list[str]:
    """``args`` less every ``--config NAME`` / ``--config=NAME``."""
    out, skip = [], False
    for arg in args:
        if skip:
            skip = False
        elif arg == "--config":
            skip = True
        elif not arg.startswith("--config="):
            out.append(arg)
    return out


def trial_state(trial: Trial) -> str:
    """``"done"``, ``"evaluate"`` (trained, not evaluated), ``"resume"`` or ``"fresh"``."""
    marker = read_json(trial.run_dir / "reproduce.json") or {}
    trained = bool(marker.get("trained")) and int(marker.get("total_steps", 0)) >= trial.total_steps
    if trained and trial.checkpoint.exists() and trial.policy.exists():
        ev = read_json(trial.run_dir / "eval.json") or {}
        fresh_eval = (
            ev.get("episodes") == trial.eval_episodes
            and ev.get("env_seed") == trial.env_seed
            and (trial.run_dir / "eval.json").stat().st_mtime >= trial.policy.stat().st_mtime
        )
        return "done" if fresh_eval else "evaluate"
    return "resume" if trial.checkpoint.exists() else "fresh"


class TrialFailed(RuntimeError):
    """A trial's subprocess exited with an error; the message ends with its log's last lines."""


class TrialStopped(TrialFailed):
    """A trial's trainer was stopped on purpose (Ctrl-C or ``kill -INT`` of the trainer, or the
    sweep's own stop) and wrote its checkpoint: not retried; the same command resumes it."""


class TrialKilled(TrialFailed):
    """A trial's subprocess was killed by a signal (the OOM killer, a node going away): Ray runs
    the task again (:data:`RETRIES`), which resumes the trial from its last checkpoint. A trial
    that exits with an error code of its own is not retried: the same error would recur."""


#: How many times Ray runs a trial again after its worker died (``max_retries``) or its training
#: subprocess was killed (:class:`TrialKilled`, ``retry_exceptions``); each retry resumes.
RETRIES = 2

#: How long a stopped sweep waits for a trainer to write its checkpoint and exit before it is
#: killed (its last periodic checkpoint stays). A checkpoint holds the replay buffer: seconds.
STOP_WAIT_S = 300.0


def _run_logged(cmd: list[str], log: Path, threads: int, pid_file: Path | None = None) -> float:
    """Run ``cmd`` with ``threads`` torch/OpenMP threads, output appended to ``log``.

    Returns the seconds it took; raises :class:`TrialFailed` on a non-zero exit. While it runs,
    ``pid_file`` holds ``HOST PID`` of the child (what a stopping sweep signals). If this process
    is interrupted (Ray cancelled the task), the child is terminated first, unless the sweep has
    signalled it already (``pid_file`` with ``.stop`` beside it): one SIGTERM, one checkpoint.
    """
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
           "COLUMNS": "120", "PYTHONUNBUFFERED": "1"}  # fmt: skip
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with log.open("ab") as out:
        out.write(f"\n$ {shlex.join(cmd)}\n".encode())
        out.flush()
        from safenav.common.stopping import die_with_parent

        preexec = die_with_parent if sys.platform.startswith("linux") else None
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env,
                                preexec_fn=preexec)  # fmt: skip
        if pid_file is not None:
            pid_file.write_text(f"{socket.gethostname()} {proc.pid}\n")
        try:
            # Poll: Ray cancels a task by interrupting its thread between bytecodes, which a
            # wait() blocked in waitpid would not see until the trainer ended on its own.
            while (rc := proc.poll()) is None:
                time.sleep(0.2)
        except BaseException:
            if not (pid_file is not None and stop_marker(pid_file).exists()):
                proc.terminate()  # the trainer's SIGTERM: a checkpoint at this step, exit 143
            try:
                proc.wait(timeout=STOP_WAIT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
            raise
        finally:
            if pid_file is not None:
                pid_file.unlink(missing_ok=True)
    seconds = time.perf_counter() - t0
    if rc != 0:
        tail = log.read_text(errors="replace").strip().splitlines()[-15:]
        # Killed from outside (the OOM killer's SIGKILL, a SIGTERM the trainer answered with a
        # checkpoint and 143), not a crash of its own (SIGSEGV, SIGABRT: they would recur).
        killed = rc in (
            -signal.SIGKILL,
            -signal.SIGTERM,
            128 + signal.SIGKILL,
            128 + signal.SIGTERM,
        )
        if rc == 128 + signal.SIGINT:  # Ctrl-C or ``kill -INT`` of the trainer itself
            raise TrialStopped(
                f"stopped by SIGINT with a checkpoint (exit code {rc}); rerun to resume\n"
                + "\n".join(tail)
            )
        raise (TrialKilled if killed else TrialFailed)(
            f"exit code {rc} from: {shlex.join(cmd[1:])}\n" + "\n".join(tail)
        )
    return seconds


def stop_marker(pid_file: Path) -> Path:
    """Written by a stopping sweep before it signals the trainer named in ``pid_file``."""
    return pid_file.with_suffix(".stop")


def was_stopped(trial: Trial) -> bool:
    """Whether the trial's last attempt ended stopped on purpose, with a checkpoint (its status
    file, written by :func:`run_trial`, is the one record of it, in a Ray worker or not)."""
    status = trial.log("status")
    return status.exists() and status.read_text().strip() == "stopped"


def _write_json(path: Path, data: dict[str, Any]) -> None:
    write_json(path, data, default=str)  # atomic and fsynced


def run_trial(trial: Trial) -> dict[str, Any]:
    """Train (fresh or resumed) and evaluate one trial as its files require; the Ray task body.

    Returns ``{"name", "state", "host", "started", "train_s", "eval_s"}`` (``state`` as found by
    :func:`trial_state` before it ran; ``started`` as ``time.time()``).
    """
    from safenav.common.logger import wait_for_run_dir

    started = time.time()
    # A retry after a worker died: its trainer may still be writing the checkpoint (SIGTERM).
    if not wait_for_run_dir(trial.run_dir):
        raise TrialFailed(f"{trial.run_dir} is still in use by another safenav train after 300 s")
    state = trial_state(trial)
    info: dict[str, Any] = {"name": trial.name, "state": state, "host": socket.gethostname(),
                            "started": started, "train_s": 0.0, "eval_s": 0.0}  # fmt: skip
    status = trial.log("status")
    status.parent.mkdir(parents=True, exist_ok=True)
    marker_path = trial.run_dir / "reproduce.json"
    if state in ("fresh", "resume"):
        status.write_text("training")
        # No checkpoint yet: whatever an earlier attempt left in the run dir is replaced.
        overwrite = state == "fresh" and trial.run_dir.exists()
        cmd = trial.train_command(resume=state == "resume", overwrite=overwrite)
        attempt: dict[str, Any] = {
            "started": datetime.fromtimestamp(started, timezone.utc).isoformat(timespec="seconds"),
            "host": info["host"],
            "resume": state == "resume",
        }
        try:
            info["train_s"] = _run_logged(cmd, trial.log("train.log"), trial.cpus,
                                          pid_file=trial.log("trainer.pid"))  # fmt: skip
        except TrialKilled:
            if stop_marker(trial.log("trainer.pid")).exists():  # the sweep stopped it: no retry
                status.write_text("stopped")
                raise TrialStopped(
                    f"{trial.name} stopped with a checkpoint; rerun to resume"
                ) from None
            status.write_text("killed")  # Ray runs it again (a resume)
            raise
        except TrialStopped:
            status.write_text("stopped")
            raise
        except TrialFailed:
            status.write_text("failed")
            raise
        finally:
            # Keep the record of every attempt, including failed ones, for the wall-clock total.
            marker = read_json(marker_path) or {}
            attempts = marker.get("attempts", [])
            attempts.append({**attempt, "seconds": round(time.time() - started, 2)})
            marker = {
                **asdict(trial),
                "run_dir": str(trial.run_dir),
                "log_dir": str(trial.log_dir),
                "trained": False,
                "attempts": attempts,
                "train_wall_clock_s": round(sum(a["seconds"] for a in attempts), 2),
                "command": shlex.join(cmd[1:]),
            }
            if trial.run_dir.exists():
                _write_json(marker_path, marker)
        marker["trained"] = True
        _write_json(marker_path, marker)
    if state != "done":
        status.write_text("evaluating")
        try:
            info["eval_s"] = _run_logged(trial.eval_command(), trial.log("eval.log"), trial.cpus)
        except TrialStopped:
            status.write_text("stopped")
            raise
        if (marker := read_json(marker_path)) is not None:  # the trial's whole time, for ETAs
            _write_json(marker_path, {**marker, "eval_wall_clock_s": round(info["eval_s"], 2)})
    write_trial_record(trial)
    status.write_text("done")
    return info


def committed_record(trial: Trial) -> dict[str, Any] | None:
    """The trial's ``OUT/trials/`` record when it is the result this trial asks for (same
    budget and test episodes) and no run directory says otherwise: what a rerun in a fresh clone,
    which has the committed records but not the (ignored) run directories, reports and skips."""
    if trial.checkpoint.exists():
        return None  # a run directory is there: its files decide (trial_state)
    rec = read_json(trial.record_path)
    if not rec or rec.get("budget_env_steps") != trial.total_steps:
        return None
    if rec.get("eval_episodes") != trial.eval_episodes or rec.get("algo") != trial.label:
        return None
    if (rec.get("selection") == "validation") != trial.select:
        return None
    return rec


def rereported_record(trial: Trial) -> dict[str, Any] | None:
    """The trial's ``OUT/trials/`` record where its report was flown again from its committed
    policy (``experiments/rereport_filter.py``: ``"rereported"``) after the run directory's own
    report (``eval.json``): that record, which the run directory's older files must not
    overwrite; else None."""
    rec = read_json(trial.record_path)
    evaluated = trial.run_dir / "eval.json"
    if not rec or not isinstance(rec.get("rereported"), dict) or not evaluated.exists():
        return None
    try:
        when = datetime.fromisoformat(str(rec["rereported"].get("date"))).timestamp()
    except ValueError:
        return None
    return rec if when > evaluated.stat().st_mtime else None


def earlier_trial_records(out: Path) -> list[dict[str, Any]]:
    """The records in ``OUT/trials/`` (each names its label and seed; its own commands say how
    it was made), e.g. of earlier sweeps into the same OUT."""
    found = []
    for path in sorted((out / "trials").glob("*.json")):
        rec = read_json(path)
        if rec and isinstance(rec.get("algo"), str) and isinstance(rec.get("seed"), int):
            found.append(rec)
    return found


#: The comparison's labels in report order: the paper's algorithms, then its variants.
REPORT_LABELS = tuple(
    dict.fromkeys(PAPER_ALGOS + tuple(v.split("=", 1)[0] for v in PAPER_VARIANTS))
    | dict.fromkeys(v.split("=", 1)[0] for v in OBSERVATION_VARIANTS)
)


def report_order(rec: dict[str, Any]) -> tuple[int, str, int]:
    """The paper comparison's labels in their order (its algorithms, then its variants), any
    other label after them by name; seeds ascending."""
    label = rec["algo"]
    rank = REPORT_LABELS.index(label) if label in REPORT_LABELS else len(REPORT_LABELS)
    return rank, label if rank == len(REPORT_LABELS) else "", int(rec.get("seed") or 0)


def write_trial_record(trial: Trial, rec: dict[str, Any] | None = None) -> dict[str, Any]:
    """``OUT/trials/<label>-s<S>.json``: the trial's row of the results (test, held-out,
    selection, budget, wall-clock, arena metrics; ``rec``, the run's :func:`seed_record` when the
    caller has it, is not modified) and the commands that made it, and beside it the evaluated
    ``policy.pt`` of a ``--select`` trial (:attr:`Trial.kept_policy_path`, named in the record's
    ``"policy"``); commit both as each trial finishes (the run directory itself is large and
    ignored, and a re-evaluation needs the policy)."""
    rec = dict(rec) if rec is not None else seed_record(trial.run_dir, algo=trial.label,
                                                         seed=trial.seed)  # fmt: skip
    marker = read_json(trial.run_dir / "reproduce.json") or {}
    out = trial.log_dir.parent
    rec["run_dir"] = os.path.relpath(trial.run_dir, out)
    rec |= {"budget_env_steps": trial.total_steps, "train_command": marker.get("command"),
            "eval_command": shlex.join(trial.eval_command()[1:]),
            "recipe": (read_json(trial.run_dir / "config.json") or {}).get("recipe", {}).get("name")}  # fmt: skip
    if marker.get("train_wall_clock_s") is not None:
        # training, selection and report (every attempt) plus the last eval: what the trial cost
        rec["trial_wall_clock_s"] = round(
            float(marker["train_wall_clock_s"]) + float(marker.get("eval_wall_clock_s") or 0.0), 2
        )
    trial.record_path.parent.mkdir(parents=True, exist_ok=True)
    if trial.select and trial.policy.exists():  # policy.pt of --select: policy-only, ~0.7 MB
        part = trial.kept_policy_path.with_suffix(".pt.part")
        shutil.copyfile(trial.policy, part)
        os.replace(part, trial.kept_policy_path)  # atomic: a killed sweep leaves no half file
        rec["policy"] = os.path.relpath(trial.kept_policy_path, out)
    write_json(trial.record_path, rec)
    return rec


# -- the sweep -----------------------------------------------------------------------------------


def parse_steps(text: str) -> int:
    """``"300000"``, ``"300_000"``, ``"300k"``, ``"2M"``, ``"1e6"`` -> an int of env steps (the
    forms ``safenav train --total-steps`` takes: :func:`safenav.common.checks.parse_count`)."""
    from safenav.common.checks import parse_count

    try:
        value = parse_count(text)
    except ValueError:
        raise SafenavError(f"--total-steps: {text!r} is not a number of env steps (1000000, 1e6, "
                           "1_000_000 or 1M)") from None  # fmt: skip
    if value < 1:
        raise SafenavError(f"--total-steps: {text!r} must be a positive whole number")
    return value


def resolve_total_steps(specs: Sequence[str], labels: Sequence[str],
                        algo_of: dict[str, str]) -> dict[str, int]:  # fmt: skip
    """Env steps per label from ``["N", "csac=300k", ...]``: a bare ``N`` is the default for all.

    Labels named nowhere get :data:`DEFAULT_TOTAL_STEPS` of their algorithm.
    """
    default: int | None = None
    named: dict[str, int] = {}
    for spec in specs:
        if "=" in spec:
            key, value = spec.split("=", 1)
            if key not in labels:
                raise SafenavError(
                    f"--total-steps {spec}: {key!r} is not among the algorithms {list(labels)}"
                )
            named[key] = parse_steps(value)
        else:
            default = parse_steps(spec)
    return {
        label: named.get(label, default if default is not None else
                         DEFAULT_TOTAL_STEPS.get(algo_of[label], FALLBACK_TOTAL_STEPS))
        for label in labels
    }  # fmt: skip


def parse_variants(specs: Sequence[str]) -> dict[str, tuple[str, tuple[str, ...]]]:
    """``["csac_min=csac --flag value"]`` -> ``{"csac_min": ("csac", ("--flag", "value"))}``."""
    variants: dict[str, tuple[str, tuple[str, ...]]] = {}
    for spec in specs:
        label, sep, rest = spec.partition("=")
        words = shlex.split(rest)
        if not sep or not label.strip() or not words:
            raise SafenavError(
                f"--variants {spec!r}: write LABEL=ALGO [train options], "
                "e.g. 'csac_nocurr=csac --csac.curriculum.no-enabled'"
            )
        if words[0] not in KNOWN_ALGOS:
            raise SafenavError(f"--variants {spec!r}: unknown algorithm {words[0]!r}; "
                               f"choose one of {list(KNOWN_ALGOS)}")  # fmt: skip
        variants[label.strip()] = (words[0], tuple(words[1:]))
    return variants


@dataclass
class SweepConfig:
    """Everything ``safenav reproduce`` needs; the CLI fills it from its flags."""

    out: Path
    algos: tuple[str, ...] = ("csac", "sac", "ppo")
    seeds: int = 5
    first_seed: int = 1
    seed_list: tuple[int, ...] = ()
    """Explicit training seeds (``--seeds 1-5``); empty: ``seeds`` seeds from ``first_seed``."""
    label_seeds: dict[str, tuple[int, ...]] = field(default_factory=dict)
    """Seeds of particular labels (``--seeds "1-5 sac_lag=1-3"``); others take the default."""
    total_steps: tuple[str, ...] = ()
    preset: str | None = "paper"
    address: str | None = None
    cpus_per_trial: int = 2
    gpus_per_trial: float = 0.0
    num_cpus: int | None = None
    eval_episodes: int = 200
    env_seed: int = 1
    device: str = "cpu"
    train_args: tuple[str, ...] = ()
    variants: tuple[str, ...] = ()
    plots: bool = True
    progress: bool = True
    select: bool = True
    report_only: bool = False
    """Train and evaluate nothing: the results and figures of the trials finished in ``out``
    (a sweep still running elsewhere, or one stopped part-way)."""
    python: str | None = None
    command: str = ""
    extra_meta: dict[str, Any] = field(default_factory=dict)


def plan(cfg: SweepConfig) -> list[Trial]:
    """The trials of a sweep, seed-major (every algorithm's seed 0 first) so that partial
    sweeps cover every algorithm."""
    if cfg.seeds < 1:
        raise SafenavError(f"--seeds {cfg.seeds}: need at least one seed")
    if cfg.cpus_per_trial < 1:
        raise SafenavError(f"--cpus-per-trial {cfg.cpus_per_trial}: need at least one CPU")
    if cfg.eval_episodes < 1:
        raise SafenavError(f"--eval-episodes {cfg.eval_episodes}: need at least one episode")
    variants = parse_variants(cfg.variants)
    labels = list(dict.fromkeys([*cfg.algos, *variants]))
    if not labels:
        raise SafenavError("--algos: name at least one algorithm")
    algo_of: dict[str, str] = {}
    for label in labels:
        if label in variants:
            algo_of[label] = variants[label][0]
        elif label in KNOWN_ALGOS:
            algo_of[label] = label
        else:
            raise SafenavError(f"--algos: unknown algorithm {label!r}; choose from "
                               f"{list(KNOWN_ALGOS)} or define it with --variants")  # fmt: skip
    steps = resolve_total_steps(cfg.total_steps, labels, algo_of)
    unknown = sorted(set(cfg.label_seeds) - set(labels))
    if unknown:
        raise SafenavError(f"--seeds: {unknown} name no algorithm or variant of this sweep "
                           f"({labels})")  # fmt: skip
    default = tuple(cfg.seed_list or range(cfg.first_seed, cfg.first_seed + cfg.seeds))
    seeds_of = {label: cfg.label_seeds.get(label, default) for label in labels}
    out = Path(cfg.out).resolve()
    return [
        Trial(label=label, algo=algo_of[label], seed=seed, total_steps=steps[label],
              run_dir=out / "runs" / label / f"seed{seed}", log_dir=out / "logs",
              preset=cfg.preset, device=cfg.device, cpus=cfg.cpus_per_trial,
              gpus=cfg.gpus_per_trial, eval_episodes=cfg.eval_episodes, env_seed=cfg.env_seed,
              train_args=tuple(cfg.train_args) + variants.get(label, ("", ()))[1],
              python=cfg.python, select=cfg.select)
        for seed in sorted(set().union(*seeds_of.values()))
        for label in labels
        if seed in seeds_of[label]
    ]  # fmt: skip


def _init_ray(cfg: SweepConfig) -> tuple[bool, float]:
    """Start or join Ray; returns ``(we started it, seconds it took)``."""
    import ray

    if ray.is_initialized():
        return False, 0.0
    t0 = time.perf_counter()
    address = cfg.address or os.environ.get("RAY_ADDRESS")
    kwargs: dict[str, Any] = {"log_to_driver": False, "configure_logging": False}
    if address:
        ray.init(address=address, **kwargs)
    else:
        ray.init(num_cpus=cfg.num_cpus or os.cpu_count() or 1, include_dashboard=False,
                 **kwargs)  # fmt: skip
    return True, time.perf_counter() - t0


def _check_resources(cfg: SweepConfig) -> dict[str, Any]:
    """Refuse a sweep no Ray node can run; returns a description of the cluster."""
    import ray

    nodes = [n for n in ray.nodes() if n.get("Alive")]
    node_cpus = [n.get("Resources", {}).get("CPU", 0.0) for n in nodes]
    node_gpus = [n.get("Resources", {}).get("GPU", 0.0) for n in nodes]
    if cfg.cpus_per_trial > max(node_cpus, default=0.0):
        raise SafenavError(
            f"--cpus-per-trial {cfg.cpus_per_trial} exceeds the largest Ray node's "
            f"{max(node_cpus, default=0.0):.0f} CPUs: lower it (or --num-cpus for local Ray)"
        )
    if cfg.gpus_per_trial > max(node_gpus, default=0.0):
        raise SafenavError(f"--gpus-per-trial {cfg.gpus_per_trial}: no Ray node has that many GPUs")
    return {"nodes": len(nodes), "cpus": sum(node_cpus), "gpus": sum(node_gpus),
            "parallel_trials": int(sum(c // cfg.cpus_per_trial for c in node_cpus))}  # fmt: skip


def run_sweep(cfg: SweepConfig) -> dict[str, Any]:
    """Train and evaluate every trial on Ray, then write ``results.json``, ``results.md`` and
    the figures into ``cfg.out``; returns the results dict.

    Trials that fail are reported (their log's last lines) and left out of the results; if any
    failed, :class:`TrialFailed` is raised after the results of the others are written.
    """
    import ray
    from rich.console import Console

    console = Console(stderr=True)
    trials = plan(cfg)
    local_cpus = cfg.num_cpus or os.cpu_count() or 1
    if not (cfg.address or os.environ.get("RAY_ADDRESS")) and cfg.cpus_per_trial > local_cpus:
        raise SafenavError(f"--cpus-per-trial {cfg.cpus_per_trial} exceeds the {local_cpus} CPUs "
                           "of the local Ray instance: lower it or raise --num-cpus")  # fmt: skip
    out = Path(cfg.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    states = {t.name: trial_state(t) for t in trials}
    # a fresh clone: the committed trial files stand for the (ignored) run directories
    kept = {t.name: rec for t in trials
            if states[t.name] == "fresh" and (rec := committed_record(t)) is not None}  # fmt: skip
    states |= dict.fromkeys(kept, "done")
    todo = [t for t in trials if states[t.name] != "done" and not cfg.report_only]
    sweep_t0 = time.perf_counter()
    started_ray, init_s = False, 0.0
    sigterm: Any = None
    cluster: dict[str, Any] = {}
    outcomes: dict[str, dict[str, Any]] = {}
    failures: dict[str, str] = {}
    try:
        if todo:
            started_ray, init_s = _init_ray(cfg)
            sigterm = _stop_on_sigterm()
            cluster = _check_resources(cfg)
            console.print(
                f"[bold]reproduce[/]: {len(trials)} trials ({len(trials) - len(todo)} already "
                f"done), {cluster['parallel_trials']} at a time on {cluster['nodes']} Ray "
                f"node(s), {cluster['cpus']:.0f} CPUs; logs in {out / 'logs'}"
            )
            per_trial, source = estimate_cpu_seconds(
                todo, [t for t in trials if t not in todo], states
            )
            cpu_s = sum(per_trial.values())
            slots = max(1, cluster["parallel_trials"])
            wall_s = schedule_seconds([per_trial[t.name] / t.cpus for t in todo], slots)
            console.print(f"[bold]reproduce[/]: about {cpu_s / 3600:.1f} CPU-hours, "
                          f"{fmt_seconds(wall_s)} of wall clock at {min(slots, len(todo))} "
                          f"trial(s) at a time (rate: {source})")  # fmt: skip
            outcomes, failures = _run_on_ray(cfg, todo, states, console, slots=slots)
    finally:
        if sigterm is not None:
            signal.signal(signal.SIGTERM, sigterm)
        if started_ray:
            ray.shutdown()
    sweep_s = time.perf_counter() - sweep_t0

    records = []
    for t in trials:
        if t.name not in outcomes and (newer := rereported_record(t)) is not None:
            records.append(newer)  # flown again since the run directory's report
        elif cfg.report_only and states[t.name] != "done":
            continue  # running or stopped: its run directory's files are not a result yet
        elif t.name not in failures and (t.run_dir / "eval.json").exists():
            rec = seed_record(t.run_dir, algo=t.label, seed=t.seed)
            # declared, as in the trial files: labels of different budgets are not compared
            rec["budget_env_steps"] = t.total_steps
            if states[t.name] == "done" and t.name not in outcomes:
                write_trial_record(t, rec)  # a trial of an earlier sweep: its file gains new fields
            rec["run_dir"] = os.path.relpath(t.run_dir, out)  # results stay valid when moved
            records.append(rec)
        elif t.name in kept:
            records.append(kept[t.name])
    # Every finished trial of OUT is reported, not only this sweep's: a sweep of one label or
    # seed at a time (what fits a session) would otherwise rewrite results.json with it alone.
    ours = {(t.label, t.seed) for t in trials}
    earlier = [rec for rec in earlier_trial_records(out) if (rec["algo"], rec["seed"]) not in ours]
    records = sorted(records + earlier, key=report_order)
    submitted = [o for o in outcomes.values() if "submitted" in o]
    latency = [o["started"] - o["submitted"] for o in submitted]
    ray_meta = {
        "address": cfg.address or os.environ.get("RAY_ADDRESS") or "local",
        "cpus_per_trial": cfg.cpus_per_trial,
        "gpus_per_trial": cfg.gpus_per_trial,
        **cluster,
        "init_s": round(init_s, 2),
        "first_task_start_s": round(min(latency), 3) if latency else None,
        "trials_run": len(todo),
    }
    previous = read_json(out / "results.json") or {}
    if not todo and "ray" in previous:
        # Nothing ran this time (a re-aggregation): keep the record of the sweep that did.
        ray_meta, sweep_s = previous["ray"], previous.get("sweep_wall_clock_s", sweep_s)
    meta = {
        "command": cfg.command,
        "machine": machine_description(),
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "env": "SafeNav-v1",
        "preset": cfg.preset,
        "selection": "validation" if cfg.select else "final checkpoint",
        "total_steps": {t.label: t.total_steps for t in trials}
        | {r["algo"]: r.get("budget_env_steps") or r.get("env_steps") for r in earlier},
        "earlier_trials": sorted(f"{r['algo']}-s{r['seed']}" for r in earlier),
        "evaluation": {"env_seed": cfg.env_seed, "episodes": cfg.eval_episodes},
        "ray": ray_meta,
        "sweep_wall_clock_s": round(sweep_s, 1),
        "failed": sorted(failures),
        **cfg.extra_meta,
    }
    results = aggregate(records, meta)
    js, md = write_results(results, out)
    figures: list[Path] = []
    # from the run directories, else (a fresh clone) from the committed trial files, whose
    # validation curves and test results redraw Fig. 3 and Fig. 4
    if cfg.plots and records:
        from safenav.experiments.plots import plot_all

        figures = plot_all([out], out / "figures")
    _print_summary(console, results, [js, md, *figures])
    if failures:
        by_name = {t.name: t for t in trials}
        for name, why in failures.items():
            word = "[yellow]stopped[/]" if was_stopped(by_name[name]) else "[red]failed[/]"
            console.print(f"{word} {name}: {why.splitlines()[0]}  (log: {out / 'logs'})")
        raise TrialFailed(f"{len(failures)} of {len(trials)} trials stopped or failed: "
                          f"{sorted(failures)}; rerun the same command to resume or retry "
                          "them")  # fmt: skip
    return results


#: CPU-seconds per env step of a whole trial (training with its periodic evaluations, the
#: validation selection and the test evaluation) on the 2-core development machine, 2 CPUs per
#: trial; :func:`estimate_cpu_seconds` prefers the rate of the sweep's own finished trials.
#: csac (since 2026-12-05 the csac-shielded-memory-pillars recipe): 1M steps in 1,390 s of
#: training alone on 2 CPUs (results/csac-v1, staticmap-s1) plus about 300 s of selection and
#: evaluation behind the shield; sac: 599 s of training for 1M (results/csac-v1/sac1m-s2) plus 170 s
#: of evaluation; sac_lag as the csac-maxcost-crashloss recipe (results/csac-maxcost-crashloss
#: seed 2, 1M steps in 18 min); ppo and ppo_lag: 2M steps in 741 s on one CPU (results/paper,
#: SafeNav-v0), rounded up.
CPU_S_PER_STEP: dict[str, float] = {"csac": 3.4e-3, "sac": 1.5e-3, "sac_lag": 2.2e-3,
                                    "ppo": 4.0e-4, "ppo_lag": 4.0e-4}  # fmt: skip

#: The same for trials that train from another recipe (``--config NAME`` in their arguments),
#: where it costs otherwise than its algorithm's default. csac-paper: 16 envs and 0.25 updates
#: per env step (8 x csac-maxcost-crashloss's updates per env step): 68-73 env steps/s on 2 CPUs
#: alone (csac_paper seed 1, 10k-50k steps, 2026-11-27), where that recipe's rate says 1/13 of it.
#: csac-maxcost-crashloss: the csac recipe until 2026-12-05 (its rate above then).
CPU_S_PER_STEP_BY_RECIPE: dict[str, float] = {
    "csac-paper": 2.9e-2,
    "csac-maxcost-crashloss": 2.2e-3,
}


def trial_recipe(trial: Trial) -> str | None:
    """The recipe a trial's ``--config`` names (the last one given), or None."""
    name, args = None, list(trial.train_args)
    for i, arg in enumerate(args):
        if arg == "--config" and i + 1 < len(args):
            name = args[i + 1]
        elif arg.startswith("--config="):
            name = arg.split("=", 1)[1]
    return name


def _behind_filter(trial: Trial) -> bool:
    """Whether the trial reports behind the planner filter (which flies each test twice)."""
    return "--flight-filter" in trial.train_args


def estimate_cpu_seconds(todo: list[Trial], done: list[Trial],
                         states: dict[str, str]) -> tuple[dict[str, float], str]:  # fmt: skip
    """``({trial name: CPU-seconds}, where the rate came from)`` that each trial of ``todo``
    still needs: its remaining steps (a resumed one has fewer; ``states`` from
    :func:`trial_state`) at its algorithm's rate, measured on the finished
    trials of ``done`` where there are any (their records' wall clock x CPUs / env steps), else
    :data:`CPU_S_PER_STEP_BY_RECIPE` for the recipe it names, else :data:`CPU_S_PER_STEP`; plus
    the time a finished trial of its label (else of its kind: behind the planner filter or not)
    took beyond training (record ``trial_wall_clock_s`` - ``wall_clock_s``): the selection and
    the report, about 10 min of a 25-min trial behind the filter, which a rate of training steps
    alone leaves out (on 2026-12-06 it printed 4.1 h for 19 trials of about 25 min each)."""
    measured: dict[str, list[float]] = {}  # by label: variants of one algorithm differ
    # What a trial costs beyond its training (selection, the test and held-out report, start-up),
    # which does not grow with its steps: by label, and by whether it reports behind the planner
    # filter (which flies each test twice), for labels with no finished trial yet.
    overhead_by_label: dict[str, list[float]] = {}
    overhead_by_filter: dict[bool, list[float]] = {}
    for t in done:
        rec = read_json(t.record_path) or {}
        wall, steps = rec.get("wall_clock_s"), rec.get("env_steps") or rec.get("budget_env_steps")
        if wall and steps:
            measured.setdefault(t.label, []).append(float(wall) * t.cpus / float(steps))
            if rec.get("trial_wall_clock_s"):
                extra = max(0.0, float(rec["trial_wall_clock_s"]) - float(wall)) * t.cpus
                overhead_by_label.setdefault(t.label, []).append(extra)
                overhead_by_filter.setdefault(_behind_filter(t), []).append(extra)
    per_trial, sources = {}, set()
    for t in todo:
        if measured.get(t.label):
            rate = sum(measured[t.label]) / len(measured[t.label])
            sources.add("this sweep's finished trials")
        else:
            rate = CPU_S_PER_STEP_BY_RECIPE.get(trial_recipe(t) or "") or CPU_S_PER_STEP.get(
                t.algo, max(CPU_S_PER_STEP.values())
            )
            sources.add("measured on the 2-core development machine")
        extra = overhead_by_label.get(t.label) or overhead_by_filter.get(_behind_filter(t))
        sources.add("the report after training " + ("measured" if extra else "not counted"))
        per_trial[t.name] = rate * max(0, t.total_steps - steps_done(t, states[t.name])) + (
            sum(extra) / len(extra) if extra else 0.0
        )
    return per_trial, "; ".join(sorted(sources)) or "-"


def schedule_seconds(durations: Sequence[float], slots: int) -> float:
    """Wall clock of jobs of these durations run in this order on ``slots`` parallel slots, each
    starting when the first slot frees (Ray's queue is first in, first out). Not the sum over
    slots: a sweep's last trials run with slots idle (3 trials on 2 slots take two trials' time)."""
    free = [0.0] * max(1, slots)
    for d in durations:
        i = free.index(min(free))
        free[i] += d
    return max(free)


def steps_done(trial: Trial, state: str) -> int:
    """Env steps a trial in ``state`` (:func:`trial_state`) will not run again: those of its
    checkpoint's run when it resumes, none when it starts afresh (rows a failed attempt left in
    progress.csv are overwritten)."""
    return last_step(trial.run_dir) if state != "fresh" else 0


def eta_line(
    done: int,
    count: int,
    steps_done: int,
    steps_total: int,
    elapsed_s: float,
    now: float | None = None,
    steps_left: Sequence[int] | None = None,
    slots: int = 1,
) -> str:
    """``"3 of 5 trials done; about 41 min left (ETA 08:12 UTC)"``: the steps left at the rate
    the sweep has made steps so far. With ``steps_left`` (each unfinished trial's, in queue
    order) and ``slots`` (trials at a time), each trial's time at one slot's share of that rate,
    scheduled on the slots (:func:`schedule_seconds`), so that a last trial running alone is not
    counted at the rate of all slots."""
    text = f"{done} of {count} trials done"
    if 0 < steps_done < steps_total and elapsed_s > 0:
        if steps_left is None:
            left = (steps_total - steps_done) * elapsed_s / steps_done
        else:
            per_step = elapsed_s * max(1, min(slots, count)) / steps_done  # one slot's s / step
            left = schedule_seconds([per_step * n for n in steps_left if n > 0], slots)
        at = datetime.fromtimestamp((time.time() if now is None else now) + left, timezone.utc)
        text += f"; about {fmt_seconds(left)} left (ETA {at:%H:%M} UTC)"
    return text


def _run_on_ray(
    cfg: SweepConfig, todo: list[Trial], states: dict[str, str], console: Any, slots: int
):
    """Submit ``todo`` as Ray tasks and wait for them with a live progress table."""
    import ray
    from rich import progress as rp

    remote = ray.remote(run_trial)
    for trial in todo:  # a status left by an interrupted sweep would show before the task runs
        trial.log("status").unlink(missing_ok=True)
        stop_marker(trial.log("trainer.pid")).unlink(missing_ok=True)
    started: set[str] = set()
    pending: dict[Any, Trial] = {}
    submitted: dict[str, float] = {}
    for trial in todo:
        ref = remote.options(num_cpus=trial.cpus, num_gpus=trial.gpus, max_retries=RETRIES,
                             retry_exceptions=[TrialKilled],
                             name=f"trial:{trial.name}").remote(trial)  # fmt: skip
        pending[ref] = trial
        submitted[trial.name] = time.time()
    outcomes: dict[str, dict[str, Any]] = {}
    failures: dict[str, str] = {}
    columns = (rp.TextColumn("{task.description:<22}"), rp.BarColumn(), rp.MofNCompleteColumn(),
               rp.TextColumn("{task.fields[status]:<10}"), rp.TimeElapsedColumn(),
               rp.TextColumn("eta"), rp.TimeRemainingColumn())  # fmt: skip
    first = {t.name: steps_done(t, states[t.name]) for t in todo}
    steps_total = sum(max(0, t.total_steps - first[t.name]) for t in todo)
    t0 = time.time()
    now = dict(first)  # each trial's last logged step, read once per poll

    def steps_now() -> int:
        return sum(max(0, min(now[t.name], t.total_steps) - first[t.name]) for t in todo)

    def steps_left() -> list[int]:  # the unfinished trials', in queue order
        return [max(0, t.total_steps - now[t.name]) for t in todo if t in pending.values()]

    with rp.Progress(*columns, console=console, disable=not cfg.progress,
                  refresh_per_second=2) as bar:  # fmt: skip
        overall = bar.add_task("all trials (steps)", total=steps_total, status="")
        rows = {t.name: bar.add_task(t.name, total=t.total_steps, status="queued", start=False,
                                     completed=first[t.name]) for t in todo}  # fmt: skip
        try:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
                for ref in ready:
                    trial = pending.pop(ref)
                    try:
                        outcome = ray.get(ref)
                        outcome["submitted"] = submitted[trial.name]
                        outcomes[trial.name] = outcome
                        status = "done"
                    except ray.exceptions.RayError as err:
                        cause = getattr(err, "cause", None) or err
                        failures[trial.name] = str(cause)
                        status = "stopped" if was_stopped(trial) else "failed"
                    now[trial.name] = last_step(trial.run_dir)
                    bar.update(rows[trial.name], completed=now[trial.name], status=status)
                    bar.stop_task(rows[trial.name])
                    finished = len(outcomes) + len(failures)
                    console.print(f"[bold]reproduce[/]: {trial.name} {status}; "
                                  + eta_line(finished, len(todo), steps_now(), steps_total,
                                             time.time() - t0, steps_left=steps_left(),
                                             slots=slots))  # fmt: skip
                for trial in pending.values():
                    status_file = trial.log("status")
                    status = status_file.read_text().strip() if status_file.exists() else "queued"
                    if status != "queued" and trial.name not in started:
                        bar.start_task(rows[trial.name])  # the clock runs from the task's start
                        started.add(trial.name)
                    now[trial.name] = last_step(trial.run_dir)
                    bar.update(rows[trial.name], completed=now[trial.name],
                               status=status if status != "done" else "finishing")  # fmt: skip
                bar.update(overall, completed=steps_now())
        except KeyboardInterrupt as err:
            from safenav.common.stopping import Terminated

            _stop_pending(pending, console)
            if _SIGTERM_RECEIVED and not isinstance(err, Terminated):
                # ray.wait turned the SIGTERM into its own KeyboardInterrupt: exit 143, not 130
                raise Terminated() from None
            raise
    return outcomes, failures


#: Set by the driver's SIGTERM handler (:func:`_stop_on_sigterm`).
_SIGTERM_RECEIVED = False


def _stop_on_sigterm() -> Any:
    """Make SIGTERM (``kill``, a scheduler's preemption) stop the sweep as Ctrl-C does; returns
    the handler it replaced (``None`` off the main thread, where no handler can be set).

    ``ray.init`` gives the driver Ray's own handler, which exits at once; Ray's cleanup then
    SIGKILLs each worker's child processes, so the trainers died without their checkpoint.
    """
    import threading

    from safenav.common.stopping import Terminated

    global _SIGTERM_RECEIVED
    if threading.current_thread() is not threading.main_thread():
        return None
    _SIGTERM_RECEIVED = False  # a sweep run before, in this process, may have set it

    def stop(signum: int, frame: Any) -> None:
        global _SIGTERM_RECEIVED
        _SIGTERM_RECEIVED = True
        raise Terminated()

    return signal.signal(signal.SIGTERM, stop)


def _stop_pending(pending: dict[Any, Trial], console: Any,
                  timeout_s: float = STOP_WAIT_S + 30) -> None:  # fmt: skip
    """Stop the trials still running or queued and wait until each has stopped; Ray must stay
    up meanwhile, since its shutdown SIGKILLs the workers' children.

    A trainer on this machine gets SIGTERM from here (its pid file), once: it writes its
    checkpoint and exits 143, which its worker reports without a retry (the stop marker). Ray's
    cancel alone did not always reach a running task (seen under load: the worker logged the
    cancel and the trainer trained on); it still removes queued tasks, and running ones on
    other nodes, whose workers send their trainers SIGTERM.
    """
    import ray

    from safenav.common.stopping import process_running

    if not pending:
        return
    console.print(f"[bold]reproduce[/]: stopping {len(pending)} trial(s); each trainer writes a "
                  "checkpoint, and the same command resumes them")  # fmt: skip
    host, local = socket.gethostname(), []
    for trial in pending.values():
        pid_file = trial.log("trainer.pid")
        stop_marker(pid_file).write_text("")
        with contextlib.suppress(OSError, ValueError):
            where, pid = pid_file.read_text().split()
            if where == host:
                os.kill(int(pid), signal.SIGTERM)
                local.append(int(pid))
    for ref in pending:
        ray.cancel(ref)
    deadline = time.monotonic() + timeout_s
    while any(process_running(pid) for pid in local) and time.monotonic() < deadline:
        time.sleep(0.2)
    ray.wait(list(pending), num_returns=len(pending),
             timeout=max(1.0, deadline - time.monotonic()))  # fmt: skip


def _print_summary(console: Any, results: dict[str, Any], files: list[Path]) -> None:
    from rich.table import Table

    table = Table(title="fixed test scenario: mean ± std across seeds")
    for col in ("algorithm", "seeds", "success", "collision", "timeout", "training / seed"):
        table.add_column(col, justify="left" if col == "algorithm" else "right")
    for name, a in results["algos"].items():
        table.add_row(display_name(name), str(a["seeds"]), fmt_rate(a["success_rate"]),
                      fmt_rate(a["collision_rate"]), fmt_rate(a["timeout_rate"]),
                      fmt_seconds(a["wall_clock_s"]))  # fmt: skip
    console.print(table)
    for path in files:
        console.print(f"wrote {path}")


__all__ = [
    "CPU_S_PER_STEP",
    "CPU_S_PER_STEP_BY_RECIPE",
    "DEFAULT_TOTAL_STEPS",
    "OBSERVATION_VARIANTS",
    "PAPER_ALGOS",
    "PAPER_SEEDS",
    "PAPER_TOTAL_STEPS",
    "PAPER_TRAIN_ARGS",
    "PAPER_VARIANTS",
    "PLANS",
    "Plan",
    "KNOWN_ALGOS",
    "SweepConfig",
    "Trial",
    "TrialFailed",
    "TrialKilled",
    "RETRIES",
    "estimate_cpu_seconds",
    "eta_line",
    "schedule_seconds",
    "machine_description",
    "parse_steps",
    "parse_variants",
    "plan",
    "resolve_total_steps",
    "run_sweep",
    "run_trial",
    "trial_recipe",
    "trial_state",
]
