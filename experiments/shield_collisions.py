"""Why does a policy collide behind its safety shield? (docs/deployment.md, "The braking cap")

Flies EPISODES episodes of one map (a validation map: 12345-12348) with a policy behind the shield
it records (``safenav train --shield``; its ``meta["shield"]``), optionally with ShieldConfig
fields overridden (JSON, e.g. ``'{"brake_time": 0.4}'``), and for each collision prints what
was struck (static, moving, the altitude band), the altitude (UAV, goal), whether the shield
corrected each of the last 10 actions, whether its correction was the last resort (no admissible
candidate: the latest time to collision) and the speed of the last 5 steps.

    .venv/bin/python experiments/shield_collisions.py runs/levers/shield1map03-s1/policy.pt \\
        12345 100 ['{"brake_time": 0.4}']

The first line is the outcome count, the last the collisions by kind and by what the shield did
in the last 3 steps (``fb_last3``: a last resort, ``corr_last3``: a correction, ``free_last3``:
none). Found: most collisions come after 10 corrected steps that were admissible to the shield,
at 1.2-2 m/s: the vehicle drifts into the pillar behind its 0.4 s velocity lag.
"""

from __future__ import annotations

import json
import sys
from collections import Counter
from pathlib import Path

import torch

import safenav.deploy.shield as S
from safenav.envs.nav import SafeNavVectorEnv
from safenav.experiments.evaluate import fixed_test_scenario
from safenav.experiments.flight import resolve_policy

LOOKBACK = 10


def main() -> None:
    torch.set_num_threads(2)
    ckpt, seed, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    overrides = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
    policy, cfg = resolve_policy(Path(ckpt), "checkpoint", "cpu")
    shield = S.shield_from_spec(policy.meta.get("shield") or {"memory": 1})
    if overrides:
        for_env = S.ShieldConfig.for_env
        S.ShieldConfig.for_env = staticmethod(lambda c, **kw: for_env(c, **{**kw, **overrides}))
    flags: dict[str, torch.Tensor] = {}
    search = S.velocity_obstacle_shield

    def watched(v_des, rel, obs_vel, radius, valid, planar=None, cfg=S.ShieldConfig(), *a, **k):
        out, corrected = search(v_des, rel, obs_vel, radius, valid, planar, cfg, *a, **k)
        flat = planar if planar is not None else torch.zeros_like(valid)
        inside, _ = S._vo_test(out[:, None], rel, obs_vel, radius, valid, flat, cfg.time_horizon)
        flags["last_resort"], flags["corrected"] = inside[:, 0] & corrected, corrected
        return out, corrected

    S.velocity_obstacle_shield = watched
    cfg, starts, goals = fixed_test_scenario(cfg, seed, n)
    env = SafeNavVectorEnv(n, config=cfg, output="torch", autoreset_mode="Disabled")
    obs, _ = env.reset(seed=seed, options={"starts": starts, "goals": goals})
    done = torch.zeros(n, dtype=torch.bool)
    history: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
    outcomes, by_cause, lines = Counter(), Counter(), []
    with torch.no_grad():
        for t in range(cfg.max_episode_steps):
            flags.clear()
            act = policy(obs).clamp(-1, 1)
            shielded = shield(env, obs, act)
            none = torch.zeros(n, dtype=torch.bool)
            history = [*history[-(LOOKBACK - 1):], (flags.get("corrected", none).clone(),
                       flags.get("last_resort", none).clone(), env.vel.norm(dim=-1).clone())]  # fmt: skip
            obs, _, term, trunc, info = env.step(torch.where(done[:, None], 0.0, shielded))
            ended = (term | trunc) & ~done
            ep = info["episode"]
            for i in ended.nonzero().flatten().tolist():
                if not bool(ep["collision"][i]):
                    outcomes["success" if bool(ep["success"][i]) else "timeout"] += 1
                    continue
                kind = ("band" if bool(ep["out_of_bounds"][i]) else
                        "static" if bool(ep["hit_static"][i]) else "moving")  # fmt: skip
                outcomes[kind] += 1
                corr = "".join(str(int(h[0][i])) for h in history)
                last = "".join(str(int(h[1][i])) for h in history)
                speed = [round(float(h[2][i]), 2) for h in history][-5:]
                lines.append(f"{kind:6s} z {float(env.pos[i, 2]):.2f} goal z {float(env.goal[i, 2]):.2f} "
                             f"step {t} corrected {corr} last resort {last} speed {speed}")  # fmt: skip
                shield_did = ("fb_last3" if "1" in last[-3:] else
                              "corr_last3" if "1" in corr[-3:] else "free_last3")  # fmt: skip
                by_cause[(kind, shield_did)] += 1
            done |= ended
            if bool(done.all()):
                break
    print(dict(outcomes))
    print("\n".join(lines))
    print(dict(by_cause))


if __name__ == "__main__":
    main()
