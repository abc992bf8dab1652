"""``safenav train``: train CSAC, SAC, PPO, PPO-Lag or SAC-Lag on SafeNav-v1 or any Gymnasium env
into a run directory."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Annotated

import tyro

from safenav.algos.config import CSACConfig
from safenav.algos.ppo_config import PPOConfig
from safenav.cli import app
from safenav.common.config import RunConfig
from safenav.common.families import CONSTRAINED, algo_family

ALGOS = ("csac", "sac", "ppo", "ppo_lag", "sac_lag")
# Options a resumed run may change; every other option comes from the run's config.json.
RESUMABLE = ("total_steps", "device", "torch_threads", "log_every", "eval_every", "eval_episodes",
             "checkpoint_every", "tensorboard", "save_buffer", "report_episodes")  # fmt: skip


@app.command(name="train")
def train(
    # A plain str checked below, not a Literal: tyro would answer a typo with a boxed usage error
    # instead of the CLI's one-line ``safenav: error: ...``.
    algo: Annotated[str, tyro.conf.arg(metavar="{" + ",".join(ALGOS) + "}")] = "csac",
    config: Annotated[str | None, tyro.conf.arg(metavar="NAME|PATH")] = None,
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
    refused unless --resume DIR (continue it: its config.json is used; --total-steps, --device,
    --report-episodes and the logging options may change) or --overwrite (replace it); one whose
    run failed before training is reused. Default run dir: runs/<algo>-<env>-s<seed>-<time>.

    --config NAME|PATH starts from a recipe: one shipped with safenav (csac, csac-paper,
    csac-maxcost, sac, sac-lag, ppo, ppo-lag, ...) or a TOML file of your own; options given on
    the command line override it (--env-kwargs adds to the recipe's env kwargs, key by key), and
    config.json records the resolved values and the recipe.
    Without --config, --algo A on SafeNav takes the recipe named A, and on any other Gymnasium
    env the recipe of its task family (classic-*, box2d-*, mujoco-*, else gym-*; -sac for csac,
    sac and sac_lag, -ppo for ppo and ppo_lag), named in the first line printed; --config none
    keeps the built-in defaults. A run whose --total-steps do not exceed its warm-up
    (--csac.learning-starts) is refused. csac, sac_lag and ppo_lag read the cost from
    info["cost"]; on an env without it they warn that they reduce to sac / ppo, and
    --cost-fn module:function supplies one (safenav.common.costs). --select ends the run by choosing its policy on validation maps only
    (RUN_DIR/policy.pt) and reporting it on the test and held-out scenarios (RUN_DIR/final.json;
    --report-episodes per scenario, 200 by default).

    Step counts take 1000000, 1e6, 1_000_000 or 1M. Everything is checked before the run
    directory is written, including the memory the run needs (refused with the estimate).
    """
    from safenav import training
    from safenav.cli import ARGS
    from safenav.common.logger import prepare_run_dir, run_dir_lock
    from safenav.envs.vector import cost_function

    algo, run, csac, ppo, recipe = apply_recipe(config, algo, run, csac, ppo, ARGS.get(), resume)
    run, cfg, run_dir, obs_shapes, note = plan(algo, run, csac, ppo, run_dir, resume, overwrite)
    with run_dir_lock(run_dir) as lock:  # one process per run dir, first write to last
        prepare_run_dir(run_dir, resume=resume is not None, overwrite=overwrite)
        lock.accepted = True  # past the refusals: a later failure keeps the lock file
        if recipe is not None:  # after every refusal: a refused command prints its error alone
            print(recipe_line(recipe, run.env, chosen=config is None))
        if "lidar" not in obs_shapes:  # SafeNav: its range image has an encoder
            warn_images(run.env, obs_shapes)
        if resume is None and note:  # a discrete task's categorical policy, no time limit
            print(note, file=sys.stderr)
        if resume is None and (rollout := rollout_note(algo, run, cfg)):
            print(rollout, file=sys.stderr)
        if resume is None:
            training.write_config(run_dir, algo, run, cfg, recipe_record(recipe))
        with cost_function(run.cost_fn):
            factory = None
            if run.shield:  # the env executes the shield's corrections; it loads Numba: only then
                from safenav.deploy.shield import shield_from_spec as factory

            result = training.train(algo, run, cfg, run_dir, resume=resume is not None,
                                    progress=progress, shield_factory=factory)  # fmt: skip
        _report_and_select(algo, run, run_dir, result)


