"""``safenav reproduce``: every algorithm × seed trained and evaluated on Ray; results table."""

from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path

from safenav.cli import app


@app.command(name="reproduce")
def reproduce(
    out: Path,
    algos: tuple[str, ...] = ("csac", "sac", "ppo"),
    seeds: int = 5,
    first_seed: int = 0,
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
) -> None:
    """Reproduce the paper's Section IV: train every algorithm x seed as a Ray task, evaluate each
    final policy on the fixed test scenario (env seed 1), and write OUT/results.json,
    OUT/results.md (mean ± std across seeds beside the paper's figures) and OUT/figures/.

    Rerunning the same command resumes: finished trials are skipped, interrupted ones resume from
    their checkpoint. Without --address a local Ray instance starts with all cores (or the
    --num-cpus given) and runs cores / --cpus-per-trial trials at once; --address joins an
    existing Ray cluster (OUT must then be on a file system every node sees). Every option,
    including each trial's train options, is checked before Ray starts.

    Example: safenav reproduce --out runs/repro-easy --algos csac ppo --seeds 2 --total-steps 300k
    ppo=2M --preset easy --cpus-per-trial 1 --train-args="--num-envs 64 --csac.batch-size 512"
    --variants "csac_nocurr=csac --csac.curriculum.no-enabled"

    Args:
        out: Output directory (runs/, logs/, results.json, results.md, figures/).
        algos: Algorithms (safenav train --algo) or --variants labels to run.
        seeds: Seeds per algorithm: first_seed, first_seed+1, ...
        first_seed: The first training seed.
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
    """
    from safenav.experiments.reproduce import SweepConfig, TrialFailed, run_sweep

    cfg = SweepConfig(
        out=out, algos=algos, seeds=seeds, first_seed=first_seed, total_steps=total_steps,
        preset=preset, address=address, cpus_per_trial=cpus_per_trial,
        gpus_per_trial=gpus_per_trial, num_cpus=num_cpus, eval_episodes=eval_episodes,
        device=device, train_args=tuple(shlex.split(train_args)), variants=variants, plots=plots,
        command=shlex.join(["safenav", *sys.argv[1:]]) if sys.argv[1:2] == ["reproduce"]
        else shlex.join(["safenav", "reproduce", "--out", str(out)]),
    )  # fmt: skip
    check_sweep(cfg)
    try:
        run_sweep(cfg)
    except TrialFailed as err:
        print(f"safenav: {err}", file=sys.stderr)
        raise SystemExit(1) from None


def check_sweep(cfg) -> None:
    """Everything a sweep's trials would refuse, refused before Ray starts: the counts, the device,
    the preset, the output directory and every trial's ``safenav train`` options (its
    --train-args and --variants, parsed as train parses them)."""
    from safenav.commands.train import parse_train_args
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
    in_range("--first-seed", cfg.first_seed, 0, MAX_SEED - cfg.seeds + 1)
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
    for trial in {t.label: t for t in trials}.values():
        try:
            parse_train_args(["--algo", trial.algo, *trial.train_args])
        except SafenavError as err:
            where = f"--variants {trial.label}" if trial.label in variants else "--train-args"
            raise SafenavError(f"{where}: {err}") from None
