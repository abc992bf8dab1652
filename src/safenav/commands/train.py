"""``safenav train``: train CSAC, SAC, PPO, PPO-Lag or SAC-Lag on SafeNav-v1 or any Gymnasium env
into a run directory."""

from __future__ import annotations

import dataclasses
import json
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
    (PPO wants many envs: e.g. --num-envs 256). A directory that holds a run is refused unless --resume DIR (continue it:
    its config.json is used; --total-steps, --device and the logging options may change) or
    --overwrite (replace it). Default run dir: runs/<algo>-<env>-s<seed>-<time>.
    """
    from safenav.algos import csac as csac_module
    from safenav.common.config import from_dict
    from safenav.common.envs import check_env
    from safenav.common.logger import prepare_run_dir
    from safenav.errors import SafenavError

    if algo not in ALGOS:
        raise SafenavError(f"unknown algorithm {algo!r} (--algo): choose one of {', '.join(ALGOS)}")
    family = "ppo" if algo in ("ppo", "ppo_lag") else "csac"
    cfg = ppo if family == "ppo" else csac
    if resume is not None:
        if run_dir is not None and Path(run_dir).resolve() != Path(resume).resolve():
            raise SafenavError(
                f"--resume {resume} and --run-dir {run_dir} name different directories"
            )
        run_dir = Path(resume)
        config_path = run_dir / "config.json"
        if not config_path.exists():
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
        changes = {k: getattr(run, k) for k in RESUMABLE if getattr(run, k) != getattr(default, k)}
        run = dataclasses.replace(saved_run, **changes)
        prepare_run_dir(run_dir, resume=True, overwrite=False)
    else:
        check_env(run.env, run.preset)  # before a run directory exists, so a retry is not refused
        if run_dir is None:
            env_name = run.env.split(":")[-1]
            run_dir = (
                Path("runs") / f"{algo}-{env_name}-s{run.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
            )
        prepare_run_dir(run_dir, resume=False, overwrite=overwrite)
    if algo == "sac":
        from safenav.algos.sac import sac_config

        cfg = sac_config(cfg)
    elif algo == "sac_lag":
        from safenav.algos.sac_lag import sac_lag_config

        cfg = sac_lag_config(cfg)
    elif family == "ppo":
        from safenav.algos import ppo as ppo_module

        cfg = dataclasses.replace(cfg, constrained=algo == "ppo_lag")
    module = ppo_module if family == "ppo" else csac_module
    if resume is None:
        module.write_config(run_dir, algo, run, cfg)
    result = module.train(algo, run, cfg, run_dir, resume=resume is not None, progress=progress)
    print(f"safenav train: {algo} finished at step {result['global_step']} ({result['updates']} updates); "
          f"last 100 episodes: success {result['success_rate']:.3f}, collision {result['collision_rate']:.3f}, "
          f"return {result['return']:.2f}; run dir {run_dir}")  # fmt: skip