def _report_and_select(algo: str, run: RunConfig, run_dir: Path, result: dict) -> None:
    from safenav.envs.vector import is_safenav

    episodes = result["episodes"]
    if not episodes:  # a budget shorter than one episode: say so rather than print nan
        recent = "no training episode ended in this run's steps (an episode is longer)"
    elif is_safenav(run.env):
        recent = (f"last {episodes} episodes: success {result['success_rate']:.3f}, collision "
                  f"{result['collision_rate']:.3f}, return {result['return']:.2f}")  # fmt: skip
    else:  # success and collision are SafeNav's notions
        recent = f"last {episodes} episodes: return {result['return']:.2f}"
    print(f"safenav train: {algo} finished at step {result['global_step']} ({result['updates']} "
          f"updates)\n  {recent}\n  run dir {run_dir}")  # fmt: skip
    if run.select:
        finish_run(run_dir, run.device, run.report_episodes)


def finish_run(run_dir: Path, device: str = "cpu", report_episodes: int = 200) -> dict:
    """``--select``: the run's policy chosen on validation maps only (``RUN_DIR/policy.pt``,
    ``selection.json``), then reported on the test scenario and the held-out maps
    (``RUN_DIR/final.json``; :mod:`safenav.experiments.selection`)."""
    from safenav.common.jsonout import write_json
    from safenav.experiments.selection import report_policy, select_final_policy

    t0 = time.perf_counter()
    selection = select_final_policy(run_dir, device=device)
    report = report_policy(run_dir / "policy.pt", episodes=report_episodes, device=device)
    final = {"policy": str(run_dir / "policy.pt"), "selection": selection,
             **report, "report_wall_clock_s": round(time.perf_counter() - t0, 1)}  # fmt: skip
    write_json(run_dir / "final.json", final)
    test, held = report["test"], report["heldout"]
    print(f"safenav train: policy chosen on validation ({selection['method']}, steps "
          f"{selection['chosen_steps']})\n  -> {run_dir / 'policy.pt'}\n"
          f"  test success {test['success_rate']:.3f} collision {test['collision_rate']:.3f}; "
          f"held-out success {held['success_rate']:.3f} collision {held['collision_rate']:.3f}\n"
          f"  test under NavRL's collision rule: success "
          f"{report['test_navrl_rule']['success_rate']:.3f} collision "
          f"{report['test_navrl_rule']['collision_rate']:.3f}")  # fmt: skip
    alone = report.get("test_without_filter")
    if alone is not None:  # the figures above fly behind the planner filter
        print(
            f"  (behind the planner filter; test without it: success "
            f"{alone['success_rate']:.3f} collision {alone['collision_rate']:.3f})"
        )
    return final


def given_flag(flag: str, args: tuple[str, ...] | list[str]) -> bool:
    """Whether ``args`` names ``--flag`` (as ``--a.b-c``, ``--a.b_c``, ``--no-...`` or with
    ``=value``)."""
    dotted, _, last = flag.rpartition(".")
    prefix = dotted + "." if dotted else ""
    forms = set()
    for name in (last.replace("_", "-"), last.replace("-", "_")):
        forms |= {f"--{prefix}{name}", f"--{prefix}no-{name}", f"--{prefix}no_{name}"}
    return any(a.split("=", 1)[0] in forms for a in args)


def _recipe_overrides(section: dict, obj, prefix: str, args) -> dict:
    """The recipe's values for the fields of ``obj`` whose flags ``args`` does not give. A
    mapping given on the command line (``--env-kwargs``) adds to the recipe's mapping, key by key
    (the command line's keys win), rather than replacing it: ``--algo csac --env-kwargs
    lidar_memory 10`` keeps the recipe's crash loss."""
    import dataclasses

    out = {}
    for key, value in section.items():
        current = getattr(obj, key, None)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            sub = _recipe_overrides(value, current, f"{prefix}{key}.", args)
            if sub:
                out[key] = sub
        elif isinstance(value, dict) and isinstance(current, dict):
            out[key] = {**value, **current} if given_flag(f"{prefix}{key}", args) else value
        elif not given_flag(f"{prefix}{key}", args):
            out[key] = value
    return out


