"""PPO as NavRL trains it and, with ``constrained=True``, PPO-Lagrangian: one file, read top to
bottom.

One iteration (the pure pieces are in :mod:`safenav.algos.ppo_losses`):

1. rollout: ``rollout_steps`` vector steps with ``a ~ Beta`` mapped to ``[-1, 1]``, storing
   ``log pi(a|s)`` and ``V(s)``; where an episode is *truncated* the value of its true final
   observation ``V(final_obs)`` is stored too -> :func:`collect_rollout`
2. (PPO-Lag) ``lambda <- max(0, lambda + Adam step on (J_c - d))`` with ``J_c`` the mean cost of the
   episodes that ended in the rollout -> :class:`~safenav.common.lagrange.Lagrange`, in :func:`train`
3. GAE of reward (and cost): ``delta_t = r_t + gamma (1 - term_t) V(s'_t) - V(s_t)``,
   ``A_t = delta_t + gamma lam (1 - done_t) A_{t+1}`` -> :func:`~safenav.algos.ppo_losses.gae`
4. value targets ``R = A + V`` normalised by running return statistics (NavRL's ValueNorm)
5. actor advantage: standardised ``A_R`` (PPO) or ``(A_R - lambda A_C) / (1 + lambda)`` with
   ``A_C`` centred (PPO-Lag) -> :func:`~safenav.algos.ppo_losses.lagrangian_advantage`
6. ``epochs`` x ``num_minibatches`` Adam steps on
   ``L = L_clip(pi) - c_H H[pi] + L_clip(V) (+ L_clip(V_C))`` with gradient-norm clipping
   -> :meth:`PPO.update`

docs/algorithms.md has the equations, every logged metric and where each default comes from.
"""

from __future__ import annotations

import math
import time
from collections import deque
from pathlib import Path
from typing import Any

import torch
from torch import nn

from safenav.algos.csac import policy_meta as csac_policy_meta
from safenav.algos.ppo_config import PPOConfig
from safenav.algos.ppo_losses import (
    beta_entropy,
    beta_log_prob,
    beta_mean_action,
    clipped_policy_loss,
    clipped_value_loss,
    gae,
    lagrangian_advantage,
    normalize,
    sample_beta_action,
)
from safenav.common.checkpoint import (
    load_training_checkpoint,
    restore_agent,
    rng_state,
    seed_everything,
    set_rng_state,
)
from safenav.common.checkpoint import policy_state as checkpoint_policy_state
from safenav.common.config import RunConfig, to_dict
from safenav.common.curriculum import ConstraintCurriculum, DensityCurriculum
from safenav.common.envs import TorchVecEnv, is_safenav, make_vec_env
from safenav.common.evaluation import BestPolicy, periodic_evaluation
from safenav.common.lagrange import Lagrange
from safenav.common.logger import RunLogger
from safenav.common.rollout import Rollout, ValueNorm
from safenav.common.runs import episode_charts, run_summary, write_run_config
from safenav.common.stopping import RunGuard, enable_sigint
from safenav.errors import SafenavError
from safenav.nn.beta import POLICY_HEAD, BetaActorCritic, BetaDeterministicActor
from safenav.nn.networks import input_order
from safenav.nn.optim import adam


