"""Constrained Soft Actor-Critic (CSAC, paper III-B, Algorithm 1) and, with ``constrained=False``,
plain SAC: one file, read top to bottom.

Algorithm 1 <-> code (the equations are pure functions in :mod:`safenav.algos.losses`):

1-2   actor, reward critics Q_R (min target), cost critics Q_C (mean target); targets hard-copied
      -> ``CSAC.__init__`` (``copy.deepcopy``)
3     alpha (``log_alpha``), lambda (:class:`~safenav.common.lagrange.Lagrange`), replay buffer
5-8   warm-up: ``learning_starts`` env steps of uniform random actions -> ``train`` (the loop)
10    act with ``a ~ pi(.|s)``, store ``(s, a, r, c, s', terminated)``
11    sample a minibatch -> ``ReplayBuffer.sample``
12    targets Eqs. 5-6, critic losses Eqs. 7-8 -> ``CSAC.update`` (first block)
13    actor Eq. 9, alpha Eq. 10, lambda Eq. 11, in the same step -> ``CSAC.update`` (second block)
14-15 Polyak averaging of every target parameter -> ``CSAC.update`` (last line)

Around it (paper III-C, Fig. 2): the constraint curriculum sets ``d`` and the density curriculum
the obstacle density, both in :mod:`safenav.common.curriculum`. docs/csac.md has the full
equation table, every logged metric, and the measurements behind the defaults.
"""

from __future__ import annotations

import copy
import math
import time
from collections import deque
from pathlib import Path
from typing import Any

import torch
from torch import nn

from safenav.algos.config import CSACConfig
from safenav.algos.losses import (
    actor_loss,
    alpha_loss,
    cost_target,
    critic_loss,
    n_step_cost_target,
    reward_target,
)
from safenav.algos.policy import POLICY_FORMAT_VERSION
from safenav.common.buffer import Batch, ReplayBuffer
from safenav.common.checkpoint import (
    load_training_checkpoint,
    restore_agent,
    rng_state,
    seed_everything,
    set_rng_state,
)
from safenav.common.checkpoint import policy_state as checkpoint_policy_state
from safenav.common.config import RunConfig, to_dict
from safenav.common.curriculum import (
    ConstraintCurriculum,
    DensityCurriculum,
    MeasuredCostScale,
    episode_cost_to_q_scale,
)
from safenav.common.envs import TorchVecEnv, env_horizon, is_safenav, make_vec_env
from safenav.common.evaluation import BestPolicy, periodic_evaluation
from safenav.common.lagrange import Lagrange
from safenav.common.logger import RunLogger
from safenav.common.nstep import NStepWindow
from safenav.common.runs import episode_charts, run_summary, write_run_config
from safenav.common.stopping import RunGuard, enable_sigint
from safenav.nn.networks import Actor, DeterministicActor, QEnsemble, input_order, make_extractor
from safenav.nn.optim import adam


