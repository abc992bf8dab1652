"""``safenav reproduce``: every algorithm × seed trained and evaluated on Ray; results table."""

from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path

from safenav.cli import app


@app.command(name="reproduce")
def reproduce(
    out: Path | None = None,
    algos: tuple[str, ...] = ("paper",),
    seeds: str = "auto",
    first_seed: int = 1,
    total_steps: tuple[str, ...] = (),
    preset: str = "paper",
    address: str | None = None,
    cpus_per_trial: int = 2,
    gpus_per_trial: float = 0.0,
    num_cpus: int | None = None,
    eval_episodes: int = 200,
    device: str = "cpu",
    train_args: str = "",
    variants: tuple[str, ...] = (),
    plots: bool = True,
    select: bool = True,
    report_only: bool = False,
) -> None:
    """Reproduce the paper's Section IV: train every algorithm x seed as a Ray task, evaluate each
    policy on the fixed test scenario (env seed 1), and write OUT/results.json, OUT/results.md
    (mean ± std and 95 % CIs across seeds beside the paper's figures), OUT/trials/ (one small
    JSON per finished trial, to commit) and OUT/figures/. Each trial trains with --select: its
    policy is chosen on validation maps only and reported on the held-out maps (env seeds 2-6).

    Rerunning the same command resumes: finished trials are skipped, interrupted ones resume from
    their checkpoint. Without --address a local Ray instance starts with all cores (or
    the --num-cpus given) and runs cores / --cpus-per-trial trials at once; --address joins an
    existing Ray cluster (OUT must then be on a file system every node sees). Every option,
    including each trial's train options, is checked before Ray starts.

    With no --algos (or --algos paper) and no --variants it runs the paper's comparison
    (docs/reproduce.md) into results/paper: CSAC, SAC and PPO with seeds 1-5; SAC-Lag, PPO-Lag and
    the CSAC ablations (csac_paper: the paper's values exactly; csac_min: min cost target;
    csac_fixed_d: no constraint curriculum) with seeds 1-3; 1M env steps each; every label but
    csac_paper on the default csac recipe's observation and shield, reported behind its planner
    filter and without it. --algos paper-observation: the same comparison on the paper's
    observation without shield or filter, at 1M and 3M, with each algorithm's tuned recipe
    (results/paper-observation).

    Example: safenav reproduce  # the paper's comparison, results/paper/ (many CPU-hours: it
    prints the estimate first; rerun the same command to resume)

    Example: safenav reproduce --algos csac --seeds 1-5  # writes results/csac/

    Example: safenav reproduce --out runs/repro-easy --algos csac ppo --seeds 2 --total-steps 300k
    ppo=2M --cpus-per-trial 1 --variants "csac_nocurr=csac --csac.curriculum.no-enabled" --preset
    easy --train-args="--num-envs 64 --csac.batch-size 512"

    Args:
        out: Output directory (runs/, logs/, trials/, results.json, results.md, figures/); default results/paper for the paper's comparison (no --algos, no --variants), else results/<algos joined by +>.
        algos: Algorithms (safenav train --algo) or --variants labels to run; paper (the default): the paper's comparison, its algorithms and ablations on the csac recipe's flight stack; paper-observation: the same comparison as it ran on the paper's observation without shield or filter, at 1M and 3M (results/paper-observation); with --variants alone, only the variants.
        seeds: Training seeds: a count N (first_seed, first_seed+1, ...), a range A-B or a list A,B,C, then optionally LABEL=SEEDS for particular labels, e.g. "1-5 sac_lag=1-3"; auto: the paper comparison's seeds, else 5.
        first_seed: The first training seed when --seeds is a count (1, as the paper comparison's
            seeds 1-5 and safenav bench: --seeds 5 is seeds 1-5).
        total_steps: Env steps per trial: N for every algorithm and/or ALGO=N (300k, 2M, 1e6 accepted); unnamed algorithms use a per-algorithm default (docs/reproduce.md).
        preset: Env preset to train on (easy, medium, paper).
        address: Ray cluster address (e.g. ray://head:10001 or auto); default: start a local Ray.
        cpus_per_trial: CPUs Ray reserves for each trial; also its torch/OpenMP threads.
        gpus_per_trial: GPUs Ray reserves for each trial (use with --device cuda).
        num_cpus: CPUs of the local Ray instance (default: all cores); ignored with --address.
        eval_episodes: Episodes of the fixed test scenario per final policy (paper protocol: 200).
        device: Torch device of training and evaluation (cpu or cuda).
        train_args: Extra options for every safenav train, one string, e.g. --train-args="--num-envs 64 --csac.batch-size 512".
        variants: Extra labelled configurations, LABEL=ALGO [train options], e.g. 'csac_nocurr=csac --csac.curriculum.no-enabled'.
        plots: Write the figures (safenav plot OUT) at the end.
        select: Each trial ends by choosing its policy on validation maps (train --select); --no-select evaluates the final checkpoint.
        report_only: Run nothing: write results.json, results.md and the figures from the trials finished in OUT (e.g. while the sweep still runs, or after it was stopped).
    """
    from safenav.errors import SafenavError
    from safenav.experiments.reproduce import (
        PAPER_TRAIN_ARGS,
        PLANS,
        SweepConfig,
        TrialFailed,
        run_sweep,
    )

    named = [a for a in algos if a in PLANS]
    if named and len(algos) > 1:
        raise SafenavError(f"--algos {named[0]} is a whole comparison: name no other algorithm "
                           "or plan with it")  # fmt: skip
    if tuple(algos) == ("paper",) and variants:
        algos = ()  # only the labels --variants defines
    plan = PLANS.get(algos[0]) if len(algos) == 1 else None
    if plan is not None:
        algos, variants = plan.algos, plan.variants
        total_steps = total_steps or plan.total_steps
        train_args = shlex.join(PAPER_TRAIN_ARGS) + (f" {train_args}" if train_args else "")
    if seeds == "auto":
        seeds = plan.seeds if plan is not None else "5"
    count, seed_list, label_seeds = parse_seed_spec(seeds)
    if out is None:
        out = Path(plan.out) if plan is not None else Path("results") / "+".join(
            algos or [v.split("=")[0] for v in variants])  # fmt: skip
    cfg = SweepConfig(
        out=out, algos=algos, seeds=count, first_seed=first_seed, seed_list=seed_list,
        label_seeds=label_seeds, total_steps=total_steps, select=select,
        preset=preset, address=address, cpus_per_trial=cpus_per_trial,
        gpus_per_trial=gpus_per_trial, num_cpus=num_cpus, eval_episodes=eval_episodes,
        device=device, train_args=tuple(shlex.split(train_args)), variants=variants, plots=plots,
        report_only=report_only,
        command=shlex.join(["safenav", *sys.argv[1:]]) if sys.argv[1:2] == ["reproduce"]
        else shlex.join(["safenav", "reproduce", "--out", str(out), "--seeds", seeds]),
    )  # fmt: skip
    check_sweep(cfg)
    try:
        run_sweep(cfg)
    except TrialFailed as err:
        print(f"safenav: {err}", file=sys.stderr)
        raise SystemExit(1) from None


