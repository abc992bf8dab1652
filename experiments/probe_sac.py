"""Feasibility probe: a minimal SAC / CSAC-style learner (flattened observation, MLP) on SafeNav-v1.

Not the product's trainer (see ``safenav train``): a quick, dependency-light script to learn how
fast the paper scenario is learnable on a CPU, to choose env-count, update ratio and curriculum.

    python experiments/probe_sac.py --preset paper --minutes 8 --num-envs 32 --utd 0.25
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from safenav.common.jsonout import write_json
from safenav.envs.config import make_config
from safenav.envs.nav import SafeNavVectorEnv
from safenav.experiments.evaluate import evaluate


def flat(obs):
    return torch.cat([obs["state"], obs["lidar"].flatten(1), obs["dynamic"].flatten(1)], -1)


def mlp(i, o, h=256):
    return nn.Sequential(nn.Linear(i, h), nn.ReLU(), nn.Linear(h, h), nn.ReLU(), nn.Linear(h, o))


class Actor(nn.Module):
    def __init__(self, i, h):
        super().__init__()
        self.net = mlp(i, 6, h)

    def forward(self, x, deterministic=False):
        mu, log_std = self.net(x).chunk(2, -1)
        log_std = log_std.clamp(-5, 2)
        if deterministic:
            return torch.tanh(mu), None
        u = mu + log_std.exp() * torch.randn_like(mu)
        a = torch.tanh(u)
        logp = (-0.5 * ((u - mu) / log_std.exp()) ** 2 - log_std - 0.5 * np.log(2 * np.pi)).sum(-1)
        logp -= (2 * (np.log(2) - u - F.softplus(-2 * u))).sum(-1)
        return a, logp


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--preset", default="paper")
    p.add_argument("--minutes", type=float, default=5)
    p.add_argument("--num-envs", type=int, default=32)
    p.add_argument("--utd", type=float, default=0.25, help="updates per env step")
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--hidden", type=int, default=256)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--density0", type=float, default=0.2)
    p.add_argument("--density-steps", type=float, default=3e5)
    p.add_argument("--lagrangian", action="store_true")
    p.add_argument("--cost-limit", type=float, default=0.05)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    cfg = make_config(args.preset)
    env = SafeNavVectorEnv(args.num_envs, config=cfg.replace(density=args.density0), output="torch")
    obs, _ = env.reset(seed=args.seed + 1000)
    dim = flat(obs).shape[1]
    actor = Actor(dim, args.hidden)
    qs = nn.ModuleList([mlp(dim + 3, 1, args.hidden) for _ in range(4)])  # 2 reward, 2 cost
    qt = nn.ModuleList([mlp(dim + 3, 1, args.hidden) for _ in range(4)])
    qt.load_state_dict(qs.state_dict())
    log_alpha = torch.zeros(1, requires_grad=True)
    lam_raw = torch.zeros(1, requires_grad=True)
    opt_a = torch.optim.Adam(actor.parameters(), lr=args.lr)
    opt_q = torch.optim.Adam(qs.parameters(), lr=args.lr)
    opt_al = torch.optim.Adam([log_alpha, lam_raw], lr=args.lr)
    cap = 1_000_000
    B = {"o": torch.zeros(cap, dim), "a": torch.zeros(cap, 3), "r": torch.zeros(cap), "c": torch.zeros(cap),
         "o2": torch.zeros(cap, dim), "d": torch.zeros(cap)}  # fmt: skip
    ptr = size = 0
    t0 = time.time()
    step = 0
    warm = 5000
    upd_debt = 0.0
    hist = {"succ": [], "coll": []}
    log = []
    x = flat(obs)
    while time.time() - t0 < args.minutes * 60:
        with torch.no_grad():
            a = torch.rand(args.num_envs, 3) * 2 - 1 if step < warm else actor(x)[0]
        obs2, r, term, trunc, info = env.step(a)
        x2 = flat(obs2)
        real_next = x2.clone()
        if "final_obs" in info:
            m = info["_final_obs"]
            real_next[m] = flat(info["final_obs"])[m]
            ep = info["episode"]
            hist["succ"] += ep["success"][m].float().tolist()
            hist["coll"] += ep["collision"][m].float().tolist()
        n = args.num_envs
        idx = (torch.arange(n) + ptr) % cap
        B["o"][idx], B["a"][idx], B["r"][idx], B["c"][idx] = x, a, r, info["cost"]
        B["o2"][idx], B["d"][idx] = real_next, term.float()
        ptr = (ptr + n) % cap
        size = min(size + n, cap)
        x = x2
        step += n
        density = min(1.0, args.density0 + (1 - args.density0) * step / args.density_steps)
        if abs(density - env.density) > 0.02:
            env.set_density(density)
        if step < warm:
            continue
        upd_debt += n * args.utd
        while upd_debt >= 1:
            upd_debt -= 1
            j = torch.randint(0, size, (args.batch,))
            o, aa, rr, cc, o2, dd = (B[k][j] for k in ("o", "a", "r", "c", "o2", "d"))
            alpha = log_alpha.exp().detach()
            lam = F.softplus(lam_raw).detach() if args.lagrangian else torch.zeros(1)
            with torch.no_grad():
                a2, lp2 = actor(o2)
                inp2 = torch.cat([o2, a2], -1)
                qv = [q(inp2).squeeze(-1) for q in qt]
                yr = rr + 0.99 * (1 - dd) * (torch.min(qv[0], qv[1]) - alpha * lp2)
                yc = cc + 0.99 * (1 - dd) * 0.5 * (qv[2] + qv[3])
            inp = torch.cat([o, aa], -1)
            qq = [q(inp).squeeze(-1) for q in qs]
            lq = (
                F.mse_loss(qq[0], yr)
                + F.mse_loss(qq[1], yr)
                + F.mse_loss(qq[2], yc)
                + F.mse_loss(qq[3], yc)
            )
            opt_q.zero_grad()
            lq.backward()
            opt_q.step()
            an, lp = actor(o)
            inpn = torch.cat([o, an], -1)
            qn = [q(inpn).squeeze(-1) for q in qs]
            qc = 0.5 * (qn[2] + qn[3])
            la = (alpha * lp - torch.min(qn[0], qn[1]) + lam * qc).mean()
            opt_a.zero_grad()
            la.backward()
            opt_a.step()
            l_alpha = -(log_alpha.exp() * (lp.detach() - 3)).mean()
            l_lam = (F.softplus(lam_raw) * (args.cost_limit - qc.detach().mean())).mean()
            opt_al.zero_grad()
            (l_alpha + l_lam).backward()
            opt_al.step()
            with torch.no_grad():
                for p_, pt in zip(qs.parameters(), qt.parameters(), strict=True):
                    pt.mul_(0.995).add_(0.005 * p_)
        if step % (args.num_envs * 500) == 0:
            s = np.mean(hist["succ"][-200:]) if hist["succ"] else 0
            c = np.mean(hist["coll"][-200:]) if hist["coll"] else 0
            rec = dict(t=round(time.time() - t0), step=step, density=round(env.density, 2), succ=round(s, 3),
                       coll=round(c, 3), alpha=round(float(log_alpha.exp()), 4),
                       lam=round(float(F.softplus(lam_raw)), 3))  # fmt: skip
            log.append(rec)
            print(rec, flush=True)
    res = evaluate(lambda o: actor(flat(o), deterministic=True)[0], cfg, episodes=200)
    summary = {k: res[k] for k in ("success_rate", "collision_rate", "timeout_rate")}
    summary.update(steps=step, args=vars(args))
    print("EVAL", json.dumps(summary), flush=True)
    if args.out:
        write_json(args.out, {"summary": summary, "log": log})


if __name__ == "__main__":
    main()
