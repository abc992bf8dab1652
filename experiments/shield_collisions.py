"""Why does a policy collide, or time out, behind its safety shield? (docs/deployment.md, "The
braking cap")

Flies EPISODES episodes of one map (a validation map: 12345-12348) with a policy behind the shield
it flies behind (``safenav train --shield``; its ``meta["flight_shield"]`` or ``meta["shield"]``),
optionally with ShieldConfig fields overridden (JSON, e.g. ``'{"brake_time": 0.4}'``; the key
``brake`` sets the shield's braking cap as ``--shield-brake`` does), and for each collision prints what
was struck (static, moving, the altitude band), the altitude (UAV, goal), whether the shield
corrected each of the last 10 actions in its velocity-obstacle search (a change by the braking
cap alone is not counted there), whether its correction was the last resort (no admissible
candidate: the latest time to collision) and the speed of the last 5 steps.

    .venv/bin/python experiments/shield_collisions.py runs/levers/shield1map03-s1/policy.pt \\
        12345 100 ['{"brake_time": 0.4}']

The first line is the outcome count, the last the collisions by kind and by what the shield did
in the last 3 steps (``fb_last3``: a last resort, ``corr_last3``: a correction, ``free_last3``:
none). For each timeout it prints the horizontal distance left to the goal, the share of the
episode's actions the shield changed, the mean speed, and over the last 20 s the path flown
against the displacement (a hovering UAV flies neither, an oscillating one a path without
displacement). Found: most collisions come after 10 corrected steps that were admissible to the shield,
at 1.2-2 m/s: the vehicle drifts into the pillar behind its 0.4 s velocity lag.
"""

from __future__ import annotations

import json
import sys
from collections import Counter
from pathlib import Path

import torch

import safenav.deploy.shield as S
from safenav.common.config import flight_shield_spec
from safenav.envs.nav import SafeNavVectorEnv
from safenav.experiments.evaluate import fixed_test_scenario
from safenav.experiments.flight import resolve_policy

LOOKBACK = 10


def main() -> None:
    torch.set_num_threads(1)
    ckpt, seed, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    overrides = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
    policy, cfg = resolve_policy(Path(ckpt), "checkpoint", "cpu")
    spec = {**(flight_shield_spec(policy.meta) or {"memory": 1})}
    if "brake" in overrides:
        spec["brake"] = overrides.pop("brake")  # true / false / "slide", checked by the shield
    shield = S.shield_from_spec(spec)
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
    window = int(round(20.0 / cfg.dt))  # the last 20 s of a timeout
    positions: list[torch.Tensor] = []
    changed = torch.zeros(n)
    outcomes, by_cause, lines = Counter(), Counter(), []
    with torch.no_grad():
        for t in range(cfg.max_episode_steps):
            flags.clear()
            act = policy(obs).clamp(-1, 1)
            shielded = shield(env, obs, act)
            none = torch.zeros(n, dtype=torch.bool)
            history = [*history[-(LOOKBACK - 1):], (flags.get("corrected", none).clone(),
                       flags.get("last_resort", none).clone(), env.vel.norm(dim=-1).clone())]  # fmt: skip
            changed += (shielded != act).any(-1).float() * ~done
            positions = [*positions[-window:], env.pos.clone()]
            obs, _, term, trunc, info = env.step(torch.where(done[:, None], 0.0, shielded))
            ended = (term | trunc) & ~done
            ep = info.get("episode")  # present at the steps where an episode ends
            if ep is None:
                continue
            for i in ended.nonzero().flatten().tolist():
                if not bool(ep["collision"][i]):
                    outcomes["success" if bool(ep["success"][i]) else "timeout"] += 1
                    if not bool(ep["success"][i]):
                        track = torch.stack([*(p[i] for p in positions), env.pos[i]])
                        path = float((track[1:] - track[:-1]).norm(dim=-1).sum())
                        moved = float((track[-1] - track[0]).norm())
                        left = float((env.pos[i, :2] - env.goal[i, :2]).norm())
                        lines.append(f"timeout goal {left:.1f} m away, shield changed "
                                     f"{float(changed[i]) / (t + 1):.0%} of actions, mean speed "
                                     f"{float(ep['mean_speed'][i]):.2f} m/s, last 20 s: "
                                     f"path {path:.1f} m, displacement {moved:.1f} m")  # fmt: skip
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