def parse_seed_spec(text: str) -> tuple[int, tuple[int, ...], dict[str, tuple[int, ...]]]:
    """``--seeds "1-5 sac_lag=1-3"``: the default seeds (:func:`parse_seeds`) and, per label, its
    own (a range or a list; a bare count there means seeds 0..N-1 would be ambiguous, so not)."""
    from safenav.errors import SafenavError

    words = str(text).split()
    if not words or "=" in words[0]:
        raise SafenavError(f"--seeds {text!r}: start with the default seeds (5, 1-5 or 1,3,5), "
                           "then LABEL=SEEDS for particular labels")  # fmt: skip
    count, seed_list = parse_seeds(words[0])
    per_label: dict[str, tuple[int, ...]] = {}
    for word in words[1:]:
        label, sep, spec = word.partition("=")
        if not sep or not label:
            raise SafenavError(f"--seeds {text!r}: {word!r} is not LABEL=SEEDS")
        _, listed = parse_seeds(spec)
        if not listed:
            raise SafenavError(f"--seeds {text!r}: give {label}'s seeds as a range (1-3) or a "
                               "list (1,2,3)")  # fmt: skip
        per_label[label] = listed
    return count, seed_list, per_label


def parse_seeds(text: str) -> tuple[int, tuple[int, ...]]:
    """``--seeds``: ``"5"`` -> ``(5, ())`` (a count from --first-seed); ``"1-5"`` or ``"1,3,5"``
    -> ``(count, seeds)``. ``SafenavError`` for anything else."""
    from safenav.common.config import MAX_SEED
    from safenav.errors import SafenavError

    text = str(text).strip()
    try:
        if "-" in text[1:] and "," not in text:
            lo, hi = (int(v) for v in text.split("-", 1))
            seeds = tuple(range(lo, hi + 1))
        elif "," in text:
            seeds = tuple(int(v) for v in text.split(","))
        else:
            count = int(text)
            if not 1 <= count <= 1000:
                raise SafenavError(f"--seeds {text}: must lie in [1, 1000]")
            return count, ()
    except ValueError:
        raise SafenavError(f"--seeds {text!r}: give a count (5), a range (1-5) or a list "
                           "(1,3,5)") from None  # fmt: skip
    if not seeds or len(seeds) > 1000 or len(set(seeds)) != len(seeds):
        raise SafenavError(f"--seeds {text}: 1 to 1000 distinct seeds, low-high in order")
    if min(seeds) < 0 or max(seeds) > MAX_SEED:
        raise SafenavError(f"--seeds {text}: seeds lie in [0, {MAX_SEED}]")
    return len(seeds), seeds


