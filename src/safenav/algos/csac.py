"""Constrained Soft Actor-Critic (CSAC, paper III-B, Algorithm 1) and, with ``constrained=False``,
plain SAC: one file, read top to bottom.

Algorithm 1 <-> code (the equations are pure functions in :mod:`safenav.algos.losses`):

1-2   actor, reward critics Q_R (min target), cost critics Q_C (mean target); targets hard-copied
      -> ``CSAC.__init__`` (``copy.deepcopy``)
3     alpha (``log_alpha``), lambda (:class:`~safenav.common.lagrange.Lagrange`); replay buffer
      -> ``CSACLearner.__init__``
5-8   warm-up: ``learning_starts`` env steps of uniform random actions -> ``CSACLearner.collect``
10    act with ``a ~ pi(.|s)``, store ``(s, a, r, c, s', terminated)`` -> ``CSACLearner.collect``
      (beyond the paper: ``action_noise_beta`` > 0 samples with colored noise, ``common.colored_noise``)
11    sample a minibatch -> ``CSACLearner.update`` (``ReplayBuffer.sample``)
12    targets Eqs. 5-6, critic losses Eqs. 7-8 -> ``CSAC.update`` (first block)
13    actor Eq. 9, alpha Eq. 10, lambda Eq. 11, in the same step -> ``CSAC.update`` (second block)
14-15 Polyak averaging of every target parameter -> ``CSAC.update`` (last line)

:class:`CSACLearner` is what the shared training loop (:mod:`safenav.training`) calls: it owns the
replay side (buffer, n-step window, warm-up, updates per env step, SAC-Lag's episode-cost lambda).
Around it (paper III-C, Fig. 2) the loop runs the constraint curriculum, which sets ``d``, and the
density curriculum, which sets the obstacle density (:mod:`safenav.common.curriculum`).
docs/csac.md has the full equation table, every logged metric, and the measurements behind the
defaults.
"""

from __future__ import annotations