class CSAC(nn.Module):
    """Networks, optimisers and the gradient update of CSAC (SAC when ``cfg.constrained`` is False)."""

    def __init__(
        self, obs_shapes: dict[str, tuple[int, ...]], action_dim: int, cfg: CSACConfig
    ) -> None:
        super().__init__()
        self.cfg, self.obs_shapes, self.action_dim = cfg, dict(obs_shapes), action_dim
        net, e = cfg.net, cfg.num_critics
        e_cost = cfg.num_cost_critics or e
        # -- line 1: actor and critics (see safenav.nn.networks for the extractor's gradient flow)
        if net.shared_extractor:
            self.encoder = make_extractor(obs_shapes, net)
            feat = self.encoder.out_features
            actor_ex, critic_ex = None, lambda k: None  # noqa: E731
        else:
            self.encoder = None
            actor_ex = make_extractor(obs_shapes, net)
            feat = actor_ex.out_features
            critic_ex = lambda k: make_extractor(obs_shapes, net, k)  # noqa: E731
        self.actor = Actor(actor_ex, feat, action_dim, net.hidden)
        self.qr = QEnsemble(critic_ex(e), feat, action_dim, net.hidden, e)
        self.qc = (
            QEnsemble(critic_ex(e_cost), feat, action_dim, net.hidden, e_cost)
            if cfg.constrained
            else None
        )
        # -- line 2: targets are hard copies
        self.encoder_target = copy.deepcopy(self.encoder)
        self.qr_target = copy.deepcopy(self.qr)
        self.qc_target = copy.deepcopy(self.qc)
        for target in (self.encoder_target, self.qr_target, self.qc_target):
            if target is not None:
                target.requires_grad_(False)
        # -- line 3: alpha, lambda
        self.log_alpha = nn.Parameter(torch.tensor(math.log(cfg.init_alpha)))
        self.target_entropy = (
            -float(action_dim) if cfg.target_entropy is None else cfg.target_entropy
        )
        lambda_lr = cfg.lambda_lr if cfg.lambda_from == "q_cost" else cfg.episode_lambda_lr
        self.lagrange = (
            Lagrange(cfg.init_lambda, lambda_lr, cfg.lambda_max) if cfg.constrained else None
        )
        # -- optimisers: one Adam per role, separate learning rates (paper IV)
        groups = [{"params": list(self.qr.parameters()), "lr": cfg.reward_critic_lr}]
        if self.qc is not None:
            groups.append({"params": list(self.qc.parameters()), "lr": cfg.cost_critic_lr})
        if self.encoder is not None:
            groups.append({"params": list(self.encoder.parameters()), "lr": cfg.reward_critic_lr})
        self.critic_optimizer = adam(groups)
        # actor (Eq. 9) and temperature (Eq. 10) step together: one backward, one Adam, two groups
        self.actor_params = list(self.actor.parameters())
        self.actor_optimizer = adam([{"params": self.actor_params, "lr": cfg.actor_lr},
                                     {"params": [self.log_alpha], "lr": cfg.alpha_lr}])  # fmt: skip
        self._policy_params = [*self.actor_params, self.log_alpha]
        online = [m for m in (self.encoder, self.qr, self.qc) if m is not None]
        target = [m for m in (self.encoder_target, self.qr_target, self.qc_target) if m is not None]
        self._online = [p for m in online for p in m.parameters()]
        self._target = [p for m in target for p in m.parameters()]

    @property
    def lam(self) -> torch.Tensor:
        return self.lagrange.value if self.lagrange is not None else torch.zeros(())

    @torch.no_grad()
    def act(self, obs: dict[str, torch.Tensor], deterministic: bool = False) -> torch.Tensor:
        x = self.encoder(obs) if self.encoder is not None else obs
        action, _, mean_action = self.actor.sample(x)
        return mean_action if deterministic else action

    def update(self, batch: Batch, d_q: float = 0.0) -> dict[str, torch.Tensor]:
        """One gradient update (Algorithm 1, lines 12-15); ``d_q`` is the threshold on the Q_C scale.
        Returns detached scalar metrics."""
        cfg = self.cfg
        obs, actions, rewards, costs, next_obs, terminated = batch[:6]
        n_step = self.qc is not None and batch.costs_n is not None
        alpha = self.log_alpha.exp().detach()
        # Features: with a shared extractor the critics train it and the actor reads it detached.
        if self.encoder is not None:
            x = self.encoder(obs)
            x_actor = x.detach()
            with torch.no_grad():
                x_next, x_next_target = self.encoder(next_obs), self.encoder_target(next_obs)
                if n_step:
                    x_n, x_n_target = (
                        self.encoder(batch.next_obs_n),
                        self.encoder_target(batch.next_obs_n),
                    )
        else:
            x = x_actor = obs
            x_next = x_next_target = next_obs
            if n_step:
                x_n = x_n_target = batch.next_obs_n

        # -- line 12: targets (Eqs. 5-6) and critic losses (Eqs. 7-8)
        with torch.no_grad():
            next_actions, next_log_prob, _ = self.actor.sample(x_next)
            y_r = reward_target(rewards, terminated, self.qr_target(x_next_target, next_actions),
                                next_log_prob, alpha, cfg.gamma)  # fmt: skip
            if n_step:  # beyond the paper: Eq. 6 over n steps (common.nstep)
                actions_n, _, _ = self.actor.sample(x_n)
                y_c = n_step_cost_target(batch.costs_n, batch.discount_n,
                                         self.qc_target(x_n_target, actions_n), cfg.cost_target)  # fmt: skip
            elif self.qc is not None:
                y_c = cost_target(costs, terminated, self.qc_target(x_next_target, next_actions),
                                  cfg.gamma, cfg.cost_target)  # fmt: skip
        q_r = self.qr(x, actions)
        loss_qr = critic_loss(q_r, y_r)
        loss_critic = loss_qr
        if self.qc is not None:
            loss_qc = critic_loss(self.qc(x, actions), y_c)
            loss_critic = loss_critic + loss_qc
        self.critic_optimizer.zero_grad(set_to_none=True)
        loss_critic.backward()
        self.critic_optimizer.step()

        # -- line 13: actor (Eq. 9), alpha (Eq. 10), lambda (Eq. 11) in the same step
        lam = self.lam
        new_actions, log_prob, _ = self.actor.sample(x_actor)
        q_r_pi = self.qr(x_actor, new_actions)
        q_c_pi = self.qc(x_actor, new_actions) if self.qc is not None else None
        loss_actor = actor_loss(log_prob, q_r_pi, alpha, q_c_pi, lam)
        if cfg.scale_actor_loss:  # SAC-Lag (OmniSafe): (Eq. 9) / (1 + lambda)
            loss_actor = loss_actor / (1.0 + lam)
        loss_alpha = alpha_loss(self.log_alpha, log_prob, self.target_entropy)
        # disjoint parameters, independent losses: the sum's gradient is each loss's own; no
        # gradient into the critics (``inputs``), none from Eq. 10 into the actor (detached log pi)
        self.actor_optimizer.zero_grad(set_to_none=True)
        (loss_actor + loss_alpha).backward(inputs=self._policy_params)
        self.actor_optimizer.step()
        metrics = {"losses/qr": loss_qr.detach(), "losses/actor": loss_actor.detach(),
                   "losses/alpha": loss_alpha.detach(), "values/qr": q_r.detach().mean(),
                   "values/entropy": -log_prob.detach().mean()}  # fmt: skip
        if self.lagrange is not None:
            q_c_mean = q_c_pi.detach().mean(0)
            if cfg.lambda_from == "q_cost":  # else the loop updates it from episode costs
                metrics["losses/lambda"] = self.lagrange.update(q_c_mean, d_q)
            metrics["losses/qc"] = loss_qc.detach()
            metrics["constraint/qc_pi"] = q_c_mean.mean()

        # -- lines 14-15: Polyak averaging of the targets
        with torch.no_grad():
            torch._foreach_lerp_(self._target, self._online, cfg.tau)
        return metrics

    def policy_module(self) -> DeterministicActor:
        """The deterministic actor (shares parameters with this agent)."""
        return DeterministicActor(self.encoder, self.actor, input_order(self.obs_shapes))

    def optimizer_state(self) -> dict[str, Any]:
        state = {
            "critic": self.critic_optimizer.state_dict(),
            "actor": self.actor_optimizer.state_dict(),
        }
        if self.lagrange is not None:
            state["lambda"] = self.lagrange.optimizer.state_dict()
        return state

    def load_optimizer_state(self, state: dict[str, Any]) -> None:
        self.critic_optimizer.load_state_dict(state["critic"])
        actor = state["actor"]
        if "alpha" in state:  # checkpoints before the actor and alpha optimisers were merged
            n = len(actor["param_groups"][0]["params"])
            alpha = state["alpha"]
            actor = {"state": {**actor["state"], **{n + int(k): v for k, v in alpha["state"].items()}},
                     "param_groups": [actor["param_groups"][0], {**alpha["param_groups"][0], "params": [n]}]}  # fmt: skip
        self.actor_optimizer.load_state_dict(actor)
        if self.lagrange is not None:
            self.lagrange.optimizer.load_state_dict(state["lambda"])