def apply_recipe(config: str | None, algo: str, run: RunConfig, csac: CSACConfig, ppo: PPOConfig,
                 args: tuple[str, ...] | list[str], resume: Path | None = None):  # fmt: skip
    """``(algo, run, csac, ppo, recipe)`` with the recipe of ``--config`` (or the default recipe
    of ``--algo`` on the env's task family, :func:`safenav.recipes.default_recipe`) applied under
    the options ``args`` gives (those win). A resumed run keeps the configuration in its
    config.json."""
    from safenav import recipes
    from safenav.errors import SafenavError

    if resume is not None:
        if config is not None:
            raise SafenavError("--config with --resume: a resumed run keeps the configuration "
                               "in its config.json")  # fmt: skip
        return algo, run, csac, ppo, None
    if config is not None and config.lower() == "none":
        return algo, run, csac, ppo, None
    name = config if config is not None else recipes.default_recipe(algo, run.env)
    if name is None:
        return algo, run, csac, ppo, None
    recipe = recipes.load_recipe(name)
    if recipe.algo not in ALGOS or set(recipe.algos) - set(ALGOS):
        raise SafenavError(f"--config {name}: its algos {list(recipe.algos)} are not all one of "
                           f"{', '.join(ALGOS)}")  # fmt: skip
    if config is not None:
        if given_flag("algo", args) and algo not in recipe.algos:
            raise SafenavError(f"--config {name} trains --algo {' / '.join(recipe.algos)}, not "
                               f"--algo {algo}: drop --algo or choose another recipe")  # fmt: skip
        if not given_flag("algo", args):
            algo = recipe.algo
    env = run.env  # the env's own values ([envs."ID"]) for the env of the command line
    run = recipes.apply(run, _recipe_overrides(recipe.section("run", env), run, "", args), "run.")
    csac = recipes.apply(csac, _recipe_overrides(recipe.section("csac", env), csac, "csac.", args),
                         "csac.")  # fmt: skip
    ppo = recipes.apply(ppo, _recipe_overrides(recipe.section("ppo", env), ppo, "ppo.", args),
                        "ppo.")  # fmt: skip
    return algo, run, csac, ppo, recipe


def recipe_line(recipe, env_id: str, chosen: bool) -> str:
    """The line ``safenav train`` prints first: the recipe it starts from, and why."""
    # Short lines: each fits 80 columns for the usual recipe and env names.
    first, second = f"safenav train: recipe {recipe.name}", f"  {recipe.source}"
    if chosen:
        from safenav.common.families import task_family

        first += f", chosen for {env_id}"
        second += f" ({task_family(env_id)[1]})"
    return f"{first}\n{second}\n  options given on the command line override it"


def recipe_record(recipe) -> dict | None:
    """What config.json keeps of the recipe a run started from."""
    if recipe is None:
        return None
    return {"name": recipe.name, "source": recipe.source, "header": recipe.header}


def plan(algo: str, run: RunConfig, csac: CSACConfig, ppo: PPOConfig, run_dir: Path | None,
         resume: Path | None, overwrite: bool) -> tuple[RunConfig, CSACConfig | PPOConfig, Path, dict, str]:  # fmt: skip
    """``(run config, algorithm config, run dir, observation shapes, note)`` of a ``safenav
    train`` command line (``note``: :func:`discrete_note`, :func:`time_limit_note`), every
    check done before anything is written: algorithm, resume config, device, env and its
    spaces, memory. ``SafenavError`` (exit 2) or ``SafenavRuntimeError`` (exit 1) otherwise."""
    from safenav.common.checks import check_device
    from safenav.common.config import from_dict
    from safenav.envs.vector import env_spaces
    from safenav.errors import SafenavError
    from safenav.training import algo_config

    if algo not in ALGOS:
        raise SafenavError(f"unknown algorithm {algo!r} (--algo): choose one of {', '.join(ALGOS)}")
    family = algo_family(algo)
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
        from safenav.cli import ARGS

        clashes = changed_options(ppo if family == "ppo" else csac, cfg, family, ARGS.get())
        if clashes:  # the run keeps its config.json: a different value would be ignored
            raise SafenavError(f"--resume {run_dir}: {'; '.join(clashes)}; a resumed run keeps "
                               "the configuration in its config.json (start a new run to "
                               "change it)")  # fmt: skip
        # a flag given at its default value counts too: --device cpu resumes a run trained on cuda
        default = RunConfig()
        changes = {k: getattr(run, k) for k in RESUMABLE
                   if getattr(run, k) != getattr(default, k) or given_flag(k, ARGS.get())}  # fmt: skip
        run = dataclasses.replace(saved_run, **changes)
    elif run_dir is None:
        env_name = run.env.split(":")[-1]
        run_dir = Path("runs") / f"{algo}-{env_name}-s{run.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
    cfg = algo_config(algo, cfg)
    check_device(run.device)
    obs_shapes, action_dim, env_cfg, num_actions = env_spaces(
        run.env, run.preset, run.env_kwargs, discrete_ok=family == "ppo"
    )
    if "lidar" in obs_shapes:  # each stride divides the range image's columns (36 -> 18 -> 9)
        columns, prefix = obs_shapes["lidar"][-1], f"--{family}.net.lidar-strides"
        if math.prod(cfg.net.lidar_strides) > columns:
            raise SafenavError(f"{prefix} {' '.join(map(str, cfg.net.lidar_strides))}: their "
                               f"product must not exceed the {columns} lidar columns")  # fmt: skip
    if family == "ppo" and cfg.num_minibatches > cfg.rollout_steps * run.num_envs:
        raise SafenavError(f"--ppo.num-minibatches {cfg.num_minibatches}: a rollout holds only "
                           f"{cfg.rollout_steps * run.num_envs} transitions (--ppo.rollout-steps x "
                           "--num-envs)")  # fmt: skip
    check_budget(family, run, cfg)
    check_cost(algo, run)
    check_training_memory(algo, run, cfg, obs_shapes, action_dim, env_cfg)
    notes = [n for n in (discrete_note(run, cfg, num_actions), time_limit_note(run)) if n]
    return run, cfg, Path(run_dir), obs_shapes, "\n".join(notes)


