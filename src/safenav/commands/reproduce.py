"""``safenav reproduce``: every algorithm × seed trained and evaluated on Ray; results table."""

from __future__ import annotations

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
    existing Ray cluster (OUT must then be on a file system every node sees).

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
        train_args: Extra options for every safenav train, one string, e.g. --train-args="--batch-size 512".
        variants: Extra labelled configurations, LABEL=ALGO [train options], e.g. 'csac_nocurr=csac --no-curriculum'.
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
    try:
        run_sweep(cfg)
    except TrialFailed as err:
        print(f"safenav: {err}", file=sys.stderr)
        raise SystemExit(1) from None