# ---------------------------------------------------------------------------------- training loop
COLUMNS = (
    "time/elapsed_s", "perf/sps", "perf/updates", "perf/updates_per_s",
    "charts/episodic_return", "charts/episodic_cost", "charts/episodic_length", "charts/success_rate",
    "charts/collision_rate", "charts/timeout_rate", "charts/episodes", "charts/density", "charts/alpha",
    "constraint/lambda", "constraint/d", "constraint/d_q", "constraint/stage", "constraint/qc_pi",
    "constraint/episode_cost",
    "losses/qr", "losses/qc", "losses/actor", "losses/alpha", "losses/lambda", "values/qr",
    "values/entropy", "eval/return", "eval/cost", "eval/length", "eval/success_rate",
    "eval/collision_rate", "eval/timeout_rate",
)  # fmt: skip


def policy_meta(
    algo: str, run: RunConfig, cfg: CSACConfig, env: TorchVecEnv, global_step: int
) -> dict[str, Any]:
    """What :func:`safenav.algos.policy.load_policy` needs to rebuild and describe the actor."""
    env_cfg = getattr(env.envs.unwrapped, "cfg", None)
    return {"format_version": POLICY_FORMAT_VERSION, "algo": algo, "env_id": run.env,
            "env_config": to_dict(env_cfg.replace(density=1.0)) if env_cfg is not None else None,
            "obs_shapes": {k: list(v) for k, v in env.obs_shapes.items()}, "action_dim": env.action_dim,
            "action_low": env._low.tolist(), "action_high": env._high.tolist(), "net": to_dict(cfg.net),
            "global_step": int(global_step)}  # fmt: skip


