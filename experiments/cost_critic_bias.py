"""Do the cost critics predict the real cost? (docs/csac.md, "Three runs of the 60-minute budget")

Loads a CSAC *training* checkpoint (``RUN/checkpoint.pt``: it holds the critics), flies its
stochastic policy (as in training) on the run's env (SafeNav at full density) and compares, over every
transition of the episodes that finished:

- ``predicted``: ``1/2 sum_j Q_C,j(s, a)``, the cost critics' value of the action taken (what
  Eq. 9 and Eq. 11 use), and
- ``realised``: the discounted cost-to-go ``sum_k gamma^k c_{t+k}`` until the episode's end
  (collisions end episodes, so this is ``gamma^(steps to the collision)`` or 0), a Monte-Carlo
  sample of the same quantity.

Averaged over transitions, equal means an unbiased critic; ``predicted / realised`` well below 1
means the constraint holds a cost lower than the real one. On a task with a time limit (Hopper's
1000 steps) the realised sum stops at the cut, so the last ~1/(1 - gamma) steps of a cut episode
read low. Both again over the transitions with cost close ahead (realised > 0.5):
``*_near_collision`` on SafeNav, ``*_cost_ahead`` on other tasks. Also the mean cost, return and
length of the episodes that finished (of this stochastic policy; an evaluation flies the
deterministic one). The same for the reward critics
(``min_j Q_R,j``, realised reward-to-go plus the entropy bonus left out: a rough check only).

Run: ``.venv/bin/python experiments/cost_critic_bias.py runs/NAME/checkpoint.pt [--steps 400]
[--json OUT]``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSAC
from safenav.common.checkpoint import load_checkpoint, restore_agent
from safenav.common.config import RunConfig, from_dict
from safenav.common.jsonout import write_json
from safenav.envs.vector import TorchVecEnv, cost_function, is_safenav, make_vec_env


@torch.no_grad()
def measure(path: Path, num_envs: int, steps: int, seed: int) -> dict[str, float]:
    state = load_checkpoint(path)
    if "agent" not in state:
        raise SystemExit(f"{path} is policy-only: the critics are in the run's checkpoint.pt")
    run = from_dict(RunConfig, state["config"]["run"])
    cfg = from_dict(CSACConfig, state["config"]["csac"])
    if run.normalize_obs or run.normalize_reward:
        raise SystemExit(
            f"{path}: trained with --normalize-obs/-reward, which this check does not replay"
        )
    with cost_function(run.cost_fn):  # a run trained with --cost-fn flies with it
        return _fly(state, run, cfg, path, num_envs, steps, seed)


def _fly(state, run, cfg, path: Path, num_envs: int, steps: int, seed: int) -> dict[str, float]:
    kwargs = dict(run.env_kwargs)
    if is_safenav(run.env):  # SafeNav at full density; a Gymnasium task as it is
        kwargs["density"] = run.density.end
    env = TorchVecEnv(make_vec_env(run.env, num_envs, "cpu", run.preset, **kwargs), "cpu")
    agent = CSAC(env.obs_shapes, env.action_dim, cfg)
    restore_agent(agent, state, path)
    torch.manual_seed(seed)
    obs = env.reset(seed=seed)
    rows = []  # per step: predicted Q_C, Q_R, cost, reward, done
    for _ in range(steps):
        x = agent.encoder(obs) if agent.encoder is not None else obs
        action = agent.actor.sample(x)[0]
        q_c = (
            agent.qc(x, action).mean(0).squeeze(-1)
            if agent.qc is not None
            else torch.zeros(num_envs)
        )
        q_r = agent.qr(x, action).min(0).values.squeeze(-1)
        step = env.step(action)
        rows.append((q_c, q_r, step.cost, step.reward, step.terminated | step.truncated))
        obs = step.next_obs
    episodes = finished_episodes([(cost, reward, done) for _, _, cost, reward, done in rows])
    gamma, gamma_c = cfg.gamma, cfg.cost_discount
    pred_c, pred_r, real_c, real_r = [], [], [], []
    g_c = torch.zeros(num_envs)
    g_r = torch.zeros(num_envs)
    finished = torch.zeros(num_envs, dtype=torch.bool)  # an episode end lies ahead of this step
    for q_c, q_r, cost, reward, done in reversed(rows):
        g_c = torch.where(done, cost, cost + gamma_c * g_c)
        g_r = torch.where(done, reward, reward + gamma * g_r)
        finished |= done
        pred_c.append(q_c[finished])
        pred_r.append(q_r[finished])
        real_c.append(g_c[finished])
        real_r.append(g_r[finished])
    pc, rc = torch.cat(pred_c), torch.cat(real_c)
    pr, rr = torch.cat(pred_r), torch.cat(real_r)
    # Transitions with cost close ahead (discounted cost-to-go > 0.5): on SafeNav, where each
    # collision costs 1 and ends the episode, those within ~70 steps of a collision.
    near = rc > 0.5
    where = "near_collision" if is_safenav(run.env) else "cost_ahead"
    return {"transitions": int(pc.numel()), "predicted_qc": float(pc.mean()), "realised_qc": float(rc.mean()),
            "fraction_qc_below_zero": float((pc < 0).float().mean()),
            "ratio_qc": float(pc.mean() / rc.mean()) if rc.mean() > 0 else float("nan"),
            f"predicted_qc_{where}": float(pc[near].mean()) if near.any() else float("nan"),
            f"realised_qc_{where}": float(rc[near].mean()) if near.any() else float("nan"),
            "predicted_qr": float(pr.mean()), "realised_qr": float(rr.mean()),
            "episodes": len(episodes),
            **{f"episode_{k}": sum(e[j] for e in episodes) / len(episodes) if episodes else float("nan")
               for j, k in enumerate(("cost", "return", "length"))},
            "lambda": float(agent.lam) if agent.lagrange is not None else 0.0,
            "global_step": int(state["global_step"])}  # fmt: skip


def finished_episodes(steps: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]) -> list[tuple]:
    """``(cost, return, length)`` of every episode that ends within ``steps`` (per vector step:
    cost, reward, done, each ``(num_envs,)``; the envs start at a reset and reset in the step
    that ends an episode). Episodes still running at the end are left out, so long ones are
    under-represented in a short window."""
    n = steps[0][0].shape[0] if steps else 0
    ep_cost, ep_ret, ep_len = torch.zeros(n), torch.zeros(n), torch.zeros(n)
    episodes = []
    for cost, reward, done in steps:
        ep_cost, ep_ret, ep_len = ep_cost + cost, ep_ret + reward, ep_len + 1
        episodes += [
            (float(ep_cost[i]), float(ep_ret[i]), float(ep_len[i])) for i in done.nonzero()[:, 0]
        ]
        ep_cost, ep_ret, ep_len = (torch.where(done, 0.0, v) for v in (ep_cost, ep_ret, ep_len))
    return episodes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--num-envs", type=int, default=64)
    ap.add_argument(
        "--steps", type=int, default=400, help="vector steps (episodes cut at the end are left out)"
    )
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    res = measure(args.checkpoint, args.num_envs, args.steps, args.seed)
    for k, v in res.items():
        print(f"{k:30s} {v:.4f}" if isinstance(v, float) else f"{k:30s} {v}")
    if args.json:
        write_json(args.json, res)  # strict: a ratio with no costly step is null, not NaN


if __name__ == "__main__":
    main()
