"""``safenav bench {env,update,latency,soak,gym,safe}``: the benchmarks whose figures the README
and docs/gymnasium.md quote."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Literal

import tyro

from safenav.cli import app


@app.command(name="bench")
def bench(
    which: tyro.conf.Positional[Literal["env", "update", "latency", "soak", "gym", "safe"]],
    json_out: Annotated[Path | None, tyro.conf.arg(name="json")] = None,
    repeats: int = 5,
    preset: str = "paper",
    num_envs: tuple[int, ...] = (1, 64, 256, 1024),
    env_steps: int = 10_000_000,
    updates: int = 100_000,
    out: Path | None = None,
    tasks: tuple[str, ...] = (),
    algos: tuple[str, ...] = (),
    seeds: int = 3,
    first_seed: int = 1,
    steps: int = 0,
    sb3: tuple[str, ...] | None = None,
    jobs: int = 1,
    max_trials: int = 0,
    cost_limit: float = 25.0,
    report_only: bool = False,
    progress: bool = True,
    train_args: str = "",
) -> None:
    """Measure throughput or latency and print a table; ``--json OUT`` writes the figures.

    env: env-steps/s at 1, 64, 256, 1024 envs (cpu, and cuda when present) and the grid ray
    caster's speed-up over a brute-force reference. update: gradient updates/s of CSAC and SAC
    beside Stable-Baselines3's SAC, and PPO's training throughput. latency: batch-1 policy and
    sensor-to-setpoint latency on one CPU thread. soak: ``--env-steps`` env steps and
    ``--updates`` CSAC updates, resident memory at the start and the end (no growth beyond the
    replay buffer). gym: SAC and PPO on Pendulum-v1, MountainCarContinuous-v0,
    LunarLanderContinuous-v3, InvertedPendulum-v5, Hopper-v5 and HalfCheetah-v5, PPO on the
    discrete CartPole-v1, Acrobot-v1 and LunarLander-v3, --seeds seeds each, Stable-Baselines3
    beside them on --sb3 tasks, against published returns; safe: CSAC,
    SAC-Lag, PPO-Lag and SAC on SafetyHopperVelocity-v5 and SafetyHalfCheetahVelocity-v5 at
    --cost-limit. Both write OUT/trials/*.json per finished trial (a rerun skips those and resumes
    interrupted runs), then OUT/table.md, OUT/curves.png and OUT/summary.json (docs/gymnasium.md).

    Args:
        which: The benchmark.
        json_out: Also write the figures here as JSON; the directory must exist.
        repeats: Repeats per measurement (1-1000; the median is reported).
        preset: Env preset of env and soak.
        num_envs: env: the env counts to measure.
        env_steps: soak: env steps.
        updates: soak: CSAC updates.
        out: gym, safe: results directory (default benchmarks/results/gym or .../safe).
        tasks: gym, safe: the tasks to run (default: all of the suite).
        algos: gym, safe: the algorithms to run (default: all of the suite).
        seeds: gym, safe: N seeds per task and algorithm, from --first-seed (1-100).
        first_seed: gym, safe: the first of the --seeds seeds (so 101 with --seeds 10 runs
            seeds 101-110: validation seeds to choose on, clear of the reported 1..N).
        steps: gym, safe: env steps per trial; 0 = each task's budget (docs/gymnasium.md).
        sb3: gym: tasks on which Stable-Baselines3 runs too (default Pendulum-v1 Hopper-v5).
        jobs: gym, safe: trials run at once, one torch thread each.
        max_trials: gym, safe: run at most this many of the pending trials (in the plan's order),
            then report; 0 = all. A long suite in pieces that each end with their trials
            finished (a stopped trial resumes, but continues differently from a run that was not
            stopped, and its row says so).
        cost_limit: safe: the episode-cost limit of the constrained algorithms.
        report_only: gym, safe: write the table and figure from the trial files, run nothing.
        progress: gym, safe: the live progress bars.
        train_args: gym, safe: more safenav train options for every safenav trial, one string
            (e.g. "--csac.learning-starts 1000"); trial files record them.
    """
    from safenav.common.checks import at_least, check_memory, check_output_file, in_range
    from safenav.common.memory import env_bytes
    from safenav.envs.config import make_config

    cfg = make_config(preset)  # ValueError for an unknown preset: exit 2
    in_range("--repeats", repeats, 1, 1000)
    at_least("--env-steps", env_steps, 1)
    at_least("--updates", updates, 1)
    if not num_envs:
        from safenav.errors import SafenavError

        raise SafenavError("--num-envs: give at least one count, e.g. --num-envs 1 64 256")
    for n in num_envs:
        at_least("--num-envs", n, 1)
    if which == "env":
        check_memory(env_bytes(max(num_envs), cfg), f"--num-envs {max(num_envs):,}",
                     "benchmark fewer envs")  # fmt: skip
    if json_out is not None:
        check_output_file(json_out, "--json", f"{which}.json")
    in_range("--seeds", seeds, 1, 100)
    in_range("--first-seed", first_seed, 1, 1_000_000)
    in_range("--jobs", jobs, 1, os.cpu_count() or 1, "CPU cores of this machine")
    at_least("--steps", steps, 0)
    at_least("--max-trials", max_trials, 0)
    at_least("--cost-limit", cost_limit, 0)
    suite = which in ("gym", "safe")
    for flag, given in (("--tasks", tasks), ("--algos", algos), ("--sb3", sb3),
                        ("--train-args", train_args), ("--max-trials", max_trials)):  # fmt: skip
        if given and not suite:
            from safenav.errors import SafenavError

            raise SafenavError(f"{flag} applies to bench gym and bench safe, not bench {which}")
    if suite:  # the throughput benchmarks' options would be ignored: say so
        from safenav.cli import ARGS
        from safenav.commands.train import given_flag

        for flag in ("json", "repeats", "preset", "num-envs", "env-steps", "updates"):
            if given_flag(flag, ARGS.get()):
                from safenav.errors import SafenavError

                raise SafenavError(f"--{flag} applies to bench env, update, latency or soak, not "
                                   f"bench {which} (its options: safenav bench --help)")  # fmt: skip
    if out is not None:
        from safenav.common.checks import check_output_dir

        check_output_dir(out, "--out")
    if suite:
        from safenav.bench.gym import bench_suite, plan_trials

        plan_trials(which, tasks, algos, seeds, steps, sb3, first_seed)  # unknown: exit 2
        extra = split_train_args(train_args)
        out = Path("benchmarks/results") / which if out is None else out
        bench_suite(which, out, tasks, algos, seeds, steps, sb3, jobs, cost_limit, report_only,
                    progress, extra, first_seed, max_trials)  # fmt: skip
    elif which == "env":
        from safenav.bench.env import bench_env

        bench_env(json_out, num_envs=num_envs, repeats=repeats, preset=preset)
    elif which == "update":
        from safenav.bench.update import bench_update

        bench_update(json_out, repeats=repeats)
    elif which == "soak":
        from safenav.bench.soak import bench_soak

        bench_soak(json_out, env_steps=env_steps, updates=updates, preset=preset)
    else:
        from safenav.bench.latency import bench_latency

        bench_latency(json_out)


TRIAL_FLAGS = ("env", "algo", "seed", "total-steps", "run-dir", "resume", "overwrite",
               "eval-every", "eval-episodes")  # fmt: skip
"""``safenav train`` options that ``bench gym`` / ``safe`` set per trial: ``--train-args`` may
not give them (the last one would win, and a trial file would be mislabelled)."""


def split_train_args(text: str) -> tuple[str, ...]:
    """``--train-args`` as argv words, checked by ``safenav train``'s own parser (exit 2)."""
    import shlex

    from safenav.errors import SafenavError

    try:
        words = tuple(shlex.split(text))
    except ValueError as err:
        raise SafenavError(f"--train-args {text!r}: {err}") from None
    if words:
        from safenav.commands.train import given_flag, parse_train_args

        # what a trial is (its task, algorithm, seed, budget, run directory) is the bench's
        if owned := [f"--{f}" for f in TRIAL_FLAGS if given_flag(f, words)]:
            raise SafenavError(f"--train-args {text!r}: {', '.join(owned)} is set by the bench for "
                               "each trial (use --tasks, --algos, --seeds, --first-seed, --steps, "
                               "--out)")  # fmt: skip

        try:
            parse_train_args(["--env", "Pendulum-v1", "--config", "none", *words])
        except SafenavError as err:
            raise SafenavError(f"--train-args {text!r}: {err}") from None
    return words
