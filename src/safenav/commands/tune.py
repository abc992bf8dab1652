"""``safenav tune``: a validation-only hyperparameter search for one algorithm on SafeNav-v1."""

from __future__ import annotations

import shlex
from pathlib import Path

from safenav.cli import app


@app.command(name="tune")
def tune(
    space: str,
    trials: int = 8,
    total_steps: int = 1_000_000,
    seed: int = 101,
    out: Path | None = None,
    episodes: int = 400,
    jobs: int = 1,
    torch_threads: int = 2,
    preset: str = "paper",
    space_seed: int = 0,
    train_args: str = "",
    progress: bool = True,
) -> None:
    """Tune one algorithm's recipe on validation maps only: --trials configurations of --space
    (trial 0 = the recipe unchanged, then a scrambled Sobol sequence over the space), each trained
    --total-steps env steps with training seed --seed, its policy chosen on validation maps as
    --select does and scored on --episodes validation episodes (success, collision). Never the
    test scenario or the held-out maps. Writes OUT/trials/tNNN.json per finished trial (to
    commit), OUT/results.md (best first) and OUT/best.toml, a recipe for safenav train --config.
    Rerunning the same command resumes (finished trials skipped, an interrupted one continued
    from its checkpoint); a larger --trials adds configurations, the earlier ones unchanged.
    Every trial gets the comparison's evaluation protocol (--eval-every 250000 --eval-episodes
    400 --checkpoint-every 250000, as safenav reproduce) before --train-args.

    Example: safenav tune --space sac --trials 8  # results/tuning/sac/

    Example: safenav tune --space my_space.toml --trials 4 --total-steps 300k --preset easy

    Args:
        space: The search space: sac, sac-lag, ppo, ppo-lag or csac (shipped, safenav/experiments/spaces/), or a path to a .toml file of the same form.
        trials: Configurations to run (trial 0 is the recipe unchanged).
        total_steps: Env steps per trial (300k, 1M, 1e6 accepted).
        seed: Training seed of every trial (101: clear of the comparison's seeds 1-5).
        out: Output directory; default results/tuning/<space name>.
        episodes: Validation episodes that score each trial's chosen policy (spread over the 4 validation maps).
        jobs: Trials run at once, each with --torch-threads threads.
        torch_threads: Torch threads per trial.
        preset: Env preset (easy, medium, paper).
        space_seed: Scramble seed of the Sobol sequence (the same for every space: shared options take the same values in every algorithm's tuning).
        train_args: More safenav train options for every trial, one string.
        progress: Progress bars.
    """
    from safenav.commands.train import check_budget, given_flag, parse_train_args
    from safenav.common.checks import check_output_dir
    from safenav.envs.config import make_config
    from safenav.errors import SafenavError
    from safenav.experiments import tune as tuning
    from safenav.experiments.reproduce import PAPER_TRAIN_ARGS
    from safenav.recipes import PPO_ALGOS

    bounds = {"--trials": (trials, 1, 1000), "--total-steps": (total_steps, 1, None),
              "--seed": (seed, 0, 2**32 - 1), "--episodes": (episodes, 4, 100_000),
              "--jobs": (jobs, 1, 256), "--torch-threads": (torch_threads, 1, 1024),
              "--space-seed": (space_seed, 0, 2**32 - 1)}  # fmt: skip
    for flag, (value, lo, hi) in bounds.items():
        if value < lo or (hi is not None and value > hi):
            raise SafenavError(
                f"{flag} {value}: must lie in [{lo}, {hi if hi is not None else 'inf'}]"
            )
    make_config(preset)  # ValueError for an unknown preset: exit 2
    sp = tuning.load_space(space, space_seed)
    if trials > 1 and not sp.params:
        raise SafenavError(f"--space {space} searches no option: only trial 0 (the recipe) exists; "
                           "give --trials 1")  # fmt: skip
    try:
        words = shlex.split(train_args)
    except ValueError as err:
        raise SafenavError(f"--train-args {train_args!r}: {err}") from None
    # what tune sets itself, or what would fly the test maps (--select) or bypass the space
    owned = ["algo", "config", "seed", "total_steps", "torch_threads", "preset", "run_dir", "resume",
             "overwrite", "select", "report_episodes", *(p.name.removeprefix("run.") for p in sp.params)]  # fmt: skip
    taken = [flag for flag in owned if given_flag(flag, words)]
    if taken:
        raise SafenavError(f"--train-args {train_args!r}: {', '.join('--' + f for f in taken)} "
                           "is tune's to set (or searched by the space)")  # fmt: skip
    extra = (*PAPER_TRAIN_ARGS, *words)
    out = out or Path("results") / "tuning" / Path(sp.source).stem
    check_output_dir(out, "--out")
    # every configuration's child command line, checked by safenav train's own parser first
    common = ["--algo", sp.algo, "--config", sp.recipe, "--seed", str(seed), "--total-steps",
              str(total_steps), "--torch-threads", str(torch_threads)]  # fmt: skip
    family = "ppo" if sp.algo in PPO_ALGOS else "csac"
    for i, config in enumerate(sp.configurations(trials)):
        try:
            parsed = parse_train_args(
                [*common, "--preset", preset, *tuning.option_args(config), *extra]
            )
            check_budget(family, parsed["run"], parsed[family])
        except SafenavError as err:
            raise SafenavError(f"trial {i} of --space {space}: {err}") from None
        if parsed["run"].select:  # a recipe of one's own may say so: it would report on seeds 1-6
            raise SafenavError(f"--space {space}: its recipe {sp.recipe} sets select: a tuning "
                               "trial must not fly the test or held-out maps")  # fmt: skip
    # what the preset and --train-args change in the recipe: best.toml carries it
    fixed = changed(
        parse_train_args(common), parse_train_args([*common, "--preset", preset, *extra])
    )
    tuning.tune(sp, out, trials=trials, total_steps=total_steps, seed=seed, episodes=episodes,
                jobs=jobs, torch_threads=torch_threads, preset=preset, extra=extra, fixed=fixed,
                progress=progress)  # fmt: skip


def changed(before: dict, after: dict) -> dict:
    """Dotted names (``run.eval_every``, ``csac.net.hidden``) whose values differ between two
    parsed ``safenav train`` command lines."""
    import dataclasses

    def flat(obj, prefix: str) -> dict:
        items = dataclasses.asdict(obj) if dataclasses.is_dataclass(obj) else obj
        out = {}
        for key, value in items.items():
            if isinstance(value, dict) and value:
                out.update(flat(value, f"{prefix}{key}."))
            else:
                out[f"{prefix}{key}"] = list(value) if isinstance(value, tuple) else value
        return out

    diff = {}
    for section in ("run", "csac", "ppo"):
        a, b = flat(before[section], f"{section}."), flat(after[section], f"{section}.")
        diff |= {k: v for k, v in b.items() if a.get(k) != v and v is not None}
    return diff
