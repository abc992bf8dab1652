"""``safenav train``: train CSAC, SAC, PPO, PPO-Lag or SAC-Lag on SafeNav-v1 or any Gymnasium env
into a run directory."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Annotated

import tyro

from safenav.algos.config import CSACConfig
from safenav.algos.ppo_config import PPOConfig
from safenav.cli import app
from safenav.common.config import RunConfig

ALGOS = ("csac", "sac", "ppo", "ppo_lag", "sac_lag")
# Options a resumed run may change; every other option comes from the run's config.json.
RESUMABLE = ("total_steps", "device", "torch_threads", "log_every", "eval_every", "eval_episodes",
             "checkpoint_every", "tensorboard", "save_buffer")  # fmt: skip


@app.command(name="train")
def train(
    # A plain str checked below, not a Literal: tyro would answer a typo with a boxed usage error
    # instead of the CLI's one-line ``safenav: error: ...``.
    algo: Annotated[str, tyro.conf.arg(metavar="{" + ",".join(ALGOS) + "}")] = "csac",
    run: Annotated[RunConfig, tyro.conf.arg(name="")] = RunConfig(),  # noqa: B008
    csac: CSACConfig = CSACConfig(),  # noqa: B008
    ppo: PPOConfig = PPOConfig(),  # noqa: B008
    run_dir: Path | None = None,
    resume: Path | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> None:
    """Train CSAC (the paper's method), SAC, PPO, PPO-Lag or SAC-Lag into a run directory.

    The run directory gets config.json, progress.csv, tb/ (TensorBoard), events.jsonl and
    checkpoint.pt (written atomically). --csac.* options set csac, sac (the same minus the cost
    side) and sac_lag (the same with OmniSafe's Lagrangian switches); --ppo.* set ppo and ppo_lag
    (PPO wants many envs: e.g. --num-envs 256). A directory that holds a run that trained is
    refused unless --resume DIR (continue it: its config.json is used; --total-steps, --device
    and the logging options may change) or --overwrite (replace it); one whose run failed before
    training is reused. Default run dir: runs/<algo>-<env>-s<seed>-<time>.

    Step counts take 1000000, 1e6, 1_000_000 or 1M. Everything is checked before the run
    directory is written, including the memory the run needs (refused with the estimate).
    """
    from safenav.algos import csac as csac_module
    from safenav.common.logger import prepare_run_dir

    run, cfg, run_dir = plan(algo, run, csac, ppo, run_dir, resume, overwrite)
    prepare_run_dir(run_dir, resume=resume is not None, overwrite=overwrite)
    if algo in ("ppo", "ppo_lag"):
        from safenav.algos import ppo as module
    else:
        module = csac_module
    if resume is None:
        module.write_config(run_dir, algo, run, cfg)
    result = module.train(algo, run, cfg, run_dir, resume=resume is not None, progress=progress)
    print(f"safenav train: {algo} finished at step {result['global_step']} ({result['updates']} updates); "
          f"last 100 episodes: success {result['success_rate']:.3f}, collision {result['collision_rate']:.3f}, "
          f"return {result['return']:.2f}; run dir {run_dir}")  # fmt: skip


def plan(algo: str, run: RunConfig, csac: CSACConfig, ppo: PPOConfig, run_dir: Path | None,
         resume: Path | None, overwrite: bool) -> tuple[RunConfig, CSACConfig | PPOConfig, Path]:  # fmt: skip
    """``(run config, algorithm config, run dir)`` of a ``safenav train`` command line, every
    check done before anything is written: algorithm, resume config, device, env and its
    spaces, memory. ``SafenavError`` (exit 2) or ``SafenavRuntimeError`` (exit 1) otherwise."""
    from safenav.common.checks import check_device
    from safenav.common.config import from_dict
    from safenav.common.envs import env_spaces
    from safenav.errors import SafenavError

    if algo not in ALGOS:
        raise SafenavError(f"unknown algorithm {algo!r} (--algo): choose one of {', '.join(ALGOS)}")
    family = "ppo" if algo in ("ppo", "ppo_lag") else "csac"
    cfg = ppo if family == "ppo" else csac
    if resume is not None:
        if overwrite:
            raise SafenavError("--resume continues a run and --overwrite replaces it: pass one")
        if run_dir is not None and Path(run_dir).resolve() != Path(resume).resolve():
            raise SafenavError(
                f"--resume {resume} and --run-dir {run_dir} name different directories"
            )
        run_dir = Path(resume)
        config_path = run_dir / "config.json"
        if not config_path.is_file():
            raise SafenavError(f"--resume {run_dir}: no config.json there")
        try:
            saved = json.loads(config_path.read_text())
            # the algorithm first: another family's config.json lacks this family's section
            if isinstance(saved, dict) and saved.get("algo") != algo:
                raise SafenavError(
                    f"--resume {run_dir}: the run is --algo {saved.get('algo')}, not {algo}"
                )
            saved_run = from_dict(RunConfig, saved["run"])
            cfg = from_dict(PPOConfig if family == "ppo" else CSACConfig, saved[family])
        except (KeyError, ValueError, TypeError) as err:
            raise SafenavError(
                f"--resume {run_dir}: config.json is not a {algo} run config ({err})"
            ) from None
        default = RunConfig()
        changes = {k: getattr(run, k) for k in RESUMABLE
                   if getattr(run, k) != getattr(default, k) or given(k)}  # fmt: skip
        run = dataclasses.replace(saved_run, **changes)
    elif run_dir is None:
        env_name = run.env.split(":")[-1]
        run_dir = Path("runs") / f"{algo}-{env_name}-s{run.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
    if algo == "sac":
        from safenav.algos.sac import sac_config

        cfg = sac_config(cfg)
    elif algo == "sac_lag":
        from safenav.algos.sac_lag import sac_lag_config

        cfg = sac_lag_config(cfg)
    elif family == "ppo":
        cfg = dataclasses.replace(cfg, constrained=algo == "ppo_lag")
    check_device(run.device)
    obs_shapes, action_dim, env_cfg = env_spaces(run.env, run.preset)
    if "lidar" in obs_shapes:  # each stride divides the range image's columns (36 -> 18 -> 9)
        columns, prefix = obs_shapes["lidar"][-1], f"--{family}.net.lidar-strides"
        if math.prod(cfg.net.lidar_strides) > columns:
            raise SafenavError(f"{prefix} {' '.join(map(str, cfg.net.lidar_strides))}: their "
                               f"product must not exceed the {columns} lidar columns")  # fmt: skip
    if family == "ppo" and cfg.num_minibatches > cfg.rollout_steps * run.num_envs:
        raise SafenavError(f"--ppo.num-minibatches {cfg.num_minibatches}: a rollout holds only "
                           f"{cfg.rollout_steps * run.num_envs} transitions (--ppo.rollout-steps x "
                           "--num-envs)")  # fmt: skip
    check_training_memory(algo, run, cfg, obs_shapes, action_dim, env_cfg)
    return run, cfg, Path(run_dir)


def given(field: str) -> bool:
    """Whether the command line names the option of RunConfig ``field`` (also when it gives
    the default value: ``--device cpu`` to resume a run trained on cuda)."""
    from safenav.cli import ARGS

    flag = "--" + field.replace("_", "-")
    negated = "--no-" + field.replace("_", "-")
    return any(a in (flag, negated) or a.startswith(flag + "=") for a in ARGS.get())


def check_training_memory(algo: str, run: RunConfig, cfg, obs_shapes, action_dim: int, env_cfg,
                          available: int | None = None) -> None:  # fmt: skip
    """``SafenavRuntimeError`` with the estimate when the run cannot fit in this machine's
    (or GPU's) memory (:mod:`safenav.common.memory`)."""
    from safenav.common.checks import check_memory, fmt_bytes
    from safenav.common.memory import training_memory

    parts = training_memory(algo, run.num_envs, run.total_steps, cfg, obs_shapes, action_dim,
                            env_cfg, run.eval_episodes if run.eval_every else 0)  # fmt: skip
    if available is None and run.device.startswith("cuda"):
        import torch

        available = torch.cuda.mem_get_info(torch.device(run.device))[0]
    family = "ppo" if algo in ("ppo", "ppo_lag") else "csac"
    knobs = {  # what sizes each part: the fix the message names
        "envs": "--num-envs", "evaluation envs": "--eval-episodes",
        "replay buffer": "--csac.buffer-size", "minibatches": "--csac.batch-size",
        "rollout": "--num-envs or --ppo.rollout-steps", "n-step window": "--csac.cost-n-step",
        "networks": f"the --{family}.net sizes or --csac.num-critics / --csac.num-cost-critics",
        "activations": f"--num-envs or --{family}.net.hidden",
    }  # fmt: skip
    big = sorted(parts.items(), key=lambda kv: -kv[1])[:3]
    detail = ", ".join(f"{k} {fmt_bytes(v)}" for k, v in big)
    check_memory(sum(parts.values()), f"training {run.num_envs:,} envs ({detail})",
                 f"lower {knobs.get(big[0][0], '--num-envs')}", available)  # fmt: skip


def parse_train_args(args: list[str]) -> dict:
    """``safenav train``'s options parsed and their configs validated, without training (what
    ``safenav reproduce`` checks its --train-args and --variants with before starting Ray)."""
    import functools

    from safenav.cli import _parse_errors_as_safenav_errors
    from safenav.common.checks import registry

    options = functools.wraps(train)(lambda **kwargs: kwargs)
    with _parse_errors_as_safenav_errors("train"):
        parsed = tyro.cli(options, args=args, prog="safenav train", registry=registry())
    if parsed["algo"] not in ALGOS:
        from safenav.errors import SafenavError

        raise SafenavError(f"unknown algorithm {parsed['algo']!r} (--algo): choose one of "
                           f"{', '.join(ALGOS)}")  # fmt: skip
    return parsed