import copy
import math
from collections import deque
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
from safenav.common.buffer import Batch, ReplayBuffer, cat_batches
from safenav.common.colored_noise import ColoredNoise
from safenav.common.config import RunConfig
from safenav.common.curriculum import MeasuredCostScale, episode_cost_to_q_scale
from safenav.common.lagrange import Lagrange, PIDLagrange
from safenav.common.nstep import NStepWindow
from safenav.envs.vector import TorchVecEnv, check_action_space, env_horizon
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
            QEnsemble(
                critic_ex(e_cost), feat, action_dim, net.hidden, e_cost, cfg.cost_critic_output
            )
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
        self.lagrange: Lagrange | PIDLagrange | None = None
        if cfg.constrained and cfg.lambda_update == "pid":
            self.lagrange = PIDLagrange(cfg.pid_kp, cfg.pid_ki, cfg.pid_kd, cfg.pid_d_delay,
                                        cfg.pid_ema, cfg.init_lambda, cfg.lambda_max)  # fmt: skip
        elif cfg.constrained:
            lambda_lr = cfg.lambda_lr if cfg.lambda_from == "q_cost" else cfg.episode_lambda_lr
            self.lagrange = Lagrange(cfg.init_lambda, lambda_lr, cfg.lambda_max)
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
        if cfg.balance_critic_losses and self.qc is not None and self.encoder is not None:
            # running means of the two critic losses (0 = not seen yet), checkpointed with the agent
            self.register_buffer("critic_loss_scale", torch.zeros(2))
        online = [m for m in (self.encoder, self.qr, self.qc) if m is not None]
        target = [m for m in (self.encoder_target, self.qr_target, self.qc_target) if m is not None]
        self._online = [p for m in online for p in m.parameters()]
        self._target = [p for m in target for p in m.parameters()]

    @property
    def lam(self) -> torch.Tensor:
        return self.lagrange.value if self.lagrange is not None else torch.zeros(())

    @torch.no_grad()
    def act(self, obs: dict[str, torch.Tensor], deterministic: bool = False,
            noise: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
        """Actions ``a ~ pi(.|s)`` (``noise``: the ``eps`` of the reparameterised sample, e.g.
        colored noise; None = standard normal), or ``tanh(mean)`` when ``deterministic``."""
        x = self.encoder(obs) if self.encoder is not None else obs
        action, _, mean_action = self.actor.sample(x, noise)
        return mean_action if deterministic else action

    def update(self, batch: Batch, d_q: float = 0.0,
               update_lambda: bool = True) -> dict[str, torch.Tensor]:  # fmt: skip
        """One gradient update (Algorithm 1, lines 12-15); ``d_q`` is the threshold on the Q_C scale;
        ``update_lambda`` False holds lambda (``lambda_warmup_steps``). Returns detached scalar
        metrics."""
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
                                  cfg.cost_discount, cfg.cost_target)  # fmt: skip
        q_r = self.qr(x, actions)
        loss_qr = critic_loss(q_r, y_r)
        loss_critic = loss_qr
        if self.qc is not None:
            loss_qc = critic_loss(self.qc(x, actions, raw=True), y_c)
            if hasattr(self, "critic_loss_scale"):  # beyond the paper: balanced extractor gradients
                loss_critic = self._balanced(loss_qr, loss_qc)
            else:
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
            # else the loop updates it from episode costs
            if cfg.lambda_from == "q_cost" and update_lambda:
                metrics["losses/lambda"] = self.lagrange.update(q_c_mean, d_q)
            metrics["losses/qc"] = loss_qc.detach()
            metrics["constraint/qc_pi"] = q_c_mean.mean()

        # -- lines 14-15: Polyak averaging of the targets
        with torch.no_grad():
            torch._foreach_lerp_(self._target, self._online, cfg.tau)
        return metrics

    def _balanced(self, loss_qr: torch.Tensor, loss_qc: torch.Tensor) -> torch.Tensor:
        """``L_R / sqrt(m_R) + L_C / sqrt(m_C)``, ``m`` running means (rate 0.01) of the detached
        losses (``balance_critic_losses``): each critic's TD errors reach the shared extractor in
        units of their own RMS, so neither critic's value scale decides what the features encode."""
        scale = self.critic_loss_scale
        losses = torch.stack([loss_qr.detach(), loss_qc.detach()])
        scale.copy_(torch.where(scale > 0, 0.99 * scale + 0.01 * losses, losses))
        rms = scale.clamp(min=1e-12).sqrt()
        return loss_qr / rms[0] + loss_qc / rms[1]

    def policy_module(self) -> DeterministicActor:
        """The deterministic actor (shares parameters with this agent)."""
        return DeterministicActor(self.encoder, self.actor, input_order(self.obs_shapes))

    def optimizer_state(self) -> dict[str, Any]:
        state = {
            "critic": self.critic_optimizer.state_dict(),
            "actor": self.actor_optimizer.state_dict(),
        }
        if isinstance(self.lagrange, Lagrange):  # a PID keeps its state in the agent's buffers
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
        if isinstance(self.lagrange, Lagrange):
            self.lagrange.optimizer.load_state_dict(state["lambda"])


# ------------------------------------------------------------------ replay and update schedule
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
"""Every progress.csv column of CSAC, SAC and SAC-Lag (docs/algorithms.md)."""


def store(buffer: ReplayBuffer, window: NStepWindow | None, transition: Batch,
          truncated: torch.Tensor, valid: torch.Tensor) -> None:  # fmt: skip
    """Put one vector step's transitions into ``buffer``; with an n-step ``window`` (n-step cost
    targets) they enter it n vector steps later, with their n-step fields."""
    released = (transition, valid) if window is None else window.push(transition, truncated, valid)
    if released is not None:
        batch, ok = released  # add() takes valid between the one- and n-step fields
        buffer.add(*batch[:6], ok, *batch[6:])


