"""PPO as NavRL trains it and, with ``constrained=True``, PPO-Lagrangian: one file, read top to
bottom.

One iteration (the pure pieces are in :mod:`safenav.algos.ppo_losses`):

1. rollout: ``rollout_steps`` vector steps with ``a ~ Beta`` mapped to ``[-1, 1]``, storing
   ``log pi(a|s)`` and ``V(s)``; where an episode is *truncated* the value of its true final
   observation ``V(final_obs)`` is stored too -> :func:`collect_rollout`. (Beyond NavRL,
   ``distribution="gaussian"``: ``a ~ N(mu, sigma^2)``, the env gets ``clip(a, -1, 1)`` and the
   rollout stores ``a`` and its log-density (SB3's PPO); with ``use_sde`` the noise is gSDE's,
   its exploration matrices drawn at the rollout's start and every ``sde_sample_freq`` steps
   (Raffin et al., CoRL 2021) -> :mod:`safenav.nn.gaussian`. On a ``Discrete(n)`` action space
   the policy is categorical whatever ``distribution`` says, ``a ~ softmax(logits)``, the rollout
   storing the index -> :mod:`safenav.nn.categorical`.)
2. (PPO-Lag) ``lambda <- max(0, lambda + Adam step on (J_c - d))`` with ``J_c`` the mean cost of the
   episodes that ended in the rollout -> :class:`~safenav.common.lagrange.Lagrange`, in
   :meth:`PPOLearner.update`
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

from typing import Any

import torch
from torch import nn

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
from safenav.common.config import RunConfig
from safenav.common.lagrange import Lagrange
from safenav.common.rollout import Rollout, ValueNorm
from safenav.envs.vector import TorchVecEnv
from safenav.errors import SafenavError
from safenav.nn.beta import POLICY_HEAD, BetaActorCritic, BetaDeterministicActor
from safenav.nn.categorical import POLICY_HEAD as CATEGORICAL_HEAD
from safenav.nn.categorical import (
    CategoricalActorCritic,
    CategoricalDeterministicActor,
    categorical_entropy,
    categorical_log_prob,
    greedy_action,
    sample_categorical,
)
from safenav.nn.gaussian import POLICY_HEAD as GAUSSIAN_HEAD
from safenav.nn.gaussian import (
    GaussianActorCritic,
    GaussianDeterministicActor,
    gaussian_entropy,
    gaussian_log_prob,
)
from safenav.nn.networks import input_order
from safenav.nn.optim import adam


class PPO(nn.Module):
    """Actor-critic, value normalisation, optimiser and the PPO update (PPO-Lag when
    ``cfg.constrained``: a second value head for cost and a Lagrange multiplier). The policy is
    NavRL's Beta or, with ``cfg.distribution == "gaussian"``, SB3's Gaussian (gSDE with
    ``cfg.use_sde``); with ``num_actions`` (a ``Discrete(n)`` action space) a categorical policy
    over the ``n`` actions, whose action is its index (``action_dim`` 1)."""

    def __init__(
        self,
        obs_shapes: dict[str, tuple[int, ...]],
        action_dim: int,
        cfg: PPOConfig,
        num_actions: int | None = None,
    ) -> None:
        super().__init__()
        self.cfg, self.obs_shapes, self.action_dim = cfg, dict(obs_shapes), action_dim
        self.num_values = 2 if cfg.constrained else 1  # column 0 reward, column 1 cost
        self.categorical = num_actions is not None
        self.gaussian = cfg.distribution == "gaussian" and not self.categorical
        self.model: BetaActorCritic | GaussianActorCritic | CategoricalActorCritic
        if self.categorical:
            self.model = CategoricalActorCritic(obs_shapes, num_actions, cfg.net, self.num_values)
        elif self.gaussian:
            self.model = GaussianActorCritic(obs_shapes, action_dim, cfg.net, self.num_values,
                                             cfg.log_std_init, cfg.use_sde)  # fmt: skip
        else:
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
        """``(action, log_prob, values)``: the action (Beta: in ``[-1, 1]^A``; Gaussian: the
        unclipped sample, or the mean; categorical: the index ``(N, 1)``, or the most probable
        one), its log-density (log-probability), and the denormalised values ``(N, K)`` of ``obs``."""
        if self.categorical:
            logits, values = self.model(obs)
            action = greedy_action(logits) if deterministic else sample_categorical(logits)
            log_prob = categorical_log_prob(logits, action)
            return action, log_prob, self.value_norm.denormalize(values)
        if self.gaussian:
            mean, std, values, latent = self.model(obs)
            action = mean if deterministic else self.model.sample(mean, std, latent)
            log_prob = gaussian_log_prob(mean, std, action)
            return action, log_prob, self.value_norm.denormalize(values)
        alpha, beta, values = self.model(obs)
        action = beta_mean_action(alpha, beta) if deterministic else sample_beta_action(alpha, beta)
        return action, beta_log_prob(alpha, beta, action), self.value_norm.denormalize(values)

    def evaluate(self, obs: dict[str, torch.Tensor], actions: torch.Tensor):
        """``(log pi(a|s), H[pi(.|s)], values)``, ``(B,)``, ``(B,)`` and normalised ``(B, K)``,
        with gradients (the update's forward pass)."""
        if self.categorical:
            logits, values = self.model(obs)
            return categorical_log_prob(logits, actions), categorical_entropy(logits), values
        if self.gaussian:
            mean, std, values, _ = self.model(obs)
            return gaussian_log_prob(mean, std, actions), gaussian_entropy(std), values
        alpha, beta, values = self.model(obs)
        return beta_log_prob(alpha, beta, actions), beta_entropy(alpha, beta), values

    def reset_noise(self, n: int) -> None:
        """gSDE: draw new exploration matrices for ``n`` envs (nothing to do otherwise)."""
        if self.gaussian and self.cfg.use_sde:
            self.model.reset_noise(n)

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
                log_prob, entropy, values = self.evaluate(
                    {k: v[idx] for k, v in obs.items()}, actions[idx]
                )
                loss_pi = clipped_policy_loss(
                    log_prob, old_log_probs[idx], adv_actor[idx], cfg.clip
                )
                entropy = entropy.mean()
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

    def env_action(self, action: torch.Tensor) -> torch.Tensor:
        """What the env gets of a rollout's action: continuous ones clipped to ``[-1, 1]`` (the
        rollout keeps the unclipped Gaussian sample), an index as it is."""
        return action if self.categorical else action.clamp(-1.0, 1.0)

    def policy_module(
        self,
    ) -> BetaDeterministicActor | GaussianDeterministicActor | CategoricalDeterministicActor:
        """The deterministic actor (the Beta mean; the Gaussian mean clipped to ``[-1, 1]``; the
        most probable action's index), sharing parameters with this agent."""
        actor = (CategoricalDeterministicActor if self.categorical
                 else GaussianDeterministicActor if self.gaussian else BetaDeterministicActor)  # fmt: skip
        return actor(self.model.actor_body, self.model.policy_head, input_order(self.obs_shapes))

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
    freq = agent.cfg.sde_sample_freq
    for t in range(rollout.steps):
        if t == 0 or (freq > 0 and t % freq == 0):  # gSDE's exploration matrices (SB3)
            agent.reset_noise(env.num_envs)
        action, log_prob, values = agent.act(obs)
        step = env.step(agent.env_action(action))  # the rollout keeps the unclipped sample
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


# ------------------------------------------------------------------------- the loop's view
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
"""Every progress.csv column of PPO and PPO-Lag (docs/algorithms.md)."""


class PPOLearner:
    """PPO in the shared training loop (:class:`safenav.training.Trainer`): one rollout per
    iteration (step 1), PPO-Lag's lambda from its episodes (step 2), then :meth:`PPO.update`."""

    section = "ppo"
    columns = COLUMNS
    policy_meta: dict[str, Any]

    def __init__(self, env: TorchVecEnv, run: RunConfig, cfg: PPOConfig) -> None:
        self.device = env.device
        n = env.num_actions  # None: continuous actions
        self.agent = PPO(env.obs_shapes, env.action_dim, cfg, n).to(env.device)
        head = (CATEGORICAL_HEAD if self.agent.categorical
                else GAUSSIAN_HEAD if self.agent.gaussian else POLICY_HEAD)  # fmt: skip
        self.policy_meta = {"policy_head": head}  # what load_policy dispatches on
        if n is not None:
            self.policy_meta["num_actions"] = n
        self.rollout = Rollout(cfg.rollout_steps, env.num_envs, env.obs_shapes, env.action_dim,
                               self.agent.num_values, env.device)  # fmt: skip
        self.rollouts = 0
        self.lr, self.total_steps, self.anneal = cfg.lr, run.total_steps, cfg.anneal_lr
        self.ep_costs: list[float] = []  # the costs of the episodes that ended in this rollout
        self.rollout_d = 0.0  # the budget those episodes ran under
        self.lam_sums, self.lam_n = {"losses/lambda": 0.0, "constraint/episode_cost": 0.0}, 0

    def collect(self, env: TorchVecEnv, obs: dict[str, torch.Tensor], global_step: int,
                d: float) -> tuple[dict[str, torch.Tensor], list[dict[str, torch.Tensor]], int]:  # fmt: skip
        """Step 1: a rollout of ``rollout_steps`` vector steps."""
        obs, episodes = collect_rollout(env, self.agent, self.rollout, obs)
        self.rollouts += 1
        self.rollout_d = d
        return obs, episodes, self.rollout.steps * env.num_envs

    def observe(self, episodes: dict[str, list[float]]) -> None:
        self.ep_costs.extend(episodes["cost"])

    def maps_changed(self) -> None:
        """Nothing to do: the next rollout starts from the new observation."""

    def update(self, global_step: int, d: float) -> tuple[int, list[dict[str, torch.Tensor]]]:
        """Step 2 (PPO-Lag) and steps 3-6 on the rollout just collected."""
        # 2. lambda from the mean episode cost J_c of this rollout against the d it ran under
        if self.agent.lagrange is not None and self.ep_costs:
            j_c = torch.tensor([sum(self.ep_costs) / len(self.ep_costs)], device=self.device)
            self.lam_sums["losses/lambda"] += float(self.agent.lagrange.update(j_c, self.rollout_d))
            self.lam_sums["constraint/episode_cost"] += float(j_c[0])
            self.lam_n += 1
        self.ep_costs = []
        # 3-6. the update, at the annealed rate where asked (CleanRL: set before the rollout)
        if self.anneal:
            before = global_step - self.rollout.steps * self.rollout.num_envs
            lr = self.lr * max(0.0, 1.0 - before / self.total_steps)
            for group in self.agent.optimizer.param_groups:
                group["lr"] = lr
        metrics = self.agent.update(self.rollout)
        return int(metrics.pop("perf/gradient_steps")), [metrics]

    def act(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """Deterministic actions in ``[-1, 1]`` (the Gaussian mean clipped, as SB3's predict), or
        the most probable action's index."""
        return self.agent.env_action(self.agent.act(obs, deterministic=True)[0])

    def log_items(self, d: float) -> dict[str, float]:
        row = {"perf/rollouts": self.rollouts}
        row.update({k: v / self.lam_n for k, v in self.lam_sums.items()} if self.lam_n else {})
        self.lam_sums, self.lam_n = dict.fromkeys(self.lam_sums, 0.0), 0
        return row

    def state_dict(self) -> dict[str, Any]:
        return {"rollouts": self.rollouts}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.rollouts = state.get("rollouts", 0)


__all__ = ["COLUMNS", "PPO", "PPOConfig", "PPOLearner", "collect_rollout"]
