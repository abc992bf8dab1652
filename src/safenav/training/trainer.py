"""The training loop every algorithm shares; the algorithm itself is a :class:`Learner`.

:class:`Trainer` owns a run from set-up to the last checkpoint: threads, matmul precision and
device, the training env and the evaluation env (``--normalize-obs`` / ``--normalize-reward``:
the training env's normalisation, :mod:`safenav.common.normalize`, whose observation statistics
the evaluation and every saved policy apply as they are), the density curriculum (obstacle
density) and the constraint curriculum (the budget ``d``, paper III-C), ``--resume``, the
progress display, the ``progress.csv`` / TensorBoard rows, periodic evaluation with ``best.pt``,
checkpoints and early stops (:class:`~safenav.common.stopping.RunGuard`). One iteration:

1. ``learner.collect``: one vector step into the replay buffer (CSAC, SAC, SAC-Lag) or one rollout
   (PPO, PPO-Lag); the episodes that ended feed the episode charts, both curricula and
   ``learner.observe``;
2. the schedule: the constraint curriculum's stage, new training maps every
   ``--map-refresh-every`` env steps (``learner.maps_changed``), the obstacle density;
3. ``learner.update``: the gradient steps due now, their metrics averaged into the next row;
4. evaluation, the progress row (``learner.log_items`` adds the algorithm's own columns) and the
   checkpoint (``learner.state_dict`` adds the algorithm's own training state), each when due.

The algorithms (:mod:`safenav.algos`) never import this module: a learner is any object with the
attributes and methods of :class:`Learner`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import torch

from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSACLearner
from safenav.algos.policy import POLICY_FORMAT_VERSION
from safenav.algos.ppo import PPOLearner
from safenav.algos.ppo_config import PPOConfig
from safenav.algos.sac import sac_config
from safenav.algos.sac_lag import sac_lag_config
from safenav.common.checkpoint import (
    load_training_checkpoint,
    policy_state,
    restore_agent,
    rng_state,
    seed_everything,
    set_rng_state,
)
from safenav.common.config import RunConfig, to_dict
from safenav.common.curriculum import ConstraintCurriculum, DensityCurriculum
from safenav.common.families import PPO_ALGOS
from safenav.common.logger import RunLogger
from safenav.common.normalize import make_normalization
from safenav.common.progress import ProgressDisplay  # here, not lazily: its import draws `random`
from safenav.common.stopping import RunGuard, enable_sigint
from safenav.envs.planner import filter_spec, observes_pillars
from safenav.envs.vector import TorchVecEnv, env_horizon, is_safenav, make_vec_env, obs_layout
from safenav.errors import SafenavError
from safenav.training.evaluation import BestPolicy, periodic_evaluation
from safenav.training.planner_flights import fly_planner
from safenav.training.runs import episode_charts, run_summary, write_run_config
from safenav.training.shielded import ShieldedVecEnv, ShieldFn


class Learner(Protocol):
    """What the trainer asks of an algorithm (``algos.csac.CSACLearner``, ``algos.ppo.PPOLearner``).

    ``agent`` is the ``nn.Module`` of networks, optimisers and update rule: its ``state_dict`` and
    ``optimizer_state`` go into the checkpoint, its ``policy_module()`` into ``best.pt``.
    """

    agent: Any
    section: str
    """The config section of the family: ``"csac"`` or ``"ppo"`` (config.json, checkpoints)."""
    columns: tuple[str, ...]
    """Every progress.csv column of the algorithm, in order."""
    policy_meta: dict[str, Any]
    """What the algorithm adds to the policy metadata (PPO: its ``policy_head``)."""

    def collect(
        self, env: TorchVecEnv, obs: dict[str, torch.Tensor], global_step: int, d: float
    ) -> tuple[dict[str, torch.Tensor], list[dict[str, torch.Tensor]], int]:
        """Act in ``env`` from ``obs`` and store what it returns; ``(the observation to go on
        from, the episode statistics of the episodes that ended, env steps taken)``."""

    def observe(self, episodes: dict[str, list[float]]) -> None:
        """The statistics of episodes that ended (``cost``, ``success``, ... lists)."""

    def maps_changed(self) -> None:
        """The trainer reset every env (new maps): episodes were cut."""

    def update(self, global_step: int, d: float) -> tuple[int, list[dict[str, torch.Tensor]]]:
        """The gradient steps due at ``global_step`` under the budget ``d``: ``(how many were
        taken, their metrics as detached scalar tensors)``."""

    def act(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """Deterministic actions (evaluation)."""

    def log_items(self, d: float) -> dict[str, float]:
        """The algorithm's own entries of the progress row about to be written."""

    def state_dict(self) -> dict[str, Any]:
        """The algorithm's training state beyond the agent's (checkpoint keys)."""

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` from a checkpoint (``state["global_step"]`` included)."""


LEARNERS: dict[str, type] = {"csac": CSACLearner, "sac": CSACLearner, "sac_lag": CSACLearner,
                             "ppo": PPOLearner, "ppo_lag": PPOLearner}  # fmt: skip
"""``--algo`` -> the learner that trains it (the variants differ only in their config)."""


def algo_config(algo: str, cfg: CSACConfig | PPOConfig) -> CSACConfig | PPOConfig:
    """``cfg`` with the switches that make ``algo`` of its family: SAC drops the cost side, SAC-Lag
    takes OmniSafe's Lagrangian, PPO-Lag is constrained and PPO is not; CSAC is ``cfg`` itself."""
    if algo == "sac":
        return sac_config(cfg)
    if algo == "sac_lag":
        return sac_lag_config(cfg)
    if algo in PPO_ALGOS:
        return dataclasses.replace(cfg, constrained=algo == "ppo_lag")
    return cfg


def write_config(run_dir: Path, algo: str, run: RunConfig, cfg: CSACConfig | PPOConfig,
                 recipe: dict | None = None) -> None:  # fmt: skip
    """``config.json`` of a run (:func:`safenav.training.runs.write_run_config`)."""
    write_run_config(run_dir, algo, run, LEARNERS[algo].section, cfg, recipe)


def map_refresh_interval(every: int, num_envs: int, horizon: int) -> int:
    """Env steps between redraws of the training maps: ``every`` (``--map-refresh-every``, 0 =
    never), raised to ``num_envs * horizon`` so that each env flies at least one full time limit
    per map set. ``every`` counts the steps of all envs, and a redraw resets every episode: the
    recipes' 200 000 give each of 256 envs 781 steps (SafeNav-v1's limit is 600), but each of
    1024 envs only 195, and then no episode longer than that ever ends, a slow success included
    (the GPU regime, docs/csac-v1.md)."""
    return max(every, num_envs * horizon) if every > 0 else 0


def train(algo: str, run: RunConfig, cfg: CSACConfig | PPOConfig, run_dir: Path,
          resume: bool = False, progress: bool = True,
          shield_factory: Callable[[dict], ShieldFn] | None = None) -> dict[str, float]:  # fmt: skip
    """Train ``algo`` (``csac``, ``sac``, ``sac_lag``, ``ppo``, ``ppo_lag``) into ``run_dir``
    (prepared by the caller; resumed from its ``checkpoint.pt`` when ``resume``). Returns the
    final step and update counts and the rates of the last 100 episodes. ``shield_factory``: a
    fresh shield of ``run.shield_spec()``, for ``run.shield`` (:mod:`safenav.training.shielded`)."""
    return Trainer(algo, run, algo_config(algo, cfg), run_dir, resume, progress,
                   shield_factory).run()  # fmt: skip


class Trainer:
    """One training run of one learner (see the module docstring)."""

    def __init__(self, algo: str, run: RunConfig, cfg: CSACConfig | PPOConfig, run_dir: Path,
                 resume: bool = False, progress: bool = True,
                 shield_factory: Callable[[dict], ShieldFn] | None = None) -> None:  # fmt: skip
        self.algo, self.run_cfg, self.cfg, self.resume = algo, run, cfg, resume
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        enable_sigint()
        torch.set_num_threads(run.torch_threads or max(1, torch.get_num_threads()))
        torch.set_float32_matmul_precision(run.matmul_precision)
        self.device = torch.device(run.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise SafenavError(
                "--device cuda: CUDA is not available on this machine (use --device cpu)"
            )
        ckpt_path = self.run_dir / "checkpoint.pt"
        ckpt = load_training_checkpoint(ckpt_path, algo, self.device) if resume else None
        seed_everything(run.seed)

        # -- envs, learner, curricula (in this order: the agent's initial weights draw from the RNG)
        self.density = DensityCurriculum(run.density, run.total_steps)
        self.nav = is_safenav(run.env)
        env_kwargs = dict(run.env_kwargs)
        if self.nav:  # the curriculum's density
            env_kwargs["density"] = self.density.density
        envs = make_vec_env(run.env, run.num_envs, run.device, run.preset, **env_kwargs)
        # --normalize-obs / --normalize-reward: statistics updated by the training env only
        self.normalization = make_normalization(obs_layout(envs.single_observation_space),
                                                run.num_envs, cfg.gamma, run.normalize_obs,
                                                run.normalize_reward)  # fmt: skip
        if self.normalization is not None:
            self.normalization.to(self.device)
        self.env = TorchVecEnv(envs, self.device, self.normalization)
        spec = run.shield_spec()
        if spec is not None and shield_factory is None:
            raise SafenavError("--shield: this caller of train() passes no shield_factory")
        if spec is not None:  # the env executes the shield's corrections (training/shielded.py)
            self.env = ShieldedVecEnv(self.env, shield_factory(spec), run.shield_penalty)
        nav_cfg = getattr(envs.unwrapped, "cfg", None)
        if run.flight_filter and not observes_pillars(nav_cfg):
            raise SafenavError("--flight-filter: the planner filter flies on the observation's "
                               "pillar list, which this env's observation lacks: add --env-kwargs "
                               "static_tracked 10, or --no-flight-filter")  # fmt: skip
        self.refresh_every = 0  # map redraws: SafeNav only
        if self.nav:
            horizon = env_horizon(envs)
            self.refresh_every = map_refresh_interval(run.map_refresh_every, run.num_envs, horizon)
            if self.refresh_every != run.map_refresh_every:
                print(f"safenav train: --map-refresh-every {run.map_refresh_every} would give each "
                      f"of {run.num_envs} envs {run.map_refresh_every // run.num_envs} steps per map "
                      f"set, under the {horizon}-step time limit: maps redrawn every "
                      f"{self.refresh_every} env steps instead")  # fmt: skip
        self.eval_env = None
        if run.eval_every > 0:
            eval_kwargs = {**env_kwargs, "density": run.density.end} if self.nav else env_kwargs
            self.eval_env = TorchVecEnv(make_vec_env(run.env, min(run.eval_episodes, 32), run.device,
                                                     run.preset, **eval_kwargs), self.device)  # fmt: skip
            if spec is not None:  # the policy is evaluated behind the shield it flies behind
                self.eval_env = ShieldedVecEnv(
                    self.eval_env, shield_factory(run.flight_shield_spec())
                )
        self.learner: Learner = LEARNERS[algo](self.env, run, cfg)
        self.agent = self.learner.agent
        self.planner_stats = None  # --csac.planner-share: the planner's flights, before training
        if getattr(cfg, "planner_share", 0.0) > 0:
            if not self.nav or self.normalization is not None:
                raise SafenavError("--csac.planner-share: the planner flies SafeNav envs and reads "
                                   "their raw observations (no --normalize-obs)")  # fmt: skip
            flights, self.planner_stats = fly_planner(
                run, {**env_kwargs, "density": run.density.end}, cfg.planner_steps,
                cfg.planner_envs, self.device, progress, cfg.planner_keep_band,
                cfg.planner_view)  # fmt: skip
            self.learner.set_planner_flights(flights)
            del flights
        self.curriculum = ConstraintCurriculum(cfg.curriculum)

        # -- resume: counters, curricula, the learner's state, then the RNG as it was
        self.global_step, self.updates, self.elapsed0 = 0, 0, 0.0
        self.next_eval: float | None = None  # the step of the next periodic evaluation
        if ckpt is not None:
            self.next_eval = ckpt.get("next_eval_step")
            restore_agent(self.agent, ckpt, ckpt_path)
            self.curriculum.load_state_dict(ckpt["curriculum"])
            self.density.load_state_dict(ckpt["density"])
            self.global_step, self.updates = ckpt["global_step"], ckpt["updates"]
            self.elapsed0 = ckpt["elapsed_s"]
            self.learner.load_state_dict(ckpt)
            if self.normalization is not None:
                if "normalization" not in ckpt:
                    raise SafenavError(f"{ckpt_path} holds no normalisation statistics, but its "
                                       "run normalises (config.json): it was not written by it")  # fmt: skip
                self.normalization.load_state_dict(ckpt["normalization"])
            set_rng_state(ckpt["rng"])
        if self.planner_stats is not None:  # the planner's minutes count in the run's wall-clock
            self.elapsed0 += self.planner_stats["wall_s"]
        self.env.set_density(self.density.density)
        columns = [*self.learner.columns, *(["charts/shield_rate"] if spec is not None else [])]
        self.logger = RunLogger(self.run_dir, columns, run.tensorboard,
                                resume_step=self.global_step if resume else None)  # fmt: skip
        self.logger.event(self.global_step, "resume" if resume else "start", algo=algo,
                          density=self.density.density, d=self.curriculum.d,
                          map_refresh_every=self.refresh_every)  # fmt: skip
        if self.planner_stats is not None:
            self.logger.event(self.global_step, "planner_flights", **self.planner_stats)
        self.guard = RunGuard(self.run_dir, self.logger, self.agent,
                              last_saved=self.global_step if ckpt is not None else None)  # fmt: skip
        self.best = BestPolicy.for_run(self.run_dir, run.keep_policies, ckpt)
        self.progress = progress

    # -- the loop ---------------------------------------------------------------------------
    def run(self) -> dict[str, float]:
        run, learner = self.run_cfg, self.learner
        self.window: dict[str, list[float]] = {}  # episodes since the last row
        self.recent = {k: deque(maxlen=100) for k in ("success", "collision", "return")}
        self.sums: dict[str, torch.Tensor] = {}  # update metrics since the last row
        self.n_sums = 0
        self.row: dict[str, float] = {}
        self.t0 = time.perf_counter()
        self.t_log, self.step_log, self.upd_log = self.t0, self.global_step, self.updates
        every = self.next_due
        next_log, next_ckpt = every(run.log_every), every(run.checkpoint_every)
        if self.next_eval is None:  # a new run, or a checkpoint from before next_eval_step
            self.next_eval = every(run.eval_every)
        self.refresh = self.global_step // self.refresh_every if self.refresh_every else 0
        self.obs = self.env.reset(seed=run.train_env_seed(self.refresh) if self.nav
                                  else run.seed + self.global_step)  # fmt: skip
        self.display = ProgressDisplay(run.total_steps, self.global_step, enabled=self.progress,
                                       title=f"{self.algo} {run.env}")  # fmt: skip
        try:
            # an evaluation that was due when the run stopped (a stop lands mostly in one: it is
            # the slow part) runs now, on the checkpoint's weights: the step it was due at
            self.evaluate_if_due()
            while self.global_step < run.total_steps:
                self.obs, episodes, steps = learner.collect(self.env, self.obs, self.global_step,
                                                            self.curriculum.d)  # fmt: skip
                self.global_step += steps
                for e in episodes:
                    self.observe({k: v.tolist() for k, v in e.items()})
                self.schedule()
                taken, metrics = learner.update(self.global_step, self.curriculum.d)
                self.updates += taken
                for m in metrics:
                    for k, v in m.items():
                        self.sums[k] = self.sums[k] + v if k in self.sums else v.clone()
                    self.n_sums += 1
                self.evaluate_if_due()
                if self.global_step >= next_log or self.global_step >= run.total_steps:
                    next_log = every(run.log_every)
                    self.log()
                self.display.advance(self.global_step)
                if self.global_step >= next_ckpt:
                    next_ckpt = every(run.checkpoint_every)
                    self.checkpoint()
        except (
            BaseException
        ) as err:  # Ctrl-C: checkpoint; divergence, errors: an event (stopping.py)
            self.guard.stopped(err, self.global_step, self.checkpoint)
            raise
        finally:
            self.display.close()
        self.checkpoint()
        self.logger.event(self.global_step, "end", updates=self.updates)
        self.logger.close()
        self.env.close()
        if self.eval_env is not None:
            self.eval_env.close()
        return run_summary(self.global_step, self.updates, self.recent)

    def observe(self, ep: dict[str, list[float]]) -> None:
        """Episodes that ended: the charts, the last 100 for the display, both curricula."""
        for k, vs in ep.items():
            self.window.setdefault(k, []).extend(vs)
        for k in self.recent:
            self.recent[k].extend(ep[k])
        self.curriculum.observe(ep["cost"])
        self.learner.observe(ep)
        self.density.observe(ep["success"])

    def schedule(self) -> None:
        """The constraint curriculum's stage, new maps when due, the obstacle density."""
        step = self.global_step
        change = self.curriculum.step(step)
        if change is not None:
            self.logger.event(step, "curriculum", **change)
            self.display.note(
                f"step {step}: d {change['d_old']:.3g} -> {change['d']:.3g} ({change['stage']})"
            )
        mode = self.run_cfg.map_refresh_mode
        due = self.refresh_every and step // self.refresh_every > self.refresh
        # per-env: a redraw waits until every env has left the maps of two redraws ago (at most
        # one time limit after the last; the interval is at least that many steps per env).
        if due and (mode == "all" or self.env.can_redraw_maps()):  # new maps
            self.refresh = step // self.refresh_every
            seed = self.run_cfg.train_env_seed(self.refresh)
            if mode == "per-env":  # each env at its next episode
                self.env.redraw_maps(seed)
            else:  # every env now: the episodes in flight end here
                self.obs = self.env.reset(seed=seed)
                self.learner.maps_changed()
            self.logger.event(step, "maps", seed=seed, mode=mode)
        new_density = self.density.step(step)
        if new_density is not None and self.env.set_density(new_density):
            self.logger.event(step, "density", density=new_density)

    def evaluate_if_due(self) -> None:
        """The periodic evaluation once ``next_eval`` is reached; the schedule moves on only after
        it, so a stop inside it leaves it due in the checkpoint and the resumed run redoes it."""
        if self.eval_env is None or self.global_step < self.next_eval:
            return
        self.evaluate()
        self.next_eval = self.next_due(self.run_cfg.eval_every)

    def next_due(self, every: int) -> float:
        """The first multiple of ``every`` after the current step (never, for 0): the schedule of
        logs, checkpoints and evaluations."""
        return (self.global_step // every + 1) * every if every else math.inf

    def evaluate(self) -> None:
        """The periodic evaluation (deterministic policy, evaluation maps), ``best.pt``."""
        ev, note = periodic_evaluation(self.eval_env, self.eval_act, self.run_cfg.eval_episodes,
                                       self.global_step, self.logger, self.best, self.policy_state)  # fmt: skip
        self.row.update(ev)
        self.display.note(note)

    def log(self) -> None:
        """One progress row: rates, episode charts, curricula, the learner's columns, the mean of
        every update metric since the last row; stops a run whose metrics or weights went NaN."""
        now, step, constrained = time.perf_counter(), self.global_step, self.cfg.constrained
        self.row.update({
            "time/elapsed_s": self.elapsed0 + now - self.t0,
            "perf/sps": (step - self.step_log) / max(now - self.t_log, 1e-9),
            "perf/updates": self.updates,
            "perf/updates_per_s": (self.updates - self.upd_log) / max(now - self.t_log, 1e-9),
            **episode_charts(self.window),
            "charts/density": self.density.density if self.nav else math.nan,
        })  # fmt: skip
        if isinstance(self.env, ShieldedVecEnv):  # the share of actions the shield changed
            self.row["charts/shield_rate"] = self.env.correction_rate()
        if constrained:
            self.row.update({"constraint/lambda": float(self.agent.lam),
                             "constraint/d": self.curriculum.d, "constraint/stage": self.curriculum.stage})  # fmt: skip
        self.row.update(self.learner.log_items(self.curriculum.d))
        update_metrics = (
            {k: float(v) / self.n_sums for k, v in self.sums.items()} if self.n_sums else {}
        )
        self.row.update(update_metrics)
        self.logger.log(step, self.row)
        self.guard.check(step, update_metrics)  # NaN/Inf: stop, keep checkpoint.pt
        self.display.metrics(
            step, self.row, self.recent, self.curriculum.d if constrained else None
        )
        self.window, self.sums, self.n_sums, self.row = {}, {}, 0, {}
        self.t_log, self.step_log, self.upd_log = now, step, self.updates

    def eval_act(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """Deterministic actions on the evaluation env's observations: normalised first with the
        training statistics as they are (``--normalize-obs``; evaluation never updates them)."""
        norm = self.normalization.obs if self.normalization is not None else None
        return self.learner.act(norm(obs) if norm is not None else obs)

    # -- checkpoints ------------------------------------------------------------------------
    def policy_meta(self) -> dict[str, Any]:
        """What :func:`safenav.algos.policy.load_policy` needs to rebuild and describe the actor."""
        env = self.env
        env_cfg = getattr(env.envs.unwrapped, "cfg", None)
        return {"format_version": POLICY_FORMAT_VERSION, "algo": self.algo, "env_id": self.run_cfg.env,
                "env_config": to_dict(env_cfg.replace(density=1.0)) if env_cfg is not None else None,
                "obs_shapes": {k: list(v) for k, v in env.obs_shapes.items()}, "action_dim": env.action_dim,
                "action_low": env._low.tolist(), "action_high": env._high.tolist(),
                "net": to_dict(self.cfg.net), "global_step": int(self.global_step),
                **self._shield_meta(),
                **self.learner.policy_meta,
                **(self.normalization.meta() if self.normalization is not None else {})}  # fmt: skip

    def _shield_meta(self) -> dict[str, Any]:
        """The shield the policy trained behind, the one it flies behind where they differ
        (``--shield-flight-brake``), and the planner filter it is reported behind
        (``--flight-filter``); each only where set, so the policies of a run resumed from before
        it still average."""
        out: dict[str, Any] = {}
        if self.run_cfg.flight_filter:
            out["flight_filter"] = filter_spec()
        if not self.run_cfg.shield:
            return out
        train, flight = self.run_cfg.shield_spec(), self.run_cfg.flight_shield_spec()
        return {"shield": train, **({"flight_shield": flight} if flight != train else {}), **out}

    def policy_state(self) -> dict[str, Any]:
        """The policy-only part of a checkpoint (``best.pt``, ``policies/``)."""
        config = {
            "algo": self.algo,
            "run": to_dict(self.run_cfg),
            self.learner.section: to_dict(self.cfg),
        }
        actor = self.agent.policy_module()
        if self.normalization is not None:  # the observation statistics go with the policy
            actor = self.normalization.policy(actor)
        return policy_state(self.algo, self.global_step, self.updates,
                            self.elapsed0 + time.perf_counter() - self.t0, config, self.policy_meta(),
                            actor)  # fmt: skip

    def checkpoint(self) -> None:
        state = self.policy_state() | {
            "agent": self.agent.state_dict(), "optimizers": self.agent.optimizer_state(),
            "curriculum": self.curriculum.state_dict(), "density": self.density.state_dict(),
            "rng": rng_state(), "best": self.best.state_dict(), **self.learner.state_dict()}  # fmt: skip
        if self.next_eval is not None and math.isfinite(self.next_eval):
            state["next_eval_step"] = int(self.next_eval)
        if self.normalization is not None:
            state["normalization"] = self.normalization.state_dict()
        self.guard.save(
            self.global_step, state
        )  # refuses non-finite weights: keeps the last good file


__all__ = [
    "LEARNERS",
    "Learner",
    "Trainer",
    "algo_config",
    "map_refresh_interval",
    "train",
    "write_config",
]