class CSACLearner:
    """CSAC in the shared training loop (:class:`safenav.training.Trainer`): Algorithm 1's data
    side around :meth:`CSAC.update` - the warm-up (lines 5-8), acting and storing (line 10) in a
    replay buffer (with the n-step window), ``updates_per_step`` gradient updates per env step, the
    threshold ``d_Q`` of Eq. 11, and SAC-Lag's lambda from episode costs."""

    section = "csac"
    columns = COLUMNS
    policy_meta: dict[str, Any] = {}

    def __init__(self, env: TorchVecEnv, run: RunConfig, cfg: CSACConfig) -> None:
        if env.num_actions is not None:  # the tanh-squashed Gaussian acts continuously only
            check_action_space(env.envs.single_action_space)
        self.cfg, self.device, self.num_envs = cfg, env.device, env.num_envs
        self.save_buffer = run.save_buffer
        self.agent = CSAC(env.obs_shapes, env.action_dim, cfg).to(env.device)
        n_step = cfg.constrained and cfg.cost_n_step > 1
        self.buffer = ReplayBuffer(min(cfg.buffer_size, max(run.total_steps, cfg.batch_size)),
                                   env.obs_shapes, env.action_dim, env.device, n_step=n_step)  # fmt: skip
        self.nstep = NStepWindow(cfg.cost_n_step, cfg.cost_discount) if n_step else None
        # --csac.planner-share: the planner's flights, a buffer of their own (set_planner_flights)
        self.planner_buffer: ReplayBuffer | None = None
        self.horizon = cfg.cost_horizon or env_horizon(env.envs)
        self.measured_scale = (MeasuredCostScale(fallback=episode_cost_to_q_scale(1.0, cfg.cost_discount, self.horizon),
                                                 span_episodes=cfg.cost_scale_episodes)
                               if cfg.constrained and cfg.cost_scale == "measured" else None)  # fmt: skip
        self.episode_lambda = cfg.constrained and cfg.lambda_from == "episode_cost"
        # SAC-Lag: the episode costs since the last lambda update, or the last lambda_window
        self.lam_costs: deque[float] = deque(maxlen=cfg.lambda_window or None)
        self.next_lambda = cfg.lambda_every
        self.warmup_until, self.update_debt, self.resumed = cfg.learning_starts, 0.0, False
        self.pending: dict[str, float] = {}  # SAC-Lag's lambda step, for the next progress row
        # beyond the paper: colored noise in the rollout actions (Eberhard et al. 2023); 0 = white
        self.noise = (ColoredNoise(cfg.action_noise_beta, env.num_envs, env.action_dim,
                                   env_horizon(env.envs), env.device)
                      if cfg.action_noise_beta > 0 else None)  # fmt: skip

    def d_q(self, d: float) -> float:
        """The threshold of Eq. 11 on the Q_C scale for the curriculum's episode budget ``d``."""
        if self.measured_scale is not None:
            return self.measured_scale.d_q(d)
        return episode_cost_to_q_scale(d, self.cfg.cost_discount, self.horizon)

    def collect(self, env: TorchVecEnv, obs: dict[str, torch.Tensor], global_step: int,
                d: float) -> tuple[dict[str, torch.Tensor], list[dict[str, torch.Tensor]], int]:  # fmt: skip
        """Lines 5-10: one vector step (``num_envs`` transitions) into the buffer, with uniform
        random actions during the warm-up, then ``a ~ pi(.|s)``."""
        if global_step < self.cfg.learning_starts and not self.resumed:
            actions = torch.rand(env.num_envs, env.action_dim, device=self.device) * 2.0 - 1.0
        else:
            noise = self.noise.sample() if self.noise is not None else None
            actions = self.agent.act(obs, noise=noise)
        step = env.step(actions)
        if self.noise is not None:  # a new episode, a new noise sequence
            self.noise.reset(step.terminated | step.truncated)
        transition = Batch(
            obs, actions, step.reward, step.cost, step.real_next_obs, step.terminated
        )
        store(self.buffer, self.nstep, transition, step.truncated, step.valid)
        return step.next_obs, [step.episodes] if step.episodes is not None else [], env.num_envs

    def set_planner_flights(self, flights: list[tuple[Batch, torch.Tensor, torch.Tensor]]) -> None:
        """Keep a planner's flights (``training.planner_flights``: ``(transition, truncated,
        valid)`` per vector step) in a buffer of their own, through an n-step window like the
        replay's; :meth:`sample` then draws ``planner_share`` of each minibatch from them."""
        total = sum(int(t.actions.shape[0]) for t, _, _ in flights)
        buffer = ReplayBuffer(max(total, 1), self.agent.obs_shapes, self.agent.action_dim,
                              self.device, n_step=self.nstep is not None)  # fmt: skip
        window = (NStepWindow(self.cfg.cost_n_step, self.cfg.cost_discount)
                  if self.nstep is not None else None)  # fmt: skip
        for transition, truncated, valid in flights:
            store(buffer, window, transition, truncated, valid)
        if len(buffer) == 0:
            raise ValueError("the planner's flights hold no transition to replay")
        self.planner_buffer = buffer

    def sample(self, batch_size: int) -> Batch:
        """A minibatch of the replay buffer, ``planner_share`` of it (rounded) from the planner's
        flights when there are any (RLPD's symmetric sampling at that share)."""
        if self.planner_buffer is None:
            return self.buffer.sample(batch_size)
        k = round(batch_size * self.cfg.planner_share)
        return cat_batches(self.buffer.sample(batch_size - k), self.planner_buffer.sample(k))

    def observe(self, episodes: dict[str, list[float]]) -> None:
        if self.measured_scale is not None:
            self.measured_scale.observe_episodes(episodes["cost"])
        if self.episode_lambda:
            self.lam_costs.extend(episodes["cost"])

    def maps_changed(self) -> None:
        if self.nstep is not None:  # later steps must not count towards earlier ones
            self.nstep.cut()
        if self.noise is not None:
            self.noise.reset()

    def update(self, global_step: int, d: float) -> tuple[int, list[dict[str, torch.Tensor]]]:
        """SAC-Lag's lambda step when due, then lines 11-15 as often as ``updates_per_step`` asks."""
        cfg = self.cfg
        # SAC-Lag (OmniSafe): lambda from the mean episode cost J_c against d, every lambda_every
        if self.episode_lambda and global_step >= self.next_lambda:
            while self.next_lambda <= global_step:
                self.next_lambda += cfg.lambda_every
            if self.lam_costs and global_step >= max(self.warmup_until, cfg.lambda_warmup_steps):
                j_c = sum(self.lam_costs) / len(self.lam_costs)
                loss = self.agent.lagrange.update(torch.tensor([j_c], device=self.device), d)
                self.pending.update({"losses/lambda": float(loss), "constraint/episode_cost": j_c})
            if not cfg.lambda_window:  # held or not, the next step reads only later episodes
                self.lam_costs.clear()
        # lines 11-15 (len: an n-step window delays the first rows of the buffer)
        metrics = []
        if global_step >= self.warmup_until and len(self.buffer):
            self.update_debt += self.num_envs * cfg.updates_per_step
            d_q = self.d_q(d)
            update_lambda = global_step >= cfg.lambda_warmup_steps
            while self.update_debt >= 1.0:
                self.update_debt -= 1.0
                m = self.agent.update(self.sample(cfg.batch_size), d_q, update_lambda)
                if self.measured_scale is not None:
                    self.measured_scale.observe_q(float(m["constraint/qc_pi"]))
                metrics.append(m)
        return len(metrics), metrics

    def act(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.agent.act(obs, deterministic=True)

    def log_items(self, d: float) -> dict[str, float]:
        row = {**self.pending, "charts/alpha": float(self.agent.log_alpha.detach().exp())}
        if self.cfg.constrained:
            row["constraint/d_q"] = self.d_q(d)
        self.pending = {}
        return row

    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {"update_debt": self.update_debt}
        if self.measured_scale is not None:
            state["cost_scale"] = self.measured_scale.state_dict()
        if self.episode_lambda:  # SAC-Lag's J_c window: a resumed run reads the same episodes
            state["lambda_costs"] = [float(c) for c in self.lam_costs]
        if self.save_buffer:
            state["buffer"] = self.buffer.state_dict()
            if self.nstep is not None:
                state["nstep_window"] = self.nstep.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        cfg, global_step = self.cfg, state["global_step"]
        self.resumed = True
        if self.noise is not None:
            # not checkpointed: the trainer resets every env on resume, so every episode - and
            # its noise sequence - starts anew, drawn from the restored RNG at the first step
            self.noise.reset()
        if self.measured_scale is not None and state.get("cost_scale"):
            self.measured_scale.load_state_dict(state["cost_scale"])
        self.update_debt = state.get("update_debt", 0.0)
        if self.episode_lambda:
            self.lam_costs = deque(state.get("lambda_costs", ()), maxlen=cfg.lambda_window or None)
        if "buffer" in state:
            self.buffer.load_state_dict(state["buffer"])
            if self.nstep is not None and state.get("nstep_window"):
                self.nstep.load_state_dict(state["nstep_window"])
        self.next_lambda = (global_step // cfg.lambda_every + 1) * cfg.lambda_every
        # without the buffer: refill it with the current policy before updating again
        self.warmup_until = (global_step if len(self.buffer) >= cfg.batch_size
                             else global_step + max(cfg.learning_starts, cfg.batch_size))  # fmt: skip


__all__ = ["CSAC", "COLUMNS", "CSACConfig", "CSACLearner"]