def time_limit_note(run: RunConfig) -> str:
    """The line that says a Gymnasium task has no time limit (CliffWalking-v1), where the run
    gives it none: an episode of a policy that walks in circles never ends, so an evaluation runs
    to its cap of 1M steps; ``""`` otherwise."""
    import gymnasium as gym

    from safenav.envs.vector import is_safenav

    if is_safenav(run.env) or "max_episode_steps" in (run.env_kwargs or {}):
        return ""
    if gym.spec(run.env).max_episode_steps is not None:
        return ""
    return (f"safenav train: note: {run.env} has no time limit, so an episode may never end (an "
            "evaluation stops after 1M steps); --env-kwargs max_episode_steps N gives it one")  # fmt: skip


def discrete_note(run: RunConfig, cfg, num_actions: int | None) -> str:
    """On a ``Discrete(n)`` task PPO's policy is categorical: the line that says so where the
    configuration asks for a continuous distribution (a recipe's ``gaussian``, gSDE), else ``""``."""
    if num_actions is None or (cfg.distribution == "beta" and not cfg.use_sde):
        return ""
    asked = [f"--ppo.distribution {cfg.distribution}"] if cfg.distribution != "beta" else []
    asked += ["--ppo.use-sde"] if cfg.use_sde else []
    return (f"safenav train: note: {run.env} acts in Discrete({num_actions}): PPO's policy is "
            f"categorical there ({' and '.join(asked)}: continuous actions only)")  # fmt: skip


def changed_options(given_cfg, saved_cfg, prefix: str, args) -> list[str]:
    """``--prefix.option VALUE (the run has SAVED)`` for each algorithm option that ``args`` names
    with a value other than the resumed run's (nested dataclasses walked)."""
    out = []
    for f in dataclasses.fields(given_cfg):
        mine, theirs = getattr(given_cfg, f.name), getattr(saved_cfg, f.name)
        flag = f"{prefix}.{f.name}"
        if dataclasses.is_dataclass(mine):
            out += changed_options(mine, theirs, flag, args)
        elif given_flag(flag, args):
            same = (tuple(mine) == tuple(theirs) if isinstance(mine, (list, tuple))
                    and isinstance(theirs, (list, tuple)) else mine == theirs)  # fmt: skip
            if not same:
                out.append(f"--{flag.replace('_', '-')} {mine} (the run has {theirs})")
    return out