def check_sweep(cfg) -> None:
    """Everything a sweep's trials would refuse, refused before Ray starts: the counts, the device,
    the preset, the output directory and every trial's ``safenav train`` command line (its
    --train-args and --variants, parsed as train parses them, then train's own checks: a budget
    within the warm-up, the memory of the run)."""
    from safenav.commands.train import parse_train_args
    from safenav.commands.train import plan as train_plan
    from safenav.common.checks import (
        at_least,
        check_device,
        check_memory,
        check_output_dir,
        in_range,
    )
    from safenav.common.config import MAX_SEED
    from safenav.common.memory import env_bytes
    from safenav.envs.config import make_config
    from safenav.errors import SafenavError, SafenavRuntimeError
    from safenav.experiments.reproduce import parse_variants, plan

    in_range("--seeds", cfg.seeds, 1, 1000)
    # checked even where listed seeds make it unused: a bad value is a mistake either way
    in_range("--first-seed", cfg.first_seed, 0, MAX_SEED - (0 if cfg.seed_list else cfg.seeds - 1))
    at_least("--gpus-per-trial", cfg.gpus_per_trial, 0)
    if cfg.num_cpus is not None:
        in_range("--num-cpus", cfg.num_cpus, 1, 1024)
    check_device(cfg.device)
    at_least("--eval-episodes", cfg.eval_episodes, 1)
    check_memory(env_bytes(cfg.eval_episodes, make_config(cfg.preset or "paper")),
                 f"--eval-episodes {cfg.eval_episodes:,} (one env each)", "evaluate fewer")  # fmt: skip
    if not (cfg.address or os.environ.get("RAY_ADDRESS")):  # a local Ray: this machine's resources
        cpus = cfg.num_cpus or os.cpu_count() or 1
        if cfg.cpus_per_trial > cpus:
            raise SafenavRuntimeError(f"--cpus-per-trial {cfg.cpus_per_trial} exceeds the {cpus} "
                                      "CPUs of the local Ray instance: lower it or raise "
                                      "--num-cpus")  # fmt: skip
        if cfg.gpus_per_trial > 0:
            import torch

            if cfg.gpus_per_trial > torch.cuda.device_count():
                raise SafenavRuntimeError(f"--gpus-per-trial {cfg.gpus_per_trial}: this machine "
                                          f"has {torch.cuda.device_count()} CUDA GPU(s)")  # fmt: skip
    if cfg.preset is not None:
        make_config(cfg.preset)  # ValueError for an unknown preset: exit 2
    trials = plan(cfg)  # seeds, algorithms, --variants, --total-steps
    check_output_dir(cfg.out, "--out")
    variants = parse_variants(cfg.variants)
    for trial in {t.label: t for t in trials}.values():  # the seeds of a label share the checks
        args = trial.train_command(resume=False)[4:]  # after `python -m safenav train`
        try:
            parsed = parse_train_args(args)
        except SafenavError as err:
            where = f"--variants {trial.label}" if trial.label in variants else "--train-args"
            raise SafenavError(f"{where}: {err}") from None
        try:  # what each trial's train would refuse after Ray started it
            train_plan(parsed["algo"], parsed["run"], parsed["csac"], parsed["ppo"],
                       trial.run_dir, None, False)  # fmt: skip
        except SafenavError as err:
            raise type(err)(f"the {trial.label} trials: {err}") from None