def train(algo: str, run: RunConfig, cfg: CSACConfig, run_dir: Path, resume: bool = False,
          progress: bool = True) -> dict[str, float]:  # fmt: skip
    """Train ``algo`` (``"csac"`` or ``"sac"``) into ``run_dir`` (prepared by the caller; resumed
    from its ``checkpoint.pt`` when ``resume``). Returns the final metrics row."""
    from safenav.common.progress import ProgressDisplay

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    enable_sigint()
    torch.set_num_threads(run.torch_threads or max(1, torch.get_num_threads()))
    torch.set_float32_matmul_precision(run.matmul_precision)
    device = torch.device(run.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        from safenav.errors import SafenavError

        raise SafenavError(
            "--device cuda: CUDA is not available on this machine (use --device cpu)"
        )
    ckpt_path = run_dir / "checkpoint.pt"
    ckpt = load_training_checkpoint(ckpt_path, algo, map_location=device) if resume else None
    seed_everything(run.seed)

    # -- env, curricula, agent, buffer
    density = DensityCurriculum(run.density, run.total_steps)
    nav = is_safenav(run.env)
    env_kwargs = {"density": density.density} if nav else {}
    env = TorchVecEnv(
        make_vec_env(run.env, run.num_envs, run.device, run.preset, **env_kwargs), device
    )
    eval_env = None
    if run.eval_every > 0:
        eval_kwargs = {"density": run.density.end} if nav else {}
        eval_env = TorchVecEnv(make_vec_env(run.env, min(run.eval_episodes, 32), run.device, run.preset,
                                            **eval_kwargs), device)  # fmt: skip
    agent = CSAC(env.obs_shapes, env.action_dim, cfg).to(device)
    n_step = cfg.constrained and cfg.cost_n_step > 1
    buffer = ReplayBuffer(min(cfg.buffer_size, max(run.total_steps, cfg.batch_size)), env.obs_shapes,
                          env.action_dim, device, n_step=n_step)  # fmt: skip
    nstep = NStepWindow(cfg.cost_n_step, cfg.gamma) if n_step else None
    curriculum = ConstraintCurriculum(cfg.curriculum)
    horizon = cfg.cost_horizon or env_horizon(env.envs)
    measured_scale = (MeasuredCostScale(fallback=episode_cost_to_q_scale(1.0, cfg.gamma, horizon))
                      if cfg.constrained and cfg.cost_scale == "measured" else None)  # fmt: skip

    def d_q_now() -> float:
        """The threshold of Eq. 11 on the Q_C scale for the curriculum's current d."""
        if measured_scale is not None:
            return measured_scale.d_q(curriculum.d)
        return episode_cost_to_q_scale(curriculum.d, cfg.gamma, horizon)

    global_step, updates, elapsed0, update_debt = 0, 0, 0.0, 0.0
    warmup_until = cfg.learning_starts
    if ckpt is not None:
        restore_agent(agent, ckpt, ckpt_path)
        curriculum.load_state_dict(ckpt["curriculum"])
        if measured_scale is not None and ckpt.get("cost_scale"):
            measured_scale.load_state_dict(ckpt["cost_scale"])
        density.load_state_dict(ckpt["density"])
        global_step, updates, elapsed0 = ckpt["global_step"], ckpt["updates"], ckpt["elapsed_s"]
        update_debt = ckpt.get("update_debt", 0.0)
        set_rng_state(ckpt["rng"])
        if "buffer" in ckpt:
            buffer.load_state_dict(ckpt["buffer"])
            if nstep is not None and ckpt.get("nstep_window"):
                nstep.load_state_dict(ckpt["nstep_window"])
        # without the buffer: refill it with the current policy before updating again
        warmup_until = (
            global_step
            if len(buffer) >= cfg.batch_size
            else global_step + max(cfg.learning_starts, cfg.batch_size)
        )
    env.set_density(density.density)
    logger = RunLogger(
        run_dir, COLUMNS, run.tensorboard, resume_step=global_step if resume else None
    )
    logger.event(
        global_step,
        "resume" if resume else "start",
        algo=algo,
        density=density.density,
        d=curriculum.d,
    )
    guard = RunGuard(run_dir, logger, agent, last_saved=global_step if ckpt is not None else None)
    best = BestPolicy.for_run(run_dir, run.keep_policies, ckpt)

    def policy_state() -> dict[str, Any]:
        return checkpoint_policy_state(algo, global_step, updates, elapsed0 + time.perf_counter() - t0,
                                       {"algo": algo, "run": to_dict(run), "csac": to_dict(cfg)},
                                       policy_meta(algo, run, cfg, env, global_step), agent.policy_module())  # fmt: skip

    def checkpoint() -> None:
        state = policy_state() | {
            "update_debt": update_debt, "agent": agent.state_dict(), "optimizers": agent.optimizer_state(),
            "curriculum": curriculum.state_dict(), "density": density.state_dict(), "rng": rng_state(),
            "best": best.state_dict()}  # fmt: skip
        if measured_scale is not None:
            state["cost_scale"] = measured_scale.state_dict()
        if run.save_buffer:
            state["buffer"] = buffer.state_dict()
            if nstep is not None:
                state["nstep_window"] = nstep.state_dict()
        guard.save(global_step, state)  # refuses non-finite weights: keeps the last good file

    # -- the loop (Algorithm 1): one vector step = num_envs transitions
    window: dict[str, list[float]] = {}
    recent: dict[str, deque] = {k: deque(maxlen=100) for k in ("success", "collision", "return")}
    sums: dict[str, torch.Tensor] = {}
    n_sums = 0
    t0 = time.perf_counter()
    t_log, step_log, upd_log = t0, global_step, updates
    next_log = (global_step // run.log_every + 1) * run.log_every
    next_eval = (global_step // run.eval_every + 1) * run.eval_every if run.eval_every else math.inf
    next_ckpt = (global_step // run.checkpoint_every + 1) * run.checkpoint_every
    refresh_every = run.map_refresh_every if nav else 0
    refresh = global_step // refresh_every if refresh_every else 0
    obs = env.reset(seed=run.train_env_seed(refresh) if nav else run.seed + global_step)
    display = ProgressDisplay(
        run.total_steps, global_step, enabled=progress, title=f"{algo} {run.env}"
    )
    row: dict[str, float] = {}
    episode_lambda = cfg.constrained and cfg.lambda_from == "episode_cost"
    lam_costs: list[float] = []  # episode costs since the last lambda update (SAC-Lag)
    next_lambda = (global_step // cfg.lambda_every + 1) * cfg.lambda_every
    try:
        while global_step < run.total_steps:
            # lines 5-10: warm-up with uniform random actions, then a ~ pi(.|s)
            if global_step < cfg.learning_starts and not resume:
                actions = torch.rand(env.num_envs, env.action_dim, device=device) * 2.0 - 1.0
            else:
                actions = agent.act(obs)
            step = env.step(actions)
            transition = Batch(
                obs, actions, step.reward, step.cost, step.real_next_obs, step.terminated
            )
            # with n-step cost targets a transition enters the buffer n vector steps later
            released = (
                (transition, step.valid)
                if nstep is None
                else nstep.push(transition, step.truncated, step.valid)
            )
            if released is not None:
                batch, valid = released  # add() takes valid between the one- and n-step fields
                buffer.add(*batch[:6], valid, *batch[6:])
            obs = step.next_obs
            global_step += env.num_envs

            if step.episodes is not None:
                ep = {k: v.tolist() for k, v in step.episodes.items()}
                for k, vs in ep.items():
                    window.setdefault(k, []).extend(vs)
                for k in recent:
                    recent[k].extend(ep[k])
                curriculum.observe(ep["cost"])
                if measured_scale is not None:
                    measured_scale.observe_episodes(ep["cost"])
                if episode_lambda:
                    lam_costs.extend(ep["cost"])
                density.observe(ep["success"])
            change = curriculum.step(global_step)
            if change is not None:
                logger.event(global_step, "curriculum", **change)
                display.note(
                    f"step {global_step}: d {change['d_old']:.3g} -> {change['d']:.3g} ({change['stage']})"
                )
            if refresh_every and global_step // refresh_every > refresh:  # new maps, new episodes
                refresh = global_step // refresh_every
                obs = env.reset(seed=run.train_env_seed(refresh))
                if nstep is not None:
                    nstep.cut()
            new_density = density.step(global_step)
            if new_density is not None and env.set_density(new_density):
                logger.event(global_step, "density", density=new_density)

            # SAC-Lag (OmniSafe): lambda from the mean episode cost J_c against d, every lambda_every
            if episode_lambda and global_step >= next_lambda:
                while next_lambda <= global_step:
                    next_lambda += cfg.lambda_every
                if lam_costs and global_step >= warmup_until:  # else keep collecting
                    j_c = sum(lam_costs) / len(lam_costs)
                    loss = agent.lagrange.update(torch.tensor([j_c], device=device), curriculum.d)
                    row.update({"losses/lambda": float(loss), "constraint/episode_cost": j_c})
                    lam_costs = []

            # lines 11-15: gradient updates
            # (len: an n-step window delays the first rows of the buffer)
            if global_step >= warmup_until and len(buffer):
                update_debt += env.num_envs * cfg.updates_per_step
                d_q = d_q_now()
                while update_debt >= 1.0:
                    update_debt -= 1.0
                    metrics = agent.update(buffer.sample(cfg.batch_size), d_q)
                    updates += 1
                    if measured_scale is not None:
                        measured_scale.observe_q(float(metrics["constraint/qc_pi"]))
                    for k, v in metrics.items():
                        sums[k] = sums[k] + v if k in sums else v.clone()
                    n_sums += 1

            if global_step >= next_eval and eval_env is not None:
                next_eval += run.eval_every
                ev, note = periodic_evaluation(eval_env, lambda o: agent.act(o, deterministic=True),
                                               run.eval_episodes, global_step, logger, best, policy_state)  # fmt: skip
                row.update(ev)
                display.note(note)

            if global_step >= next_log or global_step >= run.total_steps:
                next_log += run.log_every
                now = time.perf_counter()
                row.update({
                    "time/elapsed_s": elapsed0 + now - t0,
                    "perf/sps": (global_step - step_log) / max(now - t_log, 1e-9),
                    "perf/updates": updates,
                    "perf/updates_per_s": (updates - upd_log) / max(now - t_log, 1e-9),
                    **episode_charts(window),
                    "charts/density": density.density if nav else math.nan,
                    "charts/alpha": float(agent.log_alpha.detach().exp()),
                })  # fmt: skip
                if cfg.constrained:
                    row.update({"constraint/lambda": float(agent.lam), "constraint/d": curriculum.d,
                                "constraint/d_q": d_q_now(),
                                "constraint/stage": curriculum.stage})  # fmt: skip
                update_metrics = {k: float(v) / n_sums for k, v in sums.items()} if n_sums else {}
                row.update(update_metrics)
                logger.log(global_step, row)
                guard.check(global_step, update_metrics)  # NaN/Inf: stop, keep checkpoint.pt
                display.metrics(global_step, row, recent, curriculum.d if cfg.constrained else None)
                window, sums, n_sums, row = {}, {}, 0, {}
                t_log, step_log, upd_log = now, global_step, updates
            display.advance(global_step)

            if global_step >= next_ckpt:
                next_ckpt += run.checkpoint_every
                checkpoint()
    except BaseException as err:  # Ctrl-C: checkpoint; divergence, errors: an event (stopping.py)
        guard.stopped(err, global_step, checkpoint)
        raise
    finally:
        display.close()
    checkpoint()
    logger.event(global_step, "end", updates=updates)
    logger.close()
    env.close()
    if eval_env is not None:
        eval_env.close()
    return run_summary(global_step, updates, recent)


def write_config(
    run_dir: Path, algo: str, run: RunConfig, cfg: CSACConfig, recipe: dict | None = None
) -> None:
    """``config.json`` of a csac run (see :func:`safenav.common.runs.write_run_config`)."""
    write_run_config(run_dir, algo, run, "csac", cfg, recipe)


__all__ = ["CSAC", "COLUMNS", "CSACConfig", "train", "write_config"]