class PPO(nn.Module):
    """Actor-critic, value normalisation, optimiser and the PPO update (PPO-Lag when
    ``cfg.constrained``: a second value head for cost and a Lagrange multiplier)."""

    def __init__(
        self, obs_shapes: dict[str, tuple[int, ...]], action_dim: int, cfg: PPOConfig
    ) -> None:
        super().__init__()
        self.cfg, self.obs_shapes, self.action_dim = cfg, dict(obs_shapes), action_dim
        self.num_values = 2 if cfg.constrained else 1  # column 0 reward, column 1 cost
        self.model = BetaActorCritic(obs_shapes, action_dim, cfg.net, self.num_values)
        self.value_norm = ValueNorm(self.num_values, cfg.value_norm_beta, cfg.value_norm)
        # One Adam over actor, critic and extractor: NavRL's three Adams share lr 5e-4, and
        # Adam's per-parameter statistics make that the same update (fused kernel: nn.optim.adam).
        self.optimizer = adam(self.model.parameters(), lr=cfg.lr)
        self.lagrange = (
            Lagrange(cfg.init_lambda, cfg.lambda_lr, cfg.lambda_max) if cfg.constrained else None
        )

    @property
    def lam(self) -> torch.Tensor:
        return self.lagrange.value if self.lagrange is not None else torch.zeros(())

    @torch.no_grad()
    def act(self, obs: dict[str, torch.Tensor], deterministic: bool = False):
        """``(action, log_prob, values)``: action in ``[-1, 1]^A``, its log-density, and the
        denormalised values ``(N, K)`` of ``obs``."""
        alpha, beta, values = self.model(obs)
        action = beta_mean_action(alpha, beta) if deterministic else sample_beta_action(alpha, beta)
        return action, beta_log_prob(alpha, beta, action), self.value_norm.denormalize(values)

    @torch.no_grad()
    def value(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """Denormalised values ``(N, K)``."""
        return self.value_norm.denormalize(self.model.values(obs))

    def update(self, rollout: Rollout) -> dict[str, torch.Tensor]:
        """Steps 3-6 of the module docstring on a finished rollout; detached scalar metrics."""
        cfg = self.cfg
        # -- 3. GAE on every signal (reward, cost) at once: (T, N, K)
        term, trunc = rollout.terminated.unsqueeze(-1), rollout.truncated.unsqueeze(-1)
        adv, returns = gae(rollout.rewards, rollout.values, rollout.next_values, term, trunc,
                           cfg.gamma, cfg.gae_lambda)  # fmt: skip
        # -- 4. value targets on the normalised scale; old outputs on the scale they were made
        old_values = self.value_norm.normalize(rollout.values)
        self.value_norm.update(returns)
        targets = self.value_norm.normalize(returns)
        # -- 5. the advantage the actor follows
        adv_r = normalize(adv[..., 0]) if cfg.normalize_advantages else adv[..., 0]
        if self.lagrange is not None:
            adv_c = normalize(adv[..., 1], scale=False) if cfg.normalize_advantages else adv[..., 1]
            adv_actor = lagrangian_advantage(adv_r, adv_c, self.lam)
        else:
            adv_actor = adv_r

        # -- 6. epochs of minibatch steps
        obs = rollout.flat_obs()
        actions, old_log_probs = rollout.actions.flatten(0, 1), rollout.log_probs.flatten(0, 1)
        adv_actor, old_values, targets = (
            adv_actor.flatten(0, 1),
            old_values.flatten(0, 1),
            targets.flatten(0, 1),
        )
        n = actions.shape[0]
        size = max(1, n // cfg.num_minibatches)
        actor_params, critic_params = self.model.actor_parameters(), self.model.critic_parameters()
        sums: dict[str, torch.Tensor] = {}
        steps = 0
        for _ in range(cfg.epochs):
            perm = torch.randperm(n, device=actions.device)
            kl_sum, kl_n = torch.zeros((), device=actions.device), 0
            for start in range(0, size * cfg.num_minibatches, size):
                idx = perm[start : start + size]
                alpha, beta, values = self.model({k: v[idx] for k, v in obs.items()})
                log_prob = beta_log_prob(alpha, beta, actions[idx])
                loss_pi = clipped_policy_loss(
                    log_prob, old_log_probs[idx], adv_actor[idx], cfg.clip
                )
                entropy = beta_entropy(alpha, beta).mean()
                loss_v = [clipped_value_loss(values[:, k], old_values[idx, k], targets[idx, k],
                                             cfg.value_clip) for k in range(self.num_values)]  # fmt: skip
                loss = loss_pi - cfg.entropy_coef * entropy + sum(loss_v)
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                nn.utils.clip_grad_norm_(actor_params, cfg.max_grad_norm)
                nn.utils.clip_grad_norm_(critic_params, cfg.max_grad_norm)
                self.optimizer.step()
                with torch.no_grad():
                    log_ratio = log_prob - old_log_probs[idx]
                    approx_kl = ((log_ratio.exp() - 1.0) - log_ratio).mean()  # Schulman's k3
                    clipped = ((log_ratio.exp() - 1.0).abs() > cfg.clip).float().mean()
                metrics = {"losses/actor": loss_pi, "losses/value": loss_v[0], "losses/entropy": entropy,
                           "losses/approx_kl": approx_kl, "losses/clip_fraction": clipped}  # fmt: skip
                if self.lagrange is not None:
                    metrics["losses/value_cost"] = loss_v[1]
                for k, v in metrics.items():
                    sums[k] = sums[k] + v.detach() if k in sums else v.detach().clone()
                steps += 1
                kl_sum, kl_n = kl_sum + approx_kl, kl_n + 1
            if cfg.target_kl is not None and float(kl_sum / kl_n) > cfg.target_kl:
                break
        out = {k: v / steps for k, v in sums.items()}
        ret, val = returns[..., 0].flatten(), rollout.values[..., 0].flatten()
        out["values/value"] = val.mean()
        out["values/explained_variance"] = 1.0 - (ret - val).var() / ret.var().clamp(min=1e-8)
        if self.lagrange is not None:
            out["values/value_cost"] = rollout.values[..., 1].mean()
        out["perf/gradient_steps"] = torch.tensor(float(steps))
        return out

    def policy_module(self) -> BetaDeterministicActor:
        """The deterministic actor (the Beta mean), sharing parameters with this agent."""
        return BetaDeterministicActor(
            self.model.actor_body, self.model.policy_head, input_order(self.obs_shapes)
        )

    def optimizer_state(self) -> dict[str, Any]:
        state = {"model": self.optimizer.state_dict()}
        if self.lagrange is not None:
            state["lambda"] = self.lagrange.optimizer.state_dict()
        return state

    def load_optimizer_state(self, state: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(state["model"])
        if self.lagrange is not None:
            self.lagrange.optimizer.load_state_dict(state["lambda"])


# ------------------------------------------------------------------------------------ rollout
def collect_rollout(env: TorchVecEnv, agent: PPO, rollout: Rollout,
                    obs: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], list[dict[str, torch.Tensor]]]:  # fmt: skip
    """Fill ``rollout`` (step 1 of the module docstring) starting from ``obs``; returns the
    observation to continue from and the episode statistics of the episodes that ended."""
    episodes = []
    for _ in range(rollout.steps):
        action, log_prob, values = agent.act(obs)
        step = env.step(action)
        if not bool(step.valid.all()):
            raise SafenavError(
                "PPO needs a SAME_STEP autoreset vector env (make_vec_env builds one)"
            )
        final_values = None
        cut = step.truncated & ~step.terminated  # time limit: bootstrap from the final observation
        if bool(cut.any()):
            ids = cut.nonzero().squeeze(-1)
            final_values = torch.zeros_like(values)
            final_values[ids] = agent.value({k: v[ids] for k, v in step.real_next_obs.items()})
        signals = (
            torch.stack([step.reward, step.cost], -1)
            if agent.num_values == 2
            else step.reward.unsqueeze(-1)
        )
        rollout.add(obs, action, log_prob, values, signals, step.terminated, step.truncated,
                    final_values)  # fmt: skip
        obs = step.next_obs
        if step.episodes is not None:
            episodes.append(step.episodes)
    rollout.finish(agent.value(obs))
    return obs, episodes


# ------------------------------------------------------------------------------ training loop
COLUMNS = (
    "time/elapsed_s", "perf/sps", "perf/updates", "perf/updates_per_s", "perf/rollouts",
    "charts/episodic_return", "charts/episodic_cost", "charts/episodic_length", "charts/success_rate",
    "charts/collision_rate", "charts/timeout_rate", "charts/episodes", "charts/density",
    "constraint/lambda", "constraint/d", "constraint/stage", "constraint/episode_cost",
    "losses/actor", "losses/value", "losses/value_cost", "losses/entropy", "losses/approx_kl",
    "losses/clip_fraction", "losses/lambda", "values/value", "values/value_cost",
    "values/explained_variance", "eval/return", "eval/cost", "eval/length", "eval/success_rate",
    "eval/collision_rate", "eval/timeout_rate",
)  # fmt: skip


def policy_meta(algo: str, run: RunConfig, cfg: PPOConfig, env: TorchVecEnv,
                global_step: int) -> dict[str, Any]:  # fmt: skip
    """CSAC's policy metadata plus ``policy_head: "beta"`` (what ``load_policy`` dispatches on)."""
    return {**csac_policy_meta(algo, run, cfg, env, global_step), "policy_head": POLICY_HEAD}


def train(algo: str, run: RunConfig, cfg: PPOConfig, run_dir: Path, resume: bool = False,
          progress: bool = True) -> dict[str, float]:  # fmt: skip
    """Train ``algo`` (``"ppo"`` or ``"ppo_lag"``) into ``run_dir`` (prepared by the caller;
    resumed from its ``checkpoint.pt`` when ``resume``). Returns the final metrics."""
    from safenav.common.progress import ProgressDisplay

    run_dir = Path(run_dir)
    enable_sigint()
    torch.set_num_threads(run.torch_threads or max(1, torch.get_num_threads()))
    torch.set_float32_matmul_precision(run.matmul_precision)
    device = torch.device(run.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SafenavError(
            "--device cuda: CUDA is not available on this machine (use --device cpu)"
        )
    ckpt_path = run_dir / "checkpoint.pt"
    ckpt = load_training_checkpoint(ckpt_path, algo, map_location=device) if resume else None
    seed_everything(run.seed)

    # -- env, curricula, agent, rollout storage
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
    agent = PPO(env.obs_shapes, env.action_dim, cfg).to(device)
    rollout = Rollout(cfg.rollout_steps, env.num_envs, env.obs_shapes, env.action_dim,
                      agent.num_values, device)  # fmt: skip
    curriculum = ConstraintCurriculum(cfg.curriculum)

    global_step, updates, rollouts, elapsed0 = 0, 0, 0, 0.0
    if ckpt is not None:
        restore_agent(agent, ckpt, ckpt_path)
        curriculum.load_state_dict(ckpt["curriculum"])
        density.load_state_dict(ckpt["density"])
        global_step, updates, elapsed0 = ckpt["global_step"], ckpt["updates"], ckpt["elapsed_s"]
        rollouts = ckpt.get("rollouts", 0)
        set_rng_state(ckpt["rng"])
    env.set_density(density.density)
    logger = RunLogger(
        run_dir, COLUMNS, run.tensorboard, resume_step=global_step if resume else None
    )
    logger.event(global_step, "resume" if resume else "start", algo=algo, density=density.density,
                 d=curriculum.d)  # fmt: skip
    guard = RunGuard(run_dir, logger, agent, last_saved=global_step if ckpt is not None else None)
    best = BestPolicy.for_run(run_dir, run.keep_policies, ckpt)

    def policy_state() -> dict[str, Any]:
        return checkpoint_policy_state(algo, global_step, updates, elapsed0 + time.perf_counter() - t0,
                                       {"algo": algo, "run": to_dict(run), "ppo": to_dict(cfg)},
                                       policy_meta(algo, run, cfg, env, global_step), agent.policy_module())  # fmt: skip

    def checkpoint() -> None:
        state = policy_state() | {
            "rollouts": rollouts, "agent": agent.state_dict(), "optimizers": agent.optimizer_state(),
            "curriculum": curriculum.state_dict(), "density": density.state_dict(), "rng": rng_state(),
            "best": best.state_dict()}  # fmt: skip
        guard.save(global_step, state)  # refuses non-finite weights: keeps the last good file

    # -- the loop: rollout, lambda, update; curricula, map refreshes and density at rollout edges
    window: dict[str, list[float]] = {}
    recent: dict[str, deque] = {k: deque(maxlen=100) for k in ("success", "collision", "return")}
    sums: dict[str, torch.Tensor] = {}
    n_sums, row = 0, {}
    lam_sums, lam_n = {"losses/lambda": 0.0, "constraint/episode_cost": 0.0}, 0
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
    try:
        while global_step < run.total_steps:
            # 1. rollout
            obs, episodes = collect_rollout(env, agent, rollout, obs)
            global_step += rollout.steps * env.num_envs
            rollouts += 1
            ep_costs: list[float] = []
            for e in episodes:
                ep = {k: v.tolist() for k, v in e.items()}
                for k, vs in ep.items():
                    window.setdefault(k, []).extend(vs)
                for k in recent:
                    recent[k].extend(ep[k])
                ep_costs.extend(ep["cost"])
                curriculum.observe(ep["cost"])
                density.observe(ep["success"])
            # 2. lambda from the mean episode cost J_c of this rollout against d
            if agent.lagrange is not None and ep_costs:
                j_c = torch.tensor([sum(ep_costs) / len(ep_costs)], device=device)
                lam_sums["losses/lambda"] += float(agent.lagrange.update(j_c, curriculum.d))
                lam_sums["constraint/episode_cost"] += float(j_c[0])
                lam_n += 1
            # 3-6. the update
            metrics = agent.update(rollout)
            updates += int(metrics.pop("perf/gradient_steps"))
            for k, v in metrics.items():
                sums[k] = sums[k] + v if k in sums else v.clone()
            n_sums += 1

            change = curriculum.step(global_step)
            if change is not None:
                logger.event(global_step, "curriculum", **change)
                display.note(f"step {global_step}: d {change['d_old']:.3g} -> {change['d']:.3g} ({change['stage']})")  # fmt: skip
            if refresh_every and global_step // refresh_every > refresh:  # new maps, new episodes
                refresh = global_step // refresh_every
                obs = env.reset(seed=run.train_env_seed(refresh))
            new_density = density.step(global_step)
            if new_density is not None and env.set_density(new_density):
                logger.event(global_step, "density", density=new_density)

            if global_step >= next_eval and eval_env is not None:
                while next_eval <= global_step:
                    next_eval += run.eval_every
                ev, note = periodic_evaluation(eval_env, lambda o: agent.act(o, deterministic=True)[0],
                                               run.eval_episodes, global_step, logger, best, policy_state)  # fmt: skip
                row.update(ev)
                display.note(note)

            if global_step >= next_log or global_step >= run.total_steps:
                while next_log <= global_step:
                    next_log += run.log_every
                now = time.perf_counter()
                row.update({
                    "time/elapsed_s": elapsed0 + now - t0,
                    "perf/sps": (global_step - step_log) / max(now - t_log, 1e-9),
                    "perf/updates": updates,
                    "perf/updates_per_s": (updates - upd_log) / max(now - t_log, 1e-9),
                    "perf/rollouts": rollouts,
                    **episode_charts(window),
                    "charts/density": density.density if nav else math.nan,
                })  # fmt: skip
                if cfg.constrained:
                    row.update({"constraint/lambda": float(agent.lam), "constraint/d": curriculum.d,
                                "constraint/stage": curriculum.stage})  # fmt: skip
                update_metrics = {k: float(v) / n_sums for k, v in sums.items()} if n_sums else {}
                row.update(update_metrics)
                row.update({k: v / lam_n for k, v in lam_sums.items()} if lam_n else {})
                logger.log(global_step, row)
                guard.check(global_step, update_metrics)  # NaN/Inf: stop, keep checkpoint.pt
                display.metrics(global_step, row, recent, curriculum.d if cfg.constrained else None)
                window, sums, n_sums, row = {}, {}, 0, {}
                lam_sums, lam_n = dict.fromkeys(lam_sums, 0.0), 0
                t_log, step_log, upd_log = now, global_step, updates
            display.advance(global_step)

            if global_step >= next_ckpt:
                while next_ckpt <= global_step:
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
    run_dir: Path, algo: str, run: RunConfig, cfg: PPOConfig, recipe: dict | None = None
) -> None:
    """``config.json`` of a ppo run (see :func:`safenav.common.runs.write_run_config`)."""
    write_run_config(run_dir, algo, run, "ppo", cfg, recipe)


__all__ = ["COLUMNS", "PPO", "PPOConfig", "collect_rollout", "train", "write_config"]