def rollout_note(algo: str, run: RunConfig, cfg) -> str:
    """PPO collects whole rollouts, so a budget that is not a multiple of one rollout runs to the
    next multiple: the line that says so (printed once the run is accepted), else ``""``."""
    if algo_family(algo) != "ppo":
        return ""
    rollout = cfg.rollout_steps * run.num_envs
    steps = -(-run.total_steps // rollout) * rollout
    if steps == run.total_steps:
        return ""
    return (f"safenav train: note: PPO collects whole rollouts of {rollout:,} env steps "
            f"(--ppo.rollout-steps {cfg.rollout_steps} x --num-envs {run.num_envs}), so "
            f"--total-steps {run.total_steps:,} trains {steps:,}")  # fmt: skip


def check_budget(family: str, run: RunConfig, cfg) -> None:
    """``SafenavError`` for an off-policy run whose budget ends within its warm-up of uniform
    random actions: it would never update its networks."""
    if family == "csac" and run.total_steps <= cfg.learning_starts:
        from safenav.errors import SafenavError

        raise SafenavError(f"--total-steps {run.total_steps:,} does not exceed the warm-up of "
                           f"{cfg.learning_starts:,} random steps (--csac.learning-starts): the run "
                           "would end before its first update; raise --total-steps or lower "
                           "--csac.learning-starts")  # fmt: skip


def check_cost(algo: str, run: RunConfig) -> None:
    """``--cost-fn`` must name a function (and not be given for SafeNav, which has its own cost);
    a constrained algorithm on an env that reports no ``info["cost"]`` warns, once, that it
    trains its unconstrained form."""
    from safenav.envs.vector import is_safenav, reports_cost
    from safenav.errors import SafenavError

    if run.cost_fn is not None:
        if is_safenav(run.env):
            raise SafenavError(f"--cost-fn applies to envs without a cost; {run.env} has its own "
                               "(collisions)")  # fmt: skip
        from safenav.common.costs import load_cost_fn

        load_cost_fn(run.cost_fn)
    if run.cost_fn is not None or algo in CONSTRAINED and not is_safenav(run.env):
        try:
            has_cost = reports_cost(run.env, run.cost_fn)
        except Exception as err:  # noqa: BLE001 -- the user's function on this env's steps
            raise SafenavError(f"--cost-fn {run.cost_fn}: fails on {run.env}'s steps: "
                               f"{type(err).__name__}: {err}") from None  # fmt: skip
        if not has_cost and algo in CONSTRAINED:
            plain = "ppo" if algo_family(algo) == "ppo" else "sac"
            print(f"safenav train: warning: {run.env} reports no info['cost'], so {algo} sees cost "
                  f"0 in every step and reduces to {plain}; give a cost with --cost-fn "
                  "module:function (docs/gymnasium.md)", file=sys.stderr)  # fmt: skip


def warn_images(env_id: str, obs_shapes: dict[str, tuple[int, ...]]) -> None:
    """One warning for an observation with more than one axis (CarRacing's 96x96x3 pixels): the
    networks of Gymnasium tasks are MLPs over the flattened observation, with no image encoder
    (SafeNav's range image has its own), so such a run is slow and learns little."""
    for key, shape in obs_shapes.items():
        if len(shape) > 1 and math.prod(shape) >= 1024:  # not a small matrix of features
            print(f"safenav train: warning: {env_id}'s observation {key!r} is {'x'.join(map(str, shape))}: "
                  f"it is flattened into {math.prod(shape):,} inputs of an MLP (no image encoder "
                  "for Gymnasium tasks), slow and unlikely to learn; wrap the env to give a "
                  "feature vector (e.g. gymnasium.wrappers)", file=sys.stderr)  # fmt: skip


def check_training_memory(algo: str, run: RunConfig, cfg, obs_shapes, action_dim: int, env_cfg,
                          available: int | None = None) -> None:  # fmt: skip
    """``SafenavRuntimeError`` with the estimate when the run cannot fit in this machine's
    (or GPU's) memory (:mod:`safenav.common.memory`)."""
    from safenav.common.checks import check_memory, fmt_bytes
    from safenav.common.memory import training_memory

    parts = training_memory(algo, run.num_envs, run.total_steps, cfg, obs_shapes, action_dim,
                            env_cfg, run.eval_episodes if run.eval_every else 0,
                            2 if run.map_refresh_mode == "per-env" and run.map_refresh_every else 1)  # fmt: skip
    if available is None and run.device.startswith("cuda"):
        import torch

        available = torch.cuda.mem_get_info(torch.device(run.device))[0]
    family = algo_family(algo)
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
    algo, run, csac, ppo, _ = apply_recipe(parsed["config"], parsed["algo"], parsed["run"],
                                           parsed["csac"], parsed["ppo"], args)  # fmt: skip
    if algo not in ALGOS:
        from safenav.errors import SafenavError

        raise SafenavError(f"unknown algorithm {algo!r} (--algo): choose one of "
                           f"{', '.join(ALGOS)}")  # fmt: skip
    return parsed | {"algo": algo, "run": run, "csac": csac, "ppo": ppo}
